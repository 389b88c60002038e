//! The paper's tables and figures for a set of scenes (Choi, Chang & Ihm
//! 2013): what `slimkd report` writes.
//!
//! [`run`] builds, for every scene, the standard SAH tree (sweep builder),
//! the `fast` and `small` slim trees ([`SlimParams::FAST`],
//! [`SlimParams::SMALL`]), writes each as `.kd` bytes in memory (Morton
//! reordering on, so 2-byte leaves are used wherever they fit), opens the
//! bytes as a [`KdFile`] and traces the scene's views from them. It returns
//! a [`Report`], which renders as Markdown ([`Report::markdown`]), as JSON
//! with the same numbers ([`Report::json`]), and as files
//! ([`Report::write`]: the Markdown, the JSON and the SVG figures).
//!
//! **The tables.**
//!
//! - *Table 1* (std tree): for each triangle, the number of leaves whose
//!   list holds it, counted in intervals, with the mean longest-edge length
//!   of the triangles in each interval; the total number of leaf indices
//!   and its ratio to the triangle count.
//! - *Table 2*: geometry as the paper counts it (12 bytes per triangle, 32
//!   per vertex) against the std tree, both as stored (2-byte leaves
//!   applied, [`TreeFigures::tree_bytes`]) and in the classic layout
//!   (`8·nodes + 4·references` bytes).
//! - *Table 3(a)*: node and index counts and memory of std, fast and small,
//!   with the reduction against std in the same format and against the
//!   classic std size.
//! - *Table 3(b)*: per view, Mrays/s (median of `reps` frames) on 1 thread
//!   and on `all_threads` threads, scalar and 4×4 packets, with the loss
//!   against std. Every frame of every tree, mode and thread count must
//!   give the same per-pixel hits as the std tree's first frame; a
//!   difference is an error ([`ReportError::Mismatch`]).
//! - *Table 4*: build times (std build, slim passes, their ratio) and the
//!   time to serialise each file.
//! - *Figure 5* (with `sweep`): a τ_occu × τ_freq grid of slim trees, size
//!   reduction against the frame-rate loss (packets, all threads, median
//!   over the views), one series per scene.
//! - *Figure 6*: the leaf-depth histograms of std, fast and small.
//!
//! Percentages are `100·(1 − x/std)`: a positive reduction is a smaller
//! tree, a positive loss a slower frame.

use super::plot::{self, LabelledPoint, LinePanel, LineSeries, ScatterSeries};
use crate::build::{self, BuildConfig, Builder};
use crate::format::{
    self, AlignedBytes, FileConfig, FormatError, KdFile, Preset, TreeFigures, WriteOptions,
};
use crate::geom::Aabb;
use crate::pipeline::{figures_json, file_config, merge_json};
use crate::render::{self, Camera, View};
use crate::scene::TriangleColumns;
use crate::slim::{self, HoistRule, SlimParams};
use crate::trace::packet::{PacketTracer, SimdLevel};
use crate::trace::{ClosestHit, Hit, Scalar};
use crate::tree::{Node, TreeIr};
use serde_json::{Value, json};
use std::fmt;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The default sweep grid of Figure 5: τ_occu values.
pub const SWEEP_TAU_OCCU: [f64; 4] = [0.3, 0.5, 0.7, 0.9];
/// The default sweep grid of Figure 5: τ_freq values.
pub const SWEEP_TAU_FREQ: [f64; 4] = [0.2, 0.4, 0.6, 0.8];
/// `max_t2rn` of every tree of the sweep.
pub const SWEEP_MAX_T2RN: u32 = 4;

/// The upper ends of the Table 1 intervals (1–10, 11–20, …, 10001–15000);
/// a last interval holds everything above.
pub const DUPLICATION_BOUNDS: [u64; 11] =
    [10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000, 15000];

/// The view ids looked up for every scene.
pub const VIEW_IDS: [&str; 3] = ["1", "2", "3"];

/// What to report on.
#[derive(Clone, Debug)]
pub struct ReportOptions {
    /// `(name, geometry, load seconds)`; the name is matched against the
    /// views file by [`render::find_view`] (a file name or path works).
    pub scenes: Vec<(String, TriangleColumns, f64)>,
    pub views: Vec<View>,
    /// Image size `(width, height)` of every traced frame.
    pub size: (u32, u32),
    /// Frames traced per measurement; the median is reported.
    pub reps: usize,
    /// Whether to run the threshold sweep of Figure 5.
    pub sweep: bool,
    /// Threads of the "all threads" columns (and of the builds).
    pub all_threads: usize,
    /// The sweep grid `(τ_occu values, τ_freq values)`; `None` uses
    /// [`SWEEP_TAU_OCCU`] × [`SWEEP_TAU_FREQ`].
    pub sweep_grid: Option<(Vec<f64>, Vec<f64>)>,
    /// The hoist rule of the fast, small and sweep trees (the presets' is
    /// [`HoistRule::Bytes`] for a reordered file, as the report writes).
    pub rule: HoistRule,
}

impl Default for ReportOptions {
    /// No scenes, 1024×1024 frames, 3 repetitions, no sweep, every core.
    fn default() -> Self {
        ReportOptions {
            scenes: Vec::new(),
            views: Vec::new(),
            size: (1024, 1024),
            reps: 3,
            sweep: false,
            all_threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            sweep_grid: None,
            rule: SlimParams::FAST.rule,
        }
    }
}

/// Why a report could not be made.
#[derive(Debug)]
pub enum ReportError {
    /// An option out of range.
    Options(String),
    /// A thread pool could not be started.
    ThreadPool(rayon::ThreadPoolBuildError),
    /// A tree could not be written or read back as a `.kd` file.
    Format {
        scene: String,
        tree: String,
        source: FormatError,
    },
    /// Two trees or two traversal modes disagree on the hits of a frame,
    /// which must never happen (slim trees are exact).
    Mismatch(String),
    /// The std tree of a scene could not be built.
    Build {
        scene: String,
        source: build::BuildError,
    },
}

impl fmt::Display for ReportError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ReportError::Options(m) => write!(f, "report: {m}"),
            ReportError::ThreadPool(e) => write!(f, "report: cannot start threads: {e}"),
            ReportError::Format {
                scene,
                tree,
                source,
            } => write!(
                f,
                "report: {scene}: the {tree} tree as a .kd file: {source}"
            ),
            ReportError::Mismatch(m) => write!(f, "report: hits differ: {m}"),
            ReportError::Build { scene, source } => {
                write!(f, "report: {scene}: the std build failed: {source}")
            }
        }
    }
}

