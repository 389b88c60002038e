//! The 4×4 ray-packet traverser (Wald et al. 2001 style, over kd-trees):
//! 16 rays walk the tree together, and each leaf triangle is tested against
//! all active rays at once in SIMD lanes.
//!
//! A packet is up to 16 rays with an active mask, and it walks the tree
//! whole, whatever its rays' octants: each lane by its own split rule,
//! each child first for most of the lanes that visit both children (all of
//! them in a one-octant packet, the scalar order). Splitting an
//! incoherent packet by octant instead, with the octants of fewer than 8
//! rays going ray by ray, traced ambient-occlusion packets (4 origins × 4
//! directions) at half the rays per second, closest or any hit. In an
//! any-hit packet, a cell that only one lane visits is walked by that lane
//! alone with the scalar traverser. When all lanes
//! of a packet share the watertight test's axis permutation, as
//! nearly all coherent rays do, the leaf kernel picks each vertex
//! component once for all lanes instead of per lane. Each lane makes
//! exactly the scalar traverser's decisions (its split rule, with the same
//! expressions): a child is visited when any active lane needs it, and a
//! lane is active in a cell only when the scalar traverser would visit that
//! cell. Pending cells are culled per lane by the same rule. The
//! ray–triangle kernel performs the scalar watertight test's operations in
//! the same order (no fused multiply–add), so a packet returns exactly the
//! scalar traverser's hits, bit for bit, whatever instruction set ran it.
//! Any-hit queries drop a lane at its first hit and end when none is left;
//! in a batch they first test the triangles that blocked the packet before
//! ([`OccluderCache`]).
//!
//! **Instruction sets.** The whole packet traversal (split decisions and
//! leaf kernel) is compiled three times, for AVX-512, for AVX2 and for the
//! x86-64 baseline (SSE2), and chosen at run time by CPU feature detection;
//! on other architectures the portable version runs. The lane work is
//! written as branch-free loops over 16 lanes that LLVM vectorises to the
//! widest registers the target feature allows.

// Lane loops index several arrays by lane: the form LLVM vectorises.
#![allow(clippy::needless_range_loop)]

use super::{
    ClosestHit, Hit, KdSource, MARGIN, MAX_STACK, NO_WORD, Scalar, SourceNode, TraceStats, Walk,
};
use crate::geom::{
    Ray, RayPrecomp, edges_need_f64, intersect_triangle, scaled_distance, select_axis,
    sheared_edges, t_needs_f64,
};
use crate::tree::TriId;
use arrayvec::ArrayVec;
use glam::Vec3;

/// Rays in a packet.
pub const LANES: usize = 16;

/// A packet of fewer rays than this goes ray by ray: a packet step costs
/// several scalar steps whatever its occupancy.
pub const MIN_LANES: u32 = 8;

/// A cell that at most this many lanes of an any-hit packet visit is
/// walked lane by lane, each with the scalar traverser: a packet step
/// costs several scalar steps (1 lane: +13 % ambient-occlusion rays per
/// second; 2: +7 %; 4: −2 %). Closest-hit packets keep every cell (with
/// 1 lane, primary packets traced 15 % slower).
pub const SCALAR_LANES: u32 = 1;

pub(super) type Lanes = [f32; LANES];

/// Structure-of-arrays form of up to 16 rays, with the per-ray constants
/// of the watertight test. Lanes past the last ray repeat ray 0 and are
/// never active.
pub(super) struct Packet {
    pub(super) o: [Lanes; 3],
    pub(super) dir: [Lanes; 3],
    pub(super) inv: [Lanes; 3],
    pub(super) tmin: Lanes,
    pub(super) tmax: Lanes,
    /// Axis permutation as selectors: `kx[i] == k` picks component `k`.
    kx: [u8; LANES],
    ky: [u8; LANES],
    kz: [u8; LANES],
    sx: Lanes,
    sy: Lanes,
    sz: Lanes,
}

// The methods are inlined into the per-instruction-set traversal; as
// functions of their own they would run as baseline (SSE2) code.
impl Packet {
    #[inline(always)]
    pub(super) fn new(rays: &[Ray]) -> Packet {
        debug_assert!(!rays.is_empty() && rays.len() <= LANES);
        let mut p = Packet {
            o: [[0.0; LANES]; 3],
            dir: [[0.0; LANES]; 3],
            inv: [[0.0; LANES]; 3],
            tmin: [0.0; LANES],
            tmax: [0.0; LANES],
            kx: [0; LANES],
            ky: [0; LANES],
            kz: [0; LANES],
            sx: [0.0; LANES],
            sy: [0.0; LANES],
            sz: [0.0; LANES],
        };
        // A full packet reads its rays in order: with a lane's index
        // chosen per lane (`rays[0]` past the end), LLVM loads the fields
        // by gathers, which on Zen 4 were 15 % of a primary packet's time.
        let lane = |p: &mut Packet, i: usize, r: &Ray| {
            let (o, d) = (r.origin.to_array(), r.dir.to_array());
            for k in 0..3 {
                p.o[k][i] = o[k];
                p.dir[k][i] = d[k];
            }
            p.tmin[i] = r.tmin;
            p.tmax[i] = r.tmax;
        };
        if let Ok(full) = <&[Ray; LANES]>::try_from(rays) {
            for (i, r) in full.iter().enumerate() {
                lane(&mut p, i, r);
            }
        } else {
            for i in 0..LANES {
                lane(&mut p, i, rays.get(i).unwrap_or(&rays[0]));
            }
        }
        // `RayPrecomp::new` and the inverse direction in lanes, with the
        // same expressions (called per lane, the scalar constructor took
        // 8 % of an ambient-occlusion packet's time).
        let [dx, dy, dz] = &p.dir;
        for i in 0..LANES {
            let (x, y, z) = (dx[i], dy[i], dz[i]);
            p.inv[0][i] = 1.0 / x;
            p.inv[1][i] = 1.0 / y;
            p.inv[2][i] = 1.0 / z;
            let (ax, ay, az) = (x.abs(), y.abs(), z.abs());
            let x_max = (ax >= ay) & (ax >= az);
            let y_max = !x_max & (ay >= az);
            let kz: u8 = if x_max {
                0
            } else if y_max {
                1
            } else {
                2
            };
            let d_kz = if x_max {
                x
            } else if y_max {
                y
            } else {
                z
            };
            let (k1, k2) = (
                if kz == 2 { 0 } else { kz + 1 },
                if kz == 0 { 2 } else { kz - 1 },
            );
            let swap = d_kz < 0.0;
            let kx = if swap { k2 } else { k1 };
            let ky = if swap { k1 } else { k2 };
            p.kx[i] = kx;
            p.ky[i] = ky;
            p.kz[i] = kz;
            p.sx[i] = select_axis([x, y, z], kx) / d_kz;
            p.sy[i] = select_axis([x, y, z], ky) / d_kz;
            p.sz[i] = 1.0 / d_kz;
        }
        p
    }

