//! The `.kd` file format, written and read back: the tree, the leaf modes,
//! type II nodes and T-references survive, and traversal of the file
//! equals traversal of the tree and brute force; atomic writes.

mod common;

use common::kd::*;
use common::*;
use glam::Vec3;
use proptest::prelude::*;
use slimkd::format::{self, FormatError, KdFile, WriteOptions};
use slimkd::geom::Ray;
use slimkd::scene::TriangleColumns;
use slimkd::trace;
use slimkd::tree::TreeIr;
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
