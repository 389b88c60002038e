//! Clipping a triangle to a box: the exact bounds of `triangle ∩ box`, the
//! candidate planes of perfect splits (Havran 2000; Wald & Havran 2006 §4.4).
//!
//! The polygon is clipped in `f64` (Sutherland–Hodgman against the six
//! planes); the coordinate on the clipping axis is set to the plane exactly,
//! the others are interpolated. Its bounds are rounded outward to `f32` and
//! intersected with the box and with the triangle's own bounds, so the result
//! is conservative (it contains every point of the triangle inside the box)
//! and nests inside the box.
//!
//! [`clip_split`], which every builder's straddlers go through, runs in
//! AVX-512 lanes where the CPU has them (`lanes`), with the same bits as
//! the scalar code (a proptest holds both equal to the textbook form kept
//! in the tests). On stk_black_forest the lanes take a clip of a random
//! straddler from 161 to 123 ns.

use super::{Aabb, f32_round_down, f32_round_up};
use crate::simd::SimdLevel;
use glam::Vec3;

/// Sutherland–Hodgman on a triangle and six planes yields at most 9 vertices.
const MAX_POLY: usize = 9;

/// The polygon's storage: one slot more than it can hold, because the
/// clipping loop writes every candidate vertex and only advances past the
/// ones it keeps (no data-dependent branch), and repeats the first vertex
/// after the last.
const CAP: usize = MAX_POLY + 1;

#[derive(Clone, Copy)]
struct Polygon {
    v: [[f64; 3]; CAP],
    n: usize,
}

impl Polygon {
    const EMPTY: Polygon = Polygon {
        v: [[0.0; 3]; CAP],
        n: 0,
    };

    #[inline]
    fn triangle(tri: &[Vec3; 3]) -> Polygon {
        let mut poly = Polygon::EMPTY;
        for (i, p) in tri.iter().enumerate() {
            poly.v[i] = [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
        }
        poly.n = 3;
        poly
    }

    /// Writes into `out` the part with `p[AXIS] >= plane` (`ABOVE`) or
    /// `p[AXIS] <= plane`: Sutherland–Hodgman, walking the edges
    /// `v[i] → v[i + 1]` (the last one closing the loop) and keeping each
    /// inside start point and each crossing.
    ///
    /// Branch-free: every edge's start point and crossing are written at
    /// the output cursor, which advances only past the kept ones (the
    /// crossing of an edge that does not cross is computed and dropped).
    /// A polygon that would exceed [`MAX_POLY`] vertices keeps its first
    /// ones (it cannot happen for a triangle and six planes; the cap keeps
    /// the writes in bounds regardless).
    #[inline(always)]
    fn clip_into<const AXIS: usize, const ABOVE: bool>(&mut self, plane: f64, out: &mut Polygon) {
        let inside = |p: &[f64; 3]| {
            if ABOVE {
                p[AXIS] >= plane
            } else {
                p[AXIS] <= plane
            }
        };
        let n = self.n.min(MAX_POLY);
        let mut k = 0;
        if n > 0 {
            // The first vertex again after the last (the spare slot), so
            // the closing edge needs no wrap-around index.
            self.v[n] = self.v[0];
            let mut a = self.v[0];
            let mut ina = inside(&a);
            for i in 0..n {
                let b = self.v[i + 1];
                let inb = inside(&b);
                out.v[k] = a;
                k = (k + usize::from(ina)).min(MAX_POLY);
                out.v[k] = crossing(&a, &b, AXIS, plane);
                k = (k + usize::from(ina != inb)).min(MAX_POLY);
                a = b;
                ina = inb;
            }
        }
        out.n = k;
    }

    /// Clips to the planes of `bx` that `tb` (the polygon's bounds) crosses,
    /// in the order x min, x max, y min, y max, z min, z max. `scratch` is
    /// working storage; the result is in `self` or in `scratch`, whichever
    /// is returned (no copy back).
    #[inline]
    fn clip_to_box<'p>(
        &'p mut self,
        tb: &Aabb,
        bx: &Aabb,
        scratch: &'p mut Polygon,
    ) -> &'p Polygon {
        let mut src = self;
        let mut dst = scratch;
        macro_rules! plane {
            ($axis:literal) => {
                if tb.min[$axis] < bx.min[$axis] {
                    src.clip_into::<$axis, true>(f64::from(bx.min[$axis]), dst);
                    std::mem::swap(&mut src, &mut dst);
                }
                if tb.max[$axis] > bx.max[$axis] {
                    src.clip_into::<$axis, false>(f64::from(bx.max[$axis]), dst);
                    std::mem::swap(&mut src, &mut dst);
                }
            };
        }
        plane!(0);
        if src.n > 0 {
            plane!(1);
        }
        if src.n > 0 {
            plane!(2);
        }
        src
    }
}

/// The point of edge `a → b` on the plane `p[axis] = plane` (the edge
/// crosses it): the coordinate on `axis` is the plane exactly, the others
/// are interpolated from `a`.
#[inline(always)]
fn crossing(a: &[f64; 3], b: &[f64; 3], axis: usize, plane: f64) -> [f64; 3] {
    let t = (plane - a[axis]) / (b[axis] - a[axis]);
    let mut p = [0.0; 3];
    for k in 0..3 {
        p[k] = a[k] + (b[k] - a[k]) * t;
    }
    p[axis] = plane;
    p
}

/// Running `f64` bounds of points.
#[derive(Clone, Copy)]
struct Bounds64 {
    lo: [f64; 3],
    hi: [f64; 3],
}

impl Bounds64 {
    const EMPTY: Bounds64 = Bounds64 {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };

