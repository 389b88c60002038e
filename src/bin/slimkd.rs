//! The `slimkd` command line: build a kd-tree for a scene, store it as a
//! `.kd` file, inspect and verify files, render, and report figures.
//! Without arguments it runs the main job on the embedded default scene.
//! Exit codes: 0 success, 1 failure (bad input, invalid file, I/O), 2 bad
//! usage.

use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use slimkd::build::{self, BuildConfig, Builder, level};
use slimkd::format::{self, KdFile, Mapped, Preset, WriteOptions};
use slimkd::pipeline::{self, figures_json, merge_json};
use slimkd::progress::Progress;
use slimkd::render::{self, Camera, HitBuffer, Shading, View};
use slimkd::scene::{self, LoadSummary, TriangleColumns};
use slimkd::slim::{self, HoistRule, SlimParams, SlimPhases, SlimReport};
use slimkd::stats::bytes::ByteSplit;
use slimkd::stats::{TreeStats, report};
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{BruteForce, ClosestHit, Scalar, TreeTracer};
use slimkd::tree::TreeIr;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// The embedded default scene: nexuiz_dieselpower (see scenes/README.md).
const DEFAULT_SCENE_NAME: &str = "nexuiz_dieselpower.obj";
const DEFAULT_SCENE: &[u8] = include_bytes!("../../scenes/nexuiz_dieselpower.obj");
const DEFAULT_VIEWS: &str = include_str!("../../scenes/views.txt");
/// The name that selects the embedded scene on the command line.
const DEFAULT_ARG: &str = "default";

#[derive(Parser)]
#[command(
    name = "slimkd",
    version,
    about = "Build, store and trace SAH kd-trees for large triangle scenes.",
    long_about = "Build, store and trace SAH kd-trees for large triangle scenes.\n\n\
        Without a command, builds the tree of the embedded default scene, prints a summary, \
        renders slimkd.png into the current directory and prints Mrays/s.\n\n\
        SCENE is an OBJ file, a scene cache (.kds, made by `slimkd convert`), or `default` \
        for the embedded scene."
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Build the standard SAH kd-tree of a scene; print its figures and
    /// optionally write it as a .kd file.
    Build {
        /// OBJ file, scene cache (.kds, see `convert`), or `default`.
        scene: PathBuf,
        #[command(flatten)]
        build: BuildArgs,
        /// Write the tree and its geometry to this .kd file (atomically).
        #[arg(short = 'o', long)]
        output: Option<PathBuf>,
        /// Renumber triangles in Morton order before writing, so that most
        /// leaves fit 2-byte mode.
        #[arg(long)]
        reorder: bool,
        /// Print one JSON object instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Render a scene (built on the fly) or a .kd file.
    Render(Box<RenderArgs>),
    /// Print the header and figures of a .kd file.
    Info {
        file: PathBuf,
        /// Print one JSON object instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Check a .kd file completely, checksums included; exit 0 if valid.
    Verify { file: PathBuf },
    /// Parse a scene once and write it as a binary scene cache (.kds),
    /// which every command reads instead of the OBJ in a fraction of the
    /// time (the same triangles, bit for bit).
    Convert {
        /// OBJ file, or `default`.
        scene: PathBuf,
        /// The scene cache to write (atomically); its name must end in .kds.
        #[arg(short = 'o', long)]
        output: PathBuf,
    },
    /// Write the paper's tables and figures (Choi et al. 2013, Tables 1–4,
    /// Figures 5–6) for std, fast and small trees of the given scenes.
    Report(ReportArgs),
}

#[derive(clap::Args)]
struct ReportArgs {
    /// OBJ files or scene caches (.kds), or `default`.
    #[arg(required = true)]
    scenes: Vec<PathBuf>,
    /// Views file; each scene is matched by its file stem. Without it the
    /// embedded views are used (and scenes without views get the default
    /// camera).
    #[arg(long)]
    views: Option<PathBuf>,
    /// Image size WxH of the timed frames.
    #[arg(long, value_parser = parse_size, default_value = "512x512")]
    size: (u32, u32),
    /// Frames per measurement (median).
    #[arg(long, default_value_t = 3)]
    reps: usize,
    /// Threads for the "all threads" columns (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Also run the τ_occu × τ_freq threshold sweep (Figure 5).
    #[arg(long)]
    sweep: bool,
    /// The hoist rule of the fast, small and sweep trees (see `build
    /// --hoist-rule`; the report writes reordered files).
    #[arg(long, value_enum, default_value_t = HoistRuleArg::Bytes)]
    hoist_rule: HoistRuleArg,
    /// The Markdown report; report.json and the SVG figures go beside it.
    #[arg(short = 'o', long, default_value = "report.md")]
    output: PathBuf,
}

#[derive(clap::Args, Clone)]
struct BuildArgs {
    /// Which builder to run (all produce the same tree).
    #[arg(long, value_enum, default_value_t = BuilderArg::Level)]
    builder: BuilderArg,
    /// Level builder: bytes of per-level columns kept in RAM (e.g. 1G,
    /// 512M); above it they go to mapped scratch files. Default: no limit.
    #[arg(long, value_parser = parse_bytes)]
    mem_budget: Option<u64>,
    /// Level builder: directory for scratch files (default: the system
    /// temporary directory).
    #[arg(long)]
    scratch: Option<PathBuf>,
    /// Level builder: how the events of clipped references join their
    /// child's sorted list (the same tree either way; for measurements).
    #[arg(long, value_enum, default_value_t = NewEventsArg::Merge)]
    new_events: NewEventsArg,
    /// Level builder: the depth-first finisher sweeps nodes of at most this
    /// many references without event lists (0 to 64; the same tree either
    /// way; for measurements).
    #[arg(long, default_value_t = level::DEFAULT_TINY_THRESHOLD as u8,
          value_parser = clap::value_parser!(u8).range(0..=64))]
    tiny: u8,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Depth limit (default: 8 + 1.3·log2 N).
    #[arg(long)]
    max_depth: Option<u32>,
    /// Tree preset: `std` (no hoisting), `fast` (τ_occu 0.9, τ_freq 0.7),
    /// `small` (0.5, 0.4); max_t2rn 4 (Choi et al. 2013), with the hoist
    /// rule of --hoist-rule.
    #[arg(long, value_enum, default_value_t = PresetArg::Std)]
    preset: PresetArg,
    /// When a picked triangle is hoisted. `bytes` (the presets' rule, a
    /// deviation from the paper): only if the rebuilt subtree plus the
    /// 8-byte T-reference is smaller than the subtree it replaces, counted
    /// as the file stores it (2-byte leaves with the file's triangle
    /// numbering, so --reorder matters); otherwise the node keeps its
    /// subtree. `paper`: always (Algorithm 1 as published). With `paper`,
    /// the file records the preset as custom.
    #[arg(long, value_enum, default_value_t = HoistRuleArg::Bytes)]
    hoist_rule: HoistRuleArg,
    /// Occupancy threshold (overrides the preset's; implies hoisting).
    #[arg(long)]
    tau_occu: Option<f64>,
    /// Frequency threshold (overrides the preset's; implies hoisting).
    #[arg(long)]
    tau_freq: Option<f64>,
    /// Most hoisted triangles on a root path (overrides the preset's).
    #[arg(long)]
    max_t2rn: Option<u32>,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum HoistRuleArg {
    /// Keep a hoist only if it makes the tree smaller in bytes.
    Bytes,
    /// Hoist every picked triangle (the paper's Algorithm 1).
    Paper,
}

