//! Step 2 of a level (and the finisher's sweeps): the SAH sweep over a
//! node's sorted events, pruned by lower bounds of the cost, and the level
//! passes' parallel form of it, in which every axis's events are cut into
//! pieces and a piece that continues a node starts from counts carried
//! over the node's earlier pieces.
//!
//! Pruning never changes the split found: a plane (or a block of events)
//! is passed over only when a lower bound of its cost ([`Pricer`]) shows
//! that it cannot be the best split, or cannot keep the node from being a
//! leaf.

use super::Level;
use super::events::{ev_key, ev_kind, key_pos};
use super::pieces::{PIECE, Pair, Piece, element_carries, pieces};
use crate::build::sah::{self, PlaneCounts, SahParams, Split};
use crate::geom::Aabb;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};

/// The best split of each of the `big` nodes (`None` for an empty node
/// or a flat cell, as in the Wald-Havran builder).
pub(super) fn best_splits(
    sah: &SahParams,
    depth_limit: u32,
    l: &Level<'_>,
    big: &[usize],
) -> Vec<Option<Split>> {
    let sa: Vec<f64> = big
        .iter()
        .map(|&j| l.nodes[j].cell.surface_area())
        .collect();
    // Nodes at the depth limit are leaves whatever their best split
    // ([`sah::is_leaf`]): they are not swept.
    let valid: Vec<usize> = (0..big.len())
        .filter(|&bi| l.nodes[big[bi]].n > 0 && sa[bi] > 0.0 && l.depth < depth_limit)
        .collect();
    let mut tasks: Vec<(usize, Piece, Pair)> = Vec::new();
    for (axis, ev) in l.ev.iter().enumerate() {
        let segs: Vec<(usize, usize)> = valid
            .iter()
            .map(|&bi| {
                let nd = &l.nodes[big[bi]];
                (nd.ev[axis], nd.nev[axis])
            })
            .collect();
        let ev: &[u64] = ev;
        // A run of equal positions is priced as one plane, so it must
        // not be cut.
        let ps = pieces(&segs, PIECE, |i| ev_key(ev[i]) != ev_key(ev[i - 1]));
        // Carried counts of (starts + planars, ends + planars).
        let carry = element_carries(&ps, &segs, ev, ev_kind, |c| {
            Pair([c[2] + c[1], c[0] + c[1]])
        });
        // Piece node indices refer to `valid`.
        tasks.extend(ps.into_iter().zip(carry).map(|(p, c)| (axis, p, c)));
    }
    // Each node's least cost so far, shared by its tasks (every axis,
    // every part), so that each prunes against the others' planes too.
    let shared: Vec<AtomicU64> = valid
        .iter()
        .map(|&bi| AtomicU64::new(sah.leaf_cost(l.nodes[big[bi]].n).to_bits()))
        .collect();
    let found: Vec<Vec<(usize, Split)>> = tasks
        .par_iter()
        .map(|(axis, p, carry)| {
            let mut out = Vec::new();
            for vi in p.nodes.clone() {
                let bi = valid[vi];
                let nd = &l.nodes[big[bi]];
                let seg = (nd.ev[*axis], nd.nev[*axis]);
                let (n_l, n_r) = if p.continues(seg) {
                    (carry.0[0], nd.n - carry.0[1])
                } else {
                    (0, nd.n)
                };
                let mut best = None;
                sweep_events(
                    sah,
                    &nd.cell,
                    sa[bi],
                    *axis,
                    &l.ev[*axis][p.range(seg)],
                    n_l,
                    n_r,
                    sah.leaf_cost(nd.n),
                    &mut best,
                    &shared[vi],
                );
                if let Some(s) = best {
                    out.push((bi, s));
                }
            }
            out
        })
        .collect();
    let mut best = vec![None; big.len()];
    for (bi, s) in found.into_iter().flatten() {
        s.keep_best(&mut best[bi]);
    }
    best
}

