//! Closest-hit queries: the scalar front-to-back kd-tree traverser, the 4×4
//! packet traverser ([`packet`]) and the brute-force reference.
//!
//! Consumes any [`KdSource`]: an in-memory [`TreeIr`] with its
//! [`TriangleColumns`] ([`TreeTracer`]), or a mapped `.kd` file
//! ([`KdFile`]); produces a [`Hit`] per ray, with the *input* triangle id. Every traverser uses the same watertight test
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

pub mod context;
mod file;
pub mod lanes;
pub mod packet;
pub mod rays;
pub mod ropes;
pub mod stream;
pub mod wide;

pub use context::{HitContext, locate, locate_into};
pub use file::FileWalk;
pub(crate) use file::NO_WORD;
pub use packet::OccluderCache;

use crate::format::{KdFile, LeafIndices};
use crate::geom::{Aabb, Ray, RayPrecomp, intersect_triangle};
use crate::scene::TriangleColumns;
use crate::simd::SimdLevel;
use crate::tree::{Node, TreeIr, TriId};
use glam::Vec3;
use std::mem::MaybeUninit;

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
    /// The triangle id of a miss.
    pub const NO_TRI: TriId = TriId(u32::MAX);
    /// No hit: `t` is +inf.
    pub const MISS: Hit = Hit {
        t: f32::INFINITY,
        tri: Hit::NO_TRI,
    };

    /// Whether a triangle was hit.
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

/// Anything that answers closest-hit and any-hit queries (used by the
/// renderer and the ray-file tracer).
pub trait ClosestHit: Sync {
    /// The closest hit with `t` in `(ray.tmin, ray.tmax]` (ties go to the smaller id).
    fn closest_hit(&self, ray: &Ray) -> Hit;

    /// Whether anything is hit at a `t` in `(tmin, tmax)`: exactly
    /// `closest_hit(ray).t < ray.tmax`, found with less work.
    fn occluded(&self, ray: &Ray) -> bool {
        self.closest_hit(ray).t < ray.tmax
    }

    /// Traces up to 16 rays (`out.len() == rays.len()`); the default traces
    /// them one by one, a packet tracer as one packet.
    fn closest_hit_n(&self, rays: &[Ray], out: &mut [Hit]) {
        for (r, h) in rays.iter().zip(out.iter_mut()) {
            *h = self.closest_hit(r);
        }
    }

    /// [`ClosestHit::occluded`] for up to 16 rays.
    fn occluded_n(&self, rays: &[Ray], out: &mut [bool]) {
        for (r, o) in rays.iter().zip(out.iter_mut()) {
            *o = self.occluded(r);
        }
    }

    /// [`ClosestHit::occluded_n`] that tests the triangles of `cache` first
    /// and leaves these rays' occluders in it for the next call: the same
    /// answers, less work where consecutive calls are blocked by the same
    /// triangles ([`OccluderCache`]). The default ignores the cache.
    fn occluded_n_cached(&self, rays: &[Ray], out: &mut [bool], cache: &mut OccluderCache) {
        let _ = cache;
        self.occluded_n(rays, out)
    }

    /// Traces a 4×4 block of rays.
    fn closest_hit_4x4(&self, rays: &[Ray; 16], out: &mut [Hit; 16]) {
        self.closest_hit_n(rays, out);
    }

    /// Makes `ctx` the context of the cell holding `point`, for rays that
    /// start there ([`context`]); the default leaves one that the `_from`
    /// queries trace from the root.
    fn locate_into(&self, point: Vec3, ctx: &mut HitContext) {
        let _ = point;
        *ctx = HitContext::default();
    }

    /// [`ClosestHit::closest_hit`], walked from `ctx` ([`context`]): the
    /// same hit for any ray, less work for one that starts near the point
    /// `ctx` was made for.
    fn closest_hit_from(&self, ctx: &HitContext, ray: &Ray) -> Hit {
        let _ = ctx;
        self.closest_hit(ray)
    }

