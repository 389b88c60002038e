//! `slimkd sweep` (the trade-off front of tree bytes against trace time)
//! end to end on the embedded scene with one tiny round: the files it
//! writes, the structure of its JSON, the presets among its points with
//! the bytes `slimkd build` writes for them, and the front checked against
//! the points (times are measured, so only their kind is checked). Then
//! its usage and input errors.

mod common;

use common::{dir_entries, fresh_temp_dir, json, slimkd};
use serde_json::Value;
use slimkd::build::sah::SahParams;
use std::path::Path;
use std::sync::OnceLock;

/// The default grid's settings, `K_T` and split-price families (the unit
/// tests of `lab::report::front` hold the grid to these).
const DEFAULT_GRID_SETTINGS: usize = 20;
const FRONT_KT: [f64; 5] = [10.0, 15.0, 20.0, 30.0, 45.0];
const FRONT_SPLIT_PRICE: [f64; 5] = [0.0, 0.25, 0.5, 1.0, 8.0];

/// The sweep of the embedded scene (one round, 16×16 frames) and its
/// directory, run once for the tests that read it (a static is never
/// dropped, so this one directory stays).
fn sweep() -> &'static (Value, common::TestDir) {
    static SWEEP: OnceLock<(Value, common::TestDir)> = OnceLock::new();
    SWEEP.get_or_init(|| {
        let dir = fresh_temp_dir("sweep");
        let d = dir.to_str().unwrap();
        let j = json(&slimkd(&[
            "sweep", "default", "--reps", "1", "--size", "16x16", "-j", "2", "-o", d, "--json",
        ]));
        (j, dir)
    })
}

fn points(scene: &Value) -> &Vec<Value> {
    scene["points"].as_array().expect("points")
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("a number: {v}"))
}

#[test]
fn sweep_writes_markdown_json_and_a_chart_per_scene() {
    let (j, dir) = sweep();
    assert_eq!(j["schema"], 1);
    assert_eq!(j["command"], "sweep");
    assert_eq!(j["threads"], 2);
    assert_eq!(j["reps"], 1);
    assert_eq!(
        (j["width"].clone(), j["height"].clone()),
        (16.into(), 16.into())
    );
    assert_eq!(
        dir_entries(dir),
        ["nexuiz_dieselpower.sweep.svg", "sweep.json", "sweep.md"]
    );
    let written: Vec<&str> = j["written"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p.as_str().unwrap())
        .collect();
    assert_eq!(written.len(), 3);
    for p in &written {
        assert!(Path::new(p).is_file(), "{p}");
    }
    // The file holds what --json printed, without the command's own keys.
    let file: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("sweep.json")).unwrap()).unwrap();
    let mut printed = j.clone();
    let o = printed.as_object_mut().unwrap();
    o.remove("command");
    o.remove("written");
    assert_eq!(file, printed);

    let scene = &j["scenes"][0];
    assert_eq!(scene["name"], "nexuiz_dieselpower");
    assert_eq!(scene["views"], serde_json::json!(["1", "2", "3"]));
    assert_eq!(scene["rays"], 3 * 16 * 16);
    let svg = std::fs::read_to_string(dir.join("nexuiz_dieselpower.sweep.svg")).unwrap();
    assert!(svg.starts_with("<svg"));
    // The texts of the chart, trimmed.
    let texts: Vec<&str> = svg
        .split("<text")
        .skip(1)
        .filter_map(|t| Some(t.split_once('>')?.1.split("</text>").next()?.trim()))
        .collect();
    let md = std::fs::read_to_string(dir.join("sweep.md")).unwrap();
    assert!(md.contains("](nexuiz_dieselpower.sweep.svg)"), "{md}");
    for p in points(scene) {
        let label = p["label"].as_str().unwrap();
        assert!(texts.contains(&label), "{label} not in the chart");
        assert!(
            md.lines().any(|l| l.starts_with(&format!("| {label} |"))
                || l.starts_with(&format!("| **{label}** |"))),
            "{label} not in the table"
        );
    }
    for fam in scene["families"].as_array().unwrap() {
        assert!(texts.contains(&fam["name"].as_str().unwrap()), "{fam}");
    }
    assert!(texts.contains(&"Pareto front"));
    assert!(md.contains("Presets: std "), "{md}");
}

