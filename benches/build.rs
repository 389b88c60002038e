//! Build-speed benchmark of the kd-tree builders.
//!
//! It measures the seconds and the millions of triangles per second (the
//! median of several repetitions) of:
//!
//! - the O(N²) `naive` builder against the O(N log N) `sweep` builder on
//!   deterministic random triangle soups of 1K and 10K triangles, with the
//!   ratio naive/sweep (naive at 10K runs once, since it is slow);
//! - `sweep` on the default scene `scenes/nexuiz_dieselpower.obj`;
//! - `sweep` on `stk_black_forest.obj` (about 1M triangles) when the
//!   environment variable `SLIMKD_SCENES` names a directory holding it; its
//!   load time is reported separately and is not part of the build time.
//!
//! - the breadth-first `level` builder (Wu, Zhao & Liu 2011) on the same
//!   scenes at 1 and 2 threads, with its per-phase times, its 2-thread /
//!   1-thread speed-up and its speed-up over `sweep`; its tree is checked
//!   to equal the sweep tree (untimed).
//!
//! It also checks (untimed) that both builders produce the same tree for
//! the 1K soup, and prints the node, leaf and reference counts of each tree.
//!
//! `SLIMKD_LEVEL_THRESHOLD=N` sets the level builder's small-node
//! threshold; `SLIMKD_MEM_BUDGET=SIZE` (bytes, or with a K, M or G suffix)
//! its column budget, with scratch files in `SLIMKD_SCRATCH` (default: the
//! temporary directory); `SLIMKD_NEW_EVENTS=bucket|merge` how clipped
//! references' events join their child's list (default merge); `-- --level-only` skips the naive and sweep timings (the tree
//! check then builds the sweep tree once, untimed, unless `--no-check`).
//!
//! Run it with `cargo bench --bench build`, or with the large scene as
//! `SLIMKD_SCENES=~/.cache/slimkd-scenes cargo bench --bench build`.
//! Passing `-- --quick` runs everything once and skips naive at 10K.

mod common;

use glam::Vec3;
use slimkd::build::level::{self, LevelOptions, LevelReport, NewEvents};
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::geom::double_area;
use slimkd::scene::TriangleColumns;
use slimkd::tree::TreeIr;
use std::time::Instant;

/// Repetitions of each timed build (1 with `--quick`).
const REPS: usize = 5;
/// Repetitions of the slow naive build of the 10K soup.
const NAIVE_10K_REPS: usize = 1;
/// Repetitions of the build of the large optional scene.
const BIG_REPS: usize = 3;

/// A xorshift64* generator: deterministic, good enough for test geometry.
struct XorShift(u64);

impl XorShift {
    fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// A uniform value in `[0, 1)`.
    fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A soup of `n` small random triangles inside the unit cube. Each
/// triangle's extent is drawn log-uniformly between 0.002 and 0.1, so the
/// soup mixes tiny and larger triangles; zero-area draws are redrawn.
fn random_soup(n: usize, seed: u64) -> TriangleColumns {
    let mut rng = XorShift(seed);
    let mut tris = Vec::with_capacity(n);
    while tris.len() < n {
        let size = 0.002 * 50f32.powf(rng.unit());
        let mut coord = || size + (1.0 - 2.0 * size) * rng.unit();
        let centre = Vec3::new(coord(), coord(), coord());
        let mut corner = || {
            centre
                + size
                    * Vec3::new(
                        2.0 * rng.unit() - 1.0,
                        2.0 * rng.unit() - 1.0,
                        2.0 * rng.unit() - 1.0,
                    )
        };
        let tri = [corner(), corner(), corner()];
        if double_area(&tri) > 0.0 {
            tris.push(tri);
        }
    }
    TriangleColumns::from_triangles(&tris).expect("the soup is finite")
}

/// One timed build: the median seconds over `reps` runs and the last tree.
fn time_build(scene: &TriangleColumns, builder: Algorithm, reps: usize) -> (f64, TreeIr) {
    let config = BuildConfig::default();
    let mut times = Vec::with_capacity(reps);
    let mut tree = None;
    for _ in 0..reps {
        let start = Instant::now();
        let t = build::build(scene, &config, builder, None).expect("the build");
        times.push(start.elapsed().as_secs_f64());
        tree = Some(t);
    }
    (common::median(&times), tree.expect("reps >= 1"))
}

/// One line of the timing table.
struct Timing {
    scene: String,
    triangles: usize,
    builder: &'static str,
    reps: usize,
    seconds: f64,
    /// naive seconds / sweep seconds, on the sweep line.
    ratio: Option<f64>,
}

/// One line of the tree table.
struct TreeLine {
    scene: String,
    builder: &'static str,
    triangles: usize,
    tree: TreeIr,
}

fn builder_name(builder: Algorithm) -> &'static str {
    match builder {
        Algorithm::Naive => "naive",
        Algorithm::WaldHavran => "sweep",
        Algorithm::Level => "level",
    }
}