    /// [`ClosestHit::occluded`], walked from `ctx`: exactly
    /// `closest_hit(ray).t < ray.tmax`.
    fn occluded_from(&self, ctx: &HitContext, ray: &Ray) -> bool {
        let _ = ctx;
        self.occluded(ray)
    }
}

/// An inner node as a traverser reads it: its split and children, in
/// source numbering (a struct rather than enum fields, so that each walk
/// names it once and reads its fields where it uses them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InnerNode {
    /// Split axis (0, 1, 2 for x, y, z).
    pub axis: u8,
    /// Split position on the axis.
    pub pos: f32,
    /// The child below the plane; an empty child without a node of its
    /// own (a file's, see `format::node`) is `NO_WORD` (`u32::MAX`),
    /// which [`Walk::node`] reads as an empty leaf without a load. (The
    /// scalar walk visits it so: skipping it at the parent measured 2–4 %
    /// more instructions for 1–3 % fewer steps; the packet walk skips
    /// it.)
    pub left: u32,
    /// The child above the plane (`NO_WORD` likewise).
    pub right: u32,
    /// The hoisted triangle of a type II node.
    pub t_ref: Option<u32>,
}

/// A node as a traverser sees it.
#[derive(Clone, Copy, Debug)]
pub enum SourceNode<'a> {
    /// An inner node, with its hoisted triangle if it has one (type II).
    Inner(InnerNode),
    /// A leaf and its triangles.
    Leaf(LeafTris<'a>),
}

/// The triangles of a leaf, in source numbering.
#[derive(Clone, Copy, Debug)]
pub enum LeafTris<'a> {
    /// Triangle ids of an in-memory tree.
    Ids(&'a [TriId]),
    /// The index list of a `.kd` file's leaf.
    File(LeafIndices<'a>),
}

impl LeafTris<'_> {
    /// The number of triangles.
    #[inline(always)]
    pub fn len(&self) -> usize {
        match *self {
            LeafTris::Ids(ids) => ids.len(),
            LeafTris::File(f) => f.len(),
        }
    }

    /// Whether the leaf is empty.
    #[inline(always)]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The `i`-th triangle (`i < len()`). The traversers loop over
    /// `0..len()` with this rather than pass a closure: a closure's body
    /// is a function of its own, compiled without the target features of
    /// the SIMD traversal that inlines it (the packet leaf kernel ran as
    /// SSE2 code inside the AVX-512 traversal that way).
    #[inline(always)]
    pub fn get(&self, i: usize) -> u32 {
        match *self {
            LeafTris::Ids(ids) => ids[i].0,
            LeafTris::File(LeafIndices::Idx32(s)) => s[i],
            LeafTris::File(LeafIndices::Idx16 { upper, low }) => upper | u32::from(low[i]),
            LeafTris::File(LeafIndices::One(t)) => t,
        }
    }
}

/// A kd-tree that traversers can walk: in memory or in a file. The
/// traversers take its [`Walk`] once per query, a cheap copyable view
/// (for a file: its sections as plain slices, so that a node step is a
/// load and a few bit operations).
pub trait KdSource: Sync {
    /// The view a traverser walks.
    type Walk<'a>: Walk<'a>
    where
        Self: 'a;
    /// Takes the view (once per tracer).
    fn walk(&self) -> Self::Walk<'_>;
}

/// The view of a tree a traverser walks.
pub trait Walk<'a>: Copy + Sync {
    /// The root cell.
    fn bounds(&self) -> Aabb;
    /// Node `n` (the root is 0).
    fn node(&self, n: u32) -> SourceNode<'a>;
    /// The vertices of a triangle (source numbering).
    fn triangle(&self, t: u32) -> [Vec3; 3];
    /// The input id reported for a triangle (ties are broken on it).
    fn input_id(&self, t: u32) -> TriId;
    /// The most nodes one traversal visits: each node of a tree at most
    /// once, so a walk that takes more steps is on nodes that share
    /// subtrees (a file not validated) and stops.
    fn step_limit(&self) -> u32;
    /// The tree's identity, for [`HitContext`]s: the address and length
    /// of its node storage (a context made in a tree that was dropped,
    /// whose storage a tree of as many nodes reuses, would walk the new
    /// tree along the old path: wrong hits, never unsafe ones).
    fn tag(&self) -> (usize, usize);
}

