//! Structure-aware fuzzing of `.kd` files: valid files (small built scenes,
//! std, hoisted type II and slim trees, plain and reordered, 2-byte and
//! 4-byte leaves) are mutated field by field, as the layout names the
//! fields (right-child slot fields, empty leaf words, one-triangle leaves,
//! leaf counts and first indices, type and mode bits, T-reference indices,
//! split positions, words after the tree, header counts, offsets and
//! bounds, geometry, index arrays, the triangle map, reserved bytes), and
//! then their checksums are repaired, so that each mutation reaches the
//! structural checks (`KdFile::from_bytes`, the O(1) open, and
//! `KdFile::validate`, the full check) rather than stopping at a CRC.
//!
//! Asserted for every case: `from_bytes` never panics; on a file it
//! accepts, every traverser (scalar, and packets at every SIMD level), the
//! depth histogram, the byte split and `to_columns` run without panic, each
//! walk within its step limit (`2 · words + 1` nodes), whatever the full
//! check says of the file; a file the full check accepts passes `verify`,
//! and its traversers' work is bounded by the file's size.
//! On a valid file whose tree covers its geometry (every triangle
//! reaches every leaf the builders' classification sends it to, or a type
//! II node above: [`covers_geometry`]), single, packet and brute force
//! return the same hit, bit for bit. On an accepted file that does not
//! (a split moved within its cell, a vertex moved, a leaf listing another
//! triangle), no traversal can match brute force; there each traverser
//! must still return a real hit of the ray, never closer than brute
//! force's.
//!
//! The normal run makes 8000 cases; for a long run set `PROPTEST_CASES`:
//!
//! ```text
//! PROPTEST_CASES=200000 nice -n 19 cargo test --release --test format_fuzz
//! ```
//!
//! The named regression tests of the hostile inputs found this way follow
//! the fuzz test.

mod common;

use common::kd::Rng;
use common::kd::*;
use glam::Vec3;
use proptest::prelude::*;
use proptest::test_runner::{Config, FileFailurePersistence, TestRunner};
use slimkd::build::sah::{Side, Split};
use slimkd::build::{BuildConfig, Placement, TriRef, classify, clip_straddler};
use slimkd::format::node::{self, LEAF16_LIMIT, MAX_NODES, NodeWord};
use slimkd::format::{self, FormatError, KdFile, NodeFault, Section, WriteOptions, aligned_copy};
use slimkd::geom::{Aabb, Ray, RayPrecomp, intersect_triangle};
use slimkd::scene::TriangleColumns;
use slimkd::slim::{self, SlimParams};
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{self, ClosestHit, Hit, TraceStats};
use slimkd::tree::{Node, NodeId, TreeIr, TriId};
use std::cell::Cell;
use std::panic::{AssertUnwindSafe, catch_unwind};

// ---------------------------------------------------------------------
// Valid files to mutate.
// ---------------------------------------------------------------------

/// A valid file and what the mutator needs to know of its layout.
struct Base {
    name: &'static str,
    bytes: Vec<u8>,
    /// Inner nodes: slot, axis, cell.
    inner: Vec<(usize, usize, Aabb)>,
    /// Leaf slots and T-reference slots.
    leaves: Vec<usize>,
    trefs: Vec<usize>,
    rays: Vec<Ray>,
    packets: Vec<[Ray; 16]>,
}

impl Base {
    fn new(name: &'static str, bytes: Vec<u8>, seed: u64) -> Base {
        let file = read(&bytes);
        let words = file.nodes();
        let mut inner = Vec::new();
        let mut leaves = Vec::new();
        let mut trefs = Vec::new();
        let mut stack = vec![(Some(0u32), file.bounds())];
        while let Some((i, cell)) = stack.pop() {
            // An empty child has no word to mutate.
            let Some(i) = i else { continue };
            match node::decode(words[i as usize]).unwrap() {
                NodeWord::Inner {
                    axis,
                    t_ref,
                    right,
                    pos,
                } => {
                    let k = usize::from(axis);
                    inner.push((i as usize, k, cell));
                    if t_ref {
                        trefs.push(i as usize + 1);
                    }
                    let (lc, rc) = cell.split(k, pos);
                    let (l, r) = node::children(i, t_ref, right);
                    stack.push((r, rc));
                    stack.push((l, lc));
                }
                _ => leaves.push(i as usize),
            }
        }
        let (rays, packets) = probes(&file.bounds(), seed);
        assert!(
            covers_geometry(&file),
            "{name}: the coverage oracle refuses a written tree"
        );
        assert_agree(&file, &rays, &packets).unwrap_or_else(|e| panic!("{name}: {e}"));
        Base {
            name,
            bytes,
            inner,
            leaves,
            trefs,
            rays,
            packets,
        }
    }
}

/// Rays over `bounds`: random ones, axis-aligned ones from half-integer
/// and integer points (so some start in split planes), rays with one or
/// two zero direction components (of either sign), and packets: coherent
/// fans and axis-aligned 4×4 grids.
fn probes(bounds: &Aabb, seed: u64) -> (Vec<Ray>, Vec<[Ray; 16]>) {
    let mut rng = Rng(seed);
    let mut rays = rays_at(bounds, &mut rng, 12);
    let ext = bounds.extent();
    let point = |rng: &mut Rng, snap: f32| {
        let p = lerp(bounds.min - 1.0, bounds.max + 1.0, rng);
        (p / snap).round() * snap
    };
    let axes = [Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X, -Vec3::Y, -Vec3::Z];
    for i in 0..12 {
        let o = point(&mut rng, if i % 2 == 0 { 0.5 } else { 1.0 });
        rays.push(Ray::new(o, axes[i % 6]));
    }
    for i in 0..8 {
        let o = point(&mut rng, 0.5);
        let mut d = Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5);
        d[i % 3] = if i % 2 == 0 { 0.0 } else { -0.0 };
        if i >= 4 {
            d[(i + 1) % 3] = 0.0;
        }
        if d.abs().max_element() > 0.0 {
            rays.push(Ray::new(o, d));
        }
    }
    let mut packets = packets_at(bounds, &mut rng, 2);
    for (k, d) in [(2, -Vec3::Z), (0, Vec3::X), (1, -Vec3::Y)] {
        let (a, b) = ((k + 1) % 3, (k + 2) % 3);
        let mut o0 = bounds.min + ext * 0.1;
        o0[k] = if d[k] < 0.0 {
            bounds.max[k] + 1.0
        } else {
            bounds.min[k] - 1.0
        };
        let step = ext.max_element().max(1.0) / 8.0;
        packets.push(std::array::from_fn(|i| {
            let mut o = o0;
            o[a] += (i % 4) as f32 * step;
            o[b] += (i / 4) as f32 * step;
            Ray::new(o, d)
        }));
    }
    (rays, packets)
}

