//! The paper's tables and figures for a set of scenes (Choi, Chang & Ihm
//! 2013): what `slimkd report` writes.
//!
//! [`run()`] builds, for every scene, the standard SAH tree (level builder),
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
//!   applied, [`TreeFigures::tree_bytes`]: slimkd's std) and in the
//!   paper's layout (Wald 2004, `8·nodes + 4·references` bytes: the
//!   paper's std).
//! - *Table 3(a)*: node and index counts and memory of std, fast and small,
//!   each also in the paper's layout, with the reduction against both
//!   baselines: slimkd's std in the same format and the paper's std.
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
//! `front.rs` is the trade-off front of `slimkd sweep`: tree bytes against
//! trace time over families of settings ([`run_front`]).
//!
//! Percentages are `100·(1 − x/std)`: a positive reduction is a smaller
//! tree, a positive loss a slower frame.

pub(crate) mod front;
mod json;
mod markdown;
mod run;
mod tables;

#[cfg(test)]
pub use run::run;
pub use run::run_with_progress;

use crate::lab::plot::{self, LabelledPoint, LinePanel, LineSeries, ScatterSeries};
use slimkd::build::{self, BuildConfig};
use slimkd::format::{self, AlignedBytes, FormatError, KdFile, Preset, TreeFigures};
use slimkd::geom::Aabb;
use slimkd::render::{self, Camera, View};
use slimkd::scene::TriangleColumns;
use slimkd::slim::{HoistRule, SlimParams};
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{ClosestHit, Hit, Scalar};
use slimkd::tree::{Node, TreeIr};
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
    /// `(name, geometry, load seconds)`: the scene's name (its file's stem,
    /// as tables and legends show it and `.kd` headers record it) is
    /// matched against the views file by [`render::find_view_named`] (or,
    /// for a file name or path, by its stem).
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
    /// No scenes, 1024×1024 frames, 9 repetitions, no sweep, every core.
    fn default() -> Self {
        ReportOptions {
            scenes: Vec::new(),
            views: Vec::new(),
            size: (1024, 1024),
            reps: 9,
            sweep: false,
            all_threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            sweep_grid: None,
            rule: SlimParams::FAST.rule,
        }
    }
}

