//! Rays that start where a hit was: a [`HitContext`] holds the root path
//! of the cell that contains a point (a hit point, the origin of the
//! shadow and ambient-occlusion rays that leave it), and the walk from it
//! climbs that path instead of descending from the root.
//!
//! **The walk from a context** is the scalar walk from the root, resumed
//! at the context's leaf with the cells that walk would have pushed on
//! its way down. The ray is tested against the hoisted triangles on the
//! path (each once: they apply to their node's whole subtree, and every
//! cell walked lies under them); one pass over the path's splits finds
//! the levels where the ray starts in the plane or on the sibling's side,
//! or crosses the plane before its end; at those alone the root walk's
//! expressions give the leaf's interval and each reached sibling's (a
//! near child ends at the plane, a far one starts there, margins
//! included), and the siblings are pushed, deepest on top. The leaf and
//! the siblings tile the root cell and the pending-cell rule is the
//! walk's, so the hit is brute force's, bit for bit, *whichever* point
//! the context was made for; where the point lies decides only how much
//! is walked. An AO ray of 5 % of the diagonal from its hit point takes
//! 35 node steps instead of 61 on ravenbridge (9 instead of 23 on
//! dieselpower); the time saved is about what the pass over the path and
//! the location cost (`docs/perf-notes.md`, "Rays from a hit context").
//!
//! A context names the tree it was made in (the address of its node
//! storage); a walk given another tree's context starts at the root, so
//! a stale context costs speed, never a wrong hit.

use super::{
    Hit, MARGIN, MAX_STACK, NO_WORD, Pending, PendingStack, RayStart, SourceNode, TraceStats, Walk,
    max_num, min_num, ray_start, test_one, walk_pending, walk_ray,
};
use crate::geom::{Ray, select_axis};
use glam::Vec3;
use std::mem::MaybeUninit;

/// The most levels a context holds. Trees are at most
/// [`crate::tree::MAX_DEPTH`] deep, but the depth rule keeps real ones
/// under 45 at 50 M triangles; a point deeper than this keeps the node at
/// this depth as its start, whose subtree the walk then descends (correct,
/// only slower), and the context stays 1 KiB.
pub const CONTEXT_LEVELS: usize = 64;

/// Where rays start in a tree: the root path (splits, siblings, hoisted
/// triangles) of the cell that holds a point. Made by
/// [`ClosestHit::locate_into`](super::ClosestHit::locate_into) (or
/// [`locate`]); used by
/// [`closest_hit_from`](super::ClosestHit::closest_hit_from) and
/// [`occluded_from`](super::ClosestHit::occluded_from), which return
/// exactly what [`closest_hit`](super::ClosestHit::closest_hit) and
/// [`occluded`](super::ClosestHit::occluded) return, for any ray, with
/// less work for rays that start near the point. The path is held as
/// columns, so that a ray's first pass over it is a vector loop. About
/// 1 KiB; [`locate_into`] reuses one.
#[derive(Clone, Debug)]
pub struct HitContext {
    /// The tree's identity ([`Walk::tag`]); `(0, 0)` for none.
    tag: (usize, usize),
    /// The node the path ends at: a leaf, `NO_WORD` (an empty child), or
    /// an inner node at [`CONTEXT_LEVELS`].
    start: u32,
    /// Path nodes used.
    len: usize,
    /// Per path node, its split position.
    pos: [f32; CONTEXT_LEVELS],
    /// Per path node, its split axis (bits 0–1), and bit 2 set when the
    /// path goes right (the sibling is the left child).
    flags: [u32; CONTEXT_LEVELS],
    /// Per path node, the child not on the path (`NO_WORD`: empty).
    sibling: [u32; CONTEXT_LEVELS],
    /// The hoisted triangles on the path, `hoisted[..n_hoisted]`.
    hoisted: [u32; CONTEXT_LEVELS],
    n_hoisted: usize,
    /// The cell record of [`ropes`](super::ropes) that holds the point
    /// (`u32::MAX` for none).
    pub(crate) cell: u32,
}