fn bases() -> Vec<Base> {
    let mut rng = Rng(0x5eed);
    let scene = random_small_scene(&mut rng, 24, 6);
    let tree = std_tree(&scene);
    let scene2 = random_small_scene(&mut rng, 40, 8);
    let (tree2, hoisted) = hoist(&std_tree(&scene2), &scene2, 12, true);
    assert!(hoisted >= 3, "{hoisted} type II nodes");
    let scene3 = random_small_scene(&mut rng, 48, 6);
    let (slim3, _) = slim::slim(
        &std_tree(&scene3),
        &scene3,
        &BuildConfig::default(),
        &SlimParams::SMALL,
    );
    let scene4 = strip_scene(6);
    let mut big_leaf: Vec<u32> = (0..LEAF16_LIMIT).map(|i| i % 3).collect();
    big_leaf.sort_unstable();
    let tree4 = strip_tree(&scene4, &[big_leaf, vec![3, 4], vec![5]], false);
    let out = vec![
        Base::new("grid", write(&tree, &scene, false), 1),
        Base::new("grid-reordered", write(&tree, &scene, true), 2),
        Base::new("type2", write(&tree2, &scene2, false), 3),
        Base::new("type2-reordered", write(&tree2, &scene2, true), 4),
        Base::new("slim-reordered", write(&slim3, &scene3, true), 5),
        Base::new("idx32", write(&tree4, &scene4, false), 6),
    ];
    assert!(read(&out[5].bytes).figures().idx32 >= u64::from(LEAF16_LIMIT));
    assert!(out.iter().all(|b| !b.leaves.is_empty()));
    // The v2 encodings the mutator works on: empty children without a
    // word and one-triangle leaves.
    assert!(
        out.iter()
            .any(|b| read(&b.bytes).figures().implicit_empty > 0)
    );
    assert!(out.iter().all(|b| read(&b.bytes).figures().one_leaves > 0));
    out
}

// ---------------------------------------------------------------------
// The oracle: does a file's tree cover its geometry?
// ---------------------------------------------------------------------

/// Whether every triangle of `file` reaches, through the file's own splits
/// and the builders' classification and clipping (`build::classify`,
/// `build::clip_straddler`), only leaves that list it, or a type II node
/// above them that hoists it. A triangle lying in a split plane may go to
/// either side (the file does not record the builder's planar side). The
/// trees the builders write cover their geometry; traversal of such a tree
/// finds brute force's hit.
fn covers_geometry<D: AsRef<[u8]>>(file: &KdFile<D>) -> bool {
    let positions = file
        .vertices()
        .iter()
        .map(|&v| Vec3::from_array(v))
        .collect();
    let Ok(scene) = TriangleColumns::new(positions, file.triangles().to_vec()) else {
        return false;
    };
    (0..scene.len() as u32).all(|t| {
        let r = TriRef {
            tri: TriId(t),
            bounds: Aabb::of_triangle(&scene.tri(t)),
        };
        file.bounds().contains(&r.bounds)
            && reaches_only_listing(file, &scene, Some(0), file.bounds(), r)
    })
}

fn reaches_only_listing<D: AsRef<[u8]>>(
    file: &KdFile<D>,
    scene: &TriangleColumns,
    i: Option<u32>,
    cell: Aabb,
    r: TriRef,
) -> bool {
    // An empty child (no word) lists nothing.
    let Some(i) = i else {
        return false;
    };
    let w = node::decode(file.nodes()[i as usize]).unwrap();
    let NodeWord::Inner {
        axis,
        t_ref,
        right,
        pos,
    } = w
    else {
        let mut listed = false;
        file.leaf(w).for_each(|t| listed |= t == r.tri.0);
        return listed;
    };
    if t_ref && node::decode(file.nodes()[i as usize + 1]) == Ok(NodeWord::TRef { tri: r.tri.0 }) {
        return true;
    }
    let k = usize::from(axis);
    let (lc, rc) = cell.split(k, pos);
    let (left, right) = node::children(i, t_ref, right);
    let split = Split {
        cost: 0.0,
        axis,
        pos,
        planar: Side::Left,
    };
    let go = |child: Option<u32>, c: Aabb, b: Aabb| {
        reaches_only_listing(
            file,
            scene,
            child,
            c,
            TriRef {
                tri: r.tri,
                bounds: b,
            },
        )
    };
    if r.bounds.min[k] == pos && r.bounds.max[k] == pos {
        return go(left, lc, r.bounds) || go(right, rc, r.bounds);
    }
    match classify(&r.bounds, &split) {
        Placement::Left => go(left, lc, r.bounds),
        Placement::Right => go(right, rc, r.bounds),
        Placement::Both => {
            let (l, rr) = clip_straddler(scene, &r, &split, &lc, &rc);
            l.is_none_or(|b| go(left, lc, b)) && rr.is_none_or(|b| go(right, rc, b))
        }
    }
}

// ---------------------------------------------------------------------
// Checks of an accepted file.
// ---------------------------------------------------------------------

/// Single, packet (every SIMD level) and brute force agree on every probe.
fn assert_agree<D: AsRef<[u8]> + Sync>(
    file: &KdFile<D>,
    rays: &[Ray],
    packets: &[[Ray; 16]],
) -> Result<(), String> {
    let scene = file
        .to_columns()
        .map_err(|e| format!("to_columns of a valid file: {e}"))?;
    for ray in rays {
        let want = trace::brute_force(&scene, ray);
        let got = trace::traverse(file, ray);
        if got != want {
            return Err(format!("single {got:?}, brute force {want:?}, ray {ray:?}"));
        }
    }
    for rays in packets {
        for level in SimdLevel::available() {
            let mut got = [Hit::MISS; 16];
            PacketTracer::with_level(file, level).closest_hit_4x4(rays, &mut got);
            for (i, ray) in rays.iter().enumerate() {
                let single = trace::traverse(file, ray);
                let want = trace::brute_force(&scene, ray);
                if got[i] != single || got[i] != want {
                    return Err(format!(
                        "packet {level:?} {:?}, single {single:?}, brute force {want:?}, ray {ray:?}",
                        got[i]
                    ));
                }
            }
        }
    }
    Ok(())
}

/// A traverser's hit on a file whose tree need not cover its geometry: a
/// miss, or a real hit of the ray (the triangle's own test gives that
/// `t`), never closer than brute force's.
fn check_plausible(
    what: &str,
    got: Hit,
    want: Hit,
    scene: &TriangleColumns,
    ray: &Ray,
) -> Result<(), String> {
    if !got.is_hit() {
        return Ok(());
    }
    let real = (got.tri.0 as usize) < scene.len()
        && intersect_triangle(
            &RayPrecomp::new(ray),
            &scene.tri(got.tri.0),
            ray.tmin,
            ray.tmax,
        ) == Some(got.t);
    let not_closer = got.t > want.t || (got.t == want.t && got.tri >= want.tri);
    if real && not_closer {
        Ok(())
    } else {
        Err(format!(
            "{what} {got:?} is not a hit at or after brute force's {want:?}, ray {ray:?}"
        ))
    }
}

