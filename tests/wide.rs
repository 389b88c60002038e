//! Single rays over the wide box hierarchy (`trace::wide`) return brute
//! force's hit bit for bit, and `occluded` (single rays and packets, with
//! and without an occluder cache) is exactly `closest_hit(ray).t < tmax`: on grid scenes whose rays start and run
//! in split planes, along box faces and through edges, std trees and
//! trees with hoisted triangles, in memory and in files (reordered or
//! not), on every instruction set this CPU has; on a real scene's shadow
//! and AO rays with fewer node steps than the walk from the root; and
//! with boxes of another tree, from the root.

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
use slimkd::trace::wide::{WideBoxes, WideTracer};
use slimkd::trace::{
    self, ClosestHit, Hit, KdSource, OccluderCache, Scalar, TraceStats, TreeTracer,
};

/// Every query over `src`'s wide boxes against brute force, on every
/// instruction set, and the counting walk against the fast one.
fn check_wide(src: &impl KdSource, scene: &TriangleColumns, rays: &[Ray]) {
    let boxes = WideBoxes::new(src.walk()).unwrap();
    let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(scene, r)).collect();
    for level in SimdLevel::available() {
        let tracer = WideTracer::with_level(src, &boxes, level);
        for (i, r) in rays.iter().enumerate() {
            assert_eq!(tracer.closest_hit(r), want[i], "{level:?} ray {i} {r:?}");
            assert_eq!(
                tracer.occluded(r),
                want[i].t < r.tmax,
                "{level:?} occluded ray {i} {r:?}"
            );
        }
    }
    check_wide_packets(src, &boxes, rays, &want);
    let tracer = WideTracer::new(src, &boxes);
    for (i, r) in rays.iter().enumerate() {
        let mut stats = TraceStats::default();
        assert_eq!(tracer.trace_counted(r, false, &mut stats), want[i]);
        assert_eq!(
            tracer.trace_counted(r, true, &mut stats).is_hit(),
            want[i].t < r.tmax
        );
    }
}

/// Packets over the boxes (runs of up to 16 rays, any-hit queries with
/// and without an occluder cache carried from run to run, and closest
/// hits; fewer than `MIN_LANES` walked alone) against brute force's hits
/// `want`, on every instruction set, and the counting walks against the
/// fast ones.
fn check_wide_packets(src: &impl KdSource, boxes: &WideBoxes, rays: &[Ray], want: &[Hit]) {
    for level in SimdLevel::available() {
        let tracer = WideTracer::with_level(src, boxes, level).closest_packets();
        let mut cache = OccluderCache::new();
        for (c, chunk) in rays.chunks(16).enumerate() {
            let mut hits = vec![Hit::MISS; chunk.len()];
            tracer.closest_hit_n(chunk, &mut hits);
            assert_eq!(
                hits,
                want[c * 16..c * 16 + chunk.len()],
                "{level:?} closest packet {c}"
            );
            let expect: Vec<bool> = chunk
                .iter()
                .zip(&want[c * 16..])
                .map(|(r, h)| h.t < r.tmax)
                .collect();
            let mut got = vec![false; chunk.len()];
            tracer.occluded_n(chunk, &mut got);
            assert_eq!(got, expect, "{level:?} packet {c}");
            tracer.occluded_n_cached(chunk, &mut got, &mut cache);
            assert_eq!(got, expect, "{level:?} cached packet {c}");
            // A camera's 4×4 block through the tracer as made: the kd
            // packets, or the boxes' packets in the AVX2 copy.
            if let Ok(block) = <&[Ray; 16]>::try_from(chunk) {
                let mut hits = [Hit::MISS; 16];
                WideTracer::with_level(src, boxes, level).closest_hit_4x4(block, &mut hits);
                assert_eq!(hits[..], want[c * 16..c * 16 + 16], "{level:?} 4x4 {c}");
            }
        }
    }
    let tracer = WideTracer::new(src, boxes);
    let mut cache = OccluderCache::new();
    for (c, chunk) in rays.chunks(16).enumerate() {
        let mut hits = vec![Hit::MISS; chunk.len()];
        tracer.packet_counted(
            chunk,
            false,
            &mut hits,
            &mut TraceStats::default(),
            &mut cache,
        );
        assert_eq!(
            hits,
            want[c * 16..c * 16 + chunk.len()],
            "counted closest packet {c}"
        );
        tracer.packet_counted(
            chunk,
            true,
            &mut hits,
            &mut TraceStats::default(),
            &mut cache,
        );
        for (i, (h, r)) in hits.iter().zip(chunk).enumerate() {
            assert_eq!(
                h.is_hit(),
                want[c * 16 + i].t < r.tmax,
                "counted packet {c}"
            );
        }
    }
}