impl HoistRuleArg {
    /// The rule, counting bytes for a file written with or without
    /// reordering.
    fn rule(self, reordered: bool) -> HoistRule {
        match self {
            HoistRuleArg::Bytes => HoistRule::Bytes { reordered },
            HoistRuleArg::Paper => HoistRule::Paper,
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum PresetArg {
    Std,
    Fast,
    Small,
}

impl BuildArgs {
    /// The slim parameters, if any hoisting is asked for, and the preset
    /// recorded in the file; `reordered`: whether the tree will be written
    /// with reordering (for the byte rule).
    fn slim(&self, reordered: bool) -> (Option<SlimParams>, Preset) {
        let base = match self.preset {
            PresetArg::Std => None,
            PresetArg::Fast => Some(SlimParams::FAST),
            PresetArg::Small => Some(SlimParams::SMALL),
        };
        let custom = self.tau_occu.is_some()
            || self.tau_freq.is_some()
            || self.max_t2rn.is_some()
            || self.hoist_rule == HoistRuleArg::Paper;
        let mut p = base.unwrap_or(SlimParams::SMALL);
        p.rule = self.hoist_rule.rule(reordered);
        if let Some(v) = self.tau_occu {
            p.tau_occu = v;
        }
        if let Some(v) = self.tau_freq {
            p.tau_freq = v;
        }
        if let Some(v) = self.max_t2rn {
            p.max_t2rn = v;
        }
        match (base, custom) {
            (None, false) => (None, Preset::Std),
            (_, true) => (Some(p), Preset::Custom),
            (Some(_), false) => (
                Some(p),
                if self.preset == PresetArg::Fast {
                    Preset::Fast
                } else {
                    Preset::Small
                },
            ),
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum BuilderArg {
    /// Breadth-first, parallel (Wu, Zhao & Liu 2011).
    Level,
    /// Sequential O(N log N) sweep (Wald & Havran 2006).
    Sweep,
    /// The O(N²)-per-node reference.
    Naive,
}

#[derive(Clone, Copy, ValueEnum)]
enum NewEventsArg {
    /// Sort them and merge them in from the back.
    Merge,
    /// Wu et al.'s bucket sort, the inherited events as buckets.
    Bucket,
}

/// Parses a byte count: a number with an optional K, M, G or T suffix
/// (powers of 1024).
fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let (num, shift) = match t.chars().last().map(|c| c.to_ascii_uppercase()) {
        Some('K') => (&t[..t.len() - 1], 10),
        Some('M') => (&t[..t.len() - 1], 20),
        Some('G') => (&t[..t.len() - 1], 30),
        Some('T') => (&t[..t.len() - 1], 40),
        _ => (t, 0),
    };
    let n: f64 = num
        .trim()
        .parse()
        .map_err(|_| format!("expected a size like 512M or 2G, got `{s}`"))?;
    if !(n >= 0.0 && n.is_finite()) {
        return Err(format!("size `{s}` out of range"));
    }
    Ok((n * (1u64 << shift) as f64) as u64)
}

#[derive(Clone, Copy, ValueEnum)]
enum ShadingArg {
    EyeLight,
    Normals,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ModeArg {
    /// Scalar traversal, one ray at a time.
    Single,
    /// 4×4 SIMD ray packets.
    Packet,
    /// Brute force: every ray against every triangle (reference).
    Brute,
}

impl ModeArg {
    fn name(self) -> &'static str {
        match self {
            ModeArg::Single => "single",
            ModeArg::Packet => "packet",
            ModeArg::Brute => "brute",
        }
    }
}

#[derive(clap::Args)]
struct RenderArgs {
    /// OBJ file, scene cache (.kds), `default`, or a .kd file written by
    /// `slimkd build -o`.
    scene: PathBuf,
    #[command(flatten)]
    build: BuildArgs,
    /// Camera position x,y,z.
    #[arg(long, value_parser = parse_dvec3, allow_hyphen_values = true)]
    eye: Option<glam::DVec3>,
    /// Point looked at x,y,z.
    #[arg(long, value_parser = parse_dvec3, allow_hyphen_values = true)]
    at: Option<glam::DVec3>,
    /// Up vector x,y,z.
    #[arg(long, value_parser = parse_dvec3, allow_hyphen_values = true)]
    up: Option<glam::DVec3>,
    /// Vertical field of view in degrees.
    #[arg(long)]
    fov: Option<f64>,
    /// Image size WxH.
    #[arg(long, value_parser = parse_size, default_value = "1024x1024")]
    size: (u32, u32),
    /// Views file (`SCENE VIEW_ID eye=… at=… up=… fov=…`); the embedded
    /// scene's views are used when omitted.
    #[arg(long)]
    views: Option<PathBuf>,
    /// View id in the views file, matched with the scene file's stem.
    #[arg(long)]
    view: Option<String>,
    /// Traversal mode.
    #[arg(long, value_enum, default_value_t = ModeArg::Single)]
    mode: ModeArg,
    /// Frames to trace; Mrays/s is the median.
    #[arg(long, default_value_t = 1)]
    reps: usize,
    /// Output image (.png, or .exr with a depth channel).
    #[arg(short = 'o', long)]
    output: Option<PathBuf>,
    /// Write W·H little-endian f32 hit distances (+inf for a miss).
    #[arg(long)]
    dump_t: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = ShadingArg::EyeLight)]
    shading: ShadingArg,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

fn parse_dvec3(s: &str) -> Result<glam::DVec3, String> {
    render::parse_vec3(s).ok_or_else(|| format!("expected x,y,z with finite numbers, got `{s}`"))
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or("expected WxH")?;
    let w: u32 = w.parse().map_err(|_| format!("bad width in `{s}`"))?;
    let h: u32 = h.parse().map_err(|_| format!("bad height in `{s}`"))?;
    if w == 0 || h == 0 || u64::from(w) * u64::from(h) > 1 << 28 {
        return Err(format!("size `{s}` out of range"));
    }
    Ok((w, h))
}

type Res<T> = Result<T, Box<dyn std::error::Error + Send + Sync>>;

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        None => main_job(),
        Some(Command::Build {
            scene,
            build,
            output,
            reorder,
            json,
        }) => cmd_build(&scene, &build, output.as_deref(), reorder, json),
        Some(Command::Render(args)) => cmd_render(&args),
        Some(Command::Info { file, json }) => cmd_info(&file, json),
        Some(Command::Verify { file }) => cmd_verify(&file),
        Some(Command::Convert { scene, output }) => cmd_convert(&scene, &output),
        Some(Command::Report(args)) => cmd_report(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("slimkd: error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn pool(threads: Option<usize>) -> Res<rayon::ThreadPool> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        if n == 0 {
            return Err("--threads must be at least 1".into());
        }
        b = b.num_threads(n);
    }
    Ok(b.build()?)
}

struct Loaded {
    path: PathBuf,
    scene: TriangleColumns,
    summary: LoadSummary,
    seconds: f64,
}

/// Loads a scene; a progress bar shows the bytes read once loading has
/// taken a second, unless `quiet`.
fn load(path: &Path, quiet: bool) -> Res<Loaded> {
    let start = Instant::now();
    let (scene, summary, path) = if path.as_os_str() == DEFAULT_ARG {
        let name = scene::embedded_name(DEFAULT_SCENE_NAME);
        let (s, m) = scene::load_obj_bytes(&name, DEFAULT_SCENE)?;
        (s, m, PathBuf::from(DEFAULT_SCENE_NAME))
    } else {
        let progress = Progress::default();
        let (s, m) = with_bar(quiet, "loading", &progress, &String::new, || {
            Ok(scene::load_with_progress(path, Some(&progress))?)
        })?;
        (s, m, path.to_path_buf())
    };
    Ok(Loaded {
        path,
        scene,
        summary,
        seconds: start.elapsed().as_secs_f64(),
    })
}

struct Built {
    tree: TreeIr,
    config: BuildConfig,
    /// Wall seconds of the whole build (standard tree + slim pass).
    seconds: f64,
    /// Seconds of the standard build alone.
    std_seconds: f64,
    slim: Option<(SlimParams, SlimReport, SlimPhases)>,
    preset: Preset,
    level: Option<level::LevelReport>,
    builder: &'static str,
}

/// Runs `work` on a scoped worker thread, in a rayon pool the size of the
/// caller's (the worker is outside the caller's pool), while this thread
/// draws a progress bar of `progress` with `label` and `message()` once the
/// work has run for a second, unless `quiet`. (indicatif draws nothing
/// when standard error is not a terminal.)
fn with_bar<T: Send>(
    quiet: bool,
    label: &str,
    progress: &Progress,
    message: &(dyn Fn() -> String + Sync),
    work: impl FnOnce() -> Res<T> + Send,
) -> Res<T> {
    let start = Instant::now();
    let pool_threads = rayon::current_num_threads();
    std::thread::scope(|s| {
        // The worker sends its result, so that this thread wakes the moment
        // it is done (a plain sleep between polls added up to a poll's
        // interval to every timed build).
        let (done, result) = std::sync::mpsc::channel::<Res<T>>();
        let worker = s.spawn(move || {
            let run = || -> Res<T> {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(pool_threads)
                    .build()?;
                pool.install(work)
            };
            // The receiver waits until this is sent (or the worker panics).
            let _ = done.send(run());
        });
        let mut bar: Option<ProgressBar> = None;
        let got = loop {
            match result.recv_timeout(Duration::from_millis(50)) {
                Ok(got) => break Some(got),
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break None,
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
            }
            if bar.is_none() && !quiet && start.elapsed() > Duration::from_secs(1) {
                let b = ProgressBar::new(1000);
                b.set_style(
                    ProgressStyle::with_template(&format!(
                        "{label} {{bar:40}} {{percent:>3}}% {{elapsed_precise}} {{msg}}"
                    ))
                    .expect("the template is valid"),
                );
                bar = Some(b);
            }
            if let Some(b) = &bar {
                b.set_position((progress.fraction() * 1000.0) as u64);
                b.set_message(message());
            }
        };
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        match (got, worker.join()) {
            (Some(got), Ok(())) => got,
            _ => Err(format!("{label}: a worker panicked").into()),
        }
    })
}

/// Builds on a worker thread; shows a progress bar once the build has
/// taken a second (on a terminal), and another for the slim pass.
/// `reordered`: whether the tree will be written with reordering (what the
/// byte rule of the slim pass counts with).
fn build_tree(
    scene: &TriangleColumns,
    args: &BuildArgs,
    quiet: bool,
    reordered: bool,
) -> Res<Built> {
    let mut config = BuildConfig::default();
    config.sah.max_depth = args.max_depth;
    let progress = Progress::default();
    let status = Arc::new(level::LevelStatus::default());
    let mut options = level::LevelOptions {
        status: Some(status.clone()),
        new_events: match args.new_events {
            NewEventsArg::Merge => level::NewEvents::SortMerge,
            NewEventsArg::Bucket => level::NewEvents::Bucket,
        },
        tiny_threshold: usize::from(args.tiny),
        ..level::LevelOptions::default()
    };
    if let Some(b) = args.mem_budget {
        options.mem_budget = b;
    }
    if let Some(d) = &args.scratch {
        options.scratch_dir = d.clone();
    }
    let start = Instant::now();
    let level_message = || {
        use std::sync::atomic::Ordering::Relaxed;
        match args.builder {
            BuilderArg::Level => format!(
                "level {}, {} open nodes, {} refs",
                status.level.load(Relaxed),
                status.open_nodes.load(Relaxed),
                status.refs.load(Relaxed)
            ),
            _ => String::new(),
        }
    };
    let built = with_bar(
        quiet,
        "building",
        &progress,
        &level_message,
        || match args.builder {
            BuilderArg::Level => {
                let (tree, report) = level::build(scene, &config, Some(&progress), &options)?;
                Ok((tree, Some(report)))
            }
            BuilderArg::Sweep => Ok((
                build::build(scene, &config, Builder::Sweep, Some(&progress))?,
                None,
            )),
            BuilderArg::Naive => Ok((
                build::build(scene, &config, Builder::Naive, Some(&progress))?,
                None,
            )),
        },
    );
    let (tree, level_report) = built?;
    let std_seconds = start.elapsed().as_secs_f64();
    let (params, preset) = args.slim(reordered);
    let (tree, slim) = match params {
        Some(p) => {
            let progress = Progress::default();
            let (t, report, phases) =
                with_bar(quiet, "slim pass", &progress, &String::new, || {
                    Ok(slim::slim_with_progress(
                        &tree,
                        scene,
                        &config,
                        &p,
                        Some(&progress),
                    ))
                })?;
            (t, Some((p, report, phases)))
        }
        None => (tree, None),
    };
    Ok(Built {
        tree,
        config,
        seconds: start.elapsed().as_secs_f64(),
        std_seconds,
        slim,
        preset,
        level: level_report,
        builder: match args.builder {
            BuilderArg::Level => "level",
            BuilderArg::Sweep => "sweep",
            BuilderArg::Naive => "naive",
        },
    })
}

fn print_summary(loaded: &Loaded, built: &Built, stats: &TreeStats) {
    println!(
        "scene      {} ({}; loaded in {:.3} s)",
        loaded.path.display(),
        loaded.summary,
        loaded.seconds
    );
    println!(
        "tree       {} nodes ({} inner, {} leaves, {} empty), {} triangle references ({:.2} per triangle)",
        stats.nodes,
        stats.inner + stats.t_inner,
        stats.leaves,
        stats.empty_leaves,
        stats.refs,
        stats.refs as f64 / loaded.scene.len().max(1) as f64
    );
    println!(
        "           max depth {}, mean leaf depth {:.1}, SAH cost {:.2}",
        stats.max_depth, stats.mean_leaf_depth, stats.sah_cost
    );
    println!(
        "build      {:.3} s with the {} builder on {} threads ({:.2} Mtris/s)",
        built.std_seconds,
        built.builder,
        rayon::current_num_threads(),
        loaded.scene.len() as f64 / built.std_seconds / 1e6
    );
    if let Some(r) = &built.level {
        let p = &r.phases;
        println!(
            "           phases: SAH {:.3} s, classify+clip {:.3} s, events {:.3} s, leaves {:.3} s, small nodes {:.3} s, setup+assembly {:.3} s",
            p.sah_s,
            p.classify_clip_s,
            p.events_s,
            p.leaves_s,
            p.small_s,
            p.setup_s + p.assemble_s
        );
        if r.cpu_s > 0.0 {
            println!(
                "           processor time {:.3} s: {:.2} cores busy on average",
                r.cpu_s,
                r.cpu_s / built.std_seconds
            );
        }
        println!(
            "           peak RssAnon {:.1} MiB (start {:.1} MiB), peak RssFile {:.1} MiB, scratch written {:.1} MiB",
            r.peak_rss_anon_bytes as f64 / (1 << 20) as f64,
            r.start_rss_anon_bytes as f64 / (1 << 20) as f64,
            r.peak_rss_file_bytes as f64 / (1 << 20) as f64,
            r.scratch.file_bytes_total as f64 / (1 << 20) as f64
        );
    }
    if let Some((p, r, ph)) = &built.slim {
        println!(
            "slim       preset {} (τ_occu {}, τ_freq {}, max_t2rn {}, hoist rule {}): {} triangles hoisted, {} subtrees rebuilt ({} rejected by the byte rule, {} cancelled); std build {:.3} s, slim pass {:.3} s ({:.2}×)",
            built.preset.name(),
            p.tau_occu,
            p.tau_freq,
            p.max_t2rn,
            report::rule_name(p.rule),
            r.hoisted,
            r.rebuilds,
            r.rejected,
            r.cancelled,
            built.std_seconds,
            built.seconds - built.std_seconds,
            built.seconds / built.std_seconds
        );
        println!(
            "           phases: {} passes; analysis {:.3} s, rebuilds {:.3} s, apply {:.3} s, assembly {:.3} s",
            ph.passes, ph.analysis_s, ph.rebuild_s, ph.apply_s, ph.assemble_s
        );
    }
}

fn build_json(
    loaded: &Loaded,
    built: &Built,
    stats: &TreeStats,
    threads: usize,
) -> serde_json::Value {
    json!({
        "scene": loaded.path.display().to_string(),
        "triangles": loaded.scene.len(),
        "vertices": loaded.scene.positions().len(),
        "dropped_degenerate": loaded.summary.dropped_degenerate,
        "load_s": loaded.seconds,
        "build_s": built.seconds,
        "threads": threads,
        "nodes": stats.nodes,
        "inner": stats.inner,
        "t_inner": stats.t_inner,
        "leaves": stats.leaves,
        "empty_leaves": stats.empty_leaves,
        "refs": stats.refs,
        "max_depth": stats.max_depth,
        "mean_leaf_depth": stats.mean_leaf_depth,
        "sah_cost": stats.sah_cost,
        "leaf_depth_histogram": stats.leaf_depths,
        "k_t": built.config.sah.k_t,
        "k_i": built.config.sah.k_i,
        "preset": built.preset.name(),
        "builder": built.builder,
        "std_build_s": built.std_seconds,
        "level": built.level.as_ref().map(|r| json!({
            "sah_s": r.phases.sah_s,
            "classify_clip_s": r.phases.classify_clip_s,
            "events_s": r.phases.events_s,
            "leaves_s": r.phases.leaves_s,
            "small_nodes_s": r.phases.small_s,
            "setup_s": r.phases.setup_s,
            "assemble_s": r.phases.assemble_s,
            "levels": r.levels,
            "small_nodes": r.small_nodes,
            "start_rss_anon_bytes": r.start_rss_anon_bytes,
            "peak_rss_anon_bytes": r.peak_rss_anon_bytes,
            "peak_rss_file_bytes": r.peak_rss_file_bytes,
            "scratch_bytes_written": r.scratch.file_bytes_total,
            "cpu_s": r.cpu_s,
        })),
        // The builder's figure; `build` replaces it with the whole command's.
        "peak_rss_anon_bytes": built.level.as_ref().map_or_else(rss_anon_bytes, |r| r.peak_rss_anon_bytes),
        "hoisted": built.slim.as_ref().map_or(0, |(_, r, _)| r.hoisted),
        "tau_occu": built.slim.as_ref().map(|(p, _, _)| p.tau_occu),
        "tau_freq": built.slim.as_ref().map(|(p, _, _)| p.tau_freq),
        "max_t2rn": built.slim.as_ref().map(|(p, _, _)| p.max_t2rn),
        "hoist_rule": built.slim.as_ref().map(|(p, _, _)| report::rule_name(p.rule)),
        "slim": built.slim.as_ref().map(|(_, r, ph)| json!({
            "hoisted": r.hoisted,
            "cancelled": r.cancelled,
            "rejected": r.rejected,
            "rebuilds": r.rebuilds,
            "rebuilt_refs": r.rebuilt_refs,
            "passes": ph.passes,
            "analysis_s": ph.analysis_s,
            "rebuild_s": ph.rebuild_s,
            "apply_s": ph.apply_s,
            "assemble_s": ph.assemble_s,
        })),
    })
}

/// The current `RssAnon` of this process (0 where /proc is missing).
fn rss_anon_bytes() -> u64 {
    level::rss().0
}

/// The peak `RssAnon` and `RssFile` of this process from its creation on:
/// a thread samples `/proc/self/status` every 10 ms until it is dropped.
struct PeakRss {
    peak: Arc<[AtomicU64; 2]>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl PeakRss {
    fn start() -> PeakRss {
        let peak = Arc::new([AtomicU64::new(0), AtomicU64::new(0)]);
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (peak, stop) = (peak.clone(), stop.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    PeakRss::sample(&peak);
                    std::thread::sleep(Duration::from_millis(10));
                }
            })
        };
        PeakRss {
            peak,
            stop,
            thread: Some(thread),
        }
    }

    fn sample(peak: &[AtomicU64; 2]) {
        let (anon, file) = level::rss();
        peak[0].fetch_max(anon, Ordering::Relaxed);
        peak[1].fetch_max(file, Ordering::Relaxed);
    }

    /// (RssAnon, RssFile) peaks so far, now included.
    fn peaks(&self) -> (u64, u64) {
        PeakRss::sample(&self.peak);
        (
            self.peak[0].load(Ordering::Relaxed),
            self.peak[1].load(Ordering::Relaxed),
        )
    }
}

impl Drop for PeakRss {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn cmd_build(
    path: &Path,
    args: &BuildArgs,
    output: Option<&Path>,
    reorder: bool,
    json: bool,
) -> Res<()> {
    let pool = pool(args.threads)?;
    let watch = PeakRss::start();
    pool.install(|| {
        let loaded = load(path, json)?;
        let mut built = build_tree(&loaded.scene, args, json, reorder)?;
        let stats = TreeStats::of(&built.tree, &built.config.sah);
        let mut written = None;
        if let Some(out) = output {
            let start = Instant::now();
            let options = WriteOptions {
                reorder,
                config: pipeline::file_config(
                    &built.config,
                    loaded.scene.len(),
                    built.preset,
                    built.slim.as_ref().map(|(p, _, _)| p),
                ),
            };
            format::write_file(out, &built.tree, &loaded.scene, &options)?;
            let secs = start.elapsed().as_secs_f64();
            // Only figures are left to print: free the tree before the file
            // is mapped and checked, so that the two never add up.
            built.tree.nodes = Vec::new();
            built.tree.leaf_tris = Vec::new();
            let file = KdFile::open(out, false)?;
            written = Some((out.to_path_buf(), file.figures(), secs));
        }
        // The whole command: loading, building, writing.
        let (peak_anon, peak_file) = watch.peaks();
        let peak_anon = peak_anon.max(built.level.as_ref().map_or(0, |r| r.peak_rss_anon_bytes));
        if json {
            let mut j = build_json(&loaded, &built, &stats, pool.current_num_threads());
            if let Some((out, fig, secs)) = &written {
                merge_json(&mut j, figures_json(fig));
                merge_json(
                    &mut j,
                    json!({"output": out.display().to_string(), "write_s": secs, "reorder": reorder}),
                );
            }
            merge_json(
                &mut j,
                json!({"peak_rss_anon_bytes": peak_anon, "peak_rss_file_bytes": peak_file}),
            );
            println!("{j}");
        } else {
            print_summary(&loaded, &built, &stats);
            if let Some((out, fig, secs)) = &written {
                println!(
                    "wrote      {} in {:.3} s: tree {:.2} MiB ({} idx32, {} idx16), geometry {:.2} MiB",
                    out.display(),
                    secs,
                    fig.tree_bytes() as f64 / (1 << 20) as f64,
                    fig.idx32,
                    fig.idx16,
                    fig.geometry_bytes() as f64 / (1 << 20) as f64
                );
            }
            println!(
                "memory     peak RssAnon {:.1} MiB, peak RssFile {:.1} MiB (load, build and write)",
                peak_anon as f64 / (1 << 20) as f64,
                peak_file as f64 / (1 << 20) as f64
            );
        }
        Ok(())
    })
}

fn is_kd_file(path: &Path) -> bool {
    let mut magic = [0u8; 8];
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("kd"))
        || std::fs::File::open(path)
            .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut magic))
            .is_ok_and(|()| magic == format::MAGIC)
}

