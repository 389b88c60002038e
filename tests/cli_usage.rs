//! The command line's usage rules: what is a usage error (exit 2) and what
//! a failure (exit 1), checked before any work; errors that name their file
//! once; the report's file names and builder; the main job's table.

mod common;

use common::{dir_entries, fresh_temp_dir};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn slimkd(args: &[&str]) -> Output {
    slimkd_in(None, args)
}

fn slimkd_in(dir: Option<&Path>, args: &[&str]) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_slimkd"));
    c.args(args);
    if let Some(d) = dir {
        c.current_dir(d);
    }
    c.output().expect("the binary runs")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Asserts the exit code; returns stderr.
fn exits(out: &Output, code: i32, what: &str) -> String {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(code), "{what}: {err}");
    err
}

fn json(out: &Output) -> serde_json::Value {
    assert!(out.status.success(), "{}", stderr(out));
    serde_json::from_slice(&out.stdout).expect("one JSON object")
}

fn bunny() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes/bunny_npm.obj")
        .to_str()
        .unwrap()
        .to_string()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A hoisting flag with the std preset (given or by default) needs both
/// thresholds; with a slim preset it overrides only what it names.
#[test]
fn hoisting_flags_with_std_need_both_thresholds() {
    let scene = bunny();
    for extra in [
        &["--hoist-rule", "paper"][..],
        &["--preset", "std", "--tau-freq", "0.5"],
        &["--tau-occu", "0.5"],
        &["--max-t2rn", "3"],
        &["--coarsen", "2"],
        &[
            "--preset",
            "std",
            "--hoist-rule",
            "bytes",
            "--tau-occu",
            "0.5",
        ],
    ] {
        let mut args = vec!["build", &scene];
        args.extend_from_slice(extra);
        let err = exits(&slimkd(&args), 2, &format!("{extra:?}"));
        assert!(
            err.contains("--tau-occu") && err.contains("--tau-freq"),
            "{extra:?}: {err}"
        );
    }
    let b = json(&slimkd(&[
        "build",
        &scene,
        "--tau-occu",
        "0.6",
        "--tau-freq",
        "0.3",
        "--json",
    ]));
    assert_eq!(b["preset"], "custom");
    assert_eq!(b["tau_occu"], 0.6);
    assert_eq!(b["tau_freq"], 0.3);
    assert_eq!(b["max_t2rn"], 16);
    assert_eq!(b["coarsen"], 2.0);
    assert_eq!(b["hoist_rule"], "bytes");
    // A slim preset supplies the other threshold.
    let b = json(&slimkd(&[
        "build",
        &scene,
        "--preset",
        "fast",
        "--tau-freq",
        "0.5",
        "--json",
    ]));
    assert_eq!(b["tau_occu"], 0.1);
    assert_eq!(b["tau_freq"], 0.5);
    assert_eq!(b["coarsen"], 1.5);
    assert_eq!(b["cost_ratio"], 0.01);
    // With the paper's rule a preset is the paper's setting.
    let b = json(&slimkd(&[
        "build",
        &scene,
        "--preset",
        "fast",
        "--hoist-rule",
        "paper",
        "--json",
    ]));
    assert_eq!(
        (
            &b["tau_occu"],
            &b["tau_freq"],
            &b["max_t2rn"],
            &b["coarsen"]
        ),
        (&0.9.into(), &0.7.into(), &4.into(), &1.0.into())
    );
    // The rule and the defaults are in the help.
    let help = stdout(&slimkd(&["build", "--help"]));
    assert!(
        help.contains("need both --tau-occu and --tau-freq"),
        "{help}"
    );
    assert!(help.contains("τ_occu 0.1, τ_freq 0.05"), "{help}");
    assert!(help.contains("fast τ_occu 0.9, τ_freq 0.7"), "{help}");
}

