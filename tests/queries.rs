//! Any-hit queries and packets of any size: `occluded` is exactly
//! `closest_hit(ray).t < tmax` for the scalar and the packet traverser (every
//! instruction set, slim trees' hoisted triangles included), packets of 1–16
//! rays and of mixed octants return the scalar hits, the counting traversal
//! answers as the fast one, and ray files are read or refused by record.

mod common;

use common::kd;
use common::*;
use glam::Vec3;
use proptest::prelude::*;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, KdFile, WriteOptions};
use slimkd::geom::Ray;
use slimkd::slim::{self, SlimParams};
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::rays::{self, Query};
use slimkd::trace::{
    self, ClosestHit, Hit, KdSource, OccluderCache, Scalar, TraceStats, TreeTracer,
};

/// Every query of every traverser over `src` against brute force on `rays`.
fn check_queries(src: &impl KdSource, scene: &slimkd::scene::TriangleColumns, rays: &[Ray]) {
    let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(scene, r)).collect();
    let want_occ: Vec<bool> = want.iter().zip(rays).map(|(h, r)| h.t < r.tmax).collect();
    for level in SimdLevel::available() {
        let scalar = Scalar::with_level(src, level);
        assert_eq!(scalar.level(), level);
        for (i, r) in rays.iter().enumerate() {
            assert_eq!(scalar.closest_hit(r), want[i], "scalar {level:?} ray {i}");
            let occ = scalar.occluded(r);
            assert_eq!(occ, want_occ[i], "scalar {level:?} occluded ray {i}");
        }
    }
    for (i, r) in rays.iter().enumerate() {
        assert_eq!(trace::occluded(src, r), want_occ[i]);
        let mut stats = TraceStats::default();
        assert_eq!(trace::traverse_counted(src, r, false, &mut stats), want[i]);
        assert_eq!(
            trace::traverse_counted(src, r, true, &mut stats).is_hit(),
            want_occ[i]
        );
        assert_eq!(stats.rays, 2);
    }
    for level in SimdLevel::available() {
        let tracer = PacketTracer::with_level(src, level);
        assert_eq!(tracer.level(), level);
        // One occluder cache through every chunk of every length: each
        // packet tests the triangles that blocked the one before.
        let mut cache = OccluderCache::new();
        let mut counted_cache = OccluderCache::new();
        // Every packet length, starting anywhere.
        for len in [1, 2, 5, 7, 8, 9, 15, 16] {
            for (c, chunk) in rays.chunks(len).enumerate() {
                let base = c * len;
                let mut got = vec![Hit::MISS; chunk.len()];
                tracer.closest_hit_n(chunk, &mut got);
                assert_eq!(got, want[base..base + chunk.len()], "{level:?} len {len}");
                let mut occ = vec![false; chunk.len()];
                tracer.occluded_n(chunk, &mut occ);
                assert_eq!(
                    occ,
                    want_occ[base..base + chunk.len()],
                    "{level:?} occluded len {len}"
                );
                let mut cached = vec![false; chunk.len()];
                tracer.occluded_n_cached(chunk, &mut cached, &mut cache);
                assert_eq!(
                    cached, occ,
                    "{level:?} occluded through the cache, len {len}"
                );
                let mut stats = TraceStats::default();
                let mut counted = vec![Hit::MISS; chunk.len()];
                tracer.trace_counted(chunk, false, &mut counted, &mut stats);
                assert_eq!(counted, got);
                assert_eq!(stats.rays, chunk.len() as u64);
                tracer.trace_counted(chunk, true, &mut counted, &mut stats);
                let occ2: Vec<bool> = counted.iter().map(Hit::is_hit).collect();
                assert_eq!(occ2, occ);
                tracer.trace_counted_cached(
                    chunk,
                    true,
                    &mut counted,
                    &mut stats,
                    &mut counted_cache,
                );
                let occ3: Vec<bool> = counted.iter().map(Hit::is_hit).collect();
                assert_eq!(occ3, occ, "{level:?} counted through the cache, len {len}");
            }
        }
    }
}

