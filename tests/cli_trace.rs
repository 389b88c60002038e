//! `slimkd trace` end to end: a ray file through a `.kd` file, single and
//! packet, closest and any hit, against brute force; bad ray files are
//! errors naming the file and the record.

use glam::Vec3;
use slimkd::geom::Ray;
use slimkd::trace::{self, rays};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn slimkd(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_slimkd"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn json(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("one JSON object")
}

fn tmp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("slimkd-cli-trace-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn trace_matches_brute_force_in_every_mode() {
    let dir = tmp_dir("modes");
    let scene_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj");
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
    let o = b.center() + Vec3::new(0.0, 0.0, 3.0 * (b.max - b.min).length());
    // 700 rays: a partial last chunk and a partial last packet.
    let rays: Vec<Ray> = (0..700)
        .map(|i| {
            let target = b.min
                + (b.max - b.min) * Vec3::new((i % 28) as f32 / 28.0, (i / 28) as f32 / 25.0, 0.5);
            let mut r = Ray::new(o, target - o);
            // A hit exactly at tmax: closest hit, but not occluded.
            let t = trace::brute_force(&scene, &r).t;
            if i % 3 == 0 && t.is_finite() {
                r.tmax = t;
            }
            r
        })
        .collect();
    let ray_file = dir.join("test.rays");
    std::fs::write(&ray_file, rays::ray_bytes(&rays)).unwrap();
    let want: Vec<f32> = rays
        .iter()
        .map(|r| trace::brute_force(&scene, r).t)
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
    for mode in ["single", "packet"] {
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
    // A bad ray file: exit 1, the file and the record named.
    let mut bytes = rays::ray_bytes(&rays[..3]);
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
    let dir = tmp_dir("sah");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj");
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
        c["nodes"].as_u64().unwrap() < d["nodes"].as_u64().unwrap(),
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
