//! The `Accel` facade: built in memory, written, mapped back, it traces
//! exactly as brute force does, in the input's numbering, for single rays
//! and masked packets, per call or through its borrowing tracer, down the
//! kd-tree and over the wide boxes; bad files are errors naming the file.

mod common;

use common::kd::{Rng, load_scene, rays_at};
use common::*;
use glam::Vec3;
use slimkd::accel::{self, Accel, AccelError, BuildOptions, HitRecord, Preset, RayPacket};
use slimkd::geom::Ray;
use slimkd::scene::TriangleColumns;
use slimkd::trace::{self, OccluderCache};

/// A few hundred rays at the scene, a third of them with a finite `tmax`
/// (so that occlusion has both answers).
fn rays(accel: &Accel, seed: u64) -> Vec<Ray> {
    let mut rng = Rng(seed);
    let mut rays = rays_at(&accel.bounds(), &mut rng, 300);
    for (i, r) in rays.iter_mut().enumerate() {
        if i % 3 == 0 {
            r.tmax = rng.unit() * 1.5;
        }
        if i % 7 == 0 {
            r.tmin = rng.unit() * 0.2;
        }
    }
    rays
}

/// The record brute force's hit gives, computed from the scene directly.
fn expected(scene: &TriangleColumns, ray: &Ray) -> Option<HitRecord> {
    let hit = trace::brute_force(scene, ray);
    if !hit.is_hit() {
        return None;
    }
    let tri = scene.tri(hit.tri.0);
    let (u, v) = accel::barycentrics(ray, &tri);
    Some(HitRecord {
        t: hit.t,
        u,
        v,
        ng: (tri[1] - tri[0]).cross(tri[2] - tri[0]),
        prim: hit.tri.0,
    })
}

fn assert_traces_as_brute_force(scene: &TriangleColumns, accel: &Accel, rays: &[Ray]) {
    let mut hits = 0;
    for (i, ray) in rays.iter().enumerate() {
        let want = expected(scene, ray);
        let got = accel.intersect(ray);
        assert_eq!(got, want, "ray {i}: {ray:?}");
        assert_eq!(
            accel.occluded(ray),
            got.is_some_and(|h| h.t < ray.tmax),
            "occluded, ray {i}: {ray:?}"
        );
        if let Some(h) = got {
            hits += 1;
            // The weights interpolate the hit point.
            let [a, b, c] = scene.tri(h.prim);
            let p = a * (1.0 - h.u - h.v) + b * h.u + c * h.v;
            let q = ray.origin + ray.dir * h.t;
            let scale = (a.abs().max(b.abs()).max(c.abs()) + q.abs()).max_element();
            assert!((p - q).length() <= 1e-3 * scale, "ray {i}: {p} vs {q}");
            assert!((-1e-6..=1.0 + 1e-6).contains(&h.u) && (-1e-6..=1.0 + 1e-6).contains(&h.v));
        }
    }
    assert!(hits > rays.len() / 4, "only {hits} hits");
    for chunk in rays.chunks(16) {
        let packet = RayPacket::from_rays(chunk);
        for mask in [0xFFFFu16, 0x0001, 0x8421, 0] {
            let mask = mask & ((1u32 << chunk.len()) - 1) as u16;
            let got = accel.intersect_packet(&packet, mask);
            let occ = accel.occluded_packet(&packet, mask);
            for lane in 0..16 {
                let on = mask & (1 << lane) != 0;
                let want = if on {
                    accel.intersect(&chunk[lane])
                } else {
                    None
                };
                assert_eq!(got[lane], want, "mask {mask:#x} lane {lane}");
                let want_occ = on && accel.occluded(&chunk[lane]);
                assert_eq!(
                    occ & (1 << lane) != 0,
                    want_occ,
                    "mask {mask:#x} lane {lane}"
                );
            }
        }
    }
    // Packets from one point, as a camera's (which stay the kd packets
    // where the wide boxes are built; the rays above start apart).
    for chunk in rays.chunks(16) {
        let camera: Vec<Ray> = chunk
            .iter()
            .map(|r| Ray {
                origin: chunk[0].origin,
                ..*r
            })
            .collect();
        let got = accel.intersect_packet(&RayPacket::from_rays(&camera), 0xFFFF);
        for (lane, ray) in camera.iter().enumerate() {
            assert_eq!(got[lane], expected(scene, ray), "camera lane {lane}");
        }
    }
    assert_tracer_matches(accel, rays);
}