#[test]
fn sweep_families_hold_its_points_and_the_presets_exactly() {
    let (j, _) = sweep();
    let scene = &j["scenes"][0];
    let pts = points(scene);
    // The settings of the default grid (`lab::report::front::default_grid`,
    // whose unit tests hold these figures to it).
    assert_eq!(pts.len(), DEFAULT_GRID_SETTINGS);
    let labels: Vec<&str> = pts.iter().map(|p| p["label"].as_str().unwrap()).collect();
    let families = scene["families"].as_array().unwrap();
    assert!(families.len() >= 3, "{families:?}");
    let mut in_some_family = vec![false; pts.len()];
    for fam in families {
        let names = fam["points"].as_array().unwrap();
        assert!(names.len() >= 4, "{fam}");
        for n in names {
            let k = labels
                .iter()
                .position(|l| n == l)
                .unwrap_or_else(|| panic!("{n} of {} is no point", fam["name"]));
            in_some_family[k] = true;
        }
    }
    assert!(in_some_family.iter().all(|&x| x), "every point on a line");
    // The K_T family varies only K_T; std is its default point.
    let kt = &families[0];
    let kts: Vec<f64> = kt["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| f(&pts[labels.iter().position(|l| n == l).unwrap()]["k_t"]))
        .collect();
    assert_eq!(kts, FRONT_KT);
    // The split-price family varies only μ.
    let mu: Vec<(f64, f64)> = families[1]["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| {
            let p = &pts[labels.iter().position(|l| n == l).unwrap()];
            (f(&p["split_price"]), f(&p["k_t"]))
        })
        .collect();
    assert_eq!(mu, FRONT_SPLIT_PRICE.map(|m| (m, 15.0)));
    let preset = |name: &str| {
        let found: Vec<&Value> = pts.iter().filter(|p| p["preset"] == name).collect();
        assert_eq!(found.len(), 1, "{name}");
        found[0]
    };
    let std = preset("std");
    assert_eq!((f(&std["k_t"]), f(&std["k_i"])), (15.0, 20.0));
    assert_eq!(f(&std["split_price"]), SahParams::default().split_price);
    assert!(std["tau_occu"].is_null() && std["hoisted"] == 0);
    for (name, coarsen) in [("fast", 1.5), ("small", 2.0)] {
        let p = preset(name);
        assert_eq!((f(&p["k_t"]), f(&p["k_i"])), (15.0, 20.0), "{name}");
        assert_eq!(
            (f(&p["tau_occu"]), f(&p["tau_freq"]), &p["max_t2rn"]),
            (0.1, 0.05, &Value::from(16)),
            "{name}"
        );
        assert_eq!(f(&p["coarsen"]), coarsen, "{name}");
        assert_eq!(p["hoist_rule"], "bytes");
        assert!(p["hoisted"].as_u64().unwrap() > 0, "{name} hoists");
        assert!(f(&p["slim_s"]) > 0.0);
        // serde_json reads a float back to within an ulp, not exactly.
        let sum = f(&p["std_build_s"]) + f(&p["slim_s"]);
        assert!((f(&p["build_s"]) - sum).abs() <= 1e-12 * sum, "{p}");
    }
    for p in pts {
        let (lo, med, hi) = (
            f(&p["trace_ms_min"]),
            f(&p["trace_ms_median"]),
            f(&p["trace_ms_max"]),
        );
        assert!(0.0 < lo && lo <= med && med <= hi, "{p}");
        assert_eq!(p["trace_ms_reps"].as_array().unwrap().len(), 1);
        assert!(p["tree_bytes"].as_u64().unwrap() > 0);
    }
}