    /// Lane `i`'s constants of the scalar test, for its fallback and for
    /// a lane walked alone; rebuilt from the lane arrays rather than
    /// stored (16 copies of 48 bytes written per packet for a rare path).
    #[inline(always)]
    pub(super) fn precomp(&self, i: usize) -> RayPrecomp {
        RayPrecomp {
            origin: Vec3::new(self.o[0][i], self.o[1][i], self.o[2][i]),
            kx: usize::from(self.kx[i]),
            ky: usize::from(self.ky[i]),
            kz: usize::from(self.kz[i]),
            sx: self.sx[i],
            sy: self.sy[i],
            sz: self.sz[i],
        }
    }

    /// The permutation all lanes of `mask` share, if they do.
    #[inline(always)]
    pub(super) fn shared_permutation(&self, mask: u16) -> Option<[usize; 3]> {
        let first = mask.trailing_zeros() as usize;
        let (kx, kz) = (self.kx[first], self.kz[first]);
        let same = (0..LANES)
            .filter(|i| mask & (1 << i) != 0)
            .all(|i| self.kx[i] == kx && self.kz[i] == kz);
        same.then(|| [kx as usize, self.ky[first] as usize, kz as usize])
    }
}

/// The best hit per lane.
pub(super) struct Best {
    pub(super) t: Lanes,
    pub(super) id: [u32; LANES],
}

impl Best {
    /// No hit in any lane.
    pub(super) const NONE: Best = Best {
        t: [f32::INFINITY; LANES],
        id: [u32::MAX; LANES],
    };

    /// Lane `i`'s best hit ([`Hit::MISS`] where it has none).
    #[inline(always)]
    pub(super) fn lane(&self, i: usize) -> Hit {
        Hit {
            t: self.t[i],
            tri: TriId(self.id[i]),
        }
    }

    /// Makes `h` lane `i`'s best hit.
    #[inline(always)]
    pub(super) fn set_lane(&mut self, i: usize, h: Hit) {
        self.t[i] = h.t;
        self.id[i] = h.tri.0;
    }
}

/// The lanes a triangle test found: hits to keep, and lanes that leave
/// `f32` (an edge function zero or out of range, or the distance out of
/// range) and need the scalar test's double-precision fallback.
struct LaneHits {
    t: Lanes,
    ok: u16,
    fallback: u16,
}

/// The watertight test of one triangle in all lanes, each lane with its
/// own axis permutation.
#[inline(always)]
fn kernel_any_perm<const M: bool>(p: &Packet, tri: &[Vec3; 3], best: &Best) -> LaneHits {
    let mut t_out = [0f32; LANES];
    let mut ok = [false; LANES];
    let mut fallback = [false; LANES];
    let sel = |s: u8, v: Vec3| -> f32 {
        if s == 0 {
            v.x
        } else if s == 1 {
            v.y
        } else {
            v.z
        }
    };
    for i in 0..LANES {
        let org = Vec3::new(p.o[0][i], p.o[1][i], p.o[2][i]);
        let a = tri[0] - org;
        let b = tri[1] - org;
        let c = tri[2] - org;
        let (kx, ky, kz) = (p.kx[i], p.ky[i], p.kz[i]);
        let (akz, bkz, ckz) = (sel(kz, a), sel(kz, b), sel(kz, c));
        let (ax, ay) = (sel(kx, a), sel(ky, a));
        let (bx, by) = (sel(kx, b), sel(ky, b));
        let (cx, cy) = (sel(kx, c), sel(ky, c));
        (t_out[i], ok[i], fallback[i]) =
            lane_test(p, i, best, [ax, ay, akz], [bx, by, bkz], [cx, cy, ckz]);
    }
    pack::<M>(t_out, ok, fallback)
}

/// The watertight test of one triangle in all lanes, which share the axis
/// permutation `k`: each vertex component is picked once.
#[inline(always)]
fn kernel_shared_perm<const M: bool>(
    p: &Packet,
    tri: &[Vec3; 3],
    k: [usize; 3],
    best: &Best,
) -> LaneHits {
    let mut t_out = [0f32; LANES];
    let mut ok = [false; LANES];
    let mut fallback = [false; LANES];
    let [kx, ky, kz] = k;
    let pick = |v: Vec3| [v[kx], v[ky], v[kz]];
    let (ta, tb, tc) = (pick(tri[0]), pick(tri[1]), pick(tri[2]));
    let (ox, oy, oz) = (&p.o[kx], &p.o[ky], &p.o[kz]);
    for i in 0..LANES {
        // `tri[j] - org`, component by component: the scalar test's
        // subtractions.
        let a = [ta[0] - ox[i], ta[1] - oy[i], ta[2] - oz[i]];
        let b = [tb[0] - ox[i], tb[1] - oy[i], tb[2] - oz[i]];
        let c = [tc[0] - ox[i], tc[1] - oy[i], tc[2] - oz[i]];
        (t_out[i], ok[i], fallback[i]) = lane_test(p, i, best, a, b, c);
    }
    pack::<M>(t_out, ok, fallback)
}

