//! Helpers shared by the `build` and `trace` benches: command-line flags,
//! medians, scene paths and timed scene loading.

use slimkd::scene::{self, LoadSummary, TriangleColumns};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The file name of the optional large scene looked up in `SLIMKD_SCENES`.
pub const BIG_SCENE: &str = "stk_black_forest.obj";

/// Whether `--quick` was passed; every other argument (cargo passes
/// `--bench`) is ignored.
pub fn quick() -> bool {
    std::env::args().skip(1).any(|a| a == "--quick")
}

/// The median of some timings, as the CLI and the report take it (the
/// mean of the middle two for an even count; NaN for none).
pub fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => f64::NAN,
        _ if n % 2 == 1 => v[n / 2],
        _ => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    }
}

/// A path relative to the crate root.
pub fn crate_path(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

/// The large scene, when `SLIMKD_SCENES` names a directory holding it. A
/// note says why it is skipped when the variable is set but the file is
/// missing.
pub fn big_scene() -> Option<PathBuf> {
    let dir = std::env::var_os("SLIMKD_SCENES")?;
    let dir = PathBuf::from(dir);
    // A literal `~/` (the shell did not expand it) means the home directory.
    let dir = match (dir.strip_prefix("~"), std::env::var_os("HOME")) {
        (Ok(rest), Some(home)) => PathBuf::from(home).join(rest),
        _ => dir,
    };
    let path = dir.join(BIG_SCENE);
    if path.is_file() {
        Some(path)
    } else {
        println!(
            "note: SLIMKD_SCENES is set but {} does not exist; skipping it",
            path.display()
        );
        None
    }
}

/// A loaded scene and the seconds the load took.
pub struct Loaded {
    pub name: String,
    pub scene: TriangleColumns,
    pub summary: LoadSummary,
    pub seconds: f64,
}

/// Loads an OBJ file, timing the load; a failed load ends the bench.
pub fn load(path: &Path) -> Loaded {
    let start = Instant::now();
    let (scene, summary) =
        scene::load_obj(path).unwrap_or_else(|e| panic!("cannot load the scene: {e}"));
    let seconds = start.elapsed().as_secs_f64();
    let name = path
        .file_stem()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    Loaded {
        name,
        scene,
        summary,
        seconds,
    }
}
