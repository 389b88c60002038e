//! The watertight ray–triangle test of Woop, Benthin & Wald (JCGT 2013),
//! two-sided.
//!
//! Watertight: a ray that passes through a shared edge or vertex of a closed
//! mesh hits at least one of the triangles that share it. The arithmetic is
//! written out in a fixed order without fused multiply–adds, so every caller
//! (brute force, scalar and packet traversal) gets the same bits of `t` for
//! the same ray and triangle. Degenerate (zero-area) triangles have a zero
//! determinant and are never hit.
//!
//! *Range.* The edge functions grow with the square of the scene's scale
//! and the scaled distance with its cube, so in `f32` they overflow above
//! about 10^12 and lose their bits below about 10^-13. Where they do (an
//! edge function zero, subnormal or NaN; the scaled distance zero,
//! subnormal or not finite; the determinant not finite), the whole test is
//! redone in `f64` from the input vertices ([`edges_need_f64`],
//! [`t_needs_f64`], `watertight_f64`), where every finite `f32` scene is in
//! range. Elsewhere the `f32` result stands, bit for bit; the packet kernel
//! flags its lanes by the same two functions and hands them to
//! [`intersect_triangle`], so every caller still gets the same bits. An
//! exactly zero edge function (the ray through an edge or vertex) takes the
//! same path, which is the paper's double-precision fallback.

use super::Ray;
use glam::Vec3;
use std::ops::{Add, Mul, Sub};

/// Per-ray constants of the watertight test: the axis permutation that makes
/// `kz` the dominant direction axis, and the shear `(sx, sy, sz)`.
#[derive(Clone, Copy, Debug)]
pub struct RayPrecomp {
    /// The ray's origin, subtracted from the vertices first.
    pub origin: Vec3,
    /// The first of the two other axes (swapped with `ky` when the
    /// dominant component is negative, so the winding is kept).
    pub kx: usize,
    /// The second of the two other axes.
    pub ky: usize,
    /// The axis of the direction's largest component.
    pub kz: usize,
    /// Shear of x: `dir[kx] / dir[kz]`.
    pub sx: f32,
    /// Shear of y: `dir[ky] / dir[kz]`.
    pub sy: f32,
    /// Scale of z: `1 / dir[kz]`.
    pub sz: f32,
}

/// The axis along which `dir` is longest, the test's `kz` (ties to the
/// lower axis): the packets' lanes share their vertex permutation where
/// their rays share it and the sign of that component.
#[inline]
pub fn dominant_axis(dir: Vec3) -> usize {
    let a = dir.abs();
    if a.x >= a.y && a.x >= a.z {
        0
    } else if a.y >= a.z {
        1
    } else {
        2
    }
}

impl RayPrecomp {
    /// The constants of `ray`.
    ///
    /// The axes come from a table and the components from an array, not
    /// from `% 3`, a swap and `Vec3` indexed by a variable (75 of a single
    /// AO ray's 1,200 instructions, the call included).
    #[inline]
    pub fn new(ray: &Ray) -> RayPrecomp {
        // `(kx, ky)` per `kz`, then swapped where `dir[kz] < 0`.
        const AXES: [[(usize, usize); 2]; 3] =
            [[(1, 2), (2, 1)], [(2, 0), (0, 2)], [(0, 1), (1, 0)]];
        let d = ray.dir.to_array();
        let kz = dominant_axis(ray.dir);
        let dz = d[kz];
        let (kx, ky) = AXES[kz][usize::from(dz < 0.0)];
        RayPrecomp {
            origin: ray.origin,
            kx,
            ky,
            kz,
            sx: d[kx] / dz,
            sy: d[ky] / dz,
            sz: 1.0 / dz,
        }
    }
}

/// Returns the hit distance `t` of the ray with the triangle if the triangle
/// is hit with `tmin < t <= tmax`.
///
/// Always inlined: with its seven arms LLVM otherwise keeps it out of line,
/// and the walks then call it baseline-compiled (behind a `vzeroupper` in
/// the vector copies) with their state spilled around each call. Inlined,
/// single rays trace 1.1–1.5× faster (ravenbridge shadow rays 2.55 → 3.94
/// Mrays/s, one thread, Zen 4).
#[inline(always)]
pub fn intersect_triangle(rp: &RayPrecomp, tri: &[Vec3; 3], tmin: f32, tmax: f32) -> Option<f32> {
    // The permutation picks components with constant indices (one arm per
    // permutation `RayPrecomp::new` makes; the same arithmetic in each):
    // indexing a vector by a variable costs a third of the test.
    match (rp.kx, rp.ky, rp.kz) {
        (1, 2, 0) => watertight(rp, tri, tmin, tmax, |v| [v.y, v.z, v.x]),
        (2, 1, 0) => watertight(rp, tri, tmin, tmax, |v| [v.z, v.y, v.x]),
        (2, 0, 1) => watertight(rp, tri, tmin, tmax, |v| [v.z, v.x, v.y]),
        (0, 2, 1) => watertight(rp, tri, tmin, tmax, |v| [v.x, v.z, v.y]),
        (0, 1, 2) => watertight(rp, tri, tmin, tmax, |v| [v.x, v.y, v.z]),
        (1, 0, 2) => watertight(rp, tri, tmin, tmax, |v| [v.y, v.x, v.z]),
        (kx, ky, kz) => watertight(rp, tri, tmin, tmax, |v| [v[kx], v[ky], v[kz]]),
    }
}