    #[inline]
    fn add(&mut self, p: &[f64; 3]) {
        for (k, &x) in p.iter().enumerate() {
            self.lo[k] = self.lo[k].min(x);
            self.hi[k] = self.hi[k].max(x);
        }
    }

    /// Adds `p` when `keep`, without a branch on `keep`. The comparisons
    /// ignore the sign of zero, which [`Bounds64::finish`] drops anyway,
    /// so the bounds do not depend on the order points are added in.
    #[inline(always)]
    fn add_if(&mut self, p: &[f64; 3], keep: bool) {
        for (k, &x) in p.iter().enumerate() {
            let lo = if keep { x } else { f64::INFINITY };
            let hi = if keep { x } else { f64::NEG_INFINITY };
            self.lo[k] = if lo < self.lo[k] { lo } else { self.lo[k] };
            self.hi[k] = if hi > self.hi[k] { hi } else { self.hi[k] };
        }
    }

    /// Rounded outward to `f32`, intersected with `bx` and `tb`; `None`
    /// when empty. `-0.0` bounds become `+0.0`, so that equal planes have
    /// equal bits in every builder.
    #[inline(always)]
    fn finish(&self, bx: &Aabb, tb: &Aabb) -> Option<Aabb> {
        // Nothing was added (no NaN reaches here: scenes are validated).
        if self.lo[0] > self.hi[0] {
            return None;
        }
        let (mut min, mut max) = ([0.0f32; 3], [0.0f32; 3]);
        let mut empty = false;
        for k in 0..3 {
            // `max`/`min` by comparison: exact, and the sign of a zero is
            // dropped below.
            let lo = f32_round_down(self.lo[k]);
            let lo = if bx.min[k] > lo { bx.min[k] } else { lo };
            let lo = if tb.min[k] > lo { tb.min[k] } else { lo };
            let hi = f32_round_up(self.hi[k]);
            let hi = if bx.max[k] < hi { bx.max[k] } else { hi };
            let hi = if tb.max[k] < hi { tb.max[k] } else { hi };
            empty |= lo > hi;
            min[k] = lo + 0.0;
            max[k] = hi + 0.0;
        }
        if empty {
            None
        } else {
            Some(Aabb::new(Vec3::from(min), Vec3::from(max)))
        }
    }
}

/// The conservative bounds of `tri ∩ bx`, or `None` when they do not meet.
///
/// When the triangle lies inside the box its own bounds are returned
/// unchanged (exactly, no rounding).
pub fn clip_triangle(tri: &[Vec3; 3], bx: &Aabb) -> Option<Aabb> {
    let tb = Aabb::of_triangle(tri);
    if bx.contains(&tb) {
        return Some(tb);
    }
    if !bx.overlaps(&tb) {
        return None;
    }
    let mut poly = Polygon::triangle(tri);
    let mut scratch = Polygon::EMPTY;
    let poly = poly.clip_to_box(&tb, bx, &mut scratch);
    let mut b = Bounds64::EMPTY;
    for p in &poly.v[..poly.n] {
        b.add(p);
    }
    b.finish(bx, &tb)
}

/// The conservative bounds of the triangle in the two halves of `cell`
/// split by the plane `axis = pos`: `[tri ∩ left, tri ∩ right]` with
/// `(left, right) = cell.split(axis, pos)`, each `None` when they do not
/// meet.
///
/// The polygon `tri ∩ cell` is clipped once; one pass over its edges then
/// collects both halves' vertices (the vertices on each side and the
/// crossings of the plane), so a straddler costs one box clip instead of
/// two. The results are what [`clip_triangle`] would give up to the
/// rounding of the `f64` arithmetic, which both round outward: both are
/// conservative and nest inside their box.
///
/// `known` is a box that contains `tri ∩ cell` and lies in `cell`: the
/// reference's own clipped box, in a builder. A face of the cell that
/// `known` does not reach is not clipped against, because it cuts nothing:
/// if clipping to the other planes left a point beyond that face, the
/// segment from it to a point of `tri ∩ cell` would leave the cell first
/// through a face `known` does not reach, at a point of `tri ∩ cell`,
/// which `known` contains. (So only the faces the polygon touches are
/// clipped: deep in a tree, where triangles are large against their cells,
/// that skips about a third of the planes the triangle's own bounds
/// cross.) With `known = cell` every face the triangle crosses is clipped.
///
/// On a CPU with AVX-512 the polygon is clipped in vector lanes
/// ([`clip_split_on`]), with the same results bit for bit.
#[inline]
pub fn clip_split(
    tri: &[Vec3; 3],
    cell: &Aabb,
    known: &Aabb,
    axis: usize,
    pos: f32,
) -> [Option<Aabb>; 2] {
    #[cfg(target_arch = "x86_64")]
    let lanes = std::arch::is_x86_feature_detected!("avx512f");
    #[cfg(not(target_arch = "x86_64"))]
    let lanes = false;
    clip_split_checked(lanes, tri, cell, known, axis, pos)
}

/// [`clip_split`] on a chosen instruction set: [`SimdLevel::Avx512`]
/// clips in vector lanes, every other level runs the scalar
/// code. Both give the same bits.
///
/// # Panics
/// On [`SimdLevel::Avx512`] when this CPU lacks avx512f.
pub fn clip_split_on(
    simd: SimdLevel,
    tri: &[Vec3; 3],
    cell: &Aabb,
    known: &Aabb,
    axis: usize,
    pos: f32,
) -> [Option<Aabb>; 2] {
    let lanes = simd == SimdLevel::Avx512;
    #[cfg(target_arch = "x86_64")]
    assert!(
        !lanes || std::arch::is_x86_feature_detected!("avx512f"),
        "AVX-512 clipping on a CPU without avx512f"
    );
    clip_split_checked(lanes, tri, cell, known, axis, pos)
}

