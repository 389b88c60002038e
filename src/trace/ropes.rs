//! Rays that walk leaf to leaf: per leaf cell its box and six ropes
//! (Havran's neighbour links, optimised as Popov et al. 2007: per face,
//! the smallest node whose cell covers the whole face on its far side),
//! built in memory when a tree is opened for them. A ray that starts in a
//! known cell (a [`HitContext`] made by [`RopeTracer::locate_into`])
//! tests that cell's triangles, leaves it through the face it exits by,
//! and descends from that face's rope to the cell it enters, comparing
//! the entry distance with one split a level: no climb from the root and
//! no stack. A shadow or AO ray from a hit point crosses 2–3 cells, which
//! the walk from the root reaches only after ~30 levels.
//!
//! **Exact, as the other walks.** Every decision takes the root walk's
//! margin ([`MARGIN`]): a cell is left for its neighbour only when the
//! exit face is clearly the first (the next exit on another axis lies
//! clearly later) and the entered cell is chosen only when the entry
//! distance lies clearly off every split on the way down. A ray that
//! passes within the margin of an edge, starts outside its context's
//! cell or on one of its faces, lies in a face, or has a negative `tmin`
//! is handed to the walk
//! from the root over the rest of its interval (from the entry of the
//! last cell whose triangles it tested), so the hit is brute force's, bit
//! for bit. Closest-hit queries stop once the best hit lies clearly
//! inside the cell just tested, as the root walk's pop does.
//!
//! Ropes apply to trees without hoisted triangles (the `std` preset):
//! a slim tree's hoisted triangle applies to its node's whole subtree,
//! which a walk that never passes the node would have to track; those
//! trees keep [`context`](super::context)'s walk.

use super::context::HitContext;
use super::packet::PacketTracer;
use super::{
    ClosestHit, Hit, InnerNode, KdSource, MARGIN, NO_WORD, RayStart, Scalar, SourceNode,
    TraceStats, Walk, max_num, ray_start, test_one, walk_cells, walk_ray,
};
use crate::geom::Ray;
use glam::Vec3;
use thiserror::Error;

/// A rope that leads out of the scene.
const NONE: u32 = u32::MAX;
/// Set in a rope (and in a context's cell) that names a cell record
/// rather than an inner node.
const CELL: u32 = 1 << 31;

/// Why a tree has no ropes.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum RopesError {
    /// The tree hoists triangles into inner nodes (a slim preset).
    #[error(
        "ropes need a tree without hoisted triangles (build with --preset std): a hoisted triangle applies to its node's whole subtree"
    )]
    Hoisted,
    /// More cells than a rope can name, or a walk that does not end (a
    /// file whose children share subtrees).
    #[error("the tree has too many cells for ropes ({0})")]
    TooLarge(usize),
}

/// One leaf cell: its box, its ropes (per face `2·axis + (max side)`:
/// `CELL | record`, an inner node to descend from, or `NONE`) and its
/// leaf node (`NO_WORD` for an empty child without a node). 64 bytes, one
/// cache line.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Cell {
    lo: [f32; 3],
    hi: [f32; 3],
    rope: [u32; 6],
    node: u32,
}

/// The ropes of a tree ([`Ropes::new`]).
pub struct Ropes {
    cells: Vec<Cell>,
    /// Per node id: a leaf's cell record; an inner node's first empty
    /// child's record (its right empty child, when both are, is the
    /// next).
    slot: Vec<u32>,
    /// The tree's identity ([`Walk::tag`]).
    tag: (usize, usize),
}

/// A child as the builder and the descent name it: a cell or an inner
/// node.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Target {
    None,
    Node(u32),
    Cell(u32),
}

impl Target {
    fn encode(self) -> u32 {
        match self {
            Target::None => NONE,
            Target::Node(n) => n,
            Target::Cell(c) => CELL | c,
        }
    }
}

