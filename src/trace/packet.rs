//! The 4×4 ray-packet traverser (Wald et al. 2001 style, over kd-trees):
//! 16 rays walk the tree together, and each leaf triangle is tested against
//! all active rays at once in SIMD lanes.
//!
//! Packets whose rays share the sign of every direction component take one
//! traversal order; incoherent packets fall back to single rays. Each lane
//! makes exactly the scalar traverser's decisions
//! ([`super::split_visit`]): a child is visited when any active lane needs
//! it, and a lane is active in a cell only when the scalar traverser would
//! visit that cell. Pending cells are culled per lane by the same rule. The
//! ray–triangle kernel performs the scalar watertight test's operations in
//! the same order (no fused multiply–add), so a packet returns exactly the
//! scalar traverser's hits, bit for bit, whatever instruction set ran it.
//!
//! **Instruction sets.** The whole packet traversal (split decisions and
//! leaf kernel) is compiled three times, for AVX-512, for AVX2 and for the
//! x86-64 baseline (SSE2), and chosen at run time by CPU feature detection;
//! on other architectures the portable version runs. The lane work is
//! written as branch-free loops over 16 lanes that LLVM vectorises to the
//! widest registers the target feature allows.

use super::{ClosestHit, Hit, KdSource, MARGIN, MAX_STACK, SourceNode, clip_ray, traverse};
use crate::geom::{Ray, RayPrecomp, intersect_triangle};
use glam::Vec3;

/// Rays in a packet.
pub const LANES: usize = 16;

type Lanes = [f32; LANES];

/// Structure-of-arrays form of 16 rays, with the per-ray constants of the
/// watertight test.
struct Packet {
    o: [Lanes; 3],
    dir: [Lanes; 3],
    inv: [Lanes; 3],
    tmin: Lanes,
    tmax: Lanes,
    /// Axis permutation as selectors: `kx[i] == k` picks component `k`.
    kx: [u8; LANES],
    ky: [u8; LANES],
    kz: [u8; LANES],
    sx: Lanes,
    sy: Lanes,
    sz: Lanes,
    rp: [RayPrecomp; LANES],
}

impl Packet {
    fn new(rays: &[Ray; LANES]) -> Packet {
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
            rp: [RayPrecomp::new(&rays[0]); LANES],
        };
        for (i, r) in rays.iter().enumerate() {
            let inv = Vec3::ONE / r.dir;
            for k in 0..3 {
                p.o[k][i] = r.origin[k];
                p.dir[k][i] = r.dir[k];
                p.inv[k][i] = inv[k];
            }
            p.tmin[i] = r.tmin;
            p.tmax[i] = r.tmax;
            let rp = RayPrecomp::new(r);
            p.kx[i] = rp.kx as u8;
            p.ky[i] = rp.ky as u8;
            p.kz[i] = rp.kz as u8;
            p.sx[i] = rp.sx;
            p.sy[i] = rp.sy;
            p.sz[i] = rp.sz;
            p.rp[i] = rp;
        }
        p
    }
}

/// The best hit per lane.
struct Best {
    t: Lanes,
    id: [u32; LANES],
}

/// Tests one triangle against the lanes in `mask`; returns the lanes whose
/// edge functions hit an exact zero and need the scalar test's
/// double-precision fallback.
#[inline(always)]
fn kernel_body(p: &Packet, tri: &[Vec3; 3], id: u32, mask: u16, best: &mut Best) -> u16 {
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
        let ax = sel(kx, a) - p.sx[i] * akz;
        let ay = sel(ky, a) - p.sy[i] * akz;
        let bx = sel(kx, b) - p.sx[i] * bkz;
        let by = sel(ky, b) - p.sy[i] * bkz;
        let cx = sel(kx, c) - p.sx[i] * ckz;
        let cy = sel(ky, c) - p.sy[i] * ckz;
        let u = cx * by - cy * bx;
        let v = ax * cy - ay * cx;
        let w = bx * ay - by * ax;
        fallback[i] = (u == 0.0) | (v == 0.0) | (w == 0.0);
        let mixed = ((u < 0.0) | (v < 0.0) | (w < 0.0)) & ((u > 0.0) | (v > 0.0) | (w > 0.0));
        let det = u + v + w;
        let az = p.sz[i] * akz;
        let bz = p.sz[i] * bkz;
        let cz = p.sz[i] * ckz;
        let t = (u * az + v * bz + w * cz) / det;
        let limit = if best.t[i] < p.tmax[i] {
            best.t[i]
        } else {
            p.tmax[i]
        };
        t_out[i] = t;
        ok[i] = !mixed & (det != 0.0) & (t > p.tmin[i]) & (t <= limit);
    }
    let mut need_fallback = 0u16;
    for i in 0..LANES {
        let active = mask & (1 << i) != 0;
        if active && fallback[i] {
            need_fallback |= 1 << i;
        } else if active && ok[i] {
            let t = t_out[i];
            if t < best.t[i] || (t == best.t[i] && id < best.id[i]) {
                best.t[i] = t;
                best.id[i] = id;
            }
        }
    }
    need_fallback
}