impl std::error::Error for ReportError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            ReportError::ThreadPool(e) => Some(e),
            ReportError::Format { source, .. } => Some(source),
            ReportError::Build { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// The three trees of Tables 3 and 4.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TreeKind {
    Std,
    Fast,
    Small,
}

impl TreeKind {
    pub const ALL: [TreeKind; 3] = [TreeKind::Std, TreeKind::Fast, TreeKind::Small];

    pub fn name(self) -> &'static str {
        match self {
            TreeKind::Std => "std",
            TreeKind::Fast => "fast",
            TreeKind::Small => "small",
        }
    }

    /// The slim parameters with the given hoist rule (`None` for std).
    pub fn params(self, rule: HoistRule) -> Option<SlimParams> {
        match self {
            TreeKind::Std => None,
            TreeKind::Fast => Some(SlimParams::FAST.with_rule(rule)),
            TreeKind::Small => Some(SlimParams::SMALL.with_rule(rule)),
        }
    }

    fn preset(self) -> Preset {
        match self {
            TreeKind::Std => Preset::Std,
            TreeKind::Fast => Preset::Fast,
            TreeKind::Small => Preset::Small,
        }
    }
}

/// One interval of Table 1: triangles lying in `lo..=hi` leaves.
#[derive(Clone, Debug, PartialEq)]
pub struct DuplicationBin {
    pub lo: u64,
    /// `None`: no upper end.
    pub hi: Option<u64>,
    pub triangles: u64,
    /// Mean longest-edge length of those triangles (NaN when none).
    pub mean_longest_edge: f64,
}

impl DuplicationBin {
    /// The interval as written in the table: `11–20`, `> 15000`, `0`.
    pub fn label(&self) -> String {
        match self.hi {
            Some(hi) if hi == self.lo => format!("{hi}"),
            Some(hi) => format!("{}–{hi}", self.lo),
            None => format!("> {}", self.lo - 1),
        }
    }
}

/// Table 1 of one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Duplication {
    /// The intervals in order; a first interval `0–0` only if some triangle
    /// lies in no leaf.
    pub bins: Vec<DuplicationBin>,
    /// Leaf indices (`leaf_tris.len()`).
    pub total_indices: u64,
    pub triangles: u64,
}

impl Duplication {
    /// Indices per triangle.
    pub fn ratio(&self) -> f64 {
        ratio(self.total_indices as f64, self.triangles as f64)
    }
}

/// Table 1 for a tree: how many leaves hold each triangle, in intervals.
pub fn duplication(tree: &TreeIr, scene: &TriangleColumns) -> Duplication {
    let mut leaves_of = vec![0u64; scene.len()];
    let mut total = 0u64;
    for node in &tree.nodes {
        if let Node::Leaf { start, count } = *node {
            for t in tree.leaf(start, count) {
                leaves_of[t.0 as usize] += 1;
            }
            total += u64::from(count);
        }
    }
    // Interval 0 is "in no leaf"; then the paper's intervals and the rest.
    let mut uppers = vec![0u64];
    uppers.extend_from_slice(&DUPLICATION_BOUNDS);
    let n_bins = uppers.len() + 1;
    let mut counts = vec![0u64; n_bins];
    let mut edge_sums = vec![0f64; n_bins];
    for (t, &n) in leaves_of.iter().enumerate() {
        let bin = uppers.partition_point(|&u| u < n);
        let [a, b, c] = scene.tri(t as u32);
        let (a, b, c) = (a.as_dvec3(), b.as_dvec3(), c.as_dvec3());
        let longest = (b - a).length().max((c - b).length()).max((a - c).length());
        counts[bin] += 1;
        edge_sums[bin] += longest;
    }
    let bins = (0..n_bins)
        .filter(|&i| i > 0 || counts[0] > 0)
        .map(|i| DuplicationBin {
            lo: if i == 0 { 0 } else { uppers[i - 1] + 1 },
            hi: uppers.get(i).copied(),
            triangles: counts[i],
            mean_longest_edge: if counts[i] > 0 {
                edge_sums[i] / counts[i] as f64
            } else {
                f64::NAN
            },
        })
        .collect();
    Duplication {
        bins,
        total_indices: total,
        triangles: scene.len() as u64,
    }
}

/// One row of Table 3(a).
#[derive(Clone, Debug, PartialEq)]
pub struct SizeRow {
    pub tree: TreeKind,
    /// The counts of the written file.
    pub figures: TreeFigures,
    /// Triangles hoisted by the slim pass (0 for std).
    pub hoisted: usize,
    /// Bytes of the whole `.kd` file (geometry and header included).
    pub file_bytes: u64,
    pub max_depth: u32,
}

/// Frame rates of one tree in one view, in Mrays/s.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rates {
    pub scalar_1t: f64,
    pub scalar_all: f64,
    pub packet_1t: f64,
    pub packet_all: f64,
}

impl Rates {
    /// In column order: scalar 1 thread, scalar all, packet 1, packet all.
    pub fn as_array(&self) -> [f64; 4] {
        [
            self.scalar_1t,
            self.scalar_all,
            self.packet_1t,
            self.packet_all,
        ]
    }

    fn slot(&mut self, packet: bool, all: bool) -> &mut f64 {
        match (packet, all) {
            (false, false) => &mut self.scalar_1t,
            (false, true) => &mut self.scalar_all,
            (true, false) => &mut self.packet_1t,
            (true, true) => &mut self.packet_all,
        }
    }
}

/// Table 3(b) for one view.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewRates {
    /// The view id, or `default` for the default camera.
    pub view: String,
    /// Hit pixels of the frame (the same for every tree and mode).
    pub hits: u64,
    /// Sum of the hit distances (the same for every tree and mode).
    pub checksum: f64,
    /// Indexed like [`TreeKind::ALL`].
    pub rates: [Rates; 3],
}

impl ViewRates {
    /// The loss of `tree` against std in %, per column of [`Rates::as_array`].
    pub fn loss_pct(&self, tree: TreeKind) -> [f64; 4] {
        let std = self.rates[0].as_array();
        let r = self.rates[tree as usize].as_array();
        std::array::from_fn(|i| percent_below(r[i], std[i]))
    }
}