impl Ropes {
    /// The ropes of the tree `walk` views: two passes over its nodes (the
    /// cells numbered, then each cell's box and optimised ropes). Node
    /// ids are below the length of the node storage ([`Walk::tag`]'s
    /// second half); a child id outside it reads as an empty child, as
    /// [`Walk::node`] reads it.
    pub fn new<'a, W: Walk<'a>>(walk: W) -> Result<Ropes, RopesError> {
        let n_ids = walk.tag().1;
        let limit = walk.step_limit() as usize;
        let mut slot = vec![NONE; n_ids];
        // Pass 1: number the cells (leaves, and empty children without a
        // node) in depth-first order.
        let mut n_cells = 0usize;
        let mut stack = vec![0u32];
        let mut steps = 0usize;
        while let Some(n) = stack.pop() {
            steps += 1;
            if steps > limit || n_cells >= CELL as usize {
                return Err(RopesError::TooLarge(n_cells));
            }
            if n as usize >= n_ids {
                // Only the root can get here (children are checked below):
                // an empty tree is one empty cell.
                n_cells += 1;
                continue;
            }
            match walk.node(n) {
                SourceNode::Inner(i) => {
                    if i.t_ref.is_some() {
                        return Err(RopesError::Hoisted);
                    }
                    let mut first_empty = true;
                    for c in [i.left, i.right] {
                        if c as usize >= n_ids {
                            if first_empty {
                                slot[n as usize] = n_cells as u32;
                                first_empty = false;
                            }
                            n_cells += 1;
                        }
                    }
                    for c in [i.right, i.left] {
                        if (c as usize) < n_ids {
                            stack.push(c);
                        }
                    }
                }
                SourceNode::Leaf(_) => {
                    slot[n as usize] = n_cells as u32;
                    n_cells += 1;
                }
            }
        }
        let mut ropes = Ropes {
            cells: vec![
                Cell {
                    lo: [0.0; 3],
                    hi: [0.0; 3],
                    rope: [NONE; 6],
                    node: NO_WORD,
                };
                n_cells
            ],
            slot,
            tag: walk.tag(),
        };
        // Pass 2: each cell's box and ropes, handed down from the root.
        let b = walk.bounds();
        let root = ropes.target(walk, None, 0, false);
        let mut stack = vec![(root, b.min.to_array(), b.max.to_array(), [Target::None; 6])];
        while let Some((t, lo, hi, mut rope)) = stack.pop() {
            for (f, r) in rope.iter_mut().enumerate() {
                *r = ropes.optimise(walk, *r, f, &lo, &hi);
            }
            match t {
                Target::Cell(c) => {
                    let cell = &mut ropes.cells[c as usize];
                    cell.lo = lo;
                    cell.hi = hi;
                    cell.rope = rope.map(Target::encode);
                }
                Target::Node(n) => {
                    let SourceNode::Inner(i) = walk.node(n) else {
                        unreachable!("a node target is an inner node");
                    };
                    let k = usize::from(i.axis & 3).min(2);
                    let left = ropes.target(walk, Some(&i), n, false);
                    let right = ropes.target(walk, Some(&i), n, true);
                    let (mut lhi, mut rlo) = (hi, lo);
                    lhi[k] = i.pos;
                    rlo[k] = i.pos;
                    let (mut lrope, mut rrope) = (rope, rope);
                    lrope[2 * k + 1] = right;
                    rrope[2 * k] = left;
                    stack.push((right, rlo, hi, rrope));
                    stack.push((left, lo, lhi, lrope));
                }
                Target::None => {}
            }
        }
        // The leaf node of each cell.
        for (n, &s) in ropes.slot.iter().enumerate() {
            if s != NONE && matches!(walk.node(n as u32), SourceNode::Leaf(_)) {
                ropes.cells[s as usize].node = n as u32;
            }
        }
        Ok(ropes)
    }

    /// Bytes held (the cells and the slot per node id).
    pub fn bytes(&self) -> usize {
        self.cells.len() * std::mem::size_of::<Cell>() + self.slot.len() * 4
    }

    /// Cells (leaves and empty children).
    pub fn cells(&self) -> usize {
        self.cells.len()
    }

