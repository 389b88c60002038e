//! The command line's `clap` types and their value parsers.

use clap::{Parser, Subcommand, ValueEnum};
use slimkd::build::level;
use slimkd::format::Preset;
use slimkd::render::{self};
use slimkd::slim::{HoistRule, Rebuild, SlimParams};
use std::path::{Path, PathBuf};

use crate::CmdResult;
use crate::lab::calibrate::DEFAULT_KT_VALUES;

#[derive(Parser)]
#[command(
    name = "slimkd",
    version,
    about = "Build, store and trace SAH kd-trees for large triangle scenes.",
    long_about = "Build, store and trace SAH kd-trees for large triangle scenes.\n\n\
        Without a command (the main job), builds the std tree and the small and fast slim trees \
        of the embedded default scene, writes each as a .kd file into a temporary directory, \
        maps them back, traces the same view from each with packets and prints one table \
        (tree bytes, bytes and references per triangle, nodes, Mrays/s, and whether the hits \
        are the std tree's); then writes slimkd.png into the current directory. -v adds phase \
        times and memory.\n\n\
        SCENE is an OBJ file, a scene cache (.kds, made by `slimkd convert`), or `default` \
        for the embedded scene.\n\n\
        Without --view or camera flags, `render` uses the default camera: it looks at the centre \
        C of the scene's box from C + normalize(0.6, 0.4, 1.0) * 1.2 * (the box's diagonal), \
        up +y, 60 degrees vertical field of view.",
    after_help = EXAMPLES
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) command: Option<Command>,
    #[command(flatten)]
    pub(crate) out: OutputFlags,
    /// Read `.kd` files and `.kds` scene caches into memory instead of
    /// mapping them: for files
    /// another process may rewrite or truncate in place while slimkd reads
    /// them (a mapped file truncated under the reader ends it by SIGBUS).
    #[arg(long, global = true, display_order = 903)]
    pub(crate) no_mmap: bool,
}

/// What a command prints: the flags every command takes.
#[derive(clap::Args, Clone, Copy, Debug, Default)]
pub(crate) struct OutputFlags {
    /// Print errors only (and, with --json, the JSON object): no summary,
    /// no progress bars.
    #[arg(
        short,
        long,
        global = true,
        conflicts_with = "verbose",
        display_order = 900
    )]
    pub(crate) quiet: bool,
    /// Print more: the build's phase times, processor time and memory, the
    /// slim passes' phases, the camera of a render, the sections of a
    /// verified file, the Markdown of a report.
    #[arg(short, long, global = true, display_order = 901)]
    pub(crate) verbose: bool,
    /// Print one JSON object instead of text (`"schema": 1`; every key is
    /// listed in docs/json-schema.md).
    #[arg(long, global = true, display_order = 902)]
    pub(crate) json: bool,
}

impl OutputFlags {
    /// Whether progress bars are off: with -q, and with --json (whose
    /// output is for programs).
    pub(crate) fn bars_off(self) -> bool {
        self.quiet || self.json
    }
}

/// The examples at the end of `--help`.
const EXAMPLES: &str = "Examples:
  slimkd                                     the main job: std, small and fast trees of the embedded scene
  slimkd build scene.obj -o scene.kd --reorder --preset small
  slimkd render scene.kd --views views.txt --view 1 -o frame.png
  slimkd render default --eye 0,2,5 --at 0,0,0 --size 640x480 -o frame.exr
  slimkd info scene.kd --json
  slimkd verify scene.kd
  slimkd convert huge.obj -o huge.kds        parse once; later commands read huge.kds
  slimkd report a.obj b.kds --views views.txt --reps 9 -o report.md
  slimkd trace scene.kd rays.bin --occluded";

/// The examples of the commands of a build in cells.
const CELLS_EXAMPLES: &str = "Examples:
  slimkd build scene.obj --cells 64 -o scene.kd          plan, build the cells, stitch (resumes)
  slimkd build scene.obj --cells 64 --cells-dir w --plan-only --json
  slimkd build-cell w/cell-00012.kdcell                  writes w/cell-00012.kdpart
  slimkd stitch scene.obj --cells-dir w -o scene.kd
  python3 tools/ray_cells.py scene.obj --cells 64 --cells-dir /shared/w -o scene.kd";

/// The camera `render` uses without a view or camera flags.
const DEFAULT_CAMERA: &str = "Without --view and camera flags the camera is the default one: it \
    looks at the centre C of the scene's box from C + normalize(0.6, 0.4, 1.0) * 1.2 * (the box's \
    diagonal), up +y, fov 60 degrees. Camera flags override the view's (or the default's) values.";

