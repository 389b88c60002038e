//! The `.kd` file format, written and read back: the tree, the leaf modes,
//! type II nodes and T-references survive, and traversal of the file
//! equals traversal of the tree and brute force; atomic writes.

mod common;

use common::kd::*;
use common::*;
use glam::Vec3;
use proptest::prelude::*;
use slimkd::format::node::{self, NodeWord};
use slimkd::format::{self, FormatError, KdFile, WriteOptions};
use slimkd::geom::Ray;
use slimkd::scene::TriangleColumns;
use slimkd::trace;
use slimkd::tree::{Node, NodeId, TreeIr, TriId};
use std::path::Path;

// ---------------------------------------------------------------------
// Round trips, type II nodes included.
// ---------------------------------------------------------------------

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
            let file = KdFile::open(&path, slimkd::format::Check::Verify).unwrap();
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

/// An inner node whose two children are both empty (a hoisted triangle
/// above two empty leaves) keeps its left child as an empty leaf word and
/// says its right child is empty (slot field 0); the tree round-trips and
/// traces as brute force does, at the root's left and right.
#[test]
fn an_inner_node_with_two_empty_children_round_trips() {
    let scene = strip_scene(3);
    let inner = |pos: f32, right: u32, t_ref: Option<u32>| Node::Inner {
        axis: 0,
        pos,
        right: NodeId(right),
        t_ref: t_ref.map(TriId),
    };
    let empty = Node::Leaf { start: 0, count: 0 };
    let tree = TreeIr {
        bounds: scene.bounds(),
        nodes: vec![
            inner(0.75, 4, None),
            inner(0.25, 3, Some(0)),
            empty,
            empty,
            inner(1.75, 6, None),
            Node::Leaf { start: 0, count: 1 },
            inner(2.25, 8, Some(2)),
            Node::Leaf { start: 1, count: 0 },
            Node::Leaf { start: 1, count: 0 },
        ],
        leaf_tris: vec![TriId(1)],
    };
    tree.validate(&scene).unwrap();
    let mut rng = Rng(9);
    let mut rays = strip_rays(&scene, &mut rng, 40);
    rays.extend(rays_at(&scene.bounds(), &mut rng, 40));
    let packets = packets_at(&scene.bounds(), &mut rng, 4);
    assert!(
        rays.iter()
            .filter(|r| trace::brute_force(&scene, r).is_hit())
            .count()
            > 20
    );
    for reorder in [false, true] {
        let file = read(&write(&tree, &scene, reorder));
        assert_eq!(file_shape(&file), ir_shape(&tree));
        assert_figures(&file, &tree, &scene);
        let f = file.figures();
        // Two both-empty nodes: each keeps one empty leaf word.
        assert_eq!((f.leaves, f.implicit_empty, f.one_leaves), (5, 2, 1));
        let words: Vec<NodeWord> = file
            .nodes()
            .iter()
            .map(|&w| node::decode(w).unwrap())
            .collect();
        let both_empty: Vec<usize> = (0..words.len())
            .filter(|&i| {
                matches!(
                    words[i],
                    NodeWord::Inner {
                        t_ref: true,
                        right: 0,
                        ..
                    }
                ) && words[i + 2] == NodeWord::Leaf32 { count: 0, start: 0 }
            })
            .collect();
        assert_eq!(both_empty.len(), 2, "{words:?}");
        assert_all_agree(&tree, &scene, &file, &rays, &packets);
    }
}

/// An empty leaf costs no word: the node section holds `inner +
/// 2·t_inner + leaves − implicit_empty` words, and the empty leaves
/// without a word are all the empty leaves but the left children of the
/// nodes whose two children are empty (the hoisted bunny has both kinds).
#[test]
fn an_empty_leaf_costs_no_word() {
    let scene = load_scene("bunny_npm.obj");
    let std = std_tree(&scene);
    let (hoisted, _) = hoist(&std, &scene, 7, true);
    let mut saw_both_empty = false;
    for tree in [&std, &hoisted] {
        let is_empty = |i: usize| matches!(tree.nodes[i], Node::Leaf { count: 0, .. });
        let n_empty = (0..tree.nodes.len()).filter(|&i| is_empty(i)).count() as u64;
        let both_empty = (0..tree.nodes.len())
            .filter(|&i| match tree.nodes[i] {
                Node::Inner { right, .. } => is_empty(i + 1) && is_empty(right.0 as usize),
                Node::Leaf { .. } => false,
            })
            .count() as u64;
        saw_both_empty |= both_empty > 0;
        let file = read(&write(tree, &scene, true));
        let f = file.figures();
        assert!(n_empty > 100, "{n_empty} empty leaves");
        assert_eq!(f.implicit_empty, n_empty - both_empty);
        assert_eq!(
            f.words,
            f.inner + 2 * f.t_inner + f.leaves - f.implicit_empty
        );
        assert_eq!(file.nodes().len() as u64, f.words);
        // The walk meets exactly that many children without a word.
        let mut wordless = 0;
        walk_file(&file, |i, _| wordless += u64::from(i.is_none()));
        assert_eq!(wordless, f.implicit_empty);
    }
    assert!(
        saw_both_empty,
        "the hoisted bunny has a node with two empty children"
    );
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
    let old = KdFile::open(&path, slimkd::format::Check::Verify).unwrap();
    let old_bytes = old.as_bytes().to_vec();
    format::write_file(&path, &trees[1], &scenes[1], &options).unwrap();
    let new = KdFile::open(&path, slimkd::format::Check::Verify).unwrap();
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
    KdFile::open(&path, slimkd::format::Check::Verify).unwrap();
    assert_eq!(dir_entries(&dir), ["scene.kd"]);

    // A path without a file name is refused.
    assert!(format::write_file(Path::new("/"), &trees[0], &scenes[0], &options).is_err());
    std::fs::remove_dir_all(&dir).unwrap();
}
