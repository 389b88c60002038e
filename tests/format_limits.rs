//! The `.kd` file format's limits: the leaf modes at their boundaries, the
//! largest leaf, the depth limit, and the trees the writer refuses.

mod common;

use common::kd::*;
use common::*;
use glam::Vec3;
use slimkd::format::node::{self, LEAF16_LIMIT, MAX_LEAF32, NodeWord};
use slimkd::format::{self, FormatError, HEADER_SIZE, KdFile, Section, WriteOptions};
use slimkd::geom::Ray;
use slimkd::trace;
use slimkd::tree::{MAX_DEPTH, Node, NodeId, TreeIr, TriId};
use std::panic::{AssertUnwindSafe, catch_unwind};

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
        67_647..67_649,
        67_649..67_650,
        67_650..69_698,
    ];
    let scene = strip_scene(69_698);
    let leaves: Vec<Vec<u32>> = ranges.iter().map(|r| r.clone().collect()).collect();
    let tree = strip_tree(&scene, &leaves, false);
    tree.validate(&scene).unwrap();
    let file = read(&write(&tree, &scene, false));
    // (index bytes, count, upper bits); a one-triangle leaf has no index
    // entry, whatever its id.
    let modes: Vec<(u8, u32, u32)> = file_leaf_words(&file)
        .into_iter()
        .map(|w| match w {
            NodeWord::Leaf32 { count, .. } => (4, count, 0),
            NodeWord::Leaf16 { count, upper, .. } => (2, count, u32::from(upper)),
            NodeWord::Leaf1 { tri } => (0, 1, tri >> 16),
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(
        modes,
        [
            (4, 63_000, 0),
            (2, 2000, 0),
            (4, 600, 0),
            (2, 2047, 1),
            (2, 2, 1),
            (0, 1, 1),
            (4, 2048, 0),
        ]
    );
    let f = file.figures();
    assert_eq!(f.idx16, 2000 + 2047 + 2);
    assert_eq!(f.idx32, 63_000 + 600 + 2048);
    assert_eq!(f.one_leaves, 1);
    assert_eq!(file_shape(&file), ir_shape(&tree));
    assert_figures(&file, &tree, &scene);
    let mut rng = Rng(4);
    let mut rays = strip_rays(&scene, &mut rng, 40);
    // Aim some rays at the leaves with upper bits 1.
    for t in [
        65_535u32, 65_536, 65_537, 67_646, 67_647, 67_648, 67_649, 67_650, 69_697,
    ] {
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
    let file = KdFile::from_bytes_checked(make(node::encode_leaf32(MAX_LEAF32, 0))).unwrap();
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
    // One index past the end of idx32: the file opens (the open reads no
    // node) and the leaf reads as empty, so a ray through it misses; the
    // full check refuses it.
    let file = KdFile::from_bytes(make(node::encode_leaf32(MAX_LEAF32, 1))).unwrap();
    let w = node::decode(file.nodes()[0]).unwrap();
    assert!(file.leaf(w).is_empty());
    assert!(!trace::traverse(&file, &ray).is_hit());
    assert!(matches!(
        file.validate(),
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
    // The tree with fields of its root (an inner node) edited.
    type RootEdit = dyn Fn(&mut u8, &mut f32, &mut NodeId, &mut Option<TriId>);
    let root = |f: &RootEdit| {
        edit(&|t| {
            if let Node::Inner {
                axis,
                pos,
                right,
                t_ref,
            } = &mut t.nodes[0]
            {
                f(axis, pos, right, t_ref);
            }
        })
    };
    let cases: Vec<(&str, TreeIr)> = vec![
        ("no nodes", edit(&|t| t.nodes.clear())),
        ("axis 3", root(&|axis, _, _, _| *axis = 3)),
        ("NaN split", root(&|_, pos, _, _| *pos = f32::NAN)),
        (
            "right child out of range",
            root(&|_, _, right, _| *right = NodeId(9)),
        ),
        (
            "right child is the node itself",
            root(&|_, _, right, _| *right = NodeId(0)),
        ),
        (
            "hoisted triangle out of range",
            root(&|_, _, _, t_ref| *t_ref = Some(TriId(4))),
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