/// [`clip_split`] in lanes when `lanes` (which the callers have checked:
/// the CPU has avx512f), else scalar.
#[inline(always)]
fn clip_split_checked(
    lanes: bool,
    tri: &[Vec3; 3],
    cell: &Aabb,
    known: &Aabb,
    axis: usize,
    pos: f32,
) -> [Option<Aabb>; 2] {
    #[cfg(target_arch = "x86_64")]
    if lanes {
        // SAFETY: `lanes` is set only when the CPU reports avx512f.
        let got = unsafe {
            match axis {
                0 => lanes::clip_split_axis::<0>(tri, cell, known, pos),
                1 => lanes::clip_split_axis::<1>(tri, cell, known, pos),
                _ => lanes::clip_split_axis::<2>(tri, cell, known, pos),
            }
        };
        // `None`: the polygon outgrew the lanes (9 vertices, which needs
        // six clipping planes); the scalar code takes it.
        if let Some(got) = got {
            return got;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = lanes;
    match axis {
        0 => clip_split_axis::<0>(tri, cell, known, pos),
        1 => clip_split_axis::<1>(tri, cell, known, pos),
        _ => clip_split_axis::<2>(tri, cell, known, pos),
    }
}

/// The planes [`clip_split`] clips to, as a box for
/// [`Polygon::clip_to_box`]: the triangle's bounds `tb`, moved onto each
/// face of `cell` that `known` does not reach (so that it does not cross
/// it).
#[inline(always)]
fn crossed(tb: &Aabb, cell: &Aabb, known: &Aabb) -> Aabb {
    let mut c = *tb;
    for k in 0..3 {
        if known.min[k] > cell.min[k] {
            c.min[k] = cell.min[k];
        }
        if known.max[k] < cell.max[k] {
            c.max[k] = cell.max[k];
        }
    }
    c
}

#[inline(always)]
fn clip_split_axis<const AXIS: usize>(
    tri: &[Vec3; 3],
    cell: &Aabb,
    known: &Aabb,
    pos: f32,
) -> [Option<Aabb>; 2] {
    let tb = Aabb::of_triangle(tri);
    if !cell.overlaps(&tb) {
        return [None, None];
    }
    let mut poly = Polygon::triangle(tri);
    let mut scratch = Polygon::EMPTY;
    let poly = poly.clip_to_box(&crossed(&tb, cell, known), cell, &mut scratch);
    let (left, right) = cell.split(AXIS, pos);
    let plane = f64::from(pos);
    let mut side = [Bounds64::EMPTY; 2];
    let n = poly.n.min(MAX_POLY);
    if n > 0 {
        // Edge a → b as Sutherland–Hodgman walks it (from v[n-1] to v[0]
        // first), so crossings are computed from the same end. Branch-free
        // like `clip_into`: each side adds the start point or the crossing
        // when it keeps it, else +∞/−∞ bounds that change nothing.
        let mut a = poly.v[n - 1];
        for i in 0..n {
            let b = poly.v[i];
            let (al, ar) = (a[AXIS] <= plane, a[AXIS] >= plane);
            let (bl, br) = (b[AXIS] <= plane, b[AXIS] >= plane);
            let q = crossing(&a, &b, AXIS, plane);
            side[0].add_if(&a, al);
            side[1].add_if(&a, ar);
            side[0].add_if(&q, al != bl);
            side[1].add_if(&q, ar != br);
            a = b;
        }
    }
    [side[0].finish(&left, &tb), side[1].finish(&right, &tb)]
}

/// [`clip_split`] in AVX-512 lanes: the polygon is three vectors of `f64`
/// (x, y, z of up to 8 vertices, in order), so one clipping plane is one
/// vector division and a few shuffles instead of a scalar loop over the
/// edges.
///
/// Bit for bit the scalar code's results: every vertex and crossing is
/// computed by the same IEEE operations in the same order (`crossing`:
/// subtract, divide, multiply, add; Rust never fuses them, nor do these
/// intrinsics), the vertices a plane keeps are compressed out of the lanes
/// in Sutherland–Hodgman's order (each edge's start, then its crossing),
/// so the next plane sees the same polygon, and the bounds are minima and
/// maxima of the same points ([`Bounds64::finish`] drops the sign of a
/// zero, the only thing the order of a minimum can change).
#[cfg(target_arch = "x86_64")]
mod lanes {
    use super::Aabb;
    use glam::Vec3;
    use std::arch::x86_64::*;

    /// Vertices the lanes hold.
    const LANES: u32 = 8;

    /// A polygon of `n <= LANES` vertices: coordinate `k` of vertex `j` in
    /// lane `j` of `c[k]`. Lanes from `n` on hold anything.
    #[derive(Clone, Copy)]
    struct Poly {
        c: [__m512d; 3],
        n: u32,
    }

    impl Poly {
        /// The lanes that hold vertices, and each edge's start and end
        /// (vertex `j` and `j + 1`, the first again after the last).
        #[inline]
        #[target_feature(enable = "avx512f")]
        fn edges(&self) -> (__mmask8, [__m512d; 3], [__m512d; 3]) {
            let valid = ((1u32 << self.n) - 1) as __mmask8;
            let next = next_lane(self.n);
            let b = self.c.map(|c| _mm512_permutexvar_pd(next, c));
            (valid, self.c, b)
        }
    }

    /// `SPREAD[m]`: the 4 bits of `m` moved to the even bits 0, 2, 4, 6.
    const SPREAD: [u8; 16] = {
        let mut t = [0u8; 16];
        let mut m = 0;
        while m < 16 {
            let mut b = 0;
            while b < 4 {
                t[m] |= (((m >> b) & 1) << (2 * b)) as u8;
                b += 1;
            }
            m += 1;
        }
        t
    };

    /// Each lane's next lane around a polygon of `n` vertices (`j + 1`,
    /// and 0 after the last), as a permutation index.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn next_lane(n: u32) -> __m512i {
        const NEXT: [[i64; 8]; 9] = {
            let mut t = [[0i64; 8]; 9];
            let mut n = 1;
            while n <= 8 {
                let mut j = 0;
                while j < 8 {
                    t[n][j] = if j + 1 < n { j as i64 + 1 } else { 0 };
                    j += 1;
                }
                n += 1;
            }
            t
        };
        // SAFETY: `NEXT[n]` is 64 bytes, the unaligned load's size (the
        // index checks `n <= 8`).
        unsafe { _mm512_loadu_si512(NEXT[n as usize].as_ptr().cast()) }
    }

    /// Each edge `a → b`'s crossing of the plane `AXIS = pl`, as the scalar
    /// `crossing` computes it (meaningless where the edge does not cross).
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn crossings<const AXIS: usize>(
        a: &[__m512d; 3],
        b: &[__m512d; 3],
        pl: __m512d,
    ) -> [__m512d; 3] {
        let t = _mm512_div_pd(_mm512_sub_pd(pl, a[AXIS]), _mm512_sub_pd(b[AXIS], a[AXIS]));
        let mut q = [pl; 3];
        for k in 0..3 {
            if k != AXIS {
                q[k] = _mm512_add_pd(a[k], _mm512_mul_pd(_mm512_sub_pd(b[k], a[k]), t));
            }
        }
        q
    }

    /// Clips `p` to `p[AXIS] >= plane` (`ABOVE`) or `<= plane`, as
    /// `Polygon::clip_into` does; `None` when the result would not fit in
    /// the lanes.
    #[target_feature(enable = "avx512f")]
    fn clip<const AXIS: usize, const ABOVE: bool>(p: &Poly, plane: f64) -> Option<Poly> {
        let (valid, a, b) = p.edges();
        let pl = _mm512_set1_pd(plane);
        let (ina, inb) = if ABOVE {
            (
                _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, a[AXIS], pl),
                _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, b[AXIS], pl),
            )
        } else {
            (
                _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, a[AXIS], pl),
                _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, b[AXIS], pl),
            )
        };
        let q = crossings::<AXIS>(&a, &b, pl);
        let cross = ina ^ inb;
        // Edge j's start in slot 2j, its crossing in slot 2j + 1: the
        // order Sutherland–Hodgman writes them in.
        let spread = |m: u8| usize::from(m & 15);
        let k_lo = SPREAD[spread(ina)] | SPREAD[spread(cross)] << 1;
        let k_hi = SPREAD[spread(ina >> 4)] | SPREAD[spread(cross >> 4)] << 1;
        let (n_lo, n_hi) = (k_lo.count_ones(), k_hi.count_ones());
        if n_lo + n_hi > LANES {
            return None;
        }
        let lo_idx = _mm512_set_epi64(11, 3, 10, 2, 9, 1, 8, 0);
        let hi_idx = _mm512_set_epi64(15, 7, 14, 6, 13, 5, 12, 4);
        // Lane j of the result: lane j of the kept low half, then lane
        // j − n_lo of the kept high half (index 8 + j − n_lo).
        let lane = _mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0);
        let from_hi = _mm512_cmpge_epi64_mask(lane, _mm512_set1_epi64(i64::from(n_lo)));
        let join =
            _mm512_mask_add_epi64(lane, from_hi, lane, _mm512_set1_epi64(8 - i64::from(n_lo)));
        let c = [0, 1, 2].map(|k| {
            let lo = _mm512_maskz_compress_pd(k_lo, _mm512_permutex2var_pd(a[k], lo_idx, q[k]));
            let hi = _mm512_maskz_compress_pd(k_hi, _mm512_permutex2var_pd(a[k], hi_idx, q[k]));
            _mm512_permutex2var_pd(lo, join, hi)
        });
        Some(Poly { c, n: n_lo + n_hi })
    }

    /// The scalar `clip_split_axis` in lanes; `None` when the polygon
    /// outgrows them.
    #[target_feature(enable = "avx512f")]
    pub(super) fn clip_split_axis<const AXIS: usize>(
        tri: &[Vec3; 3],
        cell: &Aabb,
        known: &Aabb,
        pos: f32,
    ) -> Option<[Option<Aabb>; 2]> {
        let tb = Aabb::of_triangle(tri);
        if !cell.overlaps(&tb) {
            return Some([None, None]);
        }
        let coord = |k: usize| {
            let v = |i: usize| f64::from(tri[i][k]);
            _mm512_set_pd(0.0, 0.0, 0.0, 0.0, 0.0, v(2), v(1), v(0))
        };
        let mut p = Poly {
            c: [coord(0), coord(1), coord(2)],
            n: 3,
        };
        // The planes `Polygon::clip_to_box` clips to, in its order.
        let cb = super::crossed(&tb, cell, known);
        macro_rules! plane {
            ($axis:literal) => {
                if cb.min[$axis] < cell.min[$axis] && p.n > 0 {
                    p = clip::<$axis, true>(&p, f64::from(cell.min[$axis]))?;
                }
                if cb.max[$axis] > cell.max[$axis] && p.n > 0 {
                    p = clip::<$axis, false>(&p, f64::from(cell.max[$axis]))?;
                }
            };
        }
        plane!(0);
        plane!(1);
        plane!(2);
        if p.n == 0 {
            return Some([None, None]);
        }
        let (lo, hi) = split::<AXIS>(&p, f64::from(pos));
        Some(finish::<AXIS>(lo, hi, cell, &tb, pos))
    }

    /// Both halves' `f64` bounds of `p` (`n > 0`) split by `AXIS = plane`:
    /// each side's vertices and each edge's crossing where the edge changes
    /// side. Lanes 0–2 are the left half's x, y, z, lanes 3–5 the right
    /// half's; a half with no point has `+∞` minima and `−∞` maxima.
    #[target_feature(enable = "avx512f")]
    fn split<const AXIS: usize>(p: &Poly, plane: f64) -> (__m512d, __m512d) {
        let (valid, a, b) = p.edges();
        let pl = _mm512_set1_pd(plane);
        let q = crossings::<AXIS>(&a, &b, pl);
        let al = _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, a[AXIS], pl);
        let ar = _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, a[AXIS], pl);
        let bl = _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, b[AXIS], pl);
        let br = _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, b[AXIS], pl);
        let inf = _mm512_set1_pd(f64::INFINITY);
        let ninf = _mm512_set1_pd(f64::NEG_INFINITY);
        // Per side and coordinate, the kept vertices and crossings in one
        // vector: `lo[3s + k]`, `hi[3s + k]`.
        let mut lo = [inf; 6];
        let mut hi = [ninf; 6];
        for (s, (on, cross)) in [(al, al ^ bl), (ar, ar ^ br)].into_iter().enumerate() {
            for k in 0..3 {
                lo[3 * s + k] = _mm512_min_pd(
                    _mm512_mask_blend_pd(on, inf, a[k]),
                    _mm512_mask_blend_pd(cross, inf, q[k]),
                );
                hi[3 * s + k] = _mm512_max_pd(
                    _mm512_mask_blend_pd(on, ninf, a[k]),
                    _mm512_mask_blend_pd(cross, ninf, q[k]),
                );
            }
        }
        (reduce6::<true>(lo, inf), reduce6::<false>(hi, ninf))
    }

    /// The six vectors' minima (`MIN`) or maxima in lanes 0–5 (lanes 6 and
    /// 7 hold `pad`'s): halves, then quarters, then pairs of lanes, folded
    /// across vectors as they shrink.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn reduce6<const MIN: bool>(v: [__m512d; 6], pad: __m512d) -> __m512d {
        let op = |x: __m512d, y: __m512d| {
            if MIN {
                _mm512_min_pd(x, y)
            } else {
                _mm512_max_pd(x, y)
            }
        };
        // 256-bit halves: h[i] holds v[2i]'s folded half in its low 256
        // bits and v[2i + 1]'s in its high 256 bits.
        let fold = |x: __m512d, y: __m512d| {
            op(
                _mm512_shuffle_f64x2::<0b01_00_01_00>(x, y),
                _mm512_shuffle_f64x2::<0b11_10_11_10>(x, y),
            )
        };
        let h = [fold(v[0], v[1]), fold(v[2], v[3]), fold(v[4], v[5]), pad];
        // 128-bit quarters: g0 holds, in 128-bit lane j, vector j's folded
        // pair; g1 those of v[4], v[5] and the padding.
        let quarter = |x: __m512d, y: __m512d| {
            op(
                _mm512_shuffle_f64x2::<0b10_00_10_00>(x, y),
                _mm512_shuffle_f64x2::<0b11_01_11_01>(x, y),
            )
        };
        let g0 = quarter(h[0], h[1]);
        let g1 = quarter(h[2], h[3]);
        // Pairs: folding the two values of each 128-bit lane leaves, in
        // 128-bit lane j of `e`, vector j's result (from g0) and vector
        // 4 + j's (from g1); the permutation puts vector i's in lane i.
        let e = op(_mm512_unpacklo_pd(g0, g1), _mm512_unpackhi_pd(g0, g1));
        _mm512_permutexvar_pd(_mm512_set_epi64(7, 5, 3, 1, 6, 4, 2, 0), e)
    }

    /// Rounded outward to `f32` (directed rounding, as `f32_round_down` and
    /// `f32_round_up`), intersected with each half of `cell` and with
    /// `tb`; `None` for an empty half. Equal to `Bounds64::finish`.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn finish<const AXIS: usize>(
        lo: __m512d,
        hi: __m512d,
        cell: &Aabb,
        tb: &Aabb,
        pos: f32,
    ) -> [Option<Aabb>; 2] {
        let lo = _mm512_cvt_roundpd_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(lo);
        let hi = _mm512_cvt_roundpd_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(hi);
        let (left, right) = cell.split(AXIS, pos);
        let pair = |a: Vec3, b: Vec3| _mm256_set_ps(0.0, 0.0, b.z, b.y, b.x, a.z, a.y, a.x);
        let cmin = pair(left.min, right.min);
        let cmax = pair(left.max, right.max);
        let tmin = pair(tb.min, tb.min);
        let tmax = pair(tb.max, tb.max);
        // `max`/`min` by comparison as in `Bounds64::finish`; which zero a
        // tie keeps does not matter, `+ 0.0` drops its sign.
        let lo = _mm256_max_ps(_mm256_max_ps(lo, cmin), tmin);
        let hi = _mm256_min_ps(_mm256_min_ps(hi, cmax), tmax);
        let zero = _mm256_setzero_ps();
        let (lo, hi) = (_mm256_add_ps(lo, zero), _mm256_add_ps(hi, zero));
        let empty = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(lo, hi));
        let mut l = [0f32; 8];
        let mut h = [0f32; 8];
        // SAFETY: both arrays are 8 `f32`s, the unaligned stores' size.
        unsafe {
            _mm256_storeu_ps(l.as_mut_ptr(), lo);
            _mm256_storeu_ps(h.as_mut_ptr(), hi);
        }
        let side = |s: usize| {
            (empty >> (3 * s) & 7 == 0).then(|| {
                Aabb::new(
                    Vec3::new(l[3 * s], l[3 * s + 1], l[3 * s + 2]),
                    Vec3::new(h[3 * s], h[3 * s + 1], h[3 * s + 2]),
                )
            })
        };
        [side(0), side(1)]
    }
}

