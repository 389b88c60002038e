//! The space-efficient ("slim") kd-tree of Choi, Chang & Ihm (2013):
//! triangles that are duplicated into many leaves of a subtree are hoisted
//! into the subtree's root, and the subtree is rebuilt without them.
//!
//! Consumes a standard [`TreeIr`] (from any builder) and produces a
//! `TreeIr` whose inner nodes may hold one triangle (`t_ref`, a "type II"
//! node). Traversers test that triangle whenever they visit the node, so the
//! slim tree returns exactly the hits of the standard tree.
//!
//! **Measures** (§4.1). For a subtree `T_I` with leaves `L`:
//! `f_occu(t) = Σ SA(l ∈ L holding t) / Σ SA(l ∈ L)` and
//! `f_freq(t) = |{l ∈ L holding t}| / |L|` (empty leaves count).
//!
//! **Oracle.** `pick_triangle(T_I)`: among the triangles with
//! `f_occu > τ_occu`, in non-increasing occupancy order (ties: smaller id
//! first), the first with `f_freq > τ_freq`; or none.
//!
//! **Algorithm 1** (run in parallel passes, see [`slim`]). From the root of
//! the standard tree, with an explicit stack: if a triangle `t` is picked
//! at inner node `I`, the subtree is rebuilt from its triangles minus `t`
//! (the SAH builder inside `I`'s cell at `I`'s depth, see [`rebuild`]) and
//! `t` is stored at `I`; the new subtree's children are skipped once the
//! hoisted triangles on the path from `I` to the root number `max_t2rn`;
//! otherwise the non-leaf children are pushed. Leaves are never given a
//! triangle.
//!
//! *Deviation from the paper (always):* when the rebuilt subtree would be a
//! single leaf (the SAH prefers not to split the remaining triangles), the
//! hoist is *cancelled* and `I` keeps its original subtree, since a leaf
//! cannot hold a hoisted triangle in the file format.
//!
//! *Deviation from the paper ([`HoistRule::Bytes`], the rule of the `fast`
//! and `small` presets):* a hoist is kept only if it makes the tree
//! smaller. The rebuilt subtree plus the hoisted triangle's T-reference
//! word must take fewer bytes than the subtree it replaces, counted as the
//! file stores them (see [`HoistRule::Bytes`]); otherwise the hoist is
//! *rejected*: `I` keeps its original subtree and the algorithm goes on
//! with `I`'s children as if no triangle had been picked (as for a
//! cancelled hoist). Why: in the `.kd` format a node is 8 bytes and a
//! leaf index 2 (with 2-byte leaves), so a hoist pays an 8-byte word to
//! save a few indices, and the rebuilt subtree often has more nodes; with
//! the paper's rule the `fast` and `small` trees of the shared scenes came
//! out up to 7% *larger* than the standard tree. [`HoistRule::Paper`]
//! gives the paper's literal behaviour.
//!
//! **Exact arithmetic.** Leaf surface areas enter the occupancy as integers
//! (`SA(leaf)/SA(root)` in units of 2⁻⁴⁰), so sums are exact and
//! independent of summation order; the fast implementation here and the
//! literal one in the tests therefore make identical decisions.
//!
//! **Speed** (what makes this faster than the literal algorithm, with the
//! same result).
//! - *Bottom-up candidates.* A triangle frequent in `I` is frequent in one
//!   of `I`'s children (a weighted average exceeds τ only if one of its
//!   terms does), so each node's candidates are the frequent triangles of
//!   its children, merged bottom-up with their counts and occupancies
//!   (which add up). A triangle frequent in one child only is counted in
//!   the other child's leaves from the subtree's (triangle, leaf) pairs,
//!   sorted once, with prefix sums of their leaf weights (two binary
//!   searches), and only if it could still be frequent; leaves are never
//!   rescanned. One analysis gives the pick of every node of a subtree;
//!   it is computed in parallel over subtrees for large trees.
//! - *Skips.* Under the byte rule, a pick whose subtree takes at most 8
//!   bytes more than the least any rebuilt subtree of its references could
//!   take ([`min_subtree_bytes`]) is rejected without a rebuild; it could
//!   not pass the rule.
//! - *Passes.* Each pass finds, in every pending subtree, the highest nodes
//!   where a triangle is picked, rebuilds those (disjoint) subtrees in
//!   parallel, and queues their children. A node's pick depends only on
//!   its own subtree, so the order does not change the tree. Below a
//!   cancelled or rejected hoist the subtree is unchanged, so its analysis
//!   is reused.
//! - *Rebuilds* use the level builder's depth-first finisher
//!   ([`SubtreeBuilder`], no allocation per node), which builds the same
//!   subtree as the sweep builder of [`rebuild`].
//! - *Flat work tree.* Every subtree that is analysed or rebuilt is a
//!   contiguous pre-order range of nodes (and of leaf triangles) of the
//!   work tree, because rebuilt subtrees are appended whole and only the
//!   children of hoisting nodes are redirected.

use crate::build::level::SubtreeBuilder;
use crate::build::{BuildConfig, TriRef, sweep};
use crate::format::node::leaf_index_bytes;
use crate::geom::{Aabb, clip_triangle};
use crate::progress::Progress;
use crate::scene::TriangleColumns;
use crate::sys::lap;
use crate::tree::{Node, NodeId, TreeIr, TriId};
use rayon::prelude::*;
use std::borrow::Borrow;
use std::sync::Arc;
use std::time::Instant;

