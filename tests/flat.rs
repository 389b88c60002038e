//! Flat and near-flat scenes: overlapping triangles in one plane, the same
//! with the plane jittered, and a fan of slivers (an `f` line of many
//! corners). In a flat cell a split's children's surface areas sum to the
//! cell's, so without the flat-split rule of `build::sah` every builder
//! duplicates such triangles at every level down to the depth limit
//! (27,609 references per triangle for 1,000 random coplanar triangles).
//! Each test asserts a bound on the references per triangle, and that every
//! builder makes the same tree (`common::build_checked`).

mod common;

use common::*;
use glam::Vec3;
use slimkd::build::level::LevelOptions;
use slimkd::build::{self, BuildConfig};
use slimkd::geom::Ray;
use slimkd::scene::{self, TriangleColumns};
use slimkd::tree::TreeIr;

/// A fixed-seed generator of numbers in `[0, 1)` (xorshift64).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// `n` triangles with random corners in the unit square, at `z = 0`, or
/// with every `z` jittered by up to `jitter`.
fn random_in_plane(n: usize, jitter: f32) -> Vec<[Vec3; 3]> {
    let mut rng = Rng(0x2545_F491_4F6C_DD1D);
    (0..n)
        .map(|_| {
            [0; 3].map(|_| {
                let (x, y) = (rng.next(), rng.next());
                let z = (rng.next() - 0.5) * jitter;
                Vec3::new(x, y, z)
            })
        })
        .collect()
}

/// A face of `corners` corners on the unit circle in `z = 0`, loaded from
/// one OBJ `f` line (which the loader triangulates as a fan from its first
/// corner).
fn fan(corners: usize) -> TriangleColumns {
    let mut obj = String::new();
    for i in 0..corners {
        let a = std::f64::consts::TAU * i as f64 / corners as f64;
        obj.push_str(&format!("v {:.9} {:.9} 0\n", a.cos(), a.sin()));
    }
    obj.push('f');
    for i in 1..=corners {
        obj.push_str(&format!(" {i}"));
    }
    obj.push('\n');
    scene::load_obj_bytes(std::path::Path::new("fan.obj"), obj.as_bytes())
        .expect("the fan loads")
        .0
}

fn refs_per_triangle(tree: &TreeIr, scene: &TriangleColumns) -> f64 {
    tree.leaf_tris.len() as f64 / scene.len() as f64
}

/// Vertical rays through a grid of points of the unit square, both ways,
/// and a few slanted ones.
fn rays_through_plane() -> Vec<Ray> {
    let mut rays = Vec::new();
    for i in 0..24 {
        for j in 0..24 {
            let (x, y) = ((i as f32 + 0.37) / 24.0, (j as f32 + 0.61) / 24.0);
            rays.push(Ray::new(Vec3::new(x, y, 1.0), -Vec3::Z));
            rays.push(Ray::new(Vec3::new(x, y, -1.0), Vec3::Z));
            rays.push(Ray::new(Vec3::new(x, y, 2.0), Vec3::new(0.3, -0.2, -1.0)));
        }
    }
    rays
}

#[test]
fn coplanar_random_triangles_have_bounded_references() {
    let scene = columns(&random_in_plane(1_000, 0.0));
    let tree = build_checked(&scene, &BuildConfig::default());
    let refs = refs_per_triangle(&tree, &scene);
    assert!(refs <= 64.0, "{refs} references per triangle");
    assert!(tree.n_leaves() > 16, "the plane is still split");
    assert_traversal_matches(&tree, &scene, &rays_through_plane());
}

#[test]
fn near_flat_random_triangles_have_bounded_references() {
    // z jittered by 10⁻⁶ of the extent: the cells are not flat, but a
    // million times thinner than wide.
    let scene = columns(&random_in_plane(1_000, 1e-6));
    let tree = build_checked(&scene, &BuildConfig::default());
    let refs = refs_per_triangle(&tree, &scene);
    assert!(refs <= 64.0, "{refs} references per triangle");
    assert!(tree.n_leaves() > 16, "the plane is still split");
    assert_traversal_matches(&tree, &scene, &rays_through_plane());
}

#[test]
fn fan_face_has_bounded_references() {
    let scene = fan(2_000);
    assert_eq!(scene.len(), 1_998);
    let tree = build_checked(&scene, &BuildConfig::default());
    let refs = refs_per_triangle(&tree, &scene);
    assert!(refs <= 64.0, "{refs} references per triangle");
    assert!(tree.n_leaves() > 16, "the fan is still split");
    assert_traversal_matches(&tree, &scene, &rays_through_plane());
}

#[test]
fn fan_of_100k_corners_has_bounded_references_and_nodes() {
    // Without the flat-split rule: 315 M inner nodes. The level builder
    // alone (the others agree on the smaller fan above).
    let scene = fan(100_000);
    let (tree, _) = build::level::build(
        &scene,
        &BuildConfig::default(),
        None,
        &LevelOptions::default(),
    )
    .expect("the level build succeeds");
    tree.validate(&scene).expect("a valid tree");
    let refs = refs_per_triangle(&tree, &scene);
    assert!(refs <= 64.0, "{refs} references per triangle");
    assert!(tree.n_inner() <= 20_000, "{} inner nodes", tree.n_inner());
}
