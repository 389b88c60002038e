//! Any-hit queries for a batch of incoherent rays, 16 rays at a time in
//! vector lanes, each lane on its own path through the tree.
//!
//! A packet shares one node between its lanes, which incoherent rays
//! (ambient occlusion, shadow rays of scattered hit points) do not: they
//! part within a few levels, and the packet then walks one ray at a time.
//! Here every lane holds a ray of its own with its own node, interval and
//! stack, and each round of the loop either steps every lane that is at
//! an inner node (the node words gathered, the split rule evaluated in
//! all lanes at once) or tests one triangle in every lane that is in a
//! leaf (the vertices gathered, the watertight test in all lanes). A
//! lane whose ray is done takes the next ray of the batch, so the lanes
//! stay full until the batch runs dry; the last few rays finish with the
//! scalar walk from where they are. The rounds have no branch that
//! depends on one ray's decisions, and the node loads of 16 rays are in
//! flight together.
//!
//! **Where it stands.** It loses to the packets. On Zen 4 (AVX-512) a
//! node round costs ~110 cycles, 11 a lane's step against the scalar
//! walk's ~33, but a triangle round waits on three dependent gathers
//! (~40 cycles a lane's test, the scalar test's), the lane-by-lane
//! bookkeeping (refill, pops, state counts) takes a third of the time,
//! and a lane walks all of the scalar walk's steps (ambient-occlusion
//! rays occluded, one thread: dieselpower 4.4 Mrays/s against packets'
//! 9, ravenbridge 1.44 against 1.72; `docs/perf-notes.md`, "Rays in
//! lanes"). It is `trace --mode lanes`, for the record; the renderer
//! traces packets.
//!
//! Every lane makes the scalar walk's decisions with its expressions
//! (margins, rays in a split plane, empty children, the step budget) and
//! tests a leaf's triangles and a type II node's hoisted triangle with
//! the scalar test's operations (lanes whose test leaves `f32` are
//! handed to [`intersect_triangle`]), so a ray is occluded here exactly
//! when the scalar walk says so. It reads a `.kd` file's words
//! ([`FileWalk`]); every index is checked against its section, as the
//! scalar walk checks it, before it is loaded.

// Lane loops index several arrays by lane: the form LLVM vectorises.
#![allow(clippy::needless_range_loop)]

use super::file::FileWalk;
use super::packet::{bits, watertight_lane};
use super::{
    Hit, MARGIN, MAX_STACK, NO_WORD, Pending, PendingStack, TraceStats, Walk, clip_ray, max_num,
    min_num, walk_pending,
};
use crate::format::node::{A_TYPE2, E_IDX16, E_IDX32, E_ONE, MAX_LEAF32};
use crate::geom::{Ray, RayPrecomp, intersect_triangle};
use crate::simd::SimdLevel;
use glam::Vec3;
use std::mem::MaybeUninit;

/// Rays in flight at once.
pub const LANES: usize = 16;

/// Once the batch has no rays left to hand out, the lanes still busy
/// finish with the scalar walk when they are this few or fewer: a round
/// costs several scalar steps whatever its occupancy.
pub const THIN: u32 = 2;

/// A round tests triangles once this many lanes are in leaves (or no lane
/// is at an inner node): a triangle round costs about three node rounds.
pub const LEAF_ROUND: u32 = 8;

type L<T> = [T; LANES];

/// What a lane is doing.
const IDLE: u32 = 0;
const INNER: u32 = 1;
const LEAF: u32 = 2;
/// Transient states of one round, resolved before the next: the lane's
/// cell is done (pop a pending one), or its ray is (no hit).
const POP: u32 = 3;
const MISS: u32 = 4;

/// The sections of a file, each at least one element long (an empty one
/// padded), with their true lengths: a lane loads at an index clamped to
/// the padded slice and uses what it loaded only where the true length
/// says the index is in range.
#[derive(Clone, Copy)]
struct Sections<'a> {
    nodes: &'a [u64],
    idx32: &'a [u32],
    idx16: &'a [u16],
    vertices: &'a [[f32; 3]],
    triangles: &'a [[u32; 3]],
    n_nodes: u32,
    n_idx32: u32,
    n_idx16: u32,
    n_vertices: u32,
    n_triangles: u32,
}

/// Lengths above `u32::MAX` are read as `u32::MAX`: no index a word can
/// hold reaches past them.
fn len32<T>(s: &[T]) -> u32 {
    u32::try_from(s.len()).unwrap_or(u32::MAX)
}

impl<'a> Sections<'a> {
    fn new(w: &FileWalk<'a>) -> Self {
        fn padded<'a, T>(s: &'a [T], pad: &'a [T]) -> &'a [T] {
            if s.is_empty() { pad } else { s }
        }
        Sections {
            nodes: padded(w.nodes, &[0]),
            idx32: padded(w.idx32, &[0]),
            idx16: padded(w.idx16, &[0]),
            vertices: padded(w.vertices, &[[0.0; 3]]),
            triangles: padded(w.triangles, &[[0; 3]]),
            n_nodes: len32(w.nodes),
            n_idx32: len32(w.idx32),
            n_idx16: len32(w.idx16),
            n_vertices: len32(w.vertices),
            n_triangles: len32(w.triangles),
        }
    }
}