#[derive(Subcommand)]
pub(crate) enum Command {
    /// Build the standard SAH kd-tree of a scene; print its figures and
    /// optionally write it as a .kd file.
    #[command(after_help = EXAMPLES)]
    Build {
        /// OBJ file, scene cache (.kds, see `convert`), or `default`.
        scene: PathBuf,
        /// Write the tree and its geometry to this .kd file (atomically).
        #[arg(short = 'o', long)]
        output: Option<PathBuf>,
        /// Renumber triangles in Morton order before writing, so that most
        /// leaves fit 2-byte mode.
        #[arg(long)]
        reorder: bool,
        #[command(flatten)]
        cells: CellsArgs,
        #[command(flatten)]
        build: Box<BuildArgs>,
    },
    /// Build one cell of a build in cells (a cell file that `build
    /// --cells` wrote) into its part file: the cell's subtree, exactly as
    /// the whole build makes it. The cell file is all it reads.
    #[command(after_help = CELLS_EXAMPLES)]
    BuildCell {
        /// A cell file (`cell-NNNNN.kdcell` in a work directory).
        cell: PathBuf,
        /// The part file to write (atomically); default: the cell file's
        /// name with `.kdpart`, beside it, where `build --cells` and
        /// `stitch` look for it.
        #[arg(short = 'o', long)]
        output: Option<PathBuf>,
        /// Worker threads (default, or 0: all cores).
        #[arg(short = 'j', long)]
        threads: Option<usize>,
    },
    /// Stitch the top tree and the parts of a build in cells into one .kd
    /// file, byte for byte the file `build -o` writes.
    #[command(after_help = CELLS_EXAMPLES)]
    Stitch {
        /// The scene the plan was made of (its geometry hash is checked).
        scene: PathBuf,
        /// The work directory (plan, cell and part files).
        #[arg(long)]
        cells_dir: PathBuf,
        /// The .kd file to write (atomically).
        #[arg(short = 'o', long)]
        output: PathBuf,
        /// Renumber triangles in Morton order before writing (as `build
        /// --reorder`).
        #[arg(long)]
        reorder: bool,
        /// Worker threads (default, or 0: all cores).
        #[arg(short = 'j', long)]
        threads: Option<usize>,
    },
    /// Render a scene (built on the fly) or a .kd file.
    #[command(after_help = EXAMPLES, long_about = format!(
        "Render a scene (built on the fly) or a .kd file.\n\n{DEFAULT_CAMERA}"
    ))]
    Render(Box<RenderArgs>),
    /// Print the header and figures of a .kd file.
    Info {
        /// A .kd file written by `slimkd build -o`.
        file: PathBuf,
    },
    /// Check a .kd file completely, checksums included; exit 0 if valid.
    Verify {
        /// A .kd file written by `slimkd build -o`.
        file: PathBuf,
    },
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
    /// Trace a ray file (closest hit or any hit) through a .kd file and
    /// print Mrays/s, hits and a checksum comparable with the Embree peer
    /// program's `--rays` mode.
    Trace(Box<TraceArgs>),
    /// Measure the cost of a traversal step and of a ray–triangle test
    /// (trees built at several K_T, primary and AO rays, single and
    /// packets) and fit time = a·steps + b·tests + c per ray; prints a, b,
    /// c (ns), the implied K_T and R², per scene and pooled.
    Calibrate(Box<CalibrateArgs>),
    /// Draw the trade-off front of tree bytes against trace time: trees
    /// over K_T and the hoisting thresholds (std, fast and small among
    /// them), primary packets timed in rounds; writes sweep.md, sweep.json
    /// and a chart per scene (SCENE.sweep.svg) with the Pareto front.
    Sweep(Box<SweepArgs>),
}

/// The scenes and frames of a timed command (`report`, `sweep`): the
/// help text is the report's; `sweep` words some of it its own way.
#[derive(clap::Args)]
pub(crate) struct TimedScenesArgs {
    /// OBJ files or scene caches (.kds), or `default`.
    #[arg(required = true)]
    pub(crate) scenes: Vec<PathBuf>,
    /// Views file; each scene is matched by its name, the file's stem.
    /// Without it the embedded views are used. A scene without views is
    /// timed from the default camera (with a warning).
    #[arg(long)]
    pub(crate) views: Option<PathBuf>,
    /// Image size WxH of the timed frames.
    #[arg(long, value_parser = parse_size, default_value = "512x512")]
    pub(crate) size: (u32, u32),
    /// Timed frames per measurement, after a warm-up (at least 1): the
    /// median is reported with the interquartile range of the losses;
    /// fewer than 5 leave the range meaningless.
    #[arg(long, default_value_t = 9, value_parser = parse_positive)]
    pub(crate) reps: usize,
}

#[derive(clap::Args)]
pub(crate) struct ReportArgs {
    #[command(flatten)]
    pub(crate) timed: TimedScenesArgs,
    /// Threads for the "all threads" columns (at least 1; default: all
    /// cores).
    #[arg(long, value_parser = parse_positive)]
    pub(crate) threads: Option<usize>,
    /// Also run the τ_occu × τ_freq threshold sweep (Figure 5).
    #[arg(long)]
    pub(crate) sweep: bool,
    /// The hoist rule of the fast, small and sweep trees (see `build
    /// --hoist-rule`; the report writes reordered files).
    #[arg(long, value_enum, default_value_t = HoistRuleArg::Bytes)]
    pub(crate) hoist_rule: HoistRuleArg,
    /// The Markdown report; report.json and the SVG figures go beside it.
    #[arg(short = 'o', long, default_value = "report.md")]
    pub(crate) output: PathBuf,
}