/// The borrowing tracer answers what the per-call methods answer, ray by
/// ray and packet by packet (so brute force's hits too).
fn assert_tracer_matches(accel: &Accel, rays: &[Ray]) {
    let tracer = accel.tracer();
    for (i, ray) in rays.iter().enumerate() {
        assert_eq!(tracer.intersect(ray), accel.intersect(ray), "ray {i}");
        assert_eq!(tracer.occluded(ray), accel.occluded(ray), "ray {i}");
    }
    // Rays from a hit's context: the records of the root walk, for the
    // rays that leave the hit point (short and long, every octant) and
    // for unrelated rays.
    let mut from_hits = 0;
    for (i, ray) in rays.iter().enumerate() {
        let with = tracer.intersect_with_context(ray);
        assert_eq!(
            with.as_ref().map(|(h, _)| *h),
            tracer.intersect(ray),
            "ray {i}"
        );
        let Some((hit, ctx)) = with else {
            continue;
        };
        from_hits += 1;
        let n = hit.ng.normalize();
        let n = if n.dot(ray.dir) > 0.0 { -n } else { n };
        let p = ray.origin + ray.dir * hit.t + n * 1e-3;
        for k in 0..8 {
            let d = Vec3::new(
                if k & 1 == 0 { 1.0 } else { -1.0 },
                if k & 2 == 0 { 0.5 } else { -0.5 },
                if k & 4 == 0 { 0.25 } else { -0.75 },
            );
            let r = Ray {
                tmax: if k % 3 == 0 {
                    f32::INFINITY
                } else {
                    2.0 * k as f32
                },
                ..Ray::new(p, d + n)
            };
            assert_eq!(
                tracer.intersect_from(&ctx, &r),
                tracer.intersect(&r),
                "ray {i}.{k}"
            );
            assert_eq!(
                tracer.occluded_from(&ctx, &r),
                tracer.occluded(&r),
                "ray {i}.{k}"
            );
        }
        let other = &rays[(i + 1) % rays.len()];
        assert_eq!(tracer.intersect_from(&ctx, other), tracer.intersect(other));
        assert_eq!(tracer.occluded_from(&ctx, other), tracer.occluded(other));
        let located = tracer.locate(p);
        assert_eq!(
            tracer.occluded_from(&located, other),
            tracer.occluded(other)
        );
    }
    assert!(from_hits > 20, "{from_hits} hits");
    let mut cache = OccluderCache::new();
    for chunk in rays.chunks(16) {
        let packet = RayPacket::from_rays(chunk);
        for mask in [0xFFFFu16, 0x0001, 0x8421, 0x7FFE, 0] {
            assert_eq!(
                tracer.occluded_packet_cached(&packet, mask, &mut cache),
                accel.occluded_packet(&packet, mask),
                "cached, mask {mask:#x}"
            );
            assert_eq!(
                tracer.intersect_packet(&packet, mask),
                accel.intersect_packet(&packet, mask),
                "mask {mask:#x}"
            );
            assert_eq!(
                tracer.occluded_packet(&packet, mask),
                accel.occluded_packet(&packet, mask),
                "mask {mask:#x}"
            );
        }
    }
    // A batch in any order: the rays, and each reversed from half way
    // along (so every octant), interleaved.
    let batch: Vec<Ray> = rays
        .iter()
        .flat_map(|r| {
            let mid = r.origin + r.dir * 0.5 * r.tmax.min(1e3);
            [*r, Ray::new(mid, -r.dir)]
        })
        .collect();
    let mut records = vec![None; batch.len()];
    tracer.intersect_batch(&batch, &mut records);
    let mut blocked = vec![false; batch.len()];
    tracer.occluded_batch(&batch, &mut blocked, &mut cache);
    for (i, r) in batch.iter().enumerate() {
        assert_eq!(records[i], tracer.intersect(r), "batch ray {i}");
        assert_eq!(blocked[i], tracer.occluded(r), "batch ray {i}");
    }
    assert!(records.iter().any(Option::is_some) && blocked.iter().any(|b| !b));
}

