//! Speed and size benchmark of the slim post-pass (Choi et al. 2013).
//!
//! For each scene it builds the standard tree with the level builder on
//! every thread, then runs the slim pass with the `fast` and `small`
//! thresholds under both hoist rules (`bytes`, the presets', and `paper`),
//! and prints, as medians of the repetitions: the std build time, the slim
//! pass time and its ratio to the std build (each ratio within one
//! repetition, so that machine noise cancels as far as it can; in wall
//! time and in CPU time, which a shared machine disturbs less), the pass's
//! phases, what it did, and (untimed) the tree memory of the reordered
//! `.kd` file against std's.
//!
//! Scenes: the default scene `scenes/nexuiz_dieselpower.obj`, and, when
//! `SLIMKD_SCENES` names a directory holding `stk_black_forest.obj`, the
//! shared scenes found there (`nexuiz_aneurysm`,
//! `stk_ravenbridge_mansion`, `stk_candela_city`, `stk_black_forest`).
//! `-- --quick` runs everything once.
//!
//! Run it with `cargo bench --bench slim`, or
//! `SLIMKD_SCENES=~/.cache/slimkd-scenes cargo bench --bench slim`.

mod common;

use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, KdFile, WriteOptions};
use slimkd::scene::TriangleColumns;
use slimkd::slim::{self, SlimParams, SlimPhases, SlimReport};
use slimkd::tree::TreeIr;
use std::time::Instant;

/// Repetitions of each timed build (1 with `--quick`).
const REPS: usize = 5;

/// The other shared scenes looked up beside the large one.
const SHARED: [&str; 3] = [
    "nexuiz_aneurysm.obj",
    "stk_ravenbridge_mansion.obj",
    "stk_candela_city.obj",
];

/// CPU seconds (user + system) of this process so far, from
/// `/proc/self/stat` (0 where it cannot be read). On a shared machine the
/// ratio of CPU times is steadier than the ratio of wall times.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the command name (which is in parentheses): state is
    // field 3, utime and stime are fields 14 and 15, in clock ticks (100
    // per second on Linux).
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

/// Tree memory as the paper counts it, of the reordered `.kd` file.
fn tree_bytes(tree: &TreeIr, scene: &TriangleColumns) -> u64 {
    let options = WriteOptions {
        reorder: true,
        ..Default::default()
    };
    let bytes = format::write_to_vec(tree, scene, &options).expect("the tree can be written");
    let file = KdFile::from_bytes(format::aligned_copy(&bytes)).expect("the file is valid");
    file.figures().tree_bytes()
}

fn bench_scene(name: &str, scene: &TriangleColumns, reps: usize) {
    let config = BuildConfig::default();
    let runs = [
        ("fast", SlimParams::FAST),
        ("small", SlimParams::SMALL),
        ("fast/paper", SlimParams::PAPER_FAST),
        ("small/paper", SlimParams::PAPER_SMALL),
    ];
    let mut std_s = Vec::new();
    let mut slim_s = vec![Vec::new(); runs.len()];
    let mut ratio = vec![Vec::new(); runs.len()];
    let mut cpu_ratio = vec![Vec::new(); runs.len()];
    let mut phases = vec![Vec::<SlimPhases>::new(); runs.len()];
    let mut results: Vec<Option<(TreeIr, SlimReport)>> = vec![None; runs.len()];
    let mut std_tree = None;
    for _ in 0..reps {
        let (start, cpu) = (Instant::now(), cpu_seconds());
        let tree = build::build(scene, &config, Algorithm::Level, None).expect("the std build");
        let s = start.elapsed().as_secs_f64();
        let std_cpu = cpu_seconds() - cpu;
        std_s.push(s);
        for (k, (_, p)) in runs.iter().enumerate() {
            let (start, cpu) = (Instant::now(), cpu_seconds());
            let (slimmed, report, ph) = slim::slim_with_phases(&tree, scene, &config, p);
            let t = start.elapsed().as_secs_f64();
            slim_s[k].push(t);
            ratio[k].push(t / s);
            cpu_ratio[k].push((cpu_seconds() - cpu) / std_cpu);
            phases[k].push(ph);
            results[k] = Some((slimmed, report));
        }
        std_tree = Some(tree);
    }
    let std_tree = std_tree.expect("at least one repetition");
    let std_bytes = tree_bytes(&std_tree, scene);
    println!(
        "{name}: {} triangles, std build {:.3} s (level builder, {} threads), tree {} bytes",
        scene.len(),
        common::median(&std_s),
        rayon::current_num_threads(),
        std_bytes
    );
    println!(
        "  {:<12} {:>8} {:>7} {:>7} {:>9} {:>9} {:>9} {:>9} {:>8} {:>9} {:>9} {:>9} {:>10}",
        "run",
        "slim s",
        "×std",
        "cpu×std",
        "analysis",
        "rebuilds",
        "apply",
        "assembly",
        "hoisted",
        "rejected",
        "skipped",
        "rebuilt",
        "reduction"
    );
    for (k, (label, _)) in runs.iter().enumerate() {
        let ph = &phases[k];
        let med = |f: fn(&SlimPhases) -> f64| common::median(&ph.iter().map(f).collect::<Vec<_>>());
        let (tree, report) = results[k].as_ref().expect("at least one repetition");
        let bytes = tree_bytes(tree, scene);
        println!(
            "  {:<12} {:>8.3} {:>7.2} {:>7.2} {:>9.3} {:>9.3} {:>9.3} {:>9.3} {:>8} {:>9} {:>9} {:>9} {:>9.1}%",
            label,
            common::median(&slim_s[k]),
            common::median(&ratio[k]),
            common::median(&cpu_ratio[k]),
            med(|p| p.analysis_s),
            med(|p| p.rebuild_s),
            med(|p| p.apply_s),
            med(|p| p.assemble_s),
            report.hoisted,
            report.rejected,
            report.skipped,
            report.rebuilds,
            100.0 * (1.0 - bytes as f64 / std_bytes as f64)
        );
    }
}

fn main() {
    let reps = if common::quick() { 1 } else { REPS };
    let default = common::load(&common::crate_path("scenes/nexuiz_dieselpower.obj"));
    bench_scene(&default.name, &default.scene, reps);
    drop(default);
    if let Some(big) = common::big_scene() {
        let dir = big.parent().expect("a file has a directory");
        for name in SHARED {
            let path = dir.join(name);
            if path.is_file() {
                let l = common::load(&path);
                bench_scene(&l.name, &l.scene, reps);
            }
        }
        let l = common::load(&big);
        println!("({}: {}, loaded in {:.1} s)", l.name, l.summary, l.seconds);
        bench_scene(&l.name, &l.scene, reps);
    }
}
