//! The `.kd` file format: writing and reading back (the tree, the leaf
//! modes, type II nodes and T-references survive, and traversal of the file
//! equals traversal of the tree and brute force), the leaf-mode and depth
//! limits, rejection of corrupt files (without panics, with specific
//! errors, every single-bit flip caught), atomic writes, and a committed
//! golden file that must keep loading.

mod common;

use common::*;
use glam::Vec3;
use proptest::prelude::*;
use slimkd::build::{self, BuildConfig, Builder};
use slimkd::format::node::{self, LEAF16_LIMIT, MAX_LEAF32, NodeWord};
use slimkd::format::{
    self, FileConfig, FormatError, HEADER_SIZE, KdFile, Preset, Section, WriteOptions, aligned_copy,
};
use slimkd::geom::{Aabb, Ray, clip_triangle};
use slimkd::scene::TriangleColumns;
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{self, ClosestHit, Hit, TreeTracer};
use slimkd::tree::{MAX_DEPTH, Node, NodeId, TreeIr, TriId};
use std::ops::Range;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

// Header field offsets (see the table in `slimkd::format`).
const H_VERSION: usize = 8;
const H_ENDIAN: usize = 12;
const H_HEADER_SIZE: usize = 16;
const H_FLAGS: usize = 20;
const H_PRESET: usize = 52;
const H_MAX_DEPTH: usize = 68;
const H_WORDS: usize = 72;
const H_INNER: usize = 80;
const H_T_INNER: usize = 88;
const H_LEAVES: usize = 96;
const H_IDX32: usize = 104;
const H_IDX16: usize = 112;
const H_TRIANGLES: usize = 120;
const H_VERTICES: usize = 128;
const H_BOUNDS: usize = 136;
const H_TABLE: usize = 192;
const H_ENTRY: usize = 24;
const H_CRC: usize = 336;

// ---------------------------------------------------------------------
// Small helpers: a deterministic random generator, byte fields, sections.
// ---------------------------------------------------------------------

/// SplitMix64: a small deterministic generator, so that every case of the
/// suite is the same on every run.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A number in `0..n` (`n > 0`).
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    /// A number in `[0, 1)`.
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }

    fn chance(&mut self, one_in: usize) -> bool {
        self.below(one_in) == 0
    }
}

fn get_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

fn set_u32(b: &mut [u8], at: usize, v: u32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

fn get_u64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

fn set_u64(b: &mut [u8], at: usize, v: u64) {
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
}

/// Recomputes the header checksum, so that a header edit reaches the checks
/// after it.
fn fix_header_crc(b: &mut [u8]) {
    let crc = crc32fast::hash(&b[..H_CRC]);
    set_u32(b, H_CRC, crc);
}

/// The byte range of a section, as the section table states it.
fn section(b: &[u8], s: Section) -> Range<usize> {
    let e = H_TABLE + s as usize * H_ENTRY;
    let ofs = get_u64(b, e) as usize;
    ofs..ofs + get_u64(b, e + 8) as usize
}

/// Recomputes every section checksum and then the header checksum, so that
/// a file whose structure is still valid also passes `verify`.
fn fix_all_crcs(b: &mut [u8]) {
    for s in Section::ALL {
        let crc = crc32fast::hash(&b[section(b, s)]);
        set_u32(b, H_TABLE + s as usize * H_ENTRY + 16, crc);
    }
    fix_header_crc(b);
}

fn set_word(b: &mut [u8], i: usize, w: u64) {
    let at = section(b, Section::Nodes).start + 8 * i;
    set_u64(b, at, w);
}

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn load_scene(name: &str) -> TriangleColumns {
    slimkd::scene::load_obj(&manifest_dir().join("scenes").join(name))
        .unwrap()
        .0
}

fn write(tree: &TreeIr, scene: &TriangleColumns, reorder: bool) -> Vec<u8> {
    let options = WriteOptions {
        reorder,
        ..Default::default()
    };
    format::write_to_vec(tree, scene, &options).unwrap()
}

/// Reads bytes that must be a valid file, checksums included.
fn read(bytes: &[u8]) -> KdFile<format::AlignedBytes> {
    let file = KdFile::from_bytes(aligned_copy(bytes)).unwrap();
    file.verify().unwrap();
    file
}

fn std_tree(scene: &TriangleColumns) -> TreeIr {
    build::build(scene, &BuildConfig::default(), Builder::Sweep, None).unwrap()
}

fn dir_entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

// ---------------------------------------------------------------------
// Scenes, rays and trees made for these tests.
// ---------------------------------------------------------------------

/// `n` small triangles: integer vertices in a unit cube placed at an
/// integer point of `[0, g]³`, so that the SAH tree has many levels.
fn random_small_scene(rng: &mut Rng, n: usize, g: usize) -> TriangleColumns {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            let base = Vec3::new(
                rng.below(g + 1) as f32,
                rng.below(g + 1) as f32,
                rng.below(g + 1) as f32,
            );
            std::array::from_fn(|_| {
                base + Vec3::new(
                    rng.below(2) as f32,
                    rng.below(2) as f32,
                    rng.below(2) as f32,
                )
            })
        })
        .collect();
    columns(&tris)
}

/// `n` triangles with integer vertices in `[0, g]³`.
fn random_grid_scene(rng: &mut Rng, n: usize, g: usize) -> TriangleColumns {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            std::array::from_fn(|_| {
                Vec3::new(
                    rng.below(g + 1) as f32,
                    rng.below(g + 1) as f32,
                    rng.below(g + 1) as f32,
                )
            })
        })
        .collect();
    columns(&tris)
}

/// 16 rays from one origin towards a 4×4 grid of targets around `target`,
/// `step` apart in the plane across `axis`.
fn fan_packet(origin: Vec3, target: Vec3, step: f32, axis: usize) -> [Ray; 16] {
    std::array::from_fn(|i| {
        let mut t = target;
        t[(axis + 1) % 3] += (i % 4) as f32 * step;
        t[(axis + 2) % 3] += (i / 4) as f32 * step;
        let d = t - origin;
        Ray::new(origin, if d == Vec3::ZERO { Vec3::X } else { d })
    })
}

fn lerp(a: Vec3, b: Vec3, rng: &mut Rng) -> Vec3 {
    a + (b - a) * Vec3::new(rng.unit(), rng.unit(), rng.unit())
}

/// Rays from around `bounds` (30% margin) towards points inside it.
fn rays_at(bounds: &Aabb, rng: &mut Rng, n: usize) -> Vec<Ray> {
    let margin = bounds.extent() * 0.3;
    (0..n)
        .map(|_| {
            let o = lerp(bounds.min - margin, bounds.max + margin, rng);
            let d = lerp(bounds.min, bounds.max, rng) - o;
            Ray::new(o, if d == Vec3::ZERO { Vec3::Y } else { d })
        })
        .collect()
}

/// Coherent packets from around `bounds` towards small target grids inside.
fn packets_at(bounds: &Aabb, rng: &mut Rng, n: usize) -> Vec<[Ray; 16]> {
    let margin = bounds.extent() * 0.3;
    (0..n)
        .map(|_| {
            let o = lerp(bounds.min - margin, bounds.max + margin, rng);
            let t = lerp(bounds.min, bounds.max, rng);
            let step = bounds.extent().max_element().max(1.0) * 0.02;
            fan_packet(o, t, step, rng.below(3))
        })
        .collect()
}

/// A tree node with everything traversal depends on, in input numbering.
#[derive(Debug, PartialEq)]
enum Shape {
    Inner {
        axis: u8,
        pos: u32,
        t_ref: Option<u32>,
    },
    /// The leaf's input ids, sorted.
    Leaf(Vec<u32>),
}

/// The in-memory tree in pre-order.
fn ir_shape(tree: &TreeIr) -> Vec<Shape> {
    tree.nodes
        .iter()
        .map(|n| match *n {
            Node::Inner {
                axis, pos, t_ref, ..
            } => Shape::Inner {
                axis,
                pos: pos.to_bits(),
                t_ref: t_ref.map(|t| t.0),
            },
            Node::Leaf { start, count } => {
                let mut ids: Vec<u32> = tree.leaf(start, count).iter().map(|t| t.0).collect();
                ids.sort_unstable();
                Shape::Leaf(ids)
            }
        })
        .collect()
}

/// The file's tree in pre-order (left child first), in input numbering.
fn file_shape<D: AsRef<[u8]>>(file: &KdFile<D>) -> Vec<Shape> {
    let words = file.nodes();
    let mut out = Vec::new();
    let mut stack = vec![0usize];
    while let Some(i) = stack.pop() {
        match node::decode(words[i]).unwrap() {
            NodeWord::Inner {
                axis,
                t_ref,
                block,
                pos,
            } => {
                let block = block as usize;
                let tri = t_ref.then(|| match node::decode(words[block]) {
                    Ok(NodeWord::TRef { tri }) => file.input_id(tri),
                    other => panic!("node {i}: expected a T-reference, got {other:?}"),
                });
                out.push(Shape::Inner {
                    axis,
                    pos: pos.to_bits(),
                    t_ref: tri,
                });
                let first = block + usize::from(t_ref);
                stack.push(first + 1);
                stack.push(first);
            }
            w @ (NodeWord::Leaf32 { .. } | NodeWord::Leaf16 { .. }) => {
                let mut ids = Vec::new();
                file.leaf(w).for_each(|t| ids.push(file.input_id(t)));
                ids.sort_unstable();
                out.push(Shape::Leaf(ids));
            }
            NodeWord::TRef { .. } => panic!("node {i}: a T-reference where a child belongs"),
        }
    }
    out
}

/// The leaf words of a file in pre-order.
fn file_leaf_words<D: AsRef<[u8]>>(file: &KdFile<D>) -> Vec<NodeWord> {
    let words = file.nodes();
    let mut out = Vec::new();
    let mut stack = vec![0usize];
    while let Some(i) = stack.pop() {
        match node::decode(words[i]).unwrap() {
            NodeWord::Inner { t_ref, block, .. } => {
                let first = block as usize + usize::from(t_ref);
                stack.push(first + 1);
                stack.push(first);
            }
            w => out.push(w),
        }
    }
    out
}