/// The rest of the watertight test in lane `i`, given the vertices
/// relative to the origin in permuted order `[x, y, z]`, up to the
/// lane's best hit.
#[inline(always)]
fn lane_test(
    p: &Packet,
    i: usize,
    best: &Best,
    a: [f32; 3],
    b: [f32; 3],
    c: [f32; 3],
) -> (f32, bool, bool) {
    let limit = if best.t[i] < p.tmax[i] {
        best.t[i]
    } else {
        p.tmax[i]
    };
    watertight_lane([p.sx[i], p.sy[i], p.sz[i]], p.tmin[i], limit, a, b, c)
}

/// The watertight test of one lane after the permutation, for the shear
/// `[sx, sy, sz]`: the scalar test's expressions in its order, so the
/// packets' and the lanes' (`lanes.rs`) tests agree with it bit for bit.
/// Returns `t`, whether it is a hit in `(tmin, limit]`, and whether the
/// scalar test would redo it in `f64` (then `ok` is not to be read).
#[inline(always)]
pub(super) fn watertight_lane(
    [sx, sy, sz]: [f32; 3],
    tmin: f32,
    limit: f32,
    a: [f32; 3],
    b: [f32; 3],
    c: [f32; 3],
) -> (f32, bool, bool) {
    let [u, v, w] = sheared_edges(sx, sy, a, b, c);
    let mixed = ((u < 0.0) | (v < 0.0) | (w < 0.0)) & ((u > 0.0) | (v > 0.0) | (w > 0.0));
    let det = u + v + w;
    let t_scaled = scaled_distance(sz, [u, v, w], a, b, c);
    let t = t_scaled / det;
    // Exactly where the scalar test leaves `f32` (`mixed` is only read
    // where no edge needs `f64`, as there).
    let fallback = edges_need_f64(u, v, w) | (!mixed & t_needs_f64(det, t_scaled, t));
    let ok = !mixed & (det != 0.0) & (t > tmin) & (t <= limit);
    (t, ok, fallback)
}

#[inline(always)]
fn pack<const M: bool>(t: Lanes, ok: [bool; LANES], fallback: [bool; LANES]) -> LaneHits {
    LaneHits {
        t,
        ok: bits::<M>(ok),
        fallback: bits::<M>(fallback),
    }
}

/// The lane mask of 16 flags: bit `i` is `b[i]`. On x86-64 the 16 flag
/// bytes go through SSE2's byte mask (`pmovmskb`, in every instruction
/// set's build): LLVM keeps the flags as bytes in memory, and the
/// shift-and-or loop it was given before compiled to a chain of 48
/// extracts, shifts and ors even in the AVX-512 build (perf: a fifth of a
/// primary packet's time). Elsewhere each 8 flags (bytes of 0 or 1) are
/// gathered into one byte by one multiplication.
#[inline(always)]
pub(super) fn bits<const MASKS: bool>(b: [bool; LANES]) -> u16 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{
            _mm_loadu_si128, _mm_movemask_epi8, _mm_setzero_si128, _mm_sub_epi8,
        };
        let bytes = b.map(u8::from);
        // SAFETY: SSE2 is part of the x86-64 baseline, and the load reads
        // the 16 bytes of `bytes` (unaligned load).
        unsafe {
            let v = _mm_loadu_si128(bytes.as_ptr().cast());
            // Each byte is 0 or 1: negated it is 0 or all ones, whose sign
            // bit the byte mask collects. Written as a negation (not a
            // shift of bit 0 to bit 7), the sign extension of the lane
            // compares is visible to LLVM, which then takes the mask from
            // the compares (the AVX-512 copy straight from its mask
            // register): packets 2–6 % faster.
            _mm_movemask_epi8(_mm_sub_epi8(_mm_setzero_si128(), v)) as u16
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        const GATHER: u64 = 0x0102_0408_1020_4080;
        let x = u128::from_le_bytes(b.map(u8::from));
        let (lo, hi) = (x as u64, (x >> 64) as u64);
        ((lo.wrapping_mul(GATHER) >> 56) | ((hi.wrapping_mul(GATHER) >> 56) << 8)) as u16
    }
}

pub use crate::simd::SimdLevel;

/// Packet traversal of any source; also answers single rays (with the
/// [`Scalar`] traverser it holds, on the same walk and level).
pub struct PacketTracer<'a, S: KdSource + 'a> {
    /// The walk and a level this CPU has ([`PacketTracer::with_level`]).
    scalar: Scalar<'a, S>,
}

impl<'a, S: KdSource> PacketTracer<'a, S> {
    /// Uses the best instruction set of this CPU.
    pub fn new(src: &'a S) -> Self {
        Self::with_level(src, SimdLevel::detect())
    }

    /// Uses `level` if this CPU has it ([`SimdLevel::available`]), else
    /// the baseline kernel.
    pub fn with_level(src: &'a S, level: SimdLevel) -> Self {
        // `usable` keeps a level this CPU has; checked without the
        // allocation of `available`, since the facade makes a tracer per
        // packet.
        let level = if SimdLevel::usable(level) == level {
            level
        } else {
            SimdLevel::Baseline
        };
        PacketTracer {
            scalar: Scalar::on(src, level),
        }
    }

    /// The instruction set the packets run on.
    pub fn level(&self) -> SimdLevel {
        self.scalar.level()
    }

