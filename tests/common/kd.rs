//! Helpers of the `.kd` format tests (`format_roundtrip`, `format_limits`,
//! `format_corrupt`, `format_golden`): header offsets, byte fields and
//! checksums, a deterministic generator, scenes, rays and trees made for
//! them, and the checks that a file holds a tree.

use super::columns;
use glam::Vec3;
use proptest::prelude::*;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::node::{self, NodeWord};
use slimkd::format::{self, KdFile, Section, WriteOptions, aligned_copy};
use slimkd::geom::{Aabb, Ray, clip_triangle};
use slimkd::scene::TriangleColumns;
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{self, ClosestHit, Hit, TreeTracer};
use slimkd::tree::{Node, NodeId, TreeIr, TriId};
use std::ops::Range;
use std::path::Path;

// Header field offsets (see the table in `slimkd::format`).
pub const H_VERSION: usize = 8;
pub const H_ENDIAN: usize = 12;
pub const H_HEADER_SIZE: usize = 16;
pub const H_FLAGS: usize = 20;
pub const H_PRESET: usize = 52;
pub const H_MAX_DEPTH: usize = 68;
pub const H_WORDS: usize = 72;
pub const H_INNER: usize = 80;
pub const H_T_INNER: usize = 88;
pub const H_LEAVES: usize = 96;
pub const H_IDX32: usize = 104;
pub const H_IDX16: usize = 112;
pub const H_TRIANGLES: usize = 120;
pub const H_VERTICES: usize = 128;
pub const H_BOUNDS: usize = 136;
pub const H_TABLE: usize = 192;
pub const H_ENTRY: usize = 24;
pub const H_CRC: usize = 336;
/// After the checksummed part: the empty leaves without a word, and the
/// one-triangle leaves (u64 each).
pub const H_IMPLICIT_EMPTY: usize = 340;
pub const H_ONE_LEAVES: usize = 348;

// ---------------------------------------------------------------------
// Small helpers: a deterministic random generator, byte fields, sections.
// ---------------------------------------------------------------------

/// SplitMix64: a small deterministic generator, so that every case of the
/// suite is the same on every run.
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A number in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    /// A number in `[0, 1)`.
    pub fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }

    pub fn chance(&mut self, one_in: usize) -> bool {
        self.below(one_in) == 0
    }
}

pub fn get_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