/// The slim presets build at their own split price (fast 1.5, small 2),
/// which `--split-price` replaces; the paper's settings and hoisting on
/// the std preset keep std's (0.5). The file records the price built with.
#[test]
fn presets_build_at_their_split_price() {
    let dir = fresh_temp_dir("preset_price");
    let scene = bunny();
    let kd = dir.join("t.kd");
    let price = |flags: &[&str]| {
        let mut args = vec!["build", &scene, "-o", kd.to_str().unwrap(), "--json"];
        args.extend_from_slice(flags);
        let built = json(&slimkd(&args));
        let info = json(&slimkd(&["info", kd.to_str().unwrap(), "--json"]));
        assert_eq!(built["split_price"], info["split_price"], "{flags:?}");
        built["split_price"].as_f64().unwrap()
    };
    assert_eq!(price(&[]), 0.5);
    assert_eq!(price(&["--preset", "fast"]), 1.5);
    assert_eq!(price(&["--preset", "small"]), 2.0);
    assert_eq!(price(&["--preset", "small", "--tau-occu", "0.3"]), 2.0);
    assert_eq!(price(&["--preset", "small", "--split-price", "0.25"]), 0.25);
    assert_eq!(price(&["--preset", "fast", "--hoist-rule", "paper"]), 0.5);
    assert_eq!(price(&["--tau-occu", "0.3", "--tau-freq", "0.2"]), 0.5);
}

/// A rebuild's K_T factor below 1, NaN or infinite is a usage error.
#[test]
fn coarsen_below_one_is_a_usage_error() {
    let scene = bunny();
    for v in ["nan", "0.99", "0", "-1", "inf", "x"] {
        let out = slimkd(&["build", &scene, "--preset", "small", "--coarsen", v]);
        let err = exits(&out, 2, &format!("--coarsen {v}"));
        assert!(err.contains("--coarsen"), "{err}");
    }
    let b = json(&slimkd(&[
        "build",
        &scene,
        "--preset",
        "fast",
        "--coarsen",
        "1.5",
        "--json",
    ]));
    assert_eq!(
        (&b["preset"], &b["coarsen"]),
        (&"custom".into(), &1.5.into())
    );
}

/// τ outside [0, 1], NaN or infinite is a usage error.
#[test]
fn thresholds_outside_the_unit_interval_are_usage_errors() {
    let scene = bunny();
    for flag in ["--tau-occu", "--tau-freq"] {
        for v in ["nan", "2", "-0.1", "inf", "1.0000001", "x"] {
            let out = slimkd(&["build", &scene, "--preset", "small", flag, v]);
            let err = exits(&out, 2, &format!("{flag} {v}"));
            assert!(err.contains(flag), "{err}");
        }
    }
    let b = json(&slimkd(&[
        "build",
        &scene,
        "--tau-occu",
        "1",
        "--tau-freq",
        "0",
        "--json",
    ]));
    assert_eq!(b["tau_occu"], 1.0);
}