impl Default for HitContext {
    fn default() -> Self {
        HitContext {
            tag: (0, 0),
            start: NO_WORD,
            len: 0,
            pos: [0.0; CONTEXT_LEVELS],
            flags: [0; CONTEXT_LEVELS],
            sibling: [NO_WORD; CONTEXT_LEVELS],
            hoisted: [0; CONTEXT_LEVELS],
            n_hoisted: 0,
            cell: u32::MAX,
        }
    }
}

impl HitContext {
    /// Whether the context was made in the tree `walk` views.
    pub fn belongs_to<'a, W: Walk<'a>>(&self, walk: &W) -> bool {
        self.tag != (0, 0) && self.tag == walk.tag()
    }

    /// Names no path and no cell (what [`HitContext::default`] holds,
    /// without rewriting its 1 KiB).
    pub(crate) fn clear(&mut self) {
        self.tag = (0, 0);
        self.start = NO_WORD;
        self.len = 0;
        self.n_hoisted = 0;
        self.cell = u32::MAX;
    }
}

/// The context of the cell that holds `point` in the tree `walk` views.
pub fn locate<'a, W: Walk<'a>>(walk: W, point: Vec3) -> HitContext {
    let mut ctx = HitContext::default();
    locate_into(walk, point, &mut ctx);
    ctx
}

/// [`locate`] into an existing context (no 1 KiB to initialise). The
/// descent compares the point with one split a level, no ray arithmetic;
/// a point in a split plane goes left, one outside the root cell to the
/// nearest cell (any cell is correct, see the module docs).
#[inline]
pub fn locate_into<'a, W: Walk<'a>>(walk: W, point: Vec3, ctx: &mut HitContext) {
    let p = point.to_array();
    ctx.clear();
    ctx.tag = walk.tag();
    let mut node = 0u32;
    while ctx.len < CONTEXT_LEVELS {
        let SourceNode::Inner(n) = walk.node(node) else {
            break;
        };
        let k = (n.axis & 3) as usize;
        // A NaN coordinate goes right; any side is correct.
        let go_left = k < 3 && p[k] <= n.pos;
        let (next, sibling) = if go_left {
            (n.left, n.right)
        } else {
            (n.right, n.left)
        };
        let i = ctx.len;
        ctx.pos[i] = n.pos;
        ctx.flags[i] = u32::from(n.axis & 3) | (u32::from(!go_left) << 2);
        ctx.sibling[i] = sibling;
        if let Some(t) = n.t_ref {
            ctx.hoisted[ctx.n_hoisted] = t;
            ctx.n_hoisted += 1;
        }
        ctx.len += 1;
        node = next;
        if node == NO_WORD {
            break;
        }
    }
    ctx.start = node;
}

/// Whether an interval `(lo, hi)` of a cell is not clearly empty (by the
/// walk's margin; a NaN or infinite start, from a cell the ray never
/// enters, is).
#[inline(always)]
fn overlaps((lo, hi): (f32, f32)) -> bool {
    lo - lo.abs() * MARGIN <= hi + hi.abs() * MARGIN
}