/// `build --cells`: a build in cells (see docs/cells.md).
#[derive(clap::Args, Clone)]
#[command(next_help_heading = "Build in cells (docs/cells.md)")]
pub(crate) struct CellsArgs {
    /// Cut the top of the tree into at most K cells (of about N/K
    /// references each), write each cell's references to a cell file,
    /// build each cell's subtree (as `build-cell` does) and stitch them:
    /// the same .kd file as without --cells, byte for byte. Finished parts
    /// in the work directory are kept (checked against their cell's
    /// checksum), so an interrupted build resumes. The std preset only.
    #[arg(long, value_name = "K", value_parser = parse_positive)]
    pub(crate) cells: Option<usize>,
    /// The work directory of a build in cells (made if missing; kept
    /// afterwards, remove it when done). Default: OUTPUT.cells beside the
    /// .kd file.
    #[arg(long, value_name = "DIR", requires = "cells")]
    pub(crate) cells_dir: Option<PathBuf>,
    /// Write the plan and the cell files and stop: the cells are built
    /// elsewhere (`build-cell`, tools/ray_cells.py) and joined by
    /// `stitch`. With --json, the cells and which are built already.
    #[arg(long, requires = "cells")]
    pub(crate) plan_only: bool,
}

#[derive(clap::Args, Clone)]
pub(crate) struct BuildArgs {
    /// Tree preset: `std` (no hoisting), `fast` (split price 1.5, τ_occu
    /// 0.1, τ_freq 0.05, max_t2rn 16, coarsen 1.5, cost ratio 0.01),
    /// `small` (split price 2, the same thresholds, coarsen 2, cost ratio
    /// 0.05), with the hoist rule `bytes`; with `--hoist-rule paper`, the
    /// paper's settings (Choi et al. 2013): fast τ_occu 0.9, τ_freq 0.7,
    /// small 0.5, 0.4, both max_t2rn 4, coarsen 1, no cost ratio, std's
    /// split price. --split-price replaces a preset's. The hoisting flags
    /// (--tau-occu, --tau-freq, --max-t2rn, --coarsen, --cost-ratio,
    /// --hoist-rule) override what a
    /// slim preset sets; with `std` (the default) they need both
    /// --tau-occu and --tau-freq (then the rest is small's unless given,
    /// and the file records the preset as custom).
    #[arg(long, value_enum, default_value_t = PresetArg::Std)]
    pub(crate) preset: PresetArg,
    /// When a picked triangle is hoisted. `bytes` (the presets' rule, a
    /// deviation from the paper): only if the rebuilt subtree plus the
    /// 8-byte T-reference is smaller than the subtree it replaces, counted
    /// as the file stores it (2-byte leaves with the file's triangle
    /// numbering, so --reorder matters); otherwise the node keeps its
    /// subtree. `paper`: always (Algorithm 1 as published). With `paper`,
    /// the file records the preset as custom. With `--preset std` it needs
    /// --tau-occu and --tau-freq.
    #[arg(long, value_enum, default_value_t = HoistRuleArg::Bytes)]
    pub(crate) hoist_rule: HoistRuleArg,
    /// Occupancy threshold in [0, 1] (overrides the preset's: 0.1, or with
    /// `--hoist-rule paper` fast 0.9, small 0.5; with `--preset std` it
    /// needs --tau-freq too).
    #[arg(long, value_parser = parse_tau, allow_hyphen_values = true)]
    pub(crate) tau_occu: Option<f64>,
    /// Frequency threshold in [0, 1] (overrides the preset's: 0.05, or
    /// with `--hoist-rule paper` fast 0.7, small 0.4; with `--preset std`
    /// it needs --tau-occu too).
    #[arg(long, value_parser = parse_tau, allow_hyphen_values = true)]
    pub(crate) tau_freq: Option<f64>,
    /// Most hoisted triangles on a root path (overrides the preset's: 16,
    /// or 4 with `--hoist-rule paper`; with `--preset std` it needs
    /// --tau-occu and --tau-freq).
    #[arg(long)]
    pub(crate) max_t2rn: Option<u32>,
    /// Factor on K_T in the SAH of rebuilt subtrees, at least 1
    /// (overrides the preset's: fast 1.5, small 2; 1 is the paper's
    /// rebuild; with `--preset std` it needs --tau-occu and --tau-freq).
    #[arg(long, value_parser = parse_coarsen, allow_hyphen_values = true)]
    pub(crate) coarsen: Option<f64>,
    /// The price rule of the `bytes` hoist rule: a hoist is kept only if
    /// it raises the tree's SAH cost (the std tree's K_T and K_I, a
    /// hoisted triangle one test at its node) by at most this many times
    /// the share of the tree's bytes it saves; a number ≥ 0, or `inf` for
    /// no price (overrides the preset's: fast 0.01, small 0.05; with
    /// `--preset std` it needs --tau-occu and --tau-freq).
    #[arg(long, value_parser = parse_cost_ratio, allow_hyphen_values = true)]
    pub(crate) cost_ratio: Option<f64>,
    /// How a picked subtree is remade without its triangle: `sah` builds
    /// it anew (the paper's rebuild), `prune` keeps its splits, takes the
    /// triangle out of its leaves and joins sibling leaves where the
    /// rebuild's SAH (K_T × coarsen) prefers a leaf (overrides the
    /// preset's: sah; with `--preset std` it needs --tau-occu and
    /// --tau-freq).
    #[arg(long, value_enum)]
    pub(crate) rebuild: Option<RebuildArg>,
    /// Worker threads (default, or 0: all cores).
    #[arg(short = 'j', long)]
    pub(crate) threads: Option<usize>,
    /// Depth limit (default: 8 + 1.3·log2 N).
    #[arg(long)]
    pub(crate) max_depth: Option<u32>,
    /// SAH cost of a traversal step (the file records it).
    #[arg(long, value_parser = parse_cost, default_value_t = slimkd::build::sah::SahParams::default().k_t)]
    pub(crate) kt: f64,
    /// SAH cost of a ray–triangle test (the file records it).
    #[arg(long, value_parser = parse_cost, default_value_t = slimkd::build::sah::SahParams::default().k_i)]
    pub(crate) ki: f64,
    /// SAH price of a split, μ ≥ 0: a split is taken only if the SAH cost
    /// it saves (weighted by its cell's share of the root's surface area)
    /// is at least μ times the bytes it adds per triangle of the scene; 0
    /// takes every split that pays for itself (the file records it;
    /// replaces the split price of `--preset fast`, 1.5, and `small`, 2).
    #[arg(long, value_parser = parse_price, default_value_t = slimkd::build::sah::SahParams::default().split_price)]
    pub(crate) split_price: f64,
    /// SAH factor in (0, 1] on the intersection cost of a split that cuts
    /// off empty space (the file records it).
    #[arg(long, value_parser = parse_lambda, default_value_t = slimkd::build::sah::SahParams::default().lambda_empty)]
    pub(crate) lambda: f64,
    /// Which builder to run (all produce the same tree).
    #[arg(long, value_enum, default_value_t = BuilderArg::Level)]
    pub(crate) builder: BuilderArg,
    /// Level builder: bytes of anonymous memory for the build (e.g. 1G,
    /// 512M): the depth-first finishers' working memory, then the
    /// per-level columns kept in RAM; above it the columns go to mapped
    /// scratch files, and the finished depth-first subtrees go to scratch
    /// files too. The finishers take nodes of up to 65536 references
    /// under a budget (fewer levels through scratch). Default: no limit.
    #[arg(long, value_parser = parse_bytes)]
    pub(crate) mem_budget: Option<u64>,
    /// Level builder: directory for scratch files (default: the system
    /// temporary directory).
    #[arg(long)]
    pub(crate) scratch: Option<PathBuf>,
    /// Level builder: how the events of clipped references join their
    /// child's sorted list (the same tree either way; for measurements).
    #[arg(help_heading = "Measurement knobs (the same tree either way)", long, value_enum, default_value_t = NewEventsArg::Merge)]
    pub(crate) new_events: NewEventsArg,
    /// Level builder: the depth-first finisher sweeps nodes of at most this
    /// many references without event lists (0 to 64; the same tree either
    /// way; for measurements).
    #[arg(help_heading = "Measurement knobs (the same tree either way)", long, default_value_t = level::DEFAULT_TINY_THRESHOLD as u8,
          value_parser = clap::value_parser!(u8).range(0..=64))]
    pub(crate) tiny: u8,
    /// Level builder: nodes of fewer references than this are finished
    /// depth-first (default: 2048, or under `--mem-budget` up to 65536
    /// from the budget, see `LevelOptions::small_threshold_for_budget`;
    /// the same tree either way; for measurements).
    #[arg(help_heading = "Measurement knobs (the same tree either way)", long)]
    pub(crate) small: Option<usize>,
    /// The build flags given on the command line (their long names, e.g.
    /// `--preset`), filled in after parsing; `--threads` is not one.
    #[arg(skip)]
    pub(crate) given: Vec<String>,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum HoistRuleArg {
    /// Keep a hoist only if it makes the tree smaller in bytes.
    Bytes,
    /// Hoist every picked triangle (the paper's Algorithm 1).
    Paper,
}