proptest! {
    #![proptest_config(cases(160))]

    #[test]
    fn wide_walks_equal_brute_force(
        (tris, rays, seed) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=60),
            prop::collection::vec(secondary_ray(g), 1..24),
            any::<u64>(),
        )),
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        // The same tree with type II nodes, some of whose triangles are
        // left in no leaf below.
        let (hoisted, _) = kd::hoist(&tree, &scene, seed, true);
        for t in [&tree, &hoisted] {
            check_wide(&TreeTracer { tree: t, scene: &scene }, &scene, &rays);
            for reorder in [false, true] {
                let options = WriteOptions { reorder, ..Default::default() };
                let bytes = format::write_to_vec(t, &scene, &options).unwrap();
                let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
                check_wide(&file, &scene, &rays);
            }
        }
    }
}

/// A ray along −z in the plane x = 2 (a zero component, its origin in the
/// face plane of boxes on both sides) meets the triangle whose edge lies
/// in that plane; a ray with a component too small to invert is traced
/// from the root.
#[test]
fn rays_in_face_planes_and_tiny_components() {
    let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    let tris = vec![
        [v(0.0, 0.0, 0.0), v(2.0, 2.0, 0.0), v(2.0, 0.0, 0.0)],
        [v(0.0, 0.0, 0.0), v(0.0, 0.0, 0.0), v(1.0, 0.0, 1.0)],
        [v(2.0, 0.0, 0.0), v(2.0, 0.0, 0.0), v(4.0, 1.0, 0.0)],
        [v(2.0, 0.0, -1.0), v(4.0, 0.0, -1.0), v(2.0, 2.0, -1.0)],
    ];
    let scene = columns(&tris);
    let rays = [
        Ray::new(v(2.0, 0.5, 0.5), v(0.0, 0.0, -1.0)),
        Ray::new(v(2.0, 0.5, 0.5), v(-0.0, 0.0, -1.0)),
        Ray::new(v(2.0, 0.5, 0.5), v(1e-45, 0.0, -1.0)),
        Ray::new(v(2.0, 0.5, 0.5), v(-1e-40, 1e-39, -1.0)),
        Ray::new(v(3.0, 0.5, 0.5), v(0.0, 0.0, -1.0)),
    ];
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    check_wide(
        &TreeTracer {
            tree: &tree,
            scene: &scene,
        },
        &scene,
        &rays,
    );
    assert_eq!(trace::brute_force(&scene, &rays[0]).t, 0.5);
    assert_eq!(trace::brute_force(&scene, &rays[4]).t, 1.5);
}