/// Traces every probe over a file that passed the O(1) open alone: no
/// panic, no read out of bounds, and no walk past its step limit (each
/// probe ray walks twice, closest and any hit; a packet query of 16 rays
/// takes at most 48 limits: two octants of 8 lanes or more, 16 limits
/// each, and 16 lanes alone).
fn check_opened<D: AsRef<[u8]> + Sync>(file: &KdFile<D>, base: &Base) -> Result<(), String> {
    let limit = 2 * file.nodes().len() as u64 + 1;
    for ray in &base.rays {
        let mut s = TraceStats::default();
        trace::traverse_counted(file, ray, false, &mut s);
        trace::traverse_counted(file, ray, true, &mut s);
        if s.nodes > 2 * limit {
            return Err(format!(
                "{} steps over the limit {limit}, ray {ray:?}",
                s.nodes
            ));
        }
    }
    for rays in &base.packets {
        for level in SimdLevel::available() {
            let mut s = TraceStats::default();
            let mut out = [Hit::MISS; 16];
            let tracer = PacketTracer::with_level(file, level);
            tracer.trace_counted(rays, false, &mut out, &mut s);
            tracer.trace_counted(rays, true, &mut out, &mut s);
            if s.nodes > 2 * 48 * limit {
                return Err(format!("{} packet steps over the limit {limit}", s.nodes));
            }
        }
    }
    // Rays in lanes read the words with their own checks: they end, and
    // say what the scalar any-hit walk says.
    let want: Vec<bool> = base.rays.iter().map(|r| trace::occluded(file, r)).collect();
    for level in SimdLevel::available() {
        let mut got = vec![false; base.rays.len()];
        trace::lanes::occluded_lanes(trace::FileWalk::new(file), level, &base.rays, &mut got);
        if got != want {
            return Err(format!("lanes ({level:?}) disagree with the scalar walk"));
        }
    }
    let _ = std::hint::black_box((
        file.leaf_depth_histogram(),
        slimkd::stats::bytes::ByteSplit::of(file),
        file.to_columns(),
    ));
    Ok(())
}

/// Traces every probe over a valid file with bounded work, and checks
/// the hits; `Ok(covering)`.
fn check_accepted<D: AsRef<[u8]> + Sync>(file: &KdFile<D>, base: &Base) -> Result<bool, String> {
    let n_words = file.nodes().len() as u64;
    // Triangle references: index entries and one-triangle leaves.
    let n_idx = file.figures().references();
    let n_hoisted = file.figures().t_inner;
    let mut stats = TraceStats::default();
    for ray in &base.rays {
        let mut s = TraceStats::default();
        trace::traverse_counted(file, ray, false, &mut s);
        trace::traverse_counted(file, ray, true, &mut s);
        if s.nodes > 2 * n_words || s.tris > 2 * n_idx || s.hoisted > 2 * n_hoisted {
            return Err(format!("unbounded work {s:?} for ray {ray:?}"));
        }
        stats.add(&s);
    }
    for rays in &base.packets {
        for level in SimdLevel::available() {
            let mut s = TraceStats::default();
            let mut out = [Hit::MISS; 16];
            let tracer = PacketTracer::with_level(file, level);
            tracer.trace_counted(rays, false, &mut out, &mut s);
            tracer.trace_counted(rays, true, &mut out, &mut s);
            if s.nodes > 2 * 16 * n_words || s.tris > 2 * 16 * n_idx {
                return Err(format!("unbounded packet work {s:?}"));
            }
        }
    }
    let scene = file
        .to_columns()
        .map_err(|e| format!("to_columns of a valid file: {e}"))?;
    std::hint::black_box((file.leaf_depth_histogram(), stats));
    if covers_geometry(file) {
        assert_agree(file, &base.rays, &base.packets)?;
        return Ok(true);
    }
    for ray in &base.rays {
        let want = trace::brute_force(&scene, ray);
        check_plausible("single", trace::traverse(file, ray), want, &scene, ray)?;
    }

    for rays in &base.packets {
        for level in SimdLevel::available() {
            let mut got = [Hit::MISS; 16];
            PacketTracer::with_level(file, level).closest_hit_4x4(rays, &mut got);
            for (ray, &h) in rays.iter().zip(&got) {
                let want = trace::brute_force(&scene, ray);
                check_plausible(&format!("packet {level:?}"), h, want, &scene, ray)?;
            }
        }
    }
    Ok(false)
}

// ---------------------------------------------------------------------
// The mutator.
// ---------------------------------------------------------------------

/// One structural mutation: a field kind and two numbers that pick the
/// field and its new value.
#[derive(Clone, Copy, Debug)]
struct Mutation {
    kind: Kind,
    a: u64,
    b: u64,
}

#[derive(Clone, Copy, Debug)]
enum Kind {
    SlotField,
    EmptyLeaf,
    OneLeaf,
    AppendWords,
    LeafCount,
    LeafStart,
    LeafMode,
    TypeBits,
    TRefIndex,
    Split,
    SwapWords,
    HeaderCount,
    HeaderField,
    SectionTable,
    Bounds,
    Vertex,
    VertexIndex,
    IndexEntry,
    TriMap,
    Reserved,
    RawByte,
    Length,
}

const KINDS: [Kind; 22] = [
    Kind::SlotField,
    Kind::EmptyLeaf,
    Kind::OneLeaf,
    Kind::AppendWords,
    Kind::LeafCount,
    Kind::LeafStart,
    Kind::LeafMode,
    Kind::TypeBits,
    Kind::TRefIndex,
    Kind::Split,
    Kind::SwapWords,
    Kind::HeaderCount,
    Kind::HeaderField,
    Kind::SectionTable,
    Kind::Bounds,
    Kind::Vertex,
    Kind::VertexIndex,
    Kind::IndexEntry,
    Kind::TriMap,
    Kind::Reserved,
    Kind::RawByte,
    Kind::Length,
];

fn mutation() -> impl Strategy<Value = Mutation> {
    (0..KINDS.len(), any::<u64>(), any::<u64>()).prop_map(|(k, a, b)| Mutation {
        kind: KINDS[k],
        a,
        b,
    })
}

fn pick<T: Copy>(items: &[T], a: u64) -> Option<T> {
    (!items.is_empty()).then(|| items[(a % items.len() as u64) as usize])
}

fn next_up(x: f32) -> f32 {
    if x.is_nan() || x == f32::INFINITY {
        x
    } else if x == 0.0 {
        f32::from_bits(1)
    } else if x > 0.0 {
        f32::from_bits(x.to_bits() + 1)
    } else {
        f32::from_bits(x.to_bits() - 1)
    }
}

fn next_down(x: f32) -> f32 {
    -next_up(-x)
}

/// An interesting `f32`: the extremes, denormals, zeros, a value near or
/// beyond the cell `lo..hi`, or arbitrary bits.
fn special_f32(b: u64, lo: f32, hi: f32, current: f32) -> f32 {
    let r = (b >> 8) as u32;
    match b % 16 {
        0 => f32::NAN,
        1 => f32::INFINITY,
        2 => f32::NEG_INFINITY,
        3 => f32::MAX,
        4 => -f32::MAX,
        5 => f32::from_bits(1 + r % 0x7f_ffff),
        6 => -f32::from_bits(1 + r % 0x7f_ffff),
        7 => 0.0,
        8 => -0.0,
        9 => lo,
        10 => hi,
        11 => next_down(lo),
        12 => next_up(hi),
        13 => lo + (hi - lo) * ((r % 1024) as f32 / 1024.0),
        14 => {
            if r.is_multiple_of(2) {
                next_up(current)
            } else {
                next_down(current)
            }
        }
        _ => f32::from_bits(r),
    }
}