/// `s[min(i, len − 1)]`: a load that is in bounds for any `i`.
#[inline(always)]
fn clamped<T: Copy>(s: &[T], i: u32) -> T {
    let i = (i as usize).min(s.len() - 1);
    // SAFETY: `Sections` slices are never empty, so `i < s.len()`.
    unsafe { *s.get_unchecked(i) }
}

/// The lanes: each one ray and where its walk stands.
struct Lanes {
    /// The ray's index in the batch.
    ray: L<u32>,
    o: [L<f32>; 3],
    dir: [L<f32>; 3],
    inv: [L<f32>; 3],
    tmin: L<f32>,
    tmax: L<f32>,
    kx: L<u32>,
    ky: L<u32>,
    kz: L<u32>,
    sx: L<f32>,
    sy: L<f32>,
    sz: L<f32>,
    state: L<u32>,
    /// The cell: its node and the ray's interval in it.
    node: L<u32>,
    t0: L<f32>,
    t1: L<f32>,
    /// Steps left of the scalar walk's budget.
    steps: L<u32>,
    /// In `LEAF`: the triangles left are `cur..end` of the list the kind
    /// names ([`E_IDX32`], [`E_IDX16`] with the high half `upper`, or one
    /// triangle, `upper`, for `cur..end` = `0..1`).
    cur: L<u32>,
    end: L<u32>,
    kind: L<u32>,
    upper: L<u32>,
    /// The lane's node is a type II node whose hoisted triangle is tested
    /// (or being tested): its split comes next.
    hoisted: L<u32>,
    /// Pending cells: `(stack_node, stack_t0, stack_t1)[d][lane]` for
    /// `d < sp[lane]`, pushed and popped lane by lane.
    sp: L<u32>,
    stack_node: [L<u32>; MAX_STACK],
    stack_t0: [L<f32>; MAX_STACK],
    stack_t1: [L<f32>; MAX_STACK],
}

impl Lanes {
    fn new() -> Box<Lanes> {
        let z = [0f32; LANES];
        Box::new(Lanes {
            ray: [0; LANES],
            o: [z; 3],
            dir: [z; 3],
            inv: [z; 3],
            tmin: z,
            tmax: z,
            kx: [0; LANES],
            ky: [0; LANES],
            kz: [0; LANES],
            sx: z,
            sy: z,
            sz: z,
            state: [IDLE; LANES],
            node: [0; LANES],
            t0: z,
            t1: z,
            steps: [0; LANES],
            cur: [0; LANES],
            end: [0; LANES],
            kind: [0; LANES],
            upper: [0; LANES],
            hoisted: [0; LANES],
            sp: [0; LANES],
            stack_node: [[0; LANES]; MAX_STACK],
            stack_t0: [z; MAX_STACK],
            stack_t1: [z; MAX_STACK],
        })
    }

    /// Puts ray `idx` into lane `i` at the root, or says it misses the
    /// root cell.
    #[inline(always)]
    fn load(
        &mut self,
        i: usize,
        idx: u32,
        ray: &Ray,
        bounds: &crate::geom::Aabb,
        steps: u32,
    ) -> bool {
        let inv = Vec3::ONE / ray.dir;
        let Some((t0, t1)) = clip_ray(bounds, ray, inv) else {
            return false;
        };
        let rp = RayPrecomp::new(ray);
        self.ray[i] = idx;
        for k in 0..3 {
            self.o[k][i] = ray.origin[k];
            self.dir[k][i] = ray.dir[k];
            self.inv[k][i] = inv[k];
        }
        self.tmin[i] = ray.tmin;
        self.tmax[i] = ray.tmax;
        self.kx[i] = rp.kx as u32;
        self.ky[i] = rp.ky as u32;
        self.kz[i] = rp.kz as u32;
        self.sx[i] = rp.sx;
        self.sy[i] = rp.sy;
        self.sz[i] = rp.sz;
        self.state[i] = INNER;
        self.node[i] = 0;
        self.t0[i] = t0;
        self.t1[i] = t1;
        self.steps[i] = steps;
        self.hoisted[i] = 0;
        self.sp[i] = 0;
        true
    }

    /// The watertight test's constants of lane `i`'s ray.
    fn precomp(&self, i: usize) -> RayPrecomp {
        RayPrecomp {
            origin: Vec3::new(self.o[0][i], self.o[1][i], self.o[2][i]),
            kx: self.kx[i] as usize,
            ky: self.ky[i] as usize,
            kz: self.kz[i] as usize,
            sx: self.sx[i],
            sy: self.sy[i],
            sz: self.sz[i],
        }
    }

    /// Lane `i`'s cell is done: it takes the nearest pending cell that may
    /// hold a hit (the scalar walk's pop; no hit has been found, so only a
    /// NaN entry is skipped), or its ray ends without a hit.
    #[inline(always)]
    fn pop(&mut self, i: usize) {
        loop {
            if self.sp[i] == 0 {
                self.state[i] = MISS;
                return;
            }
            self.sp[i] -= 1;
            let d = self.sp[i] as usize;
            let (node, t0, t1) = (
                self.stack_node[d][i],
                self.stack_t0[d][i],
                self.stack_t1[d][i],
            );
            if t0 - t0 * MARGIN <= f32::INFINITY {
                (self.node[i], self.t0[i], self.t1[i]) = (node, t0, t1);
                self.state[i] = INNER;
                return;
            }
        }
    }
}

