//! Geometry shared by every stage: axis-aligned boxes, rays, clipping a
//! triangle to a box (perfect splits) and the watertight ray–triangle test.
//!
//! Consumes plain `f32` triangles; produces boxes and hit distances. The one
//! guarantee that matters downstream: every function here is deterministic
//! and free of fused or reordered arithmetic, so that the naive, sweep and
//! level builders see bit-identical boxes, and every traverser (scalar,
//! packet, brute force) computes bit-identical hit distances for the same
//! ray and triangle.

mod clip;
mod intersect;

pub(crate) use clip::clip_split;
pub use clip::clip_triangle;
pub use intersect::{
    RayPrecomp, dominant_axis, edge_functions, intersect_ray_triangle, intersect_triangle,
};
pub(crate) use intersect::{edges_need_f64, scaled_distance, sheared_edges, t_needs_f64};

use glam::Vec3;

/// An axis-aligned box with `min <= max` on every axis (or [`Aabb::EMPTY`]).
///
/// A box may be flat (`min[k] == max[k]`): the box of a planar triangle, or
/// of a cell cut off by a split plane lying on the node's face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// The low corner.
    pub min: Vec3,
    /// The high corner.
    pub max: Vec3,
}

impl Aabb {
    /// The empty box: the identity of [`Aabb::union`].
    pub const EMPTY: Aabb = Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };

    /// The box from `min` to `max` (not checked: an inverted box is empty).
    pub fn new(min: Vec3, max: Vec3) -> Aabb {
        Aabb { min, max }
    }

    /// The bounds of a triangle (exact: no rounding is involved).
    pub fn of_triangle(tri: &[Vec3; 3]) -> Aabb {
        Aabb {
            min: tri[0].min(tri[1]).min(tri[2]),
            max: tri[0].max(tri[1]).max(tri[2]),
        }
    }

    /// Whether the box holds no point (some `min > max`, or a NaN).
    pub fn is_empty(&self) -> bool {
        !(self.min.x <= self.max.x && self.min.y <= self.max.y && self.min.z <= self.max.z)
    }

    /// The smallest box holding both.
    pub fn union(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }

    /// The intersection; may be empty.
    pub fn intersection(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: self.min.max(o.min),
            max: self.max.min(o.max),
        }
    }

    /// True when `o` lies inside `self` (closed boxes).
    pub fn contains(&self, o: &Aabb) -> bool {
        self.min.cmple(o.min).all() && o.max.cmple(self.max).all()
    }

    /// True when the closed boxes share at least one point.
    pub fn overlaps(&self, o: &Aabb) -> bool {
        self.min.cmple(o.max).all() && o.min.cmple(self.max).all()
    }

    /// `max - min`, per axis.
    pub fn extent(&self) -> Vec3 {
        self.max - self.min
    }

    /// The midpoint of the box.
    pub fn center(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// Surface area in `f64`, the form the SAH uses: `2(dx·dy + dy·dz + dz·dx)`
    /// with each extent taken exactly (`f32` difference widened to `f64`).
    pub fn surface_area(&self) -> f64 {
        let d = [
            f64::from(self.max.x) - f64::from(self.min.x),
            f64::from(self.max.y) - f64::from(self.min.y),
            f64::from(self.max.z) - f64::from(self.min.z),
        ];
        2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
    }

    /// The two halves of `self` cut by the plane `axis = pos`.
    pub fn split(&self, axis: usize, pos: f32) -> (Aabb, Aabb) {
        let mut left = *self;
        let mut right = *self;
        left.max[axis] = pos;
        right.min[axis] = pos;
        (left, right)
    }
}

/// A ray `origin + t·dir`, valid for `t` in `(tmin, tmax]`. Laid out as
/// eight `f32` in field order, which the ray orders' vector code loads.
///
/// Every query assumes the contract [`Ray::check`] tests (as Embree's
/// does: the interval lies ahead of the origin). The kd walks decide a
/// split crossed at `t ≤ 0` to lie behind the ray, so a ray that starts
/// behind its origin would miss what lies there; the facade
/// ([`crate::accel`]) panics on such a ray and the ray files refuse it.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct Ray {
    /// Where the ray starts.
    pub origin: Vec3,
    /// Its direction (any length but zero; `t` is in units of it).
    pub dir: Vec3,
    /// Start of the interval, exclusive; at least 0 (the traversers walk
    /// the part of the line ahead of the origin).
    pub tmin: f32,
    /// End of the interval, inclusive for closest hits (any-hit queries
    /// exclude it).
    pub tmax: f32,
}

impl Ray {
    /// The ray from `origin` along `dir` for `t` in `(0, ∞]`.
    pub fn new(origin: Vec3, dir: Vec3) -> Ray {
        Ray {
            origin,
            dir,
            tmin: 0.0,
            tmax: f32::INFINITY,
        }
    }