/// Whether a picked triangle is hoisted (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HoistRule {
    /// The paper's Algorithm 1: every picked triangle is hoisted (unless
    /// the rebuilt subtree is a single leaf).
    Paper,
    /// A hoist is kept only if `bytes(rebuilt subtree) + 8 <
    /// bytes(replaced subtree)`, where a subtree's bytes are counted as the
    /// file stores them (the paper's tree memory,
    /// `8·(nodes + T-references) + 4·|idx32| + 2·|idx16|`): 8 per node, 8
    /// more per hoisted triangle, and per leaf 2 bytes per index if the
    /// leaf fits 2-byte mode, else 4 ([`leaf_index_bytes`]). Whether a leaf
    /// fits depends on the triangle ids in the file: with `reordered` they
    /// are the Morton ranks the writer gives with reordering
    /// ([`TriangleColumns::morton_order`]), else the input ids. The count
    /// is exact for a file written that way. The decision is greedy: it
    /// compares the two subtrees as they are when `I` is visited, before
    /// anything below is hoisted.
    Bytes { reordered: bool },
}

/// The thresholds of the oracle, the hoisting limit and the hoist rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlimParams {
    pub tau_occu: f64,
    pub tau_freq: f64,
    /// Most hoisted triangles on any root path.
    pub max_t2rn: u32,
    pub rule: HoistRule,
}

impl SlimParams {
    /// The `fast` preset: the paper's thresholds, with the byte rule for a
    /// reordered file.
    pub const FAST: SlimParams = SlimParams {
        tau_occu: 0.9,
        tau_freq: 0.7,
        max_t2rn: 4,
        rule: HoistRule::Bytes { reordered: true },
    };
    /// The `small` preset: the paper's thresholds, with the byte rule for
    /// a reordered file.
    pub const SMALL: SlimParams = SlimParams {
        tau_occu: 0.5,
        tau_freq: 0.4,
        max_t2rn: 4,
        rule: HoistRule::Bytes { reordered: true },
    };

    /// The same thresholds with another hoist rule.
    pub const fn with_rule(self, rule: HoistRule) -> SlimParams {
        SlimParams { rule, ..self }
    }
}

/// What the post-pass did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SlimReport {
    /// Triangles hoisted (type II nodes made).
    pub hoisted: usize,
    /// Hoists cancelled because the rebuilt subtree was a single leaf.
    pub cancelled: usize,
    /// Hoists rejected by [`HoistRule::Bytes`] (the rebuilt subtree was not
    /// smaller).
    pub rejected: usize,
    /// Hoists rejected by [`HoistRule::Bytes`] without a rebuild: the
    /// replaced subtree takes at most 8 bytes more than the smallest
    /// rebuilt subtree could ([`min_subtree_bytes`]), so no rebuild can
    /// pass the rule. (Such a pick would be rejected or cancelled.)
    pub skipped: usize,
    /// Subtrees rebuilt (`hoisted + cancelled + rejected`).
    pub rebuilds: usize,
    /// Triangle references rebuilt (the work of the rebuilds).
    pub rebuilt_refs: usize,
}

/// Where the post-pass spent its time (seconds, wall clock).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SlimPhases {
    /// Passes over the pending subtrees.
    pub passes: u32,
    /// Analyses (the oracle for every node of a subtree) and the top-down
    /// search for picks, with the byte model's setup.
    pub analysis_s: f64,
    /// Rebuilding the picked subtrees and deciding.
    pub rebuild_s: f64,
    /// Putting the rebuilt subtrees into the work tree.
    pub apply_s: f64,
    /// The final tree in canonical pre-order.
    pub assemble_s: f64,
}

/// Occupancy weight of a leaf: `SA(leaf)/SA(root)` in units of 2⁻⁴⁰.
pub fn occupancy_weight(cell: &Aabb, sa_root: f64) -> u64 {
    if sa_root > 0.0 {
        (cell.surface_area() / sa_root * (1u64 << 40) as f64).round() as u64
    } else {
        0
    }
}

/// Whether `part / whole` exceeds `tau` (the one formula).
#[inline]
pub fn above(part: f64, whole: f64, tau: f64) -> bool {
    whole > 0.0 && part / whole > tau
}

/// Rebuilds a subtree from scratch, as Algorithm 1 does: the triangles
/// `tris` (ascending), each clipped to `cell`, built by the sweep builder
/// at `depth`. Triangles that do not meet `cell` are left out. (The pass
/// itself builds the same subtree with [`SubtreeBuilder`].)
pub fn rebuild(
    scene: &TriangleColumns,
    config: &BuildConfig,
    tris: &[TriId],
    cell: &Aabb,
    depth: u32,
) -> TreeIr {
    let refs: Vec<TriRef> = tris
        .iter()
        .filter_map(|&tri| {
            clip_triangle(&scene.tri(tri.0), cell).map(|bounds| TriRef { tri, bounds })
        })
        .collect();
    sweep::build_subtree(scene, config, refs, *cell, depth, None)
}

