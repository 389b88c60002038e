//! Ray files and tracing a batch of rays: the format and the work split of
//! the Embree peer program (`../shared/peers/`), so that the two can be
//! compared ray by ray.
//!
//! A ray file is N records of 8 little-endian `f32`, 32 bytes each, no
//! header: `ox oy oz tmin dx dy dz tmax`. The result of a closest-hit query
//! is the hit's `t` (`+inf` for a miss); of an any-hit (`occluded`) query,
//! 1 when something lies in `(tmin, tmax)` and 0 when not. Rays go to the
//! threads in chunks of [`CHUNK`] consecutive rays; packets are 16
//! consecutive rays of a chunk (the chunk's last packet may be shorter).

use super::packet::LANES;
use super::{ClosestHit, Hit, HitContext, TraceStats};
use crate::geom::{Ray, dominant_axis};
use glam::Vec3;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

/// Bytes of one ray record.
pub const RECORD: usize = 32;

/// Rays in a stream of `slimkd trace --mode stream`: of 256, 1024 and
/// 4096, the fastest on dieselpower AO rays (5.35, 4.60, 5.25 Mrays/s)
/// and within 7 % of the best on ravenbridge.
pub const STREAM: usize = 256;

/// Consecutive rays a thread takes at a time.
pub const CHUNK: usize = 256;

/// Rays one rayon job holds at most (`with_max_len`). Rayon cuts a batch
/// into a few jobs a thread and cuts a job again only where another thread
/// steals it before it starts, so the thread that finished first waited
/// for the other's last long job: `trace -j 2` kept 1.6 of the 2 cores
/// busy on dieselpower's AO rays. In jobs of at most 4,096 rays those run
/// 1.2× as fast (33.4 → 40.2 Mrays/s); a worker's state (its occluder
/// cache) starts anew with each job. The renderer's frames cap their jobs
/// at as many pixels.
pub const JOB_RAYS: usize = 4096;

/// Pieces of `per` rays (or pixels) in one rayon job: [`JOB_RAYS`]'
/// worth, at least one.
pub fn job_len(per: usize) -> usize {
    (JOB_RAYS / per).max(1)
}

/// Consecutive rays a thread orders by octant at a time in
/// [`trace_batch_sorted`]: 256 pixels' AO rays at 4 a pixel, so that each
/// octant fills several packets (the renderer's AO rays ran 1.1–1.2× as
/// fast in chunks of 1,024 pixels as in chunks of 64, 256 rays, whose
/// octants left more packets part-filled).
pub const SORT_CHUNK: usize = 1024;

/// Rays a thread traces in lanes at a time.
pub const LANES_CHUNK: usize = 2048;

/// What is wrong with a ray file.
#[derive(Debug, thiserror::Error)]
pub enum RayFileError {
    /// The file could not be read.
    #[error("{}: {}", .0.display(), .1)]
    Io(PathBuf, std::io::Error),
    /// The size is not a whole number of records.
    #[error(
        "{}: size {} bytes is not a multiple of {RECORD} (records are ox oy oz tmin dx dy dz tmax, f32)",
        .0.display(), .1
    )]
    Size(PathBuf, u64),
    /// Record `index` (from 0) is not a ray.
    #[error("{}: ray {index}: {what}", .path.display())]
    Record {
        /// The ray file.
        path: PathBuf,
        /// The record's index (0-based).
        index: usize,
        /// What is wrong with it.
        what: &'static str,
    },
}

/// Parses ray records; `Err((index, what))` names the first bad record.
pub fn parse_rays(bytes: &[u8]) -> Result<Vec<Ray>, (usize, &'static str)> {
    bytes
        .chunks_exact(RECORD)
        .enumerate()
        .map(|(i, rec)| {
            let f: [f32; 8] = std::array::from_fn(|k| {
                f32::from_le_bytes(rec[4 * k..4 * k + 4].try_into().expect("4 bytes"))
            });
            let ray = Ray {
                origin: Vec3::new(f[0], f[1], f[2]),
                dir: Vec3::new(f[4], f[5], f[6]),
                tmin: f[3],
                tmax: f[7],
            };
            ray.check().map_err(|what| (i, what))?;
            // An empty interval is a valid query but no ray a renderer or
            // the peer's `--make-rays` writes: a file holding one is broken.
            if ray.tmin > ray.tmax {
                return Err((i, "tmin > tmax"));
            }
            Ok(ray)
        })
        .collect()
}

/// Reads and checks a ray file.
pub fn read_rays(path: &Path) -> Result<Vec<Ray>, RayFileError> {
    let io = |e| RayFileError::Io(path.to_path_buf(), e);
    let mut bytes = Vec::new();
    std::io::Read::read_to_end(
        &mut crate::fsio::open_regular(path).map_err(io)?,
        &mut bytes,
    )
    .map_err(io)?;
    if bytes.len() % RECORD != 0 {
        return Err(RayFileError::Size(path.to_path_buf(), bytes.len() as u64));
    }
    parse_rays(&bytes).map_err(|(index, what)| RayFileError::Record {
        path: path.to_path_buf(),
        index,
        what,
    })
}

