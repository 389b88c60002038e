//! The Wald-Havran builder (Wald & Havran 2006) builds the same tree as the naive
//! O(N²) reference, on random grid-snapped scenes where planar, coincident
//! and flat cases are common.

mod common;

use common::*;
use proptest::prelude::*;
use slimkd::build::BuildConfig;
use slimkd::build::sah::SahParams;

proptest! {
    #![proptest_config(cases(512))]

    #[test]
    fn wald_havran_equals_naive(tris in grid_scene(40)) {
        let scene = columns(&tris);
        build_checked(&scene, &BuildConfig::default());
    }

    #[test]
    fn wald_havran_equals_naive_with_depth_limit(tris in grid_scene(30), depth in 0u32..4) {
        let scene = columns(&tris);
        let config = BuildConfig { sah: SahParams { max_depth: Some(depth), ..SahParams::default() } };
        let tree = build_checked(&scene, &config);
        let stats = slimkd::stats::TreeStats::of(&tree, &config.sah);
        prop_assert!(stats.max_depth <= depth);
    }

    #[test]
    fn wald_havran_equals_naive_with_other_constants(
        tris in grid_scene(30),
        k_t in 1.0f64..40.0,
        k_i in 1.0f64..40.0,
        split_price in prop::sample::select(vec![0.0, 0.1, 1.0, 8.0]),
    ) {
        let scene = columns(&tris);
        let config = BuildConfig { sah: SahParams { k_t, k_i, split_price, ..SahParams::default() } };
        build_checked(&scene, &config);
    }
}

/// Non-grid scenes: random floats, so that clipping produces rounded boxes.
fn float_triangle() -> impl Strategy<Value = [glam::Vec3; 3]> {
    let v = (-10.0f32..10.0, -10.0f32..10.0, -10.0f32..10.0)
        .prop_map(|(x, y, z)| glam::Vec3::new(x, y, z));
    [v.clone(), v.clone(), v]
}

proptest! {
    #![proptest_config(cases(256))]

    #[test]
    fn wald_havran_equals_naive_on_float_scenes(tris in prop::collection::vec(float_triangle(), 1..60)) {
        let scene = columns(&tris);
        build_checked(&scene, &BuildConfig::default());
    }
}

#[test]
fn shipped_bunny_builds_the_same_tree() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj");
    let (scene, _) = slimkd::scene::load_obj(&path).unwrap();
    let tree = build_checked(&scene, &BuildConfig::default());
    assert!(tree.n_leaves() > 100);
}

/// The split price removes splits that save little cost for their bytes:
/// on the shipped bunny the priced tree (levels and sweep alike) is
/// smaller than the unpriced one, its SAH cost within 1 % of it.
#[test]
fn the_split_price_trades_few_cost_for_many_bytes() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj");
    let (scene, _) = slimkd::scene::load_obj(&path).unwrap();
    let of = |split_price| {
        let config = BuildConfig {
            sah: SahParams {
                split_price,
                ..SahParams::default()
            },
        };
        let tree = build_checked(&scene, &config);
        let stats = slimkd::stats::TreeStats::of(&tree, &config.sah);
        (tree.nodes.len(), stats.sah_cost)
    };
    let (free_nodes, free_cost) = of(0.0);
    let (nodes, cost) = of(SahParams::default().split_price);
    assert!(
        nodes * 10 < free_nodes * 9,
        "{nodes} against {free_nodes} nodes"
    );
    assert!(cost < free_cost * 1.01, "SAH {cost} against {free_cost}");
}
