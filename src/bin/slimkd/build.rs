//! `slimkd build`, and the loading and building that `render`, `convert`
//! and `report` share: a scene loaded, a tree built (and slimmed), its
//! summary and JSON, and the peak memory of the command.

use crate::args::{BuildArgs, BuilderArg, NewEventsArg, OutputFlags, check_output_dir};
use crate::json::{
    BuildCmdJson, BuildJson, CellsJson, LevelJson, MemoryJson, SceneJson, SlimJson, TreeJson,
    WrittenJson, print_json,
};
use crate::kd_file::{self, open_kd};
use crate::lab::figures::FiguresJson;
use crate::lab::report;
use crate::progress_bar::{si, with_bar};
use crate::{CmdResult, DEFAULT_ARG, DEFAULT_SCENE, DEFAULT_SCENE_NAME, pool};
use slimkd::build::{Algorithm, BuildConfig, level};
use slimkd::format;
use slimkd::pipeline::Pipeline;
use slimkd::progress::Progress;
use slimkd::scene::{self, LoadSummary, TriangleColumns};
use slimkd::slim::Rebuild;
use slimkd::slim::{SlimParams, SlimPhases, SlimReport};
use slimkd::stats::{StatsSink, TreeStats};
use slimkd::tree::TreeIr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

pub(crate) struct Loaded {
    pub(crate) path: PathBuf,
    pub(crate) scene: TriangleColumns,
    pub(crate) summary: LoadSummary,
    pub(crate) seconds: f64,
}

impl Loaded {
    /// The scene's name: its file's stem (what views files, tables and
    /// the `.kd` header call it).
    pub(crate) fn name(&self) -> String {
        scene_name(&self.path)
    }
}

/// The JSON of a loaded scene is made here, next to `Loaded`, so that
/// `json` names no command module.
impl SceneJson {
    pub(crate) fn of(loaded: &Loaded) -> SceneJson {
        SceneJson {
            scene: loaded.path.display().to_string(),
            scene_name: loaded.name(),
            triangles: loaded.scene.len(),
            vertices: loaded.scene.positions().len(),
            dropped_degenerate: loaded.summary.dropped_degenerate,
            load_s: loaded.seconds,
        }
    }
}

/// A scene's name: the stem of its file (`scenes/bunny_npm.obj`:
/// `bunny_npm`).
pub(crate) fn scene_name(path: &Path) -> String {
    path.file_stem()
        .unwrap_or(path.as_os_str())
        .to_string_lossy()
        .into_owned()
}

/// Loads every scene of `paths` in turn, each announced on stderr with its
/// summary unless `ui.quiet` (the multi-scene commands: report, sweep).
pub(crate) fn load_all(paths: &[PathBuf], ui: OutputFlags) -> CmdResult<Vec<Loaded>> {
    let mut out = Vec::with_capacity(paths.len());
    for path in paths {
        let loaded = load(path, ui.bars_off())?;
        if !ui.quiet {
            eprintln!("loaded {} ({})", loaded.path.display(), loaded.summary);
        }
        out.push(loaded);
    }
    Ok(out)
}