/// Sweeps one node's sorted events (all of them, or one piece starting with
/// `n_l` references left and `n_r` right of its first plane) and keeps the
/// best plane: the sweep of [`crate::build::wald_havran::sweep_axis`], with carried
/// counts.
///
/// Every plane that could win is priced by [`sah::split_cost`]. A plane is
/// skipped only when a lower bound of its cost ([`Pricer`]) exceeds the
/// best cost found so far: then its exact cost does too, it would lose the
/// comparison of [`Split::cmp_order`] on cost alone, and the result is the
/// same as pricing it. Or when the bound exceeds `cap`, the node's leaf
/// cost: a split that costs at least that much never matters, since if
/// the best split does, [`sah::is_leaf`] makes the node a leaf whatever
/// the split (so `best` may stay `None` where pricing every plane would
/// have found a split, only for nodes that become leaves either way).
/// (An optimisation the paper does not have; it halves the sweep on large
/// scenes, where most planes are far from the best.)
///
/// Whole blocks of [`SKIP_BLOCK`] events are passed over, their counts
/// added without looking at their planes, when one bound for all of their
/// planes ([`Pricer::block_bound`]) already exceeds the best cost: the
/// same reasoning, so the same result. On stk_black_forest this passes
/// over 61% of the events swept.
///
/// The best cost pruned against is also `shared`'s: the least cost found
/// by the other sweeps of the same node ([`SharedBest`]). The level
/// passes sweep a node's three axes, and each part of a large node, as
/// separate tasks; without the shared cost each would start from the leaf
/// cost alone and price every plane of a stretch where the cost falls
/// towards a best plane in another part or on another axis (sharing it
/// takes about a fifth off the level passes' SAH phase on
/// black_forest). The split found is the same: a plane is still skipped
/// only when its cost exceeds that of a plane of the node.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(super) fn sweep_events(
    params: &sah::SahParams,
    cell: &Aabb,
    sa: f64,
    axis: usize,
    events: &[u64],
    mut n_l: usize,
    mut n_r: usize,
    cap: f64,
    best: &mut Option<Split>,
    shared: &impl SharedBest,
) {
    let exact = sah::AxisPricer::new(cell, sa, axis);
    let pricer = Pricer::new(params, &exact, cell, sa, axis);
    let mut best_cost = best
        .map_or(f64::INFINITY, |b| b.cost)
        .min(cap)
        .min(shared.get());
    let len = events.len();
    let mut i = 0;
    while i < len {
        best_cost = best_cost.min(shared.get());
        // Blocks of events whose planes all cost more than the best so far
        // are passed over with their counts added up: see
        // [`Pricer::block_bound`]. The block stops before its last run of
        // equal positions, which may go on past it (a plane is priced with
        // all of its run's events counted).
        let mut until = i + 1;
        if i + SKIP_BLOCK <= len {
            let blk: &[u64; SKIP_BLOCK] = events[i..i + SKIP_BLOCK]
                .try_into()
                .expect("SKIP_BLOCK long");
            let last_key = ev_key(blk[SKIP_BLOCK - 1]);
            let mut g = SKIP_BLOCK - 1;
            while g > 0 && ev_key(blk[g - 1]) == last_key {
                g -= 1;
            }
            if g > 0 {
                // Ends and planars (they leave the right side), starts and
                // planars (they join the left side), in the first `g`.
                let (mut out, mut into) = (0usize, 0usize);
                for (c, &e) in blk.iter().enumerate() {
                    let k = ev_kind(e);
                    let inb = c < g;
                    out += usize::from(inb & (k <= 1));
                    into += usize::from(inb & (k >= 1));
                }
                let x0 = key_pos(ev_key(blk[0]));
                let x1 = key_pos(ev_key(blk[g - 1]));
                if pricer.block_bound(x0, x1, n_l, n_r - out) > best_cost {
                    n_l += into;
                    n_r -= out;
                    i += g;
                    continue;
                }
                until = i + g;
            }
        }
        while i < until {
            let e = events[i];
            let key = ev_key(e);
            let k = ev_kind(e);
            let (mut ends, mut planar) = (usize::from(k == 0), usize::from(k == 1));
            let mut j = i + 1;
            while j < len && ev_key(events[j]) == key {
                let k = ev_kind(events[j]);
                ends += usize::from(k == 0);
                planar += usize::from(k == 1);
                j += 1;
            }
            let starts = (j - i) - ends - planar;
            i = j;
            n_r -= planar + ends;
            let pos = key_pos(key);
            // With no best yet, `best_cost` is +∞ and nothing is skipped.
            if pricer.lower_bound(pos, n_l, n_r, planar) <= best_cost {
                let counts = PlaneCounts {
                    left: n_l,
                    right: n_r,
                    planar,
                };
                let cost = exact.cost(params, pos, counts);
                cost.keep_best(best);
                if cost.cost < best_cost {
                    best_cost = cost.cost;
                    shared.offer(cost.cost);
                }
            }
            n_l += starts + planar;
        }
    }
}

/// The least cost found so far by every sweep of one node (the level
/// passes sweep a node's axes, and the parts of a large node, as separate
/// tasks), which [`sweep_events`] prunes against: a plane whose bound
/// exceeds a cost some plane of the node has is not its best split,
/// whichever task found that plane, so the split found is the same
/// whatever the tasks' timing.
pub(super) trait SharedBest: Sync {
    /// The least cost offered so far (`+∞` when none).
    fn get(&self) -> f64;
    /// Offers the cost of a plane of the node.
    fn offer(&self, cost: f64);
}

/// A sweep that is the only one of its node (the finisher's).
pub(super) struct Alone;

impl SharedBest for Alone {
    #[inline]
    fn get(&self) -> f64 {
        f64::INFINITY
    }
    #[inline]
    fn offer(&self, _: f64) {}
}

/// The bits of a cost, which order as the costs do: costs are sums of
/// non-negative terms when the SAH constants are (the only case in which
/// the sweep prunes at all, see [`Pricer`]), and the bits of non-negative
/// `f64`s order as their values.
impl SharedBest for AtomicU64 {
    #[inline]
    fn get(&self) -> f64 {
        f64::from_bits(self.load(Ordering::Relaxed))
    }
    #[inline]
    fn offer(&self, cost: f64) {
        if cost >= 0.0 {
            self.fetch_min(cost.to_bits(), Ordering::Relaxed);
        }
    }
}