fn round_trip(preset: Preset, reorder: bool) {
    let scene = load_scene("nexuiz_dieselpower.obj");
    let options = BuildOptions {
        preset,
        reorder,
        threads: None,
        mem_budget: None,
    };
    let memory = Accel::build(&scene, &options).unwrap();
    assert!(!memory.is_mapped());
    assert_eq!(memory.len(), scene.len());
    let dir = fresh_temp_dir(&format!("{preset:?}-{reorder}"));
    let path = dir.join("scene.kd");
    memory.write(&path).unwrap();
    let mapped = Accel::open(&path).unwrap();
    assert!(mapped.is_mapped());
    mapped.verify().unwrap();
    assert_eq!(mapped.as_bytes(), memory.as_bytes());
    let rays = rays(&memory, 7 + reorder as u64);
    assert_traces_as_brute_force(&scene, &memory, &rays);
    assert_traces_as_brute_force(&scene, &mapped, &rays);
    // Over the wide boxes: the same records and answers.
    for accel in [&memory, &mapped] {
        let boxes = accel.prepare_secondary().unwrap();
        assert!(boxes.bytes() > 0 && accel.secondary_boxes().is_some());
        assert_traces_as_brute_force(&scene, accel, &rays);
    }
    // The header records what was built.
    let file = slimkd::format::KdFile::open(&path, slimkd::format::Check::Verify).unwrap();
    assert_eq!(file.is_reordered(), reorder);
    assert_eq!(
        file.config().preset,
        match preset {
            Preset::Std => slimkd::format::Preset::Std,
            Preset::Fast => slimkd::format::Preset::Fast,
            Preset::Small => slimkd::format::Preset::Small,
        }
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn std_reordered() {
    round_trip(Preset::Std, true);
}

#[test]
fn std_in_input_order() {
    round_trip(Preset::Std, false);
}

#[test]
fn small_reordered() {
    round_trip(Preset::Small, true);
}

#[test]
fn small_in_input_order() {
    round_trip(Preset::Small, false);
}

#[test]
fn fast_reordered() {
    round_trip(Preset::Fast, true);
}

#[test]
fn fast_in_input_order() {
    round_trip(Preset::Fast, false);
}

#[test]
fn fast_on_two_threads() {
    let scene = load_scene("nexuiz_dieselpower.obj");
    let options = BuildOptions {
        preset: Preset::Fast,
        threads: Some(2),
        ..Default::default()
    };
    let accel = Accel::build(&scene, &options).unwrap();
    assert_traces_as_brute_force(&scene, &accel, &rays(&accel, 3));
}

#[test]
fn buffers_keep_their_numbering() {
    let tris = box_mesh(v(0.0, 0.0, 0.0), v(2.0, 3.0, 4.0));
    let vertices: Vec<[f32; 3]> = tris.iter().flatten().map(|p| p.to_array()).collect();
    let indices: Vec<[u32; 3]> = (0..tris.len() as u32)
        .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
        .collect();
    let accel = Accel::from_buffers(&vertices, &indices, &BuildOptions::default()).unwrap();
    let scene = TriangleColumns::from_triangles(&tris).unwrap();
    let mut rays = rays(&accel, 11);
    rays.push(Ray::new(v(1.0, 1.5, -5.0), Vec3::Z));
    assert_traces_as_brute_force(&scene, &accel, &rays);
    let bad = Accel::from_buffers(&vertices, &[[0, 1, 99_999]], &BuildOptions::default());
    assert!(matches!(bad, Err(AccelError::Scene(_))));
}

/// A ray whose interval starts behind its origin breaks the queries'
/// contract (the walks would answer `t = 2` where brute force finds the
/// face behind the origin at `t = -2`): every query of the facade panics
/// on it, naming what it breaks, rather than answer wrongly; a bad lane
/// outside a packet's mask is not traced and not checked, and an empty
/// interval is no error.
#[test]
fn rays_behind_their_origin_panic() {
    let tris = box_mesh(v(0.0, 0.0, 0.0), v(2.0, 3.0, 4.0));
    let scene = TriangleColumns::from_triangles(&tris).unwrap();
    let accel = Accel::build(&scene, &BuildOptions::default()).unwrap();
    let good = Ray::new(v(1.0, 1.5, 2.0), Vec3::Z);
    let bad = Ray {
        tmin: -10.0,
        ..good
    };
    assert_eq!(trace::brute_force(&scene, &bad).t, -2.0);
    assert_eq!(
        bad.check().unwrap_err(),
        Ray { tmin: -0.5, ..good }.check().unwrap_err()
    );
    assert!(Ray { tmin: -0.0, ..good }.check().is_ok());
    assert!(
        Ray {
            tmin: 3.0,
            tmax: 1.0,
            ..good
        }
        .check()
        .is_ok()
    );
    let packet = RayPacket::from_rays(&[good, bad, good]);
    let tracer = accel.tracer();
    let ctx = tracer.locate(good.origin);
    let panics = |name: &str, query: &dyn Fn()| {
        let e = std::panic::catch_unwind(std::panic::AssertUnwindSafe(query)).expect_err(name);
        let msg = e.downcast_ref::<String>().expect("a formatted message");
        assert!(msg.contains("tmin is negative"), "{name}: {msg}");
    };
    panics("intersect", &|| assert!(accel.intersect(&bad).is_some()));
    panics("occluded", &|| assert!(accel.occluded(&bad)));
    panics("packet", &|| {
        assert!(accel.intersect_packet(&packet, 0b111)[0].is_some())
    });
    panics("occluded packet", &|| {
        assert_eq!(accel.occluded_packet(&packet, 0b010), 0)
    });
    panics("context", &|| {
        assert!(tracer.intersect_with_context(&bad).is_some())
    });
    panics("from", &|| {
        assert!(tracer.intersect_from(&ctx, &bad).is_some())
    });
    panics("occluded from", &|| {
        assert!(tracer.occluded_from(&ctx, &bad))
    });
    panics("batch", &|| {
        tracer.intersect_batch(&[good, bad], &mut [None; 2])
    });
    let cache = std::cell::RefCell::new(OccluderCache::new());
    panics("occluded batch", &|| {
        tracer.occluded_batch(&[bad], &mut [false], &mut cache.borrow_mut())
    });
    assert_eq!(accel.intersect(&good).map(|h| h.t), Some(2.0));
    // An empty interval around the hit at t = 2 is a valid query that
    // finds nothing, as brute force finds nothing.
    let empty = Ray {
        tmin: 3.0,
        tmax: 1.0,
        ..good
    };
    assert!(!trace::brute_force(&scene, &empty).is_hit());
    assert_eq!(accel.intersect(&empty), None);
    assert!(!accel.occluded(&empty));
    assert_eq!(accel.occluded_packet(&RayPacket::from_rays(&[empty]), 1), 0);
    assert_eq!(accel.occluded_packet(&packet, 0b101), 0b101);
}

#[test]
fn bad_files_are_errors_naming_the_file() {
    let scene =
        TriangleColumns::from_triangles(&box_mesh(v(0.0, 0.0, 0.0), v(1.0, 1.0, 1.0))).unwrap();
    let accel = Accel::build(&scene, &BuildOptions::default()).unwrap();
    let dir = fresh_temp_dir("bad");
    let bytes = accel.as_bytes();
    let cases: [(&str, Vec<u8>); 4] = [
        ("truncated.kd", bytes[..bytes.len() / 2].to_vec()),
        ("header-only.kd", bytes[..100].to_vec()),
        (
            "garbage.kd",
            (0..bytes.len()).map(|i| (i * 131 % 251) as u8).collect(),
        ),
        ("empty.kd", Vec::new()),
    ];
    for (name, data) in cases {
        let path = dir.join(name);
        std::fs::write(&path, data).unwrap();
        let err = Accel::open(&path).unwrap_err();
        assert_eq!(err.path(), Some(path.as_path()), "{name}: {err}");
        assert!(err.to_string().contains(name), "{name}: {err}");
    }
    let missing = dir.join("missing.kd");
    let err = Accel::open(&missing).unwrap_err();
    assert!(err.to_string().contains("missing.kd"), "{err}");
    let err = accel.write(dir.join("no-such-dir/out.kd")).unwrap_err();
    assert!(err.to_string().contains("no-such-dir"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A memory budget moves the builder's columns to scratch files, never
/// the tree: the image is the same byte for byte.
#[test]
fn a_budget_builds_the_same_image() {
    let scene = load_scene("nexuiz_dieselpower.obj");
    let free = Accel::build(&scene, &BuildOptions::default()).unwrap();
    let options = BuildOptions {
        mem_budget: Some(1 << 16),
        ..Default::default()
    };
    let budgeted = Accel::build(&scene, &options).unwrap();
    assert_eq!(free.as_bytes(), budgeted.as_bytes());
}