/// Output paths are checked before any work: the scene named does not even
/// exist, and the error is about the output.
#[test]
fn output_paths_are_checked_before_any_work() {
    let dir = fresh_temp_dir("outputs");
    let scene = dir.join("no_such_scene.obj");
    let scene = s(&scene);
    let missing = dir.join("missing");
    let cases: Vec<(Vec<String>, i32, PathBuf)> = vec![
        (vec!["report".into(), scene.into()], 1, missing.join("r.md")),
        (vec!["report".into(), scene.into()], 2, dir.join("r.json")),
        (vec!["render".into(), scene.into()], 2, dir.join("out.jpg")),
        (
            vec!["render".into(), scene.into()],
            1,
            missing.join("x.png"),
        ),
        (vec!["build".into(), scene.into()], 1, missing.join("x.kd")),
        (
            vec!["convert".into(), scene.into()],
            1,
            missing.join("x.kds"),
        ),
    ];
    for (mut args, code, out) in cases {
        args.push("-o".into());
        args.push(s(&out).into());
        let a: Vec<&str> = args.iter().map(String::as_str).collect();
        let err = exits(&slimkd(&a), code, &format!("{a:?}"));
        assert!(err.contains(s(&out)), "{a:?}: {err}");
        assert!(!err.contains("no_such_scene"), "{a:?}: {err}");
    }
    let dump = missing.join("d.bin");
    let err = exits(
        &slimkd(&["render", scene, "--dump-t", s(&dump)]),
        1,
        "--dump-t",
    );
    assert!(err.contains(s(&dump)), "{err}");
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Two reports in one directory keep their own figures, named after `-o`,
/// and the Markdown links them by those names; the report names the
/// builder it really runs.
#[test]
fn reports_name_their_figures_after_the_output() {
    let dir = fresh_temp_dir("reports");
    let scene = bunny();
    let run = |name: &str, extra: &[&str]| {
        let md = dir.join(name);
        let mut args = vec![
            "report",
            &scene,
            "--size",
            "8x8",
            "--reps",
            "1",
            "--threads",
            "1",
            "-o",
            s(&md),
        ];
        args.extend_from_slice(extra);
        let out = slimkd(&args);
        assert!(out.status.success(), "{}", stderr(&out));
        std::fs::read_to_string(&md).unwrap()
    };
    let a = run("a.md", &["--sweep"]);
    let b = run("b.md", &[]);
    let names = dir_entries(&dir);
    assert_eq!(
        names,
        [
            "a.figure5.svg",
            "a.figure6.svg",
            "a.json",
            "a.md",
            "b.figure6.svg",
            "b.json",
            "b.md"
        ]
    );
    assert!(a.contains("(a.figure5.svg)") && a.contains("(a.figure6.svg)"));
    assert!(b.contains("(b.figure6.svg)") && !b.contains("figure5"));
    // The builder: the level builder, in the text and the JSON.
    assert!(a.contains("level builder") && !a.contains("sweep builder"));
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("a.json")).unwrap()).unwrap();
    assert_eq!(j["build"]["builder"], "level");
    std::fs::remove_dir_all(&dir).unwrap();
}

fn count(haystack: &str, needle: &str) -> usize {
    haystack.matches(needle).count()
}

