//! The one surface-area heuristic every builder calls (Wald & Havran 2006,
//! §3), with the one tie-break, so that the naive, Wald-Havran and level builders
//! can be asserted to produce the *same* tree.
//!
//! Cost of splitting cell `V` at plane `p` into `V_L`, `V_R` with `N_L`,
//! `N_R` triangles:
//!
//! `C(p) = K_T + K_I · λ(p) · (SA(V_L)/SA(V) · N_L + SA(V_R)/SA(V) · N_R)`
//!
//! with `λ = 0.8` when one side is empty and the plane does not lie on a face
//! of `V`, else 1. A leaf costs `K_I · N`. Triangles lying in the plane
//! ("planar") go to whichever side is cheaper, the left on a tie. A node
//! becomes a leaf when no split costs less than the leaf, when the split
//! does not pay its bytes (below), or at the depth limit. All arithmetic is
//! `f64` in a fixed order.
//!
//! **The price of a split.** The tree's SAH cost is the sum over nodes of
//! `SA(V)/SA(root)` times each node's own cost, so splitting `V` instead of
//! making it a leaf lowers the tree's cost by `SA(V)/SA(root) · (K_I·N −
//! C(p))` (its children taken as leaves), and adds `8 + 2·S` bytes: one
//! node word, and a 16-bit index for each of the `S` references that
//! straddle the plane. With a price `μ > 0` ([`SahParams::split_price`]) a
//! split is taken only when `SA(V)/SA(root) · (K_I·N − C(p)) ≥ μ ·
//! (8 + 2·S) / N_root`: the build minimises cost + μ · bytes per
//! triangle, one node at a time. Deep splits in regions of many
//! overlapping triangles save the tree a sliver of cost for many
//! duplicated references; they are what the price removes (at the default
//! `μ = 0.5` the shared scenes' trees lose 18–65 % of their bytes for at
//! most 0.34 % of SAH cost).
//!
//! **Flat splits.** In a flat cell (zero extent on one axis) the children
//! of a split in its plane have surface areas that sum to the cell's, so
//! `P_L + P_R = 1` (`4/3` in a cube): a reference in both children costs
//! nothing more than in one, any plane that takes one triangle off each
//! side pays, and overlapping coplanar triangles split again at every level
//! down to the depth limit, multiplying their references (1,000 random
//! triangles in `z = 0`: 27,609 references per triangle, 12.9 s). Flat cells
//! also hold axis-aligned walls in real scenes, cut off by planes on a
//! face. So the splits whose overlap `s = P_L + P_R − 1` is below
//! `FLAT_OVERLAP` are priced as if it were `FLAT_PRICED_OVERLAP`, and
//! are taken only while few enough references straddle them
//! (`FLAT_HALVING`, `is_leaf`). Every other split is priced and decided
//! as above.
//!
//! **Tie-break.** Splits are totally ordered by (cost, axis, position,
//! planar side): the lowest cost wins; among equal costs the smaller axis,
//! then the smaller position, then planar-left.

use crate::geom::Aabb;
use std::cmp::Ordering;

/// The SAH constants and the leaf rules.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SahParams {
    /// Cost of one traversal step.
    pub k_t: f64,
    /// Cost of one ray–triangle test.
    pub k_i: f64,
    /// Bonus factor for cutting off empty space.
    pub lambda_empty: f64,
    /// Nodes at this depth (root = 0) become leaves; `None` chooses
    /// `⌊8 + 1.3·log2 N⌋` for `N` input triangles (Havran's rule, as in PBRT).
    /// Either is clamped to [`crate::tree::MAX_DEPTH`].
    pub max_depth: Option<u32>,
    /// `μ`, the SAH cost a split must save (per `SA(root)`) for each byte
    /// per triangle it adds (the module's "price of a split"); 0 takes
    /// every split that costs less than the leaf.
    pub split_price: f64,
    /// `SA(root) / N_root` of the scene the tree is for; `None` takes it
    /// from the build's root cell and triangle count. A build of a part of
    /// a scene (a rebuilt subtree, a cell) sets it to the whole scene's, so
    /// that its nodes are priced as in the whole build.
    pub price_scale: Option<f64>,
}