/// Table 4 of one scene, in seconds.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BuildTimes {
    pub load_s: f64,
    pub std_build_s: f64,
    /// The slim passes of fast and small (after the std build).
    pub slim_s: [f64; 2],
    /// Serialising std, fast and small to `.kd` bytes (in memory).
    pub write_s: [f64; 3],
}

impl BuildTimes {
    /// `(std build + slim pass) / std build` for fast (`0`) or small (`1`).
    pub fn slim_ratio(&self, i: usize) -> f64 {
        ratio(self.std_build_s + self.slim_s[i], self.std_build_s)
    }
}

/// One point of Figure 5.
#[derive(Clone, Debug, PartialEq)]
pub struct SweepPoint {
    pub tau_occu: f64,
    pub tau_freq: f64,
    pub max_t2rn: u32,
    pub tree_bytes: u64,
    pub hoisted: usize,
    /// Size reduction against std in the same format, %.
    pub reduction_pct: f64,
    /// Median over the views of the packet, all-threads frame-rate loss, %.
    pub loss_pct: f64,
    /// The loss per view, in view order.
    pub view_loss_pct: Vec<f64>,
    pub slim_s: f64,
}

/// Everything reported for one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneReport {
    pub name: String,
    pub triangles: u64,
    pub vertices: u64,
    pub table1: Duplication,
    /// Std, fast, small.
    pub table3a: [SizeRow; 3],
    pub table3b: Vec<ViewRates>,
    pub table4: BuildTimes,
    /// Figure 5 (empty without the sweep).
    pub sweep: Vec<SweepPoint>,
    /// Figure 6: leaves per depth of std, fast, small.
    pub leaf_depths: [Vec<u64>; 3],
}

impl SceneReport {
    /// Geometry as the paper counts it: 12 bytes per triangle, 32 per
    /// vertex.
    pub fn paper_geometry_bytes(&self) -> u64 {
        12 * self.triangles + 32 * self.vertices
    }

    /// The std tree as stored: 2-byte leaves applied.
    pub fn std_tree_bytes(&self) -> u64 {
        self.table3a[0].figures.tree_bytes()
    }

    /// The std tree in the classic layout: 8 bytes per node and 4 per leaf
    /// index, `8·nodes + 4·refs`.
    pub fn classic_std_bytes(&self) -> u64 {
        let f = &self.table3a[0].figures;
        8 * f.nodes() + 4 * (f.idx32 + f.idx16)
    }

    /// Size reduction of `tree` against std in the same format, %.
    pub fn reduction_pct(&self, tree: TreeKind) -> f64 {
        percent_below(
            self.table3a[tree as usize].figures.tree_bytes() as f64,
            self.std_tree_bytes() as f64,
        )
    }

    /// Size reduction of `tree` against the classic 4-byte std size, %.
    pub fn reduction_vs_classic_pct(&self, tree: TreeKind) -> f64 {
        percent_below(
            self.table3a[tree as usize].figures.tree_bytes() as f64,
            self.classic_std_bytes() as f64,
        )
    }
}

/// The whole report.
#[derive(Clone, Debug, PartialEq)]
pub struct Report {
    pub all_threads: usize,
    pub size: (u32, u32),
    pub reps: usize,
    /// The packet kernel's instruction set.
    pub simd: &'static str,
    pub sweep: bool,
    pub build: BuildConfig,
    pub rule: HoistRule,
    pub scenes: Vec<SceneReport>,
}

fn ratio(a: f64, b: f64) -> f64 {
    if b != 0.0 { a / b } else { f64::NAN }
}

/// `100·(1 − x/base)`; NaN when `base` is zero.
fn percent_below(x: f64, base: f64) -> f64 {
    if base != 0.0 {
        100.0 * (1.0 - x / base)
    } else {
        f64::NAN
    }
}

/// The name of a hoist rule as the CLI spells it.
pub fn rule_name(rule: HoistRule) -> &'static str {
    match rule {
        HoistRule::Paper => "paper",
        HoistRule::Bytes { .. } => "bytes",
    }
}

pub use crate::pipeline::median;

const MIB: f64 = (1u64 << 20) as f64;

/// A tree written and opened again.
struct Written {
    file: KdFile<AlignedBytes>,
    seconds: f64,
}

/// Serialises a tree (reordered) and opens the bytes.
fn write_tree(
    name: &str,
    label: &str,
    tree: &TreeIr,
    scene: &TriangleColumns,
    config: FileConfig,
) -> Result<Written, ReportError> {
    let err = |source| ReportError::Format {
        scene: name.to_string(),
        tree: label.to_string(),
        source,
    };
    let start = Instant::now();
    let bytes = format::write_to_vec(
        tree,
        scene,
        &WriteOptions {
            reorder: true,
            config,
        },
    )
    .map_err(err)?;
    let seconds = start.elapsed().as_secs_f64();
    let file = KdFile::from_bytes(format::aligned_copy(&bytes)).map_err(err)?;
    Ok(Written { file, seconds })
}

/// The cameras of a scene: its views 1–3, or the default camera.
fn cameras(options: &ReportOptions, name: &str, bounds: &Aabb) -> Vec<(String, Camera)> {
    let (w, h) = options.size;
    let found: Vec<(String, Camera)> = VIEW_IDS
        .iter()
        .filter_map(|id| {
            render::find_view(&options.views, Path::new(name), id)
                .map(|v| (id.to_string(), Camera::from_view(v, w, h)))
        })
        .collect();
    if found.is_empty() {
        vec![("default".to_string(), Camera::default_for(bounds, w, h))]
    } else {
        found
    }
}

/// The two thread pools: one thread and all threads.
struct Pools {
    one: rayon::ThreadPool,
    all: rayon::ThreadPool,
}

impl Pools {
    fn get(&self, all: bool) -> &rayon::ThreadPool {
        if all { &self.all } else { &self.one }
    }
}

/// Checks one frame's hits against the reference frame of its view.
fn check_hits(
    reference: &[Hit],
    got: &render::HitBuffer,
    what: impl FnOnce() -> String,
) -> Result<(), ReportError> {
    if got.hits.as_slice() == reference {
        return Ok(());
    }
    let first = reference
        .iter()
        .zip(&got.hits)
        .position(|(a, b)| a != b)
        .unwrap_or(0);
    Err(ReportError::Mismatch(format!(
        "{}: {} hits (checksum {}) against std's {} (checksum {}); first differing pixel {first}",
        what(),
        got.n_hits(),
        got.checksum(),
        reference.iter().filter(|h| h.t.is_finite()).count(),
        reference
            .iter()
            .filter(|h| h.t.is_finite())
            .fold(0.0, |s, h| s + f64::from(h.t)),
    )))
}