    /// The child of inner node `n` (`i`) on the `right` side as a target;
    /// `None` for `i` names the root.
    #[inline(always)]
    fn target<'a, W: Walk<'a>>(
        &self,
        walk: W,
        i: Option<&InnerNode>,
        n: u32,
        right: bool,
    ) -> Target {
        let Some(i) = i else {
            return match (n as usize) < self.slot.len() {
                true => self.node_target(walk, n),
                false => Target::Cell(0),
            };
        };
        let c = if right { i.right } else { i.left };
        if (c as usize) < self.slot.len() {
            self.node_target(walk, c)
        } else {
            let left_empty = (i.left as usize) >= self.slot.len();
            let s = self.slot[n as usize];
            Target::Cell(s + u32::from(right && left_empty))
        }
    }

    #[inline(always)]
    fn node_target<'a, W: Walk<'a>>(&self, walk: W, n: u32) -> Target {
        match walk.node(n) {
            SourceNode::Inner(_) => Target::Node(n),
            SourceNode::Leaf(_) => Target::Cell(self.slot[n as usize]),
        }
    }

    /// Pushes rope `r` of face `f` of the box `lo..hi` down to the
    /// smallest node whose cell still covers the whole face: through
    /// splits on the face's axis to the child next to the face, and
    /// through splits outside the face's extent to the child that holds
    /// it.
    fn optimise<'a, W: Walk<'a>>(
        &self,
        walk: W,
        mut r: Target,
        f: usize,
        lo: &[f32; 3],
        hi: &[f32; 3],
    ) -> Target {
        while let Target::Node(n) = r {
            let SourceNode::Inner(i) = walk.node(n) else {
                break;
            };
            let a = usize::from(i.axis & 3).min(2);
            let right = if a == f / 2 {
                // The neighbour across a max face lies above it: its
                // child next to the face is the left one.
                f.is_multiple_of(2)
            } else if i.pos >= hi[a] {
                false
            } else if i.pos <= lo[a] {
                true
            } else {
                break;
            };
            r = self.target(walk, Some(&i), n, right);
        }
        r
    }

    /// The cell record holding `point` (a point in a split plane goes
    /// left, as [`super::locate_into`] sends it).
    pub(crate) fn locate<'a, W: Walk<'a>>(&self, walk: W, point: Vec3) -> u32 {
        let p = point.to_array();
        let ids = self.slot.len();
        if ids == 0 {
            return 0;
        }
        // Each node decoded once: a leaf names its record, an empty child
        // its parent's (as `target` numbers them).
        let mut n = 0u32;
        for _ in 0..walk.step_limit() {
            let i = match walk.node(n) {
                SourceNode::Inner(i) => i,
                SourceNode::Leaf(_) => return self.slot[n as usize],
            };
            let k = usize::from(i.axis & 3).min(2);
            let right = p[k] > i.pos || p[k].is_nan();
            let child = if right { i.right } else { i.left };
            if (child as usize) < ids {
                n = child;
            } else {
                let left_empty = (i.left as usize) >= ids;
                return self.slot[n as usize] + u32::from(right && left_empty);
            }
        }
        NONE
    }
}