/// All ones where `c`, else zero: selects as bit operations, which the
/// lane loops vectorise (a chain of `if`s on one value becomes a switch,
/// which they do not).
#[inline(always)]
fn mask(c: bool) -> u32 {
    0u32.wrapping_sub(u32::from(c))
}

/// `v[k]` for a per-lane axis `k` (0, 1 or 2).
#[inline(always)]
fn sel(k: u32, v: [f32; 3]) -> f32 {
    let bits = (v[0].to_bits() & mask(k == 0))
        | (v[1].to_bits() & mask(k == 1))
        | (v[2].to_bits() & mask(k == 2));
    f32::from_bits(bits)
}

#[inline(always)]
fn pick(c: bool, a: u32, b: u32) -> u32 {
    (a & mask(c)) | (b & !mask(c))
}

#[inline(always)]
fn pickf(c: bool, a: f32, b: f32) -> f32 {
    f32::from_bits(pick(c, a.to_bits(), b.to_bits()))
}

const K32: u32 = E_IDX32 as u32;
const K16: u32 = E_IDX16 as u32;
const KONE: u32 = E_ONE as u32;

/// One node round: every lane at an inner node takes its step, as the
/// scalar walk's loop body does for a node (the hoisted triangle first,
/// then the split rule, or the leaf's triangle list). The lanes' fields
/// are copied into locals, worked on in loops of selects and written
/// back whole: the form LLVM vectorises (with the fields read and
/// written in place, it kept the loop scalar).
#[inline(always)]
fn step_inner<const M: bool>(l: &mut Lanes, s: &Sections) {
    let node = l.node;
    let mut word = [0u64; LANES];
    for i in 0..LANES {
        word[i] = clamped(s.nodes, node[i]);
    }
    let (state, hoisted, steps) = (l.state, l.hoisted, l.steps);
    let (t0, t1, sp) = (l.t0, l.t1, l.sp);
    let (mut n_state, mut n_hoisted, mut n_steps) = (state, hoisted, steps);
    let (mut n_node, mut n_t0, mut n_t1) = (node, t0, t1);
    let (mut cur, mut end, mut kind, mut upper) = (l.cur, l.end, l.kind, l.upper);
    let mut push = [false; LANES];
    let mut tref = [false; LANES];
    let mut push_node = [0u32; LANES];
    let mut push_t0 = [0f32; LANES];
    for i in 0..LANES {
        let active = state[i] == INNER;
        let n = node[i];
        let visit = hoisted[i] == 0;
        let out_of_steps = visit & (steps[i] == 0);
        n_steps[i] = steps[i].wrapping_sub(u32::from(active & visit));
        let valid = n < s.n_nodes;
        let w = word[i];
        let lo = w as u32;
        let hi = (w >> 32) as u32;
        let inner = valid & (lo & 3 != 3);
        let type2 = u64::from(lo) & A_TYPE2 != 0;
        let want_tref = inner & type2 & visit;
        // A leaf: its list, checked against its section.
        let leaf = valid & (lo & 0b111 == 0b011);
        let k_leaf = (lo >> 3) & 3;
        let (is32, is16, is1) = (k_leaf == K32, k_leaf == K16, k_leaf == KONE);
        let count = ((lo >> 5) & MAX_LEAF32 & mask(is32))
            | ((lo >> 5) & 0x7ff & mask(is16))
            | (1 & mask(is1));
        let limit = (s.n_idx32 & mask(is32)) | (s.n_idx16 & mask(is16)) | (1 & mask(is1));
        let start = hi & !mask(is1);
        let in_range = (start <= limit) & (count <= limit.wrapping_sub(start));
        let leaf_ok = leaf & in_range & (count > 0);
        // The split rule (the scalar walk's, see `walk_pending`).
        let k = lo & 3;
        let o = sel(k, [l.o[0][i], l.o[1][i], l.o[2][i]]);
        let d = sel(k, [l.dir[0][i], l.dir[1][i], l.dir[2][i]]);
        let iv = sel(k, [l.inv[0][i], l.inv[1][i], l.inv[2][i]]);
        let pos = f32::from_bits(hi);
        let first = n.wrapping_add(1 + u32::from(type2));
        let field = lo >> 3;
        let left = pick(field == first, NO_WORD, first);
        let right = pick(field > n, field, NO_WORD);
        let on_plane = o == pos;
        let left_near = (on_plane & (d <= 0.0)) | (!on_plane & (o < pos));
        let near = pick(left_near, left, right);
        let far = pick(left_near, right, left);
        let (a0, a1) = (t0[i], t1[i]);
        let ts = (pos - o) * iv;
        let near_only = !on_plane & ((ts <= 0.0) | (ts - ts * MARGIN > a1));
        let far_only = !on_plane & !near_only & (ts + ts * MARGIN < a0);
        let both = !near_only & !far_only;
        let lo_t = pickf(on_plane, a0, max_num(ts, a0));
        let hi_t = pickf(on_plane, a1, min_num(ts, a1));
        let near_ok = near != NO_WORD;
        let far_ok = far != NO_WORD;
        let reach = on_plane | (lo_t - lo_t * MARGIN <= f32::INFINITY);
        // near only, or both with a near child: the near child; far only,
        // or both without one: the far child.
        let to_near = near_only | (both & near_ok);
        let nn = pick(to_near, near, far);
        let nt0 = pickf(both & !near_ok, lo_t, a0);
        let nt1 = pickf(both & near_ok, hi_t, a1);
        let go = (near_only & near_ok)
            | (far_only & far_ok)
            | (both & near_ok)
            | (both & !near_ok & far_ok & reach);
        let split = inner & !want_tref;
        let moves = active & !out_of_steps & split & go;
        let to_leaf = active & !out_of_steps & !inner & leaf_ok;
        let enters = active & !out_of_steps & want_tref;
        let next = if out_of_steps {
            MISS
        } else if want_tref {
            LEAF
        } else if split {
            pick(go, INNER, POP)
        } else {
            pick(leaf_ok, LEAF, POP)
        };
        n_state[i] = pick(active, next, state[i]);
        n_hoisted[i] = pick(active, u32::from(enters), hoisted[i]);
        n_node[i] = pick(moves, nn, n);
        n_t0[i] = pickf(moves, nt0, a0);
        n_t1[i] = pickf(moves, nt1, a1);
        cur[i] = pick(to_leaf, start, pick(enters, 0, cur[i]));
        end[i] = pick(to_leaf, start.wrapping_add(count), pick(enters, 1, end[i]));
        kind[i] = pick(to_leaf, k_leaf, pick(enters, KONE, kind[i]));
        upper[i] = pick(to_leaf, pick(is16, lo & 0xffff_0000, hi), upper[i]);
        tref[i] = enters;
        push[i] = moves & both & near_ok & far_ok & (sp[i] < MAX_STACK as u32);
        push_node[i] = far;
        push_t0[i] = lo_t;
    }
    // The rounds' rare cases, lane by lane: a hoisted triangle (its word
    // follows the node; without one the node reads as empty), and the
    // pushes (a scatter to per-lane stack depths).
    let mut m = bits::<M>(tref);
    while m != 0 {
        let i = m.trailing_zeros() as usize;
        m &= m - 1;
        match s.nodes.get(node[i] as usize + 1) {
            Some(&w) if node[i] + 1 < s.n_nodes => upper[i] = (w >> 32) as u32,
            _ => {
                n_state[i] = POP;
                n_hoisted[i] = 0;
            }
        }
    }
    let mut m = bits::<M>(push);
    while m != 0 {
        let i = m.trailing_zeros() as usize;
        m &= m - 1;
        let d = l.sp[i] as usize;
        (l.stack_node[d][i], l.stack_t0[d][i], l.stack_t1[d][i]) =
            (push_node[i], push_t0[i], t1[i]);
        l.sp[i] += 1;
    }
    (l.state, l.hoisted, l.steps) = (n_state, n_hoisted, n_steps);
    (l.node, l.t0, l.t1) = (n_node, n_t0, n_t1);
    (l.cur, l.end, l.kind, l.upper) = (cur, end, kind, upper);
}