impl Default for SahParams {
    fn default() -> Self {
        SahParams {
            k_t: 15.0,
            k_i: 20.0,
            lambda_empty: 0.8,
            max_depth: None,
            split_price: DEFAULT_SPLIT_PRICE,
            price_scale: None,
        }
    }
}

/// The default `μ` ([`SahParams::split_price`]): on the shared scenes it
/// takes 18–65 % off the std trees' bytes for at most 0.34 % of SAH cost;
/// primary packets trace as fast, single rays at 0.92–1.18× (μ = 1: 23–71 %
/// fewer bytes, single rays down to 0.88×; docs/perf-notes.md, "The price
/// of a split").
pub const DEFAULT_SPLIT_PRICE: f64 = 0.5;

/// `SA(root) / N_root`, the price scale of a scene whose root cell is
/// `root` and which has `n_tris` triangles.
pub fn price_scale(root: &Aabb, n_tris: usize) -> f64 {
    root.surface_area() / n_tris.max(1) as f64
}

/// The node-independent part of the leaf rules (`is_leaf`) for one build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LeafRule {
    /// Nodes at this depth are leaves.
    pub depth_limit: u32,
    /// `μ · SA(root) / N_root`: a split of cell `V` must lower
    /// `SA(V) · (K_I·N − C(p))` by this much per byte it adds.
    pub byte_price: f64,
}

impl SahParams {
    /// The depth limit for a scene of `n_tris` triangles.
    pub fn depth_limit(&self, n_tris: usize) -> u32 {
        self.max_depth
            .unwrap_or_else(|| (8.0 + 1.3 * (n_tris.max(1) as f64).log2()).floor() as u32)
            .min(crate::tree::MAX_DEPTH)
    }

    /// The leaf rule of a build of a scene of `n_tris` triangles whose
    /// root cell is `root()` (called only when `price_scale` is `None` and
    /// the price is not 0).
    pub fn leaf_rule(&self, n_tris: usize, root: impl FnOnce() -> Aabb) -> LeafRule {
        let byte_price = if self.split_price > 0.0 {
            self.split_price
                * self
                    .price_scale
                    .unwrap_or_else(|| price_scale(&root(), n_tris))
        } else {
            0.0
        };
        LeafRule {
            depth_limit: self.depth_limit(n_tris),
            byte_price,
        }
    }

    /// The cost of a leaf with `n` triangles.
    pub fn leaf_cost(&self, n: usize) -> f64 {
        self.k_i * n as f64
    }
}

/// Which child receives the triangles lying in the split plane.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Side {
    Left,
    Right,
}

/// A candidate split with its cost.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Split {
    pub cost: f64,
    pub axis: u8,
    pub pos: f32,
    pub planar: Side,
}

impl Split {
    /// The documented total order: (cost, axis, position, planar side).
    pub(crate) fn cmp_order(&self, other: &Split) -> Ordering {
        self.cost
            .total_cmp(&other.cost)
            .then(self.axis.cmp(&other.axis))
            .then(self.pos.total_cmp(&other.pos))
            .then(self.planar.cmp(&other.planar))
    }

    /// Keeps the better of `best` and `self`.
    #[inline]
    pub(crate) fn keep_best(self, best: &mut Option<Split>) {
        match best {
            Some(b) if self.cmp_order(b) != Ordering::Less => {}
            _ => *best = Some(self),
        }
    }
}

/// How the triangles of a node lie against one plane.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct PlaneCounts {
    /// Triangles whose box starts left of the plane (`min < pos`), straddlers
    /// included.
    pub left: usize,
    /// Triangles whose box ends right of the plane (`max > pos`), straddlers
    /// included.
    pub right: usize,
    /// Triangles lying in the plane (`min == max == pos`).
    pub planar: usize,
}