impl HoistRuleArg {
    /// The rule, counting bytes for a file written with or without
    /// reordering.
    pub(crate) fn rule(self, reordered: bool) -> HoistRule {
        match self {
            HoistRuleArg::Bytes => HoistRule::Bytes { reordered },
            HoistRuleArg::Paper => HoistRule::Paper,
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum RebuildArg {
    /// Build the subtree anew with the SAH builder.
    Sah,
    /// Keep the subtree's splits, joining leaves.
    Prune,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum PresetArg {
    Std,
    Fast,
    Small,
}

impl BuildArgs {
    /// The hoisting flags.
    pub(crate) const HOISTING: [&str; 7] = [
        "--tau-occu",
        "--tau-freq",
        "--max-t2rn",
        "--coarsen",
        "--cost-ratio",
        "--rebuild",
        "--hoist-rule",
    ];

    /// Whether the flag (its long name, `--preset`) was given.
    pub(crate) fn was_given(&self, flag: &str) -> bool {
        self.given.iter().any(|g| g == flag)
    }

    /// The usage rules of the build flags: a hoisting flag with the std
    /// preset needs both thresholds.
    pub(crate) fn check(&self) -> Result<(), Usage> {
        if self.preset == PresetArg::Std {
            let hoisting: Vec<&str> = Self::HOISTING
                .into_iter()
                .filter(|f| self.was_given(f))
                .collect();
            let both = self.tau_occu.is_some() && self.tau_freq.is_some();
            if !hoisting.is_empty() && !both {
                return Err(Usage(format!(
                    "{} with --preset std (the default) needs both --tau-occu and --tau-freq \
                     (or --preset fast|small, whose thresholds they override)",
                    hoisting.join(", ")
                )));
            }
        }
        Ok(())
    }

    /// The slim parameters, if any hoisting is asked for, and the preset
    /// recorded in the file; `reordered`: whether the tree will be written
    /// with reordering (for the byte rule).
    pub(crate) fn slim(&self, reordered: bool) -> (Option<SlimParams>, Preset) {
        let paper = self.hoist_rule == HoistRuleArg::Paper;
        let base = match (self.preset, paper) {
            (PresetArg::Std, _) => None,
            (PresetArg::Fast, false) => Some(SlimParams::FAST),
            (PresetArg::Small, false) => Some(SlimParams::SMALL),
            (PresetArg::Fast, true) => Some(SlimParams::PAPER_FAST),
            (PresetArg::Small, true) => Some(SlimParams::PAPER_SMALL),
        };
        // `check` has made sure that std comes with both thresholds (which
        // replace small's below); only max_t2rn, coarsen, the cost ratio and the rule are
        // taken.
        let custom = self.tau_occu.is_some()
            || self.tau_freq.is_some()
            || self.max_t2rn.is_some()
            || self.coarsen.is_some()
            || self.cost_ratio.is_some()
            || self.rebuild.is_some()
            || paper;
        let mut p = base.unwrap_or(if paper {
            SlimParams::PAPER_SMALL
        } else {
            SlimParams::SMALL
        });
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
        if let Some(v) = self.coarsen {
            p.coarsen = v;
        }
        if let Some(v) = self.cost_ratio {
            p.cost_ratio = v;
        }
        match self.rebuild {
            Some(RebuildArg::Sah) => p.rebuild = Rebuild::Sah,
            Some(RebuildArg::Prune) => p.rebuild = Rebuild::Prune,
            None => {}
        }
        // A given --split-price (in the build configuration) replaces the
        // preset's; hoisting on the std preset keeps std's.
        if base.is_none() || self.was_given("--split-price") {
            p.split_price = None;
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
pub(crate) enum BuilderArg {
    /// Breadth-first, parallel (Wu, Zhao & Liu 2011).
    Level,
    /// Sequential O(N log N) sweep (Wald & Havran 2006).
    Sweep,
    /// The O(N²)-per-node reference.
    Naive,
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum NewEventsArg {
    /// Sort them and merge them in from the back.
    Merge,
    /// Wu et al.'s bucket sort, the inherited events as buckets.
    Bucket,
}

/// Parses a byte count: a number with an optional K, M, G or T suffix
/// (powers of 1024).
pub(crate) fn parse_bytes(s: &str) -> Result<u64, String> {
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
    let bytes = n * (1u64 << shift) as f64;
    // `u64::MAX as f64` is 2^64: every smaller value fits; a larger one
    // would saturate, and a size is never taken to mean "no limit".
    if bytes >= u64::MAX as f64 {
        return Err(format!("size `{s}` is too large (2^64 bytes or more)"));
    }
    Ok(bytes as u64)
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum ShadingArg {
    EyeLight,
    Normals,
    Ao,
}

/// How `render --shading ao` traces its shadow and AO rays.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum SecondaryArg {
    /// One ray at a time from the root.
    Single,
    /// 16 rays at a time (packets with `--mode packet`).
    Packet,
    /// One ray at a time from the context of its hit point.
    FromHit,
    /// One ray at a time leaf to leaf by ropes from the cell of its hit
    /// point (std trees; primary rays in packets).
    Ropes,
    /// 16 rays at a time over a hierarchy of eight boxes a node around the
    /// tree's leaves (primary rays in packets).
    Wide,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum ModeArg {
    /// Scalar traversal, one ray at a time.
    Single,
    /// 4×4 SIMD ray packets.
    Packet,
    /// Brute force: every ray against every triangle (reference).
    Brute,
}

impl ModeArg {
    pub(crate) fn name(self) -> &'static str {
        match self {
            ModeArg::Single => "single",
            ModeArg::Packet => "packet",
            ModeArg::Brute => "brute",
        }
    }
}

#[derive(clap::Args)]
pub(crate) struct RenderArgs {
    /// OBJ file, scene cache (.kds), `default`, or a .kd file written by
    /// `slimkd build -o`.
    pub(crate) scene: PathBuf,
    /// Output image (.png, or .exr with a depth channel).
    #[arg(short = 'o', long)]
    pub(crate) output: Option<PathBuf>,
    /// Image size WxH.
    #[arg(long, value_parser = parse_size, default_value = "1024x1024")]
    pub(crate) size: (u32, u32),
    /// Views file (`SCENE VIEW_ID eye=… at=… up=… fov=…`), with --view;
    /// the embedded scene's views are used when omitted.
    #[arg(long, requires = "view")]
    pub(crate) views: Option<PathBuf>,
    /// View id in the views file, of the scene whose name a .kd file
    /// records, else of the file's stem (or the longest scene name either
    /// starts with, followed by `.`, `_` or `-`).
    #[arg(long)]
    pub(crate) view: Option<String>,
    /// Camera position x,y,z.
    #[arg(long, value_parser = parse_dvec3, allow_hyphen_values = true)]
    pub(crate) eye: Option<glam::DVec3>,
    /// Point looked at x,y,z.
    #[arg(long, value_parser = parse_dvec3, allow_hyphen_values = true)]
    pub(crate) at: Option<glam::DVec3>,
    /// Up vector x,y,z.
    #[arg(long, value_parser = parse_dvec3, allow_hyphen_values = true)]
    pub(crate) up: Option<glam::DVec3>,
    /// Vertical field of view in degrees, in (0, 180).
    #[arg(long, value_parser = parse_fov)]
    pub(crate) fov: Option<f64>,
    /// Image colours: `eye-light` (grey, lit from the eye by the cosine
    /// to the surface) or `normals` (the geometric normal facing the eye,
    /// mapped from [-1, 1] to [0, 1] as RGB) or `ao` (a renderer's
    /// frame: per hit a shadow ray to a point light near the eye and
    /// --spp ambient-occlusion rays of 5 % of the scene's diagonal, the
    /// rays of the Embree peer's `--make-rays`; the frame time is printed
    /// by ray kind).
    #[arg(long, value_enum, default_value_t = ShadingArg::EyeLight)]
    pub(crate) shading: ShadingArg,
    /// AO rays per hit pixel with `--shading ao` (default 4).
    #[arg(long)]
    pub(crate) spp: Option<u32>,
    /// How `--shading ao` traces its shadow and AO rays: `packet` (16 at
    /// a time, in packets with `--mode packet`), `single`
    /// (one at a time from the root), `from-hit` (one at a time from the
    /// context of the hit point, one per pixel) or `ropes` (one at a time
    /// leaf to leaf from the cell of the hit point, by ropes built after
    /// opening and reported apart; std trees, `--mode packet`) or `wide`
    /// (16 at a time over boxes around the tree's leaves, eight a node,
    /// built after opening and reported apart; `--mode packet`). Default:
    /// `wide` with `--mode packet` for scenes of up to 8 Mi triangles
    /// (the boxes took up to 146 bytes a triangle), else `packet`.
    #[arg(long, value_enum)]
    pub(crate) secondary: Option<SecondaryArg>,
    /// Traversal mode: 4×4 packets (the default, as the main job), single
    /// rays, or brute force (the reference).
    #[arg(long, value_enum, default_value_t = ModeArg::Packet)]
    pub(crate) mode: ModeArg,
    /// Frames to trace (at least 1); Mrays/s is the median.
    #[arg(long, default_value_t = 1, value_parser = parse_positive)]
    pub(crate) reps: usize,
    /// Write W·H little-endian f32 hit distances (+inf for a miss).
    #[arg(long)]
    pub(crate) dump_t: Option<PathBuf>,
    /// With --shading ao: write the frame's rays, each kind in the order
    /// the frame traces it (16 consecutive rays are one of its packets),
    /// to PREFIX-primary.rays, PREFIX-shadow.rays and PREFIX-ao.rays, the
    /// ray files of the peer program's `--make-rays PREFIX`; all three or
    /// none are written.
    #[arg(long, value_name = "PREFIX")]
    pub(crate) dump_rays: Option<PathBuf>,
    #[command(
        flatten,
        next_help_heading = "Build (of a scene; a .kd file is built already)"
    )]
    pub(crate) build: BuildArgs,
}

#[derive(clap::Args)]
pub struct TraceArgs {
    /// A .kd file written by `slimkd build -o`.
    pub file: PathBuf,
    /// A ray file: 32-byte records `ox oy oz tmin dx dy dz tmax`, f32
    /// little-endian, no header.
    pub rays: PathBuf,
    /// Any-hit queries: 1 when something lies in (tmin, tmax), else 0.
    #[arg(long)]
    pub occluded: bool,
    /// Traversal: `single` ray at a time, `packet`s of 16 consecutive
    /// rays (any-hit packets test first the triangles that blocked the
    /// last packet their thread traced), packets of 16 rays of one octant
    /// and longest axis (`sorted`: each run of 1,024 consecutive rays
    /// ordered by the signs and longest axis of its directions, or by
    /// direction cell where the run's origins lie
    /// close together against its rays' length, stably and timed, as
    /// `render` orders its AO rays; a run whose packets mostly keep one
    /// octant, as shadow rays toward one light do, stays in its order), or single rays walked
    /// `from-hit`: from the context of their origin (located once for a
    /// run of rays with the same origin, as the shadow and AO rays of one
    /// hit point are; the location is timed), single rays walked leaf to leaf by `ropes` from the cell of
    /// their origin (located as from-hit's; the ropes are built after
    /// opening, untimed, and reported apart; std trees only), or any-hit
    /// queries as a `stream` of 256 rays at a time, or in `lanes`: 16 rays
    /// at a time, each on its own path, refilled from batches of 2048
    /// (both --occluded only), or single rays over `wide` boxes (the
    /// tree's leaves in a hierarchy of eight boxes a node, built after
    /// opening, untimed, and reported apart), or packets of 16
    /// consecutive rays over those boxes (`wide-packet`; any-hit packets
    /// test first the triangles that blocked the last packet).
    #[arg(long, value_enum, default_value = "packet")]
    pub mode: TraceMode,
    /// Worker threads (default: all cores).
    #[arg(short = 'j', long)]
    pub threads: Option<usize>,
    /// Timed repetitions after one untimed warm-up; the median is reported.
    #[arg(long, default_value_t = 5)]
    pub reps: usize,
    /// Also count the traversal's work per ray (nodes, leaves, triangle
    /// tests), in an untimed pass of a counting traverser.
    #[arg(long)]
    pub stats: bool,
    /// Write one little-endian f32 result per ray to this file.
    #[arg(long)]
    pub dump: Option<PathBuf>,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TraceMode {
    Single,
    Packet,
    Sorted,
    FromHit,
    Ropes,
    Stream,
    Lanes,
    Wide,
    WidePacket,
}

#[derive(clap::Args)]
pub(crate) struct CalibrateArgs {
    /// OBJ files or scene caches (.kds), or `default` (the embedded scene,
    /// also when none is given).
    pub(crate) scenes: Vec<PathBuf>,
    /// Views file; each scene is matched by its name, the file's stem
    /// (views 1–3). Without it the embedded views are used; a scene
    /// without views is traced from the default camera.
    #[arg(long)]
    pub(crate) views: Option<PathBuf>,
    /// Primary rays per scene, split over its views; about as many
    /// ambient-occlusion rays go with them.
    #[arg(long, default_value_t = 1 << 16, value_parser = parse_positive)]
    pub(crate) rays_per_scene: usize,
    /// Timed repetitions after one warm-up (at least 1); the median is
    /// fitted.
    #[arg(long, default_value_t = 7, value_parser = parse_positive)]
    pub(crate) reps: usize,
    /// The K_T values the trees are built with, comma-separated (at least
    /// two distinct).
    #[arg(long, value_delimiter = ',', value_parser = parse_cost,
          default_values_t = DEFAULT_KT_VALUES.to_vec())]
    pub(crate) kt: Vec<f64>,
    /// K_I of every tree; the implied K_T is scaled to it.
    #[arg(long, value_parser = parse_cost, default_value_t = slimkd::build::sah::SahParams::default().k_i)]
    pub(crate) ki: f64,
    /// Worker threads (default: all cores).
    #[arg(short = 'j', long, value_parser = parse_positive)]
    pub(crate) threads: Option<usize>,
}

#[derive(clap::Args)]
#[command(
    mut_arg("scenes", |a| a.help("OBJ files or scene caches (.kds), or `default` (the embedded scene)")),
    mut_arg("views", |a| a.help("Views file; each scene is matched by its name, the file's stem (views 1–3). Without it the embedded views are used; a scene without views is traced from the default camera")),
    mut_arg("size", |a| a.help("Frame size WxH of every view")),
    mut_arg("reps", |a| a.help("Timed rounds after a warm-up (at least 1); min, median and max are kept")),
)]
pub(crate) struct SweepArgs {
    #[command(flatten)]
    pub(crate) timed: TimedScenesArgs,
    /// Threads of the builds and the tracing (at least 1). The default, 2,
    /// keeps the figures comparable across machines and with the
    /// measurements in docs/perf-notes.md.
    #[arg(short = 'j', long, default_value_t = 2, value_parser = parse_positive)]
    pub(crate) threads: usize,
    /// The directory sweep.md, sweep.json and the charts (SCENE.sweep.svg)
    /// are written into; it must exist.
    #[arg(short = 'o', long, default_value = ".")]
    pub(crate) output: PathBuf,
}

/// A usage error: the command line asks for something impossible or
/// contradictory; `main` exits with 2 for it.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub(crate) struct Usage(pub(crate) String);

/// Checks, before any work, that an output file can go where it is asked
/// to: its directory exists (an error naming the path, exit 1).
pub(crate) fn check_output_dir(path: &Path) -> CmdResult<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    match std::fs::metadata(dir) {
        Ok(m) if m.is_dir() => Ok(()),
        Ok(_) => Err(format!(
            "cannot write {}: {} is not a directory",
            path.display(),
            dir.display()
        )
        .into()),
        Err(e) => Err(format!("cannot write {}: its directory: {e}", path.display()).into()),
    }
}

/// Checks an image output's name (a usage error unless `.png` or `.exr`)
/// and its directory.
pub(crate) fn check_image_output(path: &Path) -> CmdResult<()> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    if !matches!(ext.as_deref(), Some("png" | "exr")) {
        return Err(Usage(format!(
            "cannot write {}: unknown image extension (expected .png or .exr)",
            path.display()
        ))
        .into());
    }
    check_output_dir(path)
}

/// Parses a hoisting threshold: a number in [0, 1].
pub(crate) fn parse_tau(s: &str) -> Result<f64, String> {
    parse_number(s, "a number in [0, 1]", "is not in [0, 1]", |v| {
        !(0.0..=1.0).contains(&v)
    })
}

/// Parses `s` as an `f64`: "expected EXPECTED, got `s`" if it is no number,
/// "`s` REFUSED" if `rejects` holds for it.
fn parse_number(
    s: &str,
    expected: &str,
    refused: &str,
    rejects: impl Fn(f64) -> bool,
) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("expected {expected}, got `{s}`"))?;
    if rejects(v) {
        return Err(format!("`{s}` {refused}"));
    }
    Ok(v)
}

