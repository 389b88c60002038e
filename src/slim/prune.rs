//! [`Rebuild::Prune`](super::Rebuild::Prune): a pick's subtree without
//! its triangle made from the subtree itself, its splits kept. The
//! triangle leaves every leaf; then, bottom-up, an inner node whose two
//! children are leaves becomes one leaf (their triangles' union) where
//! the rebuild's leaf rule ([`joins`]) prefers a leaf to the kept split.
//!
//! Why: the SAH rebuild of every pick is what makes the slim build cost
//! 2.7–4.5× the std build on the shared scenes; pruning is linear in the
//! subtree, and the slim build takes 1.35–1.85× for 1–7 points less of
//! the bytes saved (`docs/perf-notes.md`, "Hoists that keep the splits").

use super::bytes::ByteModel;
use super::cost::CostModel;
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

/// What a prune reads besides the node: the work tree, the triangle
/// taken out, and the models whose figures the walk sums.
pub(super) struct PruneOf<'a> {
    pub(super) work: &'a Work,
    pub(super) t: TriId,
    pub(super) bytes: Option<&'a ByteModel>,
    pub(super) cost: Option<&'a CostModel>,
}

/// A pruned subtree (its nodes in pre-order and its leaves' triangles)
/// with the figures the hoist rules compare, summed in the same walk:
/// the bytes of the subtree it replaces and its own
/// ([`ByteModel::subtree`] and [`ByteModel::nodes`]; 0 without a byte
/// model), and the replaced subtree's SAH cost, added in the pre-order of
/// [`CostModel::work_subtree`] and so equal to it bit for bit (0 without a
/// cost model).
pub(super) struct Pruned<'a> {
    pub(super) nodes: &'a [Node],
    pub(super) tris: &'a [TriId],
    pub(super) old_bytes: u64,
    pub(super) new_bytes: u64,
    pub(super) old_cost: f64,
}