/// Table 3(b) for one scene: every view, mode and thread count; the trees'
/// frames interleaved within each repetition so that drift in the machine's
/// speed touches all trees alike.
fn measure_views(
    name: &str,
    cams: &[(String, Camera)],
    files: &[&KdFile<AlignedBytes>; 3],
    pools: &Pools,
    reps: usize,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<ViewRates>, ReportError> {
    let scalars: Vec<Scalar<'_, KdFile<AlignedBytes>>> = files.iter().map(|f| Scalar(*f)).collect();
    let packets: Vec<PacketTracer<'_, KdFile<AlignedBytes>>> =
        files.iter().map(|f| PacketTracer::new(*f)).collect();
    let mut out = Vec::new();
    for (id, cam) in cams {
        let reference = pools.one.install(|| render::trace_frame(&scalars[0], cam));
        let mut rates = [Rates::default(); 3];
        for packet in [false, true] {
            for all in [false, true] {
                let pool = pools.get(all);
                let threads = pool.current_num_threads();
                let mode = if packet { "packet" } else { "scalar" };
                progress(&format!(
                    "{name}: tracing view {id} ({mode}, {threads} thread{})",
                    if threads == 1 { "" } else { "s" }
                ));
                let tracers: Vec<&dyn ClosestHit> = if packet {
                    packets.iter().map(|t| t as &dyn ClosestHit).collect()
                } else {
                    scalars.iter().map(|t| t as &dyn ClosestHit).collect()
                };
                let mut samples: [Vec<f64>; 3] = Default::default();
                // One warm-up frame per tree, then the timed ones.
                for rep in 0..=reps {
                    for (k, kind) in TreeKind::ALL.iter().enumerate() {
                        let buf = pool.install(|| render::trace_frame(tracers[k], cam));
                        check_hits(&reference.hits, &buf, || {
                            format!(
                                "{name} view {id}: the {} tree, {mode}, {threads} threads",
                                kind.name()
                            )
                        })?;
                        if rep > 0 {
                            samples[k].push(buf.mrays_per_s());
                        }
                    }
                }
                for k in 0..3 {
                    *rates[k].slot(packet, all) = median(&samples[k]);
                }
            }
        }
        out.push(ViewRates {
            view: id.clone(),
            hits: reference.n_hits(),
            checksum: reference.checksum(),
            rates,
        });
    }
    Ok(out)
}

/// One point of the sweep: a slim tree with the given thresholds against
/// std, packets on all threads.
#[allow(clippy::too_many_arguments)]
fn sweep_point(
    name: &str,
    scene: &TriangleColumns,
    std_tree: &TreeIr,
    std_file: &KdFile<AlignedBytes>,
    config: &BuildConfig,
    params: SlimParams,
    cams: &[(String, Camera)],
    pools: &Pools,
    reps: usize,
) -> Result<SweepPoint, ReportError> {
    let start = Instant::now();
    let (tree, slim_report) = pools
        .all
        .install(|| slim::slim(std_tree, scene, config, &params));
    let slim_s = start.elapsed().as_secs_f64();
    let label = format!("τ_occu {} τ_freq {}", params.tau_occu, params.tau_freq);
    let cfg = file_config(config, scene.len(), Preset::Custom, Some(&params));
    let written = write_tree(name, &label, &tree, scene, cfg)?;
    drop(tree);
    let std_tracer = PacketTracer::new(std_file);
    let tracer = PacketTracer::new(&written.file);
    let mut view_loss_pct = Vec::new();
    for (id, cam) in cams {
        let (mut std_rates, mut rates) = (Vec::new(), Vec::new());
        for rep in 0..=reps {
            let a = pools.all.install(|| render::trace_frame(&std_tracer, cam));
            let b = pools.all.install(|| render::trace_frame(&tracer, cam));
            check_hits(&a.hits, &b, || {
                format!("{name} view {id}: the {label} tree")
            })?;
            if rep > 0 {
                std_rates.push(a.mrays_per_s());
                rates.push(b.mrays_per_s());
            }
        }
        view_loss_pct.push(percent_below(median(&rates), median(&std_rates)));
    }
    let tree_bytes = written.file.figures().tree_bytes();
    Ok(SweepPoint {
        tau_occu: params.tau_occu,
        tau_freq: params.tau_freq,
        max_t2rn: params.max_t2rn,
        tree_bytes,
        hoisted: slim_report.hoisted,
        reduction_pct: percent_below(tree_bytes as f64, std_file.figures().tree_bytes() as f64),
        loss_pct: median(&view_loss_pct),
        view_loss_pct,
        slim_s,
    })
}

/// Builds, writes and traces every scene; `progress` gets one line per
/// step.
pub fn run(options: &ReportOptions, progress: &mut dyn FnMut(&str)) -> Result<Report, ReportError> {
    if options.reps == 0 {
        return Err(ReportError::Options("reps must be at least 1".into()));
    }
    if options.all_threads == 0 {
        return Err(ReportError::Options("threads must be at least 1".into()));
    }
    if options.size.0 == 0 || options.size.1 == 0 {
        return Err(ReportError::Options(
            "the image size must not be zero".into(),
        ));
    }
    let pool = |n: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .map_err(ReportError::ThreadPool)
    };
    let pools = Pools {
        one: pool(1)?,
        all: pool(options.all_threads)?,
    };
    let (grid_occu, grid_freq) = match &options.sweep_grid {
        Some((o, f)) => (o.clone(), f.clone()),
        None => (SWEEP_TAU_OCCU.to_vec(), SWEEP_TAU_FREQ.to_vec()),
    };
    let config = BuildConfig::default();
    let mut scenes = Vec::new();
    for (name, scene, load_s) in &options.scenes {
        progress(&format!("{name}: building std tree"));
        let start = Instant::now();
        // The level builder is the fastest (the same tree as every other
        // builder), so the slim ratios of Table 4 are against the best std
        // build; the slim passes run on the same pool.
        let std_tree = pools
            .all
            .install(|| build::build(scene, &config, Builder::Level, None))
            .map_err(|source| ReportError::Build {
                scene: name.clone(),
                source,
            })?;
        let std_build_s = start.elapsed().as_secs_f64();
        let table1 = duplication(&std_tree, scene);
        let mut times = BuildTimes {
            load_s: *load_s,
            std_build_s,
            ..BuildTimes::default()
        };
        let mut written = Vec::new();
        let mut hoisted = [0usize; 3];
        for (k, kind) in TreeKind::ALL.into_iter().enumerate() {
            let slimmed = match kind.params(options.rule) {
                None => None,
                Some(p) => {
                    progress(&format!("{name}: slim pass ({})", kind.name()));
                    let start = Instant::now();
                    let (t, r) = pools
                        .all
                        .install(|| slim::slim(&std_tree, scene, &config, &p));
                    times.slim_s[k - 1] = start.elapsed().as_secs_f64();
                    hoisted[k] = r.hoisted;
                    Some(t)
                }
            };
            progress(&format!("{name}: writing {} file", kind.name()));
            let tree = slimmed.as_ref().unwrap_or(&std_tree);
            let cfg = file_config(
                &config,
                scene.len(),
                kind.preset(),
                kind.params(options.rule).as_ref(),
            );
            let w = write_tree(name, kind.name(), tree, scene, cfg)?;
            times.write_s[k] = w.seconds;
            written.push(w);
        }
        let files: [&KdFile<AlignedBytes>; 3] =
            [&written[0].file, &written[1].file, &written[2].file];
        let table3a: [SizeRow; 3] = std::array::from_fn(|k| SizeRow {
            tree: TreeKind::ALL[k],
            figures: files[k].figures(),
            hoisted: hoisted[k],
            file_bytes: files[k].as_bytes().len() as u64,
            max_depth: files[k].max_depth(),
        });
        let leaf_depths = files.map(|f| f.leaf_depth_histogram());
        let cams = cameras(options, name, &std_tree.bounds);
        let table3b = measure_views(name, &cams, &files, &pools, options.reps, progress)?;
        let mut sweep = Vec::new();
        if options.sweep {
            for &tau_occu in &grid_occu {
                for &tau_freq in &grid_freq {
                    progress(&format!(
                        "{name}: sweep τ_occu {tau_occu} τ_freq {tau_freq}"
                    ));
                    let params = SlimParams {
                        tau_occu,
                        tau_freq,
                        max_t2rn: SWEEP_MAX_T2RN,
                        rule: options.rule,
                    };
                    sweep.push(sweep_point(
                        name,
                        scene,
                        &std_tree,
                        files[0],
                        &config,
                        params,
                        &cams,
                        &pools,
                        options.reps,
                    )?);
                }
            }
        }
        scenes.push(SceneReport {
            name: name.clone(),
            triangles: scene.len() as u64,
            vertices: scene.positions().len() as u64,
            table1,
            table3a,
            table3b,
            table4: times,
            sweep,
            leaf_depths,
        });
    }
    Ok(Report {
        all_threads: pools.all.current_num_threads(),
        size: options.size,
        reps: options.reps,
        simd: SimdLevel::detect().name(),
        sweep: options.sweep,
        build: config,
        rule: options.rule,
        scenes,
    })
}

