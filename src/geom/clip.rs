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

#[derive(Clone, Copy)]
struct Polygon {
    v: [[f64; 3]; MAX_POLY],
    n: usize,
}

impl Polygon {
    const EMPTY: Polygon = Polygon {
        v: [[0.0; 3]; MAX_POLY],
        n: 0,
    };

    fn triangle(tri: &[Vec3; 3]) -> Polygon {
        let mut poly = Polygon::EMPTY;
        for (i, p) in tri.iter().enumerate() {
            poly.v[i] = [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
        }
        poly.n = 3;
        poly
    }

    /// Writes into `out` the part with `p[axis] >= plane` (`keep_above`)
    /// or `p[axis] <= plane`.
    #[inline]
    fn clip_into(&self, axis: usize, plane: f64, keep_above: bool, out: &mut Polygon) {
        let inside = |p: &[f64; 3]| {
            if keep_above {
                p[axis] >= plane
            } else {
                p[axis] <= plane
            }
        };
        out.n = 0;
        if self.n == 0 {
            return;
        }
        // Edges (v[i], v[i + 1]), the last one closing the loop.
        let mut a = self.v[0];
        let mut ina = inside(&a);
        for i in 0..self.n {
            let b = self.v[if i + 1 == self.n { 0 } else { i + 1 }];
            let inb = inside(&b);
            if ina {
                out.push(a);
            }
            if ina != inb {
                out.push(crossing(&a, &b, axis, plane));
            }
            a = b;
            ina = inb;
        }
    }

    /// Clips to the planes of `bx` that `tb` (the polygon's bounds) crosses,
    /// in the order x min, x max, y min, y max, z min, z max.
    fn clip_to_box(mut self, tb: &Aabb, bx: &Aabb) -> Polygon {
        let mut tmp = Polygon::EMPTY;
        for axis in 0..3 {
            if tb.min[axis] < bx.min[axis] {
                self.clip_into(axis, f64::from(bx.min[axis]), true, &mut tmp);
                std::mem::swap(&mut self, &mut tmp);
            }
            if tb.max[axis] > bx.max[axis] {
                self.clip_into(axis, f64::from(bx.max[axis]), false, &mut tmp);
                std::mem::swap(&mut self, &mut tmp);
            }
            if self.n == 0 {
                break;
            }
        }
        self
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

/// The point of edge `a → b` on the plane `p[axis] = plane` (the edge
/// crosses it): the coordinate on `axis` is the plane exactly, the others
/// are interpolated from `a`.
#[inline]
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

    /// Rounded outward to `f32`, intersected with `bx` and `tb`; `None`
    /// when empty. `-0.0` bounds become `+0.0`, so that equal planes have
    /// equal bits in every builder.
    fn finish(&self, bx: &Aabb, tb: &Aabb) -> Option<Aabb> {
        if self.lo[0] > self.hi[0] {
            return None;
        }
        let rounded = Aabb::new(
            Vec3::new(
                f32_round_down(self.lo[0]),
                f32_round_down(self.lo[1]),
                f32_round_down(self.lo[2]),
            ),
            Vec3::new(
                f32_round_up(self.hi[0]),
                f32_round_up(self.hi[1]),
                f32_round_up(self.hi[2]),
            ),
        );
        let clipped = rounded.intersection(bx).intersection(tb);
        if clipped.is_empty() {
            None
        } else {
            Some(Aabb::new(clipped.min + 0.0, clipped.max + 0.0))
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
    let poly = Polygon::triangle(tri).clip_to_box(&tb, bx);
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
pub fn clip_split(tri: &[Vec3; 3], cell: &Aabb, axis: usize, pos: f32) -> [Option<Aabb>; 2] {
    let tb = Aabb::of_triangle(tri);
    if !cell.overlaps(&tb) {
        return [None, None];
    }
    let poly = Polygon::triangle(tri).clip_to_box(&tb, cell);
    let (left, right) = cell.split(axis, pos);
    let plane = f64::from(pos);
    let mut side = [Bounds64::EMPTY; 2];
    if poly.n > 0 {
        let mut a = poly.v[poly.n - 1];
        for i in 0..poly.n {
            // Edge a → b as Sutherland–Hodgman walks it (from v[n-1] to v[0]
            // first), so crossings are computed from the same end.
            let b = poly.v[i];
            let (al, ar) = (a[axis] <= plane, a[axis] >= plane);
            let (bl, br) = (b[axis] <= plane, b[axis] >= plane);
            if al {
                side[0].add(&a);
            }
            if ar {
                side[1].add(&a);
            }
            if al != bl || ar != br {
                let q = crossing(&a, &b, axis, plane);
                if al != bl {
                    side[0].add(&q);
                }
                if ar != br {
                    side[1].add(&q);
                }
            }
            a = b;
        }
    }
    [side[0].finish(&left, &tb), side[1].finish(&right, &tb)]
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
                    let got = clip_split(tri, &cell, axis, pos);
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
}