/// Every error about a `.kd` file names it exactly once.
#[test]
fn kd_errors_name_their_file_once() {
    let dir = fresh_temp_dir("kd-errors");
    let good = dir.join("good.kd");
    json(&slimkd(&["build", &bunny(), "-o", s(&good), "--json"]));
    let bytes = std::fs::read(&good).unwrap();
    let trunc = dir.join("trunc.kd");
    std::fs::write(&trunc, &bytes[..bytes.len() / 2]).unwrap();
    let garbage = dir.join("garbage.kd");
    std::fs::write(&garbage, b"this is not a kd file, not at all").unwrap();
    let flipped = dir.join("flipped.kd");
    let mut f = bytes.clone();
    let i = f.len() - 50;
    f[i] ^= 0x08;
    std::fs::write(&flipped, &f).unwrap();
    let missing = dir.join("missing.kd");
    let rays = dir.join("none.rays");
    let dir_path = dir.to_path_buf();
    for path in [&trunc, &garbage, &missing, &dir_path] {
        let p = s(path);
        for args in [
            vec!["info", p],
            vec!["verify", p],
            vec!["render", p, "--size", "8x8", "--mode", "packet"],
            vec!["trace", p, s(&rays)],
        ] {
            if path == &dir_path && args[0] == "render" {
                continue; // a directory is not taken for a .kd file there
            }
            let err = exits(&slimkd(&args), 1, &format!("{args:?}"));
            assert_eq!(count(&err, p), 1, "{args:?}: {err}");
        }
    }
    let err = exits(&slimkd(&["verify", s(&flipped)]), 1, "verify flipped");
    assert_eq!(count(&err, s(&flipped)), 1, "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Usage errors exit 2; `-j` is `--threads`, 0 all cores.
#[test]
fn usage_errors_exit_2() {
    let dir = fresh_temp_dir("usage");
    let views = dir.join("views.txt");
    std::fs::write(&views, "default 1 eye=0,0,5 at=0,0,0 up=0,1,0 fov=60\n").unwrap();
    let kd = dir.join("b.kd");
    json(&slimkd(&["build", &bunny(), "-o", s(&kd), "--json"]));
    let x_cache = dir.join("x.cache");
    for args in [
        vec!["render", "default", "--size", "8x8", "--fov", "200"],
        vec!["render", "default", "--size", "8x8", "--fov", "nan"],
        vec!["render", "default", "--size", "8x8", "--reps", "0"],
        vec!["render", "default", "--size", "8x8", "--views", s(&views)],
        vec!["convert", "default", "-o", s(&x_cache)],
        vec!["report", "default", "--threads", "0"],
        vec!["report", "default", "--reps", "0"],
        vec!["trace", s(&kd), "r.rays", "--reps", "0"],
        vec!["trace", s(&kd), "r.rays", "-j", "0"],
    ] {
        exits(&slimkd(&args), 2, &format!("{args:?}"));
    }
    // A budget too large to count in bytes is an error, never "no budget".
    for budget in ["16777216T", "18446744073709551616", "1e30"] {
        let args = ["build", "default", "--mem-budget", budget];
        let err = exits(&slimkd(&args), 2, &format!("{args:?}"));
        assert!(err.contains("is too large (2^64 bytes or more)"), "{err}");
    }
    assert!(!x_cache.exists());
    let all = std::thread::available_parallelism().map_or(1, |n| n.get());
    let b = json(&slimkd(&["build", &bunny(), "-j", "0", "--json"]));
    assert_eq!(b["threads"], all);
    let b = json(&slimkd(&["build", &bunny(), "-j", "1", "--json"]));
    assert_eq!(b["threads"], 1);
    let r = json(&slimkd(&[
        "render",
        s(&kd),
        "-j",
        "1",
        "--size",
        "8x8",
        "--json",
    ]));
    assert_eq!(r["threads"], 1);
    let r = json(&slimkd(&[
        "render",
        &bunny(),
        "--threads",
        "0",
        "--size",
        "8x8",
        "--json",
    ]));
    assert_eq!(r["threads"], all);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Build flags with a `.kd` input would be ignored: a usage error naming
/// them.
#[test]
fn build_flags_with_a_kd_input_are_refused() {
    let dir = fresh_temp_dir("kd-input");
    let kd = dir.join("b.kd");
    json(&slimkd(&["build", &bunny(), "-o", s(&kd), "--json"]));
    let out = slimkd(&[
        "render",
        s(&kd),
        "--preset",
        "fast",
        "--builder",
        "naive",
        "--mem-budget",
        "1G",
        "--size",
        "8x8",
    ]);
    let err = exits(&out, 2, "build flags");
    for flag in ["--preset", "--builder", "--mem-budget"] {
        assert!(err.contains(flag), "{flag}: {err}");
    }
    assert!(!err.contains("--tiny"), "{err}");
    let out = slimkd(&["render", s(&kd), "--tau-occu", "0.5", "--size", "8x8"]);
    let err = exits(&out, 2, "tau");
    assert!(err.contains("--tau-occu"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The main job compares std, small and fast trees traced from their
/// `.kd` files (the same hits), writes slimkd.png into the current
/// directory and leaves nothing in the temporary directory; `-v` adds the
/// phase times and memory.
#[test]
fn main_job_compares_the_three_trees() {
    let dir = fresh_temp_dir("main-job");
    let tmp = dir.join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    for verbose in [false, true] {
        let mut c = Command::new(env!("CARGO_BIN_EXE_slimkd"));
        if verbose {
            c.arg("-v");
        }
        let out = c
            .current_dir(&dir)
            .env("TMPDIR", &tmp)
            .output()
            .expect("the binary runs");
        assert!(out.status.success(), "{}", stderr(&out));
        let text = stdout(&out);
        let rows: Vec<&str> = text
            .lines()
            .filter(|l| {
                let first = l.split_whitespace().next();
                matches!(first, Some("std" | "small" | "fast"))
            })
            .collect();
        assert_eq!(rows.len(), 3, "{text}");
        for (row, name) in rows.iter().zip(["std", "small", "fast"]) {
            assert!(row.trim_start().starts_with(name), "{text}");
            assert!(row.trim_end().ends_with("yes"), "{text}");
        }
        assert!(text.contains("same hits as std"), "{text}");
        // The embedded scene's secondary rays go over wide boxes.
        assert!(text.contains("secondary rays wide"), "{text}");
        assert_eq!(text.contains("RssAnon"), verbose, "{text}");
        assert!(dir.join("slimkd.png").exists());
        assert_eq!(std::fs::read_dir(&tmp).unwrap().count(), 0, "left behind");
        std::fs::remove_file(dir.join("slimkd.png")).unwrap();
    }
    // -q and -v contradict each other.
    let out = slimkd_in(Some(&dir), &["-q", "-v"]);
    exits(&out, 2, "-q with -v");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A small ray file: rays from the views' eye of the bunny's view 1
/// towards its body.
fn write_rays(path: &Path) {
    let mut bytes = Vec::new();
    for k in 0..8 {
        let d = [-1.4f32, 0.4 + 0.01 * k as f32, -7.8];
        for v in [1.349f32, 2.95, 6.446, 0.0, d[0], d[1], d[2], f32::INFINITY] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// Every command prints one JSON object with `--json`, with `"schema": 1`
/// and its name as `command`; the node counts have one key set
/// (`nodes_total`, `nodes_inner`, `nodes_t_inner`, `nodes_leaf`) wherever
/// they appear, and build's old keys are gone.
#[test]
fn every_command_prints_json_with_one_schema() {
    let dir = fresh_temp_dir("json_schema");
    let scene = bunny();
    let kd = dir.join("bunny_npm.kd");
    let kds = dir.join("bunny_npm.kds");
    let rays = dir.join("rays.bin");
    write_rays(&rays);
    let md = dir.join("r.md");
    let runs: Vec<(&str, Vec<&str>)> = vec![
        (
            "build",
            vec!["build", &scene, "-o", s(&kd), "--preset", "small", "--json"],
        ),
        ("info", vec!["info", s(&kd), "--json"]),
        ("verify", vec!["verify", s(&kd), "--json"]),
        ("convert", vec!["convert", &scene, "-o", s(&kds), "--json"]),
        (
            "render",
            vec!["render", s(&kd), "--size", "16x16", "--json"],
        ),
        (
            "render",
            vec!["render", s(&kds), "--size", "16x16", "--json"],
        ),
        (
            "trace",
            vec!["trace", s(&kd), s(&rays), "--reps", "1", "--json"],
        ),
        (
            "report",
            vec![
                "report",
                &scene,
                "--size",
                "16x16",
                "--reps",
                "1",
                "-o",
                s(&md),
                "--json",
            ],
        ),
        ("main", vec!["--json"]),
    ];
    let mut objects = Vec::new();
    for (command, args) in &runs {
        let out = slimkd_in(Some(&dir), args);
        let j = json(&out);
        assert_eq!(j["schema"], 1, "{args:?}: {j}");
        assert_eq!(j["command"], *command, "{args:?}: {j}");
        objects.push(j);
    }
    let node_keys = ["nodes_total", "nodes_inner", "nodes_t_inner", "nodes_leaf"];
    // build, info, verify, render of the file: the same counts.
    for j in [&objects[1], &objects[2], &objects[3 + 1]] {
        for key in node_keys {
            assert_eq!(j[key], objects[0][key], "{key}: {j}");
        }
    }
    for key in node_keys {
        assert!(objects[5][key].is_u64(), "render of a scene lacks {key}");
        assert!(
            objects[8]["trees"][0][key].is_u64(),
            "the main job lacks {key}"
        );
    }
    for old in ["nodes", "inner", "t_inner", "leaves", "empty_leaves"] {
        assert!(
            objects[0].get(old).is_none(),
            "build --json still has {old}"
        );
    }
    assert_eq!(objects[1]["scene_name"], "bunny_npm");
    assert_eq!(objects[7]["scenes"][0], "bunny_npm");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `-q` prints errors only, `-v` adds detail, on every command; the two
/// together are a usage error.
#[test]
fn quiet_prints_only_errors_and_verbose_adds_detail() {
    let dir = fresh_temp_dir("quiet_verbose");
    let scene = bunny();
    let kd = dir.join("b.kd");
    let out = slimkd(&["build", &scene, "-o", s(&kd), "-q"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!((stdout(&out), stderr(&out)), (String::new(), String::new()));
    for args in [
        vec!["info", s(&kd), "-q"],
        vec!["verify", s(&kd), "-q"],
        vec!["render", s(&kd), "--size", "8x8", "-q"],
    ] {
        let out = slimkd(&args);
        assert!(out.status.success(), "{args:?}: {}", stderr(&out));
        assert_eq!(stdout(&out), "", "{args:?}");
    }
    let missing = dir.join("missing.obj");
    let out = slimkd(&["build", s(&missing), "-q"]);
    let err = exits(&out, 1, "a missing scene with -q");
    assert!(err.contains("missing.obj"), "{err}");
    let plain = stdout(&slimkd(&["build", &scene]));
    let verbose = stdout(&slimkd(&["build", &scene, "-v"]));
    assert!(
        !plain.contains("phases:") && verbose.contains("phases:"),
        "{verbose}"
    );
    let v = stdout(&slimkd(&["verify", s(&kd), "-v"]));
    assert!(v.contains("section") && v.contains("CRC-32"), "{v}");
    let r = stdout(&slimkd(&["render", s(&kd), "--size", "8x8", "-v"]));
    assert!(r.contains("camera     eye"), "{r}");
    exits(&slimkd(&["build", &scene, "-q", "-v"]), 2, "-q with -v");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--help` states the default camera and ends with examples; the flags a
/// user needs come before the measurement knobs.
#[test]
fn help_states_the_default_camera_and_examples() {
    for args in [vec!["--help"], vec!["render", "--help"]] {
        let text = stdout(&slimkd(&args));
        assert!(
            text.contains("normalize(0.6, 0.4, 1.0)"),
            "{args:?}: {text}"
        );
        assert!(text.contains("Examples:"), "{args:?}: {text}");
    }
    let text = stdout(&slimkd(&["build", "--help"]));
    let at = |flag: &str| {
        text.find(flag)
            .unwrap_or_else(|| panic!("{flag} in {text}"))
    };
    for needed in ["--output", "--preset", "--threads"] {
        assert!(
            at(needed) < at("--tiny") && at(needed) < at("--new-events"),
            "{text}"
        );
    }
    assert!(at("Measurement knobs") < at("--tiny"), "{text}");
}

/// The report names scenes by their file stems in its tables, never by the
/// path given, and warns when a scene has no views (it is timed from the
/// default camera).
#[test]
fn report_names_scenes_by_stem_and_warns_without_views() {
    let dir = fresh_temp_dir("report_stems");
    let rabbit = dir.join("rabbit.obj");
    std::fs::copy(bunny(), &rabbit).unwrap();
    let md = dir.join("r.md");
    let out = slimkd(&[
        "report",
        &bunny(),
        s(&rabbit),
        "--size",
        "16x16",
        "--reps",
        "1",
        "-o",
        s(&md),
    ]);
    let err = exits(&out, 0, "report");
    assert!(err.contains("warning: rabbit has no views"), "{err}");
    assert!(!err.contains("warning: bunny_npm"), "{err}");
    let text = std::fs::read_to_string(&md).unwrap();
    assert!(
        text.contains("| bunny_npm") && text.contains("| rabbit"),
        "{text}"
    );
    let scenes_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
    assert!(!text.contains(scenes_dir.to_str().unwrap()), "{text}");
    assert!(!text.contains(dir.to_str().unwrap()), "{text}");
    std::fs::remove_dir_all(&dir).unwrap();
}