/// The rays as file bytes.
pub fn ray_bytes(rays: &[Ray]) -> Vec<u8> {
    let mut out = Vec::with_capacity(rays.len() * RECORD);
    for r in rays {
        for v in [
            r.origin.x, r.origin.y, r.origin.z, r.tmin, r.dir.x, r.dir.y, r.dir.z, r.tmax,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// How a batch is traced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Query {
    /// Closest hit: each result is `t`, `+inf` for a miss.
    Closest,
    /// Any hit in `(tmin, tmax)`: each result is 1 or 0.
    Occluded,
}

/// A traced batch.
pub struct Traced {
    /// One result per ray (see [`Query`]).
    pub results: Vec<f32>,
    /// Wall time of the batch.
    pub seconds: f64,
}

impl Traced {
    /// Rays hit (closest) or occluded: the peer program's `hits`.
    pub fn hits(&self, query: Query) -> u64 {
        match query {
            Query::Closest => self.results.iter().filter(|t| t.is_finite()).count() as u64,
            Query::Occluded => self.results.iter().filter(|&&r| r == 1.0).count() as u64,
        }
    }

    /// The peer program's `checksum`: the sum of the hits' `t` in ray
    /// order (closest), or of the occluded rays' indices, in `f64`.
    pub fn checksum(&self, query: Query) -> f64 {
        match query {
            Query::Closest => self
                .results
                .iter()
                .filter(|t| t.is_finite())
                .map(|&t| f64::from(t))
                .sum(),
            Query::Occluded => self
                .results
                .iter()
                .enumerate()
                .filter(|(_, r)| **r == 1.0)
                .map(|(i, _)| i as f64)
                .sum(),
        }
    }

    /// Million rays per second.
    pub fn mrays_per_s(&self) -> f64 {
        self.results.len() as f64 / self.seconds / 1e6
    }
}

fn result(query: Query, hit: Hit) -> f32 {
    match query {
        Query::Closest => hit.t,
        Query::Occluded => f32::from(u8::from(hit.is_hit())),
    }
}

/// Traces `rays` in chunks of [`CHUNK`] on the current rayon pool, one by
/// one or, with `packets`, 16 consecutive rays at a time.
pub fn trace_batch(tracer: &dyn ClosestHit, rays: &[Ray], query: Query, packets: bool) -> Traced {
    timed_chunks(
        rays,
        CHUNK,
        super::OccluderCache::new,
        |cache, rays, out| trace_chunk(tracer, rays, query, packets, out, cache),
    )
}

/// Traces `rays` in chunks of `chunk` on the current rayon pool, each by
/// `each(state, rays, results)` with a state from `init` per rayon job,
/// and times the whole batch.
fn timed_chunks<S>(
    rays: &[Ray],
    chunk: usize,
    init: impl Fn() -> S + Sync + Send,
    each: impl Fn(&mut S, &[Ray], &mut [f32]) + Sync + Send,
) -> Traced {
    let mut results = vec![0f32; rays.len()];
    let start = Instant::now();
    results
        .par_chunks_mut(chunk)
        .zip(rays.par_chunks(chunk))
        .with_max_len(job_len(chunk))
        .for_each_init(init, |state, (out, rays)| each(state, rays, out));
    Traced {
        results,
        seconds: start.elapsed().as_secs_f64(),
    }
}

/// Traces `rays` in chunks of [`SORT_CHUNK`] on the current rayon pool,
/// each chunk as one batch ([`closest_batch`], [`occluded_batch`]: in
/// packets of one octant and longest axis, or direction cell, where it
/// mixes octants, else of its own order); the ordering is timed with the
/// rays.
pub fn trace_batch_sorted(tracer: &dyn ClosestHit, rays: &[Ray], query: Query) -> Traced {
    let init = || {
        (
            super::OccluderCache::new(),
            Vec::new(),
            Vec::new(),
            Vec::new(),
        )
    };
    timed_chunks(
        rays,
        SORT_CHUNK,
        init,
        |(cache, order, hits, occ), rays, out| match query {
            Query::Closest => {
                hits.clear();
                hits.resize(rays.len(), Hit::MISS);
                closest_batch(tracer, rays, hits, order);
                for (o, h) in out.iter_mut().zip(hits.iter()) {
                    *o = h.t;
                }
            }
            Query::Occluded => {
                occ.clear();
                occ.resize(rays.len(), false);
                occluded_batch(tracer, rays, occ, cache, order);
                for (o, &h) in out.iter_mut().zip(occ.iter()) {
                    *o = f32::from(u8::from(h));
                }
            }
        },
    )
}

/// The octant of a direction: bit 0 set where `x < 0`, bit 1 `y`, bit 2
/// `z`. Rays of one octant take every split's children in one order.
#[inline]
pub fn octant(dir: Vec3) -> usize {
    usize::from(dir.x < 0.0) | usize::from(dir.y < 0.0) << 1 | usize::from(dir.z < 0.0) << 2
}

/// `order` := the indices of `rays` by octant, in their own order within
/// an octant (a counting sort: stable, so that rays that start close
/// together stay together). A packet's lanes then mostly share their
/// direction's signs (a packet may hold the last rays of one octant and
/// the first of the next): the peer's AO rays of dieselpower (4 a pixel,
/// pixel order) traced 1.10x (closest) and 1.13x (any hit) as fast as in
/// packets of 16 consecutive rays.
pub fn order_by_octant(rays: &[Ray], order: &mut Vec<u32>) {
    let keys: Vec<u16> = rays.iter().map(|r| octant(r.dir) as u16).collect();
    counting_order(&keys, 8, 0, order);
}

/// `order` := the indices of `of` ascending in `of[i] >> shift` (below
/// `keys`), in their own order where keys are equal: a counting sort.
/// The first and the second half of the rays are counted and placed in
/// one loop, each half with its own counters, so that a key that repeats
/// from ray to ray waits on one counter's store half as often: by
/// octant, dieselpower's 4.19 M AO rays in runs of 4,096 took 11.7 ms
/// instead of 20.4 (one thread, each run in the caches).
fn counting_order(of: &[u16], keys: usize, shift: u32, order: &mut Vec<u32>) {
    debug_assert!(keys <= 1 << 16);
    let n = of.len();
    let (a, b) = of.split_at(n / 2);
    let (mut at, mut bt) = (vec![0u32; keys], vec![0u32; keys]);
    let key = |x: u16| usize::from(x >> shift);
    for (&x, &y) in a.iter().zip(b) {
        at[key(x)] += 1;
        bt[key(y)] += 1;
    }
    if let (Some(&y), true) = (b.last(), b.len() > a.len()) {
        bt[key(y)] += 1;
    }
    // Key k's rays of the first half start at `at[k]`, of the second
    // half at `bt[k]`, after them.
    let mut start = 0u32;
    for k in 0..keys {
        let (na, nb) = (at[k], bt[k]);
        (at[k], bt[k]) = (start, start + na);
        start += na + nb;
    }
    order.clear();
    order.resize(n, 0);
    let half = a.len();
    for (i, (&x, &y)) in a.iter().zip(b).enumerate() {
        let (x, y) = (key(x), key(y));
        order[at[x] as usize] = i as u32;
        at[x] += 1;
        order[bt[y] as usize] = (half + i) as u32;
        bt[y] += 1;
    }
    if let (Some(&y), true) = (b.last(), b.len() > a.len()) {
        order[bt[key(y)] as usize] = (n - 1) as u32;
    }
}

/// Direction cells a side of an octant's square in [`direction_cell`].
pub const DIRECTION_BINS: usize = 8;

/// The cell of a direction within its octant: `|d|` on the octahedron
/// (`|x| / s`, `|y| / s` with `s = |x| + |y| + |z|`) in a square of
/// [`DIRECTION_BINS`]² cells, numbered in Morton order so that cells of
/// close numbers hold close directions. A zero or NaN direction is cell 0.
#[inline]
pub fn direction_cell(dir: Vec3) -> usize {
    let a = dir.abs();
    // One division a ray (the sort's keys are its cost).
    let scale = DIRECTION_BINS as f32 / (a.x + a.y + a.z);
    // `as` saturates: NaN (a zero direction) is 0, and u = 1 is clamped.
    let u = ((a.x * scale) as usize).min(DIRECTION_BINS - 1);
    let v = ((a.y * scale) as usize).min(DIRECTION_BINS - 1);
    spread_bits(u) | spread_bits(v) << 1
}

/// The bits of `x` (below [`DIRECTION_BINS`]) moved to the even bits.
#[inline(always)]
fn spread_bits(x: usize) -> usize {
    (x & 1) | (x & 2) << 1 | (x & 4) << 2
}

/// `order` := the indices of `rays` by octant, within an octant by the
/// direction's longest axis ([`dominant_axis`]) and then by direction
/// cell ([`direction_cell`]), in their own order within a cell
/// (a counting sort: stable, so that rays that start close together stay
/// together). A packet of such rays from close origins shares its sign
/// bits (one order of every split's children) and, mostly, its path: the
/// renderer's AO rays of ravenbridge, in 32×32 tiles, took 15.4 packet
/// steps a ray at 3.9 active lanes against 22.1 at 2.4 by octant alone.
/// From origins far apart it loses: the peer's AO files in chunks of
/// 1,024 rays (256 pixels of a row) ran 0.83–0.91× as fast as by octant.
pub fn order_by_direction(rays: &[Ray], order: &mut Vec<u32>) {
    let mut keys = Vec::new();
    direction_keys(rays, &mut keys);
    counting_order(&keys, DIRECTION_KEYS, 0, order);
}

/// Keys of [`order_by_direction`] ([`direction_key`]).
const DIRECTION_KEYS: usize = 8 * 3 * DIRECTION_BINS * DIRECTION_BINS;

/// The key of [`order_by_direction`]: the octant, the dominant axis
/// ([`dominant_axis`]), then the direction cell. Rays of one octant and
/// one dominant axis share the triangle test's vertex permutation, which
/// the packets' test then picks once for all lanes
/// (`Packet::shared_permutation`): by octant and cell alone, 1 % of
/// bunny_scan's AO packets shared it (12 % of dieselpower's); a cell of
/// the octahedron straddles the planes where the dominant axis changes.
#[inline]
fn direction_key(dir: Vec3) -> u16 {
    let group = octant(dir) * 3 + dominant_axis(dir);
    (group * DIRECTION_BINS * DIRECTION_BINS + direction_cell(dir)) as u16
}

/// `keys` := the [`direction_key`] of every ray of `rays`, in one pass that also
/// finds whether their origins lie close together ([`close_origins`],
/// returned). The renderer orders each tile's AO rays this way: a ray at
/// a time (its fields loaded one by one, a division and a square root
/// each), a pass for the bounds and one for the keys took 24 ms of
/// dieselpower's 250 ms of AO rays on one thread besides reading the
/// rays; one pass of eight rays at a time in AVX2 ([`keys_avx2`]) takes
/// 6 ms.
fn direction_keys(rays: &[Ray], keys: &mut Vec<u16>) -> bool {
    let simd = crate::simd::SimdLevel::detect() != crate::simd::SimdLevel::Baseline;
    direction_keys_on(rays, keys, simd)
}

/// The origins' bounds and the shortest squared length of a batch of
/// rays, as [`close_origins`] reads them.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Spread {
    lo: [f32; 3],
    hi: [f32; 3],
    /// The least `tmax² · |dir|²`.
    shortest: f32,
}

impl Spread {
    const EMPTY: Spread = Spread {
        lo: [f32::INFINITY; 3],
        hi: [f32::NEG_INFINITY; 3],
        shortest: f32::INFINITY,
    };

    /// Grown by `r` (a NaN passed over, as `f32::min` and `max` do).
    fn add(&mut self, r: &Ray) {
        for k in 0..3 {
            self.lo[k] = self.lo[k].min(r.origin[k]);
            self.hi[k] = self.hi[k].max(r.origin[k]);
        }
        let d = r.dir;
        let length = (r.tmax * r.tmax) * ((d.x * d.x + d.y * d.y) + d.z * d.z);
        self.shortest = self.shortest.min(length);
    }

    /// Whether the origins lie close together ([`close_origins`]):
    /// compared squared, so that no ray takes a square root.
    fn close(&self) -> bool {
        let mut span = 0.0f32;
        for k in 0..3 {
            let e = self.hi[k] - self.lo[k];
            span += e * e;
        }
        span < CLOSE_ORIGINS * CLOSE_ORIGINS * self.shortest
    }
}

/// [`direction_keys`], eight rays at a time in AVX2 where `simd` is set
/// and the CPU has it.
fn direction_keys_on(rays: &[Ray], keys: &mut Vec<u16>, simd: bool) -> bool {
    keys.clear();
    keys.resize(rays.len(), 0);
    let mut spread = Spread::EMPTY;
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if simd && is_x86_feature_detected!("avx2") {
        // SAFETY: this CPU has AVX2.
        done = unsafe { keys_avx2(rays, keys, &mut spread) };
    }
    for (r, k) in rays[done..].iter().zip(&mut keys[done..]) {
        *k = direction_key(r.dir);
        spread.add(r);
    }
    spread.close()
}

/// [`direction_keys_on`]'s keys and spread of the rays of `rays` in
/// whole groups of eight, bit for bit as the scalar code (the same
/// operations in the same order; `minps`/`maxps` return their second
/// operand where one is a NaN, which passes a NaN over as `f32::min`
/// does and makes a NaN cell coordinate 0); returns how many rays it
/// took. Each group's eight records are transposed into eight registers,
/// one field each.
///
/// # Safety
/// The CPU has AVX2.
///
/// # Panics
/// If `keys` is not as long as `rays`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn keys_avx2(rays: &[Ray], keys: &mut [u16], spread: &mut Spread) -> usize {
    use std::arch::x86_64::*;
    assert_eq!(keys.len(), rays.len(), "a key a ray");
    // A ray is 8 `f32`: origin, direction, tmin, tmax (`repr(C)`).
    const _: () = assert!(
        std::mem::size_of::<Ray>() == 32
            && std::mem::offset_of!(Ray, dir) == 12
            && std::mem::offset_of!(Ray, tmax) == 28
            && DIRECTION_BINS == 8
    );
    let groups = rays.len() / 8;
    let mut lo = [_mm256_set1_ps(f32::INFINITY); 3];
    let mut hi = [_mm256_set1_ps(f32::NEG_INFINITY); 3];
    let mut shortest = _mm256_set1_ps(f32::INFINITY);
    let (zero, bins, last) = (
        _mm256_setzero_ps(),
        _mm256_set1_ps(DIRECTION_BINS as f32),
        _mm256_set1_ps((DIRECTION_BINS - 1) as f32),
    );
    let abs = |x: __m256| _mm256_andnot_ps(_mm256_set1_ps(-0.0), x);
    // A cell coordinate: the last where beyond it (∞ too), 0 for a NaN
    // (`cvttps2dq` gives `i32::MIN`, raised to 0).
    let bin = |f: __m256| {
        _mm256_max_epi32(
            _mm256_cvttps_epi32(_mm256_min_ps(last, f)),
            _mm256_setzero_si256(),
        )
    };
    let spread_bits = |b: __m256i| {
        let one = _mm256_and_si256(b, _mm256_set1_epi32(1));
        let two = _mm256_slli_epi32::<1>(_mm256_and_si256(b, _mm256_set1_epi32(2)));
        let four = _mm256_slli_epi32::<2>(_mm256_and_si256(b, _mm256_set1_epi32(4)));
        _mm256_or_si256(_mm256_or_si256(one, two), four)
    };
    let sign = |x: __m256, bit: i32| {
        let neg = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LT_OQ>(x, zero));
        _mm256_and_si256(neg, _mm256_set1_epi32(bit))
    };
    for g in 0..groups {
        let base = rays[g * 8..].as_ptr() as *const f32;
        // SAFETY: ray `8g + i` is in `rays`, 8 `f32` from `base + 8i`.
        let r: [__m256; 8] = std::array::from_fn(|i| unsafe { _mm256_loadu_ps(base.add(8 * i)) });
        // Per 128-bit half: [ox oy oz dx | dy dz tmin tmax].
        let t = [
            _mm256_unpacklo_ps(r[0], r[1]),
            _mm256_unpackhi_ps(r[0], r[1]),
            _mm256_unpacklo_ps(r[2], r[3]),
            _mm256_unpackhi_ps(r[2], r[3]),
            _mm256_unpacklo_ps(r[4], r[5]),
            _mm256_unpackhi_ps(r[4], r[5]),
            _mm256_unpacklo_ps(r[6], r[7]),
            _mm256_unpackhi_ps(r[6], r[7]),
        ];
        let s = [
            _mm256_shuffle_ps::<0x44>(t[0], t[2]),
            _mm256_shuffle_ps::<0xee>(t[0], t[2]),
            _mm256_shuffle_ps::<0x44>(t[1], t[3]),
            _mm256_shuffle_ps::<0xee>(t[1], t[3]),
            _mm256_shuffle_ps::<0x44>(t[4], t[6]),
            _mm256_shuffle_ps::<0xee>(t[4], t[6]),
            _mm256_shuffle_ps::<0x44>(t[5], t[7]),
            _mm256_shuffle_ps::<0xee>(t[5], t[7]),
        ];
        let o = [
            _mm256_permute2f128_ps::<0x20>(s[0], s[4]),
            _mm256_permute2f128_ps::<0x20>(s[1], s[5]),
            _mm256_permute2f128_ps::<0x20>(s[2], s[6]),
        ];
        let d = [
            _mm256_permute2f128_ps::<0x20>(s[3], s[7]),
            _mm256_permute2f128_ps::<0x31>(s[0], s[4]),
            _mm256_permute2f128_ps::<0x31>(s[1], s[5]),
        ];
        let tmax = _mm256_permute2f128_ps::<0x31>(s[3], s[7]);
        let octant = _mm256_or_si256(_mm256_or_si256(sign(d[0], 1), sign(d[1], 2)), sign(d[2], 4));
        let (ax, ay, az) = (abs(d[0]), abs(d[1]), abs(d[2]));
        let scale = _mm256_div_ps(bins, _mm256_add_ps(_mm256_add_ps(ax, ay), az));
        let (u, v) = (bin(_mm256_mul_ps(ax, scale)), bin(_mm256_mul_ps(ay, scale)));
        let cell = _mm256_or_si256(spread_bits(u), _mm256_slli_epi32::<1>(spread_bits(v)));
        // `dominant_axis`: 0 where x is longest, else 1 where y is, else
        // 2; as `2 + 2·x_max + y_max` with the masks' -1 for true.
        let x_max = _mm256_castps_si256(_mm256_and_ps(
            _mm256_cmp_ps::<_CMP_GE_OQ>(ax, ay),
            _mm256_cmp_ps::<_CMP_GE_OQ>(ax, az),
        ));
        let y_max = _mm256_andnot_si256(
            x_max,
            _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GE_OQ>(ay, az)),
        );
        let axis = _mm256_add_epi32(
            _mm256_set1_epi32(2),
            _mm256_add_epi32(_mm256_slli_epi32::<1>(x_max), y_max),
        );
        let group = _mm256_add_epi32(
            _mm256_add_epi32(octant, _mm256_slli_epi32::<1>(octant)),
            axis,
        );
        let key = _mm256_add_epi32(_mm256_slli_epi32::<6>(group), cell);
        // The eight keys (below 1,536) as `u16`, in order.
        let packed = _mm256_permute4x64_epi64::<0b1000>(_mm256_packus_epi32(key, key));
        // SAFETY: keys `8g..8g + 8` are in `keys`.
        unsafe {
            _mm_storeu_si128(
                keys[g * 8..].as_mut_ptr() as *mut __m128i,
                _mm256_castsi256_si128(packed),
            )
        };
        for k in 0..3 {
            lo[k] = _mm256_min_ps(o[k], lo[k]);
            hi[k] = _mm256_max_ps(o[k], hi[k]);
        }
        let d2 = _mm256_add_ps(
            _mm256_add_ps(_mm256_mul_ps(d[0], d[0]), _mm256_mul_ps(d[1], d[1])),
            _mm256_mul_ps(d[2], d[2]),
        );
        let length = _mm256_mul_ps(_mm256_mul_ps(tmax, tmax), d2);
        shortest = _mm256_min_ps(length, shortest);
    }
    let lanes = |x: __m256| {
        let mut a = [0.0f32; 8];
        // SAFETY: `a` holds 8 `f32`.
        unsafe { _mm256_storeu_ps(a.as_mut_ptr(), x) };
        a
    };
    for k in 0..3 {
        for (l, h) in lanes(lo[k]).into_iter().zip(lanes(hi[k])) {
            spread.lo[k] = spread.lo[k].min(l);
            spread.hi[k] = spread.hi[k].max(h);
        }
    }
    for x in lanes(shortest) {
        spread.shortest = spread.shortest.min(x);
    }
    groups * 8
}