/// Rays with limited `(tmin, tmax)`, so that occlusion is not just "hit".
fn with_interval(rays: &[Ray], tmin: f32, span: f32) -> Vec<Ray> {
    rays.iter()
        .enumerate()
        .map(|(i, r)| {
            if i % 3 == 0 {
                *r
            } else {
                Ray {
                    tmin,
                    tmax: tmin + span * (i % 5) as f32,
                    ..*r
                }
            }
        })
        .collect()
}

proptest! {
    #![proptest_config(cases(256))]

    #[test]
    fn any_hit_and_packets_of_any_size_equal_brute_force(
        (tris, packets) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=60),
            prop::collection::vec(packet(g), 1..4),
        )),
        tmin in 0.0f32..2.0,
        span in 0.0f32..3.0,
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        // Coherent and loose packets back to back: chunks of every length
        // mix octants.
        let rays: Vec<Ray> = packets.iter().flatten().copied().collect();
        let rays = with_interval(&rays, tmin, span);
        check_queries(&TreeTracer { tree: &tree, scene: &scene }, &scene, &rays);
        for reorder in [false, true] {
            let bytes = format::write_to_vec(&tree, &scene, &WriteOptions { reorder, ..Default::default() }).unwrap();
            let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
            check_queries(&file, &scene, &rays);
        }
    }

    #[test]
    fn any_hit_counts_hoisted_triangles(
        (tris, packets) in (2i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 8..=60),
            prop::collection::vec(packet(g), 1..3),
        )),
        tmin in 0.0f32..1.0,
        span in 0.5f32..3.0,
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        let params = SlimParams { tau_occu: 0.0, tau_freq: 0.0, ..SlimParams::PAPER_SMALL };
        let (slim, _) = slim::slim(&tree, &scene, &BuildConfig::default(), &params);
        let rays: Vec<Ray> = packets.iter().flatten().copied().collect();
        let rays = with_interval(&rays, tmin, span);
        check_queries(&TreeTracer { tree: &slim, scene: &scene }, &scene, &rays);
        let bytes = format::write_to_vec(&slim, &scene, &WriteOptions::default()).unwrap();
        let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
        check_queries(&file, &scene, &rays);
    }
}

/// Ambient-occlusion packets: 4 origins, each with 4 rays in scattered
/// directions (every octant) and a short interval, as renderers trace
/// them. Such a packet walks the tree whole, lanes of different octants
/// taking children in different orders, and one-lane cells go to the
/// scalar walk; every hit is still brute force's.
fn ao_packet(g: i32) -> impl Strategy<Value = Vec<Ray>> {
    let coord = move || (-1..=2 * g + 1).prop_map(|k| k as f32 * 0.5 + 0.01);
    let point = move || (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    let dir = (-4i32..=4, -4i32..=4, -4i32..=4)
        .prop_filter("zero direction", |&(x, y, z)| (x, y, z) != (0, 0, 0))
        .prop_map(|(x, y, z)| Vec3::new(x as f32, y as f32, z as f32).normalize());
    (
        prop::collection::vec(point(), 4),
        prop::collection::vec(dir, 16),
        0.2f32..3.0,
    )
        .prop_map(|(origins, dirs, radius)| {
            (0..16)
                .map(|i| Ray {
                    tmin: 0.0,
                    tmax: radius,
                    ..Ray::new(origins[i / 4], dirs[i])
                })
                .collect()
        })
}

proptest! {
    #![proptest_config(cases(128))]

    #[test]
    fn ambient_occlusion_packets_equal_brute_force(
        (tris, packets) in (2i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 8..=80),
            prop::collection::vec(ao_packet(g), 1..4),
        )),
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        let rays: Vec<Ray> = packets.into_iter().flatten().collect();
        check_queries(&TreeTracer { tree: &tree, scene: &scene }, &scene, &rays);
        let bytes = format::write_to_vec(&tree, &scene, &WriteOptions::default()).unwrap();
        let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
        check_queries(&file, &scene, &rays);
    }
}