/// Loads a scene; a progress bar shows the bytes read once loading has
/// taken a second, unless `quiet`.
pub(crate) fn load(path: &Path, quiet: bool) -> CmdResult<Loaded> {
    let start = Instant::now();
    let (scene, summary, path) = if path.as_os_str() == DEFAULT_ARG {
        let name = scene::embedded_name(DEFAULT_SCENE_NAME);
        let (s, m) = scene::load_obj_bytes(&name, DEFAULT_SCENE)?;
        (s, m, PathBuf::from(DEFAULT_SCENE_NAME))
    } else {
        let progress = Progress::default();
        let (s, m) = with_bar(quiet, "loading", &progress, &String::new, || {
            let no_mmap = kd_file::NO_MMAP.load(std::sync::atomic::Ordering::Relaxed);
            if no_mmap && scene::SceneFormat::of_path(path) == Some(scene::SceneFormat::Cache) {
                return Ok(scene::read_scene_cache(path)?);
            }
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

pub(crate) struct Built {
    pub(crate) tree: TreeIr,
    /// What was built and how it is written.
    pub(crate) pipeline: Pipeline,
    /// Wall seconds of the whole build (standard tree + slim pass).
    pub(crate) seconds: f64,
    /// Seconds of the standard build alone.
    pub(crate) std_seconds: f64,
    pub(crate) slim: Option<(SlimParams, SlimReport, SlimPhases)>,
    pub(crate) level: Option<level::LevelReport>,
    pub(crate) builder: &'static str,
}

/// The JSON of a build is made here, next to `Built`, so that `json`
/// names no command module.
impl BuildJson {
    pub(crate) fn of(built: &Built) -> BuildJson {
        let slim = built.slim.as_ref();
        BuildJson {
            builder: built.builder,
            build_s: built.seconds,
            std_build_s: built.std_seconds,
            k_t: built.pipeline.config.sah.k_t,
            k_i: built.pipeline.config.sah.k_i,
            lambda_empty: built.pipeline.config.sah.lambda_empty,
            split_price: built.pipeline.config.sah.split_price,
            preset: built.pipeline.preset.name(),
            hoisted: slim.map_or(0, |(_, r, _)| r.hoisted),
            tau_occu: slim.map(|(p, _, _)| p.tau_occu),
            tau_freq: slim.map(|(p, _, _)| p.tau_freq),
            max_t2rn: slim.map(|(p, _, _)| p.max_t2rn),
            coarsen: slim.map(|(p, _, _)| p.coarsen),
            cost_ratio: slim.and_then(|(p, _, _)| Some(p.cost_ratio).filter(|r| r.is_finite())),
            hoist_rule: slim.map(|(p, _, _)| report::rule_name(p.rule)),
            rebuild: slim.map(|(p, _, _)| rebuild_name(p.rebuild)),
            level: built.level.as_ref().map(|r| LevelJson {
                sah_s: r.phases.sah_s,
                classify_clip_s: r.phases.classify_clip_s,
                events_s: r.phases.events_s,
                leaves_s: r.phases.leaves_s,
                small_nodes_s: r.phases.small_s,
                setup_s: r.phases.setup_s,
                assemble_s: r.phases.assemble_s,
                levels: r.levels as u64,
                groups: r.groups,
                small_nodes: r.small_nodes,
                small_threshold: r.small_threshold,
                finisher_reserve_bytes: r.finisher_reserve_bytes,
                start_rss_anon_bytes: r.start_rss_anon_bytes,
                peak_rss_anon_bytes: r.peak_rss_anon_bytes,
                peak_rss_file_bytes: r.peak_rss_file_bytes,
                scratch_bytes_written: r.scratch.file_bytes_total,
                cpu_s: r.cpu_s,
            }),
            slim: slim.map(|(_, r, ph)| SlimJson {
                hoisted: r.hoisted,
                cancelled: r.cancelled,
                rejected: r.rejected,
                priced: r.priced,
                rebuilds: r.rebuilds,
                rebuilt_refs: r.rebuilt_refs as u64,
                passes: ph.passes,
                analysis_s: ph.analysis_s,
                rebuild_s: ph.rebuild_s,
                apply_s: ph.apply_s,
                assemble_s: ph.assemble_s,
            }),
        }
    }
}

/// The pipeline of the build flags for `loaded`'s scene (the name its
/// file records), written with reordering or not (`reorder`: also what
/// the byte rule of the slim pass counts with).
pub(crate) fn pipeline_of(args: &BuildArgs, loaded: &Loaded, reorder: bool) -> Pipeline {
    let (slim, preset) = args.slim(reorder);
    Pipeline {
        algorithm: match args.builder {
            BuilderArg::Level => Algorithm::Level,
            BuilderArg::Sweep => Algorithm::WaldHavran,
            BuilderArg::Naive => Algorithm::Naive,
        },
        level: level::LevelOptions {
            new_events: match args.new_events {
                NewEventsArg::Merge => level::NewEvents::SortMerge,
                NewEventsArg::Bucket => level::NewEvents::Bucket,
            },
            tiny_threshold: usize::from(args.tiny),
            scratch_dir: args
                .scratch
                .clone()
                .unwrap_or_else(|| level::LevelOptions::default().scratch_dir),
            ..level::LevelOptions::default()
        },
        mem_budget: args.mem_budget,
        small: args.small,
        reorder,
        scene_name: Some(loaded.name()),
        ..Pipeline::new(build_config(args)).slimmed(slim, preset)
    }
}

/// Runs `pipeline`'s build and slim pass on a worker thread; shows a
/// progress bar once the build has taken a second (on a terminal), and
/// another for the slim pass.
pub(crate) fn build_tree(
    scene: &TriangleColumns,
    pipeline: Pipeline,
    quiet: bool,
) -> CmdResult<Built> {
    let (progress, status, pipeline) = with_status(pipeline);
    let start = Instant::now();
    let level_message = || match pipeline.algorithm {
        Algorithm::Level => level_message(&status),
        _ => String::new(),
    };
    let built = with_bar(quiet, "building", &progress, &level_message, || {
        Ok(pipeline.build(scene, Some(&progress))?)
    });
    let (tree, level_report) = built?;
    let std_seconds = start.elapsed().as_secs_f64();
    let (tree, slim) = match pipeline.slim {
        Some(p) => {
            let progress = Progress::default();
            let (t, report, phases) =
                with_bar(quiet, "slim pass", &progress, &String::new, || {
                    Ok(pipeline
                        .slim(&tree, scene, Some(&progress))
                        .expect("the pipeline has a slim pass"))
                })?;
            (t, Some((p, report, phases)))
        }
        None => (tree, None),
    };
    Ok(Built {
        tree,
        seconds: start.elapsed().as_secs_f64(),
        std_seconds,
        slim,
        level: level_report,
        builder: match pipeline.algorithm {
            Algorithm::Level => "level",
            Algorithm::WaldHavran => "sweep",
            Algorithm::Naive => "naive",
        },
        pipeline,
    })
}

/// The cost model and depth limit of the build flags.
pub(crate) fn build_config(args: &BuildArgs) -> BuildConfig {
    let mut config = BuildConfig::default();
    config.sah.max_depth = args.max_depth;
    config.sah.k_t = args.kt;
    config.sah.k_i = args.ki;
    config.sah.lambda_empty = args.lambda;
    config.sah.split_price = args.split_price;
    config
}

/// `pipeline` with a level status the progress bar reads, and a progress
/// counter for the build.
fn with_status(pipeline: Pipeline) -> (Progress, Arc<level::LevelStatus>, Pipeline) {
    let status = Arc::new(level::LevelStatus::default());
    let pipeline = Pipeline {
        level: level::LevelOptions {
            status: Some(status.clone()),
            ..pipeline.level
        },
        ..pipeline
    };
    (Progress::default(), status, pipeline)
}

/// The build bar's message for the level builder: the level, its open
/// nodes and references while nodes are open; once none is, the
/// depth-first finisher's subtrees (most of a build's time).
pub(crate) fn level_message(status: &level::LevelStatus) -> String {
    use std::sync::atomic::Ordering::Relaxed;
    let small = si(status.small_nodes.load(Relaxed));
    match status.open_nodes.load(Relaxed) {
        0 => format!("depth-first: {small} subtrees"),
        open => format!(
            "level {}: {} open, {} refs, {small} depth-first",
            status.level.load(Relaxed),
            si(open),
            si(status.refs.load(Relaxed))
        ),
    }
}

/// The summary's first line: the scene and its load.
pub(crate) fn print_scene_line(loaded: &Loaded) {
    println!(
        "scene      {} ({}; loaded in {:.3} s)",
        loaded.path.display(),
        loaded.summary,
        loaded.seconds
    );
}

/// The summary of a build; `verbose` adds the phases, processor time and
/// memory of the builder and the slim pass.
pub(crate) fn print_summary(loaded: &Loaded, built: &Built, stats: &TreeStats, verbose: bool) {
    print_scene_line(loaded);
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
    if let Some(r) = built.level.as_ref().filter(|_| verbose) {
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
            "slim       preset {} (τ_occu {}, τ_freq {}, max_t2rn {}, coarsen {}, cost ratio {}, hoist rule {}, rebuild {}): {} triangles hoisted, {} subtrees rebuilt ({} rejected by the byte rule, {} by the price rule, {} cancelled); std build {:.3} s, slim pass {:.3} s ({:.2}×)",
            built.pipeline.preset.name(),
            p.tau_occu,
            p.tau_freq,
            p.max_t2rn,
            p.coarsen,
            p.cost_ratio,
            report::rule_name(p.rule),
            rebuild_name(p.rebuild),
            r.hoisted,
            r.rebuilds,
            r.rejected,
            r.priced,
            r.cancelled,
            built.std_seconds,
            built.seconds - built.std_seconds,
            built.seconds / built.std_seconds
        );
        if verbose {
            println!(
                "           phases: {} passes; analysis {:.3} s, rebuilds {:.3} s, apply {:.3} s, assembly {:.3} s",
                ph.passes, ph.analysis_s, ph.rebuild_s, ph.apply_s, ph.assemble_s
            );
        }
    }
}

/// The peak `RssAnon` and `RssFile` of this process from its creation on:
/// a thread samples `/proc/self/status` every 10 ms until it is dropped.
pub(crate) struct PeakRss {
    pub(crate) peak: Arc<[AtomicU64; 2]>,
    pub(crate) stop: Arc<AtomicBool>,
    pub(crate) thread: Option<std::thread::JoinHandle<()>>,
}

impl PeakRss {
    pub(crate) fn start() -> PeakRss {
        let peak = Arc::new([AtomicU64::new(0), AtomicU64::new(0)]);
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (peak, stop) = (peak.clone(), stop.clone());
            // Where no thread can be started, the peaks are sampled only
            // when read. The sampler is waited for until it runs (see
            // `crate::pool`: a thread starting beside allocations can
            // abort the process).
            let (up_tx, up_rx) = std::sync::mpsc::channel::<()>();
            let thread = crate::room_for_threads(1)
                .then(|| {
                    std::thread::Builder::new()
                        .spawn(move || {
                            let _ = up_tx.send(());
                            while !stop.load(Ordering::Relaxed) {
                                PeakRss::sample(&peak);
                                std::thread::sleep(Duration::from_millis(10));
                            }
                        })
                        .ok()
                })
                .flatten();
            if thread.is_some() {
                let _ = up_rx.recv();
            }
            thread
        };
        PeakRss { peak, stop, thread }
    }

    pub(crate) fn sample(peak: &[AtomicU64; 2]) {
        let (anon, file) = level::rss();
        peak[0].fetch_max(anon, Ordering::Relaxed);
        peak[1].fetch_max(file, Ordering::Relaxed);
    }

    /// (RssAnon, RssFile) peaks so far, now included.
    pub(crate) fn peaks(&self) -> (u64, u64) {
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

pub(crate) fn cmd_build(
    path: &Path,
    args: &BuildArgs,
    output: Option<&Path>,
    reorder: bool,
    ui: OutputFlags,
) -> CmdResult<()> {
    args.check()?;
    if let Some(out) = output {
        check_output_dir(out)?;
    }
    let pool = pool(args.threads)?;
    let watch = PeakRss::start();
    pool.install(|| {
        let loaded = load(path, ui.bars_off())?;
        let pipeline = pipeline_of(args, &loaded, reorder);
        if let Some(out) = output
            && pipeline.algorithm == Algorithm::Level
            && pipeline.slim.is_none()
        {
            return build_streamed(&loaded, pipeline, out, ui, &watch);
        }
        let built = build_tree(&loaded.scene, pipeline, ui.bars_off())?;
        write_and_print("build", &loaded, built, output, reorder, ui, &watch, None)
    })
}

/// `build -o` of a standard tree with the level builder: the tree goes
/// into the file as it is assembled ([`level::build_into`] into
/// [`format::write_file_streamed`]), its figures taken on the way
/// ([`StatsSink`]), so the whole tree is never in memory; the file's bytes
/// are those of the path through a `TreeIr`. The slim pass works on the
/// whole tree, so slim presets take that path.
fn build_streamed(
    loaded: &Loaded,
    pipeline: Pipeline,
    out: &Path,
    ui: OutputFlags,
    watch: &PeakRss,
) -> CmdResult<()> {
    let (progress, status, pipeline) = with_status(pipeline);
    let start = Instant::now();
    let mut stats = StatsSink::new(&pipeline.config.sah);
    let mut built_s = 0.0;
    let report =
        with_bar(
            ui.bars_off(),
            "building",
            &progress,
            &|| level_message(&status),
            || {
                Ok(pipeline.build_into_file(
                    out,
                    &loaded.scene,
                    Some(&progress),
                    &mut stats,
                    || built_s = start.elapsed().as_secs_f64(),
                )?)
            },
        )?
        .ok_or("the tree did not reach the file")?;
    let seconds = start.elapsed().as_secs_f64();
    let reorder = pipeline.reorder;
    let built = streamed_built(pipeline, built_s, Some(report), "level");
    let streamed = (out, seconds - built_s, stats.finish());
    print_streamed("build", loaded, &built, streamed, reorder, ui, watch, None)
}

/// A std tree that went straight into its file: its figures without the
/// tree (`seconds` of building).
fn streamed_built(
    pipeline: Pipeline,
    seconds: f64,
    level: Option<level::LevelReport>,
    builder: &'static str,
) -> Built {
    Built {
        tree: TreeIr::default(),
        pipeline,
        seconds,
        std_seconds: seconds,
        slim: None,
        level,
        builder,
    }
}

/// [`print_built`] of a tree streamed into `out` (seconds of writing
/// after the tree was complete, and the figures taken on the way): the
/// file is opened and checked for its figures first.
#[allow(clippy::too_many_arguments)]
fn print_streamed(
    command: &'static str,
    loaded: &Loaded,
    built: &Built,
    (out, write_s, stats): (&Path, f64, TreeStats),
    reorder: bool,
    ui: OutputFlags,
    watch: &PeakRss,
    cells: Option<CellsJson>,
) -> CmdResult<()> {
    let file = open_kd(out, slimkd::format::Check::Full)?;
    let written = Some((out.to_path_buf(), file.figures(), write_s));
    print_built(
        command, loaded, built, &stats, written, reorder, ui, watch, cells,
    )
}

/// The end of `build --cells` and `stitch`: the parts of `plan` in `dir`
/// stitched straight into `out` ([`cells::stitch_dir_into`] into
/// [`format::write_file_streamed`], the figures taken on the way), so the
/// stitched tree is never in memory, one part at a time is; then printed
/// as `build -o` prints (`seconds`: the build's time before the stitch).
#[allow(clippy::too_many_arguments)]
pub(crate) fn stitch_streamed(
    command: &'static str,
    loaded: &Loaded,
    dir: &Path,
    plan: &slimkd::cells::Plan,
    config: BuildConfig,
    out: &Path,
    reorder: bool,
    ui: OutputFlags,
    watch: &PeakRss,
    cells: CellsJson,
    seconds: f64,
) -> CmdResult<()> {
    let pipeline = Pipeline {
        reorder,
        scene_name: Some(loaded.name()),
        ..Pipeline::new(config)
    };
    let write_options = pipeline.write_options(&loaded.scene);
    let start = Instant::now();
    let mut stats = StatsSink::new(&pipeline.config.sah);
    let fed =
        format::write_file_streamed(out, &loaded.scene, &write_options, |w| -> CmdResult<_> {
            Ok(slimkd::cells::stitch_dir_into(
                dir,
                plan,
                &mut (w, &mut stats),
            )?)
        })?;
    if !fed {
        return Err(format!(
            "{}: the plan's cells are not leaves of its top tree in pre-order",
            slimkd::cells::plan_path(dir).display()
        )
        .into());
    }
    let secs = start.elapsed().as_secs_f64();
    if ui.verbose && !ui.json {
        eprintln!("cells      stitched and written in {secs:.3} s");
    }
    let built = streamed_built(pipeline, seconds + secs, None, "level (cells)");
    let streamed = (out, secs, stats.finish());
    print_streamed(
        command,
        loaded,
        &built,
        streamed,
        reorder,
        ui,
        watch,
        Some(cells),
    )
}

/// The end of `build` (and of `build --cells`, `stitch`): the tree
/// written to `output` (if given) as `build -o` writes it, then its
/// summary or JSON (under `command`, with the cells' figures if any).
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_and_print(
    command: &'static str,
    loaded: &Loaded,
    mut built: Built,
    output: Option<&Path>,
    reorder: bool,
    ui: OutputFlags,
    watch: &PeakRss,
    cells: Option<CellsJson>,
) -> CmdResult<()> {
    let stats = TreeStats::of(&built.tree, &built.pipeline.config.sah);
    let mut written = None;
    if let Some(out) = output {
        let start = Instant::now();
        built.pipeline.write_file(out, &built.tree, &loaded.scene)?;
        let secs = start.elapsed().as_secs_f64();
        // Only figures are left to print: free the tree before the file
        // is mapped and checked, so that the two never add up.
        built.tree.nodes = Vec::new();
        built.tree.leaf_tris = Vec::new();
        let file = open_kd(out, slimkd::format::Check::Full)?;
        written = Some((out.to_path_buf(), file.figures(), secs));
    }
    print_built(
        command, loaded, &built, &stats, written, reorder, ui, watch, cells,
    )
}

/// The summary or JSON of a build (under `command`), with the file
/// written, if any (its path, figures and seconds of writing), and the
/// peak memory of the whole command.
#[allow(clippy::too_many_arguments)]
fn print_built(
    command: &'static str,
    loaded: &Loaded,
    built: &Built,
    stats: &TreeStats,
    written: Option<(PathBuf, format::TreeFigures, f64)>,
    reorder: bool,
    ui: OutputFlags,
    watch: &PeakRss,
    cells: Option<CellsJson>,
) -> CmdResult<()> {
    // The whole command: loading, building, writing.
    let (peak_anon, peak_file) = watch.peaks();
    let peak_anon = peak_anon.max(built.level.as_ref().map_or(0, |r| r.peak_rss_anon_bytes));
    if ui.json {
        print_json(
            command,
            BuildCmdJson {
                scene: SceneJson::of(loaded),
                tree: TreeJson::of(stats),
                build: BuildJson::of(built),
                threads: rayon::current_num_threads(),
                written: written.as_ref().map(|(out, fig, secs)| WrittenJson {
                    output: out.display().to_string(),
                    write_s: *secs,
                    reorder,
                    storage: FiguresJson::of(fig).storage,
                }),
                memory: MemoryJson {
                    peak_rss_anon_bytes: peak_anon,
                    peak_rss_file_bytes: peak_file,
                },
                cells,
            },
        )?;
    } else if !ui.quiet {
        print_summary(loaded, built, stats, ui.verbose);
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
}

/// The `--rebuild` name of a rebuild.
fn rebuild_name(r: Rebuild) -> &'static str {
    match r {
        Rebuild::Sah => "sah",
        Rebuild::Prune => "prune",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// At the end of a build no node is open and the finisher has had
    /// subtrees: the message names the depth-first finisher and their
    /// count, not the last level with 0 open nodes.
    #[test]
    fn the_bar_names_the_depth_first_finisher() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj");
        let (scene, _) = scene::load_obj(&path).unwrap();
        let status = Arc::new(level::LevelStatus::default());
        let options = level::LevelOptions {
            status: Some(status.clone()),
            ..level::LevelOptions::default()
        };
        level::build(&scene, &BuildConfig::default(), None, &options).unwrap();
        let small = status.small_nodes.load(Ordering::Relaxed);
        assert!(small > 0);
        assert_eq!(status.open_nodes.load(Ordering::Relaxed), 0);
        let message = level_message(&status);
        assert_eq!(message, format!("depth-first: {} subtrees", si(small)));
        status.open_nodes.store(1234, Ordering::Relaxed);
        status.level.store(9, Ordering::Relaxed);
        status.refs.store(45_600_000, Ordering::Relaxed);
        let message = level_message(&status);
        assert!(
            message.starts_with("level 9: 1.23k open, 45.6M refs"),
            "{message}"
        );
    }
}