/// The textbook form of the clip, kept as the reference the branch-free
/// code above must match bit for bit: Sutherland–Hodgman with branches, a
/// fresh polygon per plane, bounds by `f64::min`/`max`, and `clip_split`
/// as clip-to-cell followed by one split pass.
#[cfg(test)]
mod reference {
    use super::{Aabb, MAX_POLY, crossing};
    use crate::geom::{f32_round_down, f32_round_up};
    use glam::Vec3;

    #[derive(Clone, Copy)]
    struct Poly {
        v: [[f64; 3]; MAX_POLY],
        n: usize,
    }

    impl Poly {
        fn push(&mut self, p: [f64; 3]) {
            if self.n < MAX_POLY {
                self.v[self.n] = p;
                self.n += 1;
            }
        }

        fn clip(&self, axis: usize, plane: f64, above: bool) -> Poly {
            let inside = |p: &[f64; 3]| {
                if above {
                    p[axis] >= plane
                } else {
                    p[axis] <= plane
                }
            };
            let mut out = Poly {
                v: [[0.0; 3]; MAX_POLY],
                n: 0,
            };
            for i in 0..self.n {
                let (a, b) = (self.v[i], self.v[(i + 1) % self.n]);
                if inside(&a) {
                    out.push(a);
                }
                if inside(&a) != inside(&b) {
                    out.push(crossing(&a, &b, axis, plane));
                }
            }
            out
        }
    }

