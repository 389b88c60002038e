//! Any-hit streams (`trace::stream::occluded_stream`) and rays in lanes
//! (`trace::lanes::occluded_lanes`, every instruction set) answer every
//! ray exactly as `closest_hit(ray).t < tmax` by brute force: std and
//! fully hoisted slim trees, in memory and in files, streams that thin
//! out to the scalar walk and streams that stay whole.

mod common;

use common::*;
use glam::Vec3;
use proptest::prelude::*;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, KdFile, WriteOptions};
use slimkd::geom::Ray;
use slimkd::scene::TriangleColumns;
use slimkd::slim::{self, SlimParams};
use slimkd::trace::packet::SimdLevel;
use slimkd::trace::{self, FileWalk, KdSource, TreeTracer};

fn brute(scene: &TriangleColumns, rays: &[Ray]) -> Vec<bool> {
    rays.iter()
        .map(|r| trace::brute_force(scene, r).t < r.tmax)
        .collect()
}

fn check(src: &impl KdSource, scene: &TriangleColumns, rays: &[Ray]) {
    let want = brute(scene, rays);
    let mut got = vec![true; rays.len()];
    trace::stream::occluded_stream(src.walk(), rays, &mut got);
    assert_eq!(got, want);
}

/// Rays in lanes, on every instruction set this CPU has, whole and in
/// batches of fewer rays than lanes.
fn check_lanes<D: AsRef<[u8]> + Sync>(file: &KdFile<D>, scene: &TriangleColumns, rays: &[Ray]) {
    let want = brute(scene, rays);
    for level in SimdLevel::available() {
        for batch in [rays.len().max(1), 5] {
            let mut got = vec![true; rays.len()];
            for (r, o) in rays.chunks(batch).zip(got.chunks_mut(batch)) {
                trace::lanes::occluded_lanes(FileWalk::new(file), level, r, o);
            }
            assert_eq!(got, want, "{level:?}, batches of {batch}");
        }
    }
}

/// Short and long rays from grid points in scattered directions, many
/// from one origin (as a hit point's AO rays are).
fn stream(g: i32) -> impl Strategy<Value = Vec<Ray>> {
    let coord = move || (-1..=2 * g + 1).prop_map(|k| k as f32 * 0.5);
    let point = (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    let dir = (-4i32..=4, -4i32..=4, -4i32..=4)
        .prop_filter("zero direction", |&(x, y, z)| (x, y, z) != (0, 0, 0))
        .prop_map(|(x, y, z)| Vec3::new(x as f32, y as f32, z as f32));
    let ray = (
        point,
        prop::collection::vec((dir, 0.0f32..0.5, 0.1f32..6.0), 1..8),
    );
    prop::collection::vec(ray, 1..12).prop_map(|groups| {
        groups
            .into_iter()
            .flat_map(|(o, dirs)| {
                dirs.into_iter().map(move |(d, tmin, span)| Ray {
                    tmin,
                    tmax: tmin + span,
                    ..Ray::new(o, d)
                })
            })
            .collect()
    })
}

proptest! {
    #![proptest_config(cases(128))]

    #[test]
    fn streams_equal_brute_force(
        (tris, rays) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=60),
            stream(g),
        )),
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        let params = SlimParams { tau_occu: 0.0, tau_freq: 0.0, ..SlimParams::PAPER_SMALL };
        let (slim, _) = slim::slim(&tree, &scene, &BuildConfig::default(), &params);
        for t in [&tree, &slim] {
            check(&TreeTracer { tree: t, scene: &scene }, &scene, &rays);
            for reorder in [false, true] {
                let options = WriteOptions { reorder, ..Default::default() };
                let bytes = format::write_to_vec(t, &scene, &options).unwrap();
                let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
                check(&file, &scene, &rays);
                check_lanes(&file, &scene, &rays);
            }
        }
    }
}

/// A real scene's AO rays in one stream of a thousand: the stream stays
/// whole for many levels before it thins out.
#[test]
fn a_scenes_ao_rays_as_one_stream() {
    let scene = kd::load_scene("bunny_npm.obj");
    let tree = kd::std_tree(&scene);
    let file = kd::read(&kd::write(&tree, &scene, true));
    let mut rng = kd::Rng(5);
    let primary = kd::rays_at(&scene.bounds(), &mut rng, 300);
    let sec = trace::rays::secondary_rays(&scene, &trace::Scalar::new(&file), &primary, 4);
    assert!(sec.ao.len() > 500);
    check(&file, &scene, &sec.ao[..1000.min(sec.ao.len())]);
    check(&file, &scene, &sec.shadow);
    check_lanes(&file, &scene, &sec.ao[..1000.min(sec.ao.len())]);
    check_lanes(&file, &scene, &sec.shadow);
    let (slim, _) = slimkd::slim::slim(
        &tree,
        &scene,
        &BuildConfig::default(),
        &SlimParams {
            tau_occu: 0.0,
            tau_freq: 0.0,
            ..SlimParams::PAPER_SMALL
        },
    );
    let slim_file = kd::read(&kd::write(&slim, &scene, true));
    check_lanes(&slim_file, &scene, &sec.ao[..1000.min(sec.ao.len())]);
}
