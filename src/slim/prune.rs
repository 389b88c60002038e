//! [`Rebuild::Prune`](super::Rebuild::Prune): a pick's subtree without
//! its triangle made from the subtree itself, its splits kept. The
//! triangle leaves every leaf; then, bottom-up, an inner node whose two
//! children are leaves becomes one leaf (their triangles' union) where
//! the rebuild's leaf rule ([`joins`]) prefers a leaf to the kept split.
//!
//! Why: the SAH rebuild of every pick is what makes the slim build cost
//! 2.7–4.5× the std build on the shared scenes; pruning is linear in the
//! subtree, and the slim build takes 1.5–2.1× for 1–7 points less of the
//! bytes saved (`docs/perf-notes.md`, "Hoists that keep the splits").

use super::work::{Work, WorkNode};
use crate::build::sah::{self, LeafRule, PlaneCounts, SahParams};
use crate::geom::Aabb;
use crate::tree::{Node, NodeId, TriId};

/// Whether an inner node of `cell` at `depth`, split at `axis = pos` into
/// two leaves of `left` and `right` triangles whose union has `union`,
/// becomes one leaf: when the split's SAH cost (`sah`, the rebuild's
/// `K_T`) is at least the leaf's, or when it does not pay its bytes (the
/// split price, `rule`), as the builders' own leaf rule decides; the
/// triangles in both leaves are the split's straddlers. A cell without
/// surface area keeps its split.
#[doc(hidden)] // the literal pass of tests/slim.rs decides with it too
#[allow(clippy::too_many_arguments)]
pub fn joins(
    sah: &SahParams,
    rule: &LeafRule,
    cell: &Aabb,
    depth: u32,
    axis: u8,
    pos: f32,
    left: usize,
    right: usize,
    union: usize,
) -> bool {
    let sa = cell.surface_area();
    if sa.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return false;
    }
    let split = sah::split_cost(
        sah,
        cell,
        sa,
        axis as usize,
        pos,
        PlaneCounts {
            left,
            right,
            planar: 0,
        },
    );
    sah::is_leaf(sah, Some(&split), union, depth, rule, cell, |_| {
        left + right - union
    })
}

/// Prunes subtrees of the work tree (one per rayon worker: it keeps the
/// last pruned subtree and a scratch list).
pub(super) struct Pruner {
    sah: SahParams,
    rule: LeafRule,
    nodes: Vec<Node>,
    tris: Vec<TriId>,
    union: Vec<TriId>,
}

impl Pruner {
    /// A pruner deciding with the rebuild's SAH (`sah`, its price scale
    /// set) and leaf rule.
    pub(super) fn new(sah: SahParams, rule: LeafRule) -> Pruner {
        Pruner {
            sah,
            rule,
            nodes: Vec::new(),
            tris: Vec::new(),
            union: Vec::new(),
        }
    }

    /// The pruned subtree of work node `node` (cell `cell`, depth `depth`)
    /// without `t`: its nodes in pre-order and its leaves' triangles.
    pub(super) fn prune(
        &mut self,
        work: &Work,
        node: u32,
        cell: Aabb,
        depth: u32,
        t: TriId,
    ) -> (&[Node], &[TriId]) {
        self.nodes.clear();
        self.tris.clear();
        self.append(work, node, cell, depth, t);
        (&self.nodes, &self.tris)
    }

    /// Appends the pruned subtree of `node` to `self.nodes` and
    /// `self.tris`.
    fn append(&mut self, work: &Work, node: u32, cell: Aabb, depth: u32, t: TriId) {
        match work.nodes[node as usize] {
            WorkNode::Leaf { start, count } => {
                let tris = &mut self.tris;
                let s = tris.len();
                tris.extend(work.leaf(start, count).iter().filter(|&&u| u != t));
                self.nodes.push(Node::Leaf {
                    start: s as u32,
                    count: (tris.len() - s) as u32,
                });
            }
            WorkNode::Inner {
                axis,
                pos,
                left,
                right,
                t_ref,
            } => {
                let me = self.nodes.len();
                self.nodes.push(Node::Inner {
                    axis,
                    pos,
                    right: NodeId(u32::MAX),
                    t_ref,
                });
                let (lc, rc) = cell.split(axis as usize, pos);
                self.append(work, left, lc, depth + 1, t);
                let r = self.nodes.len();
                self.append(work, right, rc, depth + 1, t);
                let (nodes, tris) = (&mut self.nodes, &mut self.tris);
                if t_ref.is_none()
                    && let [
                        Node::Leaf {
                            start: ls,
                            count: nl,
                        },
                        Node::Leaf {
                            start: rs,
                            count: nr,
                        },
                    ] = nodes[me + 1..]
                {
                    let u = &mut self.union;
                    u.clear();
                    u.extend_from_slice(&tris[ls as usize..(rs + nr) as usize]);
                    u.sort_unstable();
                    u.dedup();
                    let (nl, nr) = (nl as usize, nr as usize);
                    if joins(
                        &self.sah,
                        &self.rule,
                        &cell,
                        depth,
                        axis,
                        pos,
                        nl,
                        nr,
                        u.len(),
                    ) {
                        tris.truncate(ls as usize);
                        tris.extend_from_slice(u);
                        nodes.truncate(me);
                        nodes.push(Node::Leaf {
                            start: ls,
                            count: u.len() as u32,
                        });
                        return;
                    }
                }
                if let Node::Inner { right, .. } = &mut nodes[me] {
                    *right = NodeId(r as u32);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// The unit cube split at x = 0.5 into leaves of `left` and `right`
    /// triangles with `union` distinct, under `K_T` × `coarsen` and no
    /// split price.
    fn unit_cube_joins(coarsen: f64, left: usize, right: usize, union: usize) -> bool {
        let sah = SahParams {
            k_t: SahParams::default().k_t * coarsen,
            split_price: 0.0,
            ..SahParams::default()
        };
        let cell = Aabb {
            min: Vec3::ZERO,
            max: Vec3::ONE,
        };
        let rule = sah.leaf_rule(1000, || cell);
        joins(&sah, &rule, &cell, 3, 0, 0.5, left, right, union)
    }

    #[test]
    fn leaves_join_where_the_split_does_not_pay() {
        // Each half has 4/6 of the cube's area: the split of 10 and 10
        // disjoint triangles costs K_T + K_I·(4/6·20) = 15 + 266.7 against
        // a leaf's 20·20 = 400, and at 10 × K_T 416.7.
        assert!(!unit_cube_joins(1.0, 10, 10, 20));
        assert!(unit_cube_joins(10.0, 10, 10, 20));
        // Two empty leaves, and two leaves of the same triangles, always.
        assert!(unit_cube_joins(1.0, 0, 0, 0));
        assert!(unit_cube_joins(1.0, 3, 3, 3));
        // A cell without area keeps its split.
        let sah = SahParams::default();
        let flat = Aabb {
            min: Vec3::ZERO,
            max: Vec3::new(1.0, 0.0, 0.0),
        };
        let rule = sah.leaf_rule(1000, || flat);
        assert!(!joins(&sah, &rule, &flat, 3, 0, 0.5, 0, 0, 0));
    }
}
