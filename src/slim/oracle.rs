//! The occupancy/frequency oracle: `pick_triangle` for every node of a
//! contiguous subtree of the work tree in one bottom-up analysis, over
//! candidate lists merged from the children, with the subtree's sorted
//! (triangle, leaf) pairs and integer prefix sums of leaf weights (exact,
//! so independent of summation order); fork–join parallel for large
//! subtrees.

use super::SlimParams;
use super::work::{Work, WorkNode};
use crate::geom::Aabb;
use crate::tree::TriId;
use rayon::prelude::*;

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

/// No triangle picked.
const NONE: u32 = u32::MAX;

/// Subtrees of more nodes than this are analysed in parallel (fork–join).
const GRAIN: u32 = 1 << 13;

/// The pick of every node of one contiguous subtree of the work tree.
pub(super) struct Analysis {
    root: u32,
    /// `picks[n - root]`: the triangle picked at node `n`, or [`NONE`].
    picks: Vec<u32>,
}

impl Analysis {
    pub(super) fn pick(&self, node: u32) -> Option<TriId> {
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
            WorkNode::Leaf { start, count } => {
                let leaf = first_leaf as usize;
                let occu = self.leaf_prefix.sum(leaf, leaf + 1);
                out.extend(self.work.leaf(start, count).iter().map(|t| Cand {
                    tri: t.0,
                    count: 1,
                    occu,
                }));
                return;
            }
            WorkNode::Inner { left, right, .. } => (left, right),
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
        WorkNode::Leaf { start, count } => {
            w[0] = occupancy_weight(&cell, sa_root);
            for (k, t) in keys.iter_mut().zip(work.leaf(start, count)) {
                *k = key(t.0, first_leaf);
            }
        }
        WorkNode::Inner {
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
/// `node` of `size` nodes with cell `cell` (the fast way; see the [module
/// docs](super)).
pub(super) fn analyze(
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