/// The cost of splitting `cell` (surface area `sa_cell > 0`) at `axis = pos`.
/// Returns the cheaper assignment of the planar triangles.
#[inline]
pub(crate) fn split_cost(
    params: &SahParams,
    cell: &Aabb,
    sa_cell: f64,
    axis: usize,
    pos: f32,
    counts: PlaneCounts,
) -> Split {
    AxisPricer::new(cell, sa_cell, axis).cost(params, pos, counts)
}

/// [`split_cost`] for the planes of one cell and axis, with the cell's
/// extents converted once (a sweep prices many planes of one node).
///
/// The arithmetic: `SA(V_L) = 2(d_x·d_y + d_y·d_z + d_z·d_x)` in `f64`,
/// each extent `d` the difference of the box's bounds converted to `f64`,
/// so `V_L`'s extent on the split axis is `pos − min` and the others are
/// the cell's; likewise `V_R`. Then `P = SA(child) / sa_cell`.
/// This is [`Aabb::surface_area`] of `cell.split(axis, pos)`'s halves,
/// operation for operation (a test holds the two equal bit for bit), plus
/// [`flat_extra`] for the flat splits (0 for all others).
#[derive(Clone, Copy, Debug)]
pub(crate) struct AxisPricer {
    d: [f64; 3],
    lo: f64,
    hi: f64,
    lo32: f32,
    hi32: f32,
    sa: f64,
    /// What each child's ratio gains from the flat-split rule
    /// ([`flat_extra`]): 0 unless the axis's splits are flat.
    extra: f64,
    axis: usize,
}

impl AxisPricer {
    #[inline]
    pub(crate) fn new(cell: &Aabb, sa_cell: f64, axis: usize) -> AxisPricer {
        let d = [0, 1, 2].map(|k| f64::from(cell.max[k]) - f64::from(cell.min[k]));
        AxisPricer {
            d,
            lo: f64::from(cell.min[axis]),
            hi: f64::from(cell.max[axis]),
            lo32: cell.min[axis],
            hi32: cell.max[axis],
            sa: sa_cell,
            extra: flat_extra(d, sa_cell, axis),
            axis,
        }
    }

    /// The cell's extents in `f64`.
    #[inline]
    pub(crate) fn extents(&self) -> [f64; 3] {
        self.d
    }

    /// What the flat-split rule adds to each child's ratio ([`flat_extra`]).
    #[inline]
    pub(crate) fn extra(&self) -> f64 {
        self.extra
    }

    #[inline(always)]
    fn area(d: [f64; 3]) -> f64 {
        2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
    }

    /// The cost of the plane at `pos` (see [`split_cost`]).
    #[inline]
    pub(crate) fn cost(&self, params: &SahParams, pos: f32, counts: PlaneCounts) -> Split {
        let (p, on_face) = match self.axis {
            0 => self.ratios_on::<0>(pos),
            1 => self.ratios_on::<1>(pos),
            _ => self.ratios_on::<2>(pos),
        };
        let PlaneCounts {
            left,
            right,
            planar,
        } = counts;
        let (cost, planar_right) =
            plane_cost(params, p, on_face, left as f64, right as f64, planar as f64);
        Split {
            cost,
            axis: self.axis as u8,
            pos,
            planar: if planar_right {
                Side::Right
            } else {
                Side::Left
            },
        }
    }

