//! Rays walked from a hit context (`closest_hit_from`, `occluded_from`)
//! return brute force's hit bit for bit and `occluded_from` is exactly
//! `closest_hit(ray).t < tmax`: for contexts made at the ray's origin, at
//! its hit point and at an unrelated point, in std and slim trees
//! (hoisted triangles tested once), in memory and in files (reordered or
//! not), on every instruction set this CPU has; a context of another tree
//! walks from the root.

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
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{self, ClosestHit, Hit, HitContext, KdSource, Scalar, TraceStats, TreeTracer};

/// The points a ray's context is made at: its origin, its brute-force hit
/// point (where it has one) and `other`.
fn context_points(ray: &Ray, hit: &Hit, other: Vec3) -> Vec<Vec3> {
    let mut points = vec![ray.origin, other];
    if hit.is_hit() {
        points.push(ray.origin + ray.dir * hit.t);
    }
    points
}

/// Every `_from` query over `src` against brute force.
fn check_from(src: &impl KdSource, scene: &TriangleColumns, rays: &[Ray], other: Vec3) {
    let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(scene, r)).collect();
    for level in SimdLevel::available() {
        let scalar = Scalar::with_level(src, level);
        let packet = PacketTracer::with_level(src, level);
        let tracers: [&dyn ClosestHit; 2] = [&scalar, &packet];
        for tracer in tracers {
            let mut ctx = HitContext::default();
            for (i, r) in rays.iter().enumerate() {
                for p in context_points(r, &want[i], other) {
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
    }
    // The counting walk answers as the fast one.
    let walk = src.walk();
    for (i, r) in rays.iter().enumerate() {
        let ctx = trace::locate(walk, r.origin);
        let mut stats = TraceStats::default();
        assert_eq!(
            trace::traverse_from_counted(src, &ctx, r, false, &mut stats),
            want[i]
        );
        assert_eq!(
            trace::traverse_from_counted(src, &ctx, r, true, &mut stats).is_hit(),
            want[i].t < r.tmax
        );
    }
}

fn trees(scene: &TriangleColumns) -> Vec<slimkd::tree::TreeIr> {
    let tree = build::build(scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    // Everything that can be hoisted is: hoisted triangles on the path of
    // nearly every context.
    let params = SlimParams {
        tau_occu: 0.0,
        tau_freq: 0.0,
        ..SlimParams::PAPER_SMALL
    };
    let (slim, _) = slim::slim(&tree, scene, &BuildConfig::default(), &params);
    vec![tree, slim]
}

proptest! {
    #![proptest_config(cases(128))]

    #[test]
    fn walks_from_any_context_equal_brute_force(
        (tris, rays, other) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=60),
            prop::collection::vec(secondary_ray(g), 1..24),
            (0..=2 * g, 0..=2 * g, 0..=2 * g),
        )),
    ) {
        let scene = columns(&tris);
        let other = Vec3::new(other.0 as f32, other.1 as f32, other.2 as f32) * 0.5;
        for tree in trees(&scene) {
            check_from(&TreeTracer { tree: &tree, scene: &scene }, &scene, &rays, other);
            for reorder in [false, true] {
                let options = WriteOptions { reorder, ..Default::default() };
                let bytes = format::write_to_vec(&tree, &scene, &options).unwrap();
                let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
                check_from(&file, &scene, &rays, other);
            }
        }
    }
}

/// The shadow and AO rays of a real scene, each from the context of its
/// origin, in the std tree and the slim presets, against the root walk
/// (itself brute force's, `tests/traversal.rs`) and, for a sample, brute
/// force.
#[test]
fn secondary_rays_of_a_scene_from_their_origin() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let b = scene.bounds();
    let mut rng = kd::Rng(7);
    let primary = kd::rays_at(&b, &mut rng, 400);
    let config = BuildConfig::default();
    let mut trees = vec![tree.clone()];
    for params in [SlimParams::FAST, SlimParams::SMALL, SlimParams::PAPER_SMALL] {
        trees.push(slim::slim(&tree, &scene, &config, &params).0);
    }
    for t in &trees {
        for reorder in [false, true] {
            let file = kd::read(&kd::write(t, &scene, reorder));
            let scalar = Scalar::new(&file);
            let sec = trace::rays::secondary_rays(&scene, &scalar, &primary, 4);
            assert!(sec.ao.len() > 400 && !sec.shadow.is_empty());
            let mut ctx = HitContext::default();
            for (i, r) in sec.shadow.iter().chain(&sec.ao).enumerate() {
                scalar.locate_into(r.origin, &mut ctx);
                let want = scalar.closest_hit(r);
                assert_eq!(scalar.closest_hit_from(&ctx, r), want, "ray {i}");
                assert_eq!(scalar.occluded_from(&ctx, r), scalar.occluded(r), "ray {i}");
                if i % 16 == 0 {
                    assert_eq!(want, trace::brute_force(&scene, r), "ray {i}");
                }
            }
        }
    }
}

/// A context made in one tree and used with another walks from the root:
/// the hits stay brute force's.
#[test]
fn a_context_of_another_tree_walks_from_the_root() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let (slim_tree, _) = slim::slim(&tree, &scene, &BuildConfig::default(), &SlimParams::SMALL);
    let a = kd::read(&kd::write(&tree, &scene, true));
    let b = kd::read(&kd::write(&slim_tree, &scene, false));
    let (ta, tb) = (Scalar::new(&a), Scalar::new(&b));
    let bounds = scene.bounds();
    let mut rng = kd::Rng(11);
    let mut checked = 0;
    for r in kd::rays_at(&bounds, &mut rng, 200) {
        let mut ctx = HitContext::default();
        ta.locate_into(r.origin + r.dir * 0.5, &mut ctx);
        assert!(ctx.belongs_to(&a.walk()) && !ctx.belongs_to(&b.walk()));
        let want = trace::brute_force(&scene, &r);
        assert_eq!(tb.closest_hit_from(&ctx, &r), want);
        assert_eq!(tb.occluded_from(&ctx, &r), want.t < r.tmax);
        checked += usize::from(want.is_hit());
    }
    assert!(checked > 20, "too few hits to mean anything: {checked}");
    // A default context belongs to no tree.
    assert!(!HitContext::default().belongs_to(&a.walk()));
}

/// From the context of its origin, a short ray in a deep leaf takes fewer
/// node steps than from the root: the point of the contexts.
#[test]
fn short_rays_from_their_context_take_fewer_steps() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let file = kd::read(&kd::write(&tree, &scene, true));
    let scalar = Scalar::new(&file);
    let b = scene.bounds();
    let mut rng = kd::Rng(3);
    let primary = kd::rays_at(&b, &mut rng, 300);
    let sec = trace::rays::secondary_rays(&scene, &scalar, &primary, 4);
    let (mut root, mut from) = (TraceStats::default(), TraceStats::default());
    for r in &sec.ao {
        let ctx = trace::locate(file.walk(), r.origin);
        trace::traverse_counted(&file, r, true, &mut root);
        trace::traverse_from_counted(&file, &ctx, r, true, &mut from);
    }
    assert!(
        from.nodes * 10 < root.nodes * 8,
        "from the context {} node steps, from the root {}",
        from.nodes,
        root.nodes
    );
}