/// [`step_inner`] written in AVX-512 intrinsics (the same selects, in
/// the same order of operations): LLVM's form of the lane loop assembled
/// its gather indices lane by lane and copied every field through the
/// stack, ~500 cycles a round.
///
/// # Safety
/// The CPU has AVX-512 F, VL, BW and DQ.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
unsafe fn step_inner_512(l: &mut Lanes, s: &Sections) {
    use std::arch::x86_64::*;
    let u = |v: u32| _mm512_set1_epi32(v as i32);
    let f = _mm512_set1_ps;
    // SAFETY: `L<u32>` is 64 bytes, one unaligned vector load.
    let ld = |a: &L<u32>| unsafe { _mm512_loadu_si512(a.as_ptr().cast()) };
    // SAFETY: `L<f32>` is 64 bytes, one unaligned vector load.
    let ldf = |a: &L<f32>| unsafe { _mm512_loadu_ps(a.as_ptr()) };
    let state = ld(&l.state);
    let active = _mm512_cmpeq_epi32_mask(state, u(INNER));
    let node = ld(&l.node);
    let hoisted = ld(&l.hoisted);
    let visit = _mm512_cmpeq_epi32_mask(hoisted, u(0));
    let steps = ld(&l.steps);
    let out_of_steps = visit & _mm512_cmpeq_epi32_mask(steps, u(0));
    let n_steps = _mm512_mask_sub_epi32(steps, active & visit, steps, u(1));
    let valid = _mm512_cmplt_epu32_mask(node, u(s.n_nodes));
    // The node words of the active lanes, 8 at a time.
    let idx = _mm512_min_epu32(node, u(s.n_nodes - 1));
    let load = active & valid;
    let base = s.nodes.as_ptr().cast::<i64>();
    // SAFETY: every index is below `nodes.len()` (clamped above).
    let (w_lo, w_hi) = unsafe {
        (
            _mm512_mask_i32gather_epi64::<8>(
                _mm512_setzero_si512(),
                load as u8,
                _mm512_castsi512_si256(idx),
                base,
            ),
            _mm512_mask_i32gather_epi64::<8>(
                _mm512_setzero_si512(),
                (load >> 8) as u8,
                _mm512_extracti64x4_epi64::<1>(idx),
                base,
            ),
        )
    };
    let join = |a: __m512i, b: __m512i| {
        _mm512_inserti64x4::<1>(
            _mm512_castsi256_si512(_mm512_cvtepi64_epi32(a)),
            _mm512_cvtepi64_epi32(b),
        )
    };
    let lo = join(w_lo, w_hi);
    let hi = join(_mm512_srli_epi64::<32>(w_lo), _mm512_srli_epi64::<32>(w_hi));
    let inner = valid & _mm512_cmpneq_epi32_mask(_mm512_and_si512(lo, u(3)), u(3));
    let type2 = _mm512_test_epi32_mask(lo, u(A_TYPE2 as u32));
    let want_tref = inner & type2 & visit;
    let leaf = valid & _mm512_cmpeq_epi32_mask(_mm512_and_si512(lo, u(7)), u(3));
    let k_leaf = _mm512_and_si512(_mm512_srli_epi32::<3>(lo), u(3));
    let is32 = _mm512_cmpeq_epi32_mask(k_leaf, u(K32));
    let is16 = _mm512_cmpeq_epi32_mask(k_leaf, u(K16));
    let is1 = _mm512_cmpeq_epi32_mask(k_leaf, u(KONE));
    let lo5 = _mm512_srli_epi32::<5>(lo);
    let mut count = _mm512_maskz_and_epi32(is32, lo5, u(MAX_LEAF32));
    count = _mm512_mask_and_epi32(count, is16, lo5, u(0x7ff));
    count = _mm512_mask_mov_epi32(count, is1, u(1));
    let mut limit = _mm512_maskz_mov_epi32(is32, u(s.n_idx32));
    limit = _mm512_mask_mov_epi32(limit, is16, u(s.n_idx16));
    limit = _mm512_mask_mov_epi32(limit, is1, u(1));
    let start = _mm512_mask_mov_epi32(hi, is1, u(0));
    let in_range = _mm512_cmple_epu32_mask(start, limit)
        & _mm512_cmple_epu32_mask(count, _mm512_sub_epi32(limit, start));
    let leaf_ok = leaf & in_range & _mm512_cmpneq_epi32_mask(count, u(0));
    // The split rule (the scalar walk's, see `walk_pending`).
    let k = _mm512_and_si512(lo, u(3));
    let (k1, k2) = (
        _mm512_cmpeq_epi32_mask(k, u(1)),
        _mm512_cmpeq_epi32_mask(k, u(2)),
    );
    let axis = |v: &[L<f32>; 3]| {
        let r = _mm512_mask_mov_ps(ldf(&v[0]), k1, ldf(&v[1]));
        _mm512_mask_mov_ps(r, k2, ldf(&v[2]))
    };
    let (o, d, iv) = (axis(&l.o), axis(&l.dir), axis(&l.inv));
    let pos = _mm512_castsi512_ps(hi);
    let first = _mm512_add_epi32(node, _mm512_mask_mov_epi32(u(1), type2, u(2)));
    let field = _mm512_srli_epi32::<3>(lo);
    let left = _mm512_mask_mov_epi32(first, _mm512_cmpeq_epi32_mask(field, first), u(NO_WORD));
    let right = _mm512_mask_mov_epi32(u(NO_WORD), _mm512_cmpgt_epu32_mask(field, node), field);
    let on_plane = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(o, pos);
    let left_near = (on_plane & _mm512_cmp_ps_mask::<_CMP_LE_OQ>(d, f(0.0)))
        | (!on_plane & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(o, pos));
    let near = _mm512_mask_mov_epi32(right, left_near, left);
    let far = _mm512_mask_mov_epi32(left, left_near, right);
    let (t0, t1) = (ldf(&l.t0), ldf(&l.t1));
    let m = f(MARGIN);
    let ts = _mm512_mul_ps(_mm512_sub_ps(pos, o), iv);
    let near_only = !on_plane
        & (_mm512_cmp_ps_mask::<_CMP_LE_OQ>(ts, f(0.0))
            | _mm512_cmp_ps_mask::<_CMP_GT_OQ>(_mm512_sub_ps(ts, _mm512_mul_ps(ts, m)), t1));
    let far_only = !on_plane
        & !near_only
        & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(_mm512_add_ps(ts, _mm512_mul_ps(ts, m)), t0);
    let both = !near_only & !far_only;
    // max_num / min_num: `ts` where it compares above / below, else the
    // bound (so a NaN `ts` gives the bound, as in the scalar walk).
    let max_t = _mm512_mask_mov_ps(t0, _mm512_cmp_ps_mask::<_CMP_GT_OQ>(ts, t0), ts);
    let min_t = _mm512_mask_mov_ps(t1, _mm512_cmp_ps_mask::<_CMP_LT_OQ>(ts, t1), ts);
    let lo_t = _mm512_mask_mov_ps(max_t, on_plane, t0);
    let hi_t = _mm512_mask_mov_ps(min_t, on_plane, t1);
    let near_ok = _mm512_cmpneq_epi32_mask(near, u(NO_WORD));
    let far_ok = _mm512_cmpneq_epi32_mask(far, u(NO_WORD));
    let reach = on_plane
        | _mm512_cmp_ps_mask::<_CMP_LE_OQ>(
            _mm512_sub_ps(lo_t, _mm512_mul_ps(lo_t, m)),
            f(f32::INFINITY),
        );
    let to_near = near_only | (both & near_ok);
    let nn = _mm512_mask_mov_epi32(far, to_near, near);
    let nt0 = _mm512_mask_mov_ps(t0, both & !near_ok, lo_t);
    let nt1 = _mm512_mask_mov_ps(t1, both & near_ok, hi_t);
    let go = (near_only & near_ok)
        | (far_only & far_ok)
        | (both & near_ok)
        | (both & !near_ok & far_ok & reach);
    let split = inner & !want_tref;
    let live = active & !out_of_steps;
    let moves = live & split & go;
    let to_leaf = live & !inner & leaf_ok;
    let enters = live & want_tref;
    let mut n_state = _mm512_mask_mov_epi32(state, active, u(POP));
    n_state = _mm512_mask_mov_epi32(n_state, moves, u(INNER));
    n_state = _mm512_mask_mov_epi32(n_state, enters | to_leaf, u(LEAF));
    n_state = _mm512_mask_mov_epi32(n_state, active & out_of_steps, u(MISS));
    let n_hoisted = _mm512_mask_mov_epi32(hoisted, active, _mm512_maskz_mov_epi32(enters, u(1)));
    let cur = _mm512_mask_mov_epi32(ld(&l.cur), to_leaf, start);
    let cur = _mm512_mask_mov_epi32(cur, enters, u(0));
    let end = _mm512_mask_mov_epi32(ld(&l.end), to_leaf, _mm512_add_epi32(start, count));
    let end = _mm512_mask_mov_epi32(end, enters, u(1));
    let kind = _mm512_mask_mov_epi32(ld(&l.kind), to_leaf, k_leaf);
    let kind = _mm512_mask_mov_epi32(kind, enters, u(KONE));
    let up = _mm512_mask_mov_epi32(hi, is16, _mm512_and_si512(lo, u(0xffff_0000)));
    let mut upper = _mm512_mask_mov_epi32(ld(&l.upper), to_leaf, up);
    if enters != 0 {
        // Hoisted triangles (slim trees): the T-reference word follows its
        // node; where it is missing the node reads as empty.
        let next = _mm512_add_epi32(node, u(1));
        let there = enters & _mm512_cmplt_epu32_mask(next, u(s.n_nodes));
        let nidx = _mm512_min_epu32(next, u(s.n_nodes - 1));
        // SAFETY: indices clamped below `nodes.len()`; the high half of
        // each word is read (little-endian), at `2 · index + 1` words of 4
        // bytes, below `2 · nodes.len()`.
        let tref = unsafe {
            _mm512_mask_i32gather_epi32::<4>(
                upper,
                there,
                _mm512_add_epi32(_mm512_add_epi32(nidx, nidx), u(1)),
                s.nodes.as_ptr().cast::<i32>(),
            )
        };
        upper = _mm512_mask_mov_epi32(upper, enters, tref);
        n_state = _mm512_mask_mov_epi32(n_state, enters & !there, u(POP));
    }
    let n_hoisted = if enters != 0 {
        let next = _mm512_add_epi32(node, u(1));
        let gone = enters & !_mm512_cmplt_epu32_mask(next, u(s.n_nodes));
        _mm512_mask_mov_epi32(n_hoisted, gone, u(0))
    } else {
        n_hoisted
    };
    let sp = ld(&l.sp);
    let push = moves & both & near_ok & far_ok & _mm512_cmplt_epu32_mask(sp, u(MAX_STACK as u32));
    // SAFETY: `L<u32>` is 64 bytes, one unaligned vector store.
    let st = |a: &mut L<u32>, v: __m512i| unsafe { _mm512_storeu_si512(a.as_mut_ptr().cast(), v) };
    // SAFETY: `L<f32>` is 64 bytes, one unaligned vector store.
    let stf = |a: &mut L<f32>, v: __m512| unsafe { _mm512_storeu_ps(a.as_mut_ptr(), v) };
    if push != 0 {
        // The pushes, lane by lane (three masked scatters were 5–10 %
        // slower on Zen 4).
        let mut pn = [0u32; LANES];
        let mut p0 = [0f32; LANES];
        let mut p1 = [0f32; LANES];
        st(&mut pn, far);
        stf(&mut p0, lo_t);
        stf(&mut p1, t1);
        let mut m = push;
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            m &= m - 1;
            let d = l.sp[i] as usize;
            (l.stack_node[d][i], l.stack_t0[d][i], l.stack_t1[d][i]) = (pn[i], p0[i], p1[i]);
        }
    }
    st(&mut l.sp, _mm512_mask_add_epi32(sp, push, sp, u(1)));
    st(&mut l.state, n_state);
    st(&mut l.hoisted, n_hoisted);
    st(&mut l.steps, n_steps);
    st(&mut l.node, _mm512_mask_mov_epi32(node, moves, nn));
    stf(&mut l.t0, _mm512_mask_mov_ps(t0, moves, nt0));
    stf(&mut l.t1, _mm512_mask_mov_ps(t1, moves, nt1));
    st(&mut l.cur, cur);
    st(&mut l.end, end);
    st(&mut l.kind, kind);
    st(&mut l.upper, upper);
}

