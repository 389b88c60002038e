//! The steps of one pass of the driver: the pending subtrees ([`Todo`])
//! with their shares of the progress, the top-down search for the highest
//! picks in each, and the rebuild of a pick's subtree without its triangle
//! with the decision (hoisted, cancelled, rejected or skipped).

use super::bytes::{ByteModel, min_subtree_bytes};
use super::cost::CostModel;
use super::oracle::{Analysis, analyze};
use super::prune::{PruneOf, Pruner};
use super::work::{Work, WorkNode};
use super::{Rebuild, SlimParams};
use crate::build::level::SubtreeBuilder;
use crate::geom::{Aabb, clip_triangle};
use crate::progress::Progress;
use crate::scene::TriangleColumns;
use crate::tree::{Node, TreeIr, TriId};
use std::sync::Arc;

/// A subtree to process: its root, node count (a contiguous pre-order
/// range of the work tree), cell, depth, the hoisted triangles on the path
/// above it, the analysis of an enclosing subtree if it still holds, and
/// its share of the progress ([`Progress::TOTAL`] for the whole tree).
#[derive(Clone)]
pub(super) struct Todo {
    pub(super) node: u32,
    pub(super) size: u32,
    pub(super) cell: Aabb,
    pub(super) depth: u32,
    pub(super) t2rn: u32,
    pub(super) analysis: Option<Arc<Analysis>>,
    pub(super) weight: u64,
}

impl Todo {
    /// The children of an inner node as subtrees to process. Each gets a
    /// share of this subtree's progress weight in proportion to its node
    /// count; the rest (this node's own share, and rounding) is done, and
    /// added to `progress`.
    pub(super) fn children(
        &self,
        work: &Work,
        t2rn: u32,
        analysis: Option<Arc<Analysis>>,
        progress: Option<&Progress>,
    ) -> [Todo; 2] {
        let WorkNode::Inner {
            axis,
            pos,
            left,
            right,
            ..
        } = work.nodes[self.node as usize]
        else {
            unreachable!("children() is called on inner nodes only");
        };
        let (lc, rc) = self.cell.split(axis as usize, pos);
        let size_l = right - left;
        let children =
            [(left, size_l, lc), (right, self.size - 1 - size_l, rc)].map(|(node, size, cell)| {
                Todo {
                    node,
                    size,
                    cell,
                    depth: self.depth + 1,
                    t2rn,
                    analysis: analysis.clone(),
                    weight: (u128::from(self.weight) * u128::from(size)
                        / u128::from(self.size.max(1))) as u64,
                }
            });
        Progress::add(
            progress,
            self.weight - children[0].weight - children[1].weight,
        );
        children
    }
}

/// A node where the oracle picked a triangle (`at.analysis` is the
/// analysis that picked it).
pub(super) struct Pick {
    pub(super) at: Todo,
    pub(super) tri: TriId,
}

/// Walks a subtree top-down and returns the highest nodes where a triangle
/// is picked (their subtrees are not walked further in this pass).
///
/// The progress weight of every node walked and not picked is done here;
/// the picks carry theirs on.
pub(super) fn find_picks(work: &Work, sub: Todo, inputs: &SlimInputs) -> Vec<Pick> {
    let mut picks = Vec::new();
    if sub.t2rn >= inputs.params.max_t2rn
        || !matches!(work.nodes[sub.node as usize], WorkNode::Inner { .. })
    {
        Progress::add(inputs.progress, sub.weight);
        return picks;
    }
    let analysis = match &sub.analysis {
        Some(a) => a.clone(),
        None => Arc::new(analyze(
            work,
            sub.node,
            sub.size,
            sub.cell,
            inputs.sa_root,
            inputs.params,
            inputs.scene.len(),
        )),
    };
    let mut stack = vec![sub];
    while let Some(mut at) = stack.pop() {
        if !matches!(work.nodes[at.node as usize], WorkNode::Inner { .. }) {
            Progress::add(inputs.progress, at.weight);
            continue;
        }
        if let Some(tri) = analysis.pick(at.node) {
            at.analysis = Some(analysis.clone());
            picks.push(Pick { at, tri });
            continue;
        }
        let [l, r] = at.children(work, at.t2rn, None, inputs.progress);
        stack.push(r);
        stack.push(l);
    }
    picks
}

/// What became of a pick.
pub(super) enum Outcome {
    Hoisted(TreeIr),
    Cancelled,
    Rejected,
    /// Smaller, but rejected by the price rule
    /// ([`SlimParams::cost_ratio`]): it costs rays more than its bytes
    /// are worth.
    Priced,
    /// Rejected without a rebuild: the subtree is too small for any
    /// rebuilt one to save bytes ([`min_subtree_bytes`]).
    Skipped,
}

/// The fixed inputs of a slim run, shared by every pick of every pass.
pub(super) struct SlimInputs<'a> {
    pub(super) scene: &'a TriangleColumns,
    pub(super) params: &'a SlimParams,
    pub(super) sa_root: f64,
    pub(super) bytes: Option<ByteModel>,
    /// The price rule: the cost model and the most SAH cost a byte saved
    /// may add (`cost_ratio · C_std / B_std`); `None` without one.
    pub(super) price: Option<(CostModel, f64)>,
    pub(super) progress: Option<&'a Progress>,
}

/// What a worker of the pass rebuilds with: the SAH finisher or the
/// pruner ([`SlimParams::rebuild`]), and scratch lists.
pub(super) struct Rebuilder<'a> {
    pub(super) builder: SubtreeBuilder<'a>,
    pub(super) pruner: Pruner,
    pub(super) tris: Vec<TriId>,
    pub(super) refs: Vec<(TriId, Aabb)>,
}