/// An in-memory tree and its scene.
#[derive(Clone, Copy)]
pub struct TreeTracer<'a> {
    /// The tree.
    pub tree: &'a TreeIr,
    /// The scene it was built over (source numbering = input ids).
    pub scene: &'a TriangleColumns,
}

impl KdSource for TreeTracer<'_> {
    type Walk<'a>
        = TreeTracer<'a>
    where
        Self: 'a;

    fn walk(&self) -> TreeTracer<'_> {
        *self
    }
}

impl<'a> Walk<'a> for TreeTracer<'a> {
    fn bounds(&self) -> Aabb {
        self.tree.bounds
    }

    #[inline]
    fn node(&self, n: u32) -> SourceNode<'a> {
        match self.tree.nodes[n as usize] {
            Node::Inner {
                axis,
                pos,
                right,
                t_ref,
            } => SourceNode::Inner(InnerNode {
                axis,
                pos,
                left: n + 1,
                right: right.0,
                t_ref: t_ref.map(|t| t.0),
            }),
            Node::Leaf { start, count } => {
                SourceNode::Leaf(LeafTris::Ids(self.tree.leaf(start, count)))
            }
        }
    }

    #[inline]
    fn triangle(&self, t: u32) -> [Vec3; 3] {
        self.scene.tri(t)
    }

    #[inline]
    fn step_limit(&self) -> u32 {
        u32::try_from(self.tree.nodes.len()).unwrap_or(u32::MAX)
    }

    #[inline]
    fn input_id(&self, t: u32) -> TriId {
        TriId(t)
    }

    fn tag(&self) -> (usize, usize) {
        (self.tree.nodes.as_ptr() as usize, self.tree.nodes.len())
    }
}

impl<D: AsRef<[u8]> + Sync> KdSource for KdFile<D> {
    type Walk<'a>
        = FileWalk<'a>
    where
        Self: 'a;

    fn walk(&self) -> FileWalk<'_> {
        FileWalk::new(self)
    }
}

/// Scalar traversal of any source (its [`Walk`] taken once).
pub struct Scalar<'a, S: KdSource + 'a> {
    walk: S::Walk<'a>,
    /// A level this CPU has ([`Scalar::with_level`]).
    level: SimdLevel,
}

impl<'a, S: KdSource> Scalar<'a, S> {
    /// Takes `src`'s walk once; the walk runs compiled for the best
    /// instruction set of this CPU ([`SimdLevel::detect`]): the scalar
    /// code alone gains the three-operand VEX forms and BMI (6.5 % fewer
    /// instructions a primary ray on dieselpower than the baseline x86-64
    /// build).
    pub fn new(src: &'a S) -> Self {
        Self::with_level(src, SimdLevel::detect())
    }

    /// Runs the walk compiled for `level` where this CPU has it, else for
    /// the best level it has ([`SimdLevel::usable`]); for the tests of
    /// every level's copy.
    pub fn with_level(src: &'a S, level: SimdLevel) -> Self {
        Self::on(src, SimdLevel::usable(level))
    }

    /// Takes `src`'s walk to run on `level`, which this CPU must have
    /// (the one constructor of both tracers; [`packet::PacketTracer`]
    /// holds a `Scalar` for its single rays).
    #[inline(always)]
    pub(crate) fn on(src: &'a S, level: SimdLevel) -> Self {
        Scalar {
            walk: src.walk(),
            level,
        }
    }

    /// The instruction set the walk runs on.
    pub fn level(&self) -> SimdLevel {
        self.level
    }

    #[inline(always)]
    fn walk<const ANY: bool>(&self, ray: &Ray) -> Hit {
        let w = self.walk;
        crate::simd_dispatch!(self.level, |_WIDE| {
            walk_ray::<_, ANY, false>(w, ray, &mut TraceStats::default())
        })
    }
}

