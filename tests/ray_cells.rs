//! `tools/ray_cells.py`, the build in cells on Ray, on a local Ray
//! instance: the file it writes is `build -o`'s, byte for byte, and a
//! rerun keeps the parts. Skipped, with a message, where `import ray`
//! fails. The Python is `$SLIMKD_PYTHON`, else the worktree's ignored
//! `.venv-ray` (`python3 -m venv .venv-ray && .venv-ray/bin/pip install
//! ray`), else `python3`.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

fn python() -> PathBuf {
    if let Some(p) = std::env::var_os("SLIMKD_PYTHON") {
        return p.into();
    }
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv-ray/bin/python");
    if venv.exists() {
        venv
    } else {
        "python3".into()
    }
}

fn ray_cells(py: &Path, scene: &Path, dir: &Path, out: &Path) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/ray_cells.py");
    let run = Command::new(py)
        .arg(script)
        .arg(scene)
        .args(["--cells", "8", "--num-cpus", "2", "--json", "--slimkd"])
        .arg(env!("CARGO_BIN_EXE_slimkd"))
        .arg("--cells-dir")
        .arg(dir)
        .arg("-o")
        .arg(out)
        .env("RAY_USAGE_STATS_ENABLED", "0")
        .output()
        .expect("python runs");
    json(&run)
}

#[test]
fn the_ray_driver_writes_the_file_of_build_o() {
    let py = python();
    let has_ray = Command::new(&py)
        .args(["-c", "import ray"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_ray {
        skip(&format!(
            "`import ray` fails with {} (pip install ray, or set SLIMKD_PYTHON)",
            py.display()
        ));
        return;
    }
    let dir = fresh_temp_dir("ray");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/nexuiz_dieselpower.obj");
    let mono = dir.join("mono.kd");
    let m = slimkd(&[
        "build",
        &scene.display().to_string(),
        "-q",
        "-o",
        &mono.display().to_string(),
    ]);
    assert!(m.status.success());
    let work = dir.join("work");
    let out = dir.join("ray.kd");
    let doc = ray_cells(&py, &scene, &work, &out);
    assert_eq!(doc["command"], "ray_cells");
    let cells = doc["cells"].as_u64().unwrap();
    assert!((2..=8).contains(&cells), "{cells} cells");
    assert_eq!(doc["built"], cells);
    assert!(std::fs::read(&out).unwrap() == std::fs::read(&mono).unwrap());
    // A rerun builds nothing: every part is kept.
    std::fs::remove_file(&out).unwrap();
    let again = ray_cells(&py, &scene, &work, &out);
    assert_eq!(again["built"], 0);
    assert!(std::fs::read(&out).unwrap() == std::fs::read(&mono).unwrap());
}
