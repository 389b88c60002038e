//! The ray–triangle test at the scales of finite `f32` scenes: the edge
//! functions grow with the square of the scale and the distance with its
//! cube, so the `f32` arithmetic over- and underflows far inside the `f32`
//! range. Held against an `f64` reference written out here (the same
//! sheared-edge test in `f64` throughout, on the same `f32` inputs), and
//! every traverser against brute force, at scales 10^-30 … 10^30 (the
//! walks over wide boxes too, whose leaves test their triangles in lanes
//! and hand the lanes that need `f64` to the scalar test).

mod common;

use common::*;
use glam::{DVec3, Vec3};
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::geom::{Ray, intersect_ray_triangle};
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::wide::{WideBoxes, WideTracer};
use slimkd::trace::{self, ClosestHit, Hit, KdSource, TreeTracer};

/// The reference: barycentrics and distance in `f64` (Möller–Trumbore, a
/// different algorithm from the watertight test), or `None` for a miss or
/// a ray too close to an edge for hit or miss to be clear-cut.
fn reference(ray: &Ray, tri: &[Vec3; 3]) -> Option<Option<f64>> {
    let o = ray.origin.as_dvec3();
    let d = ray.dir.as_dvec3();
    let [a, b, c] = tri.map(|p| p.as_dvec3());
    let (e1, e2) = (b - a, c - a);
    let p = d.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 {
        return Some(None);
    }
    let s = o - a;
    let u = s.dot(p) / det;
    let q = s.cross(e1);
    let v = d.dot(q) / det;
    let t = e2.dot(q) / det;
    let margin = 1e-3;
    if [u, v, 1.0 - u - v].iter().any(|&x| x.abs() < margin) {
        return None;
    }
    let inside = u > 0.0 && v > 0.0 && u + v < 1.0;
    Some((inside && t > f64::from(ray.tmin)).then_some(t))
}

/// Rays from `eye` towards a `n`×`n` grid over the square of half-size
/// `s` around `center` in the plane z = `center.z`, directions of unit
/// length (so `t` is a distance of the scale of the scene).
fn fan(eye: DVec3, center: DVec3, s: f64, n: usize) -> Vec<Ray> {
    let mut rays = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let x = ((i as f64 + 0.5) / n as f64 * 2.0 - 1.0) * 1.5 * s;
            let y = ((j as f64 + 0.5) / n as f64 * 2.0 - 1.0) * 1.5 * s;
            let dir = (center + DVec3::new(x, y, 0.0) - eye).normalize();
            rays.push(Ray::new(eye.as_vec3(), dir.as_vec3()));
        }
    }
    rays
}

/// One triangle of half-size S seen from 3S, slanted so that the shear is
/// not trivial: the watertight test hits exactly where the `f64` reference
/// does, with `t` to `f32` precision, at every decade 10^-30 … 10^30 (the
/// `f32` test alone hits nothing below 10^-16 and above 6·10^12).
#[test]
fn one_triangle_hits_at_every_scale() {
    for e in -30..=30 {
        let s = 10f64.powi(e);
        let tri = [
            DVec3::new(-s, -s, 0.2 * s),
            DVec3::new(s, -s, -0.1 * s),
            DVec3::new(0.0, s, 0.0),
        ]
        .map(|p| p.as_vec3());
        let eye = DVec3::new(0.4 * s, 0.3 * s, -3.0 * s);
        let rays = fan(eye, DVec3::ZERO, s, 18);
        let mut hits = 0;
        for ray in &rays {
            let Some(want) = reference(ray, &tri) else {
                continue;
            };
            let got = intersect_ray_triangle(ray, &tri);
            assert_eq!(got.is_some(), want.is_some(), "scale 1e{e}, ray {ray:?}");
            if let (Some(t), Some(w)) = (got, want) {
                let err = (f64::from(t) - w).abs() / w;
                assert!(err < 1e-5, "scale 1e{e}: t {t} against {w}");
                hits += 1;
            }
        }
        // The triangle covers 2/9 of the fan's square: 71 of its 324 rays
        // hit at S = 1, and as many at every scale.
        assert!(hits >= 70, "scale 1e{e}: {hits} hits");
    }
}