/// The byte range of section `s` as the (possibly mutated) table states
/// it, if it lies inside `b`.
fn section_in(b: &[u8], s: Section) -> Option<std::ops::Range<usize>> {
    let e = H_TABLE + s as usize * H_ENTRY;
    let (ofs, len) = (get_u64(b, e), get_u64(b, e + 8));
    let end = ofs.checked_add(len)?;
    (end <= b.len() as u64).then_some(ofs as usize..end as usize)
}

fn word_at(b: &[u8], slot: usize) -> Option<(usize, u64)> {
    let r = section_in(b, Section::Nodes)?;
    let at = r.start + 8 * slot;
    (at + 8 <= r.end).then(|| (at, get_u64(b, at)))
}

fn n_words(b: &[u8]) -> u64 {
    section_in(b, Section::Nodes).map_or(0, |r| (r.len() / 8) as u64)
}

/// Applies `m` to `b`; a mutation whose field the (already mutated) file
/// no longer has does nothing.
fn mutate(b: &mut Vec<u8>, base: &Base, m: Mutation) {
    let Mutation { kind, a, b: v } = m;
    let n = n_words(b);
    let set_word = |b: &mut Vec<u8>, slot: usize, w: u64| {
        if let Some((at, _)) = word_at(b, slot) {
            set_u64(b, at, w);
        }
    };
    match kind {
        Kind::SlotField => {
            let Some((slot, _, _)) = pick(&base.inner, a) else {
                return;
            };
            let Some((_, w)) = word_at(b, slot) else {
                return;
            };
            let right = (w as u32 >> 3) as u64;
            let first = slot as u64 + 1 + u64::from(w & node::A_TYPE2 != 0);
            let other = pick(&base.inner, v >> 8)
                .and_then(|(s, _, _)| word_at(b, s))
                .map_or(right, |(_, w)| (w as u32 >> 3) as u64);
            // A slot inside the left subtree (a second parent for it).
            let inside_left = if right > first {
                first + (v >> 8) % (right - first)
            } else {
                first + 1
            };
            let new = match v % 13 {
                0 => (slot as u64).saturating_sub(1),
                1 => slot as u64,
                // The right child empty: its subtree's words are left over.
                2 => 0,
                3 => n.saturating_sub(1),
                4 => n,
                5 => n + 1,
                6 => MAX_NODES - 1,
                7 => other,
                8 => right + 1,
                9 => right.saturating_sub(1),
                // The left child empty: the right one said to be at `first`.
                10 => first,
                11 => inside_left,
                _ => first + 1,
            } & (MAX_NODES - 1);
            set_word(b, slot, (w & !(u64::from(u32::MAX) & !0b111)) | (new << 3));
        }
        Kind::EmptyLeaf => {
            let Some(slot) = pick(&base.leaves, a) else {
                return;
            };
            // An empty leaf with a word: only the left child of a node
            // whose slot field says its right child is empty may be one,
            // and only at start 0.
            let start = [0, 1, (v >> 8) as u32][(v % 3) as usize];
            let w = match (v >> 2) % 4 {
                0 | 1 => node::encode_leaf32(0, start),
                2 => node::encode_leaf16(0, 0, start),
                _ => node::encode_leaf16(1, 0, start),
            };
            set_word(b, slot, w);
            // Sometimes its parent is also told that its right child is
            // empty (which it is only if there was none).
            if v % 5 == 0
                && let Some((p, _, _)) = base.inner.iter().find(|(p, _, _)| {
                    word_at(b, *p).is_some_and(|(_, w)| {
                        *p as u64 + 1 + u64::from(w & node::A_TYPE2 != 0) == slot as u64
                    })
                })
                && let Some((_, pw)) = word_at(b, *p)
            {
                set_word(b, *p, pw & !(u64::from(u32::MAX) & !0b111));
            }
        }
        Kind::OneLeaf => {
            let Some(slot) = pick(&base.leaves, a) else {
                return;
            };
            let Some((_, w)) = word_at(b, slot) else {
                return;
            };
            let n_tris = get_u64(b, H_TRIANGLES);
            let tri = (w >> 32) as u32;
            let new = match v % 7 {
                0 => node::encode_leaf1(((v >> 8) % n_tris.max(1)) as u32),
                1 => node::encode_leaf1(n_tris as u32),
                2 => node::encode_leaf1(u32::MAX),
                // Unused bits of a one-triangle leaf.
                3 => node::encode_leaf1(tri) | (1 << (5 + (v >> 8) % 27)),
                // One triangle with an index entry.
                4 => node::encode_leaf32(1, tri),
                5 => node::encode_leaf16(1, (v >> 8) as u16, tri),
                _ => node::encode_leaf16(2, 0, tri),
            };
            set_word(b, slot, new);
        }
        Kind::AppendWords => {
            // Words after the tree; with the counts kept adding up when
            // `v` is odd (one more inner node and leaf: two words).
            let words: Vec<u64> = (0..1 + v % 2)
                .map(|k| match (v >> (8 + k)) % 3 {
                    0 => word_at(b, ((a >> 8) % n.max(1)) as usize).map_or(0, |(_, w)| w),
                    1 => node::encode_leaf1(0),
                    _ => node::encode_leaf32(0, 0),
                })
                .collect();
            if Section::ALL.iter().any(|&s| section_in(b, s).is_none()) {
                return;
            }
            let mut out = with_words_appended(b, &words);
            if v % 2 == 1 {
                let (inner, leaves) = (get_u64(&out, H_INNER), get_u64(&out, H_LEAVES));
                set_u64(&mut out, H_INNER, inner.wrapping_add(1));
                set_u64(&mut out, H_LEAVES, leaves.wrapping_add(1));
            }
            *b = out;
        }
        Kind::LeafCount | Kind::LeafStart | Kind::LeafMode => {
            let Some(slot) = pick(&base.leaves, a) else {
                return;
            };
            let Some((_, w)) = word_at(b, slot) else {
                return;
            };
            let other_start = pick(&base.leaves, v >> 8)
                .and_then(|s| word_at(b, s))
                .map_or(0, |(_, w)| w >> 32);
            let new = match (kind, node::decode(w)) {
                (Kind::LeafMode, _) => w ^ (1 << 3),
                (Kind::LeafCount, Ok(NodeWord::Leaf32 { count, start })) => {
                    let c = [
                        count + 1,
                        count.saturating_sub(1),
                        0,
                        node::MAX_LEAF32,
                        (v >> 8) as u32,
                    ][(v % 5) as usize];
                    node::encode_leaf32(c & node::MAX_LEAF32, start)
                }
                (
                    Kind::LeafCount,
                    Ok(NodeWord::Leaf16 {
                        count,
                        upper,
                        start,
                    }),
                ) => {
                    let c = [
                        count + 1,
                        count.saturating_sub(1),
                        0,
                        LEAF16_LIMIT - 1,
                        (v >> 8) as u32,
                    ][(v % 5) as usize];
                    node::encode_leaf16(c % LEAF16_LIMIT, upper, start)
                }
                (Kind::LeafStart, Ok(_)) => {
                    let s = w >> 32;
                    let new = [
                        s + 1,
                        s.saturating_sub(1),
                        other_start,
                        u64::from(u32::MAX),
                        v >> 32,
                    ][(v % 5) as usize];
                    (w & u64::from(u32::MAX)) | ((new & u64::from(u32::MAX)) << 32)
                }
                _ => w ^ (v << 32),
            };
            set_word(b, slot, new);
        }
        Kind::TypeBits => {
            let slot = (a % n.max(1)) as usize;
            if let Some((_, w)) = word_at(b, slot) {
                let bits = if v % 2 == 0 { 0b111 } else { 0b1_1111 };
                set_word(b, slot, (w & !bits) | ((v >> 8) & bits));
            }
        }
        Kind::TRefIndex => {
            let Some(slot) = pick(&base.trefs, a) else {
                return;
            };
            let Some((_, w)) = word_at(b, slot) else {
                return;
            };
            let n_tris = get_u64(b, H_TRIANGLES);
            let tri = [
                (v >> 8) % n_tris.max(1),
                n_tris,
                u64::from(u32::MAX),
                (w >> 32) + 1,
            ][(v % 4) as usize];
            let low = if v % 7 == 0 {
                (v >> 40) as u32 | 0b111
            } else {
                0b111
            };
            set_word(
                b,
                slot,
                ((tri & u64::from(u32::MAX)) << 32) | u64::from(low),
            );
        }
        Kind::Split => {
            let Some((slot, k, cell)) = pick(&base.inner, a) else {
                return;
            };
            let Some((_, w)) = word_at(b, slot) else {
                return;
            };
            let pos = f32::from_bits((w >> 32) as u32);
            let p = if v % 17 == 16 {
                pick(&base.inner, v >> 8)
                    .and_then(|(s, _, _)| word_at(b, s))
                    .map_or(pos, |(_, w)| f32::from_bits((w >> 32) as u32))
            } else {
                special_f32(v, cell.min[k], cell.max[k], pos)
            };
            set_word(
                b,
                slot,
                (w & u64::from(u32::MAX)) | (u64::from(p.to_bits()) << 32),
            );
        }
        Kind::SwapWords => {
            let (i, j) = ((a % n.max(1)) as usize, (v % n.max(1)) as usize);
            if let (Some((ai, wi)), Some((aj, wj))) = (word_at(b, i), word_at(b, j)) {
                set_u64(b, ai, wj);
                if v % 3 != 0 {
                    set_u64(b, aj, wi);
                }
            }
        }
        Kind::HeaderCount => {
            // The eight checksummed counts, and the two after the checksum
            // (empty leaves without a word, one-triangle leaves).
            let at = match a % 10 {
                8 => H_IMPLICIT_EMPTY,
                9 => H_ONE_LEAVES,
                k => H_WORDS + 8 * k as usize,
            };
            let c = get_u64(b, at);
            let new = [
                c + 1,
                c.wrapping_sub(1),
                0,
                u64::MAX,
                1 << 29,
                1 << 32,
                v >> 8,
            ][(v % 7) as usize];
            set_u64(b, at, new);
        }
        Kind::HeaderField => {
            let fields = [
                H_VERSION,
                H_ENDIAN,
                H_HEADER_SIZE,
                H_FLAGS,
                48,
                H_PRESET,
                56,
                60,
                64,
                H_MAX_DEPTH,
                24,
                28,
                32,
                40,
            ];
            let at = fields[(a % fields.len() as u64) as usize];
            let c = get_u32(b, at);
            let new = [
                c + 1,
                c.wrapping_sub(1),
                0,
                u32::MAX,
                (v >> 8) as u32,
                c ^ 1,
            ][(v % 6) as usize];
            set_u32(b, at, new);
        }
        Kind::SectionTable => {
            let at = H_TABLE + H_ENTRY * (a % 6) as usize + 8 * ((a >> 8) % 2) as usize;
            let c = get_u64(b, at);
            let new = [
                c + 8,
                c.wrapping_sub(8),
                c + 64,
                c.wrapping_sub(64),
                0,
                v >> 8,
            ][(v % 6) as usize];
            set_u64(b, at, new);
        }
        Kind::Bounds => {
            let k = (a % 6) as usize;
            let at = H_BOUNDS + 4 * k;
            let c = f32::from_bits(get_u32(b, at));
            let (lo, hi) = (
                f32::from_bits(get_u32(b, H_BOUNDS + 4 * (k % 3))),
                f32::from_bits(get_u32(b, H_BOUNDS + 4 * (k % 3 + 3))),
            );
            set_u32(b, at, special_f32(v, lo, hi, c).to_bits());
        }
        Kind::Vertex => {
            let Some(r) = section_in(b, Section::Vertices) else {
                return;
            };
            if r.len() < 12 {
                return;
            }
            let at = r.start + 4 * (a % (r.len() / 4) as u64) as usize;
            let k = (at - r.start) / 4 % 3;
            let c = f32::from_bits(get_u32(b, at));
            let lo = f32::from_bits(get_u32(b, H_BOUNDS + 4 * k));
            let hi = f32::from_bits(get_u32(b, H_BOUNDS + 4 * (k + 3)));
            set_u32(b, at, special_f32(v, lo, hi, c).to_bits());
        }
        Kind::VertexIndex | Kind::IndexEntry | Kind::TriMap => {
            let (s, size, n_valid) = match kind {
                Kind::VertexIndex => (Section::Triangles, 4, get_u64(b, H_VERTICES)),
                Kind::TriMap => (Section::TriMap, 4, get_u64(b, H_TRIANGLES)),
                _ if v % 2 == 0 => (Section::Idx32, 4, get_u64(b, H_TRIANGLES)),
                _ => (Section::Idx16, 2, 1 << 16),
            };
            let Some(r) = section_in(b, s) else {
                return;
            };
            let len = (r.len() / size) as u64;
            if len == 0 {
                return;
            }
            let at = r.start + size * (a % len) as usize;
            let other = r.start + size * ((v >> 16) % len) as usize;
            let c = if size == 4 {
                u64::from(get_u32(b, at))
            } else {
                u64::from(u16::from_le_bytes([b[at], b[at + 1]]))
            };
            let o = if size == 4 {
                u64::from(get_u32(b, other))
            } else {
                u64::from(u16::from_le_bytes([b[other], b[other + 1]]))
            };
            let new = [
                c + 1,
                c.wrapping_sub(1),
                n_valid,
                o,
                (v >> 24) % n_valid.max(1),
                v >> 32,
            ][((v >> 1) % 6) as usize];
            let put = |b: &mut Vec<u8>, at: usize, x: u64| {
                if size == 4 {
                    set_u32(b, at, x as u32);
                } else {
                    b[at..at + 2].copy_from_slice(&(x as u16).to_le_bytes());
                }
            };
            put(b, at, new);
            // A swap keeps the triangle map a permutation.
            if (v >> 1) % 6 == 3 && v % 3 == 0 {
                put(b, other, c);
            }
        }
        Kind::Reserved => {
            let at = match a % 4 {
                0 => 160 + (v % 32) as usize,
                1 => H_TABLE + H_ENTRY * (v % 6) as usize + 20 + ((v >> 8) % 4) as usize,
                2 => 356 + (v % 28) as usize,
                _ => {
                    // A padding byte after a section, if it has any.
                    let Some(r) = section_in(b, Section::ALL[(v % 6) as usize]) else {
                        return;
                    };
                    let pad = r.end.next_multiple_of(64) - r.end;
                    if pad == 0 || r.end + pad > b.len() {
                        return;
                    }
                    r.end + ((v >> 8) as usize % pad)
                }
            };
            b[at] |= 1 << ((v >> 16) % 8);
        }
        Kind::RawByte => {
            let at = (a % b.len() as u64) as usize;
            b[at] ^= ((v % 255) + 1) as u8;
        }
        Kind::Length => {
            if v % 2 == 0 {
                b.truncate(384.max((a % b.len() as u64) as usize));
            } else {
                b.resize(b.len() + 8 * (1 + (a % 16) as usize), 0);
            }
        }
    }
}

