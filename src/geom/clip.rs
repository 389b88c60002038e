//! Clipping a triangle to a box: the exact bounds of `triangle ∩ box`, the
//! candidate planes of perfect splits (Havran 2000; Wald & Havran 2006 §4.4).
//!
//! The polygon is clipped in `f64` (Sutherland–Hodgman against the six
//! planes); the coordinate on the clipping axis is set to the plane exactly,
//! the others are interpolated. Its bounds are rounded outward to `f32` and
//! intersected with the box and with the triangle's own bounds, so the result
//! is conservative (it contains every point of the triangle inside the box)
//! and nests inside the box.

use super::{Aabb, f32_round_down, f32_round_up};
use glam::Vec3;

/// Sutherland–Hodgman on a triangle and six planes yields at most 9 vertices.
const MAX_POLY: usize = 9;

struct Polygon {
    v: [[f64; 3]; MAX_POLY],
    n: usize,
}

impl Polygon {
    /// Keeps the part with `sign·(p[axis] − plane) >= 0`.
    fn clip(&self, axis: usize, plane: f64, keep_above: bool) -> Polygon {
        let inside = |p: &[f64; 3]| {
            if keep_above {
                p[axis] >= plane
            } else {
                p[axis] <= plane
            }
        };
        let mut out = Polygon {
            v: [[0.0; 3]; MAX_POLY],
            n: 0,
        };
        for i in 0..self.n {
            let a = self.v[i];
            let b = self.v[(i + 1) % self.n];
            let (ina, inb) = (inside(&a), inside(&b));
            if ina {
                out.push(a);
            }
            if ina != inb {
                let t = (plane - a[axis]) / (b[axis] - a[axis]);
                let mut p = [0.0; 3];
                for k in 0..3 {
                    p[k] = a[k] + (b[k] - a[k]) * t;
                }
                p[axis] = plane;
                out.push(p);
            }
        }
        out
    }

    fn push(&mut self, p: [f64; 3]) {
        // A convex polygon clipped by one plane gains at most one vertex, so
        // six clips of a triangle never exceed MAX_POLY.
        debug_assert!(self.n < MAX_POLY);
        if self.n < MAX_POLY {
            self.v[self.n] = p;
            self.n += 1;
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
    let mut poly = Polygon {
        v: [[0.0; 3]; MAX_POLY],
        n: 3,
    };
    for (i, p) in tri.iter().enumerate() {
        poly.v[i] = [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
    }
    for axis in 0..3 {
        if tb.min[axis] < bx.min[axis] {
            poly = poly.clip(axis, f64::from(bx.min[axis]), true);
        }
        if tb.max[axis] > bx.max[axis] {
            poly = poly.clip(axis, f64::from(bx.max[axis]), false);
        }
        if poly.n == 0 {
            return None;
        }
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in &poly.v[..poly.n] {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let rounded = Aabb::new(
        Vec3::new(
            f32_round_down(lo[0]),
            f32_round_down(lo[1]),
            f32_round_down(lo[2]),
        ),
        Vec3::new(
            f32_round_up(hi[0]),
            f32_round_up(hi[1]),
            f32_round_up(hi[2]),
        ),
    );
    let clipped = rounded.intersection(bx).intersection(&tb);
    if clipped.is_empty() {
        None
    } else {
        // Adding +0.0 turns a -0.0 bound into +0.0, so that equal planes
        // have equal bits in every builder.
        Some(Aabb::new(clipped.min + 0.0, clipped.max + 0.0))
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
}