    /// The scalar traverser its single rays run on.
    pub(crate) fn scalar(&self) -> &Scalar<'a, S> {
        &self.scalar
    }

    /// Traces up to 16 rays as a packet, closest hit (`ANY == false`) or
    /// any hit in `(tmin, tmax)`, adding the work to `stats` when
    /// `COUNT`.
    fn dispatch<const ANY: bool, const COUNT: bool>(
        &self,
        rays: &[Ray],
        out: &mut [Hit],
        stats: &mut TraceStats,
    ) {
        assert!(rays.len() <= LANES && out.len() == rays.len());
        if rays.is_empty() {
            return;
        }
        let w = self.scalar.walk;
        crate::simd_dispatch!(self.scalar.level, |WIDE| trace_rays::<_, ANY, COUNT, WIDE>(
            w, rays, out, stats
        ))
    }

    /// Traces up to 16 rays as any-hit queries, `cache`'s triangles first
    /// ([`OccluderCache`]); a function of its own, so that the closest-hit
    /// packets' code is not touched by it.
    fn dispatch_cached<const COUNT: bool>(
        &self,
        rays: &[Ray],
        out: &mut [Hit],
        stats: &mut TraceStats,
        cache: &mut OccluderCache,
    ) {
        assert!(rays.len() <= LANES && out.len() == rays.len());
        if rays.is_empty() {
            return;
        }
        let w = self.scalar.walk;
        crate::simd_dispatch!(
            self.scalar.level,
            |WIDE| trace_rays_cached::<_, COUNT, WIDE>(w, rays, out, stats, cache)
        )
    }

    /// [`ClosestHit::closest_hit_n`] or [`ClosestHit::occluded_n`] (a hit
    /// per ray, any hit when `any`) with its work added to `stats`.
    ///
    /// # Panics
    ///
    /// If `rays` holds more than 16 rays or `out` is not as long.
    pub fn trace_counted(&self, rays: &[Ray], any: bool, out: &mut [Hit], stats: &mut TraceStats) {
        if any {
            self.dispatch::<true, true>(rays, out, stats)
        } else {
            self.dispatch::<false, true>(rays, out, stats)
        }
    }

    /// [`PacketTracer::trace_counted`] whose any-hit rays test `cache`'s
    /// triangles first, as [`ClosestHit::occluded_n_cached`]'s do (counted
    /// in [`TraceStats::cached`]).
    ///
    /// # Panics
    ///
    /// If `rays` holds more than 16 rays or `out` is not as long.
    pub fn trace_counted_cached(
        &self,
        rays: &[Ray],
        any: bool,
        out: &mut [Hit],
        stats: &mut TraceStats,
        cache: &mut OccluderCache,
    ) {
        if any {
            self.dispatch_cached::<true>(rays, out, stats, cache)
        } else {
            self.trace_counted(rays, false, out, stats)
        }
    }
}

impl<'a, S: KdSource> ClosestHit for PacketTracer<'a, S> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        self.scalar.closest_hit(ray)
    }

    fn occluded(&self, ray: &Ray) -> bool {
        self.scalar.occluded(ray)
    }

    fn locate_into(&self, point: Vec3, ctx: &mut super::HitContext) {
        self.scalar.locate_into(point, ctx);
    }

    fn closest_hit_from(&self, ctx: &super::HitContext, ray: &Ray) -> Hit {
        self.scalar.closest_hit_from(ctx, ray)
    }

    fn occluded_from(&self, ctx: &super::HitContext, ray: &Ray) -> bool {
        self.scalar.occluded_from(ctx, ray)
    }

    fn closest_hit_n(&self, rays: &[Ray], out: &mut [Hit]) {
        self.dispatch::<false, false>(rays, out, &mut TraceStats::default())
    }

    fn occluded_n(&self, rays: &[Ray], out: &mut [bool]) {
        let mut hits = [Hit::MISS; LANES];
        let hits = &mut hits[..rays.len()];
        self.dispatch::<true, false>(rays, hits, &mut TraceStats::default());
        for (o, h) in out.iter_mut().zip(hits.iter()) {
            *o = h.is_hit();
        }
    }

    fn occluded_n_cached(&self, rays: &[Ray], out: &mut [bool], cache: &mut OccluderCache) {
        let mut hits = [Hit::MISS; LANES];
        let hits = &mut hits[..rays.len()];
        self.dispatch_cached::<false>(rays, hits, &mut TraceStats::default(), cache);
        for (o, h) in out.iter_mut().zip(hits.iter()) {
            *o = h.is_hit();
        }
    }
}

/// A cell of the packet's walk. Aligned to a cache line so that the
/// 64-byte loads and stores of its intervals never span two lines.
#[repr(C, align(64))]
struct Entry {
    tmin: Lanes,
    tmax: Lanes,
    node: u32,
    mask: u16,
}

/// The per-lane children and intervals at a split.
struct LaneSplit {
    left: u16,
    right: u16,
    /// Lanes that meet the left child first (origin below the plane, or
    /// in it going down): the scalar traverser's order, per lane.
    below: u16,
    l_tmin: Lanes,
    l_tmax: Lanes,
    r_tmin: Lanes,
    r_tmax: Lanes,
}

/// One lane's case at a split: the scalar traverser's expressions (the
/// ray starts in the plane, near only, far only, both), branch-free so
/// that the lane loops around it vectorise. Returns `(below_first,
/// near_visited, far_visited, near_hi, far_lo)`: the near interval is
/// `(tmin, near_hi)`, the far one `(far_lo, tmax)`.
#[inline(always)]
fn split_lane(
    o: f32,
    d: f32,
    inv: f32,
    pos: f32,
    tmin: f32,
    tmax: f32,
) -> (bool, bool, bool, f32, f32) {
    let ts = (pos - o) * inv;
    let on_plane = o == pos;
    // Non-short-circuit `|` and `&` keep the loop free of branches.
    let below_first = (o < pos) | (on_plane & (d <= 0.0));
    let near_only = !on_plane & ((ts <= 0.0) | (ts - ts * MARGIN > tmax));
    let far_only = !on_plane & !near_only & (ts + ts * MARGIN < tmin);
    let both_split = !on_plane & !near_only & !far_only;
    let near_hi = if both_split { ts.min(tmax) } else { tmax };
    let far_lo = if both_split { ts.max(tmin) } else { tmin };
    (below_first, !far_only, !near_only, near_hi, far_lo)
}