/// The walk of `ray` from cell record `cell` (see the module docs); a
/// cell of another tree, or none, walks from the root.
#[inline(always)]
pub(crate) fn walk_ropes<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool>(
    src: W,
    ropes: &Ropes,
    cell: u32,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Hit {
    let Some(first) = ropes.cells.get((cell & !CELL) as usize) else {
        return walk_ray::<W, ANY, COUNT>(src, ray, stats);
    };
    let org = ray.origin.to_array();
    let inside = (0..3).all(|k| first.lo[k] <= org[k] && org[k] <= first.hi[k]);
    // An origin on a face (within the margin) may meet the neighbour's
    // triangles at a rounded `t` just above 0, a triangle lying in the
    // face among them, which the walk from this cell never tests.
    let near = |v: f32, f: f32| (v - f).abs() <= v.abs().max(f.abs()) * MARGIN;
    let on_face = (0..3).any(|k| near(org[k], first.lo[k]) || near(org[k], first.hi[k]));
    if !(inside && !on_face && ray.tmin >= 0.0 && ropes.tag == src.tag()) {
        return walk_ray::<W, ANY, COUNT>(src, ray, stats);
    }
    let Some(start) = ray_start::<W, COUNT>(src, ray, stats) else {
        return Hit::MISS;
    };
    let RayStart {
        inv_dir,
        t0,
        t1,
        rp,
    } = start;
    let dir = ray.dir.to_array();
    let inv = inv_dir.to_array();
    // The face a ray leaves a cell by on each axis (+∞ and −∞ inverses,
    // of ±0 directions, pick the face whose distance is +∞).
    let up = [inv[0] > 0.0, inv[1] > 0.0, inv[2] > 0.0];
    // The axes the ray runs across in no time: on them it lies in a face
    // of every cell whose face plane holds its origin.
    let flat = [dir[0] == 0.0, dir[1] == 0.0, dir[2] == 0.0];
    let mut steps_left = u64::from(src.step_limit());
    let mut best = Hit::MISS;
    let mut rec = (cell & !CELL) as usize;
    // The entry of the cell being walked: where the walk from the root
    // resumes when a decision is too close to call.
    let mut en = t0;
    let resume_at = 'chain: loop {
        if steps_left == 0 {
            return best;
        }
        steps_left -= 1;
        let Some(c) = ropes.cells.get(rec) else {
            break 'chain en;
        };
        if COUNT {
            stats.nodes += 1;
            stats.leaves += 1;
        }
        if c.node != NO_WORD
            && let SourceNode::Leaf(tris) = src.node(c.node)
        {
            for i in 0..tris.len() {
                if COUNT {
                    stats.tris += 1;
                }
                if test_one::<W, ANY>(src, &rp, ray, tris.get(i), &mut best) {
                    return best;
                }
            }
        }
        let face = |k: usize| if up[k] { c.hi[k] } else { c.lo[k] };
        let tx = [
            (face(0) - org[0]) * inv[0],
            (face(1) - org[1]) * inv[1],
            (face(2) - org[2]) * inv[2],
        ];
        let k = if tx[0] <= tx[1] && tx[0] <= tx[2] {
            0
        } else if tx[1] <= tx[2] {
            1
        } else {
            2
        };
        let x = tx[k];
        if x.is_nan() || (0..3).any(|a| flat[a] && (org[a] == c.lo[a] || org[a] == c.hi[a])) {
            // The ray lies in a face of the cell (the one it would leave
            // by, where `tx` is 0·∞, or the one behind it): the
            // neighbour's triangles in that face are met too. (A NaN exit
            // is left to the root walk whatever its cause.)
            break 'chain en;
        }
        // The ray ends in this cell, or (closest hit) its best hit lies
        // clearly before the next cell: the root walk's pop rule.
        let x_lo = x - x.abs() * MARGIN;
        if x_lo > t1 || (!ANY && x_lo > best.t) {
            return best;
        }
        // Leaving through an edge or a corner: the next cell is not
        // clearly the face's neighbour.
        let second = tx[(k + 1) % 3].min(tx[(k + 2) % 3]);
        if second - second.abs() * MARGIN <= x + x.abs() * MARGIN {
            break 'chain en;
        }
        let mut r = c.rope[2 * k + usize::from(up[k])];
        if r == NONE {
            // Out of the scene: the ray ends within the margin of its
            // bounds.
            return best;
        }
        if r & CELL == 0 {
            // Down from the rope's node to the cell entered at `x`.
            r = loop {
                if steps_left == 0 {
                    return best;
                }
                steps_left -= 1;
                if COUNT {
                    stats.nodes += 1;
                }
                let i = match src.node(r) {
                    SourceNode::Inner(i) => i,
                    SourceNode::Leaf(_) => break ropes.slot[r as usize],
                };
                let a = usize::from(i.axis & 3).min(2);
                let o = org[a];
                let right = if o == i.pos {
                    // A ray that starts in the plane is on its direction's
                    // side after its start.
                    if dir[a] == 0.0 {
                        break 'chain en;
                    }
                    dir[a] > 0.0
                } else {
                    let ts = (i.pos - o) * inv[a];
                    // Whether the ray has crossed the plane at its entry.
                    let crossed = if ts <= 0.0 || ts - ts * MARGIN > x {
                        false
                    } else if ts + ts * MARGIN < x {
                        true
                    } else {
                        break 'chain en;
                    };
                    (o > i.pos) != crossed
                };
                let child = if right { i.right } else { i.left };
                if (child as usize) < ropes.slot.len() {
                    r = child;
                } else {
                    let left_empty = (i.left as usize) >= ropes.slot.len();
                    break ropes.slot[r as usize] + u32::from(right && left_empty);
                }
            };
        }
        rec = (r & !CELL) as usize;
        en = x;
    };
    // The walk from the root has its own step limit: the chain's steps
    // are not its nodes.
    walk_cells::<W, ANY, COUNT>(
        src,
        ray,
        &rp,
        inv_dir,
        (0, max_num(resume_at, t0), t1),
        best,
        stats,
        &mut u64::from(src.step_limit()),
    )
}