/// Why a report could not be made.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// An option out of range.
    #[error("report: {0}")]
    Options(String),
    /// A thread pool could not be started.
    #[error("report: cannot start threads: {0}")]
    ThreadPool(#[source] rayon::ThreadPoolBuildError),
    /// A tree could not be written or read back as a `.kd` file.
    #[error("report: {scene}: the {tree} tree as a .kd file: {source}")]
    Format {
        scene: String,
        tree: String,
        source: FormatError,
    },
    /// Two trees or two traversal modes disagree on the hits of a frame,
    /// which must never happen (slim trees are exact).
    #[error("report: hits differ: {0}")]
    Mismatch(String),
    /// The std tree of a scene could not be built.
    #[error("report: {scene}: the std build failed: {source}")]
    Build {
        scene: String,
        source: build::BuildError,
    },
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

    /// The slim parameters with the given hoist rule (`None` for std):
    /// the paper's settings with its rule, the presets with the byte rule.
    pub fn params(self, rule: HoistRule) -> Option<SlimParams> {
        match (self, rule) {
            (TreeKind::Std, _) => None,
            (TreeKind::Fast, HoistRule::Paper) => Some(SlimParams::PAPER_FAST),
            (TreeKind::Small, HoistRule::Paper) => Some(SlimParams::PAPER_SMALL),
            (TreeKind::Fast, _) => Some(SlimParams::FAST.with_rule(rule)),
            (TreeKind::Small, _) => Some(SlimParams::SMALL.with_rule(rule)),
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

/// The spread of repeated measurements: median, quartiles (linear
/// interpolation between order statistics) and extremes; NaN for none.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Spread {
    pub median: f64,
    pub q1: f64,
    pub q3: f64,
    pub min: f64,
    pub max: f64,
}

impl Spread {
    pub fn of(values: &[f64]) -> Spread {
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        let at = |q: f64| {
            if v.is_empty() {
                return f64::NAN;
            }
            let pos = q * (v.len() - 1) as f64;
            let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
            v[lo] + (v[hi] - v[lo]) * (pos - lo as f64)
        };
        Spread {
            median: median(values),
            q1: at(0.25),
            q3: at(0.75),
            min: at(0.0),
            max: at(1.0),
        }
    }

    /// Whether 0 lies inside the interquartile range: a difference that
    /// the repetitions do not tell from the machine's noise.
    pub fn includes_zero(&self) -> bool {
        self.q1 <= 0.0 && 0.0 <= self.q3
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
    /// Indexed like [`TreeKind::ALL`]: the median of each column.
    pub rates: [Rates; 3],
    /// The loss against std in %, per tree (like [`TreeKind::ALL`]) and
    /// column (like [`Rates::as_array`]): the spread over the repetitions of
    /// the loss of each repetition's frame against std's frame of the same
    /// repetition (the two traced one after the other).
    pub loss: [[Spread; 4]; 3],
}

impl ViewRates {
    /// The loss of `tree` against std in %, per column of
    /// [`Rates::as_array`]: the median of the per-repetition losses (with
    /// one repetition, the loss of the medians).
    pub fn loss_pct(&self, tree: TreeKind) -> [f64; 4] {
        self.loss[tree as usize].map(|s| s.median)
    }
}

/// Table 4 of one scene, in seconds.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BuildTimes {
    pub load_s: f64,
    pub std_build_s: f64,
    /// The slim passes of fast and small (after their std trees).
    pub slim_s: [f64; 2],
    /// The std trees of fast and small at their own split price
    /// ([`SlimParams::split_price`]); 0 where a preset slims the std tree.
    pub base_s: [f64; 2],
    /// Serialising std, fast and small to `.kd` bytes (in memory).
    pub write_s: [f64; 3],
}

impl BuildTimes {
    /// The preset's build (its std tree, then the slim pass) over the std
    /// build, for fast (`0`) or small (`1`).
    pub fn slim_ratio(&self, i: usize) -> f64 {
        let base = if self.base_s[i] > 0.0 {
            self.base_s[i]
        } else {
            self.std_build_s
        };
        ratio(base + self.slim_s[i], self.std_build_s)
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
    /// The spread of the per-repetition losses of every view, %.
    pub loss_spread: Spread,
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

    /// The paper's std: the std tree in the paper's layout (Wald 2004: 8
    /// bytes per node, empty leaves included, and 4 per leaf index,
    /// `8·nodes + 4·refs`; [`slimkd::stats::bytes::paper_layout_bytes`]).
    pub fn classic_std_bytes(&self) -> u64 {
        slimkd::stats::bytes::paper_layout_bytes_of(&self.table3a[0].figures)
    }

    /// Size reduction of `tree` against std in the same format, %.
    pub fn reduction_pct(&self, tree: TreeKind) -> f64 {
        percent_below(
            self.table3a[tree as usize].figures.tree_bytes() as f64,
            self.std_tree_bytes() as f64,
        )
    }

    /// Size reduction of `tree` against the paper's std
    /// ([`SceneReport::classic_std_bytes`]), %.
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

pub use crate::lab::figures::median;

const MIB: f64 = (1u64 << 20) as f64;

/// The figures' file names end in these, after the Markdown file's stem
/// (`r.md`: `r.figure5.svg`, `r.figure6.svg`), so that reports in one
/// directory keep their own.
pub const FIGURE5_FILE: &str = "figure5.svg";
pub const FIGURE6_FILE: &str = "figure6.svg";

/// The files a report written to a Markdown path consists of.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReportPaths {
    pub markdown: PathBuf,
    /// Same stem, `.json`.
    pub json: PathBuf,
    /// `STEM.figure5.svg` beside the Markdown (written with the sweep).
    pub figure5: PathBuf,
    /// `STEM.figure6.svg` beside the Markdown.
    pub figure6: PathBuf,
}

impl ReportPaths {
    /// The paths for the Markdown file `md_path`.
    ///
    /// # Errors
    ///
    /// [`std::io::ErrorKind::InvalidInput`], naming the path, if it has no
    /// file name or ends in `.json` (the JSON would overwrite it). Whether
    /// the directory exists is not checked.
    pub fn for_markdown(md_path: &Path) -> std::io::Result<ReportPaths> {
        let invalid = |m: String| std::io::Error::new(std::io::ErrorKind::InvalidInput, m);
        let Some(stem) = md_path.file_stem() else {
            return Err(invalid(format!("{}: not a file name", md_path.display())));
        };
        let json = md_path.with_extension("json");
        if json == md_path {
            return Err(invalid(format!(
                "{}: the Markdown file must not end in .json (the JSON goes next to it)",
                md_path.display()
            )));
        }
        let figure = |suffix: &str| {
            let mut name = stem.to_os_string();
            name.push(".");
            name.push(suffix);
            md_path.with_file_name(name)
        };
        Ok(ReportPaths {
            markdown: md_path.to_path_buf(),
            json,
            figure5: figure(FIGURE5_FILE),
            figure6: figure(FIGURE6_FILE),
        })
    }

    /// The file names of the two figures, as the Markdown links them.
    pub fn figure_names(&self) -> (String, String) {
        let name = |p: &Path| {
            p.file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned()
        };
        (name(&self.figure5), name(&self.figure6))
    }
}

impl Report {
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
                        label: format!(
                            "{}/{}{}",
                            p.tau_occu,
                            p.tau_freq,
                            if p.loss_spread.includes_zero() {
                                " ≈"
                            } else {
                                ""
                            }
                        ),
                        y_range: Some((p.loss_spread.q1, p.loss_spread.q3)),
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
    /// `.json`), and the figures (`STEM.figure5.svg` with the sweep,
    /// `STEM.figure6.svg`, see [`ReportPaths`]) into the same directory;
    /// returns the paths written. Each file is written to a temporary file
    /// and renamed into place, and every temporary file is written before
    /// the first rename, so a failure (e.g. a missing directory) leaves no
    /// file behind.
    pub fn write(&self, md_path: &Path) -> std::io::Result<Vec<PathBuf>> {
        let paths = ReportPaths::for_markdown(md_path)?;
        let mut json_text =
            serde_json::to_string_pretty(&self.json()).map_err(std::io::Error::other)?;
        json_text.push('\n');
        let mut files = vec![
            (paths.markdown.clone(), self.markdown_for(md_path)),
            (paths.json.clone(), json_text),
        ];
        if self.sweep {
            let svg = self.figure5_svg().map_err(std::io::Error::other)?;
            files.push((paths.figure5.clone(), svg));
        }
        let svg = self.figure6_svg().map_err(std::io::Error::other)?;
        files.push((paths.figure6.clone(), svg));
        write_all_atomically(&files)?;
        Ok(files.into_iter().map(|(p, _)| p).collect())
    }
}

/// Adds the path to an I/O error's message.
fn with_path(path: &Path, e: std::io::Error) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("{}: {e}", path.display()))
}

/// Writes every file through a temporary file ([`slimkd::fsio::Staged`]);
/// renames only once all of them are written and synced. On failure, the
/// temporary files not yet renamed go.
fn write_all_atomically(files: &[(PathBuf, String)]) -> std::io::Result<()> {
    let mut staged = Vec::with_capacity(files.len());
    for (path, contents) in files {
        let mut f = slimkd::fsio::Staged::create(path).map_err(|e| with_path(path, e))?;
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

#[cfg(test)]
mod bunny_tests;
