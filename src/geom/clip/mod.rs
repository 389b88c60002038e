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
#[cfg(test)]
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
    clip_triangle_by(tri, bx, |tb| {
        let mut poly = Polygon::triangle(tri);
        let mut scratch = Polygon::EMPTY;
        let poly = poly.clip_to_box(tb, bx, &mut scratch);
        let mut b = Bounds64::EMPTY;
        for p in &poly.v[..poly.n] {
            b.add(p);
        }
        b.finish(bx, tb)
    })
}

/// [`clip_triangle`] with the clip itself `clip(tb)` (`tb`: the
/// triangle's bounds), called only when the triangle's bounds neither lie
/// inside the box (they are the answer) nor miss it (`None`).
#[inline(always)]
fn clip_triangle_by(
    tri: &[Vec3; 3],
    bx: &Aabb,
    clip: impl FnOnce(&Aabb) -> Option<Aabb>,
) -> Option<Aabb> {
    let tb = Aabb::of_triangle(tri);
    if bx.contains(&tb) {
        return Some(tb);
    }
    if !bx.overlaps(&tb) {
        return None;
    }
    clip(&tb)
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
/// (`clip_split_checked`), with the same results bit for bit.
#[inline]
pub(crate) fn clip_split(
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
/// code. Both give the same bits (the tests hold every level to the
/// reference).
///
/// # Panics
/// On [`SimdLevel::Avx512`] when this CPU lacks avx512f.
#[cfg(test)]
pub(crate) fn clip_split_on(
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
mod lanes;

/// The textbook form of the clip, kept as the reference the branch-free
/// code above must match bit for bit: Sutherland–Hodgman with branches, a
/// fresh polygon per plane, bounds by `f64::min`/`max`, and `clip_split`
/// as clip-to-cell followed by one split pass.
#[cfg(test)]
mod reference;

#[cfg(test)]
mod tests;