/// How [`HoistRule::Bytes`] counts bytes.
struct ByteModel {
    /// The file id of each triangle (`None`: the input id).
    rank: Option<Vec<u32>>,
}

impl ByteModel {
    fn new(scene: &TriangleColumns, reordered: bool) -> ByteModel {
        ByteModel {
            rank: reordered.then(|| {
                let perm = scene.morton_order();
                let mut rank = vec![0u32; perm.len()];
                for (new, &old) in perm.iter().enumerate() {
                    rank[old as usize] = new as u32;
                }
                rank
            }),
        }
    }

    fn leaf(&self, tris: &[TriId]) -> u64 {
        match &self.rank {
            Some(r) => leaf_index_bytes(tris.len(), tris.iter().map(|t| r[t.0 as usize])),
            None => leaf_index_bytes(tris.len(), tris.iter().map(|t| t.0)),
        }
    }

    fn tree(&self, t: &TreeIr) -> u64 {
        t.nodes
            .iter()
            .map(|n| match *n {
                Node::Inner { t_ref, .. } => 8 + 8 * u64::from(t_ref.is_some()),
                Node::Leaf { start, count } => 8 + self.leaf(t.leaf(start, count)),
            })
            .sum()
    }

    /// The bytes of the contiguous subtree `work.nodes[node..node + size]`.
    fn subtree(&self, work: &Work, node: u32, size: u32) -> u64 {
        work.nodes[node as usize..(node + size) as usize]
            .iter()
            .map(|n| match *n {
                WNode::Inner { t_ref, .. } => 8 + 8 * u64::from(t_ref.is_some()),
                WNode::Leaf { start, count } => 8 + self.leaf(work.leaf(start, count)),
            })
            .sum()
    }
}

/// A mutable tree with explicit children, so that subtrees can be replaced
/// without renumbering; turned back into canonical pre-order at the end.
#[derive(Clone, Copy, Debug)]
enum WNode {
    Inner {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
        t_ref: Option<TriId>,
    },
    Leaf {
        start: u32,
        count: u32,
    },
}

/// The work tree: pre-order blocks (the standard tree, then each rebuilt
/// subtree) appended one after the other. Within a block an inner node's
/// left child is the next node and its subtree is a contiguous range of
/// nodes whose leaves' triangles are a contiguous range of `tris`; only a
/// hoisting node's children lie in another block.
struct Work {
    nodes: Vec<WNode>,
    tris: Vec<TriId>,
}

impl Work {
    fn leaf(&self, start: u32, count: u32) -> &[TriId] {
        &self.tris[start as usize..(start + count) as usize]
    }

    /// Appends pre-order trees in parallel; returns the index of each root.
    fn append_all<T: Borrow<TreeIr> + Send>(&mut self, trees: Vec<T>) -> Vec<u32> {
        let mut bases = Vec::with_capacity(trees.len());
        let (mut n, mut t) = (self.nodes.len(), self.tris.len());
        for tree in trees.iter().map(Borrow::borrow) {
            bases.push((n as u32, t as u32));
            n += tree.nodes.len();
            t += tree.leaf_tris.len();
        }
        let (n0, t0) = (self.nodes.len(), self.tris.len());
        self.nodes.resize(n, WNode::Leaf { start: 0, count: 0 });
        self.tris.resize(t, TriId(0));
        // Cut the new tails into one slice per tree.
        let mut slices = Vec::with_capacity(trees.len());
        let (mut nodes, mut tris) = (&mut self.nodes[n0..], &mut self.tris[t0..]);
        for tree in trees.iter().map(Borrow::borrow) {
            let (a, rest) = std::mem::take(&mut nodes).split_at_mut(tree.nodes.len());
            let (b, rest_t) = std::mem::take(&mut tris).split_at_mut(tree.leaf_tris.len());
            slices.push((a, b));
            nodes = rest;
            tris = rest_t;
        }
        trees
            .into_par_iter()
            .zip(slices)
            .zip(bases.par_iter())
            .with_min_len(64)
            .for_each(|((tree, (nodes, tris)), &(base, tri_base))| {
                let tree: &TreeIr = tree.borrow();
                tris.copy_from_slice(&tree.leaf_tris);
                for (i, (out, n)) in nodes.iter_mut().zip(&tree.nodes).enumerate() {
                    *out = match *n {
                        Node::Inner {
                            axis,
                            pos,
                            right,
                            t_ref,
                        } => WNode::Inner {
                            axis,
                            pos,
                            left: base + i as u32 + 1,
                            right: base + right.0,
                            t_ref,
                        },
                        Node::Leaf { start, count } => WNode::Leaf {
                            start: tri_base + start,
                            count,
                        },
                    };
                }
            });
        bases.into_iter().map(|(b, _)| b).collect()
    }

    /// The range of `tris` holding the leaves of the contiguous subtree
    /// `nodes[node..node + size]`: from its leftmost leaf to its last node
    /// (its rightmost leaf).
    fn tri_range(&self, node: u32, size: u32) -> (usize, usize) {
        let mut n = node;
        let start = loop {
            match self.nodes[n as usize] {
                WNode::Inner { left, .. } => n = left,
                WNode::Leaf { start, .. } => break start,
            }
        };
        let WNode::Leaf { start: s, count } = self.nodes[(node + size - 1) as usize] else {
            unreachable!("the last node of a subtree in pre-order is a leaf");
        };
        (start as usize, (s + count) as usize)
    }