/// The scalar traverser's split rule for 16 lanes at once: which lanes
/// visit which child, and each child's interval per lane. Each lane makes
/// exactly the scalar decision.
#[inline(always)]
fn split_lanes<const M: bool>(p: &Packet, k: usize, pos: f32, cur: &Entry) -> LaneSplit {
    let mut out = LaneSplit {
        left: 0,
        right: 0,
        below: 0,
        l_tmin: [0.0; LANES],
        l_tmax: [0.0; LANES],
        r_tmin: [0.0; LANES],
        r_tmax: [0.0; LANES],
    };
    let mut l_vis = [false; LANES];
    let mut r_vis = [false; LANES];
    let mut below = [false; LANES];
    for i in 0..LANES {
        let (tmin, tmax) = (cur.tmin[i], cur.tmax[i]);
        let (below_first, near_vis, far_vis, near_hi, far_lo) =
            split_lane(p.o[k][i], p.dir[k][i], p.inv[k][i], pos, tmin, tmax);
        below[i] = below_first;
        l_vis[i] = if below_first { near_vis } else { far_vis };
        r_vis[i] = if below_first { far_vis } else { near_vis };
        out.l_tmin[i] = if below_first { tmin } else { far_lo };
        out.l_tmax[i] = if below_first { near_hi } else { tmax };
        out.r_tmin[i] = if below_first { far_lo } else { tmin };
        out.r_tmax[i] = if below_first { tmax } else { near_hi };
    }
    out.left = bits::<M>(l_vis);
    out.right = bits::<M>(r_vis);
    out.below = bits::<M>(below);
    out
}

/// The intervals of the child the packet visits first and of the one it
/// visits second, `[first tmin, first tmax, second tmin, second tmax]`,
/// recomputed per lane once the packet's order is known (`LEFT_FIRST`, a
/// constant so that each order's loop is a plain select); the lane loop
/// of [`split_lanes`] and this one share their arithmetic after inlining.
///
/// The AVX-512 copy uses it; the others choose two of
/// [`LaneSplit`]'s four intervals by reference. Chosen that way, the
/// AVX-512 copy stores four 64-byte arrays a step and loads two of them
/// back at once, which Zen 4 does not forward from its split 512-bit
/// stores: its primary packets ran at 0.70× of this way's (dieselpower,
/// one thread). The AVX2 copy, whose 32-byte stores forward, runs 8 %
/// slower this way: it keeps the flags as bytes and recomputes the split.
#[inline(always)]
fn split_intervals<const LEFT_FIRST: bool>(
    p: &Packet,
    k: usize,
    pos: f32,
    cur: &Entry,
) -> [Lanes; 4] {
    let (mut f_tmin, mut f_tmax) = ([0.0; LANES], [0.0; LANES]);
    let (mut s_tmin, mut s_tmax) = ([0.0; LANES], [0.0; LANES]);
    for i in 0..LANES {
        let (tmin, tmax) = (cur.tmin[i], cur.tmax[i]);
        let (below_first, _, _, near_hi, far_lo) =
            split_lane(p.o[k][i], p.dir[k][i], p.inv[k][i], pos, tmin, tmax);
        // A lane's near child is the packet's first where its order
        // agrees with the packet's.
        let near_first = below_first == LEFT_FIRST;
        f_tmin[i] = if near_first { tmin } else { far_lo };
        f_tmax[i] = if near_first { near_hi } else { tmax };
        s_tmin[i] = if near_first { far_lo } else { tmin };
        s_tmax[i] = if near_first { tmax } else { near_hi };
    }
    [f_tmin, f_tmax, s_tmin, s_tmax]
}

/// Walks a packet of at least [`MIN_LANES`] rays as one, and fewer ray by
/// ray; inlined into one copy per instruction set, so that its lane loops
/// are vectorised for that set.
#[inline(always)]
fn trace_rays<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool, const M: bool>(
    src: W,
    rays: &[Ray],
    out: &mut [Hit],
    stats: &mut TraceStats,
) {
    if rays.len() < MIN_LANES as usize {
        for (r, o) in rays.iter().zip(out.iter_mut()) {
            *o = super::walk_ray::<_, ANY, COUNT>(src, r, stats);
        }
        return;
    }
    let p = Packet::new(rays);
    let mut best = Best::NONE;
    walk_packet::<_, ANY, COUNT, M, _>(src, rays, &p, all_lanes(rays), &mut best, stats, &mut ());
    write_hits(&best, out);
}

/// [`trace_rays`] for any-hit queries that test `cache`'s triangles first
/// and leave the packet's occluders in it (not those found by a lane
/// walking alone: its walk reports input ids, and the cache needs source
/// numbers).
#[inline(always)]
fn trace_rays_cached<'a, W: Walk<'a>, const COUNT: bool, const M: bool>(
    src: W,
    rays: &[Ray],
    out: &mut [Hit],
    stats: &mut TraceStats,
    cache: &mut OccluderCache,
) {
    let cached = cache.tris(&src);
    if rays.len() < MIN_LANES as usize {
        for (r, o) in rays.iter().zip(out.iter_mut()) {
            *o = cached_hit::<_, COUNT>(src, r, &cached, stats)
                .unwrap_or_else(|| super::walk_ray::<_, true, COUNT>(src, r, stats));
        }
        return;
    }
    let p = Packet::new(rays);
    let mut best = Best::NONE;
    let mask = all_lanes(rays);
    // The cache's triangles first, in all lanes; the walk takes the lanes
    // they leave.
    let mut occ = [u32::MAX; LANES];
    let done = test_cached::<_, COUNT, M>(src, &p, &cached, mask, &mut best, stats, &mut occ);
    if mask & !done != 0 {
        walk_packet::<_, true, COUNT, M, _>(
            src,
            rays,
            &p,
            mask & !done,
            &mut best,
            stats,
            &mut occ,
        );
    }
    cache.update(&occ);
    write_hits(&best, out);
}

/// Tests `cached`'s triangles in the lanes of `mask` until all are
/// blocked; returns the blocked lanes, their occluders noted in `occ`.
#[inline(always)]
pub(super) fn test_cached<'a, W: Walk<'a>, const COUNT: bool, const M: bool>(
    src: W,
    p: &Packet,
    cached: &[u32],
    mask: u16,
    best: &mut Best,
    stats: &mut TraceStats,
    occ: &mut [u32; LANES],
) -> u16 {
    let mut done = 0u16;
    let perm = p.shared_permutation(mask);
    for &t in cached {
        if COUNT {
            stats.cached += u64::from((mask & !done).count_ones());
        }
        let h = test_triangle::<_, true, M>(src, p, perm, t, mask & !done, best);
        occ.note(h, t);
        done |= h;
        if done == mask {
            break;
        }
    }
    done
}

