//! The 4×4 packet traverser returns exactly the scalar traverser's hits (t
//! and triangle id) on every ray, with every instruction set this CPU has,
//! over in-memory trees and over `.kd` files.

mod common;

use common::*;
use proptest::prelude::*;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, KdFile, WriteOptions};
use slimkd::geom::Ray;
use slimkd::render::{self, Camera};
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{self, ClosestHit, Hit, TreeTracer};

fn check_packets(src: &impl trace::KdSource, rays: &[Ray; 16]) {
    let want: Vec<Hit> = rays.iter().map(|r| trace::traverse(src, r)).collect();
    for level in SimdLevel::available() {
        let tracer = PacketTracer::with_level(src, level);
        let mut got = [Hit::MISS; 16];
        tracer.closest_hit_4x4(rays, &mut got);
        assert_eq!(got.to_vec(), want, "{level:?}");
    }
}

proptest! {
    #![proptest_config(cases(384))]

    #[test]
    fn packets_equal_scalar_and_brute_force(
        (tris, packets) in (1i32..=6).prop_flat_map(|g| (
            prop::collection::vec(grid_triangle(g), 0..=60),
            prop::collection::vec(packet(g), 1..6),
        ))
    ) {
        let scene = columns(&tris);
        let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        let src = TreeTracer { tree: &tree, scene: &scene };
        for rays in &packets {
            check_packets(&src, rays);
            for r in rays {
                prop_assert_eq!(trace::traverse(&src, r), trace::brute_force(&scene, r));
            }
        }
        // The same through a file, reordered or not.
        for reorder in [false, true] {
            let bytes = format::write_to_vec(&tree, &scene, &WriteOptions { reorder, ..Default::default() }).unwrap();
            let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
            file.verify().unwrap();
            for rays in &packets {
                check_packets(&file, rays);
                for r in rays {
                    prop_assert_eq!(trace::traverse(&file, r), trace::brute_force(&scene, r));
                }
            }
        }
    }
}

#[test]
fn shipped_scene_frames_are_identical_in_every_mode() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let path = root.join("scenes/nexuiz_dieselpower.obj");
    let (scene, _) = slimkd::scene::load_obj(&path).unwrap();
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    let views =
        render::parse_views(&std::fs::read_to_string(root.join("scenes/views.txt")).unwrap())
            .unwrap();
    let ir = TreeTracer {
        tree: &tree,
        scene: &scene,
    };
    let bytes = format::write_to_vec(
        &tree,
        &scene,
        &WriteOptions {
            reorder: true,
            ..Default::default()
        },
    )
    .unwrap();
    let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
    for id in ["1", "2", "3"] {
        let cam = Camera::from_view(render::find_view(&views, &path, id).unwrap(), 67, 45);
        let want = render::trace_frame(&ir, &cam);
        assert!(want.n_hits() > 1000);
        for level in SimdLevel::available() {
            assert_eq!(
                render::trace_frame(&PacketTracer::with_level(&ir, level), &cam).hits,
                want.hits,
                "view {id} {level:?}"
            );
            assert_eq!(
                render::trace_frame(&PacketTracer::with_level(&file, level), &cam).hits,
                want.hits,
                "file view {id} {level:?}"
            );
        }
        assert_eq!(
            render::trace_frame(&trace::Scalar::new(&file), &cam).hits,
            want.hits
        );
    }
}