    /// The canonical pre-order form of the tree under `root`.
    fn to_ir(&self, root: u32, bounds: Aabb) -> TreeIr {
        let mut out = TreeIr {
            bounds,
            nodes: Vec::with_capacity(self.nodes.len()),
            leaf_tris: Vec::new(),
        };
        // (work node, index of the inner node whose `right` it becomes).
        let mut stack = vec![(root, None::<usize>)];
        while let Some((w, parent)) = stack.pop() {
            let me = out.nodes.len();
            if let Some(p) = parent
                && let Node::Inner { right, .. } = &mut out.nodes[p]
            {
                *right = NodeId(me as u32);
            }
            match self.nodes[w as usize] {
                WNode::Inner {
                    axis,
                    pos,
                    left,
                    right,
                    t_ref,
                } => {
                    out.nodes.push(Node::Inner {
                        axis,
                        pos,
                        right: NodeId(u32::MAX),
                        t_ref,
                    });
                    stack.push((right, Some(me)));
                    stack.push((left, None));
                }
                WNode::Leaf { start, count } => {
                    let s = out.leaf_tris.len() as u32;
                    out.leaf_tris.extend_from_slice(self.leaf(start, count));
                    out.nodes.push(Node::Leaf { start: s, count });
                }
            }
        }
        out
    }
}

/// No triangle picked.
const NONE: u32 = u32::MAX;

/// Subtrees of more nodes than this are analysed in parallel (fork–join).
const GRAIN: u32 = 1 << 13;

/// The pick of every node of one contiguous subtree of the work tree.
struct Analysis {
    root: u32,
    /// `picks[n - root]`: the triangle picked at node `n`, or [`NONE`].
    picks: Vec<u32>,
}

impl Analysis {
    fn pick(&self, node: u32) -> Option<TriId> {
        let t = self.picks[(node - self.root) as usize];
        (t != NONE).then_some(TriId(t))
    }
}

/// Running sums of leaf weights, in `u64` where no sum can overflow it
/// (fewer than 2²⁴ terms of at most 2⁴⁰), else `u128`.
enum Prefix {
    Narrow(Vec<u64>),
    Wide(Vec<u128>),
}

impl Prefix {
    /// The running sums of `weight(0..n)`; the terms are gathered in
    /// parallel when `parallel`.
    fn of(n: usize, weight: impl Fn(usize) -> u64 + Sync, parallel: bool) -> Prefix {
        let mut v: Vec<u64> = Vec::with_capacity(n + 1);
        v.push(0);
        if parallel {
            v.par_extend((0..n).into_par_iter().map(&weight));
        } else {
            v.extend((0..n).map(&weight));
        }
        if n < 1 << 24 {
            for i in 1..v.len() {
                v[i] += v[i - 1];
            }
            Prefix::Narrow(v)
        } else {
            let mut sum = 0u128;
            Prefix::Wide(
                v.into_iter()
                    .map(|w| {
                        sum += u128::from(w);
                        sum
                    })
                    .collect(),
            )
        }
    }

    /// The sum of terms `a..b`.
    #[inline]
    fn sum(&self, a: usize, b: usize) -> u128 {
        match self {
            Prefix::Narrow(v) => u128::from(v[b] - v[a]),
            Prefix::Wide(v) => v[b] - v[a],
        }
    }
}

/// Triangles in keys of (triangle, leaf) pairs: `tri << 32 | leaf`.
#[inline]
fn key(tri: u32, leaf: u32) -> u64 {
    (u64::from(tri) << 32) | u64::from(leaf)
}

/// What the bottom-up pass of one analysis reads.
struct Counts<'a> {
    work: &'a Work,
    params: &'a SlimParams,
    /// The subtree's (triangle, leaf number) pairs, sorted; leaves are
    /// numbered in pre-order from 0.
    keys: Vec<u64>,
    /// Running sums of the pairs' leaf weights.
    pair_prefix: Prefix,
    /// Running sums of the leaves' weights.
    leaf_prefix: Prefix,
    /// For large subtrees, the range of `keys` of each triangle (indexed
    /// by triangle id); else the whole of `keys` is searched.
    segments: Option<Vec<(u32, u32)>>,
}

