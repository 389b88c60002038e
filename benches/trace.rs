//! Ray-tracing throughput benchmark of the scalar kd-tree traverser.
//!
//! It builds the `sweep` tree of the default scene
//! `scenes/nexuiz_dieselpower.obj` and renders its three views from
//! `scenes/views.txt` at 512x512 with `slimkd::render::trace_frame` and
//! `slimkd::trace::TreeTracer`, once on a one-thread rayon pool and once
//! on the default pool (all threads). It reports millions of primary rays
//! per second (the median of 5 frames after one untimed warm-up frame), the
//! speed-up of all threads over one, and each view's hit count and
//! checksum of hit distances (which must not depend on the thread count).
//!
//! When the environment variable `SLIMKD_SCENES` names a directory holding
//! `stk_black_forest.obj` and `../shared/scenes/views.txt` (relative to the
//! crate root) exists, that scene's three views are traced as well.
//!
//! Run it with `cargo bench --bench trace`, or with the large scene as
//! `SLIMKD_SCENES=~/.cache/slimkd-scenes cargo bench --bench trace`.
//! Passing `-- --quick` times one frame per view and pool.

mod common;

use slimkd::build::{self, BuildConfig, Builder};
use slimkd::render::{self, Camera, View};
use slimkd::scene::TriangleColumns;
use slimkd::trace::TreeTracer;
use std::path::Path;
use std::time::Instant;

/// The image size.
const SIZE: u32 = 512;
/// Timed frames per view and pool (1 with `--quick`).
const REPS: usize = 5;

/// Throughput and result of one view on one pool.
struct PoolRun {
    mrays: f64,
    hits: u64,
    checksum: f64,
}

/// Traces `reps` timed frames (after one warm-up frame) on `pool`.
fn run_on(pool: &rayon::ThreadPool, tracer: &TreeTracer, camera: &Camera, reps: usize) -> PoolRun {
    pool.install(|| {
        let warm = render::trace_frame(tracer, camera);
        let mut rates = Vec::with_capacity(reps);
        let mut last = warm;
        for _ in 0..reps {
            last = render::trace_frame(tracer, camera);
            rates.push(last.mrays_per_s());
        }
        PoolRun {
            mrays: common::median(&rates),
            hits: last.n_hits(),
            checksum: last.checksum(),
        }
    })
}

/// Builds the tree of a scene and traces its views on both pools; returns
/// one table line per view.
fn bench_scene(
    name: &str,
    scene: &TriangleColumns,
    views: &[&View],
    pools: &Pools,
    reps: usize,
) -> Vec<String> {
    let start = Instant::now();
    let tree =
        build::build(scene, &BuildConfig::default(), Builder::Sweep, None).expect("the std build");
    println!(
        "{name}: {} triangles, sweep tree built in {:.2} s ({} nodes)",
        scene.len(),
        start.elapsed().as_secs_f64(),
        tree.nodes.len()
    );
    let tracer = TreeTracer { tree: &tree, scene };
    let mut rows = Vec::with_capacity(views.len());
    for view in views {
        let camera = Camera::from_view(view, SIZE, SIZE);
        let one = run_on(&pools.one, &tracer, &camera, reps);
        let all = run_on(&pools.all, &tracer, &camera, reps);
        assert_eq!(
            one.hits, all.hits,
            "the hit count depends on the thread count"
        );
        assert_eq!(
            one.checksum.to_bits(),
            all.checksum.to_bits(),
            "the checksum depends on the thread count"
        );
        rows.push(format!(
            "{:<20} {:>4} {:>12.3} {:>12.3} {:>8.2}x {:>8} {:>6.2}% {:>18.6}",
            name,
            view.id,
            one.mrays,
            all.mrays,
            all.mrays / one.mrays,
            one.hits,
            100.0 * one.hits as f64 / f64::from(SIZE * SIZE),
            one.checksum
        ));
    }
    rows
}

/// A one-thread pool and the default pool (all threads).
struct Pools {
    one: rayon::ThreadPool,
    all: rayon::ThreadPool,
}

/// The views of the scene `stem` in a views file.
fn views_of<'a>(views: &'a [View], stem: &str) -> Vec<&'a View> {
    views.iter().filter(|v| v.scene == stem).collect()
}

fn read_views(path: &Path) -> Vec<View> {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    render::parse_views(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn main() {
    let quick = common::quick();
    let reps = if quick { 1 } else { REPS };
    let pools = Pools {
        one: rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("a one-thread pool"),
        all: rayon::ThreadPoolBuilder::new()
            .build()
            .expect("the default pool"),
    };

    // The default scene with its views from the crate's views file.
    let loaded = common::load(&common::crate_path("scenes/nexuiz_dieselpower.obj"));
    let views = read_views(&common::crate_path("scenes/views.txt"));
    println!(
        "{}: {}, loaded in {:.2} s",
        loaded.name, loaded.summary, loaded.seconds
    );
    let default_views = views_of(&views, &loaded.name);
    assert_eq!(
        default_views.len(),
        3,
        "scenes/views.txt has three views of the default scene"
    );
    let mut rows = bench_scene(&loaded.name, &loaded.scene, &default_views, &pools, reps);
    drop(loaded);

    // The large scene, when both it and the shared views file are there.
    if let Some(path) = common::big_scene() {
        let views_path = common::crate_path("../shared/scenes/views.txt");
        if views_path.is_file() {
            let views = read_views(&views_path);
            let loaded = common::load(&path);
            println!(
                "{}: {}, loaded in {:.2} s",
                loaded.name, loaded.summary, loaded.seconds
            );
            let big_views = views_of(&views, &loaded.name);
            if big_views.is_empty() {
                println!(
                    "note: {} has no views of {}; skipping it",
                    views_path.display(),
                    loaded.name
                );
            } else {
                rows.extend(bench_scene(
                    &loaded.name,
                    &loaded.scene,
                    &big_views,
                    &pools,
                    reps,
                ));
            }
        } else {
            println!(
                "note: {} does not exist; skipping {}",
                views_path.display(),
                common::BIG_SCENE
            );
        }
    }

    println!();
    println!(
        "primary rays, {SIZE}x{SIZE}, scalar TreeTracer, median of {reps} frame(s); 1 thread vs {} threads",
        pools.all.current_num_threads()
    );
    println!(
        "{:<20} {:>4} {:>12} {:>12} {:>9} {:>8} {:>7} {:>18}",
        "scene", "view", "1T Mrays/s", "NT Mrays/s", "speed-up", "hits", "hit %", "checksum"
    );
    for row in &rows {
        println!("{row}");
    }
}