/// The walk of `ray` from `ctx` (see the module docs); a context of
/// another tree walks from the root.
#[inline(always)]
pub(crate) fn walk_from<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool>(
    src: W,
    ctx: &HitContext,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Hit {
    if !ctx.belongs_to(&src) {
        return walk_ray::<W, ANY, COUNT>(src, ray, stats);
    }
    let Some(RayStart {
        inv_dir,
        t0,
        t1,
        rp,
    }) = ray_start::<W, COUNT>(src, ray, stats)
    else {
        return Hit::MISS;
    };
    let mut steps_left = u64::from(src.step_limit());
    let mut best = Hit::MISS;
    // Hoisted triangles apply to their node's whole subtree, and every
    // walk below starts under them: each is tested here, once.
    for &t in &ctx.hoisted[..ctx.n_hoisted.min(CONTEXT_LEVELS)] {
        if COUNT {
            stats.hoisted += 1;
        }
        if test_one::<W, ANY>(src, &rp, ray, t, &mut best) {
            return best;
        }
    }
    let len = ctx.len.min(CONTEXT_LEVELS);
    let org = ray.origin.to_array();
    let inv = inv_dir.to_array();
    // First, the levels where anything happens, in one pass with no
    // chain between levels (vectorised): the ray starts in the plane or
    // on the sibling's side, or crosses the plane before t1. At any other
    // level a walk from the root keeps the near child with its interval
    // unchanged (ts ≤ 0, or ts > t1 ≥ the interval's end) and never
    // visits the far one, so it is passed over.
    let mut busy = 0u64;
    for i in 0..len {
        let f = ctx.flags[i];
        let k = f & 3;
        let o = select_axis(org, k);
        let iv = select_axis(inv, k);
        let pos = ctx.pos[i];
        let ts = (pos - o) * iv;
        let sibling_left = f & 4 != 0;
        let in_plane = o == pos;
        let starts_sibling = (o < pos) == sibling_left;
        let crosses = !(ts <= 0.0 || ts - ts * MARGIN > t1);
        busy |= u64::from(in_plane | starts_sibling | crosses) << i;
    }
    // Down the busy levels: each cell's part of [t0, t1] by the scalar
    // walk's expressions (a near child ends at the plane, a far one
    // starts there), so that each sibling is walked over the interval a
    // walk from the root would give it, bounded by its parent's exit: a
    // sibling walked to t1 instead visits the cells beyond the parent's
    // faces (AO rays on ravenbridge: 2.2x the leaves). The siblings the
    // ray reaches are kept with their intervals, for the climb.
    let mut cells = [const { MaybeUninit::<Pending>::uninit() }; MAX_STACK];
    let mut pending = PendingStack::new(&mut cells);
    let (mut en, mut ex) = (t0, t1);
    while busy != 0 {
        let i = busy.trailing_zeros() as usize;
        busy &= busy - 1;
        let f = ctx.flags[i];
        let k = (f & 3) as usize;
        let sibling_left = f & 4 != 0;
        let (o, pos) = (org[k], ctx.pos[i]);
        let ts = (pos - o) * inv[k];
        let ahead = ts > 0.0;
        let near = (en, if ahead { min_num(ts, ex) } else { ex });
        let far = (
            if ahead {
                max_num(ts, en)
            } else {
                f32::INFINITY
            },
            ex,
        );
        let (child, sibling, visit) = if o == pos {
            // The ray lies in the plane at its start: both children over
            // the same interval.
            ((en, ex), (en, ex), true)
        } else if (o < pos) == sibling_left {
            // The ray starts on the sibling's side.
            (far, near, !(ahead && ts + ts * MARGIN < en))
        } else {
            (near, far, !(ts <= 0.0 || ts - ts * MARGIN > ex))
        };
        let s = ctx.sibling[i];
        // Without a branch: whether a sibling is reached is a coin toss
        // at the levels that get here (5.7 mispredictions an AO ray on
        // ravenbridge with the branch, in callgrind's model).
        pending.push_if(
            (s, sibling.0, sibling.1),
            visit & (s != NO_WORD) & overlaps(sibling),
        );
        (en, ex) = child;
    }
    // The walk from the root, resumed at the context's leaf with the
    // cells it would have pushed on the way down: the deepest sibling is
    // popped first, each skipped, as any pending cell, when it starts
    // clearly beyond the best hit.
    let start = if ctx.start != NO_WORD {
        (ctx.start, en, ex)
    } else {
        match pending.pop() {
            Some(cell) => cell,
            None => return best,
        }
    };
    walk_pending::<W, ANY, COUNT>(
        src,
        ray,
        &rp,
        inv_dir,
        start,
        best,
        stats,
        &mut steps_left,
        &mut pending,
    )
}
