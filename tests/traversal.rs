//! The scalar traverser returns exactly brute force's closest hit (t and
//! triangle id) on grid-snapped scenes, where hit or miss is clear-cut.

mod common;

use common::*;
use proptest::prelude::*;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::geom::Ray;
use slimkd::trace;

proptest! {
    #![proptest_config(cases(512))]

    #[test]
    fn traversal_equals_brute_force(
        (tris, rays) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=60),
            prop::collection::vec(grid_ray(g), 1..40),
        ))
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        for ray in &rays {
            let want = trace::brute_force(&scene, ray);
            let got = trace::closest_hit(&tree, &scene, ray);
            prop_assert_eq!(got, want, "ray {:?}", ray);
        }
    }

    #[test]
    fn traversal_respects_tmin_and_tmax(
        (tris, rays) in (1i32..=4).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 1..=30),
            prop::collection::vec(grid_ray(g), 1..20),
        )),
        tmin in 0.0f32..2.0,
        span in 0.0f32..4.0,
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        for ray in &rays {
            let ray = Ray { tmin, tmax: tmin + span, ..*ray };
            let want = trace::brute_force(&scene, &ray);
            let got = trace::closest_hit(&tree, &scene, &ray);
            prop_assert_eq!(got, want);
            if got.is_hit() {
                prop_assert!(got.t > ray.tmin && got.t <= ray.tmax);
            }
        }
    }
}

#[test]
fn bunny_rays_match_brute_force() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj");
    let (scene, _) = slimkd::scene::load_obj(&path).unwrap();
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    let b = scene.bounds();
    let mut hits = 0;
    let mut rays = Vec::new();
    for i in 0..40 {
        for j in 0..40 {
            let u = (i as f32 + 0.5) / 40.0;
            let v = (j as f32 + 0.5) / 40.0;
            let target = b.min + (b.max - b.min) * glam::Vec3::new(u, v, 0.5);
            for o in [
                b.min - 1.0,
                b.max + 1.0,
                glam::Vec3::new(b.min.x - 1.0, b.max.y + 1.0, b.center().z),
            ] {
                rays.push(Ray::new(o, target - o));
            }
        }
    }
    for ray in &rays {
        let want = trace::brute_force(&scene, ray);
        assert_eq!(trace::closest_hit(&tree, &scene, ray), want);
        hits += usize::from(want.is_hit());
    }
    // The test means something only if many rays hit.
    assert!(hits > rays.len() / 4, "{hits} of {}", rays.len());
}