/// The lane mask of a packet of `rays`.
#[inline(always)]
pub(super) fn all_lanes(rays: &[Ray]) -> u16 {
    if rays.len() == LANES {
        u16::MAX
    } else {
        (1u16 << rays.len()) - 1
    }
}

/// The packet's hits, one per ray.
#[inline(always)]
pub(super) fn write_hits(best: &Best, out: &mut [Hit]) {
    for (i, o) in out.iter_mut().enumerate() {
        *o = if best.id[i] == u32::MAX {
            Hit::MISS
        } else {
            Hit {
                t: best.t[i],
                tri: TriId(best.id[i]),
            }
        };
    }
}

/// The hit of the first of `tris` that `ray` hits in `(tmin, tmax)`, by the
/// scalar walk's any-hit test.
#[inline(always)]
fn cached_hit<'a, W: Walk<'a>, const COUNT: bool>(
    src: W,
    ray: &Ray,
    tris: &[u32],
    stats: &mut TraceStats,
) -> Option<Hit> {
    if tris.is_empty() {
        return None;
    }
    let rp = RayPrecomp::new(ray);
    let mut hit = Hit::MISS;
    for &t in tris {
        if COUNT {
            stats.cached += 1;
        }
        if super::test_one::<W, true>(src, &rp, ray, t, &mut hit) {
            return Some(hit);
        }
    }
    None
}

/// [`super::clip_ray`] in 16 lanes: the lanes that enter the box, and
/// their intervals (the same expressions, so the same bits).
#[inline(always)]
fn clip_lanes<const M: bool>(p: &Packet, bounds: &crate::geom::Aabb) -> (u16, Lanes, Lanes) {
    let mut t0 = p.tmin;
    let mut t1 = p.tmax;
    let mut miss = [false; LANES];
    for k in 0..3 {
        let (lo, hi) = (bounds.min[k], bounds.max[k]);
        for i in 0..LANES {
            let (o, d, inv) = (p.o[k][i], p.dir[k][i], p.inv[k][i]);
            // Parallel to the slab: inside it for every t, or never.
            let parallel = d == 0.0;
            miss[i] |= parallel & ((o < lo) | (o > hi));
            let a = (lo - o) * inv;
            let b = (hi - o) * inv;
            t0[i] = if parallel { t0[i] } else { t0[i].max(a.min(b)) };
            t1[i] = if parallel { t1[i] } else { t1[i].min(a.max(b)) };
        }
    }
    let mut enter = [false; LANES];
    for i in 0..LANES {
        enter[i] = !(miss[i] | (t1[i] < p.tmin[i]) | (t0[i] > t1[i] + t1[i] * MARGIN));
    }
    (bits::<M>(enter), t0, t1)
}

/// Tests one triangle in the lanes of `mask`; returns the lanes it hit
/// (their first hit, for any-hit queries). Always inlined into the walk
/// (as a closure called from two places it was a call per triangle).
#[inline(always)]
pub(super) fn test_triangle<'a, W: Walk<'a>, const ANY: bool, const M: bool>(
    src: W,
    p: &Packet,
    perm: Option<[usize; 3]>,
    t_src: u32,
    mask: u16,
    best: &mut Best,
) -> u16 {
    test_triangle_of::<_, ANY, M>(src, p, perm, t_src, &src.triangle(t_src), mask, best)
}

/// [`test_triangle`] of triangle `t_src` whose vertices `tri` the caller
/// has at hand.
#[inline(always)]
pub(super) fn test_triangle_of<'a, W: Walk<'a>, const ANY: bool, const M: bool>(
    src: W,
    p: &Packet,
    perm: Option<[usize; 3]>,
    t_src: u32,
    tri: &[Vec3; 3],
    mask: u16,
    best: &mut Best,
) -> u16 {
    let id = src.input_id(t_src).0;
    // The lanes' best hits are read here, before the kernel, and written
    // back whole below: with the select's old value a load of the same
    // address in the same block, LLVM stores only the taken lanes by a
    // masked store (`vpmaskmovd` in the AVX2 copy), slow on AMD cores and
    // not forwarded to the next triangle's loads.
    let (old_t, old_id) = (best.t, best.id);
    let lanes = match perm {
        Some(k) => kernel_shared_perm::<M>(p, tri, k, best),
        None => kernel_any_perm::<M>(p, tri, best),
    };
    // Keep each lane's hit if it is closer (or, for any-hit queries,
    // before tmax), all lanes at once.
    let ok = lanes.ok & mask & !lanes.fallback;
    let mut take = [false; LANES];
    for i in 0..LANES {
        let t = lanes.t[i];
        let better = if ANY {
            t < p.tmax[i]
        } else {
            (t < old_t[i]) | ((t == old_t[i]) & (id < old_id[i]))
        };
        take[i] = (ok & (1 << i) != 0) & better;
        best.t[i] = if take[i] { t } else { old_t[i] };
        best.id[i] = if take[i] { id } else { old_id[i] };
    }
    let mut hit = bits::<M>(take);
    let mut fallback = lanes.fallback & mask;
    while fallback != 0 {
        let i = fallback.trailing_zeros() as usize;
        fallback &= fallback - 1;
        let limit = best.t[i].min(p.tmax[i]);
        if let Some(t) = intersect_triangle(&p.precomp(i), tri, p.tmin[i], limit) {
            if ANY {
                if t < p.tmax[i] {
                    best.t[i] = t;
                    best.id[i] = id;
                    hit |= 1 << i;
                }
            } else if t < best.t[i] || (t == best.t[i] && id < best.id[i]) {
                best.t[i] = t;
                best.id[i] = id;
            }
        }
    }
    hit
}

