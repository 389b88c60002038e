//! Ray-tracing throughput: primary, shadow and ambient-occlusion rays,
//! single rays and 16-ray packets, the tree in memory (`TreeIr`) and mapped
//! from a `.kd` file, down the kd-tree and over the file's wide boxes
//! (`wide`, `wide-pk`: what `Accel::prepare_secondary` switches the facade
//! to; closest-hit packets stay the kd packets there), on one thread and
//! on all.
//!
//! For each scene it builds the std tree, writes it to a temporary `.kd`
//! file and maps it back, and makes three ray sets from view 1 at 512×512:
//! primary rays (row-major, as a ray file holds them), one shadow ray per
//! hit pixel toward a point light near the eye (`--occluded`), and four
//! cosine-distributed ambient-occlusion rays per hit pixel with a radius of
//! 5 % of the scene's diagonal (`--occluded`), like the peer program's
//! `--make-rays`. Each set is traced in chunks of 256 rays
//! ([`slimkd::trace::rays::trace_batch`]); the figure is the median
//! Mrays/s of 5 runs after one warm-up. Every configuration must return
//! the same results as single rays on the file, and the bench asserts it.
//!
//! The default scene is `scenes/nexuiz_dieselpower.obj`; with
//! `SLIMKD_SCENES` naming a directory holding `stk_black_forest.obj` (and
//! `../shared/scenes/views.txt` present), that scene runs too. Run it with
//! `cargo bench --bench trace` (`-- --quick`: one timed run each);
//! `SLIMKD_SIMD=avx2` caps the packets' instruction set.

mod common;

use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, KdFile, WriteOptions};
use slimkd::geom::Ray;
use slimkd::render::{self, Camera, View};
use slimkd::scene::TriangleColumns;
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::rays::{self, Query};
use slimkd::trace::wide::{WideBoxes, WideTracer};
use slimkd::trace::{ClosestHit, KdSource, Scalar, TreeTracer};

const SIZE: u32 = 512;
const REPS: usize = 5;

/// The primary rays of a camera in row-major order, and shadow and
/// ambient-occlusion rays from their hits.
fn ray_sets(
    scene: &TriangleColumns,
    tracer: &dyn ClosestHit,
    camera: &Camera,
) -> [(&'static str, Query, Vec<Ray>); 3] {
    let primary: Vec<Ray> = (0..SIZE * SIZE)
        .map(|i| camera.ray(i % SIZE, i / SIZE))
        .collect();
    let rays::SecondaryRays { shadow, ao } = rays::secondary_rays(scene, tracer, &primary, 4);
    [
        ("primary", Query::Closest, primary),
        ("shadow", Query::Occluded, shadow),
        ("ao", Query::Occluded, ao),
    ]
}

fn bench_scene(
    name: &str,
    scene: &TriangleColumns,
    view: &View,
    reps: usize,
    pools: &[rayon::ThreadPool],
) {
    let tree = build::build(scene, &BuildConfig::default(), Algorithm::Level, None)
        .expect("the std build");
    let bytes = format::write_to_vec(
        &tree,
        scene,
        &WriteOptions {
            reorder: true,
            ..Default::default()
        },
    )
    .expect("the tree is written");
    let path = std::env::temp_dir().join(format!(
        "slimkd-bench-trace-{}-{name}.kd",
        std::process::id()
    ));
    std::fs::write(&path, &bytes).expect("the temporary file is written");
    let file = KdFile::open(&path, format::Check::Header).expect("the file maps");
    std::fs::remove_file(&path).expect("the temporary file is removed");
    let memory = TreeTracer { tree: &tree, scene };
    let camera = Camera::from_view(view, SIZE, SIZE);
    let sets = ray_sets(scene, &Scalar::new(&file), &camera);
    let file_single = Scalar::new(&file);
    let file_packet = PacketTracer::new(&file);
    let mem_single = Scalar::new(&memory);
    let mem_packet = PacketTracer::new(&memory);
    let boxes = WideBoxes::new(file.walk()).expect("the file's nodes form a tree");
    let file_wide = WideTracer::new(&file, &boxes);
    let tracers: [(&str, &str, &dyn ClosestHit, bool); 6] = [
        ("file", "single", &file_single, false),
        ("file", "packet", &file_packet, true),
        ("file", "wide", &file_wide, false),
        ("file", "wide-pk", &file_wide, true),
        ("memory", "single", &mem_single, false),
        ("memory", "packet", &mem_packet, true),
    ];
    println!(
        "{name}: {} triangles, {} nodes; view {}; packets on {}",
        scene.len(),
        tree.nodes.len(),
        view.id,
        SimdLevel::detect().name()
    );
    println!(
        "{:<10} {:>8} {:<7} {:<7} {:>8} {:>12} {:>12}",
        "rays", "count", "source", "mode", "threads", "Mrays/s", "hits"
    );
    for (kind, query, set) in &sets {
        let reference = pools[0].install(|| rays::trace_batch(&file_single, set, *query, false));
        for (source, mode, tracer, packets) in tracers {
            for pool in pools {
                let (rate, results) = pool.install(|| {
                    let mut last = rays::trace_batch(tracer, set, *query, packets);
                    let mut rates = Vec::new();
                    for _ in 0..reps {
                        last = rays::trace_batch(tracer, set, *query, packets);
                        rates.push(last.mrays_per_s());
                    }
                    (common::median(&rates), last)
                });
                assert_eq!(
                    results.results, reference.results,
                    "{kind} {source} {mode}: results differ"
                );
                println!(
                    "{kind:<10} {:>8} {source:<7} {mode:<7} {:>8} {rate:>12.3} {:>12}",
                    set.len(),
                    pool.current_num_threads(),
                    results.hits(*query)
                );
            }
        }
    }
    println!();
}

fn main() {
    let reps = if common::quick() { 1 } else { REPS };
    let pools = [
        rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("a one-thread pool"),
        rayon::ThreadPoolBuilder::new()
            .build()
            .expect("the default pool"),
    ];
    let views_of = |path: &std::path::Path| {
        let text = std::fs::read_to_string(path)
            .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
        render::parse_views(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
    };
    let loaded = common::load(&common::crate_path("scenes/nexuiz_dieselpower.obj"));
    println!(
        "{}: {}, loaded in {:.2} s",
        loaded.name, loaded.summary, loaded.seconds
    );
    let views = views_of(&common::crate_path("scenes/views.txt"));
    let view = views
        .iter()
        .find(|v| v.scene == loaded.name && v.id == "1")
        .expect("view 1 of the default scene");
    bench_scene(&loaded.name, &loaded.scene, view, reps, &pools);
    drop(loaded);
    if let Some(path) = common::big_scene() {
        let views_path = common::crate_path("../shared/scenes/views.txt");
        if views_path.is_file() {
            let views = views_of(&views_path);
            let loaded = common::load(&path);
            println!(
                "{}: {}, loaded in {:.2} s",
                loaded.name, loaded.summary, loaded.seconds
            );
            match views.iter().find(|v| v.scene == loaded.name && v.id == "1") {
                Some(view) => bench_scene(&loaded.name, &loaded.scene, view, reps, &pools),
                None => println!(
                    "note: {} has no view 1 of {}; skipping it",
                    views_path.display(),
                    loaded.name
                ),
            }
        } else {
            println!(
                "note: {} does not exist; skipping {}",
                views_path.display(),
                common::BIG_SCENE
            );
        }
    }
}