/// A number with `prec` decimals, or `–` when it is not finite.
fn num(x: f64, prec: usize) -> String {
    if x.is_finite() {
        format!("{x:.prec$}")
    } else {
        "–".to_string()
    }
}

/// A number for JSON: `null` when it is not finite.
fn jnum(x: f64) -> Value {
    if x.is_finite() { json!(x) } else { Value::Null }
}

/// A Markdown table with padded columns; `right[i]` right-aligns column
/// `i`.
fn md_table(header: &[&str], right: &[bool], rows: &[Vec<String>]) -> String {
    let width = |s: &str| s.chars().count();
    let mut w: Vec<usize> = header.iter().map(|h| width(h).max(3)).collect();
    for row in rows {
        for (i, cell) in row.iter().enumerate() {
            w[i] = w[i].max(width(cell));
        }
    }
    let line = |cells: Vec<String>| {
        let mut s = String::from("|");
        for (i, c) in cells.iter().enumerate() {
            let pad = " ".repeat(w[i] - width(c));
            if right[i] {
                s += &format!(" {pad}{c} |");
            } else {
                s += &format!(" {c}{pad} |");
            }
        }
        s + "\n"
    };
    let mut out = line(header.iter().map(|h| h.to_string()).collect());
    out += &line(
        (0..header.len())
            .map(|i| {
                if right[i] {
                    format!("{}:", "-".repeat(w[i] - 1))
                } else {
                    "-".repeat(w[i])
                }
            })
            .collect(),
    );
    for row in rows {
        out += &line(row.clone());
    }
    out
}

/// The file names of the figures, next to the Markdown file.
pub const FIGURE5_FILE: &str = "figure5.svg";
pub const FIGURE6_FILE: &str = "figure6.svg";