    fn to_cell(tri: &[Vec3; 3], tb: &Aabb, bx: &Aabb, known: &Aabb) -> Poly {
        let mut p = Poly {
            v: [[0.0; 3]; MAX_POLY],
            n: 3,
        };
        for (i, q) in tri.iter().enumerate() {
            p.v[i] = [f64::from(q.x), f64::from(q.y), f64::from(q.z)];
        }
        for axis in 0..3 {
            if tb.min[axis] < bx.min[axis] && known.min[axis] <= bx.min[axis] {
                p = p.clip(axis, f64::from(bx.min[axis]), true);
            }
            if tb.max[axis] > bx.max[axis] && known.max[axis] >= bx.max[axis] {
                p = p.clip(axis, f64::from(bx.max[axis]), false);
            }
        }
        p
    }

    fn finish(pts: &[[f64; 3]], bx: &Aabb, tb: &Aabb) -> Option<Aabb> {
        if pts.is_empty() {
            return None;
        }
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in pts {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let r = Aabb::new(
            Vec3::from(lo.map(f32_round_down)),
            Vec3::from(hi.map(f32_round_up)),
        );
        let c = r.intersection(bx).intersection(tb);
        (!c.is_empty()).then(|| Aabb::new(c.min + 0.0, c.max + 0.0))
    }

    pub fn clip_triangle(tri: &[Vec3; 3], bx: &Aabb) -> Option<Aabb> {
        let tb = Aabb::of_triangle(tri);
        if bx.contains(&tb) {
            return Some(tb);
        }
        if !bx.overlaps(&tb) {
            return None;
        }
        let p = to_cell(tri, &tb, bx, bx);
        finish(&p.v[..p.n], bx, &tb)
    }

    pub fn clip_split(
        tri: &[Vec3; 3],
        cell: &Aabb,
        known: &Aabb,
        axis: usize,
        pos: f32,
    ) -> [Option<Aabb>; 2] {
        let tb = Aabb::of_triangle(tri);
        if !cell.overlaps(&tb) {
            return [None, None];
        }
        let p = to_cell(tri, &tb, cell, known);
        let plane = f64::from(pos);
        let mut pts: [Vec<[f64; 3]>; 2] = Default::default();
        for i in 0..p.n {
            let a = p.v[(i + p.n - 1) % p.n];
            let b = p.v[i];
            let (al, ar) = (a[axis] <= plane, a[axis] >= plane);
            let (bl, br) = (b[axis] <= plane, b[axis] >= plane);
            if al {
                pts[0].push(a);
            }
            if ar {
                pts[1].push(a);
            }
            if al != bl {
                pts[0].push(crossing(&a, &b, axis, plane));
            }
            if ar != br {
                pts[1].push(crossing(&a, &b, axis, plane));
            }
        }
        let (l, r) = cell.split(axis, pos);
        [finish(&pts[0], &l, &tb), finish(&pts[1], &r, &tb)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit() -> Aabb {
        Aabb::new(Vec3::ZERO, Vec3::ONE)
    }

    #[test]
    fn inside_is_exact() {
        let t = [
            Vec3::new(0.1, 0.2, 0.3),
            Vec3::new(0.5, 0.2, 0.3),
            Vec3::new(0.1, 0.9, 0.3),
        ];
        assert_eq!(clip_triangle(&t, &unit()), Some(Aabb::of_triangle(&t)));
    }

    #[test]
    fn outside_is_none() {
        let t = [
            Vec3::new(2.0, 2.0, 2.0),
            Vec3::new(3.0, 2.0, 2.0),
            Vec3::new(2.0, 3.0, 2.0),
        ];
        assert_eq!(clip_triangle(&t, &unit()), None);
    }

    #[test]
    fn corner_cut_is_tight() {
        // The triangle x + y <= 2 at z = 0.5 only covers part of the box
        // [1,2]x[0,1]: its clipped bounds are x in [1,2], y in [0,1].
        let t = [
            Vec3::new(0.0, 0.0, 0.5),
            Vec3::new(2.0, 0.0, 0.5),
            Vec3::new(0.0, 2.0, 0.5),
        ];
        let bx = Aabb::new(Vec3::new(1.0, 0.0, 0.0), Vec3::new(2.0, 1.0, 1.0));
        let c = clip_triangle(&t, &bx).unwrap();
        assert_eq!(c.min, Vec3::new(1.0, 0.0, 0.5));
        assert_eq!(c.max, Vec3::new(2.0, 1.0, 0.5));
        // A box above the hypotenuse misses although the bounds overlap.
        let bx = Aabb::new(Vec3::new(1.5, 1.5, 0.0), Vec3::new(2.0, 2.0, 1.0));
        assert_eq!(clip_triangle(&t, &bx), None);
    }

    #[test]
    fn diagonal_result_is_conservative() {
        // Clip a skinny diagonal triangle; every sampled point of the
        // triangle inside the box must lie in the clipped bounds.
        let t = [
            Vec3::new(-0.3, 0.1, 0.17),
            Vec3::new(1.7, 0.9, 0.33),
            Vec3::new(1.1, 1.3, 0.71),
        ];
        let bx = unit();
        let c = clip_triangle(&t, &bx).unwrap();
        assert!(bx.contains(&c));
        for i in 0..=50 {
            for j in 0..=(50 - i) {
                let (u, v) = (i as f64 / 50.0, j as f64 / 50.0);
                let p = t[0].as_dvec3() * (1.0 - u - v) + t[1].as_dvec3() * u + t[2].as_dvec3() * v;
                let inside = (0..3).all(|k| p[k] >= 0.0 && p[k] <= 1.0);
                if inside {
                    for k in 0..3 {
                        assert!(p[k] >= f64::from(c.min[k]) - 1e-12);
                        assert!(p[k] <= f64::from(c.max[k]) + 1e-12);
                    }
                }
            }
        }
    }

    /// `clip_split` against `clip_triangle` of each child on a grid of
    /// planes through skinny and big triangles: the two agree up to the
    /// outward rounding (each contains the other's box shrunk by an ulp
    /// margin), both are conservative, and both meet the same children.
    #[test]
    fn split_matches_two_clips() {
        let tris = [
            [
                Vec3::new(-0.3, 0.1, 0.17),
                Vec3::new(1.7, 0.9, 0.33),
                Vec3::new(1.1, 1.3, 0.71),
            ],
            [
                Vec3::new(0.0, 0.0, 0.5),
                Vec3::new(2.0, 0.0, 0.5),
                Vec3::new(0.0, 2.0, 0.5),
            ],
            [
                Vec3::new(-5.0, 0.5, -3.0),
                Vec3::new(6.0, 0.25, 4.0),
                Vec3::new(0.5, 0.75, 9.0),
            ],
        ];
        let cell = Aabb::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 1.0));
        let mut compared = 0;
        for tri in &tris {
            for axis in 0..3 {
                for step in 0..=16 {
                    let pos = step as f32 / 16.0;
                    let (l, r) = cell.split(axis, pos);
                    let got = clip_split(tri, &cell, &cell, axis, pos);
                    for (g, child) in got.iter().zip([l, r]) {
                        let want = clip_triangle(tri, &child);
                        let near = |a: &Aabb, b: &Aabb| {
                            (0..3).all(|k| {
                                (a.min[k] - b.min[k]).abs() <= 1e-6
                                    && (a.max[k] - b.max[k]).abs() <= 1e-6
                            })
                        };
                        match (g, &want) {
                            (Some(g), Some(w)) => {
                                assert!(child.contains(g));
                                assert!(near(g, w), "{g:?} vs {w:?}");
                                for i in 0..=20 {
                                    for j in 0..=(20 - i) {
                                        let (u, v) = (i as f64 / 20.0, j as f64 / 20.0);
                                        let p = tri[0].as_dvec3() * (1.0 - u - v)
                                            + tri[1].as_dvec3() * u
                                            + tri[2].as_dvec3() * v;
                                        let inside = (0..3).all(|k| {
                                            p[k] >= f64::from(child.min[k])
                                                && p[k] <= f64::from(child.max[k])
                                        });
                                        if inside {
                                            for k in 0..3 {
                                                assert!(p[k] >= f64::from(g.min[k]) - 1e-12);
                                                assert!(p[k] <= f64::from(g.max[k]) + 1e-12);
                                            }
                                        }
                                    }
                                }
                                compared += 1;
                            }
                            (None, None) => {}
                            // A touch at the plane may round either way.
                            (Some(b), None) | (None, Some(b)) => {
                                assert!(b.max[axis] - b.min[axis] <= 1e-6 || b.is_empty());
                            }
                        }
                    }
                }
            }
        }
        assert!(compared > 100, "{compared}");
    }

    /// A triangle in the plane `x + y + z = 1.5` whose edges each cut one
    /// corner off the regular hexagon that plane cuts from the unit cube:
    /// `triangle ∩ cube` has 9 vertices, more than the vector lanes hold,
    /// so the AVX-512 clip hands it to the scalar code.
    #[test]
    fn nine_vertex_polygon_clips_alike_everywhere() {
        let c = Vec3::splat(0.5);
        let tri = [
            Vec3::new(0.5, 0.0, -0.5),
            Vec3::new(-0.5, 0.5, 0.0),
            Vec3::new(0.0, -0.5, 0.5),
        ]
        .map(|d| c - d * 1.867);
        let cell = unit();
        let tb = Aabb::of_triangle(&tri);
        let mut poly = Polygon::triangle(&tri);
        let mut scratch = Polygon::EMPTY;
        assert_eq!(poly.clip_to_box(&tb, &cell, &mut scratch).n, 9);
        for axis in 0..3 {
            for pos in [0.0, 0.3, 0.5, 0.77, 1.0] {
                let want = reference::clip_split(&tri, &cell, &cell, axis, pos);
                assert!(want[0].is_some() || want[1].is_some());
                for simd in SimdLevel::available() {
                    let got = clip_split_on(simd, &tri, &cell, &cell, axis, pos);
                    assert_eq!(got, want, "{} axis {axis} at {pos}", simd.name());
                }
            }
        }
    }

    /// Coordinates from a small grid (so that vertices often lie exactly on
    /// cell faces and planes, and triangles are often axis-aligned) or
    /// arbitrary.
    fn coord() -> impl proptest::strategy::Strategy<Value = f32> {
        use proptest::prelude::*;
        prop_oneof![(-4i32..=4).prop_map(|i| i as f32 * 0.25), -1.5f32..1.5f32]
    }

    fn point() -> impl proptest::strategy::Strategy<Value = Vec3> {
        use proptest::prelude::*;
        (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z))
    }