impl<'a, S: KdSource> ClosestHit for Scalar<'a, S> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        self.walk::<false>(ray)
    }

    fn occluded(&self, ray: &Ray) -> bool {
        self.walk::<true>(ray).is_hit()
    }

    fn locate_into(&self, point: Vec3, ctx: &mut HitContext) {
        locate_into(self.walk, point, ctx);
    }

    fn closest_hit_from(&self, ctx: &HitContext, ray: &Ray) -> Hit {
        let w = self.walk;
        crate::simd_dispatch!(self.level, |_WIDE| {
            context::walk_from::<_, false, false>(w, ctx, ray, &mut TraceStats::default())
        })
    }

    fn occluded_from(&self, ctx: &HitContext, ray: &Ray) -> bool {
        let w = self.walk;
        crate::simd_dispatch!(self.level, |_WIDE| {
            context::walk_from::<_, true, false>(w, ctx, ray, &mut TraceStats::default())
        })
        .is_hit()
    }
}

impl ClosestHit for TreeTracer<'_> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        traverse(self, ray)
    }

    fn occluded(&self, ray: &Ray) -> bool {
        occluded(self, ray)
    }

    fn locate_into(&self, point: Vec3, ctx: &mut HitContext) {
        locate_into(*self, point, ctx);
    }

    fn closest_hit_from(&self, ctx: &HitContext, ray: &Ray) -> Hit {
        context::walk_from::<_, false, false>(*self, ctx, ray, &mut TraceStats::default())
    }

    fn occluded_from(&self, ctx: &HitContext, ray: &Ray) -> bool {
        context::walk_from::<_, true, false>(*self, ctx, ray, &mut TraceStats::default()).is_hit()
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
    let (lo, hi) = (bounds.min.to_array(), bounds.max.to_array());
    let (o, d, inv) = (
        ray.origin.to_array(),
        ray.dir.to_array(),
        inv_dir.to_array(),
    );
    let mut t0 = ray.tmin;
    let mut t1 = ray.tmax;
    for k in 0..3 {
        if d[k] == 0.0 {
            // Parallel to the slab: inside it for every t, or never. (The
            // general formula would give 0 · ∞ = NaN on a face plane.)
            if o[k] < lo[k] || o[k] > hi[k] {
                return None;
            }
            continue;
        }
        let a = (lo[k] - o[k]) * inv[k];
        let b = (hi[k] - o[k]) * inv[k];
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    if t1 < ray.tmin || t0 > t1 + t1 * MARGIN {
        None
    } else {
        Some((t0, t1))
    }
}

/// The scalar traversal of an in-memory tree.
pub fn closest_hit(tree: &TreeIr, scene: &TriangleColumns, ray: &Ray) -> Hit {
    traverse(&TreeTracer { tree, scene }, ray)
}

/// Work done by traversals, counted when asked for (the counting
/// traversal is a separate instantiation, so the fast path carries no
/// counters).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraceStats {
    /// Queries traced (rays; packets count their active rays).
    pub rays: u64,
    /// Nodes visited, inner and leaf (a packet counts one per node step).
    pub nodes: u64,
    /// Leaves visited.
    pub leaves: u64,
    /// Ray–triangle tests of leaf triangles (a packet counts one per lane).
    pub tris: u64,
    /// Ray–triangle tests of hoisted triangles (type II nodes).
    pub hoisted: u64,
    /// Ray–triangle tests of cached occluders ([`OccluderCache`]; one per
    /// lane).
    pub cached: u64,
    /// Packets traced, and the active lanes summed over their node steps
    /// (`lane_steps / nodes` is the packets' mean occupancy).
    pub packets: u64,
    /// Active lanes summed over packet node steps.
    pub lane_steps: u64,
}

impl TraceStats {
    /// Adds the counts of `o`.
    pub fn add(&mut self, o: &TraceStats) {
        self.rays += o.rays;
        self.nodes += o.nodes;
        self.leaves += o.leaves;
        self.tris += o.tris;
        self.hoisted += o.hoisted;
        self.cached += o.cached;
        self.packets += o.packets;
        self.lane_steps += o.lane_steps;
    }
}