/// The part of the rays' length below which a batch's origins count as
/// close together ([`close_origins`]). The renderer's AO tiles (32×32
/// pixels, rays of 5 % of the scene's diagonal) on the six shared scenes
/// at view 1: a tile's origins span a median 0.00–0.04 of the rays'
/// length on candela_city, black_forest and ravenbridge, whose AO frames
/// ran 1.28–1.35× as fast by direction cell, and 0.20–0.26 on
/// dieselpower, aneurysm and bunny_scan: by direction cell everywhere
/// 1.04×, 1.07× and 0.86×; at 0.1, 0.98–1.02×; at 0.3, 1.05×, 1.09× and
/// 0.97×.
pub const CLOSE_ORIGINS: f32 = 0.2;

/// Whether the origins of `rays` lie within a box whose diagonal is below
/// [`CLOSE_ORIGINS`] times the shortest ray's length (`tmax · |dir|`).
/// False for an empty batch or rays of no length, true for rays without
/// an end (`tmax` ∞) from finite origins; a NaN coordinate or length is
/// passed over (`f32::min`, `max`).
pub fn close_origins(rays: &[Ray]) -> bool {
    let mut spread = Spread::EMPTY;
    rays.iter().for_each(|r| spread.add(r));
    spread.close()
}

/// `order` := the order in which `rays` make packets that share the most
/// of their paths: by direction cell ([`order_by_direction`]) where their
/// origins lie close together against their length ([`close_origins`]),
/// else by octant and longest axis (as [`order_by_octant`], each of its
/// groups cut in three), which keeps neighbouring origins together. Both
/// keep a packet's lanes to one vertex permutation of the triangle test
/// ([`order_by_direction`]): bunny_scan's AO pass in the frame ran 1.14× as
/// fast, dieselpower's 1.06× (ravenbridge 0.99×). Rays of one direction
/// from close origins cross the same cells; rays from origins far apart
/// against the cells around them (bunny_scan's scanned surface, whose AO
/// rays mostly escape) share more of their paths when their origins are
/// neighbours.
pub fn order_for_packets(rays: &[Ray], order: &mut Vec<u32>) {
    let mut keys = Vec::new();
    if direction_keys(rays, &mut keys) {
        counting_order(&keys, DIRECTION_KEYS, 0, order);
    } else {
        // The octant and the dominant axis are the key's high bits.
        let cells = (DIRECTION_BINS * DIRECTION_BINS).trailing_zeros();
        counting_order(&keys, DIRECTION_KEYS >> cells, cells, order);
    }
}

