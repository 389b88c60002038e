//! Closest-hit queries: the scalar front-to-back kd-tree traverser and the
//! brute-force reference.
//!
//! Consumes a [`TreeIr`] and the scene's [`TriangleColumns`]; produces a
//! [`Hit`] per ray. Every traverser uses the same watertight test
//! ([`intersect_triangle`]) and the same rule for the closest hit: the
//! smallest `t` in `(tmin, tmax]`, ties going to the smaller triangle id. So
//! the traverser and brute force return exactly the same hit, bit for bit.
//!
//! **Robust early exit.** Split-plane distances `ts` and hit distances `t`
//! are rounded independently, so a hit that lies on a split plane may be
//! computed just inside one cell while a triangle of the neighbouring cell
//! is computed just before it. The traverser therefore widens every
//! decision by a relative margin [`MARGIN`]: it visits both children unless
//! the plane is clearly outside `[tmin, tmax]`, and it skips a pending cell
//! only when its entry distance lies clearly beyond the best hit. (Pending
//! cells are checked one by one rather than assumed sorted: a ray lying in
//! a split plane visits both children over the same interval.) This costs a
//! rare extra cell visit and keeps the result equal to brute force unless a
//! hit distance carries a relative error above ~2⁻¹² (a triangle many
//! thousand times larger than its distance to the eye, seen at a grazing
//! angle).

use crate::geom::{Aabb, Ray, RayPrecomp, intersect_triangle};
use crate::scene::TriangleColumns;
use crate::tree::{Node, TreeIr, TriId};
use glam::Vec3;

/// Relative margin on cell boundaries (see the module docs).
pub const MARGIN: f32 = 1.0 / 4096.0;

/// Stack entries: one per inner node on a root path, so more than the
/// deepest tree ([`crate::tree::MAX_DEPTH`]) can have.
pub const MAX_STACK: usize = crate::tree::MAX_DEPTH as usize + 1;

/// The closest hit of a ray, or a miss.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Hit distance; `f32::INFINITY` for a miss.
    pub t: f32,
    /// The triangle hit; [`Hit::NO_TRI`] for a miss.
    pub tri: TriId,
}

impl Hit {
    pub const NO_TRI: TriId = TriId(u32::MAX);
    pub const MISS: Hit = Hit {
        t: f32::INFINITY,
        tri: Hit::NO_TRI,
    };

    pub fn is_hit(&self) -> bool {
        self.tri != Hit::NO_TRI
    }

    /// Keeps `(t, tri)` if it is closer, or equally close with a smaller id.
    #[inline]
    pub fn offer(&mut self, t: f32, tri: TriId) {
        if t < self.t || (t == self.t && tri < self.tri) {
            *self = Hit { t, tri };
        }
    }
}

/// Anything that answers closest-hit queries (used by the renderer).
pub trait ClosestHit: Sync {
    fn closest_hit(&self, ray: &Ray) -> Hit;
}

/// The scalar traverser over an in-memory tree.
pub struct TreeTracer<'a> {
    pub tree: &'a TreeIr,
    pub scene: &'a TriangleColumns,
}

impl ClosestHit for TreeTracer<'_> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        closest_hit(self.tree, self.scene, ray)
    }
}

/// Tests every triangle: the reference.
pub struct BruteForce<'a>(pub &'a TriangleColumns);

impl ClosestHit for BruteForce<'_> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        brute_force(self.0, ray)
    }
}

/// The closest hit by testing every triangle.
pub fn brute_force(scene: &TriangleColumns, ray: &Ray) -> Hit {
    let rp = RayPrecomp::new(ray);
    let mut best = Hit::MISS;
    for i in 0..scene.len() as u32 {
        if let Some(t) = intersect_triangle(&rp, &scene.tri(i), ray.tmin, best.t.min(ray.tmax)) {
            best.offer(t, TriId(i));
        }
    }
    best
}

/// The `[t0, t1]` interval of the ray inside the closed box `bounds`, or
/// `None` when it clearly misses.
pub fn clip_ray(bounds: &Aabb, ray: &Ray, inv_dir: Vec3) -> Option<(f32, f32)> {
    let mut t0 = ray.tmin;
    let mut t1 = ray.tmax;
    for k in 0..3 {
        let o = ray.origin[k];
        if ray.dir[k] == 0.0 {
            // Parallel to the slab: inside it for every t, or never. (The
            // general formula would give 0 · ∞ = NaN on a face plane.)
            if o < bounds.min[k] || o > bounds.max[k] {
                return None;
            }
            continue;
        }
        let a = (bounds.min[k] - o) * inv_dir[k];
        let b = (bounds.max[k] - o) * inv_dir[k];
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    if t1 < ray.tmin || t0 > t1 + t1 * MARGIN {
        None
    } else {
        Some((t0, t1))
    }
}

/// Front-to-back traversal with a stack of `(node, tmin, tmax)` entries.
pub fn closest_hit(tree: &TreeIr, scene: &TriangleColumns, ray: &Ray) -> Hit {
    let inv_dir = Vec3::ONE / ray.dir;
    let Some((t0, t1)) = clip_ray(&tree.bounds, ray, inv_dir) else {
        return Hit::MISS;
    };
    let rp = RayPrecomp::new(ray);
    let mut best = Hit::MISS;
    let mut stack = [(0u32, 0f32, 0f32); MAX_STACK];
    let mut sp = 0usize;
    let (mut node, mut tmin, mut tmax) = (0u32, t0, t1);
    loop {
        match tree.nodes[node as usize] {
            Node::Inner { axis, pos, right } => {
                let k = axis as usize;
                let o = ray.origin[k];
                let ts = (pos - o) * inv_dir[k];
                let below_first = o < pos || (o == pos && ray.dir[k] <= 0.0);
                let (near, far) = if below_first {
                    (node + 1, right.0)
                } else {
                    (right.0, node + 1)
                };
                if o == pos {
                    // The ray starts in the plane (or lies in it: ts is
                    // NaN). The far cell touches it only at t = 0, but a
                    // triangle there may be computed a rounding error
                    // beyond 0, so both cells are visited.
                    stack[sp] = (far, tmin, tmax);
                    sp += 1;
                    node = near;
                } else if ts <= 0.0 || ts - ts * MARGIN > tmax {
                    node = near;
                } else if ts + ts * MARGIN < tmin {
                    node = far;
                } else {
                    stack[sp] = (far, ts.max(tmin), tmax);
                    sp += 1;
                    node = near;
                    tmax = ts.min(tmax);
                }
            }
            Node::Leaf { start, count } => {
                for &tri in tree.leaf(start, count) {
                    if let Some(t) = intersect_triangle(&rp, &scene.tri(tri.0), ray.tmin, best.t.min(ray.tmax)) {
                        best.offer(t, tri);
                    }
                }
                // Resume with the nearest pending cell that may still hold
                // a hit at or before the best one. Once a hit lies inside
                // the current cell this skips every pending cell, which is
                // the early exit. A cell is never skipped on a tie: a
                // triangle there could hit at the same t with a smaller id.
                loop {
                    if sp == 0 {
                        return best;
                    }
                    sp -= 1;
                    (node, tmin, tmax) = stack[sp];
                    if tmin - tmin * MARGIN <= best.t {
                        break;
                    }
                }
            }
        }
    }
}