pub use crate::simd::SimdLevel;

/// Packet traversal of any source; also answers single rays (scalar).
pub struct PacketTracer<'a, S> {
    pub src: &'a S,
    pub level: SimdLevel,
}

impl<'a, S: KdSource> PacketTracer<'a, S> {
    /// Uses the best instruction set of this CPU.
    pub fn new(src: &'a S) -> Self {
        Self::with_level(src, SimdLevel::detect())
    }

    /// Uses `level`, which must be one of [`SimdLevel::available`] (a level
    /// the CPU lacks falls back to the baseline kernel).
    pub fn with_level(src: &'a S, level: SimdLevel) -> Self {
        let level = if SimdLevel::available().contains(&level) {
            level
        } else {
            SimdLevel::Baseline
        };
        PacketTracer { src, level }
    }
}

impl<S: KdSource> ClosestHit for PacketTracer<'_, S> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        traverse(self.src, ray)
    }

    fn closest_hit_4x4(&self, rays: &[Ray; LANES], out: &mut [Hit; LANES]) {
        match self.level {
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx512 => {
                // SAFETY: `with_level` keeps a level only if it is in
                // `SimdLevel::available()`, i.e. the CPU reported avx512f.
                unsafe { trace_packet_avx512(self.src, rays, out) }
            }
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx2 => {
                // SAFETY: as above, the CPU reported avx2.
                unsafe { trace_packet_avx2(self.src, rays, out) }
            }
            _ => trace_packet(self.src, rays, out),
        }
    }
}

/// True when all rays share the sign of every direction component.
fn coherent(rays: &[Ray; LANES]) -> bool {
    (0..3).all(|k| {
        let s = rays[0].dir[k].is_sign_negative();
        rays.iter().all(|r| r.dir[k].is_sign_negative() == s)
    })
}

struct Entry {
    node: u32,
    mask: u16,
    tmin: Lanes,
    tmax: Lanes,
}

/// The per-lane children and intervals at a split.
struct LaneSplit {
    left: u16,
    right: u16,
    l_tmin: Lanes,
    l_tmax: Lanes,
    r_tmin: Lanes,
    r_tmax: Lanes,
}

