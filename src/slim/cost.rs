//! The SAH cost of subtrees, for the price rule of [`SlimParams::cost_ratio`]:
//! `Σ_inner (K_T + K_I·[hoisted]) · SA(node) + Σ_leaf K_I · |leaf| · SA(leaf)`,
//! in absolute surface-area units (divide by `SA(root)` for the expected
//! work of a ray through the root). Sums run in pre-order, left child
//! first, in `f64`, so that the same tree always gives the same figure.
//!
//! [`SlimParams::cost_ratio`]: super::SlimParams::cost_ratio

use super::work::{Work, WorkNode};
use crate::build::sah::SahParams;
use crate::geom::Aabb;
use crate::tree::{Node, TreeIr};

/// What the cost of a subtree reads of a node, in either tree form (the
/// work tree's explicit children or pre-order's implicit left child).
enum CostNode {
    Inner {
        axis: u8,
        pos: f32,
        hoisted: bool,
        left: u32,
        right: u32,
    },
    Leaf {
        count: u32,
    },
}

/// The traversal-step and triangle-test costs a subtree is priced with.
#[derive(Clone, Copy, Debug)]
pub(super) struct CostModel {
    k_t: f64,
    k_i: f64,
}

impl CostModel {
    /// The costs of the std tree's SAH (not a coarsened rebuild's: the
    /// price compares what rays do, which the rebuild's `K_T` does not
    /// change).
    pub(super) fn new(sah: &SahParams) -> CostModel {
        CostModel {
            k_t: sah.k_t,
            k_i: sah.k_i,
        }
    }

    /// The cost of the subtree of work node `node`, whose cell is `cell`.
    pub(super) fn work_subtree(&self, work: &Work, node: u32, cell: Aabb) -> f64 {
        self.subtree(node, cell, |n| match work.nodes[n as usize] {
            WorkNode::Inner {
                axis,
                pos,
                left,
                right,
                t_ref,
            } => CostNode::Inner {
                axis,
                pos,
                hoisted: t_ref.is_some(),
                left,
                right,
            },
            WorkNode::Leaf { count, .. } => CostNode::Leaf { count },
        })
    }

    /// The cost of a pre-order subtree (a rebuild's nodes) over `cell`.
    pub(super) fn nodes(&self, nodes: &[Node], cell: Aabb) -> f64 {
        self.subtree(0, cell, |n| match nodes[n as usize] {
            Node::Inner {
                axis,
                pos,
                right,
                t_ref,
            } => CostNode::Inner {
                axis,
                pos,
                hoisted: t_ref.is_some(),
                left: n + 1,
                right: right.0,
            },
            Node::Leaf { count, .. } => CostNode::Leaf { count },
        })
    }

    /// The cost of the subtree of `root` over `cell`, for either tree form
    /// (`node` reads one node): summed in pre-order, left child first.
    fn subtree(&self, root: u32, cell: Aabb, node: impl Fn(u32) -> CostNode) -> f64 {
        let mut cost = 0.0;
        let mut stack = vec![(root, cell)];
        while let Some((n, cell)) = stack.pop() {
            match node(n) {
                CostNode::Inner {
                    axis,
                    pos,
                    hoisted,
                    left,
                    right,
                } => {
                    cost += self.inner(hoisted, &cell);
                    let (lc, rc) = cell.split(axis as usize, pos);
                    stack.push((right, rc));
                    stack.push((left, lc));
                }
                CostNode::Leaf { count } => cost += self.leaf(count, &cell),
            }
        }
        cost
    }

    /// The cost of a whole tree.
    pub(super) fn tree(&self, t: &TreeIr) -> f64 {
        self.nodes(&t.nodes, t.bounds)
    }

    /// A hoisted triangle at a node of cell `cell`: the test every ray
    /// that enters the cell makes.
    pub(super) fn hoisted(&self, cell: &Aabb) -> f64 {
        self.k_i * cell.surface_area()
    }

    pub(super) fn inner(&self, hoisted: bool, cell: &Aabb) -> f64 {
        let k = if hoisted {
            self.k_t + self.k_i
        } else {
            self.k_t
        };
        k * cell.surface_area()
    }

    pub(super) fn leaf(&self, count: u32, cell: &Aabb) -> f64 {
        self.k_i * f64::from(count) * cell.surface_area()
    }
}