/// The 16 rays of `rays` that `group` names, gathered for a packet.
fn gather(rays: &[Ray], group: &[u32]) -> [Ray; LANES] {
    let mut batch = [Ray::new(Vec3::ZERO, Vec3::X); LANES];
    gather_into(&mut batch, rays, group);
    batch
}

/// [`gather`] into `batch`.
fn gather_into(batch: &mut [Ray; LANES], rays: &[Ray], group: &[u32]) {
    for (b, &i) in batch.iter_mut().zip(group) {
        *b = rays[i as usize];
    }
}

/// `trace(batch, group)` for each 16 consecutive entries `group` of
/// `order`, `batch` the rays they name. Each packet is gathered while the
/// one before is traced, into the other of two buffers, so that its
/// loads do not follow right on its gather's stores (a load across
/// several smaller stores is not forwarded). Gathered right before its
/// trace, the AVX2 copy ran the renderer's AO rays of dieselpower and
/// bunny_scan 3–8 % slower (the AVX-512 copy within the noise).
fn in_packets(rays: &[Ray], order: &[u32], mut trace: impl FnMut(&[Ray], &[u32])) {
    let mut bufs = [[Ray::new(Vec3::ZERO, Vec3::X); LANES]; 2];
    let group = |k: usize| &order[k * LANES..order.len().min((k + 1) * LANES)];
    let n = order.len().div_ceil(LANES);
    if n > 0 {
        gather_into(&mut bufs[0], rays, group(0));
    }
    for k in 0..n {
        if k + 1 < n {
            gather_into(&mut bufs[(k + 1) & 1], rays, group(k + 1));
        }
        let g = group(k);
        trace(&bufs[k & 1][..g.len()], g);
    }
}