/// Closest hit of a ray (front-to-back, early exit).
pub fn traverse<S: KdSource>(src: &S, ray: &Ray) -> Hit {
    walk_ray::<_, false, false>(src.walk(), ray, &mut TraceStats::default())
}

/// Whether anything is hit in `(tmin, tmax)` (stops at the first hit).
pub fn occluded<S: KdSource>(src: &S, ray: &Ray) -> bool {
    walk_ray::<_, true, false>(src.walk(), ray, &mut TraceStats::default()).is_hit()
}

/// [`traverse_counted`] walked from `ctx` ([`context`]).
pub fn traverse_from_counted<S: KdSource>(
    src: &S,
    ctx: &HitContext,
    ray: &Ray,
    any: bool,
    stats: &mut TraceStats,
) -> Hit {
    if any {
        context::walk_from::<_, true, true>(src.walk(), ctx, ray, stats)
    } else {
        context::walk_from::<_, false, true>(src.walk(), ctx, ray, stats)
    }
}

/// [`traverse`] (or [`occluded`], whose hit is any hit in `(tmin, tmax)`)
/// with its work added to `stats`.
pub fn traverse_counted<S: KdSource>(src: &S, ray: &Ray, any: bool, stats: &mut TraceStats) -> Hit {
    if any {
        walk_ray::<_, true, true>(src.walk(), ray, stats)
    } else {
        walk_ray::<_, false, true>(src.walk(), ray, stats)
    }
}

