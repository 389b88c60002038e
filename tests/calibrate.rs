//! `slimkd calibrate` end to end on the embedded scene with tiny settings:
//! the structure of its output (the figures themselves are measured, so
//! only their kind is checked), its usage errors, and the paper's-layout
//! baseline of `info` against the build's own counts.

mod common;

use common::{fresh_temp_dir, json, slimkd};
use std::path::Path;

fn check_fit(fit: &serde_json::Value, samples: usize, intercepts: usize) {
    assert_eq!(fit["samples"], samples, "{fit}");
    for key in ["a_ns_per_step", "b_ns_per_test"] {
        let v = fit[key].as_f64().unwrap_or_else(|| panic!("{key}: {fit}"));
        assert!(v >= 0.0, "{key} is non-negative: {fit}");
    }
    assert_eq!(
        fit["c_ns_per_ray"].as_array().unwrap().len(),
        intercepts,
        "{fit}"
    );
    assert_eq!(
        fit["residuals_ns"].as_array().unwrap().len(),
        samples,
        "{fit}"
    );
    // The ratio may be infinite (b = 0: JSON null) but is never negative.
    for key in ["k_t_over_k_i", "implied_k_t", "r2", "rms_residual_ns"] {
        assert!(fit.get(key).is_some(), "{key}: {fit}");
    }
    assert!(fit["rms_residual_ns"].as_f64().unwrap() >= 0.0);
}

#[test]
fn calibrate_on_the_embedded_scene_prints_fits_per_scene_and_pooled() {
    let common = [
        "calibrate",
        "--rays-per-scene",
        "256",
        "--reps",
        "1",
        "--kt",
        "10,40",
        "-j",
        "1",
    ];
    let mut args = common.to_vec();
    args.push("--json");
    let j = json(&slimkd(&args));
    assert_eq!(j["schema"], 1);
    assert_eq!(j["command"], "calibrate");
    assert_eq!(j["threads"], 1);
    assert_eq!(j["reps"], 1);
    assert_eq!(j["k_i"], 20.0);
    assert_eq!(j["kt_values"], serde_json::json!([10.0, 40.0]));
    let scenes = j["scenes"].as_array().unwrap();
    assert_eq!(scenes.len(), 1);
    let s = &scenes[0];
    assert_eq!(s["name"], "nexuiz_dieselpower");
    assert_eq!(s["views"], serde_json::json!(["1", "2", "3"]));
    let trees = s["trees"].as_array().unwrap();
    assert_eq!(trees.len(), 2);
    // A dearer step makes a smaller tree.
    assert!(trees[1]["tree_bytes"].as_u64() < trees[0]["tree_bytes"].as_u64());
    // Every tree × {primary, ao} × {packet, single}.
    let samples = s["samples"].as_array().unwrap();
    assert_eq!(samples.len(), 8);
    for smp in samples {
        assert!(smp["n_rays"].as_u64().unwrap() > 0, "{smp}");
        assert!(smp["ns_per_ray"].as_f64().unwrap() > 0.0, "{smp}");
        assert!(smp["wall_ns_per_ray"].as_f64().unwrap() > 0.0, "{smp}");
        assert_eq!(smp["ns_per_ray_reps"].as_array().unwrap().len(), 1);
        assert!(smp["steps_per_ray"].as_f64().unwrap() >= 1.0, "{smp}");
        assert!(smp["tests_per_ray"].as_f64().unwrap() > 0.0, "{smp}");
        assert!(["primary", "ao"].contains(&smp["rays"].as_str().unwrap()));
        assert!(["packet", "single"].contains(&smp["mode"].as_str().unwrap()));
    }
    // The counts are the counting traversal's, the same in every run.
    let again = json(&slimkd(&args));
    for (a, b) in samples
        .iter()
        .zip(again["scenes"][0]["samples"].as_array().unwrap())
    {
        assert_eq!(a["steps_per_ray"], b["steps_per_ray"]);
        assert_eq!(a["tests_per_ray"], b["tests_per_ray"]);
    }
    for mode in ["packet", "single"] {
        check_fit(&s["fits"][mode], 4, 2);
        check_fit(&j["pooled"][mode], 4, 2);
        check_fit(&j["pooled_primary"][mode], 2, 1);
        check_fit(&j["pooled_ao"][mode], 2, 1);
    }
    let text = slimkd(&common);
    assert!(text.status.success());
    let out = String::from_utf8_lossy(&text.stdout);
    assert!(
        out.contains("a (ns/step)") && out.contains("K_T at K_I 20"),
        "{out}"
    );
    assert!(out.lines().any(|l| l.starts_with("pooled")), "{out}");
    assert_eq!(
        out.lines()
            .filter(|l| l.starts_with("nexuiz_dieselpower"))
            .count(),
        2,
        "{out}"
    );
}