/// Rebuilds the subtree of a pick without its triangle and decides.
/// Returns the outcome and the work done: the triangles rebuilt (with
/// [`Rebuild::Sah`]) or the references of the pruned subtree (with
/// [`Rebuild::Prune`]).
pub(super) fn rebuild_pick(
    work: &Work,
    p: &Pick,
    inputs: &SlimInputs,
    rebuilder: &mut Rebuilder<'_>,
) -> (Outcome, usize) {
    let Rebuilder {
        builder,
        pruner,
        tris,
        refs,
    } = rebuilder;
    let (s, e) = work.tri_range(p.at.node, p.at.size);
    // The subtree's triangles but the pick's, ascending.
    let distinct = |tris: &mut Vec<TriId>| {
        tris.clear();
        tris.extend_from_slice(&work.tris[s..e]);
        tris.sort_unstable();
        tris.dedup();
        tris.retain(|&t| t != p.tri);
    };
    if inputs.params.rebuild == Rebuild::Prune {
        let of = PruneOf {
            work,
            t: p.tri,
            bytes: inputs.bytes.as_ref(),
            cost: inputs.price.as_ref().map(|(model, _)| model),
        };
        let pruned = pruner.prune(&of, p.at.node, p.at.cell, p.at.depth);
        let old = inputs.bytes.as_ref().map(|_| pruned.old_bytes);
        // The skip test `old <= 8 + min_subtree_bytes(tris.len())`, taken
        // after the prune (its walk counts `old`) so that a pick is
        // reported as with a rebuild: a pruned subtree holds each of
        // `tris`, no more (no clipping). The subtree's references bound
        // `tris.len()`, so the sort is needed only where they do not
        // decide it.
        let skip = match old {
            None => false,
            Some(old) if old > 8 + min_subtree_bytes(e - s) => false,
            Some(old) => {
                distinct(tris);
                old <= 8 + min_subtree_bytes(tris.len())
            }
        };
        if skip {
            return (Outcome::Skipped, 0);
        }
        let new = old.map(|_| pruned.new_bytes + 8);
        let outcome = decide(
            work,
            p,
            inputs,
            (old, new),
            of.cost.map(|_| pruned.old_cost),
            pruned.nodes,
            pruned.tris,
        );
        return (outcome, pruned.tris.len());
    }
    let old = inputs
        .bytes
        .as_ref()
        .map(|m| m.subtree(work, p.at.node, p.at.size));
    distinct(tris);
    refs.clear();
    let mut clipped = false;
    let mut clip_all = |refs: &mut Vec<(TriId, Aabb)>| {
        if !clipped {
            clipped = true;
            refs.extend(tris.iter().filter_map(|&t| {
                clip_triangle(&inputs.scene.tri(t.0), &p.at.cell).map(|bounds| (t, bounds))
            }));
        }
    };
    // The skip test `old <= 8 + min_subtree_bytes(refs.len())`, clipping
    // only when `0 <= refs.len() <= tris.len()` does not decide it.
    let skip = match old {
        None => false,
        Some(old) if old > 8 + min_subtree_bytes(tris.len()) => false,
        Some(old) if old <= 8 + min_subtree_bytes(0) => true,
        Some(old) => {
            clip_all(refs);
            old <= 8 + min_subtree_bytes(refs.len())
        }
    };
    if skip {
        return (Outcome::Skipped, tris.len());
    }
    clip_all(refs);
    // The byte rule rejects the hoist once the rebuilt subtree takes
    // `old - 8` bytes, so the build stops as soon as a lower bound of its
    // bytes reaches that (it stops at a split, so the root is inner and the
    // hoist is not cancelled). What is built is decided on the builder's
    // own slices: only a kept subtree is copied out (two in three rebuilds
    // are cancelled or rejected).
    let limit = old.map_or(u64::MAX, |old| old.saturating_sub(8));
    let Some((nodes, leaf_tris)) =
        builder.build(refs.iter().copied(), p.at.cell, p.at.depth, limit)
    else {
        return (Outcome::Rejected, tris.len());
    };
    let new = inputs.bytes.as_ref().map(|m| m.nodes(nodes, leaf_tris) + 8);
    let outcome = decide(work, p, inputs, (old, new), None, nodes, leaf_tris);
    (outcome, tris.len())
}

/// The outcome of a pick whose subtree (`old` bytes, SAH cost `old_cost`
/// if known) is remade as `nodes` and `leaf_tris` (`new` bytes with the
/// hoisted triangle's word).
fn decide(
    work: &Work,
    p: &Pick,
    inputs: &SlimInputs,
    (old, new): (Option<u64>, Option<u64>),
    old_cost: Option<f64>,
    nodes: &[Node],
    leaf_tris: &[TriId],
) -> Outcome {
    if matches!(nodes[0], Node::Leaf { .. }) {
        Outcome::Cancelled
    } else if let (Some(new), Some(old)) = (new, old)
        && new >= old
    {
        Outcome::Rejected
    } else if let (Some((model, per_byte)), Some(new), Some(old)) = (&inputs.price, new, old)
        && model.nodes(nodes, p.at.cell) + model.hoisted(&p.at.cell)
            - old_cost.unwrap_or_else(|| model.work_subtree(work, p.at.node, p.at.cell))
            > per_byte * (old - new) as f64
    {
        Outcome::Priced
    } else {
        Outcome::Hoisted(TreeIr {
            bounds: p.at.cell,
            nodes: nodes.to_vec(),
            leaf_tris: leaf_tris.to_vec(),
        })
    }
}