/// Asserts that scalar traversal of the tree and of the file, and packet
/// traversal of both at every SIMD level, return brute force's hit.
fn assert_all_agree<D: AsRef<[u8]> + Sync>(
    tree: &TreeIr,
    scene: &TriangleColumns,
    file: &KdFile<D>,
    rays: &[Ray],
    packets: &[[Ray; 16]],
) {
    let ir = TreeTracer { tree, scene };
    for ray in rays {
        let want = trace::brute_force(scene, ray);
        assert_eq!(trace::traverse(&ir, ray), want, "tree, ray {ray:?}");
        assert_eq!(trace::traverse(file, ray), want, "file, ray {ray:?}");
    }
    for rays in packets {
        let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(scene, r)).collect();
        for level in SimdLevel::available() {
            let mut got = [Hit::MISS; 16];
            PacketTracer::with_level(&ir, level).closest_hit_4x4(rays, &mut got);
            assert_eq!(got.to_vec(), want, "tree packet {level:?} {rays:?}");
            PacketTracer::with_level(file, level).closest_hit_4x4(rays, &mut got);
            assert_eq!(got.to_vec(), want, "file packet {level:?} {rays:?}");
        }
    }
}

/// Asserts the counts a file reports against the tree it was written from.
fn assert_figures<D: AsRef<[u8]>>(file: &KdFile<D>, tree: &TreeIr, scene: &TriangleColumns) {
    let f = file.figures();
    let t_inner = tree.n_t_inner() as u64;
    assert_eq!(f.t_inner, t_inner);
    assert_eq!(f.inner, tree.n_inner() as u64 - t_inner);
    assert_eq!(f.leaves, tree.n_leaves() as u64);
    assert_eq!(f.words, f.inner + f.t_inner + f.leaves + f.t_inner);
    assert_eq!(f.words, file.nodes().len() as u64);
    assert_eq!(f.nodes(), tree.nodes.len() as u64);
    assert_eq!(f.idx32, file.idx32().len() as u64);
    assert_eq!(f.idx16, file.idx16().len() as u64);
    assert_eq!(f.idx32 + f.idx16, tree.leaf_tris.len() as u64);
    assert_eq!(f.triangles, scene.len() as u64);
    assert_eq!(f.vertices, scene.positions().len() as u64);
    assert_eq!(
        f.tree_bytes(),
        8 * (f.nodes() + f.t_inner) + 4 * f.idx32 + 2 * f.idx16
    );
    assert_eq!(f.tree_bytes(), 8 * f.words + 4 * f.idx32 + 2 * f.idx16);
    assert_eq!(file.bounds(), tree.bounds);
}

/// Where each subtree ends in pre-order: node `i`'s subtree is
/// `i..end[i]`.
fn subtree_ends(tree: &TreeIr) -> Vec<usize> {
    let mut end = vec![0; tree.nodes.len()];
    for i in (0..tree.nodes.len()).rev() {
        end[i] = match tree.nodes[i] {
            Node::Inner { right, .. } => end[right.0 as usize],
            Node::Leaf { .. } => i + 1,
        };
    }
    end
}

/// Makes type II nodes: hoists into about half of the inner nodes a
/// triangle listed in a leaf below (so it overlaps the node's cell), and
/// with `remove`, sometimes drops it from every leaf below (it stays
/// reachable there through the hoisted copy). Returns the tree, which must
/// still be valid, and the number of type II nodes.
fn hoist(tree: &TreeIr, scene: &TriangleColumns, seed: u64, remove: bool) -> (TreeIr, usize) {
    let mut rng = Rng(seed);
    let n = tree.nodes.len();
    let mut cells = vec![tree.bounds; n];
    tree.walk(|id, _, cell, _| cells[id.0 as usize] = *cell);
    let end = subtree_ends(tree);
    let mut out = tree.clone();
    let mut hoisted = 0;
    // (subtree range, triangle) to drop from the leaves.
    let mut dropped: Vec<(Range<usize>, TriId)> = Vec::new();
    for i in 0..n {
        if !matches!(tree.nodes[i], Node::Inner { .. }) || rng.chance(2) {
            continue;
        }
        let below: Vec<TriId> = (i..end[i])
            .flat_map(|j| match tree.nodes[j] {
                Node::Leaf { start, count } => tree.leaf(start, count).to_vec(),
                Node::Inner { .. } => Vec::new(),
            })
            .collect();
        if below.is_empty() {
            continue;
        }
        let t = below[rng.below(below.len())];
        if clip_triangle(&scene.tri(t.0), &cells[i]).is_none() {
            continue;
        }
        if let Node::Inner { t_ref, .. } = &mut out.nodes[i] {
            *t_ref = Some(t);
            hoisted += 1;
        }
        if remove && rng.chance(2) {
            dropped.push((i..end[i], t));
        }
    }
    // Rebuild the leaf lists so they stay contiguous in pre-order.
    let mut leaf_tris = Vec::new();
    for i in 0..n {
        if let Node::Leaf { start, count } = tree.nodes[i] {
            let first = leaf_tris.len() as u32;
            leaf_tris.extend(
                tree.leaf(start, count)
                    .iter()
                    .filter(|&&t| !dropped.iter().any(|(r, d)| r.contains(&i) && *d == t)),
            );
            out.nodes[i] = Node::Leaf {
                start: first,
                count: leaf_tris.len() as u32 - first,
            };
        }
    }
    out.leaf_tris = leaf_tris;
    if let Err(e) = out.validate(scene) {
        panic!("hand-made type II tree is invalid: {e}");
    }
    assert_eq!(out.n_t_inner(), hoisted);
    (out, hoisted)
}

/// `n` small triangles along the x axis: triangle `i` spans `[i, i + 0.5]`
/// in x, so that any set of id intervals can be separated by x planes.
fn strip_scene(n: u32) -> TriangleColumns {
    let tris: Vec<[Vec3; 3]> = (0..n)
        .map(|i| {
            let x = i as f32;
            [
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(x + 0.5, 0.0, 0.0),
                Vec3::new(x, 0.5, 0.5),
            ]
        })
        .collect();
    columns(&tris)
}

/// A tree over a strip scene with the given leaves (left to right; every id
/// of a leaf lies below every id of the next). Balanced, or with
/// `caterpillar` a chain that peels one leaf off at each level.
fn strip_tree(scene: &TriangleColumns, leaves: &[Vec<u32>], caterpillar: bool) -> TreeIr {
    fn rec(leaves: &[Vec<u32>], caterpillar: bool, tree: &mut TreeIr) {
        if let [leaf] = leaves {
            let start = tree.leaf_tris.len() as u32;
            tree.leaf_tris.extend(leaf.iter().map(|&t| TriId(t)));
            tree.nodes.push(Node::Leaf {
                start,
                count: leaf.len() as u32,
            });
            return;
        }
        let mid = if caterpillar { 1 } else { leaves.len() / 2 };
        let me = tree.nodes.len();
        tree.nodes.push(Node::Inner {
            axis: 0,
            pos: *leaves[mid].iter().min().unwrap() as f32 - 0.25,
            right: NodeId(0),
            t_ref: None,
        });
        rec(&leaves[..mid], caterpillar, tree);
        let next = NodeId(tree.nodes.len() as u32);
        if let Node::Inner { right, .. } = &mut tree.nodes[me] {
            *right = next;
        }
        rec(&leaves[mid..], caterpillar, tree);
    }
    let mut tree = TreeIr {
        bounds: scene.bounds(),
        nodes: Vec::new(),
        leaf_tris: Vec::new(),
    };
    rec(leaves, caterpillar, &mut tree);
    tree
}

/// Rays from random points around a strip scene towards the centroids of
/// random triangles (so that most of them hit).
fn strip_rays(scene: &TriangleColumns, rng: &mut Rng, n: usize) -> Vec<Ray> {
    let b = scene.bounds();
    (0..n)
        .map(|_| {
            let [a, b2, c] = scene.tri(rng.below(scene.len()) as u32);
            let target = (a + b2 + c) / 3.0;
            let o = Vec3::new(
                target.x + (rng.unit() - 0.5) * 8.0,
                b.min.y - 1.0 - rng.unit() * 4.0,
                b.max.z + 1.0 + rng.unit() * 4.0,
            );
            Ray::new(o, target - o)
        })
        .collect()
}

// ---------------------------------------------------------------------
// Round trips, type II nodes included.
// ---------------------------------------------------------------------

fn packet_strategy(g: i32) -> impl Strategy<Value = [Ray; 16]> {
    let coord = move || (-2..=2 * g + 2).prop_map(|k| k as f32 * 0.5);
    let point = move || (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    (point(), point(), 1..4i32, 0..3usize)
        .prop_map(|(o, t, step, axis)| fan_packet(o, t, 0.5 * step as f32, axis))
}

proptest! {
    #![proptest_config(cases(128))]

    /// Grid scenes: the file holds the same tree (split planes bit for
    /// bit, leaves as sets of input ids), its figures match, and every
    /// traverser over it returns brute force's hit, reordered or not.
    #[test]
    fn round_trip_grid_scenes(
        (tris, rays, packets) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=50),
            prop::collection::vec(grid_ray(g), 24),
            prop::collection::vec(packet_strategy(g), 2),
        ))
    ) {
        let scene = columns(&tris);
        let tree = std_tree(&scene);
        for reorder in [false, true] {
            let bytes = write(&tree, &scene, reorder);
            prop_assert_eq!(&bytes, &write(&tree, &scene, reorder), "the writer is deterministic");
            prop_assert_eq!(bytes.len() % 64, 0);
            let file = read(&bytes);
            prop_assert_eq!(file.is_reordered(), reorder);
            prop_assert_eq!(file_shape(&file), ir_shape(&tree));
            assert_figures(&file, &tree, &scene);
            assert_all_agree(&tree, &scene, &file, &rays, &packets);
        }
    }

    /// Type II nodes made by hand (a hoisted triangle, sometimes removed
    /// from the leaves below): the T-references round-trip, the figures
    /// count them, and traversal still equals brute force.
    #[test]
    fn type_ii_nodes_round_trip(
        (tris, rays, packets, seed, remove, reorder) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 1..=40),
            prop::collection::vec(grid_ray(g), 24),
            prop::collection::vec(packet_strategy(g), 2),
            any::<u64>(),
            any::<bool>(),
            any::<bool>(),
        ))
    ) {
        let scene = columns(&tris);
        let (tree, hoisted) = hoist(&std_tree(&scene), &scene, seed, remove);
        let file = read(&write(&tree, &scene, reorder));
        prop_assert_eq!(file.figures().t_inner, hoisted as u64);
        prop_assert_eq!(file_shape(&file), ir_shape(&tree));
        assert_figures(&file, &tree, &scene);
        assert_all_agree(&tree, &scene, &file, &rays, &packets);
    }
}