/// The shadow and AO rays of a real scene over the boxes of its std and
/// `small` trees, against the root walk (itself brute force's,
/// `tests/traversal.rs`) and, for a sample, brute force; and with fewer
/// node steps than from the root.
#[test]
fn secondary_rays_of_a_scene_over_wide_boxes() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let (small, _) = slim::slim(&tree, &scene, &BuildConfig::default(), &SlimParams::SMALL);
    assert!(
        small
            .nodes
            .iter()
            .any(|n| matches!(n, slimkd::tree::Node::Inner { t_ref: Some(_), .. }))
    );
    let b = scene.bounds();
    let mut rng = kd::Rng(7);
    let primary = kd::rays_at(&b, &mut rng, 400);
    for (t, reorder) in [(&tree, false), (&tree, true), (&small, true)] {
        let file = kd::read(&kd::write(t, &scene, reorder));
        let boxes = WideBoxes::new(file.walk()).unwrap();
        assert!(
            boxes.leaves() > 1000 && boxes.nodes() * 2 < boxes.leaves(),
            "{} nodes over {} leaves",
            boxes.nodes(),
            boxes.leaves()
        );
        let tracer = WideTracer::new(&file, &boxes);
        let scalar = Scalar::new(&file);
        let sec = trace::rays::secondary_rays(&scene, &scalar, &primary, 4);
        assert!(sec.ao.len() > 400 && !sec.shadow.is_empty());
        let (mut root, mut wide) = (TraceStats::default(), TraceStats::default());
        for (i, r) in sec.shadow.iter().chain(&sec.ao).chain(&primary).enumerate() {
            let want = scalar.closest_hit(r);
            assert_eq!(tracer.closest_hit(r), want, "ray {i}");
            assert_eq!(tracer.occluded(r), scalar.occluded(r), "ray {i}");
            if i % 16 == 0 {
                assert_eq!(want, trace::brute_force(&scene, r), "ray {i}");
            }
            trace::traverse_counted(&file, r, true, &mut root);
            tracer.trace_counted(r, true, &mut wide);
        }
        assert!(
            wide.nodes * 2 < root.nodes,
            "over wide boxes {} node steps, from the root {}",
            wide.nodes,
            root.nodes
        );
        // Packets as the renderer makes them (one octant, so the lanes
        // share their directions' signs) and in the rays' own order.
        // Shadow rays by octant as well: lanes of one octant whose `tmax`
        // differ (the AVX2 copy's test of a node's boxes for all lanes at
        // once bounds their reach by the greatest).
        let by_octant = |rays: &[Ray]| {
            let mut order = Vec::new();
            trace::rays::order_by_octant(rays, &mut order);
            order
                .iter()
                .map(|&i| rays[i as usize])
                .collect::<Vec<Ray>>()
        };
        let (ao_by_octant, shadow_by_octant) = (by_octant(&sec.ao), by_octant(&sec.shadow));
        // And rays of one octant, every fourth of them ending at once.
        let short: Vec<Ray> = by_octant(&primary)
            .into_iter()
            .enumerate()
            .map(|(i, r)| Ray {
                tmax: if i % 4 == 0 { r.tmin + 1e-3 } else { r.tmax },
                ..r
            })
            .collect();
        for batch in [
            &ao_by_octant,
            &sec.ao,
            &sec.shadow,
            &shadow_by_octant,
            &short,
        ] {
            let want: Vec<Hit> = batch.iter().map(|r| scalar.closest_hit(r)).collect();
            check_wide_packets(&file, &boxes, batch, &want);
        }
    }
}

/// Boxes made for another tree are never used: every query walks from
/// the root, with brute force's hits.
#[test]
fn boxes_of_another_tree_walk_from_the_root() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let a = kd::read(&kd::write(&tree, &scene, true));
    let b = kd::read(&kd::write(&tree, &scene, false));
    let boxes_a = WideBoxes::new(a.walk()).unwrap();
    let tracer = WideTracer::new(&b, &boxes_a);
    let mut rng = kd::Rng(11);
    let mut hits = 0;
    for r in kd::rays_at(&scene.bounds(), &mut rng, 200) {
        let want = trace::brute_force(&scene, &r);
        assert_eq!(tracer.closest_hit(&r), want);
        assert_eq!(tracer.occluded(&r), want.t < r.tmax);
        hits += usize::from(want.is_hit());
    }
    assert!(hits > 20, "too few hits to mean anything: {hits}");
}

/// An empty tree (no triangles in range of any ray) has a root without
/// children, and a one-leaf tree a root with one leaf slot.
#[test]
fn trees_of_one_leaf() {
    let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    let scene = columns(&[[v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0)]]);
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    let src = TreeTracer {
        tree: &tree,
        scene: &scene,
    };
    let boxes = WideBoxes::new(src.walk()).unwrap();
    assert_eq!((boxes.nodes(), boxes.leaves()), (1, 1));
    let rays = [
        Ray::new(v(0.25, 0.25, 1.0), v(0.0, 0.0, -1.0)),
        Ray::new(v(0.75, 0.75, 1.0), v(0.0, 0.0, -1.0)),
        Ray::new(v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0)),
    ];
    check_wide(&src, &scene, &rays);
    assert_eq!(trace::brute_force(&scene, &rays[0]).t, 1.0);
}