    /// `Ok` when the ray keeps the contract every query assumes: a finite
    /// origin, a finite direction other than zero, `tmin ≥ 0` and no NaN
    /// bound (`tmax` may be infinite; an empty interval, `tmin ≥ tmax`,
    /// is a query that finds nothing); else what it breaks.
    pub fn check(&self) -> Result<(), &'static str> {
        if !self.origin.is_finite() {
            Err("origin is not finite")
        } else if !self.dir.is_finite() {
            Err("direction is not finite")
        } else if self.dir == Vec3::ZERO {
            Err("direction is zero")
        } else if self.tmin.is_nan() || self.tmax.is_nan() {
            Err("tmin or tmax is NaN")
        } else if self.tmin < 0.0 {
            Err("tmin is negative (the interval must start at or ahead of the origin)")
        } else {
            Ok(())
        }
    }
}

/// Rounds an `f64` down to the nearest `f32` that is `<=` it.
#[inline]
pub(crate) fn f32_round_down(x: f64) -> f32 {
    let f = x as f32;
    // Both candidates, then a select: the comparison is a coin flip for
    // interpolated points, so a branch would mispredict half the time.
    let below = f32_step(f, false);
    if f64::from(f) > x { below } else { f }
}

/// Rounds an `f64` up to the nearest `f32` that is `>=` it.
#[inline]
pub(crate) fn f32_round_up(x: f64) -> f32 {
    let f = x as f32;
    let above = f32_step(f, true);
    if f64::from(f) < x { above } else { f }
}

/// [`f32::next_up`] (`up`) or [`f32::next_down`] of `f`, by selects on the
/// bits, without the library's branches for NaN and the infinities. Equal
/// to the library's for every `f` but NaN and the infinity it steps away
/// from, which the two roundings above never select: there the comparison
/// with `x` is false.
#[inline(always)]
fn f32_step(f: f32, up: bool) -> f32 {
    let b = f.to_bits();
    // A positive `f` moves away from zero going up, a negative one toward
    // it; from either zero the step is to the smallest subnormal.
    let away = (b >> 31 == 0) == up;
    let stepped = if away {
        b.wrapping_add(1)
    } else {
        b.wrapping_sub(1)
    };
    let from_zero = if up { 0x0000_0001 } else { 0x8000_0001 };
    f32::from_bits(if b & 0x7fff_ffff == 0 {
        from_zero
    } else {
        stepped
    })
}

/// Twice the area of a triangle, in `f64` (exactly zero for collinear or
/// repeated vertices up to the rounding of the cross product).
pub fn double_area(tri: &[Vec3; 3]) -> f64 {
    let a = tri[0].as_dvec3();
    let e1 = tri[1].as_dvec3() - a;
    let e2 = tri[2].as_dvec3() - a;
    e1.cross(e2).length()
}

/// Component `k` of `v` (0, 1, or 2 for any other value), chosen by
/// comparisons rather than by an index: in the lane loops it is a select,
/// which they vectorise.
#[inline(always)]
pub(crate) fn select_axis<K: Copy + PartialEq + From<u8>>(v: [f32; 3], k: K) -> f32 {
    if k == K::from(0) {
        v[0]
    } else if k == K::from(1) {
        v[1]
    } else {
        v[2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_is_outward() {
        let x = 0.1f64;
        assert!(f64::from(f32_round_down(x)) <= x);
        assert!(f64::from(f32_round_up(x)) >= x);
        assert_eq!(f32_round_up(1.0), 1.0);
        assert_eq!(f32_round_down(1.0), 1.0);
        assert!(f32_round_up(x) > f32_round_down(x));
    }

    /// The step by bits is the library's `next_up`/`next_down` wherever
    /// the roundings can select it, and the roundings are the nearest
    /// `f32` on their side.
    #[test]
    fn rounding_steps_as_the_library_does() {
        let mut specials = vec![
            0.0f32,
            -0.0,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x8000_0001),
            f32::MAX,
            f32::MIN,
            1.0,
            -1.0,
        ];
        // A deterministic spread of bit patterns (a 32-bit LCG).
        let mut s = 0x1234_5678u32;
        for _ in 0..100_000 {
            s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            specials.push(f32::from_bits(s));
        }
        for f in specials.into_iter().filter(|f| f.is_finite()) {
            assert_eq!(f32_step(f, true).to_bits(), f.next_up().to_bits(), "{f:e}");
            assert_eq!(
                f32_step(f, false).to_bits(),
                f.next_down().to_bits(),
                "{f:e}"
            );
            let x = f64::from(f);
            for x in [
                x,
                x * (1.0 + 1e-12),
                x * (1.0 - 1e-12),
                x + 1e-300,
                x - 1e-300,
            ] {
                let (d, u) = (f32_round_down(x), f32_round_up(x));
                assert!(f64::from(d) <= x && f64::from(u) >= x, "{x:e}");
                assert!(f64::from(d.next_up()) > x || d == u, "{x:e}");
                assert!(f64::from(u.next_down()) < x || d == u, "{x:e}");
            }
        }
    }

    #[test]
    fn surface_area_of_unit_box() {
        let b = Aabb::new(Vec3::ZERO, Vec3::ONE);
        assert_eq!(b.surface_area(), 6.0);
        let (l, r) = b.split(0, 0.25);
        assert_eq!(l.max.x, 0.25);
        assert_eq!(r.min.x, 0.25);
    }
}