/// The triangles that occluded the last packet of an any-hit batch, tested
/// first in the next ([`ClosestHit::occluded_n_cached`]): the shadow-ray
/// cache of Haines & Greenberg (1986). Consecutive rays of a renderer's
/// batch (the shadow rays of neighbouring pixels) are mostly blocked by the
/// same few triangles, and one triangle test in 16 lanes costs less than one
/// packet step: shadow packets ran 2.2× as fast on ravenbridge and 1.4×
/// on dieselpower, ambient-occlusion packets at 0.97–1.04×.
///
/// The answers are exact with any contents: a cached triangle counts only
/// where the watertight test (the traversal's own) hits it in `(tmin,
/// tmax)`, so some triangle is hit before `tmax` and
/// `closest_hit(ray).t < tmax`. A cache filled in one tree and handed to
/// another (a different node storage) is emptied on first use.
#[derive(Clone, Copy, Debug, Default)]
pub struct OccluderCache {
    /// Source numbers in the tree of `tag`; `tris[..len]` are set.
    tris: [u32; OCCLUDERS],
    len: u8,
    /// The tree's [`Walk::tag`].
    tag: (usize, usize),
}

/// Triangles a cache keeps: a renderer's AO packet of 16 rays from a
/// tile's hit points has up to 16 occluders, and ravenbridge's AO rays
/// (97 % occluded) ran 1.07–1.11× as fast with 8 as with 4 in the AO
/// frame (1.10× in the AVX2 copy), the other shared scenes' within
/// 2 %; shadow packets, whose lanes share fewer occluders, ran within
/// 5 % either way. With 2, ravenbridge's shadow packets ran 8 % slower.
const OCCLUDERS: usize = 8;

impl OccluderCache {
    /// An empty cache.
    pub fn new() -> OccluderCache {
        OccluderCache::default()
    }

    /// How many triangles the next packet tests first.
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    /// Whether the next packet tests no triangle first.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The cached triangles, once the cache is known to be `src`'s.
    #[inline(always)]
    pub(super) fn tris<'a, W: Walk<'a>>(&mut self, src: &W) -> ArrayVec<u32, OCCLUDERS> {
        let tag = src.tag();
        if self.tag != tag {
            *self = OccluderCache {
                tag,
                ..OccluderCache::default()
            };
        }
        self.tris[..usize::from(self.len)].iter().copied().collect()
    }

    /// Makes this packet's occluders (`occ`, per lane; `u32::MAX`: none)
    /// the next packet's, the first [`OCCLUDERS`] in lane order: a cached
    /// triangle that blocked no lane is dropped, so rays that share no
    /// occluder test each at most once. Measured against the alternatives
    /// (dieselpower and ravenbridge, AMD EPYC): keeping the old contents
    /// through a packet that nothing blocked ran ambient-occlusion packets
    /// 9 % slower, keeping only the occluders of two lanes gave up a third
    /// of the shadow rays' gain, and a cache idle for 2^k − 1 packets after
    /// k packets it did not help lost 7 % of the shadow rays' speed and
    /// gained no ambient-occlusion speed.
    #[inline(never)]
    pub(super) fn update(&mut self, occ: &[u32; LANES]) {
        let mut n = 0usize;
        let mut blocked = bits::<false>(occ.map(|t| t != u32::MAX));
        while blocked != 0 {
            let t = occ[blocked.trailing_zeros() as usize];
            blocked &= blocked - 1;
            // The eight slots compared at once, one byte a slot, those
            // past `n` masked off (compared one by one with `k < n`, the
            // update took 5 % of ravenbridge's AO packet instructions).
            let same = u64::from_le_bytes(self.tris.map(|c| u8::from(c == t)));
            if same & ((1u64 << (8 * n)) - 1) == 0 {
                self.tris[n] = t;
                n += 1;
                if n == OCCLUDERS {
                    break;
                }
            }
        }
        self.len = n as u8;
    }
}

/// Where a packet walk notes the triangle that blocked each lane: per lane
/// (`[u32; LANES]`, for the cache) or nowhere (`()`: closest hits and
/// uncached any-hit queries, whose code is then the walk alone).
pub(super) trait Occluders {
    /// Notes triangle `t` as the occluder of the lanes of `hit`.
    fn note(&mut self, hit: u16, t: u32);
}

impl Occluders for () {
    #[inline(always)]
    fn note(&mut self, _: u16, _: u32) {}
}

impl Occluders for [u32; LANES] {
    #[inline(always)]
    fn note(&mut self, mut hit: u16, t: u32) {
        while hit != 0 {
            let i = hit.trailing_zeros() as usize;
            hit &= hit - 1;
            self[i] = t;
        }
    }
}