/// Boxes at 10^-30, 1 and 10^30 in one scene (and each alone): the tree,
/// the scalar traverser and the packets of every instruction set return
/// brute force's hits, and those are the reference's.
#[test]
fn scenes_at_extreme_scales_trace_like_the_reference() {
    let scales = [1e-30f64, 1e-16, 1.0, 1e14, 1e30];
    let boxes = |s: f64| box_mesh(DVec3::splat(-s).as_vec3(), DVec3::splat(s).as_vec3());
    let mut scenes: Vec<(String, Vec<[Vec3; 3]>)> = scales
        .iter()
        .map(|&s| (format!("box {s:e}"), boxes(s)))
        .collect();
    scenes.push((
        "nested boxes 1e-30 … 1e30".into(),
        scales.iter().flat_map(|&s| boxes(s)).collect(),
    ));
    for (name, tris) in &scenes {
        let scene = columns(tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::Level, None).unwrap();
        let src = TreeTracer {
            tree: &tree,
            scene: &scene,
        };
        let boxes = WideBoxes::new(src.walk()).unwrap();
        let mut hits = 0;
        for &s in &scales {
            // From outside each box towards its front face, and from inside
            // it (every box of the nested scene is around the origin).
            for (eye, center) in [
                (
                    DVec3::new(0.3 * s, -0.2 * s, -3.0 * s),
                    DVec3::new(0.0, 0.0, -s),
                ),
                (
                    DVec3::new(0.1 * s, 0.2 * s, 0.05 * s),
                    DVec3::new(0.0, 0.0, s),
                ),
            ] {
                let rays = fan(eye, center, 0.5 * s, 8);
                for ray in &rays {
                    let w = trace::brute_force(&scene, ray);
                    assert_eq!(trace::traverse(&src, ray), w, "{name}: {ray:?}");
                    check_wide(&src, &boxes, ray, w, name);
                    // Skipped where some triangle's edge is too close.
                    let refs: Option<Vec<Option<f64>>> =
                        tris.iter().map(|t| reference(ray, t)).collect();
                    if let Some(refs) = refs {
                        let t_ref = refs.into_iter().flatten().fold(f64::INFINITY, f64::min);
                        assert_eq!(w.is_hit(), t_ref.is_finite(), "{name}: {ray:?}");
                        if w.is_hit() {
                            let err = (f64::from(w.t) - t_ref).abs() / t_ref;
                            assert!(err < 1e-5, "{name}: t {} against {t_ref}", w.t);
                            hits += 1;
                        }
                    }
                }
                for chunk in rays.chunks_exact(16) {
                    let chunk: &[Ray; 16] = chunk.try_into().unwrap();
                    for level in SimdLevel::available() {
                        let mut got = [Hit::MISS; 16];
                        PacketTracer::with_level(&src, level).closest_hit_4x4(chunk, &mut got);
                        for (g, r) in got.iter().zip(chunk) {
                            assert_eq!(*g, trace::brute_force(&scene, r), "{name} {level:?}");
                        }
                    }
                }
            }
        }
        assert!(hits > 0, "{name}: no hits");
    }
}

/// The single walks over `boxes` on every instruction set: `ray`'s
/// closest hit is brute force's `want`, and it is occluded exactly where
/// that hit lies before its `tmax`.
fn check_wide(src: &impl KdSource, boxes: &WideBoxes, ray: &Ray, want: Hit, name: &str) {
    for level in SimdLevel::available() {
        let tracer = WideTracer::with_level(src, boxes, level);
        assert_eq!(tracer.closest_hit(ray), want, "{name} {level:?}: {ray:?}");
        assert_eq!(
            tracer.occluded(ray),
            want.t < ray.tmax,
            "{name} {level:?} occluded: {ray:?}"
        );
    }
}

/// A box with corners at ±`f32::MAX`, seen from inside: its faces are hit
/// at distances near `f32::MAX` (extents and clip distances overflow to
/// infinity on the way), by every traverser as by brute force and the
/// reference.
#[test]
fn a_box_spanning_the_f32_range_is_hit_from_inside() {
    let m = f32::MAX;
    let tris = box_mesh(Vec3::splat(-m), Vec3::splat(m));
    let scene = columns(&tris);
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::Level, None).unwrap();
    let src = TreeTracer {
        tree: &tree,
        scene: &scene,
    };
    let s = f64::from(m);
    let eye = DVec3::new(0.0, 0.0, 0.1 * s);
    let rays = fan(eye, DVec3::new(0.0, 0.0, 0.5 * s), 0.1 * s, 8);
    let boxes = WideBoxes::new(src.walk()).unwrap();
    let mut hits = 0;
    for ray in &rays {
        let w = trace::brute_force(&scene, ray);
        assert_eq!(trace::traverse(&src, ray), w, "{ray:?}");
        check_wide(&src, &boxes, ray, w, "±f32::MAX box");
        let refs: Option<Vec<Option<f64>>> = tris.iter().map(|t| reference(ray, t)).collect();
        let Some(refs) = refs else { continue };
        let t_ref = refs.into_iter().flatten().fold(f64::INFINITY, f64::min);
        assert!(w.is_hit() && t_ref.is_finite(), "{ray:?}: {w:?}, {t_ref}");
        assert!(
            (f64::from(w.t) - t_ref).abs() / t_ref < 1e-5,
            "{w:?} against {t_ref}"
        );
        hits += 1;
    }
    for chunk in rays.chunks_exact(16) {
        let chunk: &[Ray; 16] = chunk.try_into().unwrap();
        for level in SimdLevel::available() {
            let mut got = [Hit::MISS; 16];
            PacketTracer::with_level(&src, level).closest_hit_4x4(chunk, &mut got);
            for (g, r) in got.iter().zip(chunk) {
                assert_eq!(*g, trace::brute_force(&scene, r), "{level:?}");
            }
        }
    }
    assert!(hits > 32, "{hits} hits");
}
