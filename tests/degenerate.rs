//! Degenerate inputs, each a named test. Every test builds with both
//! builders (asserting the same tree), validates the tree, and checks that
//! traversal equals brute force on a fan of rays.

mod common;

use common::*;
use glam::Vec3;
use slimkd::build::{self, BuildConfig, Builder};
use slimkd::geom::Ray;
use slimkd::scene::{self, TriangleColumns};
use slimkd::trace;
use slimkd::tree::{Node, TreeIr};

fn check(tris: &[[Vec3; 3]], extent: f32) -> (TriangleColumns, TreeIr) {
    let scene = columns(tris);
    let tree = build_checked(&scene, &BuildConfig::default());
    assert_traversal_matches(&tree, &scene, &ray_fan(extent));
    (scene, tree)
}

#[test]
fn empty_scene() {
    let (scene, tree) = check(&[], 1.0);
    assert_eq!(tree.nodes, vec![Node::Leaf { start: 0, count: 0 }]);
    let hit = trace::closest_hit(&tree, &scene, &Ray::new(Vec3::ZERO, Vec3::X));
    assert!(!hit.is_hit());
}

#[test]
fn one_triangle() {
    let t = [v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0)];
    let (scene, tree) = check(&[t], 1.0);
    let hit = trace::closest_hit(&tree, &scene, &Ray::new(v(0.25, 0.25, 1.0), -Vec3::Z));
    assert_eq!((hit.t, hit.tri.0), (1.0, 0));
}

#[test]
fn all_triangles_coplanar() {
    let mut tris = Vec::new();
    for i in 0..8 {
        for j in 0..8 {
            let (x, y) = (i as f32, j as f32);
            tris.push([v(x, y, 2.0), v(x + 1.0, y, 2.0), v(x, y + 1.0, 2.0)]);
            tris.push([
                v(x + 1.0, y, 2.0),
                v(x + 1.0, y + 1.0, 2.0),
                v(x, y + 1.0, 2.0),
            ]);
        }
    }
    let (_, tree) = check(&tris, 8.0);
    assert!(
        tree.n_leaves() > 1,
        "a flat scene still splits in its plane"
    );
}

#[test]
fn axis_aligned_triangles_in_split_planes() {
    // A 3x3x3 lattice of unit cubes: every face lies in a candidate plane
    // and many are planar in the chosen splits.
    let mut tris = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                let lo = v(i as f32 * 2.0, j as f32 * 2.0, k as f32 * 2.0);
                tris.extend(box_mesh(lo, lo + Vec3::ONE));
            }
        }
    }
    let (_, tree) = check(&tris, 6.0);
    assert!(tree.n_inner() > 10);
}

#[test]
fn zero_area_and_point_triangles() {
    let tris = [
        [v(0.0, 0.0, 0.0), v(1.0, 1.0, 1.0), v(2.0, 2.0, 2.0)], // collinear
        [v(1.0, 1.0, 1.0); 3],                                  // a point
        [v(3.0, 0.0, 0.0), v(3.0, 0.0, 0.0), v(3.0, 2.0, 0.0)], // repeated vertex
        [v(0.0, 0.0, 1.0), v(3.0, 0.0, 1.0), v(0.0, 3.0, 1.0)], // a real one
    ];
    let (scene, tree) = check(&tris, 3.0);
    // Degenerate triangles are never hit, even by a ray through them.
    let hit = trace::closest_hit(&tree, &scene, &Ray::new(v(1.0, 1.0, 5.0), -Vec3::Z));
    assert_eq!(hit.tri.0, 3);
    let hit = trace::closest_hit(&tree, &scene, &Ray::new(v(1.0, 1.0, 0.5), -Vec3::Z));
    assert!(!hit.is_hit());
}

#[test]
fn coincident_duplicates() {
    let t = [v(0.0, 0.0, 1.0), v(2.0, 0.0, 1.0), v(0.0, 2.0, 1.0)];
    let mut tris = vec![[v(5.0, 5.0, 5.0), v(6.0, 5.0, 5.0), v(5.0, 6.0, 5.0)]];
    tris.extend(std::iter::repeat_n(t, 10));
    let (scene, tree) = check(&tris, 6.0);
    // Equal t: the smallest id wins.
    let hit = trace::closest_hit(&tree, &scene, &Ray::new(v(0.5, 0.5, 3.0), -Vec3::Z));
    assert_eq!((hit.t, hit.tri.0), (2.0, 1));
}

#[test]
fn needle_triangle() {
    let mut tris = vec![[v(0.0, 0.0, 0.0), v(100.0, 0.001, 0.0), v(100.0, 0.0, 0.002)]];
    for i in 0..20 {
        let x = i as f32 * 5.0;
        tris.push([v(x, -1.0, -1.0), v(x, 1.0, -1.0), v(x, 0.0, 1.0)]);
    }
    check(&tris, 100.0);
}

#[test]
fn one_huge_triangle_spanning_the_scene() {
    let mut tris = vec![[
        v(-100.0, -100.0, 0.5),
        v(300.0, -100.0, 0.5),
        v(-100.0, 300.0, 0.5),
    ]];
    for i in 0..6 {
        for j in 0..6 {
            let (x, y) = (i as f32 * 10.0, j as f32 * 10.0);
            tris.push([v(x, y, 0.0), v(x + 1.0, y, 1.0), v(x, y + 1.0, 1.0)]);
        }
    }
    let (_, tree) = check(&tris, 60.0);
    // Perfect splits: the huge triangle is clipped, so it appears in many
    // leaves without making them big.
    let refs = tree.leaf_tris.iter().filter(|t| t.0 == 0).count();
    assert!(refs > 1);
}

#[test]
fn box_inside_a_box() {
    let mut tris = box_mesh(v(0.0, 0.0, 0.0), v(10.0, 10.0, 10.0));
    tris.extend(box_mesh(v(4.0, 4.0, 4.0), v(6.0, 6.0, 6.0)));
    let (scene, tree) = check(&tris, 10.0);
    // From inside the outer box, looking at the inner box.
    let hit = trace::closest_hit(&tree, &scene, &Ray::new(v(5.0, 5.0, 1.0), Vec3::Z));
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
    let mut tris = Vec::new();
    let mut s = 1.0f32;
    for _ in 0..60 {
        tris.push([v(0.0, 0.0, 0.0), v(s, 0.0, 0.0), v(0.0, s, s)]);
        s *= 0.5;
    }
    let scene = columns(&tris);
    let config = BuildConfig::default();
    let tree = build_checked(&scene, &config);
    let stats = slimkd::stats::TreeStats::of(&tree, &config.sah);
    assert!(stats.max_depth <= config.sah.depth_limit(scene.len()));
    let _ = build::build(&scene, &config, Builder::Sweep, None).unwrap();
}
