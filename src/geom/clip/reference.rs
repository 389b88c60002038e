//! The textbook form of the clip, kept as the reference the branch-free
//! code must match bit for bit (see the declaration in the parent module).

use super::{Aabb, MAX_POLY, clip_triangle_by, crossing};
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
    // The same trivial cases as the real clip; the clip itself is this
    // module's.
    clip_triangle_by(tri, bx, |tb| {
        let p = to_cell(tri, tb, bx, bx);
        finish(&p.v[..p.n], bx, tb)
    })
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