    /// Whether every sampled point of `tri` inside `child` lies in `got`
    /// (`None` meets none of them).
    fn covers_samples(tri: &[Vec3; 3], child: &Aabb, got: Option<Aabb>) -> bool {
        const N: usize = 24;
        for i in 0..=N {
            for j in 0..=(N - i) {
                let (u, v) = (i as f64 / N as f64, j as f64 / N as f64);
                let p = tri[0].as_dvec3() * (1.0 - u - v)
                    + tri[1].as_dvec3() * u
                    + tri[2].as_dvec3() * v;
                let inside = (0..3)
                    .all(|k| p[k] >= f64::from(child.min[k]) && p[k] <= f64::from(child.max[k]));
                if !inside {
                    continue;
                }
                let Some(g) = got else {
                    // A point on the child's face may round out of a touch.
                    let on_face = (0..3).any(|k| {
                        p[k] - f64::from(child.min[k]) < 1e-9
                            || f64::from(child.max[k]) - p[k] < 1e-9
                    });
                    if on_face {
                        continue;
                    }
                    return false;
                };
                if !(0..3).all(|k| {
                    p[k] >= f64::from(g.min[k]) - 1e-9 && p[k] <= f64::from(g.max[k]) + 1e-9
                }) {
                    return false;
                }
            }
        }
        true
    }