impl Report {
    /// The report as Markdown.
    pub fn markdown(&self) -> String {
        let mut md = String::new();
        let names: Vec<&str> = self.scenes.iter().map(|s| s.name.as_str()).collect();
        md += "# slimkd report\n\n";
        md += &format!(
            "The tables and figures of Choi, Chang & Ihm (2013) for {} scene{}: {}.\n\n",
            self.scenes.len(),
            if self.scenes.len() == 1 { "" } else { "s" },
            names.join(", ")
        );
        md += &format!(
            "**Machine figures.** Frame rates are the median of {} frame{} (after one warm-up frame) of \
             {}×{} primary rays, one per pixel, on 1 thread and on {} threads; the packet mode traces \
             4×4 rays with the `{}` kernel. Host: {} with {} hardware threads. Trees are built by the \
             sweep builder (K_T {}, K_I {}, λ {}), written with Morton reordering (2-byte leaves where \
             they fit) and traced from the `.kd` bytes in memory. Presets: fast τ_occu {} τ_freq {}, \
             small τ_occu {} τ_freq {}, max_t2rn {}, hoist rule `{}`. Percentages are 100·(1 − x/std): a positive \
             reduction is a smaller tree, a positive loss a slower frame.\n\n",
            self.reps,
            if self.reps == 1 { "" } else { "s" },
            self.size.0,
            self.size.1,
            self.all_threads,
            self.simd,
            std::env::consts::ARCH,
            std::thread::available_parallelism().map_or(1, |n| n.get()),
            self.build.sah.k_t,
            self.build.sah.k_i,
            self.build.sah.lambda_empty,
            SlimParams::FAST.tau_occu,
            SlimParams::FAST.tau_freq,
            SlimParams::SMALL.tau_occu,
            SlimParams::SMALL.tau_freq,
            SlimParams::FAST.max_t2rn,
            rule_name(self.rule),
        );

        md += "## Table 1. Leaves per triangle (std tree)\n\n";
        md += "For each triangle, the number of leaves whose list holds it; per interval the number \
               of triangles and their mean longest-edge length (scene units).\n\n";
        for s in &self.scenes {
            md += &format!("### {}\n\n", s.name);
            let rows: Vec<Vec<String>> = s
                .table1
                .bins
                .iter()
                .map(|b| {
                    vec![
                        b.label(),
                        b.triangles.to_string(),
                        num(100.0 * ratio(b.triangles as f64, s.triangles as f64), 2),
                        num(b.mean_longest_edge, 4),
                    ]
                })
                .collect();
            md += &md_table(
                &["leaves", "triangles", "% of triangles", "mean longest edge"],
                &[false, true, true, true],
                &rows,
            );
            md += &format!(
                "\nTotal indices {} for {} triangles: {} per triangle.\n\n",
                s.table1.total_indices,
                s.table1.triangles,
                num(s.table1.ratio(), 3)
            );
        }

        md += "## Table 2. Geometry against the std tree\n\n";
        md += "Geometry as the paper counts it: 12 bytes per triangle and 32 per vertex. Std tree as \
               stored: 8 bytes per node, 4 or 2 per leaf index (2-byte leaves applied). Classic std: \
               8·nodes + 4·references bytes (4-byte indices only).\n\n";
        let rows: Vec<Vec<String>> = self
            .scenes
            .iter()
            .map(|s| {
                let g = s.paper_geometry_bytes() as f64;
                vec![
                    s.name.clone(),
                    s.triangles.to_string(),
                    s.vertices.to_string(),
                    num(g / MIB, 3),
                    num(s.std_tree_bytes() as f64 / MIB, 3),
                    num(ratio(s.std_tree_bytes() as f64, g), 3),
                    num(s.classic_std_bytes() as f64 / MIB, 3),
                    num(ratio(s.classic_std_bytes() as f64, g), 3),
                ]
            })
            .collect();
        md += &md_table(
            &[
                "scene",
                "triangles",
                "vertices",
                "geometry (MiB)",
                "std tree, 2-byte leaves (MiB)",
                "tree / geometry",
                "classic std, 4-byte (MiB)",
                "classic / geometry",
            ],
            &[false, true, true, true, true, true, true, true],
            &rows,
        );
        md += "\n";

        md += "## Table 3(a). Tree size\n\n";
        md += "Nodes as the paper counts them (inner, t-inner, leaf); memory is 8·(nodes + \
               T-references) + 4·idx32 + 2·idx16 bytes. *Reduction (same format)* compares with the \
               std tree as stored (2-byte leaves applied); *reduction vs classic* compares with the \
               classic 4-byte std size of Table 2.\n\n";
        let mut rows = Vec::new();
        for s in &self.scenes {
            for row in &s.table3a {
                let f = &row.figures;
                rows.push(vec![
                    s.name.clone(),
                    row.tree.name().to_string(),
                    f.inner.to_string(),
                    f.t_inner.to_string(),
                    f.leaves.to_string(),
                    f.nodes().to_string(),
                    f.idx32.to_string(),
                    f.idx16.to_string(),
                    num(f.tree_bytes() as f64 / MIB, 3),
                    num(s.reduction_pct(row.tree), 1),
                    num(s.reduction_vs_classic_pct(row.tree), 1),
                ]);
            }
        }
        md += &md_table(
            &[
                "scene",
                "tree",
                "inner",
                "t-inner",
                "leaf",
                "total",
                "4-byte idx",
                "2-byte idx",
                "memory (MiB)",
                "reduction, same format (%)",
                "reduction vs classic 4-byte std (%)",
            ],
            &[
                false, false, true, true, true, true, true, true, true, true, true,
            ],
            &rows,
        );
        md += "\n";

        md += "## Table 3(b). Frame rate\n\n";
        md += &format!(
            "Mrays/s (median of {}); *loss* is the drop against std in the same column, %. Every tree \
             and mode gave the same hits as std (checked per pixel).\n\n",
            self.reps
        );
        let all = format!("{}T", self.all_threads);
        let heads = [
            "scalar 1T".to_string(),
            "loss".to_string(),
            format!("scalar {all}"),
            "loss".to_string(),
            "packet 1T".to_string(),
            "loss".to_string(),
            format!("packet {all}"),
            "loss".to_string(),
        ];
        let mut header: Vec<&str> = vec!["scene", "view", "hits", "tree"];
        header.extend(heads.iter().map(String::as_str));
        let mut rows = Vec::new();
        for s in &self.scenes {
            for v in &s.table3b {
                for kind in TreeKind::ALL {
                    let r = v.rates[kind as usize].as_array();
                    let l = v.loss_pct(kind);
                    let mut row = vec![
                        s.name.clone(),
                        v.view.clone(),
                        v.hits.to_string(),
                        kind.name().to_string(),
                    ];
                    for i in 0..4 {
                        row.push(num(r[i], 2));
                        row.push(if kind == TreeKind::Std {
                            String::new()
                        } else {
                            num(l[i], 1)
                        });
                    }
                    rows.push(row);
                }
            }
        }
        let mut right = vec![false, false, true, false];
        right.extend([true; 8]);
        md += &md_table(&header, &right, &rows);
        md += "\n";

        md += "## Table 4. Build times\n\n";
        md += "Seconds. The slim passes run on the std tree; *ratio* is (std build + slim pass) / std \
               build. *Write* serialises the tree and geometry to `.kd` bytes in memory.\n\n";
        let rows: Vec<Vec<String>> = self
            .scenes
            .iter()
            .map(|s| {
                let t = &s.table4;
                vec![
                    s.name.clone(),
                    s.triangles.to_string(),
                    num(t.load_s, 3),
                    num(t.std_build_s, 3),
                    num(t.slim_s[0], 3),
                    num(t.slim_ratio(0), 2),
                    num(t.slim_s[1], 3),
                    num(t.slim_ratio(1), 2),
                    num(t.write_s[0], 3),
                    num(t.write_s[1], 3),
                    num(t.write_s[2], 3),
                ]
            })
            .collect();
        md += &md_table(
            &[
                "scene",
                "triangles",
                "load",
                "std build",
                "fast pass",
                "fast ratio",
                "small pass",
                "small ratio",
                "write std",
                "write fast",
                "write small",
            ],
            &[
                false, true, true, true, true, true, true, true, true, true, true,
            ],
            &rows,
        );
        md += "\n";

        if self.sweep {
            md += "## Figure 5. Threshold sweep\n\n";
            md += &format!(
                "Size reduction against std (same format) and frame-rate loss (packets, {} threads, \
                 median over the views) for a τ_occu × τ_freq grid, max_t2rn {SWEEP_MAX_T2RN}.\n\n\
                 ![Figure 5]({FIGURE5_FILE})\n\n",
                self.all_threads
            );
            let mut rows = Vec::new();
            for s in &self.scenes {
                for p in &s.sweep {
                    rows.push(vec![
                        s.name.clone(),
                        format!("{}", p.tau_occu),
                        format!("{}", p.tau_freq),
                        p.hoisted.to_string(),
                        num(p.tree_bytes as f64 / MIB, 3),
                        num(p.reduction_pct, 1),
                        num(p.loss_pct, 1),
                        num(p.slim_s, 3),
                    ]);
                }
            }
            md += &md_table(
                &[
                    "scene",
                    "τ_occu",
                    "τ_freq",
                    "hoisted",
                    "memory (MiB)",
                    "reduction (%)",
                    "loss (%)",
                    "slim pass (s)",
                ],
                &[false, true, true, true, true, true, true, true],
                &rows,
            );
            md += "\n";
        }

        md += "## Figure 6. Leaf-depth histograms\n\n";
        md += &format!("Leaves per depth (root = 0).\n\n![Figure 6]({FIGURE6_FILE})\n\n");
        for s in &self.scenes {
            md += &format!("### {}\n\n", s.name);
            let depth = s.leaf_depths.iter().map(Vec::len).max().unwrap_or(0);
            let rows: Vec<Vec<String>> = (0..depth)
                .map(|d| {
                    let mut row = vec![d.to_string()];
                    row.extend(
                        s.leaf_depths
                            .iter()
                            .map(|h| h.get(d).copied().unwrap_or(0).to_string()),
                    );
                    row
                })
                .collect();
            md += &md_table(
                &["depth", "std", "fast", "small"],
                &[true, true, true, true],
                &rows,
            );
            md += "\n";
        }
        md
    }

