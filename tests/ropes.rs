//! Rays walked leaf to leaf by ropes (`trace::ropes`) return brute
//! force's hit bit for bit and `occluded_from` is exactly
//! `closest_hit(ray).t < tmax`: from cells located at the ray's origin,
//! at its hit point and at an unrelated point, on grid scenes whose rays
//! start and run in split planes and through edges, in memory and in
//! files (reordered or not), on every instruction set this CPU has; slim
//! trees have no ropes; and a short ray takes fewer node steps than from
//! the root.

mod common;

use common::kd;
use common::*;
use glam::Vec3;
use proptest::prelude::*;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, KdFile, WriteOptions};
use slimkd::geom::Ray;
use slimkd::scene::TriangleColumns;
use slimkd::slim::{self, SlimParams};
use slimkd::trace::packet::SimdLevel;
use slimkd::trace::ropes::{RopeTracer, Ropes, RopesError};
use slimkd::trace::{self, ClosestHit, Hit, HitContext, KdSource, Scalar, TraceStats, TreeTracer};

/// Every `_from` query over `src` by ropes against brute force.
fn check_ropes(src: &impl KdSource, scene: &TriangleColumns, rays: &[Ray], other: Vec3) {
    let ropes = Ropes::new(src.walk()).unwrap();
    let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(scene, r)).collect();
    let tracer = RopeTracer::new(src, &ropes);
    for level in SimdLevel::available() {
        let tracer = RopeTracer::with_level(src, &ropes, level);
        let mut ctx = HitContext::default();
        for (i, r) in rays.iter().enumerate() {
            let mut points = vec![r.origin, other];
            if want[i].is_hit() {
                points.push(r.origin + r.dir * want[i].t);
            }
            for p in points {
                tracer.locate_into(p, &mut ctx);
                assert_eq!(
                    tracer.closest_hit_from(&ctx, r),
                    want[i],
                    "{level:?} ray {i} {r:?} from {p}"
                );
                assert_eq!(
                    tracer.occluded_from(&ctx, r),
                    want[i].t < r.tmax,
                    "{level:?} occluded ray {i} {r:?} from {p}"
                );
            }
        }
    }
    // The counting walk answers as the fast one.
    let mut ctx = HitContext::default();
    for (i, r) in rays.iter().enumerate() {
        tracer.locate_into(r.origin, &mut ctx);
        let mut stats = TraceStats::default();
        assert_eq!(
            tracer.trace_from_counted(&ctx, r, false, &mut stats),
            want[i]
        );
        assert_eq!(
            tracer
                .trace_from_counted(&ctx, r, true, &mut stats)
                .is_hit(),
            want[i].t < r.tmax
        );
    }
}

proptest! {
    #![proptest_config(cases(160))]

    #[test]
    fn rope_walks_equal_brute_force(
        (tris, rays, other) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=60),
            prop::collection::vec(secondary_ray(g), 1..24),
            (0..=2 * g, 0..=2 * g, 0..=2 * g),
        )),
    ) {
        let scene = columns(&tris);
        let other = Vec3::new(other.0 as f32, other.1 as f32, other.2 as f32) * 0.5;
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        check_ropes(&TreeTracer { tree: &tree, scene: &scene }, &scene, &rays, other);
        for reorder in [false, true] {
            let options = WriteOptions { reorder, ..Default::default() };
            let bytes = format::write_to_vec(&tree, &scene, &options).unwrap();
            let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
            check_ropes(&file, &scene, &rays, other);
        }
    }
}

/// A ray that runs along −z in the plane x = 2, from the cell to the right
/// of that plane, meets the triangle to its left whose edge lies in the
/// plane: the ray lies in the face behind it, not only in the face it
/// would leave by (a case the proptest above found).
#[test]
fn a_ray_in_the_face_behind_it_meets_the_neighbours_triangle() {
    let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    let tris = vec![
        [v(0.0, 0.0, 0.0); 3],
        [v(0.0, 0.0, 0.0), v(2.0, 2.0, 0.0), v(2.0, 0.0, 0.0)],
        [v(0.0, 0.0, 0.0), v(0.0, 0.0, 0.0), v(1.0, 0.0, 1.0)],
        [v(2.0, 0.0, 0.0), v(2.0, 0.0, 0.0), v(4.0, 1.0, 0.0)],
    ];
    let scene = columns(&tris);
    let rays = [
        Ray::new(v(2.0, 0.5, 0.5), v(0.0, 0.0, -1.0)),
        Ray::new(v(2.0, 0.5, 0.5), v(-0.0, 0.0, -1.0)),
    ];
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    let src = TreeTracer {
        tree: &tree,
        scene: &scene,
    };
    check_ropes(&src, &scene, &rays, v(2.5, 0.0, 0.0));
    assert_eq!(trace::brute_force(&scene, &rays[0]).t, 0.5);
}