/// The shipped bunny through `write_file` and `KdFile::open` (a memory
/// map, checksums verified), reordered or not, with and without type II
/// nodes.
#[test]
fn round_trip_bunny_through_mmap() {
    let scene = load_scene("bunny_npm.obj");
    let std = std_tree(&scene);
    let (hoisted, n_hoisted) = hoist(&std, &scene, 7, true);
    assert!(n_hoisted > 100, "{n_hoisted} type II nodes");
    let dir = fresh_temp_dir("bunny");
    let mut rng = Rng(1);
    let rays = rays_at(&scene.bounds(), &mut rng, 300);
    let packets = packets_at(&scene.bounds(), &mut rng, 12);
    for (name, tree) in [("std", &std), ("type2", &hoisted)] {
        for reorder in [false, true] {
            let path = dir.join(format!("bunny-{name}-{reorder}.kd"));
            let options = WriteOptions {
                reorder,
                ..Default::default()
            };
            format::write_file(&path, tree, &scene, &options).unwrap();
            let file = KdFile::open(&path, true).unwrap();
            assert_eq!(
                file.as_bytes(),
                format::write_to_vec(tree, &scene, &options).unwrap()
            );
            assert_eq!(file.is_reordered(), reorder);
            assert_eq!(file_shape(&file), ir_shape(tree));
            assert_figures(&file, tree, &scene);
            assert_all_agree(tree, &scene, &file, &rays, &packets);
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------
// Leaf modes, count limits and the depth limit.
// ---------------------------------------------------------------------

/// One leaf of 2047 ids sharing their upper 16 bits is a 2-byte leaf; one
/// of 2048 is a 4-byte leaf.
#[test]
fn leaf_mode_at_2047_and_2048_indices() {
    let mut rng = Rng(3);
    for n in [LEAF16_LIMIT - 1, LEAF16_LIMIT] {
        let scene = strip_scene(n);
        let tree = strip_tree(&scene, &[(0..n).collect()], false);
        tree.validate(&scene).unwrap();
        let file = read(&write(&tree, &scene, false));
        let f = file.figures();
        let want = if n < LEAF16_LIMIT {
            assert_eq!((f.idx16, f.idx32), (2047, 0));
            NodeWord::Leaf16 {
                count: n,
                upper: 0,
                start: 0,
            }
        } else {
            assert_eq!((f.idx16, f.idx32), (0, 2048));
            NodeWord::Leaf32 { count: n, start: 0 }
        };
        assert_eq!(node::decode(file.nodes()[0]), Ok(want));
        assert_figures(&file, &tree, &scene);
        let rays = strip_rays(&scene, &mut rng, 24);
        let packets = packets_at(&scene.bounds(), &mut rng, 2);
        assert_all_agree(&tree, &scene, &file, &rays, &packets);
    }
}

/// Leaves around the 65536 boundary: ids below it, a leaf straddling it
/// (4-byte), ids above it with equal upper bits (2-byte, upper 1, at 2047
/// and 1 ids), and 2048 ids above it (4-byte).
#[test]
fn leaf_modes_around_the_65536_boundary() {
    let ranges = [
        0..63_000u32,
        63_000..65_000,
        65_000..65_600,
        65_600..67_647,
        67_647..67_648,
        67_648..69_696,
    ];
    let scene = strip_scene(69_696);
    let leaves: Vec<Vec<u32>> = ranges.iter().map(|r| r.clone().collect()).collect();
    let tree = strip_tree(&scene, &leaves, false);
    tree.validate(&scene).unwrap();
    let file = read(&write(&tree, &scene, false));
    let modes: Vec<(bool, u32, u16)> = file_leaf_words(&file)
        .into_iter()
        .map(|w| match w {
            NodeWord::Leaf32 { count, .. } => (false, count, 0),
            NodeWord::Leaf16 { count, upper, .. } => (true, count, upper),
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(
        modes,
        [
            (false, 63_000, 0),
            (true, 2000, 0),
            (false, 600, 0),
            (true, 2047, 1),
            (true, 1, 1),
            (false, 2048, 0),
        ]
    );
    let f = file.figures();
    assert_eq!(f.idx16, 2000 + 2047 + 1);
    assert_eq!(f.idx32, 63_000 + 600 + 2048);
    assert_eq!(file_shape(&file), ir_shape(&tree));
    assert_figures(&file, &tree, &scene);
    let mut rng = Rng(4);
    let mut rays = strip_rays(&scene, &mut rng, 40);
    // Aim some rays at the leaves with upper bits 1.
    for t in [65_535u32, 65_536, 65_537, 67_646, 67_647, 67_648, 69_695] {
        let [a, b, c] = scene.tri(t);
        let target = (a + b + c) / 3.0;
        let o = target + Vec3::new(0.3, -2.0, 3.0);
        rays.push(Ray::new(o, target - o));
    }
    for ray in &rays[40..] {
        assert!(trace::brute_force(&scene, ray).is_hit());
    }
    let packets = packets_at(&scene.bounds(), &mut rng, 2);
    assert_all_agree(&tree, &scene, &file, &rays, &packets);
}

/// With reordering, the triangles of a leaf get nearby ids, so most
/// indices of a real scene are stored in 2 bytes.
#[test]
fn reordering_puts_most_indices_in_idx16() {
    let scene = load_scene("bunny_npm.obj");
    let tree = std_tree(&scene);
    let f = read(&write(&tree, &scene, true)).figures();
    let share = f.idx16 as f64 / (f.idx16 + f.idx32) as f64;
    assert!(share >= 0.9, "{share:.3} of the indices in idx16: {f:?}");
}

/// A 4-byte leaf at the largest count, 2^27 − 1: the node word round-trips
/// and the reader accepts a file holding it (made in a zero-initialised
/// buffer, so that the 512 MiB idx32 section costs no memory; the leaf
/// repeats triangle 0); one more index than idx32 holds is rejected; and
/// the writer refuses a leaf of 2^27 rather than wrap the count field. (The
/// writer is not run at 2^27 − 1: its copies of the indices would take
/// about 3 GB.)
#[test]
fn leaf_at_the_maximum_count() {
    let w = node::encode_leaf32(MAX_LEAF32, 5);
    assert_eq!(
        node::decode(w),
        Ok(NodeWord::Leaf32 {
            count: MAX_LEAF32,
            start: 5
        })
    );

    // A template file: one triangle, one 4-byte leaf listing it 2048 times.
    let scene = columns(&[[Vec3::ZERO, Vec3::X, Vec3::Y]]);
    let small_tree = TreeIr {
        bounds: scene.bounds(),
        nodes: vec![Node::Leaf {
            start: 0,
            count: LEAF16_LIMIT,
        }],
        leaf_tris: vec![TriId(0); LEAF16_LIMIT as usize],
    };
    let small = write(&small_tree, &scene, false);
    let ray = Ray::new(Vec3::new(0.25, 0.25, 1.0), -Vec3::Z);
    {
        let file = read(&small);
        assert_eq!(file.figures().idx32, u64::from(LEAF16_LIMIT));
        assert_eq!(
            trace::traverse(&file, &ray),
            trace::brute_force(&scene, &ray)
        );
    }

    // The same file with the leaf grown to MAX_LEAF32 entries.
    let n = MAX_LEAF32 as usize;
    let lens = Section::ALL.map(|s| {
        if s == Section::Idx32 {
            4 * n
        } else {
            section(&small, s).len()
        }
    });
    let mut offsets = [0usize; 6];
    let mut end = HEADER_SIZE;
    for s in Section::ALL {
        offsets[s as usize] = end.next_multiple_of(64);
        end = offsets[s as usize] + lens[s as usize];
    }
    let total = end.next_multiple_of(64);
    let make = |leaf: u64| {
        let mut big = ZeroedBytes(vec![0u64; total / 8]);
        let b = big.bytes_mut();
        b[..HEADER_SIZE].copy_from_slice(&small[..HEADER_SIZE]);
        set_u64(b, H_IDX32, n as u64);
        for s in Section::ALL {
            let (ofs, len) = (offsets[s as usize], lens[s as usize]);
            if s != Section::Idx32 {
                b[ofs..ofs + len].copy_from_slice(&small[section(&small, s)]);
            }
            set_u64(b, H_TABLE + s as usize * H_ENTRY, ofs as u64);
            set_u64(b, H_TABLE + s as usize * H_ENTRY + 8, len as u64);
        }
        set_word(b, 0, leaf);
        fix_all_crcs(b);
        big
    };
    let file = KdFile::from_bytes(make(node::encode_leaf32(MAX_LEAF32, 0))).unwrap();
    file.verify().unwrap();
    let w = node::decode(file.nodes()[0]).unwrap();
    assert_eq!(
        w,
        NodeWord::Leaf32 {
            count: MAX_LEAF32,
            start: 0
        }
    );
    assert_eq!(file.leaf(w).len(), n);
    assert_eq!(file.figures().idx32, n as u64);
    // Every index of the leaf is readable (tracing a ray through it would
    // test the triangle 2^27 times: seconds, so it is left out).
    let mut zeros = 0usize;
    file.leaf(w).for_each(|t| zeros += usize::from(t == 0));
    assert_eq!(zeros, n);
    drop(file);
    // One index past the end of idx32.
    assert!(matches!(
        KdFile::from_bytes(make(node::encode_leaf32(MAX_LEAF32, 1))),
        Err(FormatError::Node { index: 0, .. })
    ));

    // The writer refuses 2^27 indices in a leaf.
    let huge = TreeIr {
        bounds: scene.bounds(),
        nodes: vec![Node::Leaf {
            start: 0,
            count: MAX_LEAF32 + 1,
        }],
        leaf_tris: vec![TriId(0); n + 1],
    };
    match format::write_to_vec(&huge, &scene, &WriteOptions::default()) {
        Err(FormatError::TooLarge(_)) => {}
        Err(e) => panic!("refused with the wrong error: {e}"),
        Ok(_) => panic!("written"),
    }
}

/// Bytes in a `Vec<u64>` (8-byte aligned); `vec![0u64; n]` maps zero pages
/// lazily, so untouched parts cost no memory.
struct ZeroedBytes(Vec<u64>);

impl ZeroedBytes {
    fn bytes_mut(&mut self) -> &mut [u8] {
        bytemuck::cast_slice_mut(&mut self.0)
    }
}

impl AsRef<[u8]> for ZeroedBytes {
    fn as_ref(&self) -> &[u8] {
        bytemuck::cast_slice(&self.0)
    }
}

/// A chain of inner nodes whose deepest leaves lie at exactly `MAX_DEPTH`
/// is written, read and traversed (the traversal stack fills up for rays
/// going down the chain); one level more is refused by the writer.
#[test]
fn depth_limit() {
    let depth = MAX_DEPTH;
    let scene = strip_scene(depth + 1);
    let leaves: Vec<Vec<u32>> = (0..=depth).map(|i| vec![i]).collect();
    let tree = strip_tree(&scene, &leaves, true);
    tree.validate(&scene).unwrap();
    let file = read(&write(&tree, &scene, false));
    assert_eq!(file.max_depth(), depth);
    let hist = file.leaf_depth_histogram();
    assert_eq!(hist.len(), depth as usize + 1);
    assert_eq!(hist[depth as usize], 2);
    let mut rng = Rng(5);
    let mut rays = strip_rays(&scene, &mut rng, 30);
    // Along the strip in both directions, from beyond each end.
    let b = scene.bounds();
    for x in [b.min.x - 1.0, b.max.x + 1.0] {
        for dx in [1.0, -1.0] {
            rays.push(Ray::new(Vec3::new(x, 0.1, 0.1), Vec3::new(dx, 0.0, 0.0)));
            rays.push(Ray::new(Vec3::new(x, 0.1, 0.1), Vec3::new(dx, 0.001, 0.0)));
        }
    }
    // Coherent packets (every lane's direction has the same signs).
    let packets = vec![
        fan_packet(
            Vec3::new(b.max.x + 5.0, 0.1, 0.1),
            Vec3::new(b.min.x, 0.2, 0.2),
            0.05,
            0,
        ),
        fan_packet(
            Vec3::new(b.min.x - 5.0, 0.1, 0.1),
            Vec3::new(b.max.x, 0.2, 0.2),
            0.05,
            0,
        ),
    ];
    assert_all_agree(&tree, &scene, &file, &rays, &packets);

    let scene = strip_scene(depth + 2);
    let leaves: Vec<Vec<u32>> = (0..=depth + 1).map(|i| vec![i]).collect();
    let tree = strip_tree(&scene, &leaves, true);
    match format::write_to_vec(&tree, &scene, &WriteOptions::default()) {
        Err(FormatError::TooLarge(_)) => {}
        Err(e) => panic!("refused with the wrong error: {e}"),
        Ok(_) => panic!("written"),
    }
}

/// The writer refuses, with an error rather than a panic or a file the
/// reader rejects, trees that are malformed.
#[test]
fn writer_refuses_malformed_trees() {
    let scene = strip_scene(4);
    let good = strip_tree(&scene, &[vec![0, 1], vec![2, 3]], false);
    let write = |t: &TreeIr| format::write_to_vec(t, &scene, &WriteOptions::default());
    assert!(write(&good).is_ok());
    let edit = |f: &dyn Fn(&mut TreeIr)| {
        let mut t = good.clone();
        f(&mut t);
        t
    };
    let cases: Vec<(&str, TreeIr)> = vec![
        ("no nodes", edit(&|t| t.nodes.clear())),
        (
            "axis 3",
            edit(&|t| {
                if let Node::Inner { axis, .. } = &mut t.nodes[0] {
                    *axis = 3;
                }
            }),
        ),
        (
            "NaN split",
            edit(&|t| {
                if let Node::Inner { pos, .. } = &mut t.nodes[0] {
                    *pos = f32::NAN;
                }
            }),
        ),
        (
            "right child out of range",
            edit(&|t| {
                if let Node::Inner { right, .. } = &mut t.nodes[0] {
                    *right = NodeId(9);
                }
            }),
        ),
        (
            "right child is the node itself",
            edit(&|t| {
                if let Node::Inner { right, .. } = &mut t.nodes[0] {
                    *right = NodeId(0);
                }
            }),
        ),
        (
            "hoisted triangle out of range",
            edit(&|t| {
                if let Node::Inner { t_ref, .. } = &mut t.nodes[0] {
                    *t_ref = Some(TriId(4));
                }
            }),
        ),
        (
            "leaf triangle out of range",
            edit(&|t| t.leaf_tris[3] = TriId(4)),
        ),
        ("leaf list out of range", edit(&|t| t.leaf_tris.truncate(3))),
        (
            "bounds not finite",
            edit(&|t| t.bounds.max.x = f32::INFINITY),
        ),
        ("bounds inverted", edit(&|t| t.bounds.min.y = 1.0)),
    ];
    for (what, tree) in cases {
        let result = catch_unwind(AssertUnwindSafe(|| write(&tree)));
        match result {
            Ok(Err(_)) => {}
            Ok(Ok(_)) => panic!("{what}: written"),
            Err(_) => panic!("{what}: the writer panicked"),
        }
    }
}

// ---------------------------------------------------------------------
// Corrupt files.
// ---------------------------------------------------------------------

/// What reading a byte string gave.
#[derive(Debug)]
enum Outcome {
    /// `from_bytes` refused it.
    Rejected(FormatError),
    /// `from_bytes` accepted it and `verify` refused it.
    BadChecksum(FormatError),
    /// Both accepted it.
    Accepted,
}

/// Rays and packets traced over every file `from_bytes` accepts.
struct Probes {
    rays: Vec<Ray>,
    packets: Vec<[Ray; 16]>,
    levels: Vec<SimdLevel>,
}

impl Probes {
    fn around(bounds: &Aabb, seed: u64) -> Probes {
        let mut rng = Rng(seed);
        Probes {
            rays: rays_at(bounds, &mut rng, 16),
            packets: packets_at(bounds, &mut rng, 1),
            levels: SimdLevel::available(),
        }
    }
}

/// Reads `bytes` as a file; when `from_bytes` accepts it, traces every
/// probe over it with every traverser. `Err` says what panicked.
fn probe(bytes: &[u8], probes: &Probes) -> Result<Outcome, String> {
    let data = aligned_copy(bytes);
    let file = match catch_unwind(AssertUnwindSafe(|| KdFile::from_bytes(data))) {
        Ok(Ok(file)) => file,
        Ok(Err(e)) => return Ok(Outcome::Rejected(e)),
        Err(_) => return Err("from_bytes panicked".into()),
    };
    let verified =
        catch_unwind(AssertUnwindSafe(|| file.verify())).map_err(|_| "verify panicked")?;
    catch_unwind(AssertUnwindSafe(|| {
        for ray in &probes.rays {
            std::hint::black_box(trace::traverse(&file, ray));
        }
        for rays in &probes.packets {
            for &level in &probes.levels {
                let mut out = [Hit::MISS; 16];
                PacketTracer::with_level(&file, level).closest_hit_4x4(rays, &mut out);
                std::hint::black_box(out);
            }
        }
        std::hint::black_box(file.leaf_depth_histogram());
        std::hint::black_box(file.figures().tree_bytes());
    }))
    .map_err(|_| "traversal panicked")?;
    Ok(match verified {
        Ok(()) => Outcome::Accepted,
        Err(e) => Outcome::BadChecksum(e),
    })
}

/// Runs cases and collects failures, so that one run reports many.
struct Suite {
    probes: Probes,
    cases: usize,
    accepted: usize,
    failures: Vec<String>,
}

impl Suite {
    fn new(probes: Probes) -> Suite {
        Suite {
            probes,
            cases: 0,
            accepted: 0,
            failures: Vec::new(),
        }
    }

    /// Probes one case; `check` judges the outcome (`Err` = failure).
    fn case(
        &mut self,
        what: &dyn Fn() -> String,
        bytes: &[u8],
        check: impl FnOnce(&Outcome) -> Result<(), String>,
    ) {
        self.cases += 1;
        match probe(bytes, &self.probes) {
            Ok(outcome) => {
                if matches!(outcome, Outcome::Accepted) {
                    self.accepted += 1;
                }
                if let Err(msg) = check(&outcome) {
                    self.fail(format!("{}: {msg} (got {outcome:?})", what()));
                }
            }
            Err(msg) => self.fail(format!("{}: {msg}", what())),
        }
    }

    fn fail(&mut self, msg: String) {
        if self.failures.len() < 20 {
            self.failures.push(msg);
        } else if self.failures.len() == 20 {
            self.failures.push("...".into());
        }
    }

    fn finish(self, name: &str, min_cases: usize) -> usize {
        assert!(
            self.failures.is_empty(),
            "{name}: {} failures in {} cases:\n{}",
            self.failures.len(),
            self.cases,
            self.failures.join("\n")
        );
        assert!(self.cases >= min_cases, "{name}: only {} cases", self.cases);
        eprintln!(
            "{name}: {} cases, {} accepted by from_bytes and verify",
            self.cases, self.accepted
        );
        self.cases
    }
}

fn no_check(_: &Outcome) -> Result<(), String> {
    Ok(())
}

fn must_fail(o: &Outcome) -> Result<(), String> {
    match o {
        Outcome::Accepted => Err("accepted".into()),
        _ => Ok(()),
    }
}

/// A valid file to corrupt, with what it was made from.
struct Base {
    name: &'static str,
    bytes: Vec<u8>,
    bounds: Aabb,
}

/// Small valid files: plain, reordered, with type II nodes (reordered), and
/// one with a 4-byte leaf (2048 ids, repeating triangles).
fn small_bases() -> Vec<Base> {
    let mut rng = Rng(11);
    let scene = random_small_scene(&mut rng, 24, 6);
    let tree = std_tree(&scene);
    let scene2 = random_small_scene(&mut rng, 40, 8);
    let (tree2, hoisted) = hoist(&std_tree(&scene2), &scene2, 12, true);
    assert!(hoisted >= 3, "{hoisted} type II nodes");
    let scene3 = strip_scene(6);
    let mut big_leaf: Vec<u32> = (0..LEAF16_LIMIT).map(|i| i % 3).collect();
    big_leaf.sort_unstable();
    let tree3 = strip_tree(&scene3, &[big_leaf, vec![3, 4], vec![5]], false);
    let bases = vec![
        Base {
            name: "grid",
            bytes: write(&tree, &scene, false),
            bounds: tree.bounds,
        },
        Base {
            name: "grid-reordered",
            bytes: write(&tree, &scene, true),
            bounds: tree.bounds,
        },
        Base {
            name: "type2-reordered",
            bytes: write(&tree2, &scene2, true),
            bounds: tree2.bounds,
        },
        Base {
            name: "idx32",
            bytes: write(&tree3, &scene3, false),
            bounds: tree3.bounds,
        },
    ];
    for b in &bases {
        read(&b.bytes);
    }
    let f = read(&bases[2].bytes).figures();
    assert!(f.t_inner >= 3 && f.idx16 > 0);
    assert!(read(&bases[3].bytes).figures().idx32 >= u64::from(LEAF16_LIMIT));
    bases
}

/// The bunny, reordered, with type II nodes: a bigger file, sampled.
fn bunny_base() -> Base {
    let scene = load_scene("bunny_npm.obj");
    let (tree, _) = hoist(&std_tree(&scene), &scene, 21, true);
    Base {
        name: "bunny-type2-reordered",
        bytes: write(&tree, &scene, true),
        bounds: tree.bounds,
    }
}

/// Which part of a valid file a byte lies in.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Region {
    Magic,
    Version,
    Endianness,
    /// Covered by the header checksum (the checksum itself included).
    Header,
    /// Header bytes 340..384: reserved, zero.
    Reserved,
    Section(Section),
    /// Zero padding after a section.
    Padding(Section),
}

fn region(b: &[u8], pos: usize) -> Region {
    match pos {
        0..8 => Region::Magic,
        8..12 => Region::Version,
        12..16 => Region::Endianness,
        16..340 => Region::Header,
        340..HEADER_SIZE => Region::Reserved,
        _ => {
            let s = Section::ALL
                .into_iter()
                .rev()
                .find(|&s| section(b, s).start <= pos)
                .unwrap();
            if section(b, s).contains(&pos) {
                Region::Section(s)
            } else {
                Region::Padding(s)
            }
        }
    }
}

/// The error a single corrupted byte at `pos` of a valid file must give.
fn check_single_flip(b: &[u8], pos: usize, o: &Outcome) -> Result<(), String> {
    let ok = match (region(b, pos), o) {
        (Region::Magic, Outcome::Rejected(FormatError::BadMagic)) => true,
        (Region::Version, Outcome::Rejected(FormatError::Version { expected: 1, .. })) => true,
        (Region::Endianness, Outcome::Rejected(FormatError::Endianness)) => true,
        (Region::Header, Outcome::Rejected(FormatError::HeaderChecksum { .. })) => true,
        (Region::Reserved, Outcome::Rejected(FormatError::Header(_))) => true,
        (Region::Padding(s), Outcome::Rejected(FormatError::Section { section, .. })) => {
            *section == s.name()
        }
        (Region::Section(_), Outcome::Rejected(_)) => true,
        (
            Region::Section(s),
            Outcome::BadChecksum(FormatError::ChecksumMismatch { section, .. }),
        ) => *section == s.name(),
        _ => false,
    };
    if ok {
        Ok(())
    } else {
        Err(format!("wrong outcome for {:?}", region(b, pos)))
    }
}

/// (a) Every single-bit flip of the small files (exhaustively) and a sample
/// of the bunny's is caught by `from_bytes` or `verify`, with the error of
/// the region it lies in; random multi-bit flips are caught too.
#[test]
fn corrupt_bit_flips() {
    let mut bases = small_bases();
    bases.push(bunny_base());
    let mut rng = Rng(100);
    let mut total = 0;
    for base in &bases {
        let mut suite = Suite::new(Probes::around(&base.bounds, 1));
        let orig = &base.bytes;
        let bits = orig.len() * 8;
        // The idx32 base and the bunny are sampled; the others exhaustive.
        let exhaustive = bits <= 40_000;
        let singles: Vec<usize> = if exhaustive {
            (0..bits).collect()
        } else {
            (0..3000).map(|_| rng.below(bits)).collect()
        };
        let mut b = orig.clone();
        for bit in singles {
            b[bit / 8] ^= 1 << (bit % 8);
            suite.case(
                &|| format!("{}: flip bit {bit} (byte {})", base.name, bit / 8),
                &b,
                |o| check_single_flip(orig, bit / 8, o),
            );
            b[bit / 8] ^= 1 << (bit % 8);
        }
        for _ in 0..1500 {
            let k = 2 + rng.below(15);
            let mut flipped = Vec::new();
            while flipped.len() < k {
                let bit = rng.below(bits);
                if !flipped.contains(&bit) {
                    flipped.push(bit);
                }
            }
            for &bit in &flipped {
                b[bit / 8] ^= 1 << (bit % 8);
            }
            suite.case(
                &|| format!("{}: flip bits {flipped:?}", base.name),
                &b,
                must_fail,
            );
            for &bit in &flipped {
                b[bit / 8] ^= 1 << (bit % 8);
            }
        }
        total += suite.finish(base.name, 1000);
    }
    assert!(total >= 20_000, "{total} cases");
}

/// (b) Truncation to every length of the small files and to a sample of
/// the bunny's is reported as `Truncated`.
#[test]
fn corrupt_truncations() {
    let mut bases = small_bases();
    bases.push(bunny_base());
    let mut rng = Rng(200);
    let mut total = 0;
    for base in &bases {
        let mut suite = Suite::new(Probes::around(&base.bounds, 2));
        let len = base.bytes.len();
        let lengths: Vec<usize> = if len <= 16_384 {
            (0..len).collect()
        } else {
            let mut v: Vec<usize> = (0..400).map(|_| rng.below(len)).collect();
            v.extend([0, 1, HEADER_SIZE - 1, HEADER_SIZE, HEADER_SIZE + 1, len - 1]);
            v
        };
        for cut in lengths {
            suite.case(
                &|| format!("{}: truncated to {cut} of {len}", base.name),
                &base.bytes[..cut],
                |o| match o {
                    Outcome::Rejected(FormatError::Truncated { needed, got })
                        if *got == cut as u64 && *needed > *got =>
                    {
                        Ok(())
                    }
                    _ => Err("not reported as truncated".into()),
                },
            );
        }
        // Longer than the layout: trailing bytes are refused too.
        for extra in [1, 7, 64, 200] {
            let mut b = base.bytes.clone();
            b.resize(len + extra, 0);
            suite.case(
                &|| format!("{}: {extra} trailing zero bytes", base.name),
                &b,
                |o| match o {
                    Outcome::Rejected(FormatError::Header(_)) => Ok(()),
                    _ => Err("trailing bytes not refused".into()),
                },
            );
        }
        total += suite.finish(base.name, 300);
    }
    assert!(total >= 5_000, "{total} cases");
}

/// (c) Random byte overwrites anywhere are caught; overwrites of node words
/// and vertices with plausible values and all checksums repaired, accepted
/// or not, never make reading or traversal panic (these reach traversal of
/// odd but valid trees: moved splits, other leaf ranges, extreme
/// coordinates).
#[test]
fn corrupt_overwrites() {
    let mut bases = small_bases();
    bases.push(bunny_base());
    let mut rng = Rng(300);
    let mut total = 0;
    for base in &bases {
        let mut suite = Suite::new(Probes::around(&base.bounds, 3));
        let orig = &base.bytes;
        let len = orig.len();
        for _ in 0..600 {
            let mut b = orig.clone();
            for _ in 0..1 + rng.below(8) {
                let at = rng.below(len);
                b[at] = rng.next() as u8;
            }
            let changed = b != *orig;
            suite.case(&|| format!("{}: random overwrite", base.name), &b, |o| {
                if changed { must_fail(o) } else { Ok(()) }
            });
        }
        let n_words = section(orig, Section::Nodes).len() / 8;
        let n_idx32 = section(orig, Section::Idx32).len() / 4;
        let n_idx16 = section(orig, Section::Idx16).len() / 2;
        let n_tris = section(orig, Section::Triangles).len() / 12;
        let verts = section(orig, Section::Vertices);
        for _ in 0..600 {
            let mut b = orig.clone();
            for _ in 0..1 + rng.below(3) {
                if rng.chance(3) {
                    // A vertex coordinate: anything finite, extremes
                    // included.
                    let at = verts.start + 4 * rng.below(verts.len() / 4);
                    let v = match rng.below(4) {
                        0 => f32::MAX * (rng.unit() - 0.5),
                        1 => f32::MIN_POSITIVE * rng.unit(),
                        2 => (rng.unit() - 0.5) * 1e6,
                        _ => f32::from_bits(rng.next() as u32),
                    };
                    set_u32(&mut b, at, v.to_bits());
                } else {
                    let i = rng.below(n_words);
                    let w = plausible_word(&mut rng, i, n_words, n_idx32, n_idx16, n_tris);
                    set_word(&mut b, i, w);
                }
            }
            fix_all_crcs(&mut b);
            suite.case(
                &|| format!("{}: plausible edit, checksums repaired", base.name),
                &b,
                |o| match o {
                    Outcome::BadChecksum(_) => Err("checksums were repaired".into()),
                    _ => Ok(()),
                },
            );
        }
        // Header fields set to small or nearby values, header checksum
        // repaired.
        // (offset, 8 bytes wide): the counts, the section table, and the
        // 4-byte fields that the reader checks.
        let fields: Vec<(usize, bool)> = [
            H_WORDS,
            H_INNER,
            H_T_INNER,
            H_LEAVES,
            H_IDX32,
            H_IDX16,
            H_TRIANGLES,
            H_VERTICES,
        ]
        .into_iter()
        .chain((0..6).flat_map(|s| [H_TABLE + s * H_ENTRY, H_TABLE + s * H_ENTRY + 8]))
        .map(|f| (f, true))
        .chain(
            [H_MAX_DEPTH, H_FLAGS, H_PRESET]
                .into_iter()
                .chain((0..6).map(|k| H_BOUNDS + 4 * k))
                .map(|f| (f, false)),
        )
        .collect();
        for _ in 0..600 {
            let mut b = orig.clone();
            for _ in 0..1 + rng.below(3) {
                let (at, wide) = fields[rng.below(fields.len())];
                if wide {
                    let old = get_u64(&b, at);
                    let v = match rng.below(4) {
                        0 => old.wrapping_add(rng.below(130) as u64).wrapping_sub(65),
                        1 => rng.below(64) as u64,
                        2 => rng.next(),
                        _ => old ^ (1 << rng.below(64)),
                    };
                    set_u64(&mut b, at, v);
                } else {
                    let old = get_u32(&b, at);
                    let v = match rng.below(3) {
                        0 => old.wrapping_add(rng.below(5) as u32).wrapping_sub(2),
                        1 => (rng.unit() * 20.0 - 10.0).to_bits(),
                        _ => rng.next() as u32,
                    };
                    set_u32(&mut b, at, v);
                }
            }
            fix_header_crc(&mut b);
            suite.case(
                &|| format!("{}: header fields, checksum repaired", base.name),
                &b,
                no_check,
            );
        }
        total += suite.finish(base.name, 1500);
    }
    assert!(total >= 5_000, "{total} cases");
}

/// A node word likely to pass some of the reader's checks: a leaf with a
/// range inside the index arrays, an inner node with a forward child block,
/// a T-reference, or random bits.
fn plausible_word(
    rng: &mut Rng,
    i: usize,
    n_words: usize,
    n_idx32: usize,
    n_idx16: usize,
    n_tris: usize,
) -> u64 {
    let tri = rng.below(n_tris.max(1) + 2) as u32;
    match rng.below(6) {
        0 => {
            let start = rng.below(n_idx16 + 2);
            let count = rng.below((n_idx16 + 2).saturating_sub(start) + 1);
            node::encode_leaf16(count as u32, rng.below(2) as u16, start as u32)
        }
        1 => {
            let start = rng.below(n_idx32 + 2);
            let count = rng.below((n_idx32 + 2).saturating_sub(start) + 1);
            node::encode_leaf32(count as u32, start as u32)
        }
        2 => {
            let block = i + rng.below(n_words.saturating_sub(i) + 2);
            let pos = (rng.unit() - 0.25) * 12.0;
            node::encode_inner(rng.below(3) as u8, rng.chance(3), block as u32, pos)
        }
        3 => node::encode_tref(tri),
        4 => {
            // Keep the word's type and move its split or range a little.
            (rng.next() & 0xFFFF_FFFF_0000_0000) | (rng.below(256) as u64 & !0b111) | 0b011
        }
        _ => rng.next(),
    }
}

/// (d) Random byte strings: raw, and with a valid magic, version, byte
/// order and header checksum (so that they reach the later checks).
#[test]
fn corrupt_random_strings() {
    let mut rng = Rng(400);
    let mut suite = Suite::new(Probes::around(&Aabb::new(Vec3::ZERO, Vec3::splat(4.0)), 4));
    for _ in 0..1500 {
        let len = rng.below(3000);
        let b: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        suite.case(&|| format!("random {len} bytes"), &b, must_fail);
    }
    let template = &small_bases()[0].bytes;
    for _ in 0..1500 {
        let len = HEADER_SIZE + 64 * rng.below(40);
        let mut b: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        b[..16].copy_from_slice(&template[..16]);
        set_u32(&mut b, H_HEADER_SIZE, HEADER_SIZE as u32);
        if rng.chance(2) {
            // Plausible small counts.
            for f in [
                H_INNER,
                H_T_INNER,
                H_IDX32,
                H_IDX16,
                H_TRIANGLES,
                H_VERTICES,
            ] {
                set_u64(&mut b, f, rng.below(8) as u64);
            }
            let leaves = get_u64(&b, H_INNER) + get_u64(&b, H_T_INNER) + 1;
            set_u64(&mut b, H_LEAVES, leaves);
            let words = get_u64(&b, H_LEAVES) * 2 - 1 + get_u64(&b, H_T_INNER);
            set_u64(&mut b, H_WORDS, words);
        }
        fix_header_crc(&mut b);
        suite.case(&|| format!("forged header, {len} bytes"), &b, no_check);
    }
    suite.finish("random strings", 3000);
}

/// (e) Targeted edits, each with the specific error it must give. Header
/// edits repair the header checksum so that they reach the later checks;
/// node and section edits repair nothing, so `from_bytes` must refuse them
/// structurally (or, for pure data edits, `verify` by checksum).
#[test]
fn corrupt_targeted_edits() {
    let bases = small_bases();
    let mut suite = Suite::new(Probes::around(&bases[0].bounds, 5));
    for base in &bases {
        let orig = &base.bytes;
        let file = read(orig);
        let f = file.figures();
        let words: Vec<u64> = file.nodes().to_vec();
        let n = words.len();
        let decoded: Vec<NodeWord> = words.iter().map(|&w| node::decode(w).unwrap()).collect();
        // Inner nodes with their child blocks, leaves, T-references.
        let inners: Vec<(usize, bool, usize)> = decoded
            .iter()
            .enumerate()
            .filter_map(|(i, w)| match *w {
                NodeWord::Inner { t_ref, block, .. } => Some((i, t_ref, block as usize)),
                _ => None,
            })
            .collect();
        let leaves: Vec<usize> = (0..n)
            .filter(|&i| {
                matches!(
                    decoded[i],
                    NodeWord::Leaf16 { .. } | NodeWord::Leaf32 { .. }
                )
            })
            .collect();
        let trefs: Vec<usize> = (0..n)
            .filter(|&i| matches!(decoded[i], NodeWord::TRef { .. }))
            .collect();
        assert!(!inners.is_empty() && !leaves.is_empty());

        type Check = fn(&FormatError) -> bool;
        let mut cases: Vec<(String, Vec<u8>, Check)> = Vec::new();
        let mut add = |what: &str, edit: &dyn Fn(&mut Vec<u8>), check: Check| {
            let mut b = orig.clone();
            edit(&mut b);
            cases.push((what.to_string(), b, check));
        };
        let header = |at: usize, v: u64, wide: bool| {
            move |b: &mut Vec<u8>| {
                if wide {
                    set_u64(b, at, v);
                } else {
                    set_u32(b, at, v as u32);
                }
                fix_header_crc(b);
            }
        };

        // The first checks.
        add("bad magic", &|b| b[3] = b'X', |e| {
            matches!(e, FormatError::BadMagic)
        });
        add("empty", &|b| b.clear(), |e| {
            matches!(
                e,
                FormatError::Truncated {
                    needed: 384,
                    got: 0
                }
            )
        });
        add("100 bytes", &|b| b.truncate(100), |e| {
            matches!(
                e,
                FormatError::Truncated {
                    needed: 384,
                    got: 100
                }
            )
        });
        add(
            "one byte short",
            &|b| {
                b.pop();
            },
            |e| matches!(e, FormatError::Truncated { .. }),
        );
        add("version 2", &header(H_VERSION, 2, false), |e| {
            matches!(
                e,
                FormatError::Version {
                    expected: 1,
                    got: 2
                }
            )
        });
        add("version 0", &header(H_VERSION, 0, false), |e| {
            matches!(
                e,
                FormatError::Version {
                    expected: 1,
                    got: 0
                }
            )
        });
        add(
            "other byte order",
            &header(H_ENDIAN, 0x0D0C_0B0A, false),
            |e| matches!(e, FormatError::Endianness),
        );
        add(
            "header checksum off by one",
            &|b| {
                let c = get_u32(b, H_CRC);
                set_u32(b, H_CRC, c.wrapping_add(1));
            },
            |e| matches!(e, FormatError::HeaderChecksum { .. }),
        );
        add(
            "count edited, checksum not repaired",
            &|b| {
                set_u64(b, H_LEAVES, f.leaves + 1);
            },
            |e| matches!(e, FormatError::HeaderChecksum { .. }),
        );
        // Header fields out of range.
        add("header size 512", &header(H_HEADER_SIZE, 512, false), |e| {
            matches!(e, FormatError::Header(_))
        });
        add("unknown flag", &header(H_FLAGS, 2, false), |e| {
            matches!(e, FormatError::Header(_))
        });
        add("unknown preset", &header(H_PRESET, 9, false), |e| {
            matches!(e, FormatError::Header(_))
        });
        add(
            "NaN bound",
            &header(H_BOUNDS, f32::NAN.to_bits().into(), false),
            |e| matches!(e, FormatError::Header(_)),
        );
        add(
            "infinite bound",
            &header(H_BOUNDS + 20, f32::INFINITY.to_bits().into(), false),
            |e| matches!(e, FormatError::Header(_)),
        );
        add(
            "inverted bounds",
            &header(H_BOUNDS, 1e30f32.to_bits().into(), false),
            |e| matches!(e, FormatError::Header(_)),
        );
        add(
            "depth over MAX_DEPTH",
            &header(H_MAX_DEPTH, 101, false),
            |e| matches!(e, FormatError::Header(_)),
        );
        add("zero node words", &header(H_WORDS, 0, true), |e| {
            matches!(e, FormatError::Header(_))
        });
        add("node words + 1", &header(H_WORDS, f.words + 1, true), |e| {
            matches!(e, FormatError::Header(_))
        });
        add("leaves + 1", &header(H_LEAVES, f.leaves + 1, true), |e| {
            matches!(e, FormatError::Header(_))
        });
        add("inner + 1", &header(H_INNER, f.inner + 1, true), |e| {
            matches!(e, FormatError::Header(_))
        });
        add(
            "counts add up but not to the section",
            &|b| {
                set_u64(b, H_INNER, f.inner + 1);
                set_u64(b, H_LEAVES, f.leaves + 1);
                set_u64(b, H_WORDS, f.words + 2);
                fix_header_crc(b);
            },
            |e| {
                matches!(
                    e,
                    FormatError::Section {
                        section: "nodes",
                        ..
                    }
                )
            },
        );
        add(
            "a type I node counted as type II",
            &|b| {
                // Inner − 1 and t-inner + 1 keep leaves = inner + t-inner + 1
                // but add a T-reference word, which the node section lacks.
                set_u64(b, H_INNER, f.inner.wrapping_sub(1));
                set_u64(b, H_T_INNER, f.t_inner + 1);
                set_u64(b, H_WORDS, f.words + 1);
                fix_header_crc(b);
            },
            |e| {
                matches!(
                    e,
                    FormatError::Section {
                        section: "nodes",
                        ..
                    }
                )
            },
        );
        add(
            "triangles + 1",
            &header(H_TRIANGLES, f.triangles + 1, true),
            |e| {
                matches!(
                    e,
                    FormatError::Section {
                        section: "triangles",
                        ..
                    }
                )
            },
        );
        add("idx16 + 1", &header(H_IDX16, f.idx16 + 1, true), |e| {
            matches!(
                e,
                FormatError::Section {
                    section: "idx16",
                    ..
                }
            )
        });
        add(
            "vertices count - 1",
            &header(H_VERTICES, f.vertices - 1, true),
            |e| {
                matches!(
                    e,
                    FormatError::Section {
                        section: "vertices",
                        ..
                    }
                )
            },
        );
        add("2^40 triangles", &header(H_TRIANGLES, 1 << 40, true), |e| {
            matches!(e, FormatError::Header(_))
        });
        let flags = get_u32(orig, H_FLAGS);
        add(
            "reordered flag toggled",
            &header(H_FLAGS, u64::from(flags ^ 1), false),
            |e| {
                matches!(
                    e,
                    FormatError::Section {
                        section: "tri_map",
                        ..
                    }
                )
            },
        );
        add(
            "header depth below the tree's",
            &header(H_MAX_DEPTH, 0, false),
            |e| matches!(e, FormatError::Node { .. }),
        );
        // The section table.
        for s in Section::ALL {
            let e = H_TABLE + s as usize * H_ENTRY;
            let ofs = get_u64(orig, e);
            let name = s.name();
            add(
                &format!("{name} offset + 64"),
                &header(e, ofs + 64, true),
                |e| matches!(e, FormatError::Section { .. }),
            );
            add(
                &format!("{name} offset misaligned"),
                &header(e, ofs + 4, true),
                |e| matches!(e, FormatError::Section { .. }),
            );
            add(
                &format!("{name} offset into the header"),
                &header(e, 320, true),
                |e| matches!(e, FormatError::Section { .. }),
            );
            // The start of the last non-empty section before this one.
            if let Some(prev) = Section::ALL[..s as usize]
                .iter()
                .map(|&p| section(orig, p))
                .rfind(|r| !r.is_empty())
            {
                add(
                    &format!("{name} overlaps the previous section"),
                    &header(e, prev.start as u64, true),
                    |e| matches!(e, FormatError::Section { .. }),
                );
            }
            add(
                &format!("{name} offset near 2^64"),
                &header(e, u64::MAX - 63, true),
                |e| matches!(e, FormatError::Section { .. }),
            );
            add(
                &format!("{name} length + 8"),
                &header(e + 8, get_u64(orig, e + 8) + 8, true),
                |e| matches!(e, FormatError::Section { .. }),
            );
        }
        add("non-zero reserved header byte", &|b| b[380] = 1, |e| {
            matches!(e, FormatError::Header(_))
        });
        add("trailing byte", &|b| b.push(0), |e| {
            matches!(e, FormatError::Header(_))
        });
        if let Some(s) = Section::ALL
            .into_iter()
            .find(|&s| !section(orig, s).len().is_multiple_of(64))
        {
            let at = section(orig, s).end;
            let check: Check = match s {
                Section::Nodes => |e| {
                    matches!(
                        e,
                        FormatError::Section {
                            section: "nodes",
                            ..
                        }
                    )
                },
                Section::Idx32 => |e| {
                    matches!(
                        e,
                        FormatError::Section {
                            section: "idx32",
                            ..
                        }
                    )
                },
                Section::Idx16 => |e| {
                    matches!(
                        e,
                        FormatError::Section {
                            section: "idx16",
                            ..
                        }
                    )
                },
                Section::Vertices => |e| {
                    matches!(
                        e,
                        FormatError::Section {
                            section: "vertices",
                            ..
                        }
                    )
                },
                Section::Triangles => |e| {
                    matches!(
                        e,
                        FormatError::Section {
                            section: "triangles",
                            ..
                        }
                    )
                },
                Section::TriMap => |e| {
                    matches!(
                        e,
                        FormatError::Section {
                            section: "tri_map",
                            ..
                        }
                    )
                },
            };
            add("non-zero padding", &|b| b[at] = 0x80, check);
        }

        // Node words (nothing repaired).
        let node_err: Check = |e| matches!(e, FormatError::Node { .. });
        let with_block = |i: usize, block: usize| {
            let (axis, t_ref, pos) = match decoded[i] {
                NodeWord::Inner {
                    axis, t_ref, pos, ..
                } => (axis, t_ref, pos),
                _ => unreachable!(),
            };
            node::encode_inner(axis, t_ref, block as u32, pos)
        };
        let (root_block, last) = (inners[0].2, inners[inners.len() - 1]);
        add(
            "root's child block is itself",
            &|b| set_word(b, 0, with_block(0, 0)),
            node_err,
        );
        add(
            "child block past the end",
            &|b| set_word(b, 0, with_block(0, n - 1)),
            node_err,
        );
        add(
            "child block at 2^29 - 1",
            &|b| set_word(b, 0, with_block(0, (1 << 29) - 1)),
            node_err,
        );
        add(
            "child block shifted by one",
            &|b| set_word(b, 0, with_block(0, root_block + 1)),
            node_err,
        );
        if last.0 > 0 {
            add(
                "child block backwards",
                &|b| set_word(b, last.0, with_block(last.0, last.0 - 1)),
                node_err,
            );
            add(
                "child block pointing to itself",
                &|b| set_word(b, last.0, with_block(last.0, last.0)),
                node_err,
            );
            add(
                "child block pointing to the root",
                &|b| set_word(b, last.0, with_block(last.0, 0)),
                node_err,
            );
        }
        if inners.len() >= 2 {
            let (i, _, block) = inners[1];
            add(
                "two parents for one block",
                &|b| set_word(b, i, with_block(i, root_block)),
                node_err,
            );
            add(
                "child block skips a node",
                &|b| set_word(b, i, with_block(i, block + 1)),
                node_err,
            );
        }
        let leaf = leaves[0];
        add(
            "a T-reference where a child belongs",
            &|b| set_word(b, leaf, node::encode_tref(0)),
            node_err,
        );
        add(
            "the root is a T-reference",
            &|b| set_word(b, 0, node::encode_tref(0)),
            node_err,
        );
        let (i, ..) = inners[0];
        add(
            "type I and II swapped",
            &|b| set_word(b, i, words[i] ^ node::A_TYPE2),
            |e| matches!(e, FormatError::Node { .. } | FormatError::Header(_)),
        );
        assert_eq!(trefs.len() as u64, f.t_inner);
        for &t in &trefs {
            add(
                "T-reference replaced by a leaf",
                &|b| set_word(b, t, node::encode_leaf16(0, 0, 0)),
                node_err,
            );
            add(
                "T-reference to a triangle out of range",
                &|b| set_word(b, t, node::encode_tref(f.triangles as u32)),
                node_err,
            );
            add(
                "T-reference with unused bits",
                &|b| set_word(b, t, words[t] | 0x100),
                node_err,
            );
        }
        add(
            "NaN split",
            &|b| {
                set_word(
                    b,
                    0,
                    (u64::from(f32::NAN.to_bits()) << 32) | (words[0] & 0xFFFF_FFFF),
                )
            },
            node_err,
        );
        add(
            "infinite split",
            &|b| {
                set_word(
                    b,
                    0,
                    (u64::from(f32::NEG_INFINITY.to_bits()) << 32) | (words[0] & 0xFFFF_FFFF),
                )
            },
            node_err,
        );
        for mode in [0b10u64, 0b11] {
            add(
                &format!("leaf mode E = {mode:02b}"),
                &|b| set_word(b, leaf, (words[leaf] & !0b11000) | (mode << 3)),
                node_err,
            );
        }
        for &l in &leaves {
            match decoded[l] {
                NodeWord::Leaf32 { count, start } => {
                    let past = f.idx32 as u32 - start + 1;
                    add(
                        "4-byte leaf range past idx32",
                        &|b| set_word(b, l, node::encode_leaf32(past.max(count + 1), start)),
                        node_err,
                    );
                    add(
                        "4-byte leaf starting past idx32",
                        &|b| set_word(b, l, node::encode_leaf32(1, f.idx32 as u32)),
                        node_err,
                    );
                    add(
                        "4-byte leaf start near 2^32",
                        &|b| set_word(b, l, node::encode_leaf32(count.max(1), u32::MAX)),
                        node_err,
                    );
                    add(
                        "index of idx32 out of range",
                        &|b| {
                            let at = section(b, Section::Idx32).start + 4 * start as usize;
                            set_u32(b, at, f.triangles as u32);
                        },
                        |e| {
                            matches!(
                                e,
                                FormatError::Index {
                                    section: "idx32",
                                    ..
                                }
                            )
                        },
                    );
                }
                NodeWord::Leaf16 {
                    count,
                    upper,
                    start,
                } if count > 0 => {
                    add(
                        "2-byte leaf range past idx16",
                        &|b| {
                            set_word(
                                b,
                                l,
                                node::encode_leaf16(count, upper, f.idx16 as u32 - count + 1),
                            )
                        },
                        node_err,
                    );
                    add(
                        "2-byte leaf with upper bits out of range",
                        &|b| set_word(b, l, node::encode_leaf16(count, upper + 1, start)),
                        node_err,
                    );
                    add(
                        "index of idx16 out of range",
                        &|b| {
                            let at = section(b, Section::Idx16).start + 2 * start as usize;
                            b[at..at + 2].copy_from_slice(&[0xFF, 0xFF]);
                        },
                        |e| matches!(e, FormatError::Node { .. }),
                    );
                }
                _ => {}
            }
        }
        // Geometry.
        add(
            "vertex index out of range",
            &|b| {
                let at = section(b, Section::Triangles).start + 4;
                set_u32(b, at, f.vertices as u32);
            },
            |e| {
                matches!(
                    e,
                    FormatError::Index {
                        section: "triangles",
                        ..
                    }
                )
            },
        );
        add(
            "NaN vertex",
            &|b| {
                let at = section(b, Section::Vertices).start + 8;
                set_u32(b, at, f32::NAN.to_bits());
            },
            |e| {
                matches!(
                    e,
                    FormatError::Index {
                        section: "vertices",
                        ..
                    }
                )
            },
        );
        add(
            "infinite vertex",
            &|b| {
                let at = section(b, Section::Vertices).start;
                set_u32(b, at, f32::INFINITY.to_bits());
            },
            |e| {
                matches!(
                    e,
                    FormatError::Index {
                        section: "vertices",
                        ..
                    }
                )
            },
        );
        if file.is_reordered() {
            add(
                "tri_map repeats an id",
                &|b| {
                    let at = section(b, Section::TriMap).start;
                    let first = get_u32(b, at);
                    set_u32(b, at + 4, first);
                },
                |e| {
                    matches!(
                        e,
                        FormatError::Index {
                            section: "tri_map",
                            ..
                        }
                    )
                },
            );
            add(
                "tri_map id out of range",
                &|b| {
                    let at = section(b, Section::TriMap).start;
                    set_u32(b, at, f.triangles as u32);
                },
                |e| {
                    matches!(
                        e,
                        FormatError::Index {
                            section: "tri_map",
                            ..
                        }
                    )
                },
            );
        }

        // Pure data edits: structurally valid, caught by the checksums.
        let mut data_edits: Vec<(String, Vec<u8>, &'static str)> = Vec::new();
        let mut b = orig.clone();
        let at = section(&b, Section::Vertices).start;
        let v = f32::from_bits(get_u32(&b, at));
        set_u32(&mut b, at, (v + 1.0).to_bits());
        data_edits.push(("vertex moved".into(), b, "vertices"));
        let mut b = orig.clone();
        let (i, ..) = inners[0];
        let pos = match decoded[i] {
            NodeWord::Inner { pos, .. } => pos,
            _ => unreachable!(),
        };
        set_word(
            &mut b,
            i,
            (u64::from((pos + 0.5).to_bits()) << 32) | (words[i] & 0xFFFF_FFFF),
        );
        data_edits.push(("split moved".into(), b, "nodes"));
        let mut b = orig.clone();
        let at = section(&b, Section::Triangles).start;
        let (v0, v1) = (get_u32(&b, at), get_u32(&b, at + 4));
        set_u32(&mut b, at, v1);
        set_u32(&mut b, at + 4, v0);
        if v0 != v1 {
            data_edits.push(("triangle's vertices swapped".into(), b, "triangles"));
        }

        for (what, bytes, check) in cases {
            suite.case(&|| format!("{}: {what}", base.name), &bytes, |o| match o {
                Outcome::Rejected(e) if check(e) => Ok(()),
                _ => Err("not the expected error".into()),
            });
        }
        for (what, bytes, name) in data_edits {
            suite.case(&|| format!("{}: {what}", base.name), &bytes, |o| match o {
                Outcome::BadChecksum(FormatError::ChecksumMismatch { section, .. })
                    if *section == name =>
                {
                    Ok(())
                }
                _ => Err("not caught by the section checksum".into()),
            });
        }
    }
    // An unaligned buffer.
    let mut words = vec![0u64; bases[0].bytes.len() / 8 + 1];
    let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut words);
    bytes[1..=bases[0].bytes.len()].copy_from_slice(&bases[0].bytes);
    let unaligned = &bytes[1..=bases[0].bytes.len()];
    assert!(matches!(
        KdFile::from_bytes(unaligned),
        Err(FormatError::Misaligned)
    ));
    suite.finish("targeted edits", 200);
}

// ---------------------------------------------------------------------
// Atomic writes.
// ---------------------------------------------------------------------

/// `write_file` into a missing directory fails and creates nothing; over an
/// existing file it replaces the file whole (a map of the old one stays
/// readable); concurrent writes to one path all succeed and leave one of
/// the written files; no temporary file remains.
#[test]
fn atomic_writes() {
    let dir = fresh_temp_dir("atomic");
    let mut rng = Rng(500);
    let scenes: Vec<TriangleColumns> = (0..4)
        .map(|k| random_grid_scene(&mut rng, 10 + 5 * k, 4))
        .collect();
    let trees: Vec<TreeIr> = scenes.iter().map(std_tree).collect();
    let options = WriteOptions::default();

    let missing = dir.join("missing").join("a.kd");
    let err = format::write_file(&missing, &trees[0], &scenes[0], &options).unwrap_err();
    assert!(
        matches!(&err, FormatError::Io { path, .. } if *path == missing),
        "{err}"
    );
    assert!(!dir.join("missing").exists());
    assert!(dir_entries(&dir).is_empty());

    // A path that is a directory: the rename fails, the temporary goes.
    let sub = dir.join("sub");
    std::fs::create_dir(&sub).unwrap();
    std::fs::write(sub.join("keep"), b"x").unwrap();
    assert!(format::write_file(&sub, &trees[0], &scenes[0], &options).is_err());
    assert_eq!(dir_entries(&dir), ["sub"]);
    std::fs::remove_dir_all(&sub).unwrap();

    let path = dir.join("scene.kd");
    format::write_file(&path, &trees[0], &scenes[0], &options).unwrap();
    let old = KdFile::open(&path, true).unwrap();
    let old_bytes = old.as_bytes().to_vec();
    format::write_file(&path, &trees[1], &scenes[1], &options).unwrap();
    let new = KdFile::open(&path, true).unwrap();
    assert_eq!(new.figures().triangles, scenes[1].len() as u64);
    // The old map still shows the old file, intact.
    assert_eq!(old.as_bytes(), &old_bytes[..]);
    old.verify().unwrap();
    assert_eq!(old.figures().triangles, scenes[0].len() as u64);
    let ray = Ray::new(Vec3::splat(-1.0), Vec3::ONE);
    assert_eq!(
        trace::traverse(&old, &ray),
        trace::brute_force(&scenes[0], &ray)
    );
    assert_eq!(dir_entries(&dir), ["scene.kd"]);
    drop((old, new));

    // Concurrent writers of one path.
    let expected: Vec<Vec<u8>> = (0..4)
        .map(|k| format::write_to_vec(&trees[k], &scenes[k], &options).unwrap())
        .collect();
    std::thread::scope(|s| {
        for k in 0..4 {
            let (path, tree, scene) = (&path, &trees[k], &scenes[k]);
            s.spawn(move || {
                for _ in 0..10 {
                    format::write_file(path, tree, scene, &WriteOptions::default()).unwrap();
                }
            });
        }
    });
    let last = std::fs::read(&path).unwrap();
    assert!(expected.contains(&last));
    KdFile::open(&path, true).unwrap();
    assert_eq!(dir_entries(&dir), ["scene.kd"]);

    // A path without a file name is refused.
    assert!(format::write_file(Path::new("/"), &trees[0], &scenes[0], &options).is_err());
    std::fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------
// The golden file.
// ---------------------------------------------------------------------

/// How the golden file was made: the bunny, the SAH tree of the sweep
/// builder with the default costs and a depth limit of 16 (to keep the file
/// small), type II nodes made by `hoist` (seed 2024, hoisted triangles
/// sometimes removed from the leaves below), reordered; the header records
/// the costs, the depth limit and the `custom` preset.
fn golden_inputs() -> (TriangleColumns, TreeIr, WriteOptions) {
    let scene = load_scene("bunny_npm.obj");
    let mut config = BuildConfig::default();
    config.sah.max_depth = Some(GOLDEN_DEPTH_LIMIT);
    let std = build::build(&scene, &config, Builder::Sweep, None).unwrap();
    let (tree, _) = hoist(&std, &scene, 2024, true);
    let options = WriteOptions {
        reorder: true,
        config: FileConfig {
            k_t: config.sah.k_t,
            k_i: config.sah.k_i,
            lambda_empty: config.sah.lambda_empty,
            depth_limit: GOLDEN_DEPTH_LIMIT,
            preset: Preset::Custom,
            ..FileConfig::default()
        },
    };
    (scene, tree, options)
}

const GOLDEN_DEPTH_LIMIT: u32 = 16;

fn golden_path() -> PathBuf {
    manifest_dir().join("tests/golden/bunny_npm.kd")
}

/// Rewrites `tests/golden/bunny_npm.kd`. Run only on purpose, when the
/// format changes (with a new version number):
/// `cargo test --release --test format -- --ignored regenerate_golden`.
#[test]
#[ignore]
fn regenerate_golden() {
    let (scene, tree, options) = golden_inputs();
    format::write_file(&golden_path(), &tree, &scene, &options).unwrap();
    let file = KdFile::open(&golden_path(), true).unwrap();
    eprintln!(
        "wrote {} ({} bytes): {:?}, max depth {}",
        golden_path().display(),
        file.as_bytes().len(),
        file.figures(),
        file.max_depth()
    );
}

/// The committed golden file (see `tests/golden/README.md`) still loads,
/// verifies, has the figures it was written with, and traces exactly like
/// brute force on the scene re-loaded from the OBJ: files written by
/// earlier builds stay readable.
#[test]
fn golden_file_still_loads() {
    let bytes = std::fs::read(golden_path()).unwrap();
    assert_eq!(bytes.len(), GOLDEN_SIZE);
    let file = KdFile::from_bytes(aligned_copy(&bytes)).unwrap();
    file.verify().unwrap();
    assert_eq!(file.figures(), GOLDEN_FIGURES);
    assert_eq!(file.max_depth(), GOLDEN_MAX_DEPTH);
    assert!(file.is_reordered());
    let scene = load_scene("bunny_npm.obj");
    let c = file.config();
    assert_eq!((c.k_t, c.k_i, c.lambda_empty), (15.0, 20.0, 0.8));
    assert_eq!(c.depth_limit, GOLDEN_DEPTH_LIMIT);
    assert_eq!(c.preset, Preset::Custom);
    assert_eq!(file.bounds(), scene.bounds());
    // A fan of rays from a grid of points around the bunny towards its
    // centre, and along the axes.
    let b = scene.bounds();
    let (lo, ext) = (b.min - b.extent() * 0.25, b.extent() * 1.5);
    let centre = b.center();
    let mut rays = Vec::new();
    for i in 0..6 {
        for j in 0..6 {
            for k in 0..6 {
                let o = lo + ext * Vec3::new(i as f32, j as f32, k as f32) / 5.0;
                rays.push(Ray::new(o, centre - o));
                rays.push(Ray::new(o, Vec3::X));
                rays.push(Ray::new(o, -Vec3::Y));
                rays.push(Ray::new(o, Vec3::Z));
            }
        }
    }
    let mut hits = 0;
    for ray in &rays {
        let want = trace::brute_force(&scene, ray);
        hits += usize::from(want.is_hit());
        assert_eq!(trace::traverse(&file, ray), want, "ray {ray:?}");
    }
    assert!(hits > rays.len() / 10, "{hits} hits");
    let mut rng = Rng(600);
    for rays in packets_at(&b, &mut rng, 8) {
        let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(&scene, r)).collect();
        for level in SimdLevel::available() {
            let mut got = [Hit::MISS; 16];
            PacketTracer::with_level(&file, level).closest_hit_4x4(&rays, &mut got);
            assert_eq!(got.to_vec(), want, "{level:?}");
        }
    }
}

// The golden file's size and figures, as written by `regenerate_golden`.
const GOLDEN_SIZE: usize = 170_368;
const GOLDEN_MAX_DEPTH: u32 = 16;
const GOLDEN_FIGURES: format::TreeFigures = format::TreeFigures {
    inner: 1721,
    t_inner: 1852,
    leaves: 3574,
    idx32: 0,
    idx16: 8525,
    triangles: 3674,
    vertices: 1839,
    words: 8999,
};
