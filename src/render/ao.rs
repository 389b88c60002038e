//! A renderer's frame of ambient occlusion: what the library is for. The
//! primary rays of a camera, then per hit a shadow ray to a point light
//! and `spp` cosine-distributed AO rays, each any-hit, starting from the
//! hit point; the frame time split by ray kind.
//!
//! The secondary rays are built as the Embree peer program's
//! `--make-rays` builds its ray files (`../shared/peers/`), so that the
//! frame compares kind by kind with Embree tracing those files: in `f64`,
//! the hit point `p = o + t·d + ε·n` with `ε = 10⁻⁵` of the scene's
//! diagonal and `n` the unit geometric normal facing the ray; the light
//! at `eye + 0.05·diag·(right + up)`, the shadow ray ending `10⁻⁵` of its
//! length short of it; AO rays of length `0.05·diag` about `n` (Duff et
//! al. 2017's basis), their random numbers from splitmix64 seeded by
//! `spp·pixel + k` (with `spp = 4`, the peer's rays exactly). Like the
//! peer's files, the rays are made before the clock starts, the AO rays
//! already in the order their packets take them.

use super::{Camera, Frame, HitBuffer, TriangleNormals, trace_frame};
use crate::geom::{Aabb, Ray};
use crate::trace::packet::LANES;
use crate::trace::rays::{occluded_ahead, order_for_packets};
use crate::trace::{ClosestHit, HitContext, OccluderCache};
use glam::{DVec3, Vec3};
use rayon::prelude::*;
use std::time::Instant;

/// How the secondary rays are traced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Secondary {
    /// One ray at a time from the root.
    Single,
    /// 16 rays at a time through [`ClosestHit::occluded_n_cached`] (a
    /// packet tracer's packets), one [`OccluderCache`] per worker and
    /// kind of ray.
    Packet,
    /// One ray at a time from the [`HitContext`] of the hit point, one
    /// context for the pixel's shadow and AO rays (its location timed
    /// apart).
    FromHit,
}

impl Secondary {
    /// The mode's name, as the CLI spells it.
    pub fn name(self) -> &'static str {
        match self {
            Secondary::Single => "single",
            Secondary::Packet => "packet",
            Secondary::FromHit => "from-hit",
        }
    }
}

/// The settings of an AO frame.
#[derive(Clone, Copy, Debug)]
pub struct AoOptions {
    /// AO rays per hit pixel.
    pub spp: u32,
    /// How the shadow and AO rays are traced.
    pub secondary: Secondary,
}

/// The figures of one AO frame: seconds of wall time by ray kind (the
/// secondary pass's wall time split in proportion to its threads' time
/// on each kind) and the rays traced.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AoTimes {
    /// Tracing the primary rays (one per pixel); as for every kind, the
    /// time spent making the rays is not counted.
    pub primary_s: f64,
    /// Locating the hit points' contexts ([`Secondary::FromHit`] only).
    pub context_s: f64,
    /// Shadow rays.
    pub shadow_s: f64,
    /// AO rays.
    pub ao_s: f64,
    /// Primary rays traced.
    pub primary_rays: u64,
    /// Shadow rays traced.
    pub shadow_rays: u64,
    /// AO rays traced.
    pub ao_rays: u64,
    /// Shadow rays that found something before the light.
    pub shadowed: u64,
    /// AO rays that found something within their length.
    pub ao_occluded: u64,
    /// Making the rays of every kind, not part of the frame (the peer's
    /// rays come from files): wall time, the primary rays' share of their
    /// pass (see [`HitBuffer::making_s`]) and the secondary rays' pass,
    /// which also puts each chunk's AO rays in the order of their packets
    /// (the order the peer's files hold them in).
    pub making_s: f64,
}

impl AoTimes {
    /// The whole frame's seconds.
    pub fn frame_s(&self) -> f64 {
        self.primary_s + self.context_s + self.shadow_s + self.ao_s
    }
}

/// A traced AO frame: the primary hits, per pixel the light it gets
/// (`[0, 1]`, 0 where the primary ray missed) and the figures.
pub struct AoFrame {
    /// The primary hits.
    pub primary: HitBuffer,
    /// Per pixel, row-major: AO times the light's share.
    pub light: Vec<f32>,
    /// The figures.
    pub times: AoTimes,
}