fn print_timings(rows: &[Timing]) {
    println!(
        "{:<22} {:>9} {:>7} {:>5} {:>11} {:>9} {:>12}",
        "scene", "triangles", "builder", "reps", "median s", "Mtris/s", "naive/sweep"
    );
    for r in rows {
        let ratio = r
            .ratio
            .map_or_else(|| "-".to_string(), |x| format!("{x:.1}x"));
        println!(
            "{:<22} {:>9} {:>7} {:>5} {:>11.4} {:>9.3} {:>12}",
            r.scene,
            r.triangles,
            r.builder,
            r.reps,
            r.seconds,
            r.triangles as f64 / r.seconds / 1e6,
            ratio
        );
    }
}

fn print_trees(lines: &[TreeLine]) {
    println!(
        "{:<22} {:>7} {:>9} {:>9} {:>10} {:>8}",
        "scene", "builder", "nodes", "leaves", "refs", "refs/tri"
    );
    for l in lines {
        println!(
            "{:<22} {:>7} {:>9} {:>9} {:>10} {:>8.2}",
            l.scene,
            l.builder,
            l.tree.nodes.len(),
            l.tree.n_leaves(),
            l.tree.leaf_tris.len(),
            l.tree.leaf_tris.len() as f64 / l.triangles.max(1) as f64
        );
    }
}

/// One timed level build at `threads` threads: the median seconds, the
/// report of the median run and the last tree.
fn time_level(
    scene: &TriangleColumns,
    threads: usize,
    reps: usize,
    options: &LevelOptions,
) -> (f64, LevelReport, TreeIr) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool");
    let config = BuildConfig::default();
    let mut runs = Vec::with_capacity(reps);
    let mut tree = None;
    for _ in 0..reps {
        let start = Instant::now();
        let (t, report) = pool
            .install(|| level::build(scene, &config, None, options))
            .unwrap_or_else(|e| panic!("level build failed: {e}"));
        runs.push((start.elapsed().as_secs_f64(), report));
        tree = Some(t);
    }
    runs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (secs, report) = runs.swap_remove(runs.len() / 2);
    (secs, report, tree.expect("reps >= 1"))
}

/// A size in bytes: digits with an optional K, M or G (binary) suffix.
fn parse_size(s: &str) -> Option<u64> {
    let s = s.trim();
    let (digits, shift) = match s.char_indices().last()? {
        (i, 'K' | 'k') => (&s[..i], 10),
        (i, 'M' | 'm') => (&s[..i], 20),
        (i, 'G' | 'g') => (&s[..i], 30),
        _ => (s, 0),
    };
    digits.parse::<u64>().ok()?.checked_mul(1 << shift)
}

/// One line of the level table.
struct LevelLine {
    scene: String,
    triangles: usize,
    threads: usize,
    reps: usize,
    seconds: f64,
    report: LevelReport,
    /// 1-thread seconds / these seconds.
    speedup: Option<f64>,
    /// sweep seconds / these seconds.
    vs_sweep: Option<f64>,
}

