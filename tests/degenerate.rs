//! Degenerate inputs, each a named test on a scene of
//! `common::degenerate_scenes`. Every test builds with every builder
//! (asserting the same tree), validates the tree, slims it, round-trips both
//! through a `.kd` file (`common::build_checked`), and checks that traversal
//! equals brute force on a fan of rays.

mod common;

use common::*;
use glam::Vec3;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::geom::Ray;
use slimkd::scene::{self, TriangleColumns};
use slimkd::trace;
use slimkd::tree::{Node, TreeIr};

/// Builds the degenerate scene `name` with [`build_checked`] and traces a
/// fan of rays over `[-1, extent + 1]³` through it.
fn check(name: &str, extent: f32) -> (TriangleColumns, TreeIr) {
    let scene = columns(&degenerate_scene(name));
    let tree = build_checked(&scene, &BuildConfig::default());
    assert_traversal_matches(&tree, &scene, &ray_fan(extent));
    (scene, tree)
}

/// The closest hit of the ray from `o` along `d`.
fn closest(tree: &TreeIr, scene: &TriangleColumns, o: Vec3, d: Vec3) -> trace::Hit {
    trace::closest_hit(tree, scene, &Ray::new(o, d))
}

/// A hit's distance and input triangle id.
fn t_and_tri(hit: trace::Hit) -> (f32, u32) {
    (hit.t, hit.tri.0)
}

#[test]
fn empty_scene() {
    let (scene, tree) = check("empty", 1.0);
    assert_eq!(tree.nodes, vec![Node::Leaf { start: 0, count: 0 }]);
    assert!(!closest(&tree, &scene, Vec3::ZERO, Vec3::X).is_hit());
}

#[test]
fn one_triangle() {
    let (scene, tree) = check("one triangle", 1.0);
    let hit = closest(&tree, &scene, v(0.25, 0.25, 1.0), -Vec3::Z);
    assert_eq!(t_and_tri(hit), (1.0, 0));
}

#[test]
fn all_triangles_coplanar() {
    let (_, tree) = check("all coplanar", 8.0);
    assert!(
        tree.n_leaves() > 1,
        "a flat scene still splits in its plane"
    );
}

#[test]
fn axis_aligned_triangles_in_split_planes() {
    // A 3x3x3 lattice of unit cubes: every face lies in a candidate plane
    // and many are planar in the chosen splits.
    let (_, tree) = check("axis-aligned in split planes", 6.0);
    assert!(tree.n_inner() > 10);
}

#[test]
fn zero_area_and_point_triangles() {
    // Collinear, a point, a repeated vertex, and a real one (id 3).
    let (scene, tree) = check("zero-area and point", 3.0);
    // Degenerate triangles are never hit, even by a ray through them.
    let from_above = closest(&tree, &scene, v(1.0, 1.0, 5.0), -Vec3::Z);
    assert_eq!(from_above.tri.0, 3);
    assert!(!closest(&tree, &scene, v(1.0, 1.0, 0.5), -Vec3::Z).is_hit());
}

#[test]
fn coincident_duplicates() {
    let (scene, tree) = check("coincident duplicates", 6.0);
    let hit = closest(&tree, &scene, v(0.5, 0.5, 3.0), -Vec3::Z);
    assert_eq!(t_and_tri(hit), (2.0, 1), "equal t: the smallest id wins");
}

#[test]
fn needle_triangle() {
    check("needle", 100.0);
}

#[test]
fn one_huge_triangle_spanning_the_scene() {
    let (_, tree) = check("huge triangle spanning the scene", 60.0);
    // Perfect splits: the huge triangle is clipped, so it appears in many
    // leaves without making them big.
    let refs = tree.leaf_tris.iter().filter(|t| t.0 == 0).count();
    assert!(refs > 1);
}

#[test]
fn box_inside_a_box() {
    let (scene, tree) = check("box inside a box", 10.0);
    // From inside the outer box, looking at the inner box.
    let hit = closest(&tree, &scene, v(5.0, 5.0, 1.0), Vec3::Z);
    assert_eq!(hit.t, 3.0);
    assert!(hit.tri.0 >= 12);
}

#[test]
fn nan_and_inf_vertices_are_rejected_with_the_line() {
    for bad in ["nan", "inf", "-inf", "NaN"] {
        let text = format!("v 0 0 0\nv 1 0 0\nv 0 {bad} 0\nf 1 2 3\n");
        let err =
            scene::load_obj_bytes(std::path::Path::new("bad.obj"), text.as_bytes()).unwrap_err();
        let msg = err.to_string();
        assert!(msg.starts_with("bad.obj:3:"), "{msg}");
        assert!(msg.contains("non-finite"), "{msg}");
    }
    let bad = [[v(0.0, 0.0, 0.0), v(f32::NAN, 0.0, 0.0), v(0.0, 1.0, 0.0)]];
    assert!(TriangleColumns::from_triangles(&bad).is_err());
    let bad = [[
        v(0.0, 0.0, 0.0),
        v(f32::INFINITY, 0.0, 0.0),
        v(0.0, 1.0, 0.0),
    ]];
    assert!(TriangleColumns::from_triangles(&bad).is_err());
}

#[test]
fn deep_scene_respects_the_depth_limit() {
    // Many tiny triangles clustered at one corner force deep trees.
    let scene = columns(&degenerate_scene("deep corner cluster"));
    let config = BuildConfig::default();
    let tree = build_checked(&scene, &config);
    let stats = slimkd::stats::TreeStats::of(&tree, &config.sah);
    assert!(stats.max_depth <= config.sah.depth_limit(scene.len()));
    let _ = build::build(&scene, &config, Algorithm::WaldHavran, None).unwrap();
}
