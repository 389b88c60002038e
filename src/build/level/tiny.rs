//! The best split of a tiny node without events: every candidate plane is
//! counted and priced directly from the references' boxes, many planes at
//! once in vector lanes.
//!
//! A node's candidate planes on an axis are the positions of its events:
//! the `min` and `max` of every reference's box there. The sweep
//! ([`super::best_split::sweep_events`]) walks them in sorted order, keeping running
//! counts; the counts at plane `p` are, by definition,
//!
//! - `N_L(p)`: references whose box starts before `p` (`min < p`),
//! - `N_R(p)`: references whose box ends after `p` (`max > p`),
//! - `N_P(p)`: flat references lying in `p` (`min == max == p`),
//!
//! and these are counted for [`LANES`] planes at once by comparing each
//! box with a vector of positions: `n · ⌈2n / LANES⌉` vector steps per
//! axis for `n` references, with no sort, no event list to keep in order
//! for the children, and no data-dependent branch. Every plane is then
//! priced in the lanes too, by the arithmetic of [`sah::AxisPricer::cost`]
//! ([`sah::CellPricer::ratios`], [`sah::plane_cost`]) inlined into the
//! loop over lanes (IEEE operations give the same bits in a lane as in a
//! scalar register, and Rust never fuses a multiply and an add), so the
//! costs are bit for bit [`sah::split_cost`]'s; a test holds the best
//! split equal to one found plane by plane on every instruction set this
//! CPU has.
//!
//! The three axes' candidates lie packed in one array, each lane priced on
//! its own axis, and every plane is priced before the least cost is looked
//! for: a node of one or two references prices its planes in one vector,
//! not three, and no branch waits on a block's costs (on black_forest this
//! takes a third off the search's cycles against a vector per axis and a
//! test of each block against the best so far).
//!
//! The best split is the same as the three sweeps': [`Split::keep_best`]
//! is a total order, so the order the planes are offered in does not
//! matter, nor does offering a plane shared by several boxes more than
//! once. The sweep does not price a plane whose cost bound exceeds the
//! node's leaf cost; here every plane is priced, which can only change the
//! best split of a node whose every split costs more than its leaf, and
//! [`sah::is_leaf`] makes that node a leaf either way.
//!
//! The work grows as `n²`, so [`super::dfs::Finisher`] uses this only for
//! nodes of at most [`super::LevelOptions::tiny_threshold`] references
//! (at most [`MAX_TINY`]), and builds no events for children that are
//! tiny.

use super::events::PackedBox;
use crate::build::sah::{self, SahParams, Side, Split};
use crate::geom::Aabb;
use crate::simd::SimdLevel;

/// Planes counted and priced at once.
pub const LANES: usize = 16;

/// Planes priced at once: one 512-bit vector of `f64`.
const PRICE_LANES: usize = 8;

/// Costs compared with the least at once, when its planes are looked for.
const SCAN: usize = 32;

/// The largest node the counting sweep takes.
pub const MAX_TINY: usize = 64;

/// Candidate slots: at most two per box, or the faces, per axis, the three
/// axes one after the other, then NaN padding to a whole number of lanes.
const CAND: usize = 3 * (2 * MAX_TINY + 2) + LANES;

/// A finisher's working storage for [`best_split`] (kept, so that no call
/// fills fresh arrays), and the last node's candidates and counts, which
/// [`best_split`] can price again for a node with the same boxes.
pub struct Scratch {
    lo: [f32; MAX_TINY],
    hi: [f32; MAX_TINY],
    flat: [f32; MAX_TINY],
    /// The candidate planes: axis `a`'s at `off[a]..off[a + 1]`, then NaN
    /// padding. Packed without a gap between the axes, so that a node with
    /// few candidates prices them all in one or two vectors.
    cand: [f32; CAND],
    /// Each candidate's counts (left, right, planar).
    counts: [[i32; CAND]; 3],
    /// Where each axis's candidates start, and where they end.
    off: [usize; 4],
    /// Each candidate's cost and whether its planar triangles go right.
    cost: [f64; CAND + SCAN],
    right: [bool; CAND],
    /// Whether `cand`, `counts` and `off` belong to the last node counted.
    counted: bool,
}