fn print_level(rows: &[LevelLine], threshold: usize) {
    println!(
        "level builder (small-node threshold {threshold}; median of the reps; phases of the median run, seconds)"
    );
    println!(
        "{:<22} {:>9} {:>3} {:>4} {:>8} {:>7} {:>6} {:>7} {:>6} {:>7} {:>6} {:>6} {:>6} {:>6} {:>6} {:>7} {:>8} {:>8} {:>8} {:>11}",
        "scene",
        "triangles",
        "thr",
        "reps",
        "median s",
        "Mtris/s",
        "2t/1t",
        "/sweep",
        "setup",
        "sah",
        "clip",
        "events",
        "leaves",
        "small",
        "asm",
        "levels",
        "anon MiB",
        "(start)",
        "file MiB",
        "scratch MiB"
    );
    for r in rows {
        let p = &r.report.phases;
        let opt = |x: Option<f64>| x.map_or_else(|| "-".to_string(), |x| format!("{x:.2}x"));
        println!(
            "{:<22} {:>9} {:>3} {:>4} {:>8.4} {:>7.3} {:>6} {:>7} {:>6.3} {:>7.3} {:>6.3} {:>6.3} {:>6.3} {:>6.3} {:>6.3} {:>7} {:>8.1} {:>8.1} {:>8.1} {:>11.1}",
            r.scene,
            r.triangles,
            r.threads,
            r.reps,
            r.seconds,
            r.triangles as f64 / r.seconds / 1e6,
            opt(r.speedup),
            opt(r.vs_sweep),
            p.setup_s,
            p.sah_s,
            p.classify_clip_s,
            p.events_s,
            p.leaves_s,
            p.small_s,
            p.assemble_s,
            r.report.levels,
            r.report.peak_rss_anon_bytes as f64 / (1 << 20) as f64,
            r.report.start_rss_anon_bytes as f64 / (1 << 20) as f64,
            r.report.peak_rss_file_bytes as f64 / (1 << 20) as f64,
            r.report.scratch.file_bytes_total as f64 / (1 << 20) as f64
        );
    }
}