/// Parses the factor on K_T of rebuilt subtrees: a finite number ≥ 1.
pub(crate) fn parse_coarsen(s: &str) -> Result<f64, String> {
    parse_number(s, "a number ≥ 1", "is not a finite number ≥ 1", |v| {
        !(v.is_finite() && v >= 1.0)
    })
}

/// Parses the price rule's ratio: a number ≥ 0, or `inf`.
pub(crate) fn parse_cost_ratio(s: &str) -> Result<f64, String> {
    parse_number(
        s,
        "a number ≥ 0 or `inf`",
        "is not a number ≥ 0 or `inf`",
        |v| v.is_nan() || v < 0.0,
    )
}

/// Parses an SAH cost constant: a finite number above 0.
pub(crate) fn parse_cost(s: &str) -> Result<f64, String> {
    parse_number(
        s,
        "a positive number",
        "is not a finite number above 0",
        |v| !(v.is_finite() && v > 0.0),
    )
}

/// Parses the split price μ, a finite number ≥ 0.
pub(crate) fn parse_price(s: &str) -> Result<f64, String> {
    parse_number(s, "a number ≥ 0", "is not a finite number ≥ 0", |v| {
        !(v.is_finite() && v >= 0.0)
    })
}

/// Parses the empty-space factor λ, in (0, 1].
pub(crate) fn parse_lambda(s: &str) -> Result<f64, String> {
    parse_number(s, "a number in (0, 1]", "is not in (0, 1]", |v| {
        !(v > 0.0 && v <= 1.0)
    })
}

/// Parses a field of view in degrees, in (0, 180).
pub(crate) fn parse_fov(s: &str) -> Result<f64, String> {
    parse_number(s, "degrees in (0, 180)", "is not in (0, 180)", |v| {
        !(v > 0.0 && v < 180.0)
    })
}

/// Parses a count of at least 1.
pub(crate) fn parse_positive(s: &str) -> Result<usize, String> {
    match s.trim().parse::<usize>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!("expected a whole number of at least 1, got `{s}`")),
    }
}

pub(crate) fn parse_dvec3(s: &str) -> Result<glam::DVec3, String> {
    render::parse_vec3(s).ok_or_else(|| format!("expected x,y,z with finite numbers, got `{s}`"))
}

pub(crate) fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or("expected WxH")?;
    let w: u32 = w.parse().map_err(|_| format!("bad width in `{s}`"))?;
    let h: u32 = h.parse().map_err(|_| format!("bad height in `{s}`"))?;
    if w == 0 || h == 0 || u64::from(w) * u64::from(h) > 1 << 28 {
        return Err(format!("size `{s}` out of range"));
    }
    Ok((w, h))
}