fn cmd_convert(scene: &Path, output: &Path) -> Res<()> {
    if !scene::is_scene_cache(output) {
        return Err(format!(
            "{}: a scene cache's name must end in .kds (that is how commands recognise it)",
            output.display()
        )
        .into());
    }
    let loaded = load(scene, false)?;
    let start = Instant::now();
    scene::write_scene_cache(output, &loaded.scene, &loaded.summary)?;
    let write_s = start.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(output).map(|m| m.len()).unwrap_or(0);
    println!("scene:   {} ({})", loaded.path.display(), loaded.summary);
    println!("load:    {:.3} s", loaded.seconds);
    println!(
        "written: {} ({:.1} MiB) in {write_s:.3} s",
        output.display(),
        bytes as f64 / (1 << 20) as f64
    );
    Ok(())
}

fn cmd_info(path: &Path, json: bool) -> Res<()> {
    let start = Instant::now();
    let file = KdFile::open(path, false)?;
    let open_ms = start.elapsed().as_secs_f64() * 1e3;
    let f = file.figures();
    let c = file.config();
    let hist = file.leaf_depth_histogram();
    let split = ByteSplit::of(&file);
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    let per_tri = |b: u64| b as f64 / f.triangles.max(1) as f64;
    if json {
        let mut j = figures_json(&f);
        merge_json(
            &mut j,
            json!({
                "file": path.display().to_string(),
                "file_bytes": file.as_bytes().len(),
                "version": format::VERSION,
                "preset": c.preset.name(),
                "k_t": c.k_t, "k_i": c.k_i, "lambda_empty": c.lambda_empty,
                "depth_limit": c.depth_limit,
                "tau_occu": c.tau_occu, "tau_freq": c.tau_freq, "max_t2rn": c.max_t2rn,
                "reordered": file.is_reordered(),
                "triangles": f.triangles,
                "vertices": f.vertices,
                "tree_bytes_per_triangle": per_tri(f.tree_bytes()),
                "max_depth": file.max_depth(),
                "leaf_depth_histogram": hist,
                "bytes": json!({
                    "inner": split.inner_bytes,
                    "t_inner": split.t_inner_bytes,
                    "leaves": split.leaf_bytes,
                    "empty_leaves": split.empty_leaf_bytes,
                    "idx32": split.idx32_bytes,
                    "idx16": split.idx16_bytes,
                    "duplicates": split.duplicate_bytes,
                    "hoist_bound": split.hoist_bound_bytes,
                }),
                "open_ms": open_ms,
            }),
        );
        println!("{j}");
        return Ok(());
    }
    let b = file.bounds();
    println!(
        "file        {} ({} bytes, format version {})",
        path.display(),
        file.as_bytes().len(),
        format::VERSION
    );
    println!(
        "build       preset {}, K_T {}, K_I {}, λ {}, depth limit {}, τ_occu {}, τ_freq {}, max_t2rn {}",
        c.preset.name(),
        c.k_t,
        c.k_i,
        c.lambda_empty,
        c.depth_limit,
        c.tau_occu,
        c.tau_freq,
        c.max_t2rn
    );
    println!(
        "scene       {} triangles{}, {} vertices, bounds ({}, {}, {}) – ({}, {}, {})",
        f.triangles,
        if file.is_reordered() {
            " (Morton-reordered)"
        } else {
            ""
        },
        f.vertices,
        b.min.x,
        b.min.y,
        b.min.z,
        b.max.x,
        b.max.y,
        b.max.z
    );
    println!(
        "table 3(a)  inner      t-inner     leaf       total      4-byte idx  2-byte idx  memory (MiB)"
    );
    println!(
        "            {:<10} {:<11} {:<10} {:<10} {:<11} {:<11} {:.2}",
        f.inner,
        f.t_inner,
        f.leaves,
        f.nodes(),
        f.idx32,
        f.idx16,
        mib(f.tree_bytes())
    );
    println!(
        "bytes       tree {} ({:.1} per triangle), geometry {} ({:.1} per triangle)",
        f.tree_bytes(),
        per_tri(f.tree_bytes()),
        f.geometry_bytes(),
        per_tri(f.geometry_bytes())
    );
    let pct = |b: u64| 100.0 * b as f64 / split.total().max(1) as f64;
    println!(
        "split       inner {:.1}%, t-inner + T-ref {:.1}%, leaves {:.1}%, empty leaves {:.1}%, idx32 {:.1}%, idx16 {:.1}%",
        pct(split.inner_bytes),
        pct(split.t_inner_bytes),
        pct(split.leaf_bytes),
        pct(split.empty_leaf_bytes),
        pct(split.idx32_bytes),
        pct(split.idx16_bytes)
    );
    println!(
        "bound       with the nodes unchanged: duplicate references {} bytes ({:.1}%), hoisting saves at most {} bytes ({:.1}%)",
        split.duplicate_bytes,
        pct(split.duplicate_bytes),
        split.hoist_bound_bytes,
        pct(split.hoist_bound_bytes)
    );
    println!("depth       max {}; leaves per depth:", file.max_depth());
    let peak = hist.iter().copied().max().unwrap_or(1).max(1);
    for (d, &n) in hist.iter().enumerate() {
        if n > 0 {
            let bar = "#".repeat(((n as f64 / peak as f64) * 50.0).ceil() as usize);
            println!("            {d:>3} {n:>10} {bar}");
        }
    }
    println!("open        {open_ms:.3} ms (mmap + validation)");
    Ok(())
}