    /// The children's surface-area ratios `[P_L, P_R]` of the plane at
    /// `pos` on axis `AXIS` (which must be this pricer's axis) and whether
    /// the plane lies on a face of the cell. Generic over the axis so that
    /// a loop over many planes vectorizes (`build::level::tiny`).
    #[inline(always)]
    pub(crate) fn ratios_on<const AXIS: usize>(&self, pos: f32) -> ([f64; 2], bool) {
        debug_assert_eq!(AXIS, self.axis);
        let x = f64::from(pos);
        let (mut dl, mut dr) = (self.d, self.d);
        dl[AXIS] = x - self.lo;
        dr[AXIS] = self.hi - x;
        let p_l = Self::area(dl) / self.sa + self.extra;
        let p_r = Self::area(dr) / self.sa + self.extra;
        let on_face = pos == self.lo32 || pos == self.hi32;
        ([p_l, p_r], on_face)
    }
}

/// Splits whose overlap `s` ([`split_overlap`]) is below this are *flat*:
/// a flat cell's splits in its plane (`s = 0`), and those of cells a
/// thousand times thinner than they are wide.
pub(crate) const FLAT_OVERLAP: f64 = 1e-3;

/// The overlap flat splits are priced with: each child's ratio gains
/// `(FLAT_PRICED_OVERLAP − s) / 2`, so that a reference in both children
/// costs what it costs in a slab ten times thinner than wide. With the true
/// ratios it costs nothing, and 1,000 random triangles in one plane make
/// 27,609 references per triangle; priced so (without [`FLAT_HALVING`]),
/// 117, with an SAH cost of 2,285 against the unbounded tree's 1,794.
pub(crate) const FLAT_PRICED_OVERLAP: f64 = 0.1;

/// A flat split is taken only if at most `n / 2^⌊depth / FLAT_HALVING⌋` of
/// the node's `n` references straddle it ([`is_leaf`]), so that flat splits
/// at most multiply the references per triangle by
/// `∏_d (1 + 2^−⌊d/6⌋)` over the depths `d` of a path (about 11,700 over
/// all depths; 12 to 27 measured). Pricing alone still lets a fan of
/// slivers meeting in one corner blow up (10⁴ corners: 3,121 references
/// per triangle, 19 s); with this, 26.5 (0.56 s; 10⁵ corners 4.4 s).
pub(crate) const FLAT_HALVING: u32 = 6;

/// The overlap `s = P_L + P_R − 1` of every split on `axis` of a cell with
/// extents `d` and surface area `sa`: the children's surface areas sum to
/// the cell's plus twice the plane's cross-section `A_⊥`, so
/// `s = 2·A_⊥ / SA` whatever the position (`1/3` in a cube, `0` in a flat
/// cell; `NaN` for a cell without area, which is never split).
#[inline]
pub(crate) fn split_overlap(d: [f64; 3], sa: f64, axis: usize) -> f64 {
    2.0 * (d[(axis + 1) % 3] * d[(axis + 2) % 3]) / sa
}

/// What the flat-split rule adds to each child's surface-area ratio for the
/// splits on `axis` of a cell with extents `d` and surface area `sa`:
/// `(FLAT_PRICED_OVERLAP − s) / 2` for a flat split, else 0.
#[inline]
pub(crate) fn flat_extra(d: [f64; 3], sa: f64, axis: usize) -> f64 {
    if is_flat_split(d, sa, axis) {
        (FLAT_PRICED_OVERLAP - split_overlap(d, sa, axis)) / 2.0
    } else {
        0.0
    }
}

/// Whether the splits on `axis` of a cell with extents `d` and surface
/// area `sa` are flat: their overlap is below [`FLAT_OVERLAP`] (never for
/// a cell without area, whose overlap is `NaN`).
#[inline]
pub(crate) fn is_flat_split(d: [f64; 3], sa: f64, axis: usize) -> bool {
    split_overlap(d, sa, axis) < FLAT_OVERLAP
}

/// Whether a reference whose box spans `lo..=hi` on the split axis
/// straddles the plane at `pos`, going to both children (as
/// [`crate::build::classify`] places it).
#[inline]
pub(crate) fn straddles(lo: f32, hi: f32, pos: f32) -> bool {
    lo < pos && pos < hi
}