/// [`super::split_visit`] for 16 lanes at once, written branch-free so that
/// it vectorises. Each lane makes exactly the scalar decision: the cases
/// (ray starts in the plane, near only, far only, both) and intervals are
/// the same expressions.
#[inline(always)]
fn split_lanes(p: &Packet, k: usize, pos: f32, cur: &Entry) -> LaneSplit {
    let mut out = LaneSplit {
        left: 0,
        right: 0,
        l_tmin: [0.0; LANES],
        l_tmax: [0.0; LANES],
        r_tmin: [0.0; LANES],
        r_tmax: [0.0; LANES],
    };
    let mut l_vis = [false; LANES];
    let mut r_vis = [false; LANES];
    for i in 0..LANES {
        let (o, d, inv) = (p.o[k][i], p.dir[k][i], p.inv[k][i]);
        let (tmin, tmax) = (cur.tmin[i], cur.tmax[i]);
        let ts = (pos - o) * inv;
        let on_plane = o == pos;
        // Non-short-circuit `|` and `&` keep the loop free of branches.
        let below_first = (o < pos) | (on_plane & (d <= 0.0));
        let near_only = !on_plane & ((ts <= 0.0) | (ts - ts * MARGIN > tmax));
        let far_only = !on_plane & !near_only & (ts + ts * MARGIN < tmin);
        let both_split = !on_plane & !near_only & !far_only;
        let near_hi = if both_split { ts.min(tmax) } else { tmax };
        let far_lo = if both_split { ts.max(tmin) } else { tmin };
        let (near_vis, far_vis) = (!far_only, !near_only);
        l_vis[i] = if below_first { near_vis } else { far_vis };
        r_vis[i] = if below_first { far_vis } else { near_vis };
        out.l_tmin[i] = if below_first { tmin } else { far_lo };
        out.l_tmax[i] = if below_first { near_hi } else { tmax };
        out.r_tmin[i] = if below_first { far_lo } else { tmin };
        out.r_tmax[i] = if below_first { tmax } else { near_hi };
    }
    for i in 0..LANES {
        out.left |= u16::from(l_vis[i]) << i;
        out.right |= u16::from(r_vis[i]) << i;
    }
    out
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn trace_packet_avx512<S: KdSource + ?Sized>(src: &S, rays: &[Ray; LANES], out: &mut [Hit; LANES]) {
    trace_packet(src, rays, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn trace_packet_avx2<S: KdSource + ?Sized>(src: &S, rays: &[Ray; LANES], out: &mut [Hit; LANES]) {
    trace_packet(src, rays, out)
}

/// The packet traversal; inlined into one copy per instruction set, so
/// that its lane loops are vectorised for that set.
#[inline(always)]
fn trace_packet<S: KdSource + ?Sized>(src: &S, rays: &[Ray; LANES], out: &mut [Hit; LANES]) {
    if !coherent(rays) {
        for (r, h) in rays.iter().zip(out.iter_mut()) {
            *h = traverse(src, r);
        }
        return;
    }
    let p = Packet::new(rays);
    let mut best = Best {
        t: [f32::INFINITY; LANES],
        id: [u32::MAX; LANES],
    };
    let mut cur = Entry {
        node: src.root(),
        mask: 0,
        tmin: [0.0; LANES],
        tmax: [0.0; LANES],
    };
    let bounds = src.bounds();
    for (i, r) in rays.iter().enumerate() {
        let inv = Vec3::new(p.inv[0][i], p.inv[1][i], p.inv[2][i]);
        if let Some((t0, t1)) = clip_ray(&bounds, r, inv) {
            cur.mask |= 1 << i;
            cur.tmin[i] = t0;
            cur.tmax[i] = t1;
        }
    }
    let mut stack: Vec<Entry> = Vec::with_capacity(MAX_STACK);
    let test = |t_src: u32, mask: u16, best: &mut Best| {
        let tri = src.triangle(t_src);
        let id = src.input_id(t_src).0;
        let mut fallback = kernel_body(&p, &tri, id, mask, best);
        while fallback != 0 {
            let i = fallback.trailing_zeros() as usize;
            fallback &= fallback - 1;
            let limit = best.t[i].min(p.tmax[i]);
            if let Some(t) = intersect_triangle(&p.rp[i], &tri, p.tmin[i], limit)
                && (t < best.t[i] || (t == best.t[i] && id < best.id[i]))
            {
                best.t[i] = t;
                best.id[i] = id;
            }
        }
    };
    'outer: loop {
        if cur.mask != 0 {
            match src.node(cur.node) {
                SourceNode::Inner {
                    axis,
                    pos,
                    left,
                    right,
                    t_ref,
                } => {
                    if let Some(tri) = t_ref {
                        test(tri, cur.mask, &mut best);
                    }
                    let k = axis as usize;
                    let split = split_lanes(&p, k, pos, &cur);
                    let (l_mask, r_mask) = (split.left & cur.mask, split.right & cur.mask);
                    // All lanes share the direction sign: rays going up the
                    // axis meet the left child first.
                    let left_first = !p.dir[k][0].is_sign_negative();
                    let (first, second) = if left_first {
                        (
                            (left, l_mask, &split.l_tmin, &split.l_tmax),
                            (right, r_mask, &split.r_tmin, &split.r_tmax),
                        )
                    } else {
                        (
                            (right, r_mask, &split.r_tmin, &split.r_tmax),
                            (left, l_mask, &split.l_tmin, &split.l_tmax),
                        )
                    };
                    if second.1 != 0 {
                        stack.push(Entry {
                            node: second.0,
                            mask: second.1,
                            tmin: *second.2,
                            tmax: *second.3,
                        });
                    }
                    if first.1 != 0 {
                        cur.node = first.0;
                        cur.mask = first.1;
                        cur.tmin = *first.2;
                        cur.tmax = *first.3;
                        continue 'outer;
                    }
                }
                SourceNode::Leaf(tris) => tris.for_each(|t| test(t, cur.mask, &mut best)),
            }
        }
        // Pop the next cell and keep the lanes that may still find a hit
        // there (the scalar traverser's rule, per lane).
        loop {
            let Some(mut e) = stack.pop() else {
                break 'outer;
            };
            for i in 0..LANES {
                if e.mask & (1 << i) != 0 && e.tmin[i] - e.tmin[i] * MARGIN > best.t[i] {
                    e.mask &= !(1 << i);
                }
            }
            if e.mask != 0 {
                cur = e;
                continue 'outer;
            }
        }
    }
    for (i, o) in out.iter_mut().enumerate() {
        *o = if best.id[i] == u32::MAX {
            Hit::MISS
        } else {
            Hit {
                t: best.t[i],
                tri: crate::tree::TriId(best.id[i]),
            }
        };
    }
}
