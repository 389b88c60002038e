//! What the command line and the lab share: the version of their JSON,
//! a tree's figures as JSON, and the median of timings.

use serde::Serialize;
use slimkd::format::TreeFigures;
use slimkd::stats::TreeStats;

/// The version of the JSON that `--json` prints and the report writes
/// (the `schema` key; docs/json-schema.md). It changes when a key changes
/// meaning or goes away, not when one is added.
pub const JSON_SCHEMA: u32 = 1;

/// A tree's node counts as the paper's Table 3(a) counts them, with the
/// same keys wherever they appear (`build`, `render`, `info`, `verify`, the
/// main job and the report).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct NodeCounts {
    /// Inner, t-inner and leaf nodes (T-references are not nodes).
    pub nodes_total: u64,
    /// Inner nodes without a hoisted triangle (type I).
    pub nodes_inner: u64,
    /// Inner nodes holding a hoisted triangle (type II).
    pub nodes_t_inner: u64,
    /// Leaves, empty ones included.
    pub nodes_leaf: u64,
}

impl NodeCounts {
    pub(crate) fn of_figures(f: &TreeFigures) -> NodeCounts {
        NodeCounts {
            nodes_total: f.nodes(),
            nodes_inner: f.inner,
            nodes_t_inner: f.t_inner,
            nodes_leaf: f.leaves,
        }
    }

    pub fn of_stats(s: &TreeStats) -> NodeCounts {
        NodeCounts {
            nodes_total: s.nodes as u64,
            nodes_inner: s.inner as u64,
            nodes_t_inner: s.t_inner as u64,
            nodes_leaf: s.leaves as u64,
        }
    }
}

/// What a stored tree takes: its leaf indices and bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct StorageJson {
    /// 4-byte leaf index entries.
    pub idx32: u64,
    /// 2-byte leaf index entries.
    pub idx16: u64,
    /// Bytes of the node words and leaf indices.
    pub tree_bytes: u64,
    /// Bytes of the vertices and triangles (and the triangle map).
    pub geometry_bytes: u64,
}

/// A stored tree's figures: [`NodeCounts`] and [`StorageJson`] in one
/// object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct FiguresJson {
    #[serde(flatten)]
    pub nodes: NodeCounts,
    #[serde(flatten)]
    pub storage: StorageJson,
}

impl FiguresJson {
    pub fn of(f: &TreeFigures) -> FiguresJson {
        FiguresJson {
            nodes: NodeCounts::of_figures(f),
            storage: StorageJson {
                idx32: f.idx32,
                idx16: f.idx16,
                tree_bytes: f.tree_bytes(),
                geometry_bytes: f.geometry_bytes(),
            },
        }
    }
}

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
