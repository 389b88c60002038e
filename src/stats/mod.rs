//! Figures about a tree: node, leaf and reference counts, depths, the SAH
//! cost, and the leaf-depth histogram (the figures of Choi et al. 2013,
//! Table 3 and Figure 6, for the standard tree).

pub mod bytes;
#[doc(hidden)] // the `slimkd calibrate` command
pub mod calibrate;
pub(crate) mod plot;
#[doc(hidden)] // the `slimkd report` driver
pub mod report;

use crate::build::sah::SahParams;
use crate::tree::{Node, TreeIr};

/// Summary figures of one tree.
#[derive(Clone, Debug, PartialEq)]
pub struct TreeStats {
    /// All nodes.
    pub nodes: usize,
    /// Inner nodes without a hoisted triangle (type I).
    pub inner: usize,
    /// Inner nodes holding a hoisted triangle (type II, "t-inner").
    pub t_inner: usize,
    /// Leaves, empty ones included.
    pub leaves: usize,
    /// Leaves with no triangle.
    pub empty_leaves: usize,
    /// Triangle references in leaves (`leaf_tris.len()`).
    pub refs: usize,
    /// The deepest leaf's depth (root = 0).
    pub max_depth: u32,
    /// Mean depth of the non-empty leaves.
    pub mean_leaf_depth: f64,
    /// `leaf_depths[d]` = number of leaves at depth `d`.
    pub leaf_depths: Vec<u64>,
    /// The SAH cost of the whole tree: `Σ_inner K_T·SA(n)/SA(root) +
    /// Σ_leaf K_I·N(n)·SA(n)/SA(root)`.
    pub sah_cost: f64,
}

impl TreeStats {
    /// The figures of `tree`, its SAH cost priced with `params`.
    pub fn of(tree: &TreeIr, params: &SahParams) -> TreeStats {
        let sa_root = tree.bounds.surface_area();
        let mut s = TreeStats {
            nodes: tree.nodes.len(),
            inner: 0,
            t_inner: 0,
            leaves: 0,
            empty_leaves: 0,
            refs: tree.leaf_tris.len(),
            max_depth: 0,
            mean_leaf_depth: 0.0,
            leaf_depths: Vec::new(),
            sah_cost: 0.0,
        };
        let mut depth_sum = 0u64;
        tree.walk(|_, node, cell, depth| {
            let p = if sa_root > 0.0 {
                cell.surface_area() / sa_root
            } else {
                1.0
            };
            s.max_depth = s.max_depth.max(depth);
            match *node {
                Node::Inner { t_ref, .. } => {
                    if t_ref.is_some() {
                        s.t_inner += 1;
                    } else {
                        s.inner += 1;
                    }
                    s.sah_cost += params.k_t * p;
                }
                Node::Leaf { count, .. } => {
                    s.leaves += 1;
                    if count == 0 {
                        s.empty_leaves += 1;
                    } else {
                        depth_sum += u64::from(depth);
                    }
                    if s.leaf_depths.len() <= depth as usize {
                        s.leaf_depths.resize(depth as usize + 1, 0);
                    }
                    s.leaf_depths[depth as usize] += 1;
                    s.sah_cost += params.k_i * f64::from(count) * p;
                }
            }
        });
        let full = s.leaves - s.empty_leaves;
        s.mean_leaf_depth = if full > 0 {
            depth_sum as f64 / full as f64
        } else {
            0.0
        };
        s
    }
}