/// A tracer whose `_from` queries walk by ropes, a context located as a
/// cell record; its other queries are a [`PacketTracer`]'s (single rays
/// from the root, batches in packets), so that a renderer traces its
/// primary rays in packets and its secondary rays from their hit's cell.
pub struct RopeTracer<'a, S: KdSource + 'a> {
    packet: PacketTracer<'a, S>,
    ropes: &'a Ropes,
}

impl<'a, S: KdSource> RopeTracer<'a, S> {
    /// A tracer over `src` and its `ropes` (made by [`Ropes::new`] from
    /// `src`'s walk: ropes of another tree are never used, every query
    /// then walks from the root).
    pub fn new(src: &'a S, ropes: &'a Ropes) -> Self {
        RopeTracer {
            packet: PacketTracer::new(src),
            ropes,
        }
    }

    /// [`RopeTracer::new`] compiled for `level` where this CPU has it
    /// ([`PacketTracer::with_level`]); for the tests of every level's copy.
    pub fn with_level(src: &'a S, ropes: &'a Ropes, level: crate::simd::SimdLevel) -> Self {
        RopeTracer {
            packet: PacketTracer::with_level(src, level),
            ropes,
        }
    }

    fn scalar(&self) -> &Scalar<'a, S> {
        self.packet.scalar()
    }

    /// [`ClosestHit::closest_hit_from`] with its work added to `stats`.
    pub fn trace_from_counted(
        &self,
        ctx: &HitContext,
        ray: &Ray,
        any: bool,
        stats: &mut TraceStats,
    ) -> Hit {
        let (w, cell) = (self.scalar().walk, ctx.cell);
        if any {
            walk_ropes::<_, true, true>(w, self.ropes, cell, ray, stats)
        } else {
            walk_ropes::<_, false, true>(w, self.ropes, cell, ray, stats)
        }
    }
}

impl<'a, S: KdSource> ClosestHit for RopeTracer<'a, S> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        self.packet.closest_hit(ray)
    }

    fn occluded(&self, ray: &Ray) -> bool {
        self.packet.occluded(ray)
    }

    fn closest_hit_n(&self, rays: &[Ray], out: &mut [Hit]) {
        self.packet.closest_hit_n(rays, out)
    }

    fn occluded_n(&self, rays: &[Ray], out: &mut [bool]) {
        self.packet.occluded_n(rays, out)
    }

    /// Locates the cell record only: the context's root path is left
    /// unset (a [`Scalar`] given it walks from the root).
    fn locate_into(&self, point: Vec3, ctx: &mut HitContext) {
        ctx.clear();
        ctx.cell = CELL | self.ropes.locate(self.scalar().walk, point);
    }

    fn closest_hit_from(&self, ctx: &HitContext, ray: &Ray) -> Hit {
        let (w, ropes, cell) = (self.scalar().walk, self.ropes, ctx.cell);
        crate::simd_dispatch!(self.scalar().level, |_WIDE| {
            walk_ropes::<_, false, false>(w, ropes, cell, ray, &mut TraceStats::default())
        })
    }

    fn occluded_from(&self, ctx: &HitContext, ray: &Ray) -> bool {
        let (w, ropes, cell) = (self.scalar().walk, self.ropes, ctx.cell);
        crate::simd_dispatch!(self.scalar().level, |_WIDE| {
            walk_ropes::<_, true, false>(w, ropes, cell, ray, &mut TraceStats::default())
        })
        .is_hit()
    }
}