    /// The report as one JSON object, with the numbers of the Markdown
    /// (unrounded; `null` for a value that is not finite).
    pub fn json(&self) -> Value {
        let scenes: Vec<Value> = self.scenes.iter().map(scene_json).collect();
        json!({
            "machine": {
                "all_threads": self.all_threads,
                "width": self.size.0,
                "height": self.size.1,
                "reps": self.reps,
                "simd": self.simd,
                "arch": std::env::consts::ARCH,
                "available_parallelism": std::thread::available_parallelism().map_or(1, |n| n.get()),
            },
            "build": {
                "builder": "sweep",
                "k_t": self.build.sah.k_t,
                "k_i": self.build.sah.k_i,
                "lambda_empty": self.build.sah.lambda_empty,
                "reorder": true,
            },
            "presets": TreeKind::ALL.iter().filter_map(|k| k.params(self.rule).map(|p| json!({
                "tree": k.name(),
                "tau_occu": p.tau_occu,
                "tau_freq": p.tau_freq,
                "max_t2rn": p.max_t2rn,
                "hoist_rule": rule_name(p.rule),
            }))).collect::<Vec<_>>(),
            "sweep": self.sweep,
            "scenes": scenes,
        })
    }

    /// Figure 5 as SVG: one series per scene.
    pub fn figure5_svg(&self) -> Result<String, plot::PlotError> {
        let series: Vec<ScatterSeries> = self
            .scenes
            .iter()
            .map(|s| ScatterSeries {
                name: s.name.clone(),
                points: s
                    .sweep
                    .iter()
                    .map(|p| LabelledPoint {
                        x: p.reduction_pct,
                        y: p.loss_pct,
                        label: format!("{}/{}", p.tau_occu, p.tau_freq),
                    })
                    .collect(),
            })
            .collect();
        plot::scatter_svg(
            &format!(
                "Figure 5: τ_occu/τ_freq sweep (max_t2rn {SWEEP_MAX_T2RN}), packets, {} threads",
                self.all_threads
            ),
            "size reduction against std (%)",
            "frame-rate loss (%)",
            &series,
            (900, 640),
        )
    }

    /// Figure 6 as SVG: one panel per scene, a line per tree.
    pub fn figure6_svg(&self) -> Result<String, plot::PlotError> {
        let panels: Vec<LinePanel> = self
            .scenes
            .iter()
            .map(|s| LinePanel {
                title: format!("Figure 6: leaf depths, {}", s.name),
                series: TreeKind::ALL
                    .iter()
                    .zip(&s.leaf_depths)
                    .map(|(k, h)| LineSeries {
                        name: k.name().to_string(),
                        points: h
                            .iter()
                            .enumerate()
                            .map(|(d, &n)| (d as f64, n as f64))
                            .collect(),
                    })
                    .collect(),
            })
            .collect();
        plot::line_panels_svg(&panels, "depth", "leaves", (900, 360))
    }