/// The test with the vertices relative to the origin in permuted order
/// `[x, y, z]` (`pick`).
#[inline(always)]
fn watertight(
    rp: &RayPrecomp,
    tri: &[Vec3; 3],
    tmin: f32,
    tmax: f32,
    pick: impl Fn(Vec3) -> [f32; 3],
) -> Option<f32> {
    let a = pick(tri[0] - rp.origin);
    let b = pick(tri[1] - rp.origin);
    let c = pick(tri[2] - rp.origin);
    let [u, v, w] = sheared_edges(rp.sx, rp.sy, a, b, c);
    if edges_need_f64(u, v, w) {
        return watertight_f64(rp, tri, tmin, tmax);
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    // Not mixed and none below the normal range: `det` is nonzero.
    let det = u + v + w;
    let t_scaled = scaled_distance(rp.sz, [u, v, w], a, b, c);
    let t = t_scaled / det;
    if t_needs_f64(det, t_scaled, t) {
        return watertight_f64(rp, tri, tmin, tmax);
    }
    if t > tmin && t <= tmax { Some(t) } else { None }
}

/// The smaller of `a` and `b` (`b` where either is NaN): one vector `min`.
#[inline(always)]
fn min_of(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// Whether the `f32` edge functions `u, v, w` cannot decide the test: one
/// is zero (the ray through an edge or vertex), subnormal (its sign may be
/// a rounding artefact) or NaN (an overflow of opposite infinities).
#[inline(always)]
#[allow(
    clippy::neg_cmp_op_on_partial_ord,
    reason = "NaN must count as out of range"
)]
pub(crate) fn edges_need_f64(u: f32, v: f32, w: f32) -> bool {
    let m = min_of(min_of(u.abs(), v.abs()), w.abs());
    !(m >= f32::MIN_POSITIVE)
}

/// Whether `t = t_scaled / det` of edge functions that decide the test
/// (not mixed, see [`edges_need_f64`]) cannot stand: the scaled distance
/// underflowed (zero or subnormal: few or no bits left) or something
/// overflowed (`det`, `t_scaled` or `t` infinite or NaN; `det + t` is
/// finite exactly when both are, but for two values near `f32::MAX`).
#[inline(always)]
#[allow(
    clippy::neg_cmp_op_on_partial_ord,
    reason = "NaN must count as out of range"
)]
pub(crate) fn t_needs_f64(det: f32, t_scaled: f32, t: f32) -> bool {
    !(t_scaled.abs() >= f32::MIN_POSITIVE) | !((det + t).abs() <= f32::MAX)
}

/// The test in `f64` from the input vertices, the origin and the ray's
/// (`f32`) shear: the same operations in the same order, in a precision
/// in which no finite `f32` scene overflows or underflows. Both triangles
/// of an edge compute its edge function from the same two vertices, so
/// the test stays watertight.
#[inline(never)]
fn watertight_f64(rp: &RayPrecomp, tri: &[Vec3; 3], tmin: f32, tmax: f32) -> Option<f32> {
    let [u, v, w, t_scaled] = sheared_f64(rp, tri);
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    // A distance beyond the `f32` range is no hit (as in the `f32` test,
    // whose infinite `t` comes here).
    let t = (t_scaled / det) as f32;
    if t > tmin && t <= tmax && t.is_finite() {
        Some(t)
    } else {
        None
    }
}

/// The edge functions `[e0, e1, e2]` and the scaled distance of the test,
/// in `f64` (see [`watertight_f64`]).
fn sheared_f64(rp: &RayPrecomp, tri: &[Vec3; 3]) -> [f64; 4] {
    let o = rp.origin.as_dvec3();
    let pick = |p: Vec3| {
        let d = p.as_dvec3() - o;
        [d[rp.kx], d[rp.ky], d[rp.kz]]
    };
    let (a, b, c) = (pick(tri[0]), pick(tri[1]), pick(tri[2]));
    let (sx, sy, sz) = (f64::from(rp.sx), f64::from(rp.sy), f64::from(rp.sz));
    let [u, v, w] = sheared_edges(sx, sy, a, b, c);
    let t_scaled = scaled_distance(sz, [u, v, w], a, b, c);
    [u, v, w, t_scaled]
}