impl Default for Scratch {
    fn default() -> Scratch {
        Scratch {
            lo: [0.0; MAX_TINY],
            hi: [0.0; MAX_TINY],
            flat: [0.0; MAX_TINY],
            cand: [f32::NAN; CAND],
            counts: [[0; CAND]; 3],
            off: [0; 4],
            cost: [0.0; CAND + SCAN],
            right: [false; CAND],
            counted: false,
        }
    }
}

/// Whose candidates [`best_split`] prices.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Boxes {
    /// Count the candidates of these boxes (and keep them in the scratch).
    Count,
    /// The boxes are those of the last node counted with this scratch
    /// (only the cell differs): price its candidates and counts again.
    ///
    /// A plane's counts depend on the boxes alone, and the last node's
    /// candidates are every distinct bound of those boxes (each face it
    /// skipped as a box's bound is a candidate once if any box touches
    /// it), which are this node's candidates. The finisher passes this
    /// for the one occupied child of a split that sends every reference,
    /// unclipped, to one side: deep in a tree about 4 in 10 tiny nodes
    /// (a split that cuts off empty space, then the next).
    Same,
}

/// Keeps in `best` the best split of the node whose references have boxes
/// `boxes` (at most [`MAX_TINY`]) in `cell` (surface area `sa > 0`); see
/// the module docs for why it is the sweeps' best split. With
/// [`Boxes::Same`] the boxes are the last counted node's (`boxes` is then
/// only checked for its length).
#[allow(clippy::too_many_arguments)]
pub fn best_split(
    simd: SimdLevel,
    params: &SahParams,
    cell: &Aabb,
    sa: f64,
    boxes: &[PackedBox],
    which: Boxes,
    scratch: &mut Scratch,
    best: &mut Option<Split>,
) {
    assert!(
        boxes.len() <= MAX_TINY,
        "a tiny node has at most {MAX_TINY} references"
    );
    assert!(
        which == Boxes::Count || scratch.counted,
        "no counted node to price again"
    );
    let node = TinyNode {
        params,
        cell,
        sa,
        boxes,
        which,
    };
    crate::simd_dispatch!(simd, |_WIDE| best_split_lanes(&node, scratch, best))
}

/// The arguments of [`best_split`] that describe the node.
struct TinyNode<'a> {
    params: &'a SahParams,
    cell: &'a Aabb,
    sa: f64,
    boxes: &'a [PackedBox],
    which: Boxes,
}

#[inline(always)]
fn best_split_lanes(node: &TinyNode<'_>, scratch: &mut Scratch, best: &mut Option<Split>) {
    let TinyNode {
        params,
        cell,
        sa,
        boxes,
        which,
    } = *node;
    if which == Boxes::Count {
        scratch.off[0] = 0;
        for axis in 0..3 {
            count_axis(cell, boxes, axis, scratch);
        }
        scratch.counted = true;
    }
    price_node(params, cell, sa, scratch, best);
}

/// Fills the scratch's candidates and counts of one axis, after those of
/// the axes before it.
#[inline(always)]
fn count_axis(cell: &Aabb, boxes: &[PackedBox], axis: usize, scratch: &mut Scratch) {
    let n = boxes.len();
    let Scratch {
        lo,
        hi,
        flat,
        cand,
        counts,
        off,
        ..
    } = scratch;
    let start = off[axis];
    // The candidates: every box's min, and its max unless the box is flat
    // there (then it is the same plane). Deep in the tree many boxes are
    // clipped to the cell, so a face of the cell is a candidate once, if
    // any box has an event there, rather than once per such box (the same
    // set of planes, fewer lanes).
    let (face_lo, face_hi) = (cell.min[axis], cell.max[axis]);
    let mut on_face = [false; 2];
    let mut nc = start;
    for (i, b) in boxes.iter().enumerate().take(MAX_TINY) {
        let (l, h) = (b[axis], b[axis + 3]);
        lo[i] = l;
        hi[i] = h;
        flat[i] = if l == h { l } else { f32::NAN };
        cand[nc] = l;
        nc += usize::from(l != face_lo);
        cand[nc] = h;
        nc += usize::from((l != h) & (h != face_hi));
        on_face[0] |= l == face_lo;
        on_face[1] |= h == face_hi;
    }
    cand[nc] = face_lo;
    nc += usize::from(on_face[0]);
    cand[nc] = face_hi;
    nc += usize::from(on_face[1]);
    // The padding only counts nothing: the next axis's candidates (and
    // counts) overwrite it.
    cand[nc..nc + LANES].fill(f32::NAN);
    off[axis + 1] = nc;
    for c0 in (start..nc).step_by(LANES) {
        let pos: &[f32; LANES] = cand[c0..c0 + LANES].try_into().expect("LANES long");
        let got = count_lanes(&lo[..n], &hi[..n], &flat[..n], pos);
        for (dst, src) in counts.iter_mut().zip(&got) {
            dst[c0..c0 + LANES].copy_from_slice(src);
        }
    }
}