/// Recomputes every checksum the (possibly mutated) section table lets
/// one compute, then the header's.
fn repair_crcs(b: &mut [u8]) {
    for s in Section::ALL {
        if let Some(r) = section_in(b, s) {
            let crc = crc32fast::hash(&b[r]);
            set_u32(b, H_TABLE + s as usize * H_ENTRY + 16, crc);
        }
    }
    fix_header_crc(b);
}

// ---------------------------------------------------------------------
// The fuzz test.
// ---------------------------------------------------------------------

#[derive(Default)]
struct Tally {
    /// Refused by the O(1) open.
    rejected: Cell<usize>,
    /// Opened, and refused by the full check.
    invalid: Cell<usize>,
    covering: Cell<usize>,
    not_covering: Cell<usize>,
}

fn bump(c: &Cell<usize>) {
    c.set(c.get() + 1);
}

#[test]
fn mutated_files_are_rejected_or_traced_consistently() {
    let bases = bases();
    let cases = common::cases(8000).cases;
    let mut runner = TestRunner::new(Config {
        cases,
        // A failing case is shrunk and saved next to this file
        // (`format_fuzz.proptest-regressions`), and replayed first on
        // every later run.
        failure_persistence: Some(Box::new(FileFailurePersistence::WithSource(
            "proptest-regressions",
        ))),
        source_file: Some(file!()),
        ..Config::default()
    });
    let tally = Tally::default();
    let strategy = (0..bases.len(), prop::collection::vec(mutation(), 1..=3));
    runner
        .run(&strategy, |(which, mutations)| {
            let base = &bases[which];
            let mut b = base.bytes.clone();
            for &m in &mutations {
                mutate(&mut b, base, m);
            }
            repair_crcs(&mut b);
            let file = catch_unwind(AssertUnwindSafe(|| KdFile::from_bytes(aligned_copy(&b))))
                .map_err(|_| TestCaseError::fail(format!("{}: from_bytes panicked", base.name)))?;
            let file = match file {
                Err(e) => {
                    prop_assert!(!e.to_string().is_empty());
                    bump(&tally.rejected);
                    return Ok(());
                }
                Ok(file) => file,
            };
            catch_unwind(AssertUnwindSafe(|| check_opened(&file, base)))
                .map_err(|_| {
                    TestCaseError::fail(format!(
                        "{}: a reader of the opened file panicked",
                        base.name
                    ))
                })?
                .map_err(|e| TestCaseError::fail(format!("{}: {e}", base.name)))?;
            let valid = catch_unwind(AssertUnwindSafe(|| file.validate()))
                .map_err(|_| TestCaseError::fail(format!("{}: validate panicked", base.name)))?;
            if let Err(e) = valid {
                prop_assert!(!e.to_string().is_empty());
                bump(&tally.invalid);
                return Ok(());
            }
            prop_assert!(
                file.verify().is_ok(),
                "{}: checksums were repaired",
                base.name
            );
            let covering = catch_unwind(AssertUnwindSafe(|| check_accepted(&file, base)))
                .map_err(|_| TestCaseError::fail(format!("{}: traversal panicked", base.name)))?
                .map_err(|e| TestCaseError::fail(format!("{}: {e}", base.name)))?;
            bump(if covering {
                &tally.covering
            } else {
                &tally.not_covering
            });
            Ok(())
        })
        .unwrap();
    let (rejected, invalid, covering, not_covering) = (
        tally.rejected.get(),
        tally.invalid.get(),
        tally.covering.get(),
        tally.not_covering.get(),
    );
    eprintln!(
        "{cases} cases: {rejected} rejected on open, {invalid} opened and refused by the full \
         check, {covering} valid and covering their geometry, {not_covering} valid and not \
         covering it"
    );
    // Each outcome must be reached, or the test checks less than it says.
    let least = cases as usize / 50;
    assert!(rejected >= least, "{rejected} rejected");
    assert!(invalid >= least, "{invalid} invalid");
    assert!(covering >= least, "{covering} covering");
    assert!(not_covering >= least / 4, "{not_covering} not covering");
}