/// Prunes subtrees of the work tree (one per rayon worker: it keeps the
/// last pruned subtree and a scratch list).
pub(super) struct Pruner {
    sah: SahParams,
    rule: LeafRule,
    nodes: Vec<Node>,
    tris: Vec<TriId>,
    union: Vec<TriId>,
    old_bytes: u64,
    new_bytes: u64,
    old_cost: f64,
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
            old_bytes: 0,
            new_bytes: 0,
            old_cost: 0.0,
        }
    }

    /// The pruned subtree of work node `node` (cell `cell`, depth `depth`)
    /// without `of.t`.
    pub(super) fn prune(
        &mut self,
        of: &PruneOf<'_>,
        node: u32,
        cell: Aabb,
        depth: u32,
    ) -> Pruned<'_> {
        self.nodes.clear();
        self.tris.clear();
        (self.old_bytes, self.new_bytes, self.old_cost) = (0, 0, 0.0);
        self.append(of, node, cell, depth);
        if let (Some(m), [Node::Leaf { count: 0, .. }, ..]) = (of.bytes, &self.nodes[..]) {
            self.new_bytes += m.empty_root();
        }
        Pruned {
            nodes: &self.nodes,
            tris: &self.tris,
            old_bytes: self.old_bytes,
            new_bytes: self.new_bytes,
            old_cost: self.old_cost,
        }
    }

    /// Appends the pruned subtree of `node` to `self.nodes` and
    /// `self.tris`, and its figures to the sums.
    fn append(&mut self, of: &PruneOf<'_>, node: u32, cell: Aabb, depth: u32) {
        let work = of.work;
        match work.nodes[node as usize] {
            WorkNode::Leaf { start, count } => {
                let old = work.leaf(start, count);
                let tris = &mut self.tris;
                let s = tris.len();
                tris.extend(old.iter().filter(|&&u| u != of.t));
                if let Some(m) = of.bytes {
                    self.old_bytes += m.leaf(old);
                    self.new_bytes += m.leaf(&tris[s..]);
                }
                if let Some(c) = of.cost {
                    self.old_cost += c.leaf(count, &cell);
                }
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
                if let Some(m) = of.bytes {
                    let empty =
                        |n: u32| matches!(work.nodes[n as usize], WorkNode::Leaf { count: 0, .. });
                    self.old_bytes += m.inner(t_ref.is_some(), empty(left) && empty(right));
                }
                if let Some(c) = of.cost {
                    self.old_cost += c.inner(t_ref.is_some(), &cell);
                }
                let me = self.nodes.len();
                self.nodes.push(Node::Inner {
                    axis,
                    pos,
                    right: NodeId(u32::MAX),
                    t_ref,
                });
                let (lc, rc) = cell.split(axis as usize, pos);
                self.append(of, left, lc, depth + 1);
                let r = self.nodes.len();
                self.append(of, right, rc, depth + 1);
                let (nodes, tris) = (&mut self.nodes, &mut self.tris);
                let children = match nodes[me + 1..] {
                    [
                        Node::Leaf {
                            start: ls,
                            count: nl,
                        },
                        Node::Leaf {
                            start: rs,
                            count: nr,
                        },
                    ] => Some((ls, nl, rs, nr)),
                    _ => None,
                };
                if t_ref.is_none()
                    && let Some((ls, nl, rs, nr)) = children
                {
                    let u = &mut self.union;
                    u.clear();
                    u.extend_from_slice(&tris[ls as usize..(rs + nr) as usize]);
                    u.sort_unstable();
                    u.dedup();
                    if joins(
                        &self.sah,
                        &self.rule,
                        &cell,
                        depth,
                        axis,
                        pos,
                        nl as usize,
                        nr as usize,
                        u.len(),
                    ) {
                        if let Some(m) = of.bytes {
                            // The two leaves' bytes, counted, become the
                            // joined leaf's.
                            self.new_bytes -= m.leaf(&tris[ls as usize..rs as usize])
                                + m.leaf(&tris[rs as usize..(rs + nr) as usize]);
                            self.new_bytes += m.leaf(u);
                        }
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
                if let Some(m) = of.bytes {
                    let both_empty = matches!(children, Some((_, 0, _, 0)));
                    self.new_bytes += m.inner(t_ref.is_some(), both_empty);
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
    fn the_walk_sums_what_the_models_count() {
        // Every inner node of the std trees of two scenes, pruned of each
        // triangle under it (joins at twice K_T, which joins often): the
        // walk's bytes and cost are those of the models' own walks, the
        // cost bit for bit.
        use crate::build::{self, Algorithm, BuildConfig};
        use crate::scene::TriangleColumns;
        let mut tris = crate::scene::slanted_grid(6);
        tris.push([
            Vec3::new(-1.0, 0.5, -1.0),
            Vec3::new(13.0, 0.5, -1.0),
            Vec3::new(-1.0, 0.5, 13.0),
        ]);
        for scene in [
            super::super::huge_over_grid(),
            TriangleColumns::from_triangles(&tris).unwrap(),
        ] {
            let config = BuildConfig::default();
            let tree = build::build(&scene, &config, Algorithm::WaldHavran, None).unwrap();
            let mut work = Work {
                nodes: Vec::new(),
                tris: Vec::new(),
            };
            let root = work.append_all(vec![&tree])[0];
            let mut sah = config.sah;
            sah.k_t *= 2.0;
            sah.price_scale = Some(sah::price_scale(&tree.bounds, scene.len()));
            let mut pruner = Pruner::new(sah, sah.leaf_rule(scene.len(), || tree.bounds));
            let bytes = ByteModel::new(&scene, true);
            let cost = CostModel::new(&config.sah);
            let (mut checked, mut joined) = (0, 0);
            // (node, size, cell, depth)
            let mut stack = vec![(root, tree.nodes.len() as u32, tree.bounds, 0)];
            while let Some((node, size, cell, depth)) = stack.pop() {
                let WorkNode::Inner {
                    axis,
                    pos,
                    left,
                    right,
                    ..
                } = work.nodes[node as usize]
                else {
                    continue;
                };
                let (lc, rc) = cell.split(axis as usize, pos);
                stack.push((left, right - left, lc, depth + 1));
                stack.push((right, size - 1 - (right - left), rc, depth + 1));
                let (s, e) = work.tri_range(node, size);
                let mut under = work.tris[s..e].to_vec();
                under.sort_unstable();
                under.dedup();
                for &t in &under {
                    let of = PruneOf {
                        work: &work,
                        t,
                        bytes: Some(&bytes),
                        cost: Some(&cost),
                    };
                    let p = pruner.prune(&of, node, cell, depth);
                    assert_eq!(p.old_bytes, bytes.subtree(&work, node, size));
                    assert_eq!(p.new_bytes, bytes.nodes(p.nodes, p.tris));
                    assert_eq!(
                        p.old_cost.to_bits(),
                        cost.work_subtree(&work, node, cell).to_bits()
                    );
                    checked += 1;
                    joined += usize::from(p.nodes.len() + 1 < size as usize);
                }
            }
            assert!(
                checked > 100 && joined > 10,
                "{checked} prunes, {joined} joined"
            );
        }
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