/// Prices the scratch's candidates of every axis in `cell`, keeping the
/// best split in `best`.
///
/// The three axes' candidates lie packed one after the other, so a block
/// of lanes may hold planes of two axes (each lane is priced on its own
/// axis). Every block is priced first, into the scratch, with one running
/// minimum in the lanes; only then are the planes of that least cost
/// offered to `best` (ties are broken by [`Split::keep_best`]'s order). So
/// the pricing has no branch between its blocks, where a test of each
/// block's least cost against the best so far made every block wait for
/// the one before.
#[inline(always)]
fn price_node(
    params: &SahParams,
    cell: &Aabb,
    sa: f64,
    scratch: &mut Scratch,
    best: &mut Option<Split>,
) {
    let pricer = LanePricer::new(params, cell, sa);
    let off = scratch.off;
    let total = off[3];
    let mut least = [f64::INFINITY; PRICE_LANES];
    // Priced [`PRICE_LANES`] at a time, so that a node with few candidates
    // does not price a whole vector of padding.
    for h0 in (0..total).step_by(PRICE_LANES) {
        let at = |k: usize| -> [i32; PRICE_LANES] {
            scratch.counts[k][h0..h0 + PRICE_LANES]
                .try_into()
                .expect("PRICE_LANES long")
        };
        let counts = [at(0), at(1), at(2)];
        let pos: &[f32; PRICE_LANES] = scratch.cand[h0..h0 + PRICE_LANES]
            .try_into()
            .expect("PRICE_LANES long");
        let axes = std::array::from_fn(|c| axis_of(&off, h0 + c));
        let (cost, right) = pricer.price(pos, &counts, axes);
        for (c, (m, &v)) in least.iter_mut().zip(&cost).enumerate() {
            let v = if h0 + c < total { v } else { f64::INFINITY };
            *m = if v < *m { v } else { *m };
        }
        scratch.cost[h0..h0 + PRICE_LANES].copy_from_slice(&cost);
        scratch.right[h0..h0 + PRICE_LANES].copy_from_slice(&right);
    }
    let least = least_of(least);
    if best.is_some_and(|b| least > b.cost) {
        return;
    }
    // The slots of that cost: a vector compare per [`SCAN`] slots and a
    // branch per slot found (mostly one), not a branch per slot.
    for h0 in (0..total).step_by(SCAN) {
        let cost: &[f64; SCAN] = scratch.cost[h0..h0 + SCAN].try_into().expect("SCAN long");
        let mut hits = 0u32;
        for (c, &v) in cost.iter().enumerate() {
            hits |= u32::from(v == least) << c;
        }
        let valid = total - h0;
        if valid < SCAN {
            hits &= (1u32 << valid) - 1;
        }
        while hits != 0 {
            let c = h0 + hits.trailing_zeros() as usize;
            hits &= hits - 1;
            let axis = axis_of(&off, c) as u8;
            let planar = if scratch.right[c] {
                Side::Right
            } else {
                Side::Left
            };
            Split {
                cost: least,
                axis,
                pos: scratch.cand[c],
                planar,
            }
            .keep_best(best);
        }
    }
}