/// [`AxisPricer::ratios_on`] for planes whose axis varies from one call to
/// the next: the same operations on the chosen axis's bounds, which are
/// picked by selects, so that a loop over planes of several axes
/// vectorizes (`build::level::tiny` packs a small node's three axes into
/// the same vectors).
#[derive(Clone, Copy, Debug)]
pub(crate) struct CellPricer([AxisPricer; 3]);

impl CellPricer {
    #[inline]
    pub(crate) fn new(cell: &Aabb, sa_cell: f64) -> CellPricer {
        CellPricer([0, 1, 2].map(|axis| AxisPricer::new(cell, sa_cell, axis)))
    }

    /// `[P_L, P_R]` of the plane at `pos` on axis `axis` (0, 1, or 2 for
    /// any other value), and whether it lies on a face of the cell.
    #[inline(always)]
    pub(crate) fn ratios(&self, axis: u32, pos: f32) -> ([f64; 2], bool) {
        /// Element `axis` (the last for any larger value), by selects.
        #[inline(always)]
        fn pick<T: Copy>(axis: u32, v: [T; 3]) -> T {
            match axis {
                0 => v[0],
                1 => v[1],
                _ => v[2],
            }
        }
        let a = &self.0;
        let x = f64::from(pos);
        let (l, r) = (
            x - pick(axis, a.map(|a| a.lo)),
            pick(axis, a.map(|a| a.hi)) - x,
        );
        // Every pricer holds the cell's extents and surface area.
        let (d, sa) = (a[0].d, a[0].sa);
        let with = |v: f64| [0, 1, 2].map(|j| if j == axis.min(2) { v } else { d[j as usize] });
        let extra = pick(axis, a.map(|a| a.extra));
        let p_l = AxisPricer::area(with(l)) / sa + extra;
        let p_r = AxisPricer::area(with(r)) / sa + extra;
        let on_face = pos == pick(axis, a.map(|a| a.lo32)) || pos == pick(axis, a.map(|a| a.hi32));
        ([p_l, p_r], on_face)
    }
}

/// The cost of a split with the children's surface-area ratios
/// `p = [P_L, P_R]` and `n_l`, `n_r`, `n_p` triangles left, right and in
/// the plane (whole numbers, as `f64`): `λ`, the cost of each planar
/// assignment, and the cheaper one, as `(cost, planar triangles go
/// right)`. Branch-free in effect (selects only), so that a loop over
/// many planes vectorizes; every builder's pricing ends here.
#[inline(always)]
pub(crate) fn plane_cost(
    params: &SahParams,
    p: [f64; 2],
    on_face: bool,
    n_l: f64,
    n_r: f64,
    n_p: f64,
) -> (f64, bool) {
    let cost = |nl: f64, nr: f64| {
        let lambda = if (nl == 0.0 || nr == 0.0) && !on_face {
            params.lambda_empty
        } else {
            1.0
        };
        params.k_t + params.k_i * lambda * (p[0] * nl + p[1] * nr)
    };
    let c_left = cost(n_l + n_p, n_r);
    let c_right = cost(n_l, n_r + n_p);
    let left = c_left <= c_right;
    (if left { c_left } else { c_right }, !left)
}