/// One triangle round: every lane in a leaf tests its next triangle (the
/// scalar test's operations in its order; lanes where the test leaves
/// `f32` are redone by [`intersect_triangle`]). Returns the lanes whose ray
/// is occluded; the others go on to their next triangle, back to their
/// node's split (a hoisted triangle) or to `POP`.
#[inline(always)]
fn step_leaf<const M: bool>(l: &mut Lanes, s: &Sections, walk: &FileWalk) -> u16 {
    let (state, cur, kind, upper) = (l.state, l.cur, l.kind, l.upper);
    let mut tri = [0u32; LANES];
    for i in 0..LANES {
        let t32 = clamped(s.idx32, cur[i]);
        let t16 = upper[i] | u32::from(clamped(s.idx16, cur[i]));
        tri[i] = pick(kind[i] == K32, t32, pick(kind[i] == K16, t16, upper[i]));
    }
    let mut corner = [[0u32; LANES]; 3];
    for i in 0..LANES {
        let [a, b, c] = clamped(s.triangles, tri[i]);
        (corner[0][i], corner[1][i], corner[2][i]) = (a, b, c);
    }
    let mut vert = [[[0f32; LANES]; 3]; 3];
    for j in 0..3 {
        for i in 0..LANES {
            let v = clamped(s.vertices, corner[j][i]);
            (vert[j][0][i], vert[j][1][i], vert[j][2][i]) = (v[0], v[1], v[2]);
        }
    }
    let mut hit = [false; LANES];
    let mut fallback = [false; LANES];
    let mut n_state = state;
    let mut n_cur = cur;
    for i in 0..LANES {
        let active = state[i] == LEAF;
        let real = (tri[i] < s.n_triangles)
            & (corner[0][i] < s.n_vertices)
            & (corner[1][i] < s.n_vertices)
            & (corner[2][i] < s.n_vertices);
        let org = [l.o[0][i], l.o[1][i], l.o[2][i]];
        let (kx, ky, kz) = (l.kx[i], l.ky[i], l.kz[i]);
        // `tri[j] - org` component by component, permuted: the scalar
        // test's subtractions.
        let rel = |j: usize| {
            let v = [
                vert[j][0][i] - org[0],
                vert[j][1][i] - org[1],
                vert[j][2][i] - org[2],
            ];
            [sel(kx, v), sel(ky, v), sel(kz, v)]
        };
        let (a, b, c) = (rel(0), rel(1), rel(2));
        let shear = [l.sx[i], l.sy[i], l.sz[i]];
        let (t, ok, redo) = watertight_lane(shear, l.tmin[i], l.tmax[i], a, b, c);
        // An any-hit query excludes `tmax`.
        hit[i] = active & real & !redo & ok & (t < l.tmax[i]);
        fallback[i] = active & real & redo;
        // Lanes that go on: the next triangle, or past the list.
        let c1 = cur[i].wrapping_add(1);
        n_cur[i] = pick(active, c1, cur[i]);
        let after = pick(l.hoisted[i] != 0, INNER, POP);
        n_state[i] = pick(active & (c1 >= l.end[i]), after, state[i]);
    }
    l.cur = n_cur;
    l.state = n_state;
    let mut hits = bits::<M>(hit);
    let mut m = bits::<M>(fallback);
    while m != 0 {
        let i = m.trailing_zeros() as usize;
        m &= m - 1;
        let v = walk.triangle(tri[i]);
        let (tmin, tmax) = (l.tmin[i], l.tmax[i]);
        if intersect_triangle(&l.precomp(i), &v, tmin, tmax).is_some_and(|t| t < tmax) {
            hits |= 1 << i;
        }
    }
    hits
}