/// The axis of candidate slot `c` (slots past the last axis's say 2:
/// they are padding).
#[inline(always)]
fn axis_of(off: &[usize; 4], c: usize) -> u32 {
    u32::from(c >= off[1]) + u32::from(c >= off[2])
}

/// The least of the lanes, as a tree of pairwise minima, which vectorizes
/// where a running minimum is a chain of dependent selects. The costs are
/// sums of non-negative terms (never NaN, never −0), so the order of the
/// comparisons does not change the result.
#[inline(always)]
fn least_of(mut m: [f64; PRICE_LANES]) -> f64 {
    let mut w = PRICE_LANES / 2;
    while w > 0 {
        for c in 0..w {
            m[c] = if m[c + w] < m[c] { m[c + w] } else { m[c] };
        }
        w /= 2;
    }
    m[0]
}

/// The counts ([`sah::PlaneCounts`]: left, right, planar) of the planes `pos`
/// against boxes whose bounds on the axis are `lo`, `hi` and, for a box
/// flat there, `flat` (its position; NaN for other boxes, so that it
/// equals no plane). NaN lanes of `pos` count nothing.
#[inline(always)]
fn count_lanes(lo: &[f32], hi: &[f32], flat: &[f32], pos: &[f32; LANES]) -> [[i32; LANES]; 3] {
    let mut n_l = [0i32; LANES];
    let mut n_r = [0i32; LANES];
    let mut n_p = [0i32; LANES];
    for ((&l, &h), &f) in lo.iter().zip(hi).zip(flat) {
        for c in 0..LANES {
            n_l[c] += i32::from(l < pos[c]);
            n_r[c] += i32::from(h > pos[c]);
            n_p[c] += i32::from(f == pos[c]);
        }
    }
    [n_l, n_r, n_p]
}

/// [`sah::AxisPricer::cost`] for a vector of planes of one cell, each on
/// its own axis: the same two functions ([`sah::CellPricer::ratios`], which
/// is [`sah::AxisPricer`]'s arithmetic with the axis chosen per lane, and
/// [`sah::plane_cost`]), inlined into a loop over lanes.
struct LanePricer<'a> {
    params: &'a SahParams,
    exact: sah::CellPricer,
}