fn cmd_verify(path: &Path) -> Res<()> {
    let file = KdFile::open(path, true).map_err(|e| format!("{}: invalid: {e}", path.display()))?;
    let f = file.figures();
    println!(
        "{}: ok ({} nodes, {} triangles, all checksums match)",
        path.display(),
        f.nodes(),
        f.triangles
    );
    Ok(())
}

fn cmd_report(args: &ReportArgs) -> Res<()> {
    let views = match &args.views {
        Some(file) => {
            let text =
                std::fs::read_to_string(file).map_err(|e| format!("{}: {e}", file.display()))?;
            render::parse_views(&text).map_err(|e| format!("{}: {e}", file.display()))?
        }
        None => render::parse_views(DEFAULT_VIEWS)?,
    };
    let mut scenes = Vec::new();
    for path in &args.scenes {
        let loaded = load(path, false)?;
        eprintln!("loaded {} ({})", loaded.path.display(), loaded.summary);
        scenes.push((
            loaded.path.display().to_string(),
            loaded.scene,
            loaded.seconds,
        ));
    }
    let all_threads = match args.threads {
        Some(0) => return Err("--threads must be at least 1".into()),
        Some(n) => n,
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    let options = report::ReportOptions {
        scenes,
        views,
        size: args.size,
        reps: args.reps,
        sweep: args.sweep,
        all_threads,
        sweep_grid: None,
        rule: args.hoist_rule.rule(true),
    };
    let start = Instant::now();
    let report = report::run(&options, &mut |line| {
        eprintln!("[{:7.1} s] {line}", start.elapsed().as_secs_f64())
    })?;
    let written = report
        .write(&args.output)
        // Its errors name the file.
        .map_err(|e| format!("cannot write the report: {e}"))?;
    for p in written {
        println!("wrote {}", p.display());
    }
    Ok(())
}

/// The camera: explicit flags override a view, a view overrides the
/// default camera of the scene box.
fn camera_for(args: &RenderArgs, scene_path: &Path, bounds: &slimkd::geom::Aabb) -> Res<Camera> {
    let (w, h) = args.size;
    let mut cam = Camera::default_for(bounds, w, h);
    if let Some(id) = &args.view {
        let views: Vec<View> = match &args.views {
            Some(file) => {
                let text = std::fs::read_to_string(file)
                    .map_err(|e| format!("{}: {e}", file.display()))?;
                render::parse_views(&text).map_err(|e| format!("{}: {e}", file.display()))?
            }
            None => render::parse_views(DEFAULT_VIEWS)?,
        };
        let view = render::find_view(&views, scene_path, id).ok_or_else(|| {
            format!(
                "no view `{id}` for scene `{}` in the views file",
                scene_path.file_stem().unwrap_or_default().to_string_lossy()
            )
        })?;
        cam = Camera::from_view(view, w, h);
    } else if args.views.is_some() {
        return Err("--views needs --view ID".into());
    }
    if let Some(v) = args.eye {
        cam.eye = v;
    }
    if let Some(v) = args.at {
        cam.at = v;
    }
    if let Some(v) = args.up {
        cam.up = v;
    }
    if let Some(v) = args.fov {
        if !(v > 0.0 && v < 180.0) {
            return Err(format!("--fov {v} is not in (0, 180)").into());
        }
        cam.fov_deg = v;
    }
    cam.check()?;
    Ok(cam)
}

/// What a render traces: a tree built from a scene, or a mapped file.
enum Source {
    Built {
        loaded: Loaded,
        built: Box<Built>,
        stats: TreeStats,
    },
    File {
        file: KdFile<Mapped>,
        columns: TriangleColumns,
        open_ms: f64,
    },
}

fn cmd_render(args: &RenderArgs) -> Res<()> {
    if args.reps == 0 {
        return Err("--reps must be at least 1".into());
    }
    let pool = pool(args.build.threads)?;
    pool.install(|| {
        let source = if args.scene.as_os_str() != DEFAULT_ARG && is_kd_file(&args.scene) {
            let start = Instant::now();
            let file = KdFile::open(&args.scene, false)?;
            let open_ms = start.elapsed().as_secs_f64() * 1e3;
            let columns = file.to_columns();
            Source::File { file, columns, open_ms }
        } else {
            let loaded = load(&args.scene, args.json)?;
            // Not written: bytes are counted as in a reordered file.
            let built = build_tree(&loaded.scene, &args.build, args.json, true)?;
            let stats = TreeStats::of(&built.tree, &built.config.sah);
            Source::Built {
                loaded,
                built: Box::new(built),
                stats,
            }
        };
        let (scene_path, columns, bounds) = match &source {
            Source::Built { loaded, built, .. } => (loaded.path.clone(), &loaded.scene, built.tree.bounds),
            Source::File { file, columns, .. } => (args.scene.clone(), columns, file.bounds()),
        };
        let camera = camera_for(args, &scene_path, &bounds)?;
        let tree_tracer = match &source {
            Source::Built { loaded, built, .. } => Some(TreeTracer {
                tree: &built.tree,
                scene: &loaded.scene,
            }),
            Source::File { .. } => None,
        };
        let tracer: Box<dyn ClosestHit + '_> = match (&source, args.mode) {
            (_, ModeArg::Brute) => Box::new(BruteForce(columns)),
            (Source::Built { .. }, ModeArg::Single) => Box::new(Scalar(tree_tracer.as_ref().expect("built"))),
            (Source::Built { .. }, ModeArg::Packet) => {
                Box::new(PacketTracer::new(tree_tracer.as_ref().expect("built")))
            }
            (Source::File { file, .. }, ModeArg::Single) => Box::new(Scalar(file)),
            (Source::File { file, .. }, ModeArg::Packet) => Box::new(PacketTracer::new(file)),
        };
        let mut rates = Vec::new();
        let mut last: Option<HitBuffer> = None;
        for rep in 0..args.reps {
            let progress = Progress::default();
            let rep_message = || format!("frame {} of {}", rep + 1, args.reps);
            let buf = with_bar(args.json, "rendering", &progress, &rep_message, || {
                Ok(render::trace_frame_with_progress(
                    tracer.as_ref(),
                    &camera,
                    Some(&progress),
                ))
            })?;
            rates.push(buf.mrays_per_s());
            last = Some(buf);
        }
        let buf = last.expect("reps >= 1");
        let shading = match args.shading {
            ShadingArg::EyeLight => Shading::EyeLight,
            ShadingArg::Normals => Shading::Normals,
        };
        let frame = render::shade(&buf, &camera, columns, shading);
        if let Some(out) = &args.output {
            render::write_image(out, &frame)?;
        }
        if let Some(out) = &args.dump_t {
            render::write_depth_f32(out, &frame)?;
        }
        let mrays = pipeline::median(&rates);
        let mode = args.mode.name();
        let simd = if args.mode == ModeArg::Packet {
            SimdLevel::detect().name()
        } else {
            "scalar"
        };
        let threads = pool.current_num_threads();
        if args.json {
            let mut j = match &source {
                Source::Built { loaded, built, stats } => build_json(loaded, built, stats, threads),
                Source::File { file, open_ms, .. } => {
                    let mut j = figures_json(&file.figures());
                    merge_json(
                        &mut j,
                        json!({"file": args.scene.display().to_string(), "open_ms": open_ms,
                               "triangles": file.figures().triangles, "threads": threads}),
                    );
                    j
                }
            };
            merge_json(
                &mut j,
                json!({
                    "mode": mode,
                    "simd": simd,
                    "width": camera.width,
                    "height": camera.height,
                    "reps": args.reps,
                    "mrays_per_s": mrays,
                    "hits": buf.n_hits(),
                    "checksum": buf.checksum(),
                    "eye": [camera.eye.x, camera.eye.y, camera.eye.z],
                    "at": [camera.at.x, camera.at.y, camera.at.z],
                    "up": [camera.up.x, camera.up.y, camera.up.z],
                    "fov": camera.fov_deg,
                }),
            );
            println!("{j}");
        } else {
            match &source {
                Source::Built { loaded, built, stats } => print_summary(loaded, built, stats),
                Source::File { file, open_ms, .. } => println!(
                    "file       {} ({} triangles), opened in {open_ms:.3} ms",
                    args.scene.display(),
                    file.figures().triangles
                ),
            }
            println!(
                "render     {}x{} {mode} ({simd}), {threads} threads: {:.2} Mrays/s (median of {}), {} hits, checksum {:.6}",
                camera.width,
                camera.height,
                mrays,
                args.reps,
                buf.n_hits(),
                buf.checksum()
            );
            if let Some(out) = &args.output {
                println!("wrote      {}", out.display());
            }
        }
        Ok(())
    })
}

/// `slimkd` without arguments: the embedded scene, its first view, an image.
fn main_job() -> Res<()> {
    let args = RenderArgs {
        scene: PathBuf::from(DEFAULT_ARG),
        build: BuildArgs {
            builder: BuilderArg::Level,
            mem_budget: None,
            scratch: None,
            new_events: NewEventsArg::Merge,
            tiny: level::DEFAULT_TINY_THRESHOLD as u8,
            threads: None,
            max_depth: None,
            preset: PresetArg::Std,
            tau_occu: None,
            tau_freq: None,
            max_t2rn: None,
            hoist_rule: HoistRuleArg::Bytes,
        },
        eye: None,
        at: None,
        up: None,
        fov: None,
        size: (1024, 1024),
        views: None,
        view: Some("1".into()),
        mode: ModeArg::Packet,
        reps: 3,
        output: Some(PathBuf::from("slimkd.png")),
        dump_t: None,
        shading: ShadingArg::EyeLight,
        json: false,
    };
    cmd_render(&args)
}
