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

pub use clip::{clip_split, clip_triangle};
pub use intersect::{RayPrecomp, intersect_ray_triangle, intersect_triangle};

use glam::Vec3;

/// An axis-aligned box with `min <= max` on every axis (or [`Aabb::EMPTY`]).
///
/// A box may be flat (`min[k] == max[k]`): the box of a planar triangle, or
/// of a cell cut off by a split plane lying on the node's face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    /// The empty box: the identity of [`Aabb::union`].
    pub const EMPTY: Aabb = Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };

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

    pub fn is_empty(&self) -> bool {
        !(self.min.x <= self.max.x && self.min.y <= self.max.y && self.min.z <= self.max.z)
    }

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

    pub fn extent(&self) -> Vec3 {
        self.max - self.min
    }

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

/// A ray `origin + t·dir`, valid for `t` in `(tmin, tmax]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
    pub tmin: f32,
    pub tmax: f32,
}

impl Ray {
    pub fn new(origin: Vec3, dir: Vec3) -> Ray {
        Ray {
            origin,
            dir,
            tmin: 0.0,
            tmax: f32::INFINITY,
        }
    }
}

/// Rounds an `f64` down to the nearest `f32` that is `<=` it.
pub fn f32_round_down(x: f64) -> f32 {
    let f = x as f32;
    // Both candidates, then a select: the comparison is a coin flip for
    // interpolated points, so a branch would mispredict half the time.
    let below = f.next_down();
    if f64::from(f) > x { below } else { f }
}

/// Rounds an `f64` up to the nearest `f32` that is `>=` it.
pub fn f32_round_up(x: f64) -> f32 {
    let f = x as f32;
    let above = f.next_up();
    if f64::from(f) < x { above } else { f }
}

/// Twice the area of a triangle, in `f64` (exactly zero for collinear or
/// repeated vertices up to the rounding of the cross product).
pub fn double_area(tri: &[Vec3; 3]) -> f64 {
    let a = tri[0].as_dvec3();
    let e1 = tri[1].as_dvec3() - a;
    let e2 = tri[2].as_dvec3() - a;
    e1.cross(e2).length()
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

    #[test]
    fn surface_area_of_unit_box() {
        let b = Aabb::new(Vec3::ZERO, Vec3::ONE);
        assert_eq!(b.surface_area(), 6.0);
        let (l, r) = b.split(0, 0.25);
        assert_eq!(l.max.x, 0.25);
        assert_eq!(r.min.x, 0.25);
    }
}