/// `out[i]`: whether anything is hit by `rays[i]` in `(tmin, tmax)`
/// (`out.len() == rays.len()`), traced in lanes compiled for `level` (or
/// the best level this CPU has, [`SimdLevel::usable`]).
pub fn occluded_lanes(walk: FileWalk<'_>, level: SimdLevel, rays: &[Ray], out: &mut [bool]) {
    assert_eq!(rays.len(), out.len(), "one result per ray");
    crate::simd_dispatch!(level, |WIDE| run::<WIDE>(walk, rays, out))
}

/// Groups of lanes in flight together, round by round, so that one
/// group's node loads overlap another's round (2 groups: 5 % faster than
/// 1; 4 no faster than 2).
pub const GROUPS: usize = 2;

#[inline(always)]
fn run<const M: bool>(walk: FileWalk<'_>, rays: &[Ray], out: &mut [bool]) {
    let s = Sections::new(&walk);
    let mut groups: [Box<Lanes>; GROUPS] = std::array::from_fn(|_| Lanes::new());
    let mut live = [true; GROUPS];
    let mut next = 0usize;
    while live.iter().any(|&x| x) {
        for g in 0..GROUPS {
            if live[g] {
                live[g] = round::<M>(&mut groups[g], &s, walk, rays, out, &mut next);
            }
        }
    }
}