/// A wall (two triangles at z = 4) and packets of rays toward it from
/// z = 0: the first packet fills the cache with the wall; the cached wall
/// then counts only inside each ray's interval, and a cache filled in one
/// tree is emptied in another.
#[test]
fn cached_occluders_count_only_inside_the_interval() {
    let wall = |z: f32| {
        [
            [v(-8.0, -8.0, z), v(8.0, -8.0, z), v(8.0, 8.0, z)],
            [v(-8.0, -8.0, z), v(8.0, 8.0, z), v(-8.0, 8.0, z)],
        ]
    };
    let mut tris = wall(4.0).to_vec();
    // Clutter beside the wall, so that the tree has more than one leaf.
    tris.extend(box_mesh(v(10.0, 10.0, 0.0), v(11.0, 11.0, 1.0)));
    let scene = columns(&tris);
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    let src = TreeTracer {
        tree: &tree,
        scene: &scene,
    };
    let packet = |tmin: f32, tmax: f32| -> Vec<Ray> {
        (0..16)
            .map(|i| Ray {
                tmin,
                tmax,
                ..Ray::new(
                    v((i % 4) as f32 - 1.5, (i / 4) as f32 - 1.5, 0.0),
                    v(0.1, 0.05, 1.0).normalize(),
                )
            })
            .collect()
    };
    for level in SimdLevel::available() {
        let tracer = PacketTracer::with_level(&src, level);
        let mut cache = OccluderCache::new();
        let mut occ = [false; 16];
        for (tmin, tmax, want) in [
            (0.0, 100.0, true),
            // Ends before the wall, starts past it, ends on the plane
            // short of it: the cached wall is hit, outside the interval.
            (0.0, 3.9, false),
            (4.2, 100.0, false),
            (0.0, 4.0, false),
            (0.0, 4.1, true),
        ] {
            let rays = packet(tmin, tmax);
            for len in [16, 9, 3] {
                tracer.occluded_n_cached(&rays[..len], &mut occ[..len], &mut cache);
                for (i, r) in rays[..len].iter().enumerate() {
                    let brute = trace::brute_force(&scene, r).t < r.tmax;
                    assert_eq!(
                        occ[i], brute,
                        "{level:?} ({tmin}, {tmax}) len {len} lane {i}"
                    );
                    assert_eq!(
                        occ[i], want,
                        "{level:?} ({tmin}, {tmax}) len {len} lane {i}"
                    );
                }
            }
            // Refill with the wall for the next interval.
            tracer.occluded_n_cached(&packet(0.0, 100.0), &mut occ, &mut cache);
            assert!(
                !cache.is_empty() && cache.len() <= 2,
                "{level:?}: {cache:?}"
            );
        }
        // The wall's cache in a tree of another scene (one triangle, far
        // away): no wall there.
        let other = columns(&[[
            v(50.0, 50.0, 50.0),
            v(51.0, 50.0, 50.0),
            v(50.0, 51.0, 50.0),
        ]]);
        let other_tree =
            build::build(&other, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        let other_src = TreeTracer {
            tree: &other_tree,
            scene: &other,
        };
        let rays = packet(0.0, 100.0);
        PacketTracer::with_level(&other_src, level).occluded_n_cached(&rays, &mut occ, &mut cache);
        assert_eq!(occ, [false; 16], "{level:?} another tree");
    }
}

#[test]
fn hoisted_triangles_are_counted_and_tested() {
    // A scene whose slim tree hoists: the counting traversal reports hoisted
    // tests, and the hoisted triangle occludes.
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let params = SlimParams::PAPER_SMALL;
    let (slim, report) = slim::slim(&tree, &scene, &BuildConfig::default(), &params);
    assert!(report.hoisted > 0);
    assert!(
        slim.nodes
            .iter()
            .any(|n| matches!(n, slimkd::tree::Node::Inner { t_ref: Some(_), .. }))
    );
    let src = TreeTracer {
        tree: &slim,
        scene: &scene,
    };
    let b = scene.bounds();
    let mut stats = TraceStats::default();
    let mut rays = Vec::new();
    for i in 0..32 {
        for j in 0..32 {
            let target = b.min
                + (b.max - b.min)
                    * Vec3::new((i as f32 + 0.5) / 32.0, (j as f32 + 0.5) / 32.0, 0.5);
            let o = b.max + 1.0;
            rays.push(Ray::new(o, target - o));
        }
    }
    check_queries(&src, &scene, &rays);
    for r in &rays {
        trace::traverse_counted(&src, r, false, &mut stats);
    }
    assert!(stats.hoisted > 0, "{stats:?}");
    assert!(stats.nodes > stats.leaves && stats.leaves > 0 && stats.tris > 0);
}

#[test]
fn ray_files_round_trip_and_bad_records_are_named() {
    let rays = vec![
        Ray::new(Vec3::new(1.0, 2.0, 3.0), Vec3::new(0.0, 0.0, -1.0)),
        Ray {
            origin: Vec3::ZERO,
            dir: Vec3::X,
            tmin: 0.5,
            tmax: f32::INFINITY,
        },
    ];
    let bytes = rays::ray_bytes(&rays);
    assert_eq!(bytes.len(), 64);
    let back = rays::parse_rays(&bytes).unwrap();
    assert_eq!(back.len(), 2);
    for (a, b) in back.iter().zip(&rays) {
        assert_eq!(
            (a.origin, a.dir, a.tmin, a.tmax),
            (b.origin, b.dir, b.tmin, b.tmax)
        );
    }
    let bad = |f: &dyn Fn(&mut Ray)| {
        let mut rs = rays.clone();
        f(&mut rs[1]);
        rays::parse_rays(&rays::ray_bytes(&rs)).unwrap_err()
    };
    assert_eq!(bad(&|r| r.origin.y = f32::NAN), (1, "origin is not finite"));
    assert_eq!(bad(&|r| r.dir.z = f32::NAN), (1, "direction is not finite"));
    assert_eq!(bad(&|r| r.dir = Vec3::ZERO), (1, "direction is zero"));
    assert_eq!(
        bad(&|r| {
            r.tmin = 2.0;
            r.tmax = 1.0;
        }),
        (1, "tmin > tmax")
    );
    assert_eq!(bad(&|r| r.tmax = f32::NAN), (1, "tmin or tmax is NaN"));
    assert_eq!(
        bad(&|r| r.tmin = -0.5),
        (
            1,
            "tmin is negative (the interval must start at or ahead of the origin)"
        )
    );
    let mut zero = rays.clone();
    zero[1].tmin = -0.0;
    assert_eq!(rays::parse_rays(&rays::ray_bytes(&zero)).unwrap().len(), 2);

    let dir = std::env::temp_dir().join(format!("slimkd-rays-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let short = dir.join("short.rays");
    std::fs::write(&short, &bytes[..40]).unwrap();
    let e = rays::read_rays(&short).unwrap_err().to_string();
    assert!(e.contains("short.rays") && e.contains("size 40"), "{e}");
    let nan = dir.join("nan.rays");
    let mut b = bytes.clone();
    b[32..36].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&nan, &b).unwrap();
    let e = rays::read_rays(&nan).unwrap_err().to_string();
    assert!(e.contains("nan.rays") && e.contains("ray 1"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn batches_match_one_by_one_and_the_peer_checksums() {
    let scene = kd::load_scene("bunny_npm.obj");
    let file = kd::read(&kd::write(&kd::std_tree(&scene), &scene, true));
    let b = scene.bounds();
    // 1000 rays (not a multiple of 16 or 256) from a point; every other one
    // ends exactly at its closest hit (a hit, but not occluded: the open
    // interval), every fourth a little beyond it.
    let o = b.max + (b.max - b.min);
    let rays: Vec<Ray> = (0..1000)
        .map(|i| {
            let target = b.min
                + (b.max - b.min) * Vec3::new((i % 40) as f32 / 40.0, (i / 40) as f32 / 25.0, 0.5);
            let mut r = Ray::new(o, target - o);
            let t = trace::brute_force(&scene, &r).t;
            if i % 2 == 1 && t.is_finite() {
                r.tmax = if i % 4 == 1 { t } else { t * 1.01 };
            }
            r
        })
        .collect();
    let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(&scene, r)).collect();
    let scalar = Scalar::new(&file);
    let packet = PacketTracer::new(&file);
    for (tracer, packets) in [
        (&scalar as &dyn ClosestHit, false),
        (&packet as &dyn ClosestHit, true),
    ] {
        let closest = rays::trace_batch(tracer, &rays, Query::Closest, packets);
        let t: Vec<f32> = want.iter().map(|h| h.t).collect();
        assert_eq!(closest.results, t);
        let hits = want.iter().filter(|h| h.is_hit()).count() as u64;
        assert!(hits > 100 && hits < 1000);
        assert_eq!(closest.hits(Query::Closest), hits);
        let sum: f64 = want
            .iter()
            .filter(|h| h.is_hit())
            .map(|h| f64::from(h.t))
            .sum();
        assert_eq!(closest.checksum(Query::Closest), sum);
        let occ = rays::trace_batch(tracer, &rays, Query::Occluded, packets);
        let o: Vec<f32> = want
            .iter()
            .zip(&rays)
            .map(|(h, r)| f32::from(u8::from(h.t < r.tmax)))
            .collect();
        assert_eq!(occ.results, o);
        let idx: f64 = o
            .iter()
            .enumerate()
            .filter(|(_, v)| **v == 1.0)
            .map(|(i, _)| i as f64)
            .sum();
        assert_eq!(occ.checksum(Query::Occluded), idx);
        assert!(occ.hits(Query::Occluded) < hits, "tmax must cut some hits");
    }
}

#[test]
fn sorted_batches_match_brute_force_in_every_octant() {
    let scene = kd::load_scene("bunny_npm.obj");
    let file = kd::read(&kd::write(&kd::std_tree(&scene), &scene, true));
    let b = scene.bounds();
    let (lo, ext) = (b.min, b.max - b.min);
    // 2,500 rays (not a multiple of 16 or 1,024) from points inside the
    // box in every direction, short and long, as AO rays of many pixels
    // interleaved: batches that mix octants, traced in octant order.
    let mut seed = 7u64;
    let mut unit = move || {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (seed >> 40) as f32 / (1u64 << 24) as f32
    };
    let mut point = || lo + ext * Vec3::new(unit(), unit(), unit());
    let rays: Vec<Ray> = (0..2500)
        .map(|i| {
            let o = point();
            let d = point() - point();
            let mut r = Ray::new(o, d);
            r.tmax = if i % 3 == 0 {
                f32::INFINITY
            } else {
                0.2 * ext.length() / d.length()
            };
            r
        })
        .collect();
    let octants: std::collections::HashSet<usize> =
        rays.iter().map(|r| rays::octant(r.dir)).collect();
    assert_eq!(octants.len(), 8);
    assert!(rays.chunks(rays::SORT_CHUNK).all(rays::mixed_octants));
    check_sorted_batches(&scene, &file, &rays);
    // Shadow rays toward a light inside the box, 50 from each of 50
    // points: runs of one octant far longer than a packet, traced in
    // their own order.
    let light = lo + ext * Vec3::new(0.6, 0.7, 0.4);
    let shadow: Vec<Ray> = (0..2500)
        .map(|_| point())
        .collect::<Vec<_>>()
        .chunks(50)
        .flat_map(|c| {
            let d = light - c[0];
            c.iter().map(move |&o| {
                let mut r = Ray::new(o, d);
                r.tmax = 1.0;
                r
            })
        })
        .collect();
    let octants: std::collections::HashSet<usize> =
        shadow.iter().map(|r| rays::octant(r.dir)).collect();
    assert!(octants.len() >= 4, "{octants:?}");
    assert!(!shadow.chunks(rays::SORT_CHUNK).any(rays::mixed_octants));
    check_sorted_batches(&scene, &file, &shadow);
    // AO-like rays: each run of 1,024 from close origins around a point of
    // its own (a tile's hits), in every direction, 0.3 of the box's
    // diagonal long: batches that mix octants, traced by direction cell.
    let centres: Vec<Vec3> = (0..3).map(|_| point()).collect();
    let spread = 0.01 * ext.length();
    let ao: Vec<Ray> = (0..2500)
        .map(|i| {
            let c = centres[i / rays::SORT_CHUNK];
            let o = c + ((point() - lo) / ext - 0.5) * spread;
            let d = point() - point();
            let mut r = Ray::new(o, d);
            r.tmax = 0.3 * ext.length() / d.length();
            r
        })
        .collect();
    assert!(ao.chunks(rays::SORT_CHUNK).all(rays::mixed_octants));
    assert!(ao.chunks(rays::SORT_CHUNK).all(rays::close_origins));
    check_sorted_batches(&scene, &file, &ao);
}

/// `trace_batch_sorted` returns the brute-force results for `rays` with
/// every instruction set and both tracers, and finds occluded and free
/// rays among them.
fn check_sorted_batches(
    scene: &slimkd::scene::TriangleColumns,
    file: &KdFile<format::AlignedBytes>,
    rays: &[Ray],
) {
    let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(scene, r)).collect();
    let t: Vec<f32> = want.iter().map(|h| h.t).collect();
    let o: Vec<f32> = want
        .iter()
        .zip(rays)
        .map(|(h, r)| f32::from(u8::from(h.t < r.tmax)))
        .collect();
    assert!(o.iter().filter(|&&v| v == 1.0).count() > 200);
    assert!(o.iter().filter(|&&v| v == 0.0).count() > 200);
    for level in SimdLevel::available() {
        let scalar = Scalar::with_level(file, level);
        let packet = PacketTracer::with_level(file, level);
        for tracer in [&scalar as &dyn ClosestHit, &packet as &dyn ClosestHit] {
            let closest = rays::trace_batch_sorted(tracer, rays, Query::Closest);
            assert_eq!(closest.results, t, "{level:?}");
            let occ = rays::trace_batch_sorted(tracer, rays, Query::Occluded);
            assert_eq!(occ.results, o, "{level:?}");
            // The whole batch at once, as the facade traces its batches,
            // and in each order the renderer takes for its AO rays, into
            // answers that start wrong.
            let wrong = Hit {
                t: -1.0,
                tri: slimkd::tree::TriId(0),
            };
            let mut hits = vec![wrong; rays.len()];
            rays::closest_batch(tracer, rays, &mut hits, &mut Vec::new());
            assert!(hits.iter().map(|h| h.t).eq(t.iter().copied()), "{level:?}");
            let mut octants = Vec::new();
            rays::order_by_octant(rays, &mut octants);
            hits.fill(wrong);
            rays::closest_in_order(tracer, rays, &octants, &mut hits);
            assert!(hits.iter().map(|h| h.t).eq(t.iter().copied()), "{level:?}");
            let mut cache = slimkd::trace::OccluderCache::new();
            let answers = |occ: &[bool]| {
                occ.iter()
                    .map(|&b| f32::from(u8::from(b)))
                    .collect::<Vec<_>>()
            };
            let mut occ: Vec<bool> = o.iter().map(|&v| v == 0.0).collect();
            rays::occluded_batch(tracer, rays, &mut occ, &mut cache, &mut Vec::new());
            assert_eq!(answers(&occ), o, "{level:?}");
            occ = o.iter().map(|&v| v == 0.0).collect();
            rays::occluded_in_order(tracer, rays, &octants, &mut occ, &mut cache);
            assert_eq!(answers(&occ), o, "{level:?}");
            // By direction cell, as the renderer traces a tile's AO rays.
            let mut order = Vec::new();
            rays::order_by_direction(rays, &mut order);
            hits.fill(wrong);
            rays::closest_in_order(tracer, rays, &order, &mut hits);
            assert!(hits.iter().map(|h| h.t).eq(t.iter().copied()), "{level:?}");
            occ = o.iter().map(|&v| v == 0.0).collect();
            rays::occluded_in_order(tracer, rays, &order, &mut occ, &mut cache);
            assert_eq!(answers(&occ), o, "{level:?}");
            // In their own order, as the renderer traces its AO rays made
            // in their packets' order, the next rays read on the way.
            occ = o.iter().map(|&v| v == 0.0).collect();
            let (now, next) = rays.split_at(rays.len() / 2);
            let (occ_now, occ_next) = occ.split_at_mut(now.len());
            rays::occluded_ahead(tracer, now, occ_now, &mut cache, next);
            rays::occluded_ahead(tracer, next, occ_next, &mut cache, &[]);
            assert_eq!(answers(&occ), o, "{level:?}");
        }
    }
}

#[test]
fn octant_order_is_stable_and_grouped() {
    let dirs = [
        Vec3::new(-1.0, 1.0, 1.0),
        Vec3::new(1.0, 1.0, 1.0),
        Vec3::new(1.0, -1.0, -1.0),
        Vec3::new(-1.0, 2.0, 0.5),
        Vec3::new(2.0, 0.0, 3.0),
        Vec3::new(1.0, -0.0, -1.0),
    ];
    let rays: Vec<Ray> = dirs.iter().map(|&d| Ray::new(Vec3::ZERO, d)).collect();
    let mut order = vec![99; 2];
    rays::order_by_octant(&rays, &mut order);
    // Octants 0 (rays 1 and 4), 1 (0, 3), 4 (5: -0.0 is not negative),
    // 6 (2); within an octant, the rays' own order.
    assert_eq!(order, [1, 4, 0, 3, 5, 2]);
}

/// The counting sorts against a stable sort by the same key, for every
/// batch length up to 70 (odd and even: the sorts count and place the
/// two halves of a batch apart).
#[test]
fn packet_orders_equal_a_stable_sort_by_their_keys() {
    let mut rng = kd::Rng(11);
    let mut order = Vec::new();
    for n in 0..70 {
        let rays: Vec<Ray> = (0..n)
            .map(|_| {
                // Eight octants: keys repeat from ray to ray.
                let mut c = || if rng.chance(2) { -1.0 } else { 1.0 } * (1.0 + rng.unit());
                Ray::new(Vec3::ZERO, Vec3::new(c(), c(), c()))
            })
            .collect();
        let stable = |key: &dyn Fn(Vec3) -> usize| {
            let mut idx: Vec<u32> = (0..n as u32).collect();
            idx.sort_by_key(|&i| key(rays[i as usize].dir));
            idx
        };
        rays::order_by_octant(&rays, &mut order);
        assert_eq!(order, stable(&rays::octant), "{n} rays by octant");
        rays::order_by_direction(&rays, &mut order);
        let by_cell = |d: Vec3| {
            (rays::octant(d) * 3 + slimkd::geom::dominant_axis(d)) * 64 + rays::direction_cell(d)
        };
        assert_eq!(order, stable(&by_cell), "{n} rays by direction cell");
    }
}

#[test]
fn direction_cells_number_the_octahedron_in_morton_order() {
    let cell = |x: f32, y: f32, z: f32| rays::direction_cell(Vec3::new(x, y, z));
    assert_eq!(rays::DIRECTION_BINS, 8);
    // u = |x| / (|x| + |y| + |z|) and v alike, in eighths; the cell
    // interleaves their bits, u in the lower bit of each pair.
    assert_eq!(cell(0.0, 0.0, 1.0), 0);
    assert_eq!(cell(1.0, 0.0, 0.0), 0b01_01_01); // u = 1 clamps to 7
    assert_eq!(cell(0.0, -1.0, 0.0), 0b10_10_10);
    assert_eq!(cell(1.0, 1.0, 0.0), 0b11_00_00); // u = v = 4
    assert_eq!(cell(-1.0, 1.0, 2.0), 0b00_11_00); // u = v = 2
    assert_eq!(cell(3.0, 1.0, 4.0), 0b00_01_11); // u = 3, v = 1
    // The sign and the length do not matter; a zero or NaN direction is
    // cell 0.
    assert_eq!(cell(-6.0, 2.0, -8.0), cell(3.0, 1.0, 4.0));
    assert_eq!(cell(0.0, 0.0, 0.0), 0);
    assert_eq!(cell(f32::NAN, 1.0, 0.0), 0);
    assert!(cell(f32::INFINITY, 1.0, 0.0) < 64);
}

#[test]
fn packets_by_direction_cell_only_from_close_origins() {
    // Rays of length 10 (tmax 5 along directions of length 2).
    let ray = |o: Vec3, d: Vec3| {
        let mut r = Ray::new(o, d.normalize() * 2.0);
        r.tmax = 5.0;
        r
    };
    let dirs = [
        Vec3::new(1.0, 0.1, 0.2),
        Vec3::new(-1.0, 1.0, 1.0),
        Vec3::new(0.1, 1.0, 0.2),
        Vec3::new(1.0, 0.15, 0.2),
        Vec3::new(-1.0, 1.1, 1.0),
        Vec3::new(0.2, 1.0, 0.1),
    ];
    let at = |spread: f32| -> Vec<Ray> {
        dirs.iter()
            .enumerate()
            .map(|(i, &d)| ray(Vec3::new(100.0 + spread * (i % 2) as f32, 0.0, 0.0), d))
            .collect()
    };
    // The origins span 1.9 and 2.1 of the rays' length 10 (0.2 of it).
    let (close, far) = (at(1.9), at(2.1));
    assert!(rays::close_origins(&close));
    assert!(!rays::close_origins(&far));
    assert!(!rays::close_origins(&[]));
    let mut flat = close.clone();
    flat[3].tmax = 0.0;
    assert!(!rays::close_origins(&flat), "a ray of no length");
    let mut endless = far.clone();
    endless.iter_mut().for_each(|r| r.tmax = f32::INFINITY);
    assert!(rays::close_origins(&endless), "rays without an end");
    // Octant 0 holds rays 0, 2, 3 and 5, in cells 20 (u = 6, v = 0), 40
    // (0, 6), 17 (5, 0) and 41 (1, 6), x their longest axis in rays 0
    // and 3, y in 2 and 5; octant 1 rays 1 and 4, both in cell 12 (2, 2),
    // x the longest in ray 1 (a tie goes to the lower axis), y in 4.
    let mut got = Vec::new();
    rays::order_for_packets(&close, &mut got);
    assert_eq!(got, [3, 0, 2, 5, 1, 4]);
    // From origins far apart: by octant and longest axis, each group in
    // the rays' own order.
    rays::order_for_packets(&far, &mut got);
    assert_eq!(got, [0, 3, 2, 5, 1, 4]);
}

#[test]
fn direction_order_groups_octants_axes_then_cells_stably() {
    let mut seed = 3u64;
    let mut unit = move || {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (seed >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    };
    let rays: Vec<Ray> = (0..3000)
        .map(|_| Ray::new(Vec3::ZERO, Vec3::new(unit(), unit(), unit())))
        .collect();
    let mut order = vec![7; 5];
    rays::order_by_direction(&rays, &mut order);
    let mut seen = order.clone();
    seen.sort_unstable();
    assert!(seen.iter().copied().eq(0..rays.len() as u32));
    let key = |i: u32| {
        let d = rays[i as usize].dir;
        (
            rays::octant(d),
            slimkd::geom::dominant_axis(d),
            rays::direction_cell(d),
            i,
        )
    };
    assert!(order.windows(2).all(|w| key(w[0]) < key(w[1])));
    // Most cells of every octant are used (u + v ≤ 1 is half the square;
    // a cell the planes of equal components cross is used once per axis).
    let cells: std::collections::HashSet<(usize, usize)> =
        order.iter().map(|&i| (key(i).0, key(i).2)).collect();
    assert!(cells.len() > 8 * 30, "{}", cells.len());
    // Neighbours of one octant and longest axis share the triangle test's
    // vertex permutation, which the packets' test then picks once; at
    // most 23 places in the order change group.
    let perm = |i: u32| {
        let p = slimkd::geom::RayPrecomp::new(&rays[i as usize]);
        (p.kx, p.ky, p.kz)
    };
    let changes = order
        .windows(2)
        .filter(|w| perm(w[0]) != perm(w[1]))
        .count();
    let groups = order
        .windows(2)
        .filter(|w| key(w[0]).0 != key(w[1]).0 || key(w[0]).1 != key(w[1]).1)
        .count();
    assert_eq!(changes, groups);
    assert!(groups <= 23, "{groups}");
}