pub fn set_u32(b: &mut [u8], at: usize, v: u32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

pub fn get_u64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

pub fn set_u64(b: &mut [u8], at: usize, v: u64) {
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
}

/// Recomputes the header checksum, so that a header edit reaches the checks
/// after it.
pub fn fix_header_crc(b: &mut [u8]) {
    let crc = crc32fast::hash(&b[..H_CRC]);
    set_u32(b, H_CRC, crc);
}

/// The byte range of a section, as the section table states it.
pub fn section(b: &[u8], s: Section) -> Range<usize> {
    let e = H_TABLE + s as usize * H_ENTRY;
    let ofs = get_u64(b, e) as usize;
    ofs..ofs + get_u64(b, e + 8) as usize
}

/// Recomputes every section checksum and then the header checksum, so that
/// a file whose structure is still valid also passes `verify`.
pub fn fix_all_crcs(b: &mut [u8]) {
    for s in Section::ALL {
        let crc = crc32fast::hash(&b[section(b, s)]);
        set_u32(b, H_TABLE + s as usize * H_ENTRY + 16, crc);
    }
    fix_header_crc(b);
}

pub fn set_word(b: &mut [u8], i: usize, w: u64) {
    let at = section(b, Section::Nodes).start + 8 * i;
    set_u64(b, at, w);
}

pub fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

pub fn load_scene(name: &str) -> TriangleColumns {
    slimkd::scene::load_obj(&manifest_dir().join("scenes").join(name))
        .unwrap()
        .0
}

pub fn write(tree: &TreeIr, scene: &TriangleColumns, reorder: bool) -> Vec<u8> {
    let options = WriteOptions {
        reorder,
        ..Default::default()
    };
    format::write_to_vec(tree, scene, &options).unwrap()
}

/// Reads bytes that must be a valid file, checksums included.
pub fn read(bytes: &[u8]) -> KdFile<format::AlignedBytes> {
    let file = KdFile::from_bytes(aligned_copy(bytes)).unwrap();
    file.verify().unwrap();
    file
}

pub fn std_tree(scene: &TriangleColumns) -> TreeIr {
    build::build(scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap()
}

// ---------------------------------------------------------------------
// Scenes, rays and trees made for these tests.
// ---------------------------------------------------------------------

/// `n` small triangles: integer vertices in a unit cube placed at an
/// integer point of `[0, g]³`, so that the SAH tree has many levels.
pub fn random_small_scene(rng: &mut Rng, n: usize, g: usize) -> TriangleColumns {
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
pub fn random_grid_scene(rng: &mut Rng, n: usize, g: usize) -> TriangleColumns {
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
pub fn fan_packet(origin: Vec3, target: Vec3, step: f32, axis: usize) -> [Ray; 16] {
    std::array::from_fn(|i| {
        let mut t = target;
        t[(axis + 1) % 3] += (i % 4) as f32 * step;
        t[(axis + 2) % 3] += (i / 4) as f32 * step;
        let d = t - origin;
        Ray::new(origin, if d == Vec3::ZERO { Vec3::X } else { d })
    })
}

pub fn lerp(a: Vec3, b: Vec3, rng: &mut Rng) -> Vec3 {
    a + (b - a) * Vec3::new(rng.unit(), rng.unit(), rng.unit())
}

/// Rays from around `bounds` (30% margin) towards points inside it.
pub fn rays_at(bounds: &Aabb, rng: &mut Rng, n: usize) -> Vec<Ray> {
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
pub fn packets_at(bounds: &Aabb, rng: &mut Rng, n: usize) -> Vec<[Ray; 16]> {
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
pub enum Shape {
    Inner {
        axis: u8,
        pos: u32,
        t_ref: Option<u32>,
    },
    /// The leaf's input ids, sorted.
    Leaf(Vec<u32>),
}

/// The in-memory tree in pre-order.
pub fn ir_shape(tree: &TreeIr) -> Vec<Shape> {
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

/// Visits the file's nodes in pre-order (left child first), with their
/// slots; an empty child without a word is visited as `(None, an empty
/// Leaf32)`. T-references are not visited (their inner node is).
pub fn walk_file<D: AsRef<[u8]>>(file: &KdFile<D>, mut visit: impl FnMut(Option<usize>, NodeWord)) {
    let words = file.nodes();
    let mut stack = vec![Some(0u32)];
    while let Some(i) = stack.pop() {
        let Some(i) = i else {
            visit(None, NodeWord::Leaf32 { count: 0, start: 0 });
            continue;
        };
        let w = node::decode(words[i as usize]).unwrap();
        visit(Some(i as usize), w);
        if let NodeWord::Inner { t_ref, right, .. } = w {
            let (l, r) = node::children(i, t_ref, right);
            stack.push(r);
            stack.push(l);
        }
    }
}

/// The file's tree in pre-order (left child first), in input numbering.
pub fn file_shape<D: AsRef<[u8]>>(file: &KdFile<D>) -> Vec<Shape> {
    let words = file.nodes();
    let mut out = Vec::new();
    walk_file(file, |i, w| match w {
        NodeWord::Inner {
            axis, t_ref, pos, ..
        } => {
            let i = i.unwrap();
            let tri = t_ref.then(|| match node::decode(words[i + 1]) {
                Ok(NodeWord::TRef { tri }) => file.input_id(tri),
                other => panic!("node {i}: expected a T-reference, got {other:?}"),
            });
            out.push(Shape::Inner {
                axis,
                pos: pos.to_bits(),
                t_ref: tri,
            });
        }
        NodeWord::Leaf32 { .. } | NodeWord::Leaf16 { .. } | NodeWord::Leaf1 { .. } => {
            let mut ids = Vec::new();
            file.leaf(w).for_each(|t| ids.push(file.input_id(t)));
            ids.sort_unstable();
            out.push(Shape::Leaf(ids));
        }
        NodeWord::TRef { .. } => panic!("node {i:?}: a T-reference where a child belongs"),
    });
    out
}

/// The leaf words of a file in pre-order (not the empty leaves without a
/// word).
pub fn file_leaf_words<D: AsRef<[u8]>>(file: &KdFile<D>) -> Vec<NodeWord> {
    let mut out = Vec::new();
    walk_file(file, |i, w| {
        if i.is_some() && !matches!(w, NodeWord::Inner { .. }) {
            out.push(w);
        }
    });
    out
}

/// Asserts that scalar traversal of the tree and of the file, and packet
/// traversal of both at every SIMD level, return brute force's hit.
pub fn assert_all_agree<D: AsRef<[u8]> + Sync>(
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

/// What the writer makes of a tree's leaves: `(empty leaves without a
/// word, one-triangle leaves)`. Every empty leaf but an empty root and the
/// left child of an inner node whose two children are both empty goes
/// without a word.
pub fn ir_leaf_counts(tree: &TreeIr) -> (u64, u64) {
    let empty = |i: usize| matches!(tree.nodes.get(i), Some(Node::Leaf { count: 0, .. }));
    let (mut implicit, mut ones) = (0, 0);
    for (i, n) in tree.nodes.iter().enumerate() {
        match *n {
            Node::Inner { right, .. } => {
                let (l, r) = (empty(i + 1), empty(right.0 as usize));
                implicit += u64::from(l) + u64::from(r) - u64::from(l && r);
            }
            Node::Leaf { count, .. } => ones += u64::from(count == 1),
        }
    }
    (implicit, ones)
}

/// Asserts the counts a file reports against the tree it was written from:
/// an empty leaf costs no word ([`ir_leaf_counts`]), a one-triangle leaf no
/// index entry.
pub fn assert_figures<D: AsRef<[u8]>>(file: &KdFile<D>, tree: &TreeIr, scene: &TriangleColumns) {
    let f = file.figures();
    let t_inner = tree.n_t_inner() as u64;
    let (implicit, ones) = ir_leaf_counts(tree);
    assert_eq!(f.t_inner, t_inner);
    assert_eq!(f.inner, tree.n_inner() as u64 - t_inner);
    assert_eq!(f.leaves, tree.n_leaves() as u64);
    assert_eq!(f.implicit_empty, implicit);
    assert_eq!(f.one_leaves, ones);
    assert_eq!(
        f.words,
        f.inner + f.t_inner + f.leaves + f.t_inner - f.implicit_empty
    );
    assert_eq!(f.words, file.nodes().len() as u64);
    assert_eq!(f.nodes(), tree.nodes.len() as u64);
    assert_eq!(f.idx32, file.idx32().len() as u64);
    assert_eq!(f.idx16, file.idx16().len() as u64);
    assert_eq!(
        f.idx32 + f.idx16 + f.one_leaves,
        tree.leaf_tris.len() as u64
    );
    assert_eq!(f.references(), tree.leaf_tris.len() as u64);
    assert_eq!(f.triangles, scene.len() as u64);
    assert_eq!(f.vertices, scene.positions().len() as u64);
    assert_eq!(
        f.tree_bytes(),
        8 * (f.nodes() + f.t_inner - f.implicit_empty) + 4 * f.idx32 + 2 * f.idx16
    );
    assert_eq!(f.tree_bytes(), 8 * f.words + 4 * f.idx32 + 2 * f.idx16);
    assert_eq!(file.bounds(), tree.bounds);
}

/// Where each subtree ends in pre-order: node `i`'s subtree is
/// `i..end[i]`.
pub fn subtree_ends(tree: &TreeIr) -> Vec<usize> {
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
pub fn hoist(tree: &TreeIr, scene: &TriangleColumns, seed: u64, remove: bool) -> (TreeIr, usize) {
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
pub fn strip_scene(n: u32) -> TriangleColumns {
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
pub fn strip_tree(scene: &TriangleColumns, leaves: &[Vec<u32>], caterpillar: bool) -> TreeIr {
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
pub fn strip_rays(scene: &TriangleColumns, rng: &mut Rng, n: usize) -> Vec<Ray> {
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

pub fn packet_strategy(g: i32) -> impl Strategy<Value = [Ray; 16]> {
    let coord = move || (-2..=2 * g + 2).prop_map(|k| k as f32 * 0.5);
    let point = move || (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    (point(), point(), 1..4i32, 0..3usize)
        .prop_map(|(o, t, step, axis)| fan_packet(o, t, 0.5 * step as f32, axis))
}

/// The file `b` with its sections replaced by `sections` (in
/// [`Section::ALL`] order) and laid out as the writer lays them out (each
/// 64-byte aligned after the previous one, zero padding); the header's
/// section table and every checksum follow, the counts do not.
pub fn with_sections(b: &[u8], sections: &[Vec<u8>; 6]) -> Vec<u8> {
    let mut out = b[..format::HEADER_SIZE].to_vec();
    for s in Section::ALL {
        let ofs = out.len().next_multiple_of(64);
        out.resize(ofs, 0);
        out.extend_from_slice(&sections[s as usize]);
        let e = H_TABLE + s as usize * H_ENTRY;
        set_u64(&mut out, e, ofs as u64);
        set_u64(&mut out, e + 8, sections[s as usize].len() as u64);
    }
    out.resize(out.len().next_multiple_of(64), 0);
    fix_all_crcs(&mut out);
    out
}

/// The file `b` with `words` appended to its node section (the node count
/// raised to match, every checksum repaired; the other counts as they
/// were).
pub fn with_words_appended(b: &[u8], words: &[u64]) -> Vec<u8> {
    let mut sections = Section::ALL.map(|s| b[section(b, s)].to_vec());
    for w in words {
        sections[Section::Nodes as usize].extend_from_slice(&w.to_le_bytes());
    }
    let mut out = b.to_vec();
    let n = get_u64(b, H_WORDS);
    set_u64(&mut out, H_WORDS, n + words.len() as u64);
    with_sections(&out, &sections)
}