/// Events [`sweep_events`] tries to pass over at once.
const SKIP_BLOCK: usize = 16;

/// A lower bound of [`sah::split_cost`] for one node and axis, cheaper
/// than the cost itself: the surface areas as `2(A + d·B)` for the other
/// two extents' product `A` and sum `B`, divided by one multiplication;
/// `λ` and the planar side decided as `split_cost` decides them (a bound
/// with `λ = min(1, λ_empty)` throughout would need no branch, but prunes
/// so much less that the sweep is slower).
///
/// Both this and `split_cost` sum non-negative `f64` terms, so each is
/// within a relative 2⁻⁴⁸ of the true value; the bound is shrunk by a
/// relative 10⁻¹⁰, far more than both errors together. With a negative or
/// non-finite constant the bound would not be valid, and it is `-∞`
/// (nothing is skipped).
struct Pricer {
    valid: bool,
    k_t: f64,
    k_i: f64,
    lambda_empty: f64,
    /// `2A / SA(V)` plus the flat-split addition
    /// ([`sah::AxisPricer::extra`], a constant of the cell and axis), and
    /// `2B / SA(V)`.
    a2: f64,
    b2: f64,
    lo: f64,
    hi: f64,
    lo32: f32,
    hi32: f32,
}

impl Pricer {
    #[inline]
    fn new(
        params: &sah::SahParams,
        exact: &sah::AxisPricer,
        cell: &Aabb,
        sa: f64,
        axis: usize,
    ) -> Pricer {
        let d = exact.extents();
        let (u, v) = (d[(axis + 1) % 3], d[(axis + 2) % 3]);
        let inv = 1.0 / sa;
        let valid = params.k_t >= 0.0
            && params.k_i >= 0.0
            && params.lambda_empty >= 0.0
            && params.k_t.is_finite()
            && params.k_i.is_finite()
            && params.lambda_empty.is_finite()
            && inv.is_finite();
        Pricer {
            valid,
            k_t: params.k_t,
            k_i: params.k_i,
            lambda_empty: params.lambda_empty,
            a2: 2.0 * u * v * inv + exact.extra(),
            b2: 2.0 * (u + v) * inv,
            lo: f64::from(cell.min[axis]),
            hi: f64::from(cell.max[axis]),
            lo32: cell.min[axis],
            hi32: cell.max[axis],
        }
    }

    /// A lower bound of the cost of every plane of a block of events
    /// from position `x0` to `x1`, where `n_l` references are left of the
    /// first plane and `n_r` right of the last: counts only grow to the
    /// left and shrink to the right along the sweep, `P_L` grows with the
    /// position and `P_R` shrinks, planar references only add terms, and
    /// `λ` is 1 at every plane when both counts are non-zero (both sides
    /// stay occupied), else at least `min(1, λ_empty)`. (With that
    /// minimum throughout, the bound would pass over 13% of black_forest's
    /// events instead of 61%.) Shrunk like [`Pricer::lower_bound`]; `-∞`
    /// when the constants make it invalid.
    #[inline]
    fn block_bound(&self, x0: f32, x1: f32, n_l: usize, n_r: usize) -> f64 {
        if !self.valid {
            return f64::NEG_INFINITY;
        }
        let p_l = self.a2 + (f64::from(x0) - self.lo) * self.b2;
        let p_r = self.a2 + (self.hi - f64::from(x1)) * self.b2;
        // Both sides occupied at every plane: λ = 1.
        let lambda = if n_l > 0 && n_r > 0 {
            1.0
        } else {
            self.lambda_empty.min(1.0)
        };
        let c = self.k_t + self.k_i * lambda * (p_l * n_l as f64 + p_r * n_r as f64);
        c * (1.0 - 1e-10)
    }

    #[inline]
    fn lower_bound(&self, pos: f32, n_l: usize, n_r: usize, n_p: usize) -> f64 {
        if !self.valid {
            return f64::NEG_INFINITY;
        }
        let x = f64::from(pos);
        let p_l = self.a2 + (x - self.lo) * self.b2;
        let p_r = self.a2 + (self.hi - x) * self.b2;
        if n_p == 0 && n_l != 0 && n_r != 0 {
            // The common case: no planar triangles, both sides occupied, so
            // λ = 1 and the planar side does not matter.
            let c = self.k_t + self.k_i * (p_l * n_l as f64 + p_r * n_r as f64);
            return c * (1.0 - 1e-10);
        }
        let on_face = pos == self.lo32 || pos == self.hi32;
        let cost = |nl: usize, nr: usize| {
            let lambda = if (nl == 0 || nr == 0) && !on_face {
                self.lambda_empty
            } else {
                1.0
            };
            self.k_t + self.k_i * lambda * (p_l * nl as f64 + p_r * nr as f64)
        };
        let c = cost(n_l + n_p, n_r).min(cost(n_l, n_r + n_p));
        c * (1.0 - 1e-10)
    }
}