/// `a.max(b)` for a `b` that is never NaN, as one `maxss` (`f32::max`'s
/// NaN rule costs three instructions more a push in the walk); for a NaN
/// `a` it is `b`, as `f32::max` gives.
#[inline(always)]
fn max_num(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// `a.min(b)` for a `b` that is never NaN, as one `minss` (see [`max_num`]).
#[inline(always)]
fn min_num(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// Tests triangle `t_src` against `ray`, keeping the better hit in
/// `best`; under `ANY`, says whether the ray is done. A function rather
/// than a closure of the walk: a closure's body is compiled on its own,
/// without the target features of the packet traversal that inlines the
/// walk for its small packets and one-lane cells.
#[inline(always)]
pub(crate) fn test_one<'a, W: Walk<'a>, const ANY: bool>(
    src: W,
    rp: &RayPrecomp,
    ray: &Ray,
    t_src: u32,
    best: &mut Hit,
) -> bool {
    if let Some(t) = intersect_triangle(rp, &src.triangle(t_src), ray.tmin, best.t.min(ray.tmax)) {
        if ANY {
            if t < ray.tmax {
                *best = Hit {
                    t,
                    tri: src.input_id(t_src),
                };
                return true;
            }
        } else {
            best.offer(t, src.input_id(t_src));
        }
    }
    false
}

/// What every walk of a ray starts from: its inverse direction, its
/// interval in the root cell and the watertight test's constants.
pub(crate) struct RayStart {
    pub(crate) inv_dir: Vec3,
    pub(crate) t0: f32,
    pub(crate) t1: f32,
    pub(crate) rp: RayPrecomp,
}

/// The [`RayStart`] of `ray` in `src`, counted as a ray under `COUNT`;
/// `None` when it misses the root cell.
#[inline(always)]
pub(crate) fn ray_start<'a, W: Walk<'a>, const COUNT: bool>(
    src: W,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Option<RayStart> {
    if COUNT {
        stats.rays += 1;
    }
    let inv_dir = Vec3::ONE / ray.dir;
    let (t0, t1) = clip_ray(&src.bounds(), ray, inv_dir)?;
    Some(RayStart {
        inv_dir,
        t0,
        t1,
        rp: RayPrecomp::new(ray),
    })
}

/// One ray, front to back, with a fixed-size stack of pending cells.
/// `ANY`: stop at the first hit in `(tmin, tmax)`; `COUNT`: add the work
/// to `stats`.
#[inline(always)]
pub(crate) fn walk_ray<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool>(
    src: W,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Hit {
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
    let start = (0, t0, t1);
    walk_cells::<W, ANY, COUNT>(
        src,
        ray,
        &rp,
        inv_dir,
        start,
        Hit::MISS,
        stats,
        &mut steps_left,
    )
}

/// The scalar walk of the subtree at `start.0` over the ray's interval
/// `[start.1, start.2]` in its cell, keeping the closest of `best` and
/// the hits found (any hit under `ANY`). [`walk_ray`] starts it at the
/// root; the packet traverser hands it a lane of a cell that only that
/// lane or few others visit. It stops once `steps_left` (a node a step,
/// shared with the packet walk that hands it lanes) is spent.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn walk_cells<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool>(
    src: W,
    ray: &Ray,
    rp: &RayPrecomp,
    inv_dir: Vec3,
    start: (u32, f32, f32),
    best: Hit,
    stats: &mut TraceStats,
    steps_left: &mut u64,
) -> Hit {
    // Left uninitialised: zeroing 1.2 KB per ray cost 4 % of short rays'
    // time.
    let mut stack = [const { MaybeUninit::<Pending>::uninit() }; MAX_STACK];
    let mut pending = PendingStack::new(&mut stack);
    walk_pending::<W, ANY, COUNT>(
        src,
        ray,
        rp,
        inv_dir,
        start,
        best,
        stats,
        steps_left,
        &mut pending,
    )
}

/// A pending cell: its node and the ray's interval in it.
pub(crate) type Pending = (u32, f32, f32);

/// The walk's stack of pending cells: `cells[..len]` are written. The
/// traversal depth is at most MAX_DEPTH (checked by TreeIr::validate and
/// KdFile::validate), so `len` stays below MAX_STACK; a push checks it all
/// the same (the compare the indexing made anyway) and drops the cell of
/// a deeper path, which only a file that was not validated can make.
pub(crate) struct PendingStack<'s> {
    cells: &'s mut [MaybeUninit<Pending>; MAX_STACK],
    len: usize,
}

impl<'s> PendingStack<'s> {
    /// An empty stack over `cells`.
    #[inline(always)]
    pub(crate) fn new(cells: &'s mut [MaybeUninit<Pending>; MAX_STACK]) -> Self {
        PendingStack { cells, len: 0 }
    }

    /// Pushes `cell` when `keep`, without a branch on `keep` (the write
    /// is made either way, past the last cell when not kept).
    #[inline(always)]
    pub(crate) fn push_if(&mut self, cell: Pending, keep: bool) {
        if self.len < MAX_STACK {
            self.cells[self.len].write(cell);
            self.len += usize::from(keep);
        }
    }

    /// Pops the last cell pushed.
    #[inline(always)]
    pub(crate) fn pop(&mut self) -> Option<Pending> {
        if self.len == 0 {
            return None;
        }
        self.len -= 1;
        // SAFETY: `cells[..len]` are written (`new` starts empty, `push`
        // writes before it counts).
        Some(unsafe { self.cells[self.len].assume_init() })
    }
}

/// [`walk_cells`] with cells already pending below `start` (the walk from
/// a [`HitContext`] resumes the root walk at its leaf with the cells the
/// root walk would have pushed on the way down).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn walk_pending<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool>(
    src: W,
    ray: &Ray,
    rp: &RayPrecomp,
    inv_dir: Vec3,
    start: (u32, f32, f32),
    mut best: Hit,
    stats: &mut TraceStats,
    steps_left: &mut u64,
    pending: &mut PendingStack<'_>,
) -> Hit {
    // `stack[..sp]` are written (the stack's invariant), and the walk
    // keeps it so.
    let mut sp = pending.len;
    let stack = &mut *pending.cells;
    let (mut node, mut tmin, mut tmax) = start;
    let org = ray.origin.to_array();
    let dir = ray.dir.to_array();
    let inv = inv_dir.to_array();
    loop {
        if *steps_left == 0 {
            return best;
        }
        *steps_left -= 1;
        if COUNT {
            stats.nodes += 1;
        }
        match src.node(node) {
            SourceNode::Inner(n) => {
                if let Some(tri) = n.t_ref {
                    // Early intersection (Choi et al. 2013, §4.2): a hoisted
                    // triangle is tested when its node is visited.
                    if COUNT {
                        stats.hoisted += 1;
                    }
                    if test_one::<W, ANY>(src, rp, ray, tri, &mut best) {
                        return best;
                    }
                }
                // The one decision rule at a split (the packet traverser
                // makes it per lane with the same expressions), written with
                // branches: a predicted branch lets the next node's load
                // start before the decision is computed (branch-free selects
                // measured 1.9x slower on single rays).
                let k = n.axis as usize;
                let (o, d) = (org[k], dir[k]);
                if o == n.pos {
                    // The ray starts in the plane (or lies in it): both
                    // children over the same interval.
                    let (first, second) = if d <= 0.0 {
                        (n.left, n.right)
                    } else {
                        (n.right, n.left)
                    };
                    if first != NO_WORD {
                        if second != NO_WORD && sp < MAX_STACK {
                            stack[sp].write((second, tmin, tmax));
                            sp += 1;
                        }
                        node = first;
                        continue;
                    }
                    if second != NO_WORD {
                        node = second;
                        continue;
                    }
                    // Both empty: resume below.
                } else {
                    let ts = (n.pos - o) * inv[k];
                    // The side the ray starts on is a branch, not a select: each
                    // arm names its near and far child itself, so that the next
                    // node's load waits only on the prediction of this branch,
                    // not on this node's split position (with the child picked
                    // by a conditional move, single rays traced 1.4x slower).
                    //
                    // An empty child (a file's `NO_WORD`: no word, no triangles)
                    // is neither entered nor pushed; a step into one and its pop
                    // were a tenth of all steps (3.6 of 35 a primary ray on
                    // dieselpower, 11 of 88 on ravenbridge). The far child
                    // entered at once, where the near one is empty, is checked
                    // against the best hit as its pop would check it.
                    macro_rules! descend {
                        ($near:expr, $far:expr) => {{
                            if ts <= 0.0 || ts - ts * MARGIN > tmax {
                                if $near != NO_WORD {
                                    node = $near;
                                    continue;
                                }
                            } else if ts + ts * MARGIN < tmin {
                                if $far != NO_WORD {
                                    node = $far;
                                    continue;
                                }
                            } else if $near == NO_WORD {
                                let lo = max_num(ts, tmin);
                                if $far != NO_WORD && lo - lo * MARGIN <= best.t {
                                    node = $far;
                                    tmin = lo;
                                    continue;
                                }
                            } else {
                                if $far != NO_WORD && sp < MAX_STACK {
                                    stack[sp].write(($far, max_num(ts, tmin), tmax));
                                    sp += 1;
                                }
                                node = $near;
                                tmax = min_num(ts, tmax);
                                continue;
                            }
                        }};
                    }
                    if o < n.pos {
                        descend!(n.left, n.right);
                    } else {
                        descend!(n.right, n.left);
                    }
                }
            }
            SourceNode::Leaf(tris) => {
                if COUNT {
                    stats.leaves += 1;
                }
                for i in 0..tris.len() {
                    if COUNT {
                        stats.tris += 1;
                    }
                    if test_one::<W, ANY>(src, rp, ray, tris.get(i), &mut best) {
                        return best;
                    }
                }
            }
        }
        // Resume with the nearest pending cell that may still hold a hit
        // at or before the best one. Once a hit lies inside the current
        // cell this skips every pending cell, which is the early exit. A
        // cell is never skipped on a tie: a triangle there could hit at the
        // same t with a smaller id.
        loop {
            if sp == 0 {
                return best;
            }
            sp -= 1;
            // SAFETY: entries below the old `sp` were written.
            (node, tmin, tmax) = unsafe { stack[sp].assume_init() };
            // A cell entered at `tmin` = +∞ (pushed by a ray parallel to
            // its split plane) gives NaN here and is skipped: the packet
            // traverser's pop is this expression too.
            if tmin - tmin * MARGIN <= best.t {
                break;
            }
        }
    }
}