/// One round of a group: idle lanes take rays, then a node or triangle
/// round, then the cells done pop. Returns whether the group has work
/// left.
#[inline(always)]
fn round<const M: bool>(
    l: &mut Lanes,
    s: &Sections,
    walk: FileWalk<'_>,
    rays: &[Ray],
    out: &mut [bool],
    next: &mut usize,
) -> bool {
    // Idle lanes take the next rays (those that miss the root cell are
    // answered at once).
    let mut idle = bits::<M>(l.state.map(|x| x == IDLE));
    while idle != 0 && *next < rays.len() {
        let i = idle.trailing_zeros() as usize;
        let idx = *next;
        *next += 1;
        if l.load(i, idx as u32, &rays[idx], &walk.bounds(), walk.step_limit()) {
            idle &= idle - 1;
        } else {
            out[idx] = false;
        }
    }
    let inner = bits::<M>(l.state.map(|x| x == INNER)).count_ones();
    let leaf = bits::<M>(l.state.map(|x| x == LEAF)).count_ones();
    if inner + leaf == 0 {
        return false;
    }
    if *next == rays.len() && inner + leaf <= THIN {
        let mut busy = bits::<M>(l.state.map(|x| x == INNER || x == LEAF));
        while busy != 0 {
            let i = busy.trailing_zeros() as usize;
            busy &= busy - 1;
            let idx = l.ray[i] as usize;
            out[idx] = finish(l, i, walk, &rays[idx]);
        }
        return false;
    }
    if leaf >= LEAF_ROUND || inner == 0 {
        let mut hits = step_leaf::<M>(l, s, &walk);
        while hits != 0 {
            let i = hits.trailing_zeros() as usize;
            hits &= hits - 1;
            out[l.ray[i] as usize] = true;
            l.state[i] = IDLE;
        }
    } else if M {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `M` is true only in the AVX-512 copy (`simd_dispatch!`),
        // which runs only where the CPU has these features.
        unsafe {
            step_inner_512(l, s)
        };
        #[cfg(not(target_arch = "x86_64"))]
        step_inner::<M>(l, s);
    } else {
        step_inner::<M>(l, s);
    }
    // Cells done: the next pending cell, or the ray ends unoccluded.
    let mut pops = bits::<M>(l.state.map(|x| x == POP || x == MISS));
    while pops != 0 {
        let i = pops.trailing_zeros() as usize;
        pops &= pops - 1;
        if l.state[i] == POP {
            l.pop(i);
        }
        if l.state[i] == MISS {
            out[l.ray[i] as usize] = false;
            l.state[i] = IDLE;
        }
    }
    true
}