/// Any-hit queries of `rays` into `out`, in packets of 16 consecutive
/// rays through the worker's occluder cache
/// ([`ClosestHit::occluded_n_cached`]), with each packet a share of
/// `ahead` (the rays the caller traces next, may be empty) read into the
/// caches, so that those rays come from memory while these are traced:
/// the renderer's first pass over a tile's AO rays, fresh from memory,
/// took 22 ms of dieselpower's 240 ms of AO rays on one thread, 6 ms in
/// the caches.
///
/// # Panics
/// If `out` and `rays` differ in length.
pub fn occluded_ahead(
    tracer: &dyn ClosestHit,
    rays: &[Ray],
    out: &mut [bool],
    cache: &mut super::OccluderCache,
    ahead: &[Ray],
) {
    assert_eq!(rays.len(), out.len(), "one answer per ray");
    // The rays of `ahead` a packet reads, two to a cache line.
    let share = ahead.len().div_ceil(rays.len().div_ceil(LANES).max(1));
    let share = share.next_multiple_of(2);
    for (k, (rays, out)) in rays.chunks(LANES).zip(out.chunks_mut(LANES)).enumerate() {
        if let Some(next) = ahead.get(k * share..ahead.len().min((k + 1) * share)) {
            for r in next.iter().step_by(2) {
                prefetch(r);
            }
        }
        tracer.occluded_n_cached(rays, out, cache);
    }
}