fn main() {
    let quick = common::quick();
    let level_only = std::env::args().any(|a| a == "--level-only");
    let no_check = std::env::args().any(|a| a == "--no-check");
    let threshold = std::env::var("SLIMKD_LEVEL_THRESHOLD")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(level::DEFAULT_SMALL_THRESHOLD);
    let mem_budget = std::env::var("SLIMKD_MEM_BUDGET")
        .ok()
        .map(|v| parse_size(&v).unwrap_or_else(|| panic!("SLIMKD_MEM_BUDGET: bad size {v:?}")));
    let level_options = LevelOptions {
        small_threshold: threshold,
        mem_budget,
        scratch_dir: std::env::var_os("SLIMKD_SCRATCH")
            .map(Into::into)
            .unwrap_or_else(std::env::temp_dir),
        new_events: match std::env::var("SLIMKD_NEW_EVENTS").as_deref() {
            Ok("bucket") => NewEvents::Bucket,
            Ok("merge") | Err(_) => NewEvents::SortMerge,
            Ok(v) => panic!("SLIMKD_NEW_EVENTS: {v:?} is not bucket or merge"),
        },
        tiny_threshold: std::env::var("SLIMKD_TINY")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(level::DEFAULT_TINY_THRESHOLD),
        ..LevelOptions::default()
    };
    if let Some(mem_budget) = mem_budget {
        println!("note: level builder column budget {mem_budget} bytes");
    }
    let reps = if quick { 1 } else { REPS };
    let mut timings = Vec::new();
    let mut trees = Vec::new();
    let mut loads = Vec::new();
    let mut level_rows = Vec::new();

    // Naive against sweep on random soups.
    let soups: &[(usize, &str)] = if level_only {
        &[]
    } else {
        &[(1_000, "random 1K"), (10_000, "random 10K")]
    };
    for &(n, label) in soups {
        let scene = random_soup(n, 0x5EED_0000 + n as u64);
        let naive = if n >= 10_000 && quick {
            None
        } else {
            let naive_reps = if n >= 10_000 {
                NAIVE_10K_REPS.min(reps)
            } else {
                reps
            };
            if naive_reps < reps {
                println!(
                    "note: naive on {label} runs {naive_reps} time(s), since it is O(N²) per node"
                );
            }
            Some((naive_reps, time_build(&scene, Algorithm::Naive, naive_reps)))
        };
        let (sweep_s, sweep_tree) = time_build(&scene, Algorithm::WaldHavran, reps);
        // Naive's time over sweep's, where naive ran.
        let ratio = naive.as_ref().map(|(_, (naive_s, _))| naive_s / sweep_s);
        if let Some((naive_reps, (naive_s, naive_tree))) = naive {
            timings.push(Timing {
                scene: label.into(),
                triangles: n,
                builder: builder_name(Algorithm::Naive),
                reps: naive_reps,
                seconds: naive_s,
                ratio: None,
            });
            if n == 1_000 {
                // The sanity check: both builders define the same tree.
                assert!(
                    naive_tree == sweep_tree,
                    "naive and sweep trees differ on {label}"
                );
                sweep_tree
                    .validate(&scene)
                    .expect("the sweep tree is valid");
                println!("check: naive and sweep trees are equal on {label}");
            }
            trees.push(TreeLine {
                scene: label.into(),
                builder: builder_name(Algorithm::Naive),
                triangles: n,
                tree: naive_tree,
            });
        } else {
            println!("note: --quick skips the naive build of {label}");
        }
        timings.push(Timing {
            scene: label.into(),
            triangles: n,
            builder: builder_name(Algorithm::WaldHavran),
            reps,
            seconds: sweep_s,
            ratio,
        });
        trees.push(TreeLine {
            scene: label.into(),
            builder: builder_name(Algorithm::WaldHavran),
            triangles: n,
            tree: sweep_tree,
        });
    }

    // Sweep on the default scene and, when available, on the large one.
    let mut scenes = vec![(common::crate_path("scenes/nexuiz_dieselpower.obj"), reps)];
    if let Some(path) = common::big_scene() {
        scenes.push((path, BIG_REPS.min(reps)));
    }
    for (path, scene_reps) in scenes {
        let loaded = common::load(&path);
        let n = loaded.scene.len();
        let sweep = if level_only {
            (!no_check).then(|| {
                (
                    None,
                    build::build(
                        &loaded.scene,
                        &BuildConfig::default(),
                        Algorithm::WaldHavran,
                        None,
                    )
                    .expect("the build"),
                )
            })
        } else {
            let (seconds, tree) = time_build(&loaded.scene, Algorithm::WaldHavran, scene_reps);
            timings.push(Timing {
                scene: loaded.name.clone(),
                triangles: n,
                builder: builder_name(Algorithm::WaldHavran),
                reps: scene_reps,
                seconds,
                ratio: None,
            });
            Some((Some(seconds), tree))
        };
        // The level builder at 1 and 2 threads.
        let mut one_thread = None;
        for threads in [1, 2] {
            let (seconds, report, tree) =
                time_level(&loaded.scene, threads, scene_reps, &level_options);
            if let Some((_, want)) = &sweep {
                assert!(
                    &tree == want,
                    "level and sweep trees differ on {}",
                    loaded.name
                );
            }
            let speedup = one_thread.map(|s1: f64| s1 / seconds);
            one_thread.get_or_insert(seconds);
            level_rows.push(LevelLine {
                scene: loaded.name.clone(),
                triangles: n,
                threads,
                reps: scene_reps,
                seconds,
                report,
                speedup,
                vs_sweep: sweep.as_ref().and_then(|(s, _)| s.map(|s| s / seconds)),
            });
        }
        if let Some((_, tree)) = sweep {
            println!("check: level and sweep trees are equal on {}", loaded.name);
            trees.push(TreeLine {
                scene: loaded.name.clone(),
                builder: builder_name(Algorithm::WaldHavran),
                triangles: n,
                tree,
            });
        }
        loads.push(loaded);
    }

    println!();
    println!("build time (sequential builders, median of the reps; --quick: {quick})");
    print_timings(&timings);
    println!();
    print_level(&level_rows, threshold);
    println!();
    println!("trees");
    print_trees(&trees);
    println!();
    println!("scene loads (not part of the build times)");
    println!(
        "{:<22} {:>9} {:>10} {:>9}",
        "scene", "triangles", "dropped", "load s"
    );
    for l in &loads {
        println!(
            "{:<22} {:>9} {:>10} {:>9.3}",
            l.name, l.summary.triangles, l.summary.dropped_degenerate, l.seconds
        );
    }
}