    /// Writes the Markdown to `md_path`, the JSON next to it (same stem,
    /// `.json`), and the figures (`figure5.svg` with the sweep,
    /// `figure6.svg`) into the same directory; returns the paths written.
    /// Each file is written to a temporary file and renamed into place, and
    /// every temporary file is written before the first rename, so a
    /// failure (e.g. a missing directory) leaves no file behind.
    pub fn write(&self, md_path: &Path) -> std::io::Result<Vec<PathBuf>> {
        let invalid = |m: String| std::io::Error::new(std::io::ErrorKind::InvalidInput, m);
        if md_path.file_name().is_none() {
            return Err(invalid(format!("{}: not a file name", md_path.display())));
        }
        let json_path = md_path.with_extension("json");
        if json_path == md_path {
            return Err(invalid(format!(
                "{}: the Markdown file must not end in .json (the JSON goes next to it)",
                md_path.display()
            )));
        }
        let dir = match md_path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let mut json_text =
            serde_json::to_string_pretty(&self.json()).map_err(std::io::Error::other)?;
        json_text.push('\n');
        let mut files = vec![
            (md_path.to_path_buf(), self.markdown()),
            (json_path, json_text),
        ];
        if self.sweep {
            let svg = self.figure5_svg().map_err(std::io::Error::other)?;
            files.push((dir.join(FIGURE5_FILE), svg));
        }
        let svg = self.figure6_svg().map_err(std::io::Error::other)?;
        files.push((dir.join(FIGURE6_FILE), svg));
        write_all_atomically(&files)?;
        Ok(files.into_iter().map(|(p, _)| p).collect())
    }
}

fn scene_json(s: &SceneReport) -> Value {
    let g = s.paper_geometry_bytes();
    json!({
        "name": s.name,
        "triangles": s.triangles,
        "vertices": s.vertices,
        "table1": {
            "bins": s.table1.bins.iter().map(|b| json!({
                "lo": b.lo,
                "hi": b.hi,
                "triangles": b.triangles,
                "mean_longest_edge": jnum(b.mean_longest_edge),
            })).collect::<Vec<_>>(),
            "total_indices": s.table1.total_indices,
            "indices_per_triangle": jnum(s.table1.ratio()),
        },
        "table2": {
            "geometry_bytes": g,
            "std_tree_bytes": s.std_tree_bytes(),
            "std_classic_bytes": s.classic_std_bytes(),
            "tree_to_geometry": jnum(ratio(s.std_tree_bytes() as f64, g as f64)),
            "classic_to_geometry": jnum(ratio(s.classic_std_bytes() as f64, g as f64)),
        },
        "table3a": s.table3a.iter().map(|r| {
            let f = &r.figures;
            let mut row = figures_json(f);
            merge_json(&mut row, json!({
                "tree": r.tree.name(),
                "mib": f.tree_bytes() as f64 / MIB,
                "reduction_pct": jnum(s.reduction_pct(r.tree)),
                "reduction_vs_classic_pct": jnum(s.reduction_vs_classic_pct(r.tree)),
                "hoisted": r.hoisted,
                "file_bytes": r.file_bytes,
                "max_depth": r.max_depth,
            }));
            row
        }).collect::<Vec<_>>(),
        "table3b": s.table3b.iter().map(|v| json!({
            "view": v.view,
            "hits": v.hits,
            "checksum": v.checksum,
            "trees": TreeKind::ALL.iter().map(|&k| {
                let r = &v.rates[k as usize];
                let l = v.loss_pct(k);
                json!({
                    "tree": k.name(),
                    "scalar_1t": jnum(r.scalar_1t),
                    "scalar_all": jnum(r.scalar_all),
                    "packet_1t": jnum(r.packet_1t),
                    "packet_all": jnum(r.packet_all),
                    "loss_pct": {
                        "scalar_1t": jnum(l[0]),
                        "scalar_all": jnum(l[1]),
                        "packet_1t": jnum(l[2]),
                        "packet_all": jnum(l[3]),
                    },
                })
            }).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
        "table4": {
            "load_s": s.table4.load_s,
            "std_build_s": s.table4.std_build_s,
            "fast_slim_s": s.table4.slim_s[0],
            "small_slim_s": s.table4.slim_s[1],
            "fast_ratio": jnum(s.table4.slim_ratio(0)),
            "small_ratio": jnum(s.table4.slim_ratio(1)),
            "write_s": {
                "std": s.table4.write_s[0],
                "fast": s.table4.write_s[1],
                "small": s.table4.write_s[2],
            },
        },
        "figure5": s.sweep.iter().map(|p| json!({
            "tau_occu": p.tau_occu,
            "tau_freq": p.tau_freq,
            "max_t2rn": p.max_t2rn,
            "tree_bytes": p.tree_bytes,
            "hoisted": p.hoisted,
            "reduction_pct": jnum(p.reduction_pct),
            "loss_pct": jnum(p.loss_pct),
            "view_loss_pct": p.view_loss_pct.iter().map(|&x| jnum(x)).collect::<Vec<_>>(),
            "slim_s": p.slim_s,
        })).collect::<Vec<_>>(),
        "figure6": {
            "std": s.leaf_depths[0],
            "fast": s.leaf_depths[1],
            "small": s.leaf_depths[2],
        },
    })
}

/// Adds the path to an I/O error's message.
fn with_path(path: &Path, e: std::io::Error) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("{}: {e}", path.display()))
}

/// Writes every file through a temporary file ([`crate::fsio::Staged`]);
/// renames only once all of them are written and synced. On failure, the
/// temporary files not yet renamed go.
fn write_all_atomically(files: &[(PathBuf, String)]) -> std::io::Result<()> {
    let mut staged = Vec::with_capacity(files.len());
    for (path, contents) in files {
        let mut f = crate::fsio::Staged::create(path).map_err(|e| with_path(path, e))?;
        f.file()
            .write_all(contents.as_bytes())
            .and_then(|()| f.stage())
            .map_err(|e| with_path(path, e))?;
        staged.push(f);
    }
    for ((path, _), f) in files.iter().zip(staged) {
        f.commit().map_err(|e| with_path(path, e))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn md_table_pads_columns() {
        let t = md_table(
            &["a", "bb"],
            &[false, true],
            &[
                vec!["τ_occu".into(), "1".into()],
                vec!["x".into(), "12345".into()],
            ],
        );
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 4);
        let widths: Vec<usize> = lines.iter().map(|l| l.chars().count()).collect();
        assert!(widths.iter().all(|&w| w == widths[0]), "{t}");
        assert!(
            lines[1].ends_with("---: |") || lines[1].ends_with("----: |"),
            "{t}"
        );
    }

    #[test]
    fn bin_labels() {
        let b = |lo, hi| DuplicationBin {
            lo,
            hi,
            triangles: 0,
            mean_longest_edge: f64::NAN,
        };
        assert_eq!(b(0, Some(0)).label(), "0");
        assert_eq!(b(11, Some(20)).label(), "11–20");
        assert_eq!(b(15001, None).label(), "> 15000");
    }
}