/// The secondary rays of one hit pixel.
struct PixelRays {
    pixel: u32,
    /// The hit point, off the surface (every ray's origin).
    origin: Vec3,
    /// Whether the point has a shadow ray (it is not at the light):
    /// `shadow[shadow_at]` of its [`ChunkRays`], where a pixel without
    /// one has the next pixel's index. The rays lie apart from the pixels
    /// so that the shadow packets read 32 bytes a ray, as from a ray
    /// file: read through the pixels, dieselpower's shadow rays took 21.7
    /// ms of its frame, 19.2 so (16 from a ray file).
    has_shadow: bool,
    shadow_at: usize,
    /// `spp` AO rays, from `ao[first..first + spp]` of its [`ChunkRays`]
    /// where those are in the pixels' order.
    first: usize,
    /// `n · l` toward the light (0 when facing away).
    cos_light: f32,
}

fn splitmix64(s: &mut u64) -> u64 {
    *s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *s;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn unit01(s: &mut u64) -> f64 {
    (splitmix64(s) >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
}

/// The secondary rays of a chunk of a frame's hit pixels (a tile's
/// worth, [`CHUNK`]): each chunk's rays are made, traced and dumped
/// together.
struct ChunkRays {
    pixels: Vec<PixelRays>,
    /// The shadow rays, pixel after pixel.
    shadow: Vec<Ray>,
    /// The AO rays, `spp` a pixel: pixel after pixel, or in the order
    /// their packets take them (`order_for_packets`), as `ao_of` says.
    ao: Vec<Ray>,
    /// Where the AO rays are in their packets' order, `ao[q]` is the ray
    /// `ao_of[q]` of the pixels' order (`spp · pixel + k`, the pixel's
    /// place in the chunk); empty where they are in the pixels' order.
    ao_of: Vec<u32>,
}

/// The secondary rays of every hit pixel (see the module docs), the hit
/// pixels in tiles of [`TILE_SIDE`]², row after row of tiles, in Morton
/// order within each ([`tile_order`]), so that a chunk is a square of
/// neighbours and the 16 rays of an octant or direction cell that make a
/// packet start close together; [`CHUNK`] hit pixels a chunk (fewer
/// where a hit triangle has no normal).
///
/// With `packets`, each chunk's AO rays are put in the order their packets
/// take them ([`order_for_packets`]) while they are in the caches, so that
/// the packets are traced straight from the array as from a ray file:
/// ordered (the first pass over rays fresh from memory) and gathered 16 at
/// a time while timed, dieselpower's AO rays took 242 ms of its frame at
/// view 1 against 217 so, for a making of 291 ms against 335 (medians of 8
/// alternated pairs). The order is the making's work, not the frame's, as
/// the peer's files hold the rays in it.
///
/// Each chunk's rays in vectors of its own, as they are traced: made a
/// pixel at a time (a vector of AO rays each), sorted into tiles and
/// joined into one array, they took most of the allocator's, the copies'
/// and the page faults' share of a 1024² dieselpower render's 1.4 s a
/// frame on two threads (0.6 s so, 0.25 s of it tracing).
fn secondary_rays(
    primary: &HitBuffer,
    camera: &Camera,
    bounds: &Aabb,
    normals: &(impl TriangleNormals + ?Sized),
    spp: u32,
    packets: bool,
) -> Vec<ChunkRays> {
    let (lo, hi) = (bounds.min.as_dvec3(), bounds.max.as_dvec3());
    let diag = (hi - lo).length();
    let (eps, radius) = (1e-5 * diag, 0.05 * diag);
    let f = (camera.at - camera.eye).normalize();
    let r = f.cross(camera.up).normalize();
    let u = r.cross(f);
    let light = camera.eye + 0.05 * diag * (r + u);
    let (width, lens) = (primary.width, camera.lens());
    // The rays of hit pixel `i`: its pixel (without its places in the
    // arrays), its shadow ray, its AO rays pushed onto `ao`.
    let pixel = |i: u32, ao: &mut Vec<Ray>| -> Option<(PixelRays, Option<Ray>)> {
        let hit = &primary.hits[i as usize];
        let ray = lens.ray(i % width, i / width);
        let mut n = normals.normal(hit.tri.0).as_dvec3();
        let len = n.length();
        if len.is_nan() || len <= 0.0 {
            return None;
        }
        let d = ray.dir.as_dvec3();
        n /= if n.dot(d) > 0.0 { -len } else { len };
        let p = ray.origin.as_dvec3() + f64::from(hit.t) * d + eps * n;
        let origin = p.as_vec3();
        let to_light = light - p;
        let dist = to_light.length();
        let shadow = (dist > 0.0).then(|| Ray {
            origin,
            dir: (to_light / dist).as_vec3(),
            tmin: 0.0,
            tmax: (dist * (1.0 - 1e-5)) as f32,
        });
        let cos_light = if dist > 0.0 {
            n.dot(to_light / dist).max(0.0) as f32
        } else {
            0.0
        };
        // The orthonormal basis about n of Duff et al. (2017).
        let sg = if n.z >= 0.0 { 1.0 } else { -1.0 };
        let a = -1.0 / (sg + n.z);
        let b = n.x * n.y * a;
        let t1 = DVec3::new(1.0 + sg * n.x * n.x * a, sg * b, -sg * n.x);
        let t2 = DVec3::new(b, sg + n.y * n.y * a, -n.y);
        ao.extend((0..spp).map(|k| {
            let mut st = u64::from(spp) * u64::from(i) + u64::from(k);
            let (u1, u2) = (unit01(&mut st), unit01(&mut st));
            let (rr, ph) = (u1.sqrt(), 2.0 * std::f64::consts::PI * u2);
            let lz = (1.0 - u1).max(0.0).sqrt();
            let w = rr * ph.cos() * t1 + rr * ph.sin() * t2 + lz * n;
            Ray {
                origin,
                dir: (w / w.length()).as_vec3(),
                tmin: 0.0,
                tmax: radius as f32,
            }
        }));
        let px = PixelRays {
            pixel: i,
            origin,
            has_shadow: shadow.is_some(),
            shadow_at: 0,
            first: 0,
            cos_light,
        };
        Some((px, shadow))
    };
    tile_order(primary)
        .par_chunks(CHUNK)
        // With `packets`, a worker's AO rays are made in the pixels' order
        // into `made`, then copied in their packets' order into the
        // chunk's array: one vector allocated a chunk, as without.
        .map_init(Vec::new, |made: &mut Vec<Ray>, chunk| {
            let mut part = ChunkRays {
                pixels: Vec::with_capacity(chunk.len()),
                shadow: Vec::with_capacity(chunk.len()),
                ao: Vec::with_capacity(chunk.len() * spp as usize),
                ao_of: Vec::new(),
            };
            let ao = if packets { &mut *made } else { &mut part.ao };
            ao.clear();
            for &i in chunk {
                let first = ao.len();
                if let Some((mut px, shadow)) = pixel(i, ao) {
                    px.first = first;
                    px.shadow_at = part.shadow.len();
                    part.shadow.extend(shadow);
                    part.pixels.push(px);
                }
            }
            if packets {
                order_for_packets(made, &mut part.ao_of);
                part.ao.extend(part.ao_of.iter().map(|&i| made[i as usize]));
            }
            part
        })
        .collect()
}

/// The hit pixels of `primary` in tiles of [`TILE_SIDE`]², row after row
/// of tiles, each tile's pixels in Morton order ([`morton2`]).
fn tile_order(primary: &HitBuffer) -> Vec<u32> {
    let (width, height) = (primary.width, primary.height);
    let mut offsets: Vec<(u32, u32)> = (0..TILE_SIDE * TILE_SIDE)
        .map(|k| (k % TILE_SIDE, k / TILE_SIDE))
        .collect();
    offsets.sort_unstable_by_key(|&(x, y)| morton2(x, y));
    let mut order = Vec::with_capacity(primary.hits.len());
    for ty in (0..height).step_by(TILE_SIDE as usize) {
        for tx in (0..width).step_by(TILE_SIDE as usize) {
            for &(dx, dy) in &offsets {
                let (x, y) = (tx + dx, ty + dy);
                if x < width && y < height {
                    let i = y * width + x;
                    if primary.hits[i as usize].is_hit() {
                        order.push(i);
                    }
                }
            }
        }
    }
    order
}

/// The side of the pixel tiles the secondary rays are traced in; a tile
/// is a chunk ([`CHUNK`]). The AO rays of a chunk are cut into packets of
/// one octant or direction cell (`order_for_packets`), and a chunk of
/// 1,024 pixels leaves fewer packets part-filled than one of 64 (8×8
/// tiles, by octant: the AO frame at view 1 ran 1.09–1.17× as fast on
/// bunny_scan, dieselpower and ravenbridge). Tiles of 64², every tile by
/// direction cell, ran ravenbridge's frame 1.10× and dieselpower's 0.96×
/// as fast as tiles of 32².
const TILE_SIDE: u32 = 32;

/// Hit pixels a worker takes at a time (a tile's worth); each chunk's
/// kinds are timed apart (a clock read per kind and chunk, not per ray).
const CHUNK: usize = (TILE_SIDE * TILE_SIDE) as usize;

/// `x` and `y` (below 2^16) with their bits interleaved, `x` in the even
/// bits: the Morton order of a tile's pixels.
fn morton2(x: u32, y: u32) -> u32 {
    let spread = |v: u32| {
        let mut v = v & 0xffff;
        v = (v | v << 8) & 0x00ff_00ff;
        v = (v | v << 4) & 0x0f0f_0f0f;
        v = (v | v << 2) & 0x3333_3333;
        (v | v << 1) & 0x5555_5555
    };
    spread(x) | spread(y) << 1
}

/// What one chunk of pixels gives back.
#[derive(Default)]
struct ChunkOut {
    context_s: f64,
    shadow_s: f64,
    ao_s: f64,
    /// Per pixel of the chunk: shadowed, and AO rays that got out.
    results: Vec<(bool, u32)>,
}

/// Traces an AO frame with `tracer` on the current rayon pool: the
/// primary rays in 4×4 packets ([`trace_frame`]), then the secondary rays
/// as `options` says. `bounds` is the scene's box (its diagonal sets the
/// offsets and lengths); `normals` gives the normals of the triangles the
/// primary rays hit (a file's [`FileNormals`](super::FileNormals) is made
/// from the hits).
pub fn trace_ao_frame<N: TriangleNormals>(
    tracer: &dyn ClosestHit,
    camera: &Camera,
    bounds: &Aabb,
    normals: impl FnOnce(&HitBuffer) -> N,
    options: &AoOptions,
) -> AoFrame {
    let primary = trace_frame(tracer, camera);
    let spp = options.spp as usize;
    let normals = normals(&primary);
    let start = Instant::now();
    let packets = options.secondary == Secondary::Packet;
    let rays = secondary_rays(&primary, camera, bounds, &normals, options.spp, packets);
    let making_s = primary.making_s + start.elapsed().as_secs_f64();
    let start = Instant::now();
    let chunks: Vec<ChunkOut> = rays
        .par_iter()
        .enumerate()
        .with_max_len(crate::trace::rays::job_len(CHUNK))
        .map_init(
            || {
                let n = if options.secondary == Secondary::FromHit {
                    CHUNK
                } else {
                    0
                };
                Scratch {
                    contexts: vec![HitContext::default(); n],
                    shadow: OccluderCache::new(),
                    ao: OccluderCache::new(),
                }
            },
            |scratch, (k, chunk)| {
                // The next chunk's AO rays, read on the way.
                let ahead = rays.get(k + 1).map_or(&[][..], |c| &c.ao[..]);
                trace_chunk(tracer, options.secondary, chunk, ahead, spp, scratch)
            },
        )
        .collect();
    let secondary_s = start.elapsed().as_secs_f64();
    let thread_s: f64 = chunks
        .iter()
        .map(|c| c.context_s + c.shadow_s + c.ao_s)
        .sum();
    let share = |f: fn(&ChunkOut) -> f64| {
        if thread_s > 0.0 {
            secondary_s * chunks.iter().map(f).sum::<f64>() / thread_s
        } else {
            0.0
        }
    };
    let mut light = vec![0f32; primary.hits.len()];
    let (mut shadowed, mut ao_occluded) = (0u64, 0u64);
    let pixels = rays.iter().flat_map(|c| &c.pixels);
    for (px, &(dark, open)) in pixels.zip(chunks.iter().flat_map(|c| &c.results)) {
        shadowed += u64::from(dark);
        ao_occluded += u64::from(options.spp - open);
        let ambient = if spp > 0 {
            open as f32 / spp as f32
        } else {
            1.0
        };
        let direct = if dark { 0.0 } else { px.cos_light };
        light[px.pixel as usize] = ambient * (0.3 + 0.7 * direct);
    }
    let times = AoTimes {
        // Tracing only, as the secondary kinds (whose rays are made
        // before their clock starts) and the peer's figures from ray
        // files: making the rays took 4–5 ms of dieselpower's and
        // bunny_scan's primary pass of 23 and 37 ms.
        primary_s: primary.seconds - primary.making_s,
        context_s: share(|c| c.context_s),
        shadow_s: share(|c| c.shadow_s),
        ao_s: share(|c| c.ao_s),
        primary_rays: primary.hits.len() as u64,
        shadow_rays: rays.iter().map(|c| c.shadow.len() as u64).sum(),
        ao_rays: rays.iter().map(|c| c.ao.len() as u64).sum(),
        shadowed,
        ao_occluded,
        making_s,
    };
    AoFrame {
        primary,
        light,
        times,
    }
}

/// The rays of an AO frame, each kind in the order the frame traces it,
/// for the peer program (`embree_bench --rays`): the same rays, so that
/// the frame compares kind by kind.
pub struct FrameRays {
    /// The primary rays ([`super::primary_rays`]: 16 consecutive rays are
    /// a 4×4 packet).
    pub primary: Vec<Ray>,
    /// The hit pixels' shadow rays, tile by tile (32×32 pixels), Morton
    /// order within a tile.
    pub shadow: Vec<Ray>,
    /// The AO rays, chunk by chunk (1,024 hit pixels, a tile's worth),
    /// each chunk's in the order its packets take them
    /// (`order_for_packets`: 16 consecutive rays of a chunk are a packet;
    /// a chunk's last packet may hold fewer, which a tracer of the whole
    /// file fills from the next chunk).
    pub ao: Vec<Ray>,
}

/// The rays [`trace_ao_frame`] traces after its primary rays hit as
/// `primary` says ([`AoFrame::primary`]), with `spp` AO rays a hit
/// pixel.
pub fn frame_rays<N: TriangleNormals>(
    primary: &HitBuffer,
    camera: &Camera,
    bounds: &Aabb,
    normals: &N,
    spp: u32,
) -> FrameRays {
    let chunks = secondary_rays(primary, camera, bounds, normals, spp, true);
    let (mut shadow, mut ao) = (Vec::new(), Vec::new());
    for chunk in &chunks {
        shadow.extend_from_slice(&chunk.shadow);
        ao.extend_from_slice(&chunk.ao);
    }
    FrameRays {
        primary: super::primary_rays(camera),
        shadow,
        ao,
    }
}

/// What a worker keeps from chunk to chunk: the contexts of a chunk's
/// pixels (from-hit mode) and one occluder cache per kind of ray, so that
/// the first packet of a chunk tests the occluders of the worker's last
/// one (its neighbour in the image as often as not).
struct Scratch {
    contexts: Vec<HitContext>,
    shadow: OccluderCache,
    ao: OccluderCache,
}

/// One chunk of pixels: contexts, shadow rays, AO rays, each kind timed;
/// `ahead` are the AO rays traced next.
fn trace_chunk(
    tracer: &dyn ClosestHit,
    mode: Secondary,
    rays: &ChunkRays,
    ahead: &[Ray],
    spp: usize,
    scratch: &mut Scratch,
) -> ChunkOut {
    let (chunk, shadow, ao) = (&rays.pixels[..], &rays.shadow[..], &rays.ao[..]);
    let shadow_ray = |px: &PixelRays| px.has_shadow.then(|| shadow[px.shadow_at]);
    let contexts = &mut scratch.contexts[..];
    let mut out = ChunkOut {
        results: vec![(false, 0); chunk.len()],
        ..ChunkOut::default()
    };
    let t0 = Instant::now();
    if mode == Secondary::FromHit {
        for (px, ctx) in chunk.iter().zip(contexts.iter_mut()) {
            tracer.locate_into(px.origin, ctx);
        }
    }
    let t1 = Instant::now();
    match mode {
        Secondary::Single => {
            for (px, res) in chunk.iter().zip(out.results.iter_mut()) {
                res.0 = shadow_ray(px).is_some_and(|r| tracer.occluded(&r));
            }
        }
        Secondary::FromHit => {
            for ((px, res), ctx) in chunk
                .iter()
                .zip(out.results.iter_mut())
                .zip(contexts.iter())
            {
                res.0 = shadow_ray(px).is_some_and(|r| tracer.occluded_from(ctx, &r));
            }
        }
        Secondary::Packet => {
            // The chunk's shadow rays in packets of 16 straight from
            // their array, then their answers to the pixels that have one.
            let mut occ = vec![false; shadow.len()];
            let cache = &mut scratch.shadow;
            for (rays, occ) in shadow.chunks(LANES).zip(occ.chunks_mut(LANES)) {
                tracer.occluded_n_cached(rays, occ, cache);
            }
            let mut occ = occ.into_iter();
            for (px, res) in chunk.iter().zip(out.results.iter_mut()) {
                if px.has_shadow {
                    res.0 = occ.next().expect("a shadow ray per pixel that has one");
                }
            }
        }
    }
    let t2 = Instant::now();
    match mode {
        Secondary::Single | Secondary::FromHit => {
            for (i, (px, res)) in chunk.iter().zip(out.results.iter_mut()).enumerate() {
                let rays = &ao[px.first..px.first + spp];
                res.1 = if mode == Secondary::FromHit {
                    let ctx = &contexts[i];
                    rays.iter()
                        .filter(|r| !tracer.occluded_from(ctx, r))
                        .count() as u32
                } else {
                    rays.iter().filter(|r| !tracer.occluded(r)).count() as u32
                };
            }
        }
        Secondary::Packet => {
            // In their packets' order, made so (`secondary_rays`). The
            // next chunk's AO rays (a worker mostly takes the chunks of
            // one range in turn) are read on the way, so that they are in
            // the caches when their turn comes: on one thread
            // dieselpower's AO rays take 228 ms instead of 247. (Its next
            // shadow rays read likewise took 0.8 ms off the shadow rays on
            // two threads and added 4 to the AO rays.)
            let mut occ = vec![false; ao.len()];
            occluded_ahead(tracer, ao, &mut occ, &mut scratch.ao, ahead);
            // Back to the pixels' order, where a pixel's `spp` answers are
            // consecutive (a division a ray to find its pixel took 2.6 ms
            // of dieselpower's frame on one thread).
            let mut by_pixel = vec![false; ao.len()];
            for (&i, &o) in rays.ao_of.iter().zip(&occ) {
                by_pixel[i as usize] = o;
            }
            for (res, occ) in out.results.iter_mut().zip(by_pixel.chunks(spp.max(1))) {
                res.1 = occ.iter().filter(|&&o| !o).count() as u32;
            }
        }
    }
    let t3 = Instant::now();
    out.context_s = (t1 - t0).as_secs_f64();
    out.shadow_s = (t2 - t1).as_secs_f64();
    out.ao_s = (t3 - t2).as_secs_f64();
    out
}

/// The frame's picture: grey, the light each pixel gets, a dark blue
/// background.
pub fn shade_ao(frame: &AoFrame) -> Frame {
    let background = [0.05f32, 0.05, 0.08];
    let rgb = frame
        .primary
        .hits
        .iter()
        .zip(&frame.light)
        .map(|(h, &l)| if h.is_hit() { [l, l, l] } else { background })
        .collect();
    Frame {
        width: frame.primary.width,
        height: frame.primary.height,
        rgb,
        depth: frame.primary.depth(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_order_is_the_hit_pixels_sorted_by_tile_then_morton() {
        // Neither side a multiple of the tile, and a scatter of misses.
        let (width, height) = (TILE_SIDE * 2 + 7, TILE_SIDE + 9);
        let hits: Vec<crate::trace::Hit> = (0..width * height)
            .map(|i| {
                if i % 7 == 3 || i % 11 == 0 {
                    crate::trace::Hit::MISS
                } else {
                    crate::trace::Hit {
                        t: 1.0,
                        tri: crate::tree::TriId(i),
                    }
                }
            })
            .collect();
        let mut want: Vec<u32> = (0..width * height)
            .filter(|&i| hits[i as usize].is_hit())
            .collect();
        want.sort_by_key(|&i| {
            let (x, y) = (i % width, i / width);
            (
                (y / TILE_SIDE) * width.div_ceil(TILE_SIDE) + x / TILE_SIDE,
                morton2(x % TILE_SIDE, y % TILE_SIDE),
            )
        });
        let primary = HitBuffer {
            width,
            height,
            hits,
            seconds: 0.0,
            making_s: 0.0,
        };
        assert_eq!(tile_order(&primary), want);
    }

    #[test]
    fn morton2_interleaves_and_orders_a_tile_in_2x2_blocks() {
        assert_eq!(morton2(0b11, 0b01), 0b0111);
        assert_eq!(morton2(0, 0xffff), 0xaaaa_aaaa);
        let mut order: Vec<(u32, u32)> = (0..TILE_SIDE)
            .flat_map(|y| (0..TILE_SIDE).map(move |x| (x, y)))
            .collect();
        order.sort_by_key(|&(x, y)| morton2(x, y));
        let codes: Vec<u32> = order.iter().map(|&(x, y)| morton2(x, y)).collect();
        assert_eq!(codes, (0..TILE_SIDE * TILE_SIDE).collect::<Vec<_>>());
        for block in order.chunks(4) {
            let (x0, y0) = (block[0].0 & !1, block[0].1 & !1);
            assert!(block.iter().all(|&(x, y)| x & !1 == x0 && y & !1 == y0));
        }
    }
}