/// Asks for the cache line of `r` to be read into the caches (L2 and
/// beyond), without waiting for it.
#[inline(always)]
fn prefetch(r: &Ray) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch only hints; the address is that of a live ray.
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T1, _mm_prefetch};
        _mm_prefetch::<_MM_HINT_T1>((r as *const Ray).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = r;
}

/// Whether at least half of the packets of 16 consecutive rays of `rays`
/// end in another octant than they start in, so that packets in the
/// batch's order would mix their directions' signs (AO rays, 4 a pixel:
/// 7 in 8 packets) and an order by octant pays. Shadow rays toward one
/// light and primary rays come in runs of one octant far longer than a
/// packet (the peer's shadow files: at most 10 changes in 1,024 rays);
/// ordered by octant they kept their packets and lost 9-18 % to the
/// order's passes and copies. Two rays of a packet are looked at.
pub fn mixed_octants(rays: &[Ray]) -> bool {
    let packets = rays.chunks(LANES);
    let half = packets.len().div_ceil(2);
    let mut mixed = 0;
    for p in packets {
        mixed += usize::from(octant(p[0].dir) != octant(p[p.len() - 1].dir));
        if mixed >= half {
            return true;
        }
    }
    false
}

/// Closest hits of `rays` into `out`, traced in packets of the 16 rays
/// that each 16 consecutive entries of `order` name
/// ([`order_by_octant`], [`order_by_direction`]). Indices past `rays`
/// panic.
pub fn closest_in_order(tracer: &dyn ClosestHit, rays: &[Ray], order: &[u32], out: &mut [Hit]) {
    in_packets(rays, order, |batch, group| {
        let mut hits = [Hit::MISS; LANES];
        tracer.closest_hit_n(batch, &mut hits[..group.len()]);
        for (&i, h) in group.iter().zip(hits) {
            out[i as usize] = h;
        }
    });
}

/// [`closest_in_order`] for any-hit queries, through the worker's
/// occluder cache ([`ClosestHit::occluded_n_cached`]).
pub fn occluded_in_order(
    tracer: &dyn ClosestHit,
    rays: &[Ray],
    order: &[u32],
    out: &mut [bool],
    cache: &mut super::OccluderCache,
) {
    in_packets(rays, order, |batch, group| {
        let mut occ = [false; LANES];
        tracer.occluded_n_cached(batch, &mut occ[..group.len()], cache);
        for (&i, o) in group.iter().zip(occ) {
            out[i as usize] = o;
        }
    });
}

/// Closest hits of a batch of `rays` into `out`, 16 at a time: in the
/// order of [`order_for_packets`] (by direction cell where the origins
/// lie close together, else by octant and longest axis) where the batch
/// mixes octants ([`mixed_octants`]), else in packets of its own order.
/// `order` is scratch.
pub fn closest_batch(tracer: &dyn ClosestHit, rays: &[Ray], out: &mut [Hit], order: &mut Vec<u32>) {
    if mixed_octants(rays) {
        order_for_packets(rays, order);
        closest_in_order(tracer, rays, order, out);
    } else {
        for (rays, out) in rays.chunks(LANES).zip(out.chunks_mut(LANES)) {
            tracer.closest_hit_n(rays, out);
        }
    }
}