/// Walks the lanes of `mask` as one packet, whatever their octants.
#[inline(always)]
fn walk_packet<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool, const M: bool, O: Occluders>(
    src: W,
    rays: &[Ray],
    p: &Packet,
    mask: u16,
    best: &mut Best,
    stats: &mut TraceStats,
    occ: &mut O,
) {
    let mut cur = Entry {
        node: 0,
        mask: 0,
        tmin: [0.0; LANES],
        tmax: [0.0; LANES],
    };
    let (entered, t0, t1) = clip_lanes::<M>(p, &src.bounds());
    cur.mask = mask & entered;
    cur.tmin = t0;
    cur.tmax = t1;
    if COUNT {
        stats.packets += 1;
        stats.rays += u64::from(mask.count_ones());
    }
    let perm = p.shared_permutation(mask);
    // The lanes that are done (any-hit queries only).
    let mut done = 0u16;
    let mut stack: ArrayVec<Entry, MAX_STACK> = ArrayVec::new();
    // Each lane visits a node of a tree at most once, by the packet or
    // alone: so `LANES` times the step limit bounds this walk and the lanes
    // it hands to the scalar walk together.
    let mut steps_left = u64::from(src.step_limit()) * LANES as u64;
    'outer: loop {
        if steps_left == 0 {
            return;
        }
        steps_left -= 1;
        if ANY && cur.mask != 0 && cur.mask.count_ones() <= SCALAR_LANES {
            // So few lanes left in this cell: each walks its subtree alone.
            let mut m = cur.mask;
            while m != 0 {
                let i = m.trailing_zeros() as usize;
                m &= m - 1;
                let inv = Vec3::new(p.inv[0][i], p.inv[1][i], p.inv[2][i]);
                let prev = best.lane(i);
                let start = (cur.node, cur.tmin[i], cur.tmax[i]);
                let h = super::walk_cells::<W, ANY, COUNT>(
                    src,
                    &rays[i],
                    &p.precomp(i),
                    inv,
                    start,
                    prev,
                    stats,
                    &mut steps_left,
                );
                best.set_lane(i, h);
                if ANY && h.is_hit() {
                    done |= 1 << i;
                }
            }
            if ANY && mask & !done == 0 {
                return;
            }
        } else if cur.mask != 0 {
            if COUNT {
                stats.nodes += 1;
                stats.lane_steps += u64::from(cur.mask.count_ones());
            }
            match src.node(cur.node) {
                SourceNode::Inner(n) => {
                    if let Some(tri) = n.t_ref {
                        if COUNT {
                            stats.hoisted += u64::from(cur.mask.count_ones());
                        }
                        if ANY {
                            let h = test_triangle::<_, ANY, M>(src, p, perm, tri, cur.mask, best);
                            occ.note(h, tri);
                            done |= h;
                            cur.mask &= !done;
                            if mask & !done == 0 {
                                return;
                            }
                        } else {
                            test_triangle::<_, ANY, M>(src, p, perm, tri, cur.mask, best);
                        }
                    }
                    let k = n.axis as usize;
                    let split = split_lanes::<M>(p, k, n.pos, &cur);
                    let (l_mask, r_mask) = (split.left & cur.mask, split.right & cur.mask);
                    // The child most of the lanes that visit both meet
                    // first goes first (in a one-octant packet, all of
                    // them: the scalar order).
                    let both = l_mask & r_mask;
                    let left_first = 2 * (both & split.below).count_ones() >= both.count_ones();
                    let (first, second) = if left_first {
                        ((n.left, l_mask), (n.right, r_mask))
                    } else {
                        ((n.right, r_mask), (n.left, l_mask))
                    };
                    let ordered;
                    let [f_tmin, f_tmax, s_tmin, s_tmax] = if M {
                        ordered = if left_first {
                            split_intervals::<true>(p, k, n.pos, &cur)
                        } else {
                            split_intervals::<false>(p, k, n.pos, &cur)
                        };
                        [&ordered[0], &ordered[1], &ordered[2], &ordered[3]]
                    } else if left_first {
                        [&split.l_tmin, &split.l_tmax, &split.r_tmin, &split.r_tmax]
                    } else {
                        [&split.r_tmin, &split.r_tmax, &split.l_tmin, &split.l_tmax]
                    };
                    if second.1 != 0 && second.0 != NO_WORD {
                        // An empty child (a file's child without a word) is
                        // not visited. One entry per inner node on the path: the depth
                        // bound (MAX_DEPTH) keeps it below MAX_STACK; a
                        // deeper path, which only a file that was not
                        // validated can make, drops the cell (as the
                        // scalar walk does).
                        let _ = stack.try_push(Entry {
                            node: second.0,
                            mask: second.1,
                            tmin: *s_tmin,
                            tmax: *s_tmax,
                        });
                    }
                    if first.1 != 0 && first.0 != NO_WORD {
                        cur.node = first.0;
                        cur.mask = first.1;
                        cur.tmin = *f_tmin;
                        cur.tmax = *f_tmax;
                        continue 'outer;
                    }
                }
                SourceNode::Leaf(tris) => {
                    if COUNT {
                        stats.leaves += 1;
                    }
                    for i in 0..tris.len() {
                        let t = tris.get(i);
                        if COUNT {
                            stats.tris += u64::from(cur.mask.count_ones());
                        }
                        if ANY {
                            let h = test_triangle::<_, ANY, M>(src, p, perm, t, cur.mask, best);
                            occ.note(h, t);
                            done |= h;
                            cur.mask &= !done;
                            if cur.mask == 0 {
                                if mask & !done == 0 {
                                    return;
                                }
                                break;
                            }
                        } else {
                            test_triangle::<_, ANY, M>(src, p, perm, t, cur.mask, best);
                        }
                    }
                }
            }
        }
        // Pop the next cell and keep the lanes that may still find a hit
        // there (the scalar traverser's rule, per lane).
        loop {
            let Some(mut e) = stack.pop() else {
                break 'outer;
            };
            let mut keep = [false; LANES];
            // The scalar pop's expression, literally: an entry at `tmin` =
            // +∞ (a lane parallel to the split plane, whose distance to it
            // is ∞) gives NaN, and a NaN drops the lane, as it ends the
            // scalar traverser's wait for that cell.
            for i in 0..LANES {
                keep[i] = e.tmin[i] - e.tmin[i] * MARGIN <= best.t[i];
            }
            e.mask &= !done & bits::<M>(keep);
            if e.mask != 0 {
                cur = e;
                continue 'outer;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `bits` packs flag `i` into bit `i`, in both of its forms.
    #[test]
    fn bits_packs_each_flag_into_its_bit() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..1000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let want = state as u16;
            let flags: [bool; LANES] = std::array::from_fn(|i| want & (1 << i) != 0);
            assert_eq!(bits::<true>(flags), want);
            assert_eq!(bits::<false>(flags), want);
        }
        assert_eq!(bits::<true>([true; LANES]), u16::MAX);
        assert_eq!(bits::<false>([false; LANES]), 0);
    }

    /// A packet's occluders become the cache: the first `OCCLUDERS`
    /// distinct triangles in lane order, lanes without one skipped.
    #[test]
    fn cache_keeps_the_first_distinct_occluders_in_lane_order() {
        let none = u32::MAX;
        let mut cache = OccluderCache::new();
        let mut occ = [none; LANES];
        cache.update(&occ);
        assert!(cache.is_empty());
        occ[3] = 7;
        occ[4] = 7;
        occ[9] = 2;
        occ[12] = 7;
        cache.update(&occ);
        assert_eq!(cache.tris[..cache.len()], [7, 2]);
        let occ: [u32; LANES] = std::array::from_fn(|i| match i {
            0 | 5 => none,
            _ => (20 - i as u32) / 2,
        });
        cache.update(&occ);
        assert_eq!(cache.tris[..cache.len()], [9, 8, 7, 6, 5, 4, 3, 2]);
    }
}