/// The edge functions `[e0, e1, e2]` of the permuted vertices `a`, `b`,
/// `c` (relative to the origin) sheared by `(sx, sy)`: `e_i` is opposite
/// vertex `i`. The one copy of this arithmetic: the `f32` test, its `f64`
/// redo and each lane of the packet kernel run it, so that they agree bit
/// for bit (`F` is `f32` or `f64`; plain operations, never fused).
#[inline(always)]
pub(crate) fn sheared_edges<F>(sx: F, sy: F, a: [F; 3], b: [F; 3], c: [F; 3]) -> [F; 3]
where
    F: Copy + Sub<Output = F> + Mul<Output = F>,
{
    let ax = a[0] - sx * a[2];
    let ay = a[1] - sy * a[2];
    let bx = b[0] - sx * b[2];
    let by = b[1] - sy * b[2];
    let cx = c[0] - sx * c[2];
    let cy = c[1] - sy * c[2];
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    [u, v, w]
}

/// The scaled distance `t · det` of the edge functions `[u, v, w]`
/// ([`sheared_edges`]) of the vertices `a`, `b`, `c`: their `z` scaled by
/// `sz` and weighted, in this order, by every copy of the test.
#[inline(always)]
pub(crate) fn scaled_distance<F>(sz: F, [u, v, w]: [F; 3], a: [F; 3], b: [F; 3], c: [F; 3]) -> F
where
    F: Copy + Add<Output = F> + Mul<Output = F>,
{
    let az = sz * a[2];
    let bz = sz * b[2];
    let cz = sz * c[2];
    u * az + v * bz + w * cz
}

/// The watertight test's edge functions `[e0, e1, e2]` for this ray and
/// triangle, by its own operations: divided by their sum they are the
/// barycentric weights of vertices 0, 1, 2 that its `t` was computed with.
/// Where the test works in `f64`, they are its `f64` edge functions
/// divided by their sum (rounded to `f32`, which they fit).
pub fn edge_functions(rp: &RayPrecomp, tri: &[Vec3; 3]) -> [f32; 3] {
    let pick = |v: Vec3| [v[rp.kx], v[rp.ky], v[rp.kz]];
    let a = pick(tri[0] - rp.origin);
    let b = pick(tri[1] - rp.origin);
    let c = pick(tri[2] - rp.origin);
    let [u, v, w] = sheared_edges(rp.sx, rp.sy, a, b, c);
    let det = u + v + w;
    let t_scaled = scaled_distance(rp.sz, [u, v, w], a, b, c);
    if edges_need_f64(u, v, w) || t_needs_f64(det, t_scaled, t_scaled / det) {
        let [u, v, w, _] = sheared_f64(rp, tri);
        let det = u + v + w;
        return [(u / det) as f32, (v / det) as f32, (w / det) as f32];
    }
    [u, v, w]
}

/// Convenience wrapper for a single test.
pub fn intersect_ray_triangle(ray: &Ray, tri: &[Vec3; 3]) -> Option<f32> {
    intersect_triangle(&RayPrecomp::new(ray), tri, ray.tmin, ray.tmax)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri() -> [Vec3; 3] {
        [
            Vec3::new(0.0, 0.0, 5.0),
            Vec3::new(2.0, 0.0, 5.0),
            Vec3::new(0.0, 2.0, 5.0),
        ]
    }

    #[test]
    fn hits_front_and_back() {
        let r = Ray::new(Vec3::new(0.5, 0.5, 0.0), Vec3::Z);
        assert_eq!(intersect_ray_triangle(&r, &tri()), Some(5.0));
        let r = Ray::new(Vec3::new(0.5, 0.5, 10.0), -Vec3::Z);
        assert_eq!(intersect_ray_triangle(&r, &tri()), Some(5.0));
        let r = Ray::new(Vec3::new(0.5, 0.5, 10.0), Vec3::Z);
        assert_eq!(intersect_ray_triangle(&r, &tri()), None);
    }

    #[test]
    fn shared_edge_is_watertight() {
        // Two triangles sharing the diagonal of a square; a ray exactly
        // through the diagonal hits at least one.
        let t1 = [
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(1.0, 1.0, 1.0),
        ];
        let t2 = [
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(1.0, 1.0, 1.0),
            Vec3::new(0.0, 1.0, 1.0),
        ];
        for i in 1..10 {
            let p = i as f32 / 10.0;
            let r = Ray::new(Vec3::new(p, p, 0.0), Vec3::Z);
            assert!(
                intersect_ray_triangle(&r, &t1).is_some()
                    || intersect_ray_triangle(&r, &t2).is_some()
            );
        }
    }

    #[test]
    fn degenerate_is_never_hit() {
        let t = [
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(1.0, 1.0, 1.0),
            Vec3::new(2.0, 2.0, 1.0),
        ];
        let r = Ray::new(Vec3::new(1.0, 1.0, 0.0), Vec3::Z);
        assert_eq!(intersect_ray_triangle(&r, &t), None);
        let p = [Vec3::ONE; 3];
        let r = Ray::new(Vec3::new(1.0, 1.0, 0.0), Vec3::Z);
        assert_eq!(intersect_ray_triangle(&r, &p), None);
    }
}
