//! What the command line and the report ([`crate::stats::report`]) share
//! on the way from a scene to a tree file: the median of timings, the
//! build parameters a `.kd` file records, and a tree's figures as JSON.

use crate::build::BuildConfig;
use crate::format::{FileConfig, Preset, TreeFigures};
use crate::slim::SlimParams;
use serde_json::{Value, json};

/// The median (the mean of the middle two for an even count; NaN for
/// none).
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

/// The build parameters a `.kd` file records: the SAH constants and depth
/// limit of `config` for `n_tris` triangles, the preset, and the slim
/// thresholds (zero without a slim pass).
pub fn file_config(
    config: &BuildConfig,
    n_tris: usize,
    preset: Preset,
    slim: Option<&SlimParams>,
) -> FileConfig {
    let (tau_occu, tau_freq, max_t2rn) = slim.map_or((0.0, 0.0, 0), |p| {
        (p.tau_occu as f32, p.tau_freq as f32, p.max_t2rn)
    });
    FileConfig {
        k_t: config.sah.k_t,
        k_i: config.sah.k_i,
        lambda_empty: config.sah.lambda_empty,
        depth_limit: config.sah.depth_limit(n_tris),
        preset,
        tau_occu,
        tau_freq,
        max_t2rn,
    }
}

/// A tree's figures (Table 3(a) and its bytes) as JSON, with the keys of
/// `slimkd build --json` and `info --json` (see README.md).
pub fn figures_json(f: &TreeFigures) -> Value {
    json!({
        "nodes_inner": f.inner,
        "nodes_t_inner": f.t_inner,
        "nodes_leaf": f.leaves,
        "nodes_total": f.nodes(),
        "idx32": f.idx32,
        "idx16": f.idx16,
        "tree_bytes": f.tree_bytes(),
        "geometry_bytes": f.geometry_bytes(),
    })
}

/// Adds the keys of the object `extra` to the object `into` (replacing
/// those it has); nothing if either is not an object.
pub fn merge_json(into: &mut Value, extra: Value) {
    if let (Some(a), Value::Object(b)) = (into.as_object_mut(), extra) {
        a.extend(b);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_even_and_none() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(&[]).is_nan());
    }
}