// ---------------------------------------------------------------------
// Named regression tests.
// ---------------------------------------------------------------------

/// Opens `b` as the readers do (the header alone), traces rays over it
/// (which must not panic, whatever it holds), and returns what the full
/// check says.
fn open(b: &[u8]) -> Result<KdFile<format::AlignedBytes>, FormatError> {
    let file = KdFile::from_bytes(aligned_copy(b))?;
    let mut rng = Rng(3);
    for ray in rays_at(&file.bounds(), &mut rng, 32) {
        std::hint::black_box(trace::traverse(&file, &ray));
    }
    file.validate()?;
    Ok(file)
}

fn grid_file() -> (TriangleColumns, TreeIr, Vec<u8>) {
    let mut rng = Rng(0x5eed);
    let scene = random_small_scene(&mut rng, 24, 6);
    let tree = std_tree(&scene);
    let bytes = write(&tree, &scene, false);
    (scene, tree, bytes)
}

fn set_split(b: &mut [u8], slot: usize, pos: f32) {
    let at = section(b, Section::Nodes).start + 8 * slot;
    let w = get_u64(b, at);
    set_u64(
        b,
        at,
        (w & u64::from(u32::MAX)) | (u64::from(pos.to_bits()) << 32),
    );
}

fn expect_split_error(r: Result<KdFile<format::AlignedBytes>, FormatError>, slot: usize) {
    match r {
        Err(FormatError::Node { index, fault }) if index == slot as u64 => {
            assert!(
                matches!(fault, NodeFault::SplitOutsideCell { .. }),
                "{fault}"
            )
        }
        Err(e) => panic!("node {slot}: wrong error {e}"),
        Ok(_) => panic!("node {slot}: a split outside its cell was accepted"),
    }
}

