//! Any-hit queries for a batch of rays as a stream (after Barringer &
//! Akenine-Möller 2014): the batch walks the tree together, each node
//! taking the rays that visit it, deciding them one after another with
//! the scalar walk's rule and handing each child its rays; a leaf tests
//! each of its triangles against all its rays. A part of the stream of
//! fewer than [`THIN`] rays goes on ray by ray with the scalar walk.
//!
//! Every ray visits exactly the cells the scalar walk would (the same
//! decision at every split, margins included) and is tested with the same
//! watertight test, so a ray is occluded here exactly when the scalar walk
//! says so; only the order of the cells differs, which an any-hit query
//! does not depend on.

use super::{MARGIN, NO_WORD, SourceNode, TraceStats, Walk, clip_ray, walk_cells};
use crate::geom::{Ray, RayPrecomp, intersect_triangle};
use glam::Vec3;

/// A node whose rays are fewer than this walks them one by one: a node
/// of the stream costs a loop over its rays and two lists, several scalar
/// steps when it holds one or two rays.
pub const THIN: usize = 4;

/// One ray in a part of the stream: its index and its interval in the
/// node's cell.
#[derive(Clone, Copy)]
struct Entry {
    ray: u32,
    tmin: f32,
    tmax: f32,
}

/// `out[i]`: whether anything is hit by `rays[i]` in `(tmin, tmax)`, for
/// every ray of the batch (`out.len() == rays.len()`).
pub fn occluded_stream<'a, W: Walk<'a>>(src: W, rays: &[Ray], out: &mut [bool]) {
    assert_eq!(rays.len(), out.len(), "one result per ray");
    let inv: Vec<Vec3> = rays.iter().map(|r| Vec3::ONE / r.dir).collect();
    let rp: Vec<RayPrecomp> = rays.iter().map(RayPrecomp::new).collect();
    out.fill(false);
    // The arena holds the parts of the stream waiting on the stack, each a
    // range of it; a part is always the arena's last until it is taken,
    // and what lies above a part when it is taken is finished.
    let mut arena: Vec<Entry> = Vec::with_capacity(rays.len() * 4);
    let bounds = src.bounds();
    for (i, r) in rays.iter().enumerate() {
        if let Some((t0, t1)) = clip_ray(&bounds, r, inv[i]) {
            arena.push(Entry {
                ray: i as u32,
                tmin: t0,
                tmax: t1,
            });
        }
    }
    let mut stack: Vec<(u32, usize, usize)> = vec![(0, 0, arena.len())];
    // Every (node, ray) visit is one of the scalar walks' steps, so the
    // stream takes at most their budgets together.
    let mut steps_left = u64::from(src.step_limit()) * rays.len() as u64;
    let mut scratch = TraceStats::default();
    let (mut lefts, mut rights): (Vec<Entry>, Vec<Entry>) = (Vec::new(), Vec::new());
    while let Some((node, start, end)) = stack.pop() {
        arena.truncate(end);
        let live_from = arena.len();
        for k in start..end {
            let e = arena[k];
            if !out[e.ray as usize] {
                arena.push(e);
            }
        }
        let part = live_from..arena.len();
        if part.is_empty() {
            continue;
        }
        let n = part.len() as u64;
        if steps_left < n {
            return;
        }
        steps_left -= n;
        if part.len() < THIN {
            for k in part {
                let e = arena[k];
                let i = e.ray as usize;
                let mut budget = u64::from(src.step_limit());
                out[i] = walk_cells::<W, true, false>(
                    src,
                    &rays[i],
                    &rp[i],
                    inv[i],
                    (node, e.tmin, e.tmax),
                    super::Hit::MISS,
                    &mut scratch,
                    &mut budget,
                )
                .is_hit();
            }
            continue;
        }
        match src.node(node) {
            SourceNode::Inner(n) => {
                if let Some(tri) = n.t_ref {
                    let v = src.triangle(tri);
                    for k in part.clone() {
                        let i = arena[k].ray as usize;
                        let r = &rays[i];
                        out[i] |= intersect_triangle(&rp[i], &v, r.tmin, r.tmax)
                            .is_some_and(|t| t < r.tmax);
                    }
                }
                let ax = usize::from((n.axis & 3).min(2));
                // The children's parts above this one, the left child's
                // (taken first) on top.
                lefts.clear();
                rights.clear();
                for k in part.clone() {
                    let e = arena[k];
                    let i = e.ray as usize;
                    if out[i] {
                        continue;
                    }
                    let (l, r) = decide(&rays[i], inv[i], ax, n.pos, e);
                    if let Some(l) = l {
                        lefts.push(l);
                    }
                    if let Some(r) = r {
                        rights.push(r);
                    }
                }
                let right_from = arena.len();
                arena.extend_from_slice(&rights);
                let left_from = arena.len();
                arena.extend_from_slice(&lefts);
                let left_to = arena.len();
                if n.right != NO_WORD && left_from > right_from {
                    stack.push((n.right, right_from, left_from));
                }
                if n.left != NO_WORD && left_to > left_from {
                    stack.push((n.left, left_from, left_to));
                }
            }
            SourceNode::Leaf(tris) => {
                for j in 0..tris.len() {
                    let v = src.triangle(tris.get(j));
                    for k in part.clone() {
                        let i = arena[k].ray as usize;
                        if out[i] {
                            continue;
                        }
                        let r = &rays[i];
                        out[i] = intersect_triangle(&rp[i], &v, r.tmin, r.tmax)
                            .is_some_and(|t| t < r.tmax);
                    }
                }
            }
        }
    }
}

/// Which children the scalar walk visits, with their intervals: `o ==
/// pos` both over the same interval; else near only, far only, or both,
/// by the walk's margins, a far child entered at `+∞` (a ray parallel to
/// the plane) not at all.
#[inline(always)]
fn decide(ray: &Ray, inv: Vec3, axis: usize, pos: f32, e: Entry) -> (Option<Entry>, Option<Entry>) {
    let o = ray.origin[axis];
    if o == pos {
        return (Some(e), Some(e));
    }
    let ts = (pos - o) * inv[axis];
    let near_only = ts <= 0.0 || ts - ts * MARGIN > e.tmax;
    let far_only = !near_only && ts + ts * MARGIN < e.tmin;
    let near = (!far_only).then_some(Entry {
        tmax: if near_only || ts >= e.tmax {
            e.tmax
        } else {
            ts
        },
        ..e
    });
    let lo = if ts > e.tmin { ts } else { e.tmin };
    let far = (!near_only && lo - lo * MARGIN <= f32::INFINITY).then_some(Entry {
        tmin: if far_only { e.tmin } else { lo },
        ..e
    });
    if o < pos { (near, far) } else { (far, near) }
}