impl<'a> LanePricer<'a> {
    #[inline(always)]
    fn new(params: &'a SahParams, cell: &Aabb, sa: f64) -> LanePricer<'a> {
        LanePricer {
            params,
            exact: sah::CellPricer::new(cell, sa),
        }
    }

    /// Each plane's cost and whether its planar triangles go right; plane
    /// `c` lies at `pos[c]` on axis `axes[c]`.
    #[inline(always)]
    fn price(
        &self,
        pos: &[f32; PRICE_LANES],
        counts: &[[i32; PRICE_LANES]; 3],
        axes: [u32; PRICE_LANES],
    ) -> ([f64; PRICE_LANES], [bool; PRICE_LANES]) {
        let mut cost = [0f64; PRICE_LANES];
        let mut right = [false; PRICE_LANES];
        for c in 0..PRICE_LANES {
            let (p, on_face) = self.exact.ratios(axes[c], pos[c]);
            let [n_l, n_r, n_p] = [0, 1, 2].map(|k| f64::from(counts[k][c]));
            (cost[c], right[c]) = sah::plane_cost(self.params, p, on_face, n_l, n_r, n_p);
        }
        (cost, right)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::sah::{PlaneCounts, split_cost};
    use glam::Vec3;
    use proptest::prelude::*;

    /// Boxes on a coarse grid inside `cell`, so that planes coincide, boxes
    /// are flat and lie on the cell's faces often.
    fn grid_boxes(cell: &Aabb, raw: &[[u8; 6]]) -> Vec<PackedBox> {
        raw.iter()
            .map(|r| {
                let mut b = [0f32; 6];
                for k in 0..3 {
                    let at = |g: u8| {
                        let t = f32::from(g % 5) / 4.0;
                        cell.min[k] + (cell.max[k] - cell.min[k]) * t
                    };
                    let (a, z) = (at(r[k]), at(r[k + 3]));
                    b[k] = a.min(z);
                    b[k + 3] = a.max(z);
                }
                b
            })
            .collect()
    }

    /// The best split by the definition: every candidate plane counted one
    /// reference at a time and priced by `split_cost`.
    fn reference(params: &SahParams, cell: &Aabb, boxes: &[PackedBox]) -> Option<Split> {
        let sa = cell.surface_area();
        let mut best = None;
        for axis in 0..3 {
            for b in boxes {
                for pos in [b[axis], b[axis + 3]] {
                    let counts = PlaneCounts {
                        left: boxes.iter().filter(|o| o[axis] < pos).count(),
                        right: boxes.iter().filter(|o| o[axis + 3] > pos).count(),
                        planar: boxes
                            .iter()
                            .filter(|o| o[axis] == pos && o[axis + 3] == pos)
                            .count(),
                    };
                    split_cost(params, cell, sa, axis, pos, counts).keep_best(&mut best);
                }
            }
        }
        best
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        #[test]
        fn lanes_price_every_plane_as_split_cost(
            lo in prop::array::uniform3(-8.0f32..8.0),
            ext in prop::array::uniform3(prop_oneof![1 => Just(0.0f32), 4 => 0.001f32..10.0]),
            raw in prop::collection::vec(any::<[u8; 6]>(), 1..=MAX_TINY),
            k_t in 0.5f64..40.0,
            k_i in 0.5f64..40.0,
            lambda_empty in 0.1f64..1.5,
        ) {
            let cell = Aabb::new(Vec3::from(lo), Vec3::from(lo) + Vec3::from(ext));
            let sa = cell.surface_area();
            prop_assume!(sa > 0.0);
            let params = SahParams { k_t, k_i, lambda_empty, ..SahParams::default() };
            let boxes = grid_boxes(&cell, &raw);
            let want = reference(&params, &cell, &boxes);
            for simd in SimdLevel::available() {
                let mut got = None;
                let mut scratch = Scratch::default();
                best_split(simd, &params, &cell, sa, &boxes, Boxes::Count, &mut scratch, &mut got);
                prop_assert_eq!(got, want, "{}", simd.name());
            }
        }

        /// A node priced again with [`Boxes::Same`] in a smaller cell that
        /// still holds every box (as after a split that cuts off empty
        /// space, in any direction, or none) gets the best split found by
        /// counting afresh in that cell.
        #[test]
        fn same_boxes_in_a_smaller_cell_price_as_counted(
            lo in prop::array::uniform3(-8.0f32..8.0),
            ext in prop::array::uniform3(prop_oneof![1 => Just(0.0f32), 4 => 0.001f32..10.0]),
            raw in prop::collection::vec(any::<[u8; 6]>(), 1..=MAX_TINY),
            grow in prop::array::uniform6(prop_oneof![1 => Just(0.0f32), 2 => 0.0f32..4.0]),
            k_t in 0.5f64..40.0,
            k_i in 0.5f64..40.0,
        ) {
            let inner = Aabb::new(Vec3::from(lo), Vec3::from(lo) + Vec3::from(ext));
            let boxes = grid_boxes(&inner, &raw);
            let outer = Aabb::new(
                inner.min - Vec3::new(grow[0], grow[1], grow[2]),
                inner.max + Vec3::new(grow[3], grow[4], grow[5]),
            );
            prop_assume!(inner.surface_area() > 0.0);
            let params = SahParams { k_t, k_i, ..SahParams::default() };
            let want = reference(&params, &inner, &boxes);
            for simd in SimdLevel::available() {
                let mut scratch = Scratch::default();
                let mut first = None;
                let sa = outer.surface_area();
                best_split(simd, &params, &outer, sa, &boxes, Boxes::Count, &mut scratch, &mut first);
                let mut got = None;
                let sa = inner.surface_area();
                best_split(simd, &params, &inner, sa, &boxes, Boxes::Same, &mut scratch, &mut got);
                prop_assert_eq!(got, want, "{}", simd.name());
            }
        }
    }
}