/// The issue's file: one split moved to -FLT_MAX passed `verify`, and the
/// scalar traverser (20 hits, checksum 360.517) disagreed with packets and
/// brute force (355.406). A split outside its node's cell (the header
/// bounds narrowed by the ancestors' splits) is now refused on open, and
/// by the writer.
#[test]
fn split_at_minus_flt_max_is_rejected() {
    let (scene, tree, bytes) = grid_file();
    let base = Base::new("grid", bytes.clone(), 1);
    for &(slot, _, _) in &base.inner {
        let mut b = bytes.clone();
        set_split(&mut b, slot, -f32::MAX);
        fix_all_crcs(&mut b);
        expect_split_error(open(&b), slot);
    }
    // Outside the cell but inside the scene bounds: the cell is narrowed
    // by the ancestors' splits.
    let bounds = read(&bytes).bounds();
    let mut narrowed = 0;
    for &(slot, k, cell) in &base.inner {
        for pos in [next_down(cell.min[k]), next_up(cell.max[k])] {
            if pos >= bounds.min[k] && pos <= bounds.max[k] {
                let mut b = bytes.clone();
                set_split(&mut b, slot, pos);
                fix_all_crcs(&mut b);
                expect_split_error(open(&b), slot);
                narrowed += 1;
            }
        }
    }
    assert!(
        narrowed >= 4,
        "{narrowed} splits checked against narrowed cells"
    );
    // The writer refuses the same tree rather than write it.
    let mut bad = tree.clone();
    if let Node::Inner { pos, .. } = &mut bad.nodes[0] {
        *pos = -f32::MAX;
    }
    match format::write_to_vec(&bad, &scene, &WriteOptions::default()) {
        Err(FormatError::Node { index: 0, fault }) => {
            assert!(
                matches!(fault, NodeFault::SplitOutsideCell { .. }),
                "{fault}"
            )
        }
        other => panic!(
            "the writer wrote a split outside its cell: {:?}",
            other.err()
        ),
    }
}

/// Scalar and packet traversal culled a pending cell entered at +∞ (pushed
/// by a ray parallel to the split plane: its distance to the plane is
/// (pos - o)·∞) differently: the scalar pop skipped it (the NaN of
/// `tmin - tmin·MARGIN` fails `<=`), the packet pop kept it. On a valid
/// file whose right leaf lists a triangle that lies left of the split
/// (which no check of the file's structure can see), rays along -z with
/// x = +0 direction components found that triangle only in packets. Both
/// pops are now one expression and agree.
#[test]
fn single_and_packet_cull_cells_entered_at_infinity_alike() {
    let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    let tris = [
        [v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0)],
        [v(2.0, 0.0, 0.0), v(3.0, 0.0, 0.0), v(2.0, 1.0, 0.0)],
        [v(0.0, 0.0, 0.5), v(1.0, 0.0, 0.5), v(0.0, 1.0, 0.5)],
    ];
    let scene = common::columns(&tris);
    let tree = TreeIr {
        bounds: scene.bounds(),
        nodes: vec![
            Node::Inner {
                axis: 0,
                pos: 1.5,
                right: NodeId(2),
                t_ref: None,
            },
            Node::Leaf { start: 0, count: 1 },
            Node::Leaf { start: 1, count: 2 },
        ],
        leaf_tris: vec![TriId(0), TriId(1), TriId(2)],
    };
    let file = read(&write(&tree, &scene, false));
    let rays: [Ray; 16] = std::array::from_fn(|i| {
        let o = v(
            0.1 + 0.05 * (i % 4) as f32,
            0.1 + 0.05 * (i / 4) as f32,
            2.0,
        );
        Ray::new(o, v(0.0, 0.0, -1.0))
    });
    for level in SimdLevel::available() {
        let mut got = [Hit::MISS; 16];
        PacketTracer::with_level(&file, level).closest_hit_4x4(&rays, &mut got);
        for (ray, h) in rays.iter().zip(got) {
            let single = trace::traverse(&file, ray);
            assert_eq!(h, single, "{level:?}, ray {ray:?}");
            assert_eq!(single.tri, TriId(0), "the left leaf's triangle");
        }
    }
}

/// Splits at the extremes of `f32` (±FLT_MAX, denormals, ±0) in trees
/// that cover their geometry, traced by axis-aligned rays and packets and
/// rays with zero direction components: split distances overflow to ±∞
/// (and `ts - ts·MARGIN` is NaN) on valid input, and single, packet and
/// brute force must still agree.
#[test]
fn extreme_splits_single_packet_brute_force_agree() {
    let mut rng = Rng(77);
    let small = random_small_scene(&mut rng, 30, 4);
    let mut tris: Vec<[Vec3; 3]> = (0..small.len() as u32)
        .map(|t| small.tri(t).map(|p| p - Vec3::splat(2.0)))
        .collect();
    let m = f32::MAX;
    // Huge triangles, so that the scene bounds reach ±FLT_MAX on x and y.
    tris.push([
        Vec3::new(-m, -1.0, -3.0),
        Vec3::new(m, -1.0, -3.0),
        Vec3::new(0.0, 1.0, -3.0),
    ]);
    tris.push([
        Vec3::new(-1.0, -m, 3.0),
        Vec3::new(1.0, m, 3.0),
        Vec3::new(0.0, 0.0, 3.5),
    ]);
    let scene = common::columns(&tris);
    let den = f32::from_bits(3);
    let candidates = [-m, m, -0.0, 0.0, den, -den, 0.5, -1.0, 1.5, -m / 2.0];
    let mut checked = 0;
    for seed in 0..12u64 {
        let tree = extreme_tree(&scene, seed, &candidates);
        if let Err(e) = tree.validate(&scene) {
            panic!("seed {seed}: invalid hand-made tree: {e}");
        }
        for reorder in [false, true] {
            let file = read(&write(&tree, &scene, reorder));
            assert!(covers_geometry(&file), "seed {seed}");
            let (rays, packets) = probes(&Aabb::new(Vec3::splat(-3.0), Vec3::splat(4.0)), seed);
            assert_agree(&file, &rays, &packets).unwrap_or_else(|e| panic!("seed {seed}: {e}"));
            checked += 1;
        }
    }
    assert_eq!(checked, 24);
}