impl Counts<'_> {
    /// Count and occupancy of triangle `t` in the leaves `a..b`.
    #[inline]
    fn stats(&self, t: u32, a: u32, b: u32) -> (u32, u128) {
        let (s, e) = match &self.segments {
            Some(seg) => {
                let (s, e) = seg[t as usize];
                (s as usize, e as usize)
            }
            None => (0, self.keys.len()),
        };
        let list = &self.keys[s..e];
        let lo = s + list.partition_point(|&k| k < key(t, a));
        let hi = s + list.partition_point(|&k| k < key(t, b));
        ((hi - lo) as u32, self.pair_prefix.sum(lo, hi))
    }

    /// Appends the frequent triangles of the subtree `node` (`size` nodes,
    /// first leaf number `first_leaf`) to `out`, ascending, with their
    /// counts and occupancies there, and fills `picks` (the subtree's
    /// slice). `merged` is scratch.
    fn candidates(
        &self,
        node: u32,
        size: u32,
        first_leaf: u32,
        out: &mut Vec<Cand>,
        picks: &mut [u32],
        merged: &mut Vec<Cand>,
    ) {
        let (left, right) = match self.work.nodes[node as usize] {
            WNode::Leaf { start, count } => {
                let leaf = first_leaf as usize;
                let occu = self.leaf_prefix.sum(leaf, leaf + 1);
                out.extend(self.work.leaf(start, count).iter().map(|t| Cand {
                    tri: t.0,
                    count: 1,
                    occu,
                }));
                return;
            }
            WNode::Inner { left, right, .. } => (left, right),
        };
        let size_l = right - left;
        let size_r = size - 1 - size_l;
        let first_r = first_leaf + size_l.div_ceil(2);
        let (picks_l, picks_r) = picks[1..].split_at_mut(size_l as usize);
        let base = out.len();
        let mid = if size > GRAIN {
            let (mut a, mut b) = (Vec::new(), Vec::new());
            rayon::join(
                || self.candidates(left, size_l, first_leaf, &mut a, picks_l, &mut Vec::new()),
                || self.candidates(right, size_r, first_r, &mut b, picks_r, &mut Vec::new()),
            );
            out.extend_from_slice(&a);
            let mid = out.len();
            out.extend_from_slice(&b);
            mid
        } else {
            self.candidates(left, size_l, first_leaf, out, picks_l, merged);
            let mid = out.len();
            self.candidates(right, size_r, first_r, out, picks_r, merged);
            mid
        };
        // Leaves `a..m` are the left child's, `m..b` the right child's.
        let (a, m, b) = (first_leaf, first_r, first_leaf + size.div_ceil(2));
        let n_leaves = f64::from(b - a);
        let tau_freq = self.params.tau_freq;
        // The union of the children's candidates, ascending, with their
        // counts and occupancies here: a triangle frequent in one child
        // only is looked up in the other child's leaves, unless it cannot
        // be frequent here even if it lay in all of them.
        merged.clear();
        let other = |c: &Cand, lo: u32, hi: u32| {
            if above(f64::from(c.count + (hi - lo)), n_leaves, tau_freq) {
                let (count, occu) = self.stats(c.tri, lo, hi);
                Some(Cand {
                    tri: c.tri,
                    count: c.count + count,
                    occu: c.occu + occu,
                })
            } else {
                None
            }
        };
        let (l, r) = out[base..].split_at(mid - base);
        let (mut i, mut j) = (0, 0);
        while i < l.len() || j < r.len() {
            let (x, y) = (l.get(i), r.get(j));
            match (x, y) {
                (Some(x), Some(y)) if x.tri == y.tri => {
                    merged.push(Cand {
                        tri: x.tri,
                        count: x.count + y.count,
                        occu: x.occu + y.occu,
                    });
                    i += 1;
                    j += 1;
                }
                (Some(x), y) if y.is_none_or(|y| x.tri < y.tri) => {
                    merged.extend(other(x, m, b));
                    i += 1;
                }
                (_, Some(y)) => {
                    merged.extend(other(y, a, m));
                    j += 1;
                }
                (_, None) => unreachable!("the left list is handled above"),
            }
        }
        out.truncate(base);
        // Keep the frequent ones; pick the best of those above τ_occu.
        let total = self.leaf_prefix.sum(a as usize, b as usize) as f64;
        let mut best: Option<(u128, u32)> = None;
        for c in merged.iter() {
            if above(f64::from(c.count), n_leaves, tau_freq) {
                out.push(*c);
                if above(c.occu as f64, total, self.params.tau_occu)
                    && best.is_none_or(|(bo, bt)| c.occu > bo || (c.occu == bo && c.tri < bt))
                {
                    best = Some((c.occu, c.tri));
                }
            }
        }
        picks[0] = best.map_or(NONE, |(_, t)| t);
    }
}

/// A candidate triangle of a subtree, with its count and occupancy there.
#[derive(Clone, Copy)]
struct Cand {
    tri: u32,
    count: u32,
    occu: u128,
}

/// Fills the leaf weights and the (triangle, leaf) pairs of the subtree
/// `node` (`size` nodes, cell `cell`, first leaf `first_leaf`); `w` and
/// `keys` are the subtree's slices, its leaves' triangles start at
/// `tri_start` of the work tree.
#[allow(clippy::too_many_arguments)]
fn fill(
    work: &Work,
    node: u32,
    size: u32,
    cell: Aabb,
    first_leaf: u32,
    tri_start: usize,
    sa_root: f64,
    w: &mut [u64],
    keys: &mut [u64],
) {
    match work.nodes[node as usize] {
        WNode::Leaf { start, count } => {
            w[0] = occupancy_weight(&cell, sa_root);
            for (k, t) in keys.iter_mut().zip(work.leaf(start, count)) {
                *k = key(t.0, first_leaf);
            }
        }
        WNode::Inner {
            axis,
            pos,
            left,
            right,
            ..
        } => {
            let (lc, rc) = cell.split(axis as usize, pos);
            let size_l = right - left;
            let leaves_l = size_l.div_ceil(2);
            let (right_start, _) = work.tri_range(right, size - 1 - size_l);
            let (wl, wr) = w.split_at_mut(leaves_l as usize);
            let (kl, kr) = keys.split_at_mut(right_start - tri_start);
            let l = |wl: &mut [u64], kl: &mut [u64]| {
                fill(
                    work, left, size_l, lc, first_leaf, tri_start, sa_root, wl, kl,
                )
            };
            let r = |wr: &mut [u64], kr: &mut [u64]| {
                fill(
                    work,
                    right,
                    size - 1 - size_l,
                    rc,
                    first_leaf + leaves_l,
                    right_start,
                    sa_root,
                    wr,
                    kr,
                )
            };
            if size > GRAIN {
                rayon::join(|| l(wl, kl), || r(wr, kr));
            } else {
                l(wl, kl);
                r(wr, kr);
            }
        }
    }
}