/// Whether a node of `n` references in `cell` becomes a leaf, given its
/// best split: when there is none, at the depth limit, when the split
/// costs at least the leaf, when it does not pay its bytes
/// ([`LeafRule::byte_price`]; the module's "price of a split"), or when
/// it is a flat split that more than `n / 2^⌊depth / FLAT_HALVING⌋`
/// references straddle ([`FLAT_HALVING`]). `straddlers` counts the
/// references that straddle the split, and is called only for a split
/// that costs less than the leaf, and at most once.
///
/// Each rule depends on the node alone, so every builder decides alike; a
/// stricter rule than "costs at least the leaf" keeps every sweep's
/// pruning valid (a pruned plane costs more than the best, or at least the
/// leaf).
pub(crate) fn is_leaf(
    params: &SahParams,
    best: Option<&Split>,
    n: usize,
    depth: u32,
    rule: &LeafRule,
    cell: &Aabb,
    straddlers: impl FnOnce(&Split) -> usize,
) -> bool {
    match best {
        None => true,
        Some(s) => {
            let leaf = params.leaf_cost(n);
            if depth >= rule.depth_limit || s.cost >= leaf {
                return true;
            }
            let sa = cell.surface_area();
            let d = [0, 1, 2].map(|k| f64::from(cell.max[k]) - f64::from(cell.min[k]));
            let flat = is_flat_split(d, sa, s.axis as usize);
            if !flat && rule.byte_price == 0.0 {
                return false;
            }
            let st = straddlers(s);
            if sa * (leaf - s.cost) < rule.byte_price * (8 + 2 * st as u64) as f64 {
                return true;
            }
            let halvings = depth / FLAT_HALVING;
            flat && (st as u128) << halvings > n as u128
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    const NO_PRICE: LeafRule = LeafRule {
        depth_limit: 40,
        byte_price: 0.0,
    };

    fn pc(left: usize, right: usize, planar: usize) -> PlaneCounts {
        PlaneCounts {
            left,
            right,
            planar,
        }
    }

    #[test]
    fn empty_space_bonus_only_off_the_faces() {
        let p = SahParams::default();
        let cell = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let sa = cell.surface_area();
        // One triangle on the right; cut off the empty left half.
        let s = split_cost(&p, &cell, sa, 0, 0.5, pc(0, 1, 0));
        let expect = 15.0 + 20.0 * 0.8 * (4.0 / 6.0);
        assert_eq!(s.cost, expect);
        // A plane on the face gets no bonus.
        let s = split_cost(&p, &cell, sa, 0, 0.0, pc(0, 1, 0));
        assert_eq!(s.cost, 15.0 + 20.0 * 1.0);
    }

    #[test]
    fn planar_goes_to_cheaper_side() {
        let p = SahParams::default();
        let cell = Aabb::new(Vec3::ZERO, Vec3::new(4.0, 1.0, 1.0));
        let sa = cell.surface_area();
        // Plane near the left face: planar triangles are cheaper on the left.
        let s = split_cost(&p, &cell, sa, 0, 1.0, pc(3, 3, 2));
        assert_eq!(s.planar, Side::Left);
        let s = split_cost(&p, &cell, sa, 0, 3.0, pc(3, 3, 2));
        assert_eq!(s.planar, Side::Right);
    }

    #[test]
    fn tie_break_is_total() {
        let a = Split {
            cost: 1.0,
            axis: 0,
            pos: 2.0,
            planar: Side::Left,
        };
        let b = Split {
            cost: 1.0,
            axis: 1,
            pos: 0.0,
            planar: Side::Left,
        };
        let c = Split {
            cost: 1.0,
            axis: 0,
            pos: 2.0,
            planar: Side::Right,
        };
        assert_eq!(a.cmp_order(&b), Ordering::Less);
        assert_eq!(a.cmp_order(&c), Ordering::Less);
        let mut best = None;
        b.keep_best(&mut best);
        c.keep_best(&mut best);
        a.keep_best(&mut best);
        assert_eq!(best, Some(a));
    }

    #[test]
    fn a_split_must_pay_its_bytes() {
        let p = SahParams::default();
        let cube = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let split = Split {
            cost: 150.0,
            axis: 0,
            pos: 0.5,
            planar: Side::Left,
        };
        // SA 6 times the saving 200 − 150 is 300; 5 straddlers add
        // 8 + 2·5 = 18 bytes, so the split pays up to a price of 300/18.
        let rule = |byte_price| LeafRule {
            depth_limit: 40,
            byte_price,
        };
        assert!(!is_leaf(&p, Some(&split), 10, 3, &rule(16.0), &cube, |_| 5));
        assert!(is_leaf(&p, Some(&split), 10, 3, &rule(17.0), &cube, |_| 5));
        assert!(!is_leaf(&p, Some(&split), 10, 3, &rule(17.0), &cube, |_| 4));
        // Without a price the straddlers are not counted.
        let never = |_: &Split| -> usize { unreachable!() };
        assert!(!is_leaf(&p, Some(&split), 10, 3, &NO_PRICE, &cube, never));
    }

    #[test]
    fn the_price_scale_is_the_root_area_per_triangle() {
        let root = Aabb::new(Vec3::ZERO, Vec3::new(1.0, 2.0, 3.0));
        let p = SahParams {
            split_price: 2.0,
            ..SahParams::default()
        };
        assert_eq!(price_scale(&root, 11), 22.0 / 11.0);
        assert_eq!(p.leaf_rule(11, || root).byte_price, 4.0);
        let given = SahParams {
            price_scale: Some(0.5),
            ..p
        };
        assert_eq!(given.leaf_rule(11, || unreachable!()).byte_price, 1.0);
        let free = SahParams {
            split_price: 0.0,
            ..p
        };
        assert_eq!(free.leaf_rule(11, || unreachable!()).byte_price, 0.0);
    }

    #[test]
    fn depth_limit_rule() {
        let p = SahParams::default();
        assert_eq!(p.depth_limit(0), 8);
        assert_eq!(p.depth_limit(1024), 21);
        assert_eq!(
            SahParams {
                max_depth: Some(3),
                ..p
            }
            .depth_limit(1024),
            3
        );
    }

    #[test]
    fn flat_splits_are_priced_with_the_flat_overlap() {
        let p = SahParams::default();
        let cube = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let d = |c: &Aabb| [0, 1, 2].map(|k| f64::from(c.max[k]) - f64::from(c.min[k]));
        assert_eq!(split_overlap(d(&cube), cube.surface_area(), 0), 1.0 / 3.0);
        assert_eq!(flat_extra(d(&cube), cube.surface_area(), 0), 0.0);
        let flat = Aabb::new(Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0));
        let sa = flat.surface_area();
        assert_eq!(split_overlap(d(&flat), sa, 0), 0.0);
        // Splits across the flat axis are not flat splits.
        assert_eq!(flat_extra(d(&flat), sa, 2), 0.0);
        // Every triangle in both halves: no gain with the true ratios, a
        // loss of the priced overlap with the rule.
        let s = split_cost(&p, &flat, sa, 0, 0.5, pc(10, 10, 0));
        assert_eq!(s.cost, 15.0 + 20.0 * (0.5 + 0.05) * 20.0);
        assert!(s.cost > p.leaf_cost(10));
    }

    #[test]
    fn flat_split_is_taken_only_while_few_references_straddle() {
        let p = SahParams::default();
        let flat = Aabb::new(Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0));
        let split = |axis| Split {
            cost: 100.0,
            axis,
            pos: 0.5,
            planar: Side::Left,
        };
        let n = 64;
        // At depth 0 up to all of them, at depth 6 up to half, at 12 a quarter.
        for (depth, allowed) in [(0, 64), (5, 64), (6, 32), (12, 16)] {
            assert!(!is_leaf(
                &p,
                Some(&split(0)),
                n,
                depth,
                &NO_PRICE,
                &flat,
                |_| { allowed }
            ));
            assert!(is_leaf(
                &p,
                Some(&split(0)),
                n,
                depth,
                &NO_PRICE,
                &flat,
                |_| allowed + 1
            ));
        }
        // Not a flat split (across the flat axis, or in a cube): not counted.
        let cube = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let never = |_: &Split| -> usize { panic!("counted a split that is not flat") };
        for (s, cell) in [(split(2), &flat), (split(0), &cube)] {
            assert!(!is_leaf(&p, Some(&s), n, 12, &NO_PRICE, cell, never));
        }
        // A split that does not pay is a leaf without counting.
        assert!(is_leaf(
            &p,
            Some(&Split {
                cost: 2000.0,
                ..split(0)
            }),
            n,
            0,
            &NO_PRICE,
            &flat,
            never
        ));
    }

    /// `AxisPricer` against the definition spelled out with
    /// The module docs' formula as written there, with the ratios given:
    /// the oracle of `AxisPricer::cost` (and so of `plane_cost`).
    fn priced_textbook(
        params: &SahParams,
        axis: usize,
        pos: f32,
        p: [f64; 2],
        on_face: bool,
        counts: PlaneCounts,
    ) -> Split {
        let PlaneCounts {
            left: n_l,
            right: n_r,
            planar: n_p,
        } = counts;
        let cost = |nl: usize, nr: usize| {
            let lambda = if (nl == 0 || nr == 0) && !on_face {
                params.lambda_empty
            } else {
                1.0
            };
            params.k_t + params.k_i * lambda * (p[0] * nl as f64 + p[1] * nr as f64)
        };
        let (c_left, c_right) = (cost(n_l + n_p, n_r), cost(n_l, n_r + n_p));
        if c_left <= c_right {
            Split {
                cost: c_left,
                axis: axis as u8,
                pos,
                planar: Side::Left,
            }
        } else {
            Split {
                cost: c_right,
                axis: axis as u8,
                pos,
                planar: Side::Right,
            }
        }
    }

    /// `Aabb::split` and `Aabb::surface_area`, bit for bit, on cells and
    /// planes from a small grid (faces, flat cells) and arbitrary ones.
    #[test]
    fn axis_and_cell_pricers_are_surface_area_of_the_halves() {
        let mut next = crate::build::xorshift(0x9E37_79B9_7F4A_7C15);
        let coord = |next: &mut dyn FnMut() -> u64| {
            if next().is_multiple_of(2) {
                (next() % 9) as f32 * 0.25 - 1.0
            } else {
                (next() % 1_000_000) as f32 * 1.7e-6 - 0.9
            }
        };
        let params = SahParams::default();
        for _ in 0..20_000 {
            let a = Vec3::new(coord(&mut next), coord(&mut next), coord(&mut next));
            let b = Vec3::new(coord(&mut next), coord(&mut next), coord(&mut next));
            let cell = Aabb::new(a.min(b), a.max(b));
            let sa = cell.surface_area();
            if sa <= 0.0 {
                continue;
            }
            let axis = (next() % 3) as usize;
            let t = (next() % 1001) as f32 / 1000.0;
            let pos = cell.min[axis] + (cell.max[axis] - cell.min[axis]) * t;
            let pos = pos.clamp(cell.min[axis], cell.max[axis]) + 0.0;
            let counts = pc(
                (next() % 5) as usize,
                (next() % 5) as usize,
                (next() % 3) as usize,
            );
            let (l, r) = cell.split(axis, pos);
            let d = [0, 1, 2].map(|k| f64::from(cell.max[k]) - f64::from(cell.min[k]));
            let extra = flat_extra(d, sa, axis);
            let p = [l.surface_area() / sa + extra, r.surface_area() / sa + extra];
            let on_face = pos == cell.min[axis] || pos == cell.max[axis];
            let want = priced_textbook(&params, axis, pos, p, on_face, counts);
            let got = AxisPricer::new(&cell, sa, axis).cost(&params, pos, counts);
            assert_eq!(got.cost.to_bits(), want.cost.to_bits());
            assert_eq!(got.planar, want.planar);
            // The per-call axis of `CellPricer` gives the same ratios.
            let (q, q_face) = CellPricer::new(&cell, sa).ratios(axis as u32, pos);
            assert_eq!(q.map(f64::to_bits), p.map(f64::to_bits));
            assert_eq!(q_face, on_face);
        }
    }
}
