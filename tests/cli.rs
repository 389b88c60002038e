//! The command line end to end: `build -o`, `info`, `verify`, and `render`
//! of a `.kd` file in every mode, against the same scene rendered from OBJ;
//! `trace` of a ray file in every mode against brute force, and bad ray
//! files named by record; the SAH-constant flags.

mod common;

use common::{fresh_temp_dir, json, slimkd};
use std::path::Path;
use std::process::{Command, Output};

fn manifest(p: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(p)
        .to_str()
        .unwrap()
        .to_string()
}

#[test]
fn build_info_verify_render_round_trip() {
    let dir = fresh_temp_dir("roundtrip");
    let scene = manifest("scenes/bunny_npm.obj");
    let views = manifest("scenes/views.txt");
    for preset in ["std", "small"] {
        let kd = dir.join(format!("bunny_npm.{preset}.kd"));
        let kd_s = kd.to_str().unwrap();
        let b = json(&slimkd(&[
            "build",
            &scene,
            "-o",
            kd_s,
            "--reorder",
            "--preset",
            preset,
            "--json",
        ]));
        assert_eq!(b["triangles"], 3674);
        assert_eq!(b["preset"], preset);
        for key in [
            "tree_bytes",
            "nodes_inner",
            "nodes_t_inner",
            "nodes_leaf",
            "idx32",
            "idx16",
        ] {
            assert!(b.get(key).is_some(), "build --json lacks {key}");
        }

        let info = json(&slimkd(&["info", kd_s, "--json"]));
        for key in [
            "tree_bytes",
            "geometry_bytes",
            "nodes_inner",
            "nodes_t_inner",
            "nodes_leaf",
            "idx32",
            "idx16",
            "max_depth",
            "open_ms",
        ] {
            assert!(info.get(key).is_some(), "info --json lacks {key}");
        }
        assert_eq!(info["tree_bytes"], b["tree_bytes"]);
        assert_eq!(info["preset"], preset);
        let f = |k: &str| info[k].as_u64().unwrap();
        // The counts are the file's; its empty leaves without a word take
        // no bytes.
        let fig =
            slimkd::format::KdFile::open(std::path::Path::new(kd_s), slimkd::format::Check::Verify)
                .unwrap()
                .figures();
        assert_eq!(
            [
                f("nodes_inner"),
                f("nodes_t_inner"),
                f("nodes_leaf"),
                f("empty_leaves_without_word"),
                f("one_triangle_leaves")
            ],
            [
                fig.inner,
                fig.t_inner,
                fig.leaves,
                fig.implicit_empty,
                fig.one_leaves
            ]
        );
        assert!(f("empty_leaves_without_word") > 0);
        assert_eq!(
            f("tree_bytes"),
            8 * (f("nodes_inner") + 2 * f("nodes_t_inner") + f("nodes_leaf")
                - f("empty_leaves_without_word"))
                + 4 * f("idx32")
                + 2 * f("idx16")
        );
        let text = slimkd(&["info", kd_s]);
        assert!(text.status.success());
        assert!(String::from_utf8_lossy(&text.stdout).contains("table 3(a)"));

        let v = slimkd(&["verify", kd_s]);
        assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stderr));

        // The same view from the OBJ (scalar, in memory) and from the file
        // in every mode gives the same hits and checksum.
        let reference = json(&slimkd(&[
            "render", &scene, "--views", &views, "--view", "2", "--size", "40x24", "--json",
        ]));
        for mode in ["single", "packet", "brute"] {
            let r = json(&slimkd(&[
                "render", kd_s, "--views", &views, "--view", "2", "--size", "40x24", "--mode",
                mode, "--json",
            ]));
            assert_eq!(r["hits"], reference["hits"], "{preset} {mode}");
            assert_eq!(r["checksum"], reference["checksum"], "{preset} {mode}");
            assert_eq!(r["mode"], mode);
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn verify_rejects_corrupt_and_truncated_files() {
    let dir = fresh_temp_dir("corrupt");
    let kd = dir.join("d.kd");
    let kd_s = kd.to_str().unwrap();
    let out = slimkd(&["build", "default", "-o", kd_s]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes = std::fs::read(&kd).unwrap();

    // A flipped bit in the geometry: the structure is valid, the checksum
    // is not.
    let mut flipped = bytes.clone();
    let last = flipped.len() - 100;
    flipped[last] ^= 0x10;
    let bad = dir.join("flipped.kd");
    std::fs::write(&bad, &flipped).unwrap();
    let v = slimkd(&["verify", bad.to_str().unwrap()]);
    assert_eq!(v.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&v.stderr).contains("checksum"),
        "{}",
        String::from_utf8_lossy(&v.stderr)
    );

    let short = dir.join("short.kd");
    std::fs::write(&short, &bytes[..bytes.len() / 2]).unwrap();
    let v = slimkd(&["verify", short.to_str().unwrap()]);
    assert_eq!(v.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&v.stderr).contains("truncated"));
    let r = slimkd(&["render", short.to_str().unwrap(), "--size", "8x8"]);
    assert_eq!(r.status.code(), Some(1));

    let junk = dir.join("junk.kd");
    std::fs::write(&junk, b"not a kd file at all").unwrap();
    let v = slimkd(&["info", junk.to_str().unwrap()]);
    assert_eq!(v.status.code(), Some(1));
    // Another kind of file is named as such, short or long, not as a
    // truncated `.kd` file; a directory is named as one.
    for other in [&b"v 0 0 0\n"[..], &[b'#'; 4096][..]] {
        std::fs::write(&junk, other).unwrap();
        let v = slimkd(&["verify", junk.to_str().unwrap()]);
        assert_eq!(v.status.code(), Some(1));
        let err = String::from_utf8_lossy(&v.stderr);
        assert!(err.contains("not a slimkd .kd file"), "{err}");
    }
    let v = slimkd(&["info", dir.to_str().unwrap()]);
    assert_eq!(v.status.code(), Some(1));
    let err = String::from_utf8_lossy(&v.stderr);
    assert!(err.contains("is a directory"), "{err}");

    // A failed build leaves no output file behind.
    let missing = dir.join("no/such/dir/x.kd");
    let out = slimkd(&["build", "default", "-o", missing.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    assert!(!missing.exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// `convert` writes a scene cache; building from it gives the same file,
/// byte for byte, as building from the OBJ; a bad output name, a truncated
/// cache and a corrupted one are clear errors naming the file.
#[test]
fn scene_cache_builds_the_same_tree() {
    let dir = fresh_temp_dir("kds");
    let scene = manifest("scenes/bunny_npm.obj");
    // The cache has the scene's stem, so the files record the same scene
    // name.
    let kds = dir.join("bunny_npm.kds");
    let kds_s = kds.to_str().unwrap();
    let out = slimkd(&["convert", &scene, "-o", kds_s]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let from_obj = dir.join("obj.kd");
    let from_kds = dir.join("kds.kd");
    let a = json(&slimkd(&[
        "build",
        &scene,
        "-o",
        from_obj.to_str().unwrap(),
        "--json",
    ]));
    let b = json(&slimkd(&[
        "build",
        kds_s,
        "-o",
        from_kds.to_str().unwrap(),
        "--json",
    ]));
    assert_eq!(a["triangles"], b["triangles"]);
    assert_eq!(a["dropped_degenerate"], b["dropped_degenerate"]);
    assert_eq!(
        std::fs::read(&from_obj).unwrap(),
        std::fs::read(&from_kds).unwrap()
    );

    let wrong = dir.join("bunny.bin");
    let out = slimkd(&["convert", &scene, "-o", wrong.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains(".kds"));
    assert!(!wrong.exists());

    let bytes = std::fs::read(&kds).unwrap();
    let bad = dir.join("bad.kds");
    for damaged in [bytes[..bytes.len() / 2].to_vec(), {
        let mut b = bytes.clone();
        let i = b.len() / 3;
        b[i] ^= 0x40;
        b
    }] {
        std::fs::write(&bad, &damaged).unwrap();
        let out = slimkd(&["build", bad.to_str().unwrap()]);
        assert_eq!(out.status.code(), Some(1));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains("bad.kds") && err.contains("not a valid scene cache"),
            "{err}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--tiny` changes how the finisher finds splits, never the tree: 0
/// (events everywhere), the default and 64 write the same file, byte for
/// byte. A value above 64 is a usage error (exit 2) that writes nothing.
#[test]
fn tiny_threshold_writes_the_same_file() {
    let dir = fresh_temp_dir("tiny");
    let scene = manifest("scenes/nexuiz_dieselpower.obj");
    let build = |name: &str, extra: &[&str]| {
        let out = dir.join(name);
        let mut args = vec!["build", &scene, "-o", out.to_str().unwrap(), "--json"];
        args.extend_from_slice(extra);
        json(&slimkd(&args));
        std::fs::read(&out).unwrap()
    };
    let default = build("default.kd", &[]);
    assert!(default == build("events.kd", &["--tiny", "0"]), "--tiny 0");
    assert!(default == build("all.kd", &["--tiny", "64"]), "--tiny 64");

    let bad = dir.join("bad.kd");
    let out = slimkd(&["build", &scene, "-o", bad.to_str().unwrap(), "--tiny", "65"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--tiny"));
    assert!(!bad.exists());
    std::fs::remove_dir_all(dir).unwrap();
}

/// A camera that defines no rays (`up` along the view direction, `eye` on
/// `at`) is an error naming the cause, not an image of NaN rays that all
/// miss; and no image is written.
#[test]
fn render_refuses_a_degenerate_camera() {
    let dir = fresh_temp_dir("camera");
    let png = dir.join("x.png");
    let png_s = png.to_str().unwrap();
    for (eye, at, up, what) in [
        ("0,5,0", "0,0,0", "0,1,0", "parallel"),
        ("1,2,3", "1,2,3", "0,1,0", "same point"),
        ("0,0,5", "0,0,0", "0,0,0", "zero"),
    ] {
        let out = slimkd(&[
            "render", "default", "--eye", eye, "--at", at, "--up", up, "--size", "8x8", "-o", png_s,
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains(what), "{err}");
        assert!(!png.exists());
    }
    // The same views with a usable up render.
    let out = slimkd(&[
        "render", "default", "--eye", "0,5,0", "--at", "0,0,0", "--up", "0,0,1", "--size", "8x8",
        "-o", png_s,
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(png.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn trace_matches_brute_force_in_every_mode() {
    let dir = fresh_temp_dir("trace-modes");
    let scene_path = Path::new(&manifest("scenes/bunny_npm.obj")).to_path_buf();
    let kd = dir.join("bunny.kd");
    let out = slimkd(&[
        "build",
        scene_path.to_str().unwrap(),
        "-o",
        kd.to_str().unwrap(),
        "--reorder",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (scene, _) = slimkd::scene::load_obj(&scene_path).unwrap();
    let b = scene.bounds();
    let o = b.center() + glam::Vec3::new(0.0, 0.0, 3.0 * (b.max - b.min).length());
    // 700 rays: a partial last chunk and a partial last packet.
    let rays: Vec<slimkd::geom::Ray> = (0..700)
        .map(|i| {
            let target = b.min
                + (b.max - b.min)
                    * glam::Vec3::new((i % 28) as f32 / 28.0, (i / 28) as f32 / 25.0, 0.5);
            let mut r = slimkd::geom::Ray::new(o, target - o);
            // A hit exactly at tmax: closest hit, but not occluded.
            let t = slimkd::trace::brute_force(&scene, &r).t;
            if i % 3 == 0 && t.is_finite() {
                r.tmax = t;
            }
            r
        })
        .collect();
    let ray_file = dir.join("test.rays");
    std::fs::write(&ray_file, slimkd::trace::rays::ray_bytes(&rays)).unwrap();
    let want: Vec<f32> = rays
        .iter()
        .map(|r| slimkd::trace::brute_force(&scene, r).t)
        .collect();
    let hits = want.iter().filter(|t| t.is_finite()).count() as u64;
    let sum: f64 = want
        .iter()
        .filter(|t| t.is_finite())
        .map(|&t| f64::from(t))
        .sum();
    let occ: Vec<bool> = want.iter().zip(&rays).map(|(&t, r)| t < r.tmax).collect();
    let occ_hits = occ.iter().filter(|&&o| o).count() as u64;
    let occ_sum: f64 = occ
        .iter()
        .enumerate()
        .filter(|(_, o)| **o)
        .map(|(i, _)| i as f64)
        .sum();
    assert!(hits > 100 && occ_hits < hits, "{hits} {occ_hits}");
    for mode in [
        "single",
        "packet",
        "sorted",
        "from-hit",
        "ropes",
        "wide",
        "wide-packet",
    ] {
        let dump = dir.join(format!("{mode}.f32"));
        let j = json(&slimkd(&[
            "trace",
            kd.to_str().unwrap(),
            ray_file.to_str().unwrap(),
            "--mode",
            mode,
            "--reps",
            "2",
            "--stats",
            "--json",
            "--dump",
            dump.to_str().unwrap(),
        ]));
        assert_eq!(j["mode"], mode);
        assert_eq!(j["rays"], 700);
        assert_eq!(j["hits"], hits);
        assert_eq!(j["checksum"].as_f64().unwrap(), sum);
        assert!(j["mrays_per_s"].as_f64().unwrap() > 0.0);
        assert!(j["stats"]["nodes_per_ray"].as_f64().unwrap() > 1.0);
        // Ropes are reported apart from the tree, and only in their mode.
        assert_eq!(
            j["ropes"]["cells"].as_u64().unwrap_or(0) > 0,
            mode == "ropes"
        );
        assert_eq!(
            j["wide"]["nodes"].as_u64().unwrap_or(0) > 0,
            mode.starts_with("wide")
        );
        let bytes = std::fs::read(&dump).unwrap();
        let got: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(got, want);
        let j = json(&slimkd(&[
            "trace",
            kd.to_str().unwrap(),
            ray_file.to_str().unwrap(),
            "--occluded",
            "--mode",
            mode,
            "--reps",
            "1",
            "--json",
        ]));
        assert_eq!(j["query"], "occluded");
        assert_eq!(j["hits"], occ_hits);
        assert_eq!(j["checksum"].as_f64().unwrap(), occ_sum);
    }
    // Ropes of a slim tree: exit 1, the file named and why.
    let slim_kd = dir.join("slim.kd");
    let out = slimkd(&[
        "build",
        scene_path.to_str().unwrap(),
        "-o",
        slim_kd.to_str().unwrap(),
        "--preset",
        "small",
    ]);
    assert!(out.status.success());
    let out = slimkd(&[
        "trace",
        slim_kd.to_str().unwrap(),
        ray_file.to_str().unwrap(),
        "--mode",
        "ropes",
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("slim.kd") && err.contains("--preset std"),
        "{err}"
    );
    // A bad ray file: exit 1, the file and the record named.
    let mut bytes = slimkd::trace::rays::ray_bytes(&rays[..3]);
    bytes[2 * 32 + 16..2 * 32 + 20].copy_from_slice(&f32::NAN.to_le_bytes());
    let bad = dir.join("bad.rays");
    std::fs::write(&bad, &bytes).unwrap();
    let out = slimkd(&["trace", kd.to_str().unwrap(), bad.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.rays") && err.contains("ray 2") && err.contains("direction"),
        "{err}"
    );
    std::fs::write(&bad, &bytes[..50]).unwrap();
    let out = slimkd(&["trace", kd.to_str().unwrap(), bad.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("multiple of 32"));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn sah_constants_are_flags_recorded_in_the_file() {
    let dir = fresh_temp_dir("sah-flags");
    let scene = Path::new(&manifest("scenes/bunny_npm.obj")).to_path_buf();
    let scene = scene.to_str().unwrap();
    let default = dir.join("default.kd");
    let cheap = dir.join("kt30.kd");
    let d = json(&slimkd(&[
        "build",
        scene,
        "-o",
        default.to_str().unwrap(),
        "--json",
    ]));
    let c = json(&slimkd(&[
        "build",
        scene,
        "-o",
        cheap.to_str().unwrap(),
        "--kt",
        "30",
        "--ki",
        "20",
        "--lambda",
        "1",
        "--json",
    ]));
    // Dearer traversal steps make fewer nodes.
    assert!(
        c["nodes_total"].as_u64().unwrap() < d["nodes_total"].as_u64().unwrap(),
        "{c} {d}"
    );
    let info = json(&slimkd(&["info", cheap.to_str().unwrap(), "--json"]));
    assert_eq!(info["k_t"], 30.0);
    assert_eq!(info["k_i"], 20.0);
    assert_eq!(info["lambda_empty"], 1.0);
    for bad in [
        ["--kt", "0"],
        ["--kt", "nan"],
        ["--ki", "-1"],
        ["--lambda", "0"],
        ["--lambda", "1.5"],
    ] {
        let out = slimkd(&["build", scene, bad[0], bad[1]]);
        assert_eq!(out.status.code(), Some(2), "{bad:?}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_closed_output_pipe_ends_quietly() {
    use std::io::Read;
    use std::process::Stdio;
    // The main job prints its first line before a second of work, so the
    // lines after it meet the closed pipe.
    let dir = fresh_temp_dir("closed-pipe");
    let mut child = Command::new(env!("CARGO_BIN_EXE_slimkd"))
        .current_dir(&dir)
        .env("TMPDIR", &*dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the binary runs");
    // Read one byte of the output, then close the pipe (as `| head -c 1`).
    let mut out = child.stdout.take().unwrap();
    let mut byte = [0u8; 1];
    out.read_exact(&mut byte).unwrap();
    drop(out);
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    child.wait().unwrap();
    assert!(!err.contains("panicked"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Runs `args`, killing it after `secs` seconds: `None` if it was still
/// running then.
fn slimkd_within(args: &[&str], secs: u64) -> Option<Output> {
    use std::process::Stdio;
    let mut child = Command::new(env!("CARGO_BIN_EXE_slimkd"))
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the binary runs");
    let start = std::time::Instant::now();
    while start.elapsed() < std::time::Duration::from_secs(secs) {
        if child.try_wait().unwrap().is_some() {
            return Some(child.wait_with_output().unwrap());
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().ok();
    child.wait().ok();
    None
}

/// `verify`, `info` and `build` refuse a FIFO within 2 s (an `open` of it
/// waits for a writer forever), naming the file and what it is.
#[cfg(target_os = "linux")]
#[test]
fn a_fifo_is_refused_at_once() {
    let dir = fresh_temp_dir("fifo");
    let out_kd = dir.join("out.kd");
    for name in ["pipe.kd", "pipe.obj", "pipe.kds"] {
        let fifo = dir.join(name);
        let made = Command::new("mkfifo").arg(&fifo).status();
        if !made.is_ok_and(|s| s.success()) {
            common::skip("mkfifo is not available");
            return;
        }
        let f = fifo.to_str().unwrap();
        let runs: Vec<Vec<&str>> = vec![
            vec!["verify", f],
            vec!["info", f],
            vec!["build", f, "-o", out_kd.to_str().unwrap()],
        ];
        for args in runs {
            let out = slimkd_within(&args, 2).unwrap_or_else(|| panic!("{args:?} blocked"));
            assert_eq!(out.status.code(), Some(1), "{args:?}");
            let err = String::from_utf8_lossy(&out.stderr);
            // A name of the wrong kind for the command (`build pipe.kd`,
            // `info pipe.obj`) is refused by its name, before any open.
            let refused_by_name =
                err.contains("but a scene was expected") || err.contains("expects a .kd tree file");
            assert!(
                err.contains(f) && (err.contains("not a regular file (a FIFO)") || refused_by_name),
                "{err}"
            );
        }
    }
    assert!(!out_kd.exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// Under an address-space limit (`ulimit -v`) too small for it, a build
/// of the embedded scene ends with exit status 1 and a message, never by
/// a signal (an allocation's abort, status 134) or a panic (101); with
/// room enough it succeeds.
#[test]
fn a_build_out_of_memory_is_an_error() {
    let probe = Command::new("sh").args(["-c", "ulimit -v 100000"]).status();
    if !probe.is_ok_and(|s| s.success()) {
        common::skip("this shell has no ulimit -v");
        return;
    }
    let dir = fresh_temp_dir("ulimit");
    let out = dir.join("out.kd");
    for kib in [15000, 20000, 30000, 45000, 400000] {
        let script = format!("ulimit -v {kib} && exec \"$0\" build default -o \"$1\"",);
        let run = Command::new("sh")
            .args([
                "-c",
                &script,
                env!("CARGO_BIN_EXE_slimkd"),
                out.to_str().unwrap(),
            ])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&run.stderr);
        let clean_error = err.contains("slimkd: error: ") && err.contains("memory");
        // Where the limit falls on a thread's start-up, the Rust runtime of
        // a thread starting beside the one that ran out can fail to map its
        // signal stack and panic (or abort) on its own, after slimkd's
        // error is out and while the process ends: accepted only then, and
        // only that panic.
        let runtime_start_race =
            clean_error && err.contains("failed to allocate an alternative stack");
        match run.status.code() {
            Some(0) => assert!(out.exists(), "{kib} KiB"),
            Some(1) => assert!(clean_error, "{kib} KiB: {err}"),
            _ if runtime_start_race => {}
            other => panic!("{kib} KiB: status {other:?} ({})\n{err}", run.status),
        }
        let panics = err.matches("panicked").count();
        let runtime_panics = err
            .matches("failed to allocate an alternative stack")
            .count();
        assert!(
            panics == 0 || (runtime_start_race && panics == runtime_panics),
            "{kib} KiB: {err}"
        );
        if kib == 400000 {
            assert_eq!(run.status.code(), Some(0), "{err}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// `strace` kills the build at its rename, which leaves the complete
/// temporary file `.out.kd.tmp.PID.N` beside the missing `out.kd`; the next
/// build of `out.kd` removes it. (Without strace the unit test
/// `fsio::tests::a_kill_before_the_rename_is_cleaned_up` kills a writer
/// there itself.)
#[test]
fn a_kill_at_the_rename_leaves_nothing_lasting() {
    let probe = Command::new("strace").arg("-V").output();
    if !probe.is_ok_and(|o| o.status.success()) {
        common::skip("strace is not installed");
        return;
    }
    let dir = fresh_temp_dir("kill-at-rename");
    let out = dir.join("out.kd");
    let killed = Command::new("strace")
        .args([
            "-f",
            "-o",
            "/dev/null",
            "-e",
            "inject=rename:signal=SIGKILL:when=1",
        ])
        .arg(env!("CARGO_BIN_EXE_slimkd"))
        .args(["build", "default", "-o", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!killed.status.success());
    let left = common::dir_entries(&dir);
    if left.is_empty() {
        common::skip("strace could not inject the kill here");
        return;
    }
    assert_eq!(left.len(), 1, "{left:?}");
    assert!(left[0].starts_with(".out.kd.tmp."), "{left:?}");
    let again = slimkd(&["build", "default", "-o", out.to_str().unwrap()]);
    assert!(
        again.status.success(),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    assert_eq!(common::dir_entries(&dir), ["out.kd"]);
    std::fs::remove_dir_all(&dir).ok();
}

/// A `.kd` file keeps its views when renamed: the header records the
/// scene's name (`bunny_npm`), which views are matched by before the file's
/// stem (`die_small`); `info` shows the name and the geometry hash, the
/// same for every file of the scene.
#[test]
fn a_renamed_kd_file_keeps_its_views() {
    let dir = fresh_temp_dir("renamed_views");
    let scene = manifest("scenes/bunny_npm.obj");
    let views = manifest("scenes/views.txt");
    let kd = dir.join("die_small.kd");
    let kd_s = kd.to_str().unwrap();
    let built = slimkd(&["build", &scene, "-o", kd_s, "--preset", "small"]);
    assert!(
        built.status.success(),
        "{}",
        String::from_utf8_lossy(&built.stderr)
    );
    let render = |file: &str, view: &str| {
        slimkd(&[
            "render", file, "--views", &views, "--view", view, "--size", "32x32", "--json",
        ])
    };
    let from_kd = json(&render(kd_s, "2"));
    let from_obj = json(&render(&scene, "2"));
    assert_eq!(from_kd["eye"], from_obj["eye"]);
    assert_eq!(from_kd["checksum"], from_obj["checksum"]);
    let info = json(&slimkd(&["info", kd_s, "--json"]));
    assert_eq!(info["scene_name"], "bunny_npm");
    let std_kd = dir.join("other.kd");
    json(&slimkd(&[
        "build",
        &scene,
        "-o",
        std_kd.to_str().unwrap(),
        "--reorder",
        "--json",
    ]));
    let info_std = json(&slimkd(&["info", std_kd.to_str().unwrap(), "--json"]));
    assert_eq!(info["geometry_hash"], info_std["geometry_hash"]);
    assert_ne!(info["geometry_hash"], "0000000000000000");
    // A view of no scene of that name: the error gives both names and the rule.
    let missing = render(kd_s, "9");
    assert_eq!(missing.status.code(), Some(1));
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(
        err.contains("`bunny_npm`") && err.contains("`die_small`") && err.contains("file's stem"),
        "{err}"
    );
}