/// Lane `i`'s ray finished by the scalar walk from where the lane stands:
/// the rest of its leaf, then its cell or pending cells.
fn finish(l: &Lanes, i: usize, walk: FileWalk<'_>, ray: &Ray) -> bool {
    let rp = RayPrecomp::new(ray);
    let inv = Vec3::ONE / ray.dir;
    let mut best = Hit::MISS;
    let mut cells = [const { MaybeUninit::<Pending>::uninit() }; MAX_STACK];
    let mut pending = PendingStack::new(&mut cells);
    for d in 0..l.sp[i] as usize {
        pending.push_if(
            (l.stack_node[d][i], l.stack_t0[d][i], l.stack_t1[d][i]),
            true,
        );
    }
    let mut start = (l.node[i], l.t0[i], l.t1[i]);
    if l.state[i] == LEAF {
        for c in l.cur[i]..l.end[i] {
            let tri = match l.kind[i] {
                K32 => walk.idx32.get(c as usize).copied(),
                K16 => walk
                    .idx16
                    .get(c as usize)
                    .map(|&x| l.upper[i] | u32::from(x)),
                _ => Some(l.upper[i]),
            };
            if tri.is_some_and(|t| super::test_one::<_, true>(walk, &rp, ray, t, &mut best)) {
                return true;
            }
        }
        // A hoisted triangle's node resumes at its split (the scalar walk
        // tests the triangle again there, in vain); a leaf pops.
        if l.hoisted[i] == 0 {
            loop {
                match pending.pop() {
                    None => return false,
                    Some(c) if c.1 - c.1 * MARGIN <= f32::INFINITY => {
                        start = c;
                        break;
                    }
                    Some(_) => {}
                }
            }
        }
    }
    // A hoisted triangle's node was counted when the lane first visited
    // it; the scalar walk counts it again as it resumes there.
    let mut steps_left = u64::from(l.steps[i]) + u64::from(l.hoisted[i] != 0);
    walk_pending::<FileWalk<'_>, true, false>(
        walk,
        ray,
        &rp,
        inv,
        start,
        best,
        &mut TraceStats::default(),
        &mut steps_left,
        &mut pending,
    )
    .is_hit()
}