/// [`closest_batch`] for any-hit queries, through the worker's occluder
/// cache.
pub fn occluded_batch(
    tracer: &dyn ClosestHit,
    rays: &[Ray],
    out: &mut [bool],
    cache: &mut super::OccluderCache,
    order: &mut Vec<u32>,
) {
    if mixed_octants(rays) {
        order_for_packets(rays, order);
        occluded_in_order(tracer, rays, order, out, cache);
    } else {
        occluded_ahead(tracer, rays, out, cache, &[]);
    }
}

/// Traces `rays` like [`trace_batch`] one by one, each walked from the
/// [`HitContext`] of its origin: a run of consecutive rays with the same
/// origin (the shadow and AO rays of one hit point, as the peer program
/// writes them) shares one context, located for the first of them and
/// timed with the rays.
pub fn trace_batch_from_hit(tracer: &dyn ClosestHit, rays: &[Ray], query: Query) -> Traced {
    timed_chunks(
        rays,
        CHUNK,
        || (),
        |(), rays, out| {
            let mut ctx = HitContext::default();
            let mut at = None;
            for (r, o) in rays.iter().zip(out.iter_mut()) {
                if at != Some(r.origin) {
                    tracer.locate_into(r.origin, &mut ctx);
                    at = Some(r.origin);
                }
                *o = match query {
                    Query::Closest => tracer.closest_hit_from(&ctx, r).t,
                    Query::Occluded => f32::from(u8::from(tracer.occluded_from(&ctx, r))),
                };
            }
        },
    )
}

/// Traces `rays` as any-hit queries in streams of `stream` consecutive
/// rays ([`super::stream::occluded_stream`]), the streams on the current
/// rayon pool; results as [`trace_batch`]'s with [`Query::Occluded`].
pub fn trace_batch_stream<S: super::KdSource>(src: &S, rays: &[Ray], stream: usize) -> Traced {
    let walk = src.walk();
    timed_chunks(
        rays,
        stream.max(1),
        || (),
        |(), rays, out| {
            let mut occ = vec![false; rays.len()];
            super::stream::occluded_stream(walk, rays, &mut occ);
            for (o, h) in out.iter_mut().zip(occ) {
                *o = f32::from(u8::from(h));
            }
        },
    )
}

/// Traces `rays` as any-hit queries in lanes
/// ([`super::lanes::occluded_lanes`]), [`LANES_CHUNK`] rays at a time on the
/// current rayon pool; results as [`trace_batch`]'s with
/// [`Query::Occluded`].
pub fn trace_batch_lanes<D: AsRef<[u8]> + Sync>(
    file: &crate::format::KdFile<D>,
    rays: &[Ray],
) -> Traced {
    let walk = super::FileWalk::new(file);
    let level = crate::simd::SimdLevel::detect();
    timed_chunks(
        rays,
        LANES_CHUNK,
        || (),
        |(), rays, out| {
            let mut occ = [false; LANES_CHUNK];
            super::lanes::occluded_lanes(walk, level, rays, &mut occ[..rays.len()]);
            for (o, h) in out.iter_mut().zip(occ) {
                *o = f32::from(u8::from(h));
            }
        },
    )
}

/// Traces one chunk; any-hit packets go through `cache`, the worker's
/// (the first packet of a chunk tests the occluders of the last packet the
/// worker traced).
fn trace_chunk(
    tracer: &dyn ClosestHit,
    rays: &[Ray],
    query: Query,
    packets: bool,
    out: &mut [f32],
    cache: &mut super::OccluderCache,
) {
    if !packets {
        for (r, o) in rays.iter().zip(out.iter_mut()) {
            *o = match query {
                Query::Closest => tracer.closest_hit(r).t,
                Query::Occluded => f32::from(u8::from(tracer.occluded(r))),
            };
        }
        return;
    }
    for (rays, out) in rays.chunks(16).zip(out.chunks_mut(16)) {
        match query {
            Query::Closest => {
                let mut hits = [Hit::MISS; 16];
                tracer.closest_hit_n(rays, &mut hits[..rays.len()]);
                for (o, h) in out.iter_mut().zip(hits) {
                    *o = h.t;
                }
            }
            Query::Occluded => {
                let mut occ = [false; 16];
                tracer.occluded_n_cached(rays, &mut occ[..rays.len()], cache);
                for (o, h) in out.iter_mut().zip(occ) {
                    *o = f32::from(u8::from(h));
                }
            }
        }
    }
}

/// Traces the rays of one piece of a chunk into their hits, counting the
/// work; packets of any-hit rays may use the worker's occluder cache, as
/// [`trace_batch`]'s do.
pub type CountFn<'a> =
    dyn Fn(&[Ray], &mut [Hit], &mut TraceStats, &mut super::OccluderCache) + Sync + 'a;

/// How a batch is cut into the pieces a tracer takes at a time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pieces {
    /// One ray at a time ([`trace_batch`] without packets).
    Single,
    /// 16 consecutive rays ([`trace_batch`] with packets).
    Packets,
    /// 16 rays of one octant and longest axis (or one direction cell)
    /// where a chunk mixes octants, as [`trace_batch_sorted`] cuts them.
    Sorted,
}