/// The shadow and AO rays of a real scene, each from the cell of its
/// origin, against the root walk (itself brute force's,
/// `tests/traversal.rs`) and, for a sample, brute force; and with fewer
/// node steps than from the root.
#[test]
fn secondary_rays_of_a_scene_by_ropes() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let b = scene.bounds();
    let mut rng = kd::Rng(7);
    let primary = kd::rays_at(&b, &mut rng, 400);
    for reorder in [false, true] {
        let file = kd::read(&kd::write(&tree, &scene, reorder));
        let ropes = Ropes::new(file.walk()).unwrap();
        assert!(ropes.cells() > 1000 && ropes.bytes() >= ropes.cells() * 64);
        let tracer = RopeTracer::new(&file, &ropes);
        let scalar = Scalar::new(&file);
        let sec = trace::rays::secondary_rays(&scene, &scalar, &primary, 4);
        assert!(sec.ao.len() > 400 && !sec.shadow.is_empty());
        let mut ctx = HitContext::default();
        let (mut root, mut by_ropes) = (TraceStats::default(), TraceStats::default());
        for (i, r) in sec.shadow.iter().chain(&sec.ao).enumerate() {
            tracer.locate_into(r.origin, &mut ctx);
            let want = scalar.closest_hit(r);
            assert_eq!(tracer.closest_hit_from(&ctx, r), want, "ray {i}");
            assert_eq!(tracer.occluded_from(&ctx, r), scalar.occluded(r), "ray {i}");
            if i % 16 == 0 {
                assert_eq!(want, trace::brute_force(&scene, r), "ray {i}");
            }
            trace::traverse_counted(&file, r, true, &mut root);
            tracer.trace_from_counted(&ctx, r, true, &mut by_ropes);
        }
        assert!(
            by_ropes.nodes * 2 < root.nodes,
            "by ropes {} node steps, from the root {}",
            by_ropes.nodes,
            root.nodes
        );
    }
}

/// A slim tree's hoisted triangles apply to whole subtrees: no ropes.
#[test]
fn slim_trees_have_no_ropes() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let (slim_tree, _) = slim::slim(&tree, &scene, &BuildConfig::default(), &SlimParams::SMALL);
    assert!(
        slim_tree
            .nodes
            .iter()
            .any(|n| matches!(n, slimkd::tree::Node::Inner { t_ref: Some(_), .. }))
    );
    let file = kd::read(&kd::write(&slim_tree, &scene, false));
    assert_eq!(Ropes::new(file.walk()).err(), Some(RopesError::Hoisted));
}

/// A context located by another tracer (a root path, no cell) or made in
/// another tree walks from the root: the hits stay brute force's.
#[test]
fn foreign_contexts_walk_from_the_root() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let a = kd::read(&kd::write(&tree, &scene, true));
    let b = kd::read(&kd::write(&tree, &scene, false));
    let (ra, rb) = (Ropes::new(a.walk()).unwrap(), Ropes::new(b.walk()).unwrap());
    let (ta, tb) = (RopeTracer::new(&a, &ra), RopeTracer::new(&b, &rb));
    let bounds = scene.bounds();
    let mut rng = kd::Rng(11);
    let mut checked = 0;
    for r in kd::rays_at(&bounds, &mut rng, 200) {
        let want = trace::brute_force(&scene, &r);
        let mut ctx = HitContext::default();
        ta.locate_into(r.origin + r.dir * 0.5, &mut ctx);
        assert_eq!(tb.closest_hit_from(&ctx, &r), want);
        assert_eq!(tb.occluded_from(&ctx, &r), want.t < r.tmax);
        Scalar::new(&a).locate_into(r.origin, &mut ctx);
        assert_eq!(ta.closest_hit_from(&ctx, &r), want);
        assert_eq!(tb.closest_hit_from(&HitContext::default(), &r), want);
        checked += usize::from(want.is_hit());
    }
    assert!(checked > 20, "too few hits to mean anything: {checked}");
}