/// Where no primary ray hits, the AO set is empty: its samples have no
/// time, and the fits come from the primary rays alone.
#[test]
fn calibrate_with_views_that_miss_has_no_ao_samples_timed() {
    let dir = fresh_temp_dir("calibrate-miss");
    let views = dir.join("views.txt");
    std::fs::write(
        &views,
        "nexuiz_dieselpower 1 eye=100000,100000,100000 at=200000,200000,200000 up=0,0,1 fov=60\n",
    )
    .unwrap();
    let j = json(&slimkd(&[
        "calibrate",
        "--views",
        views.to_str().unwrap(),
        "--rays-per-scene",
        "64",
        "--reps",
        "1",
        "--kt",
        "10,40",
        "-j",
        "1",
        "--json",
    ]));
    let s = &j["scenes"][0];
    assert_eq!(s["views"], serde_json::json!(["1"]));
    for smp in s["samples"].as_array().unwrap() {
        if smp["rays"] == "ao" {
            assert_eq!(smp["n_rays"], 0, "{smp}");
            assert!(smp["ns_per_ray"].is_null(), "{smp}");
        } else {
            assert!(smp["n_rays"].as_u64().unwrap() > 0, "{smp}");
        }
    }
    for mode in ["packet", "single"] {
        check_fit(&s["fits"][mode], 2, 1);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn calibrate_usage_errors_exit_2() {
    for bad in [
        &["calibrate", "--kt", "15"][..],
        &["calibrate", "--kt", "15,15"],
        &["calibrate", "--kt", "0,15"],
        &["calibrate", "--reps", "0"],
        &["calibrate", "--rays-per-scene", "0"],
        &["calibrate", "-j", "0"],
    ] {
        let out = slimkd(bad);
        assert_eq!(out.status.code(), Some(2), "{bad:?}");
    }
    let out = slimkd(&["calibrate", "no-such-scene.obj", "--rays-per-scene", "16"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such-scene.obj"));
}

#[test]
fn info_gives_the_paper_layout_of_the_tree_shape() {
    let dir = fresh_temp_dir("paper-layout");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj");
    for preset in ["std", "small"] {
        let kd = dir.join(format!("{preset}.kd"));
        let b = json(&slimkd(&[
            "build",
            scene.to_str().unwrap(),
            "-o",
            kd.to_str().unwrap(),
            "--reorder",
            "--preset",
            preset,
            "--json",
        ]));
        let i = json(&slimkd(&["info", kd.to_str().unwrap(), "--json"]));
        // From the built tree's own counts: every node (empty leaves
        // included) and T-reference an 8-byte word, every leaf reference 4
        // bytes.
        let n = |k: &str| b[k].as_u64().unwrap();
        let want = 8 * (n("nodes_total") + n("nodes_t_inner")) + 4 * n("refs");
        assert_eq!(i["paper_layout_bytes"], want, "{preset}");
        assert!(n("nodes_empty_leaf") > 0);
        let per_tri = i["paper_layout_bytes_per_triangle"].as_f64().unwrap();
        assert!((per_tri - want as f64 / 3674.0).abs() < 1e-9);
        // The stored tree (2-byte leaves) is smaller than the paper's.
        assert!(i["tree_bytes"].as_u64().unwrap() < want);
        let text = slimkd(&["info", kd.to_str().unwrap()]);
        let out = String::from_utf8_lossy(&text.stdout);
        assert!(
            out.contains("paper's std layout") && out.contains(&want.to_string()),
            "{out}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