/// Traces `rays` as [`trace_batch`] or [`trace_batch_sorted`] cut them
/// (`pieces`), with a counting traversal (`trace` gets the rays of one
/// piece and returns their hits), and returns the work done; it is slower,
/// so it is never timed.
pub fn count_batch(
    rays: &[Ray],
    query: Query,
    pieces: Pieces,
    trace: &CountFn<'_>,
) -> (Vec<f32>, TraceStats) {
    let total = Mutex::new(TraceStats::default());
    let mut results = vec![0f32; rays.len()];
    let (chunk, step) = match pieces {
        Pieces::Single => (CHUNK, 1),
        Pieces::Packets => (CHUNK, LANES),
        Pieces::Sorted => (SORT_CHUNK, LANES),
    };
    results
        .par_chunks_mut(chunk)
        .zip(rays.par_chunks(chunk))
        .with_max_len(job_len(chunk))
        .for_each_init(super::OccluderCache::new, |cache, (out, rays)| {
            let mut stats = TraceStats::default();
            let mut order = Vec::new();
            if pieces == Pieces::Sorted && mixed_octants(rays) {
                order_for_packets(rays, &mut order);
            } else {
                order.extend(0..rays.len() as u32);
            }
            for group in order.chunks(step) {
                let batch = gather(rays, group);
                let mut hits = [Hit::MISS; LANES];
                trace(
                    &batch[..group.len()],
                    &mut hits[..group.len()],
                    &mut stats,
                    cache,
                );
                for (&i, h) in group.iter().zip(hits) {
                    out[i as usize] = result(query, h);
                }
            }
            total.lock().expect("no panics while held").add(&stats);
        });
    let stats = total.into_inner().expect("no panics while held");
    (results, stats)
}

/// Shadow and ambient-occlusion rays from the hits of primary rays, the
/// sets of `benches/trace.rs` and `slimkd calibrate`, like the peer
/// program's `--make-rays`.
pub struct SecondaryRays {
    /// One per hit, toward a point light near the first ray's origin (an
    /// any-hit query up to just short of the light).
    pub shadow: Vec<Ray>,
    /// `ao_per_hit` per hit, cosine-distributed about the normal facing
    /// the ray, up to 5 % of the scene's diagonal (any-hit queries).
    pub ao: Vec<Ray>,
}

/// The shadow and ambient-occlusion rays of `primary` (traced with
/// `tracer` for their hits), in the order of the primary rays. The rays
/// leave the hit point offset along the normal by 10⁻⁴ of the scene's
/// diagonal; the directions come from a fixed-seed splitmix64, so every
/// run makes the same rays.
pub fn secondary_rays(
    scene: &crate::scene::TriangleColumns,
    tracer: &dyn ClosestHit,
    primary: &[Ray],
    ao_per_hit: usize,
) -> SecondaryRays {
    let b = scene.bounds();
    let diag = (b.max - b.min).length();
    let eye = primary.first().map_or(Vec3::ZERO, |r| r.origin);
    let light = eye + Vec3::new(0.05, 0.05, 0.0) * diag;
    let mut out = SecondaryRays {
        shadow: Vec::new(),
        ao: Vec::new(),
    };
    let mut seed = 0x5eed_u64;
    let mut uniform = move || {
        seed = seed.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = seed;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    };
    for r in primary {
        let hit = tracer.closest_hit(r);
        if !hit.is_hit() {
            continue;
        }
        let mut n = scene.normal(hit.tri.0).normalize();
        if n.dot(r.dir) > 0.0 {
            n = -n;
        }
        let p = r.origin + r.dir * hit.t + n * (1e-4 * diag);
        let to_light = light - p;
        out.shadow.push(Ray {
            origin: p,
            dir: to_light.normalize(),
            tmin: 0.0,
            tmax: to_light.length() * (1.0 - 1e-5),
        });
        let (t1, t2) = n.any_orthonormal_pair();
        for _ in 0..ao_per_hit {
            let (u1, u2) = (uniform(), uniform());
            let (rad, phi) = (u1.sqrt(), std::f32::consts::TAU * u2);
            let d =
                t1 * (rad * phi.cos()) + t2 * (rad * phi.sin()) + n * (1.0 - u1).max(0.0).sqrt();
            out.ao.push(Ray {
                origin: p,
                dir: d.normalize(),
                tmin: 0.0,
                tmax: 0.05 * diag,
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The keys and the spread in groups of eight (AVX2) equal those a
    /// ray at a time, bit for bit, over random rays and directions with
    /// zero, negative zero, subnormal, infinite and NaN components, NaN
    /// origins and lengths; and each ray's key is its octant and cell.
    #[test]
    fn keys_in_groups_equal_keys_one_at_a_time() {
        let mut seed = 7u64;
        let mut next = move || {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            seed >> 33
        };
        let special = [
            0.0,
            -0.0,
            1e-40,
            -1e-40,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::MAX,
        ];
        let value = |next: &mut dyn FnMut() -> u64| {
            let r = next();
            if r.is_multiple_of(8) {
                special[(r / 8 % 8) as usize]
            } else {
                (r % 20_001) as f32 / 1000.0 - 10.0
            }
        };
        for n in [0usize, 1, 7, 8, 9, 64, 1000, 1003] {
            let rays: Vec<Ray> = (0..n)
                .map(|_| Ray {
                    origin: Vec3::new(value(&mut next), value(&mut next), value(&mut next)),
                    dir: Vec3::new(value(&mut next), value(&mut next), value(&mut next)),
                    tmin: 0.0,
                    tmax: value(&mut next).abs(),
                })
                .collect();
            let (mut a, mut b) = (Vec::new(), Vec::new());
            let close = direction_keys_on(&rays, &mut a, false);
            assert_eq!(direction_keys_on(&rays, &mut b, true), close, "{n} rays");
            assert_eq!(a, b, "{n} rays");
            for (r, &k) in rays.iter().zip(&a) {
                assert_eq!(k, direction_key(r.dir), "{r:?}");
            }
        }
        // The spread alone: origins close together, then one far off.
        let ray = |x: f32| {
            let mut r = Ray::new(Vec3::new(x, 0.0, 0.0), Vec3::new(0.0, 0.6, 0.8));
            r.tmax = 10.0;
            r
        };
        let mut rays: Vec<Ray> = (0..20).map(|i| ray(i as f32 * 0.1)).collect();
        for simd in [false, true] {
            assert!(direction_keys_on(&rays, &mut Vec::new(), simd));
        }
        rays[11] = ray(2.5);
        for simd in [false, true] {
            assert!(!direction_keys_on(&rays, &mut Vec::new(), simd));
        }
    }
}