/// A tree over `scene` whose splits are drawn from `candidates` (those
/// inside the cell), with the builders' classification and clipping, so it
/// covers its geometry; planar triangles go left.
fn extreme_tree(scene: &TriangleColumns, seed: u64, candidates: &[f32]) -> TreeIr {
    fn rec(
        scene: &TriangleColumns,
        rng: &mut Rng,
        candidates: &[f32],
        cell: Aabb,
        refs: Vec<TriRef>,
        depth: u32,
        tree: &mut TreeIr,
    ) {
        let k = rng.below(3);
        let inside: Vec<f32> = candidates
            .iter()
            .copied()
            .filter(|&p| p >= cell.min[k] && p <= cell.max[k])
            .collect();
        if depth >= 7 || refs.len() <= 2 || inside.is_empty() {
            let start = tree.leaf_tris.len() as u32;
            let mut ids: Vec<TriId> = refs.iter().map(|r| r.tri).collect();
            ids.sort_unstable();
            tree.leaf_tris.extend(ids);
            tree.nodes.push(Node::Leaf {
                start,
                count: refs.len() as u32,
            });
            return;
        }
        let pos = inside[rng.below(inside.len())];
        let split = Split {
            cost: 0.0,
            axis: k as u8,
            pos,
            planar: Side::Left,
        };
        let (lc, rc) = cell.split(k, pos);
        let (mut left, mut right) = (Vec::new(), Vec::new());
        for r in refs {
            match classify(&r.bounds, &split) {
                Placement::Left => left.push(r),
                Placement::Right => right.push(r),
                Placement::Both => {
                    let (l, rr) = clip_straddler(scene, &r, &split, &lc, &rc);
                    left.extend(l.map(|b| TriRef {
                        tri: r.tri,
                        bounds: b,
                    }));
                    right.extend(rr.map(|b| TriRef {
                        tri: r.tri,
                        bounds: b,
                    }));
                }
            }
        }
        let me = tree.nodes.len();
        tree.nodes.push(Node::Inner {
            axis: k as u8,
            pos,
            right: NodeId(0),
            t_ref: None,
        });
        rec(scene, rng, candidates, lc, left, depth + 1, tree);
        let next = NodeId(tree.nodes.len() as u32);
        if let Node::Inner { right: r, .. } = &mut tree.nodes[me] {
            *r = next;
        }
        rec(scene, rng, candidates, rc, right, depth + 1, tree);
    }
    let (bounds, refs) = slimkd::build::root(scene);
    let mut tree = TreeIr {
        bounds,
        nodes: Vec::new(),
        leaf_tris: Vec::new(),
    };
    rec(
        scene,
        &mut Rng(seed),
        candidates,
        bounds,
        refs,
        0,
        &mut tree,
    );
    tree
}

/// Header bounds that do not contain the geometry passed `verify` (664 of
/// the accepted fuzzed files): the default camera then failed ("eye and
/// at are the same point"), or an explicit one saw 0 hits where brute
/// force saw 22. Every triangle's vertices must lie inside the bounds, on
/// open and in the writer.
#[test]
fn bounds_not_containing_a_vertex_are_rejected() {
    let (scene, tree, bytes) = grid_file();
    for k in 0..6 {
        let mut b = bytes.clone();
        let at = H_BOUNDS + 4 * k;
        let c = f32::from_bits(get_u32(&b, at));
        // Bounds are the union of the triangles' boxes: one ulp inwards
        // leaves a vertex outside.
        set_u32(
            &mut b,
            at,
            if k < 3 { next_up(c) } else { next_down(c) }.to_bits(),
        );
        fix_header_crc(&mut b);
        match open(&b) {
            Err(FormatError::Index {
                section, message, ..
            }) => {
                assert_eq!(section, "vertices");
                assert!(
                    message.contains("outside the header's scene bounds"),
                    "{message}"
                );
            }
            Err(e) => panic!("bound {k}: wrong error {e}"),
            Ok(_) => panic!("bound {k}: bounds that miss a vertex were accepted"),
        }
    }
    let mut bad = tree.clone();
    bad.bounds.max.x = next_down(bad.bounds.max.x);
    assert!(matches!(
        format::write_to_vec(&bad, &scene, &WriteOptions::default()),
        Err(FormatError::Index {
            section: "vertices",
            ..
        })
    ));
}

/// Reserved fields are documented as zero (header bytes 364..380 after the
/// header checksum, and the reserved word of each section-table entry) but
/// were accepted non-zero; the two counts before them (340..356, empty
/// leaves without a word and one-triangle leaves) lie outside the header
/// checksum too, and are checked against the nodes; the split price
/// (356..364) and the reserved bytes are covered by the tail's CRC-32
/// (380..384).
#[test]
fn reserved_header_bytes_and_section_words_must_be_zero() {
    let (_, _, bytes) = grid_file();
    let section_words = (0..6).flat_map(|s| {
        let e = H_TABLE + s * H_ENTRY + 20;
        e..e + 4
    });
    // Header bytes 160..192 are the scene tag.
    for at in (356..384).chain(section_words) {
        let mut b = bytes.clone();
        b[at] ^= 0x40;
        fix_header_crc(&mut b);
        let reserved = !(356..364).contains(&at) && !(380..384).contains(&at);
        match open(&b) {
            Err(FormatError::Header(m)) if reserved => {
                assert!(m.to_string().contains("reserved"), "byte {at}: {m}")
            }
            Err(FormatError::Header(m)) => {
                assert!(m.to_string().contains("CRC-32"), "byte {at}: {m}")
            }
            Err(e) => panic!("byte {at}: wrong error {e}"),
            Ok(_) => panic!("byte {at}: a non-zero reserved byte was accepted"),
        }
    }
    for at in 340..356 {
        for bit in 0..8 {
            let mut b = bytes.clone();
            b[at] ^= 1 << bit;
            match open(&b) {
                Err(FormatError::Header(m)) => {
                    assert!(
                        m.to_string().contains("node counts"),
                        "byte {at} bit {bit}: {m}"
                    )
                }
                Err(e) => panic!("byte {at} bit {bit}: wrong error {e}"),
                Ok(_) => panic!("byte {at} bit {bit}: a wrong count was accepted"),
            }
        }
    }
}

/// NaN and infinite bounds or vertices are refused, and so is a `-0.0`
/// vertex coordinate (the scene's columns hold none, and
/// `KdFile::to_columns` hands the file's vertices to brute force as
/// columns).
#[test]
fn non_finite_or_negative_zero_geometry_is_rejected() {
    let (_, _, bytes) = grid_file();
    for x in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        for k in 0..6 {
            let mut b = bytes.clone();
            set_u32(&mut b, H_BOUNDS + 4 * k, x.to_bits());
            fix_header_crc(&mut b);
            assert!(
                matches!(open(&b), Err(FormatError::Header(_))),
                "bound {k} = {x}"
            );
        }
    }
    let verts = section(&bytes, Section::Vertices);
    // A vertex at the origin's corner of the grid has coordinates 0.0.
    let zero = (verts.start..verts.end)
        .step_by(4)
        .find(|&at| get_u32(&bytes, at) == 0)
        .expect("a zero coordinate");
    for x in [f32::NAN, f32::INFINITY, -0.0] {
        let mut b = bytes.clone();
        set_u32(&mut b, zero, x.to_bits());
        fix_all_crcs(&mut b);
        match open(&b) {
            Err(FormatError::Index { section, .. }) => assert_eq!(section, "vertices"),
            Err(e) => panic!("vertex coordinate {x}: wrong error {e}"),
            Ok(_) => panic!("vertex coordinate {x} accepted"),
        }
    }
}