/// Computes `pick_triangle` for every inner node of the contiguous subtree
/// `node` of `size` nodes with cell `cell` (the fast way; see the module
/// docs).
fn analyze(
    work: &Work,
    node: u32,
    size: u32,
    cell: Aabb,
    sa_root: f64,
    params: &SlimParams,
    n_tris: usize,
) -> Analysis {
    let n_leaves = size.div_ceil(2) as usize;
    let (s, e) = work.tri_range(node, size);
    let mut w = vec![0u64; n_leaves];
    let mut keys = vec![0u64; e - s];
    fill(work, node, size, cell, 0, s, sa_root, &mut w, &mut keys);
    let large = size > GRAIN;
    if large {
        keys.par_sort_unstable();
    } else {
        keys.sort_unstable();
    }
    let tri_of = |i: usize| (keys[i] >> 32) as u32;
    let (pair_prefix, (leaf_prefix, segments)) = rayon::join(
        || Prefix::of(keys.len(), |i| w[keys[i] as u32 as usize], large),
        || {
            rayon::join(
                || Prefix::of(w.len(), |i| w[i], large),
                || {
                    large.then(|| {
                        // Where each triangle's pairs start, then its range.
                        let starts: Vec<u32> = (0..keys.len())
                            .into_par_iter()
                            .filter(|&i| i == 0 || tri_of(i) != tri_of(i - 1))
                            .map(|i| i as u32)
                            .collect();
                        let mut seg = vec![(0u32, 0u32); n_tris];
                        for (j, &a) in starts.iter().enumerate() {
                            let b = starts.get(j + 1).copied().unwrap_or(keys.len() as u32);
                            seg[tri_of(a as usize) as usize] = (a, b);
                        }
                        seg
                    })
                },
            )
        },
    );
    let counts = Counts {
        work,
        params,
        keys,
        pair_prefix,
        leaf_prefix,
        segments,
    };
    let mut picks = vec![NONE; size as usize];
    counts.candidates(node, size, 0, &mut Vec::new(), &mut picks, &mut Vec::new());
    Analysis { root: node, picks }
}

/// A subtree to process: its root, node count (a contiguous pre-order
/// range of the work tree), cell, depth, the hoisted triangles on the path
/// above it, the analysis of an enclosing subtree if it still holds, and
/// its share of the progress ([`Progress::TOTAL`] for the whole tree).
#[derive(Clone)]
struct Todo {
    node: u32,
    size: u32,
    cell: Aabb,
    depth: u32,
    t2rn: u32,
    analysis: Option<Arc<Analysis>>,
    weight: u64,
}