/// The tree bytes of a point are those of the file `slimkd build
/// --reorder` writes with the same settings.
#[test]
fn sweep_tree_bytes_are_the_written_files() {
    let (j, _) = sweep();
    let pts = points(&j["scenes"][0]);
    let dir = fresh_temp_dir("sweep-bytes");
    for (label, flags) in [
        ("std", &[][..]),
        ("fast", &["--preset", "fast"][..]),
        ("small", &["--preset", "small"][..]),
        ("K_T 30", &["--kt", "30"][..]),
        // small's split price, coarsening and price rule, other thresholds.
        (
            "0.3/0.2 c2 p0.05 μ2",
            &[
                "--preset",
                "small",
                "--tau-occu",
                "0.3",
                "--tau-freq",
                "0.2",
            ][..],
        ),
    ] {
        let out = dir.join("t.kd");
        let mut args = vec!["build", "default", "--reorder", "-j", "2", "--json", "-o"];
        args.push(out.to_str().unwrap());
        args.extend_from_slice(flags);
        let built = json(&slimkd(&args));
        let p = pts
            .iter()
            .find(|p| p["label"] == label)
            .unwrap_or_else(|| panic!("no point {label}"));
        assert_eq!(p["tree_bytes"], built["tree_bytes"], "{label}");
        assert_eq!(p["nodes_total"], built["nodes_total"], "{label}");
    }
}

/// The front, recomputed from the points: a point is on it exactly when no
/// other point has at most its bytes and at most its median time, one of
/// them strictly less; `front` lists those points by median time.
#[test]
fn sweep_front_is_the_pareto_front_of_its_points() {
    let (j, _) = sweep();
    let scene = &j["scenes"][0];
    let pts = points(scene);
    let xy: Vec<(u64, f64)> = pts
        .iter()
        .map(|p| (p["tree_bytes"].as_u64().unwrap(), f(&p["trace_ms_median"])))
        .collect();
    let mut expected = Vec::new();
    for (i, &(b, t)) in xy.iter().enumerate() {
        let dominated = xy
            .iter()
            .enumerate()
            .any(|(k, &(b2, t2))| k != i && b2 <= b && t2 <= t && (b2 < b || t2 < t));
        assert_eq!(pts[i]["on_front"], !dominated, "{}", pts[i]);
        if !dominated {
            expected.push((t, pts[i]["label"].as_str().unwrap()));
        }
    }
    assert!(!expected.is_empty());
    // The smallest tree and the fastest are always on it.
    let smallest = xy.iter().map(|p| p.0).min().unwrap();
    assert!(
        pts.iter()
            .zip(&xy)
            .any(|(p, q)| q.0 == smallest && p["on_front"] == true)
    );
    expected.sort_by(|a, b| a.0.total_cmp(&b.0));
    let front: Vec<&str> = scene["front"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l.as_str().unwrap())
        .collect();
    assert_eq!(front, expected.iter().map(|e| e.1).collect::<Vec<_>>());
}

#[test]
fn sweep_usage_errors_exit_2_and_a_missing_directory_exits_1() {
    for args in [
        &["sweep"][..],
        &["sweep", "default", "--reps", "0"],
        &["sweep", "default", "-j", "0"],
        &["sweep", "default", "--size", "0x16"],
    ] {
        let out = slimkd(args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
    }
    let dir = fresh_temp_dir("sweep-missing");
    let missing = dir.join("no-such-dir");
    let out = slimkd(&[
        "sweep",
        "default",
        "--reps",
        "1",
        "-o",
        missing.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no-such-dir"), "{err}");
    assert!(dir_entries(&dir).is_empty());
    let out = slimkd(&[
        "sweep",
        "no-such-scene.obj",
        "--reps",
        "1",
        "-o",
        dir.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such-scene.obj"));
    assert!(dir_entries(&dir).is_empty());
}