    /// A triangle, a cell, an axis and a plane position in the cell.
    fn split_case() -> impl proptest::strategy::Strategy<Value = ([Vec3; 3], Aabb, usize, f32)> {
        use proptest::prelude::*;
        (
            point(),
            point(),
            point(),
            point(),
            point(),
            0usize..3,
            0.0f32..=1.0,
        )
            .prop_map(|(a, b, c, p, q, axis, t)| {
                let cell = Aabb::new(p.min(q), p.max(q));
                let pos = cell.min[axis] + (cell.max[axis] - cell.min[axis]) * t;
                let pos = pos.clamp(cell.min[axis], cell.max[axis]) + 0.0;
                ([a, b, c], cell, axis, pos)
            })
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(5_000))]
        /// Clipping only to the faces the known box reaches stays
        /// conservative, nests in the children, and agrees with clipping to
        /// every face the triangle crosses up to the rounding.
        #[test]
        fn known_box_skips_only_faces_that_cut_nothing(
            (tri, cell, axis, pos) in split_case(),
        ) {
            let Some(known) = clip_triangle(&tri, &cell) else {
                return Ok(());
            };
            let (l, r) = cell.split(axis, pos);
            let got = clip_split(&tri, &cell, &known, axis, pos);
            let all = clip_split(&tri, &cell, &cell, axis, pos);
            for ((g, w), child) in got.into_iter().zip(all).zip([l, r]) {
                if let Some(g) = g {
                    proptest::prop_assert!(child.contains(&g));
                }
                proptest::prop_assert!(covers_samples(&tri, &child, g), "{:?} in {:?}", g, child);
                match (g, w) {
                    (Some(g), Some(w)) => {
                        for k in 0..3 {
                            proptest::prop_assert!((g.min[k] - w.min[k]).abs() <= 1e-5);
                            proptest::prop_assert!((g.max[k] - w.max[k]).abs() <= 1e-5);
                        }
                    }
                    (None, None) => {}
                    // A touch may round either way.
                    (Some(b), None) | (None, Some(b)) => {
                        proptest::prop_assert!((0..3).any(|k| b.max[k] - b.min[k] <= 1e-5));
                    }
                }
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(20_000))]
        /// The branch-free clip equals the textbook one bit for bit.
        #[test]
        fn branch_free_equals_reference(
            (tri, cell, axis, pos) in split_case(),
        ) {
            proptest::prop_assert_eq!(clip_triangle(&tri, &cell), reference::clip_triangle(&tri, &cell));
            for simd in SimdLevel::available() {
                proptest::prop_assert_eq!(
                    clip_split_on(simd, &tri, &cell, &cell, axis, pos),
                    reference::clip_split(&tri, &cell, &cell, axis, pos),
                    "{}", simd.name()
                );
                // With the triangle's clipped box as the known box, as the
                // builders call it.
                if let Some(known) = clip_triangle(&tri, &cell) {
                    proptest::prop_assert_eq!(
                        clip_split_on(simd, &tri, &cell, &known, axis, pos),
                        reference::clip_split(&tri, &cell, &known, axis, pos),
                        "{}", simd.name()
                    );
                }
            }
        }
    }
}