impl Todo {
    /// The children of an inner node as subtrees to process. Each gets a
    /// share of this subtree's progress weight in proportion to its node
    /// count; the rest (this node's own share, and rounding) is done, and
    /// added to `progress`.
    fn children(
        &self,
        work: &Work,
        t2rn: u32,
        analysis: Option<Arc<Analysis>>,
        progress: Option<&Progress>,
    ) -> [Todo; 2] {
        let WNode::Inner {
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
struct Pick {
    at: Todo,
    tri: TriId,
}

/// Walks a subtree top-down and returns the highest nodes where a triangle
/// is picked (their subtrees are not walked further in this pass).
///
/// The progress weight of every node walked and not picked is done here;
/// the picks carry theirs on.
fn find_picks(work: &Work, sub: Todo, ctx: &Ctx) -> Vec<Pick> {
    let mut picks = Vec::new();
    if sub.t2rn >= ctx.params.max_t2rn
        || !matches!(work.nodes[sub.node as usize], WNode::Inner { .. })
    {
        Progress::add(ctx.progress, sub.weight);
        return picks;
    }
    let analysis = match &sub.analysis {
        Some(a) => a.clone(),
        None => Arc::new(analyze(
            work,
            sub.node,
            sub.size,
            sub.cell,
            ctx.sa_root,
            ctx.params,
            ctx.scene.len(),
        )),
    };
    let mut stack = vec![sub];
    while let Some(mut at) = stack.pop() {
        if !matches!(work.nodes[at.node as usize], WNode::Inner { .. }) {
            Progress::add(ctx.progress, at.weight);
            continue;
        }
        if let Some(tri) = analysis.pick(at.node) {
            at.analysis = Some(analysis.clone());
            picks.push(Pick { at, tri });
            continue;
        }
        let [l, r] = at.children(work, at.t2rn, None, ctx.progress);
        stack.push(r);
        stack.push(l);
    }
    picks
}

/// What became of a pick.
enum Outcome {
    Hoisted(TreeIr),
    Cancelled,
    Rejected,
    /// Rejected without a rebuild: the subtree is too small for any
    /// rebuilt one to save bytes ([`min_subtree_bytes`]).
    Skipped,
}

/// The fixed inputs of a run.
struct Ctx<'a> {
    scene: &'a TriangleColumns,
    params: &'a SlimParams,
    sa_root: f64,
    bytes: Option<ByteModel>,
    progress: Option<&'a Progress>,
}

/// Rebuilds the subtree of a pick without its triangle and decides.
/// Returns the outcome and the number of triangles rebuilt.
fn rebuild_pick(
    work: &Work,
    p: &Pick,
    ctx: &Ctx,
    builder: &mut SubtreeBuilder,
    tris: &mut Vec<TriId>,
    refs: &mut Vec<(TriId, Aabb)>,
) -> (Outcome, usize) {
    let (s, e) = work.tri_range(p.at.node, p.at.size);
    tris.clear();
    tris.extend_from_slice(&work.tris[s..e]);
    tris.sort_unstable();
    tris.dedup();
    tris.retain(|&t| t != p.tri);
    refs.clear();
    let mut clipped = false;
    let mut clip_all = |refs: &mut Vec<(TriId, Aabb)>| {
        if !clipped {
            clipped = true;
            refs.extend(tris.iter().filter_map(|&t| {
                clip_triangle(&ctx.scene.tri(t.0), &p.at.cell).map(|bounds| (t, bounds))
            }));
        }
    };
    let old = ctx
        .bytes
        .as_ref()
        .map(|m| m.subtree(work, p.at.node, p.at.size));
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
    let fresh = builder.build(refs.iter().copied(), p.at.cell, p.at.depth);
    let outcome = if matches!(fresh.nodes[0], Node::Leaf { .. }) {
        Outcome::Cancelled
    } else if let (Some(m), Some(old)) = (&ctx.bytes, old)
        && m.tree(&fresh) + 8 >= old
    {
        Outcome::Rejected
    } else {
        Outcome::Hoisted(fresh)
    };
    (outcome, tris.len())
}

/// The fewest bytes a rebuilt subtree of `n_refs` references that can hold
/// a hoisted triangle takes: an inner node and two leaves, and every
/// reference in some leaf at 2 bytes at least.
pub fn min_subtree_bytes(n_refs: usize) -> u64 {
    3 * 8 + 2 * n_refs as u64
}

/// Applies Algorithm 1 to a standard tree.
///
/// The algorithm runs in passes: each pass finds, in every pending subtree,
/// the highest nodes where a triangle is picked, rebuilds those (disjoint)
/// subtrees in parallel on the current rayon pool, and queues their
/// children. A node's pick depends only on its own subtree, so this order
/// gives the same tree as the sequential stack of the paper (the tests
/// assert it against a literal implementation), for any thread count.
pub fn slim(
    tree: &TreeIr,
    scene: &TriangleColumns,
    config: &BuildConfig,
    params: &SlimParams,
) -> (TreeIr, SlimReport) {
    let (tree, report, _) = slim_with_phases(tree, scene, config, params);
    (tree, report)
}

/// [`slim`], with the time spent in each phase.
pub fn slim_with_phases(
    tree: &TreeIr,
    scene: &TriangleColumns,
    config: &BuildConfig,
    params: &SlimParams,
) -> (TreeIr, SlimReport, SlimPhases) {
    slim_with_progress(tree, scene, config, params, None)
}

/// [`slim_with_phases`], advancing `progress` from 0 to 1 as it goes
/// (for a progress bar). Each subtree to process carries a share of the
/// progress in proportion to its node count; the share of a node is done
/// when the pass decides it (no pick there, or the pick's rebuild taken or
/// not), and a rebuilt subtree hands its share on to its children.
pub fn slim_with_progress(
    tree: &TreeIr,
    scene: &TriangleColumns,
    config: &BuildConfig,
    params: &SlimParams,
    progress: Option<&Progress>,
) -> (TreeIr, SlimReport, SlimPhases) {
    let mut report = SlimReport::default();
    let mut phases = SlimPhases::default();
    if params.max_t2rn == 0 {
        Progress::add_all(progress);
        return (tree.clone(), report, phases);
    }
    let mut clock = Instant::now();
    let mut work = Work {
        nodes: Vec::new(),
        tris: Vec::new(),
    };
    let root = work.append_all(vec![tree])[0];
    phases.apply_s += lap(&mut clock);
    let (bytes, analysis) = rayon::join(
        || match params.rule {
            HoistRule::Paper => None,
            HoistRule::Bytes { reordered } => Some(ByteModel::new(scene, reordered)),
        },
        || {
            analyze(
                &work,
                root,
                tree.nodes.len() as u32,
                tree.bounds,
                tree.bounds.surface_area(),
                params,
                scene.len(),
            )
        },
    );
    let ctx = Ctx {
        scene,
        params,
        sa_root: tree.bounds.surface_area(),
        bytes,
        progress,
    };
    phases.analysis_s += lap(&mut clock);
    let mut todo = vec![Todo {
        node: root,
        size: tree.nodes.len() as u32,
        cell: tree.bounds,
        depth: 0,
        t2rn: 0,
        analysis: Some(Arc::new(analysis)),
        weight: Progress::TOTAL,
    }];
    while !todo.is_empty() {
        phases.passes += 1;
        let picks: Vec<Pick> = todo
            .par_drain(..)
            .flat_map_iter(|sub| find_picks(&work, sub, &ctx))
            .collect();
        phases.analysis_s += lap(&mut clock);
        let outcomes: Vec<(Outcome, usize)> = picks
            .par_iter()
            .map_init(
                || (SubtreeBuilder::new(scene, config), Vec::new(), Vec::new()),
                |(builder, tris, refs), p| rebuild_pick(&work, p, &ctx, builder, tris, refs),
            )
            .collect();
        phases.rebuild_s += lap(&mut clock);
        let mut fresh = Vec::new();
        for (p, (outcome, n)) in picks.iter().zip(outcomes) {
            if !matches!(outcome, Outcome::Skipped) {
                report.rebuilds += 1;
                report.rebuilt_refs += n;
            }
            match outcome {
                Outcome::Hoisted(t) => {
                    report.hoisted += 1;
                    fresh.push((p, t));
                }
                // The original subtree stays, and its children are
                // processed as if nothing was picked here, with the same
                // analysis.
                Outcome::Cancelled | Outcome::Rejected | Outcome::Skipped => {
                    match outcome {
                        Outcome::Cancelled => report.cancelled += 1,
                        Outcome::Rejected => report.rejected += 1,
                        _ => report.skipped += 1,
                    }
                    todo.extend(p.at.children(&work, p.at.t2rn, p.at.analysis.clone(), progress));
                }
            }
        }
        let (at, trees): (Vec<&Pick>, Vec<TreeIr>) = fresh.into_iter().unzip();
        let sizes: Vec<(u32, u32)> = trees
            .iter()
            .map(|t| match t.nodes[0] {
                Node::Inner { right, .. } => (right.0, t.nodes.len() as u32),
                Node::Leaf { .. } => unreachable!("hoisted subtrees have an inner root"),
            })
            .collect();
        let bases = work.append_all(trees);
        for ((p, base), (right, size)) in at.into_iter().zip(bases).zip(sizes) {
            let WNode::Inner { axis, pos, .. } = work.nodes[base as usize] else {
                unreachable!("hoisted subtrees have an inner root");
            };
            // The fresh root's split, with the hoisted triangle, at the
            // pick's node; the fresh root itself stays unreachable.
            work.nodes[p.at.node as usize] = WNode::Inner {
                axis,
                pos,
                left: base + 1,
                right: base + right,
                t_ref: Some(p.tri),
            };
            let here = Todo {
                size,
                analysis: None,
                ..p.at.clone()
            };
            if p.at.t2rn + 1 < params.max_t2rn {
                todo.extend(here.children(&work, p.at.t2rn + 1, None, progress));
            } else {
                Progress::add(progress, here.weight);
            }
        }
        phases.apply_s += lap(&mut clock);
    }
    let out = work.to_ir(root, tree.bounds);
    phases.assemble_s = lap(&mut clock);
    (out, report, phases)
}

/// A test scene: triangle 0 is big and spans an 8×8 grid of small
/// slanted triangles 2 apart, so the standard tree lists it in many leaves.
#[cfg(test)]
pub(crate) fn huge_over_grid() -> TriangleColumns {
    use glam::Vec3;
    let mut tris = vec![[
        Vec3::new(-1.0, -1.0, 0.5),
        Vec3::new(30.0, -1.0, 0.5),
        Vec3::new(-1.0, 30.0, 0.5),
    ]];
    tris.extend(crate::scene::slanted_grid(8));
    TriangleColumns::from_triangles(&tris).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::{self, Builder};

    #[test]
    fn huge_triangle_is_hoisted() {
        // A big triangle spanning a grid of small ones lies in most leaves:
        // with the paper's rule it is hoisted into the root. With the byte
        // rule it is not (the rebuilt tree cuts the empty space around the
        // small triangles and takes more nodes), and the tree never grows.
        let scene = huge_over_grid();
        let config = BuildConfig::default();
        let std_tree = build::build(&scene, &config, Builder::Sweep, None).unwrap();
        let paper = SlimParams::SMALL.with_rule(HoistRule::Paper);
        let (slim_tree, report) = slim(&std_tree, &scene, &config, &paper);
        slim_tree.validate(&scene).unwrap();
        assert!(report.hoisted >= 1, "{report:?}");
        assert!(matches!(
            slim_tree.nodes[0],
            Node::Inner {
                t_ref: Some(TriId(0)),
                ..
            }
        ));
        assert!(slim_tree.leaf_tris.len() < std_tree.leaf_tris.len());
        for reordered in [false, true] {
            let p = SlimParams::SMALL.with_rule(HoistRule::Bytes { reordered });
            let (slim_tree, report) = slim(&std_tree, &scene, &config, &p);
            slim_tree.validate(&scene).unwrap();
            let m = ByteModel::new(&scene, reordered);
            assert!(m.tree(&slim_tree) <= m.tree(&std_tree), "{report:?}");
            assert!(report.rejected + report.skipped > 0, "{report:?}");
        }
    }
}
