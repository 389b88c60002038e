//! The trade-off front of tree bytes against trace time (`slimkd sweep`).
//!
//! [`run_front`] builds, for every scene, a small grid of settings in
//! families ([`default_grid`]): the std tree at several `K_T` (one `K_I`),
//! and slim trees over the hoisting thresholds and the rebuilds' `coarsen`
//! at the default constants, the `fast` and `small` presets among them
//! exactly. Each tree is written as `.kd` bytes in memory (Morton
//! reordering on, as `build --reorder` writes it) and opened again; its
//! `tree_bytes` are the file's. Then the scene's views (1–3, or the default
//! camera) are traced as primary packets on the given thread count, `reps`
//! rounds after a warm-up, every tree once per round and each round
//! starting with the next tree, so that drift in the machine's speed
//! touches all alike; a point's trace time is the whole round's frames
//! (every view) of its tree, and min, median and max over the rounds are
//! kept, since on a shared machine the spread is as large as the effect.
//! Every frame's hits must equal the first tree's ([`ReportError::Mismatch`]
//! otherwise). A point is on the Pareto front if no other point has at most
//! its bytes and at most its median time, one of them strictly less.
//!
//! The result, a [`FrontReport`], renders as Markdown, JSON (documented in
//! `docs/json-schema.md`) and one SVG chart per scene ([`FrontReport::write`]).

use super::run::{cameras_of, check_timing_options};
use super::tables::{check_hits, write_tree};
use super::*;
use crate::lab::figures::JSON_SCHEMA;
use serde::Serialize;
use slimkd::pipeline::Pipeline;
use slimkd::progress::Progress;

/// `K_T` of the std trees of the `K_T` family (with the default `K_I`,
/// 20): from two thirds of the default (15) to three times it. The SAH's
/// decisions depend on the ratio `K_T/K_I` alone (up to rounding), so no
/// family varies `K_I`.
pub const FRONT_KT: [f64; 5] = [10.0, 15.0, 20.0, 30.0, 45.0];
/// `(τ_occu, τ_freq)` of the threshold families, from the least hoisting
/// to the most; `(0.1, 0.05)` is the presets'.
pub const FRONT_TAUS: [(f64, f64); 4] = [(0.5, 0.4), (0.3, 0.2), (0.1, 0.05), (0.05, 0.025)];
/// `μ` of the split-price family (std trees, default `K_T`, `K_I`): from
/// none to eight times the default.
pub const FRONT_SPLIT_PRICE: [f64; 5] = [0.0, 0.25, 0.5, 1.0, 8.0];
/// `coarsen` of the coarsen family, at `small`'s thresholds, price rule
/// and split price (2 is `small`).
pub const FRONT_COARSEN: [f64; 4] = [1.0, 1.5, 2.0, 3.0];

/// One tree of the sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct FrontSetting {
    /// Unique within the grid: `std`, `fast`, `small`, `K_T 30`, `μ 0.25`,
    /// `0.3/0.2 c2`, `0.3/0.2 c1.5 p0.01` (τ_occu/τ_freq, coarsen, the
    /// price rule's ratio).
    pub label: String,
    pub k_t: f64,
    pub k_i: f64,
    /// The SAH's split price `μ`.
    pub split_price: f64,
    /// The slim pass after the std build of `k_t`, `k_i`; `None`: the std
    /// tree itself.
    pub slim: Option<SlimParams>,
    /// The preset this setting is exactly (default constants and the
    /// preset's slim parameters), if any.
    pub preset: Option<TreeKind>,
}

/// A family of settings: one line of the chart, by index into the grid's
/// settings, in the line's order.
#[derive(Clone, Debug, PartialEq)]
pub struct FrontFamily {
    pub name: String,
    pub points: Vec<usize>,
}

/// The settings and their families.
#[derive(Clone, Debug, PartialEq)]
pub struct FrontGrid {
    pub settings: Vec<FrontSetting>,
    pub families: Vec<FrontFamily>,
}

impl FrontGrid {
    /// The index of `setting` (by constants and slim parameters), added if
    /// new.
    fn add(&mut self, setting: FrontSetting) -> usize {
        let same = |s: &FrontSetting| {
            s.k_t == setting.k_t
                && s.k_i == setting.k_i
                && s.split_price == setting.split_price
                && s.slim == setting.slim
        };
        if let Some(i) = self.settings.iter().position(same) {
            return i;
        }
        self.settings.push(setting);
        self.settings.len() - 1
    }
}

/// The default grid: 20 trees in five families.
///
/// - `K_T` (std trees at K_I 20): [`FRONT_KT`]; `K_T 15` is `std`.
/// - the split price (std trees): [`FRONT_SPLIT_PRICE`], through `std`.
/// - hoisting with `fast`'s split price and rebuild (`coarsen`, price
///   rule) and with `small`'s: [`FRONT_TAUS`] with the presets'
///   `max_t2rn` and rule, each line starting at `std` (no hoisting);
///   `0.1/0.05` is `fast` and `small`.
/// - coarsen at `small`'s τ 0.1/0.05, price rule and split price:
///   [`FRONT_COARSEN`], through `small`.
pub fn default_grid() -> FrontGrid {
    let sah = build::sah::SahParams::default();
    let mut grid = FrontGrid {
        settings: Vec::new(),
        families: Vec::new(),
    };
    let std_priced = |k_t: f64, split_price: f64| {
        let default = k_t == sah.k_t && split_price == sah.split_price;
        FrontSetting {
            label: if default {
                "std".into()
            } else if split_price == sah.split_price {
                format!("K_T {k_t}")
            } else {
                format!("μ {split_price}")
            },
            k_t,
            k_i: sah.k_i,
            split_price,
            slim: None,
            preset: default.then_some(TreeKind::Std),
        }
    };
    let std_of = |k_t: f64| std_priced(k_t, sah.split_price);
    let slim_of = |(tau_occu, tau_freq): (f64, f64), base: SlimParams| {
        let params = SlimParams {
            tau_occu,
            tau_freq,
            ..base
        };
        let preset = [TreeKind::Fast, TreeKind::Small]
            .into_iter()
            .find(|k| k.params(SlimParams::FAST.rule) == Some(params));
        let mut label = format!("{tau_occu}/{tau_freq}");
        if params.coarsen != 1.0 {
            label += &format!(" c{}", params.coarsen);
        }
        if params.cost_ratio.is_finite() {
            label += &format!(" p{}", params.cost_ratio);
        }
        let split_price = params.split_price.unwrap_or(sah.split_price);
        if split_price != sah.split_price {
            label += &format!(" μ{split_price}");
        }
        FrontSetting {
            label: preset.map_or(label, |k| k.name().to_string()),
            k_t: sah.k_t,
            k_i: sah.k_i,
            split_price,
            slim: Some(params),
            preset,
        }
    };
    let kt: Vec<usize> = FRONT_KT.iter().map(|&k| grid.add(std_of(k))).collect();
    grid.families.push(FrontFamily {
        name: format!("K_T (std, K_I {})", sah.k_i),
        points: kt,
    });
    let priced: Vec<usize> = FRONT_SPLIT_PRICE
        .iter()
        .map(|&mu| grid.add(std_priced(sah.k_t, mu)))
        .collect();
    grid.families.push(FrontFamily {
        name: format!("split price μ (std, K_T {})", sah.k_t),
        points: priced,
    });
    let std = grid.add(std_of(sah.k_t));
    for (name, base) in [("fast", SlimParams::FAST), ("small", SlimParams::SMALL)] {
        let mut points = vec![std];
        points.extend(FRONT_TAUS.iter().map(|&t| grid.add(slim_of(t, base))));
        grid.families.push(FrontFamily {
            name: format!("τ_occu/τ_freq, rebuilt as {name}"),
            points,
        });
    }
    let taus = (SlimParams::FAST.tau_occu, SlimParams::FAST.tau_freq);
    let points = FRONT_COARSEN
        .iter()
        .map(|&coarsen| {
            grid.add(slim_of(
                taus,
                SlimParams {
                    coarsen,
                    ..SlimParams::SMALL
                },
            ))
        })
        .collect();
    grid.families.push(FrontFamily {
        name: format!("coarsen, τ {}/{}, as small", taus.0, taus.1),
        points,
    });
    grid
}

/// What to sweep.
#[derive(Clone, Debug)]
pub struct FrontOptions {
    /// `(name, geometry)`: the name (the file's stem) finds the views.
    pub scenes: Vec<(String, TriangleColumns)>,
    pub views: Vec<View>,
    /// Frame size `(width, height)` of every view.
    pub size: (u32, u32),
    /// Timed rounds after the warm-up (at least 1).
    pub reps: usize,
    /// Threads of the builds and the tracing.
    pub threads: usize,
    /// `None`: [`default_grid`].
    pub grid: Option<FrontGrid>,
}

/// One measured point.
#[derive(Clone, Debug, PartialEq)]
pub struct FrontPoint {
    pub setting: FrontSetting,
    /// `tree_bytes` of the written (reordered) file.
    pub tree_bytes: u64,
    pub nodes: u64,
    /// Triangles hoisted (0 for a std tree).
    pub hoisted: usize,
    /// The std build of the setting's constants (seconds).
    pub std_build_s: f64,
    /// The slim pass after it (0 for a std tree).
    pub slim_s: f64,
    /// Milliseconds of a round's frames (every view): spread over the
    /// rounds.
    pub trace_ms: Spread,
    /// Each round's milliseconds, in round order.
    pub trace_ms_reps: Vec<f64>,
    /// On the Pareto front of bytes against median time.
    pub on_front: bool,
}

impl FrontPoint {
    /// The build of the tree: std build plus slim pass.
    pub fn build_s(&self) -> f64 {
        self.std_build_s + self.slim_s
    }
}

/// The sweep of one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneFront {
    pub name: String,
    pub triangles: u64,
    /// The views traced (`default`: the default camera).
    pub views: Vec<String>,
    /// Primary rays of one round per tree.
    pub rays: u64,
    /// Like the grid's settings.
    pub points: Vec<FrontPoint>,
    pub families: Vec<FrontFamily>,
}

impl SceneFront {
    /// The point of a preset.
    pub fn preset(&self, kind: TreeKind) -> Option<&FrontPoint> {
        self.points.iter().find(|p| p.setting.preset == Some(kind))
    }
}

/// The whole sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct FrontReport {
    pub threads: usize,
    pub size: (u32, u32),
    pub reps: usize,
    /// The packet kernel's instruction set.
    pub simd: &'static str,
    pub scenes: Vec<SceneFront>,
}

/// Which of `(bytes, time)` points no other point dominates (at most its
/// bytes and at most its time, one strictly less). Points with a
/// non-finite time are on no front and dominate nothing.
pub fn pareto_front(points: &[(u64, f64)]) -> Vec<bool> {
    points
        .iter()
        .map(|&(b, t)| {
            t.is_finite()
                && !points
                    .iter()
                    .any(|&(b2, t2)| t2.is_finite() && b2 <= b && t2 <= t && (b2 < b || t2 < t))
        })
        .collect()
}

/// Builds, writes and traces every setting of every scene (see the module
/// documentation); `bar` advances one share per step, `log` gets a line
/// per step (a build, a slim pass, a timing round).
///
/// # Errors
///
/// Options out of range, a thread pool that cannot start, a build or a
/// `.kd` write that fails, or frames whose hits differ between trees.
pub fn run_front(
    options: &FrontOptions,
    bar: Option<&Progress>,
    log: &mut dyn FnMut(&str),
) -> Result<FrontReport, ReportError> {
    check_timing_options(options.reps, options.threads, options.size)?;
    let grid = options.grid.clone().unwrap_or_else(default_grid);
    if grid.settings.is_empty() {
        return Err(ReportError::Options("the grid has no settings".into()));
    }
    if let Some(f) = grid
        .families
        .iter()
        .find(|f| f.points.iter().any(|&k| k >= grid.settings.len()))
    {
        return Err(ReportError::Options(format!(
            "family {} names a setting that is not in the grid",
            f.name
        )));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(options.threads)
        .build()
        .map_err(ReportError::ThreadPool)?;
    // Per scene: a step per std build, per slim pass and per round.
    let mut keys: Vec<(f64, f64, f64)> = (grid.settings.iter())
        .map(|s| (s.k_t, s.k_i, s.split_price))
        .collect();
    keys.sort_by(|a, b| {
        (a.0.total_cmp(&b.0))
            .then(a.1.total_cmp(&b.1))
            .then(a.2.total_cmp(&b.2))
    });
    keys.dedup();
    let slims = grid.settings.iter().filter(|s| s.slim.is_some()).count();
    let per_scene = keys.len() + slims + options.reps + 1;
    let total = (options.scenes.len() * per_scene) as u64;
    let mut done = 0u64;
    let mut step = |line: &str| {
        if done > 0 {
            Progress::advance(bar, done - 1, done, total);
        }
        done += 1;
        log(line);
    };
    let mut scenes = Vec::new();
    for (name, scene) in &options.scenes {
        scenes.push(sweep_scene(name, scene, &grid, options, &pool, &mut step)?);
    }
    if done > 0 {
        Progress::advance(bar, done - 1, done, total);
    }
    Ok(FrontReport {
        threads: pool.current_num_threads(),
        size: options.size,
        reps: options.reps,
        simd: SimdLevel::detect().name(),
        scenes,
    })
}

/// One scene of [`run_front`].
fn sweep_scene(
    name: &str,
    scene: &TriangleColumns,
    grid: &FrontGrid,
    options: &FrontOptions,
    pool: &rayon::ThreadPool,
    step: &mut dyn FnMut(&str),
) -> Result<SceneFront, ReportError> {
    // The std trees a setting starts from, by (K_T, K_I, μ), with their
    // build times.
    let mut bases: Vec<((f64, f64, f64), TreeIr, f64)> = Vec::new();
    let mut files = Vec::new();
    let mut points = Vec::new();
    for setting in &grid.settings {
        let mut config = BuildConfig::default();
        config.sah.k_t = setting.k_t;
        config.sah.k_i = setting.k_i;
        config.sah.split_price = setting.split_price;
        let preset = setting.preset.map_or(Preset::Custom, TreeKind::preset);
        let pipeline = Pipeline {
            scene_name: Some(name.to_string()),
            ..Pipeline::new(config)
        }
        .slimmed(setting.slim, preset);
        let key = (setting.k_t, setting.k_i, setting.split_price);
        let base = match bases.iter().position(|(k, _, _)| *k == key) {
            Some(i) => i,
            None => {
                step(&format!(
                    "{name}: building std tree, K_T {} K_I {} μ {}",
                    setting.k_t, setting.k_i, setting.split_price
                ));
                let start = Instant::now();
                let (tree, _) = pool
                    .install(|| pipeline.build(scene, None))
                    .map_err(|source| ReportError::Build {
                        scene: name.to_string(),
                        source,
                    })?;
                bases.push((key, tree, start.elapsed().as_secs_f64()));
                bases.len() - 1
            }
        };
        let (std_tree, std_build_s) = (&bases[base].1, bases[base].2);
        let (slimmed, hoisted, slim_s) = match &setting.slim {
            None => (None, 0, 0.0),
            Some(_) => {
                step(&format!("{name}: slim pass ({})", setting.label));
                let start = Instant::now();
                let slimmed = pool.install(|| pipeline.slim(std_tree, scene, None));
                let (t, r, _) = slimmed.expect("the setting has a slim pass");
                (Some(t), r.hoisted, start.elapsed().as_secs_f64())
            }
        };
        let tree = slimmed.as_ref().unwrap_or(std_tree);
        let written = write_tree(name, &setting.label, tree, scene, &pipeline)?;
        let figures = written.file.figures();
        points.push(FrontPoint {
            setting: setting.clone(),
            tree_bytes: figures.tree_bytes(),
            nodes: figures.nodes(),
            hoisted,
            std_build_s,
            slim_s,
            trace_ms: Spread::default(),
            trace_ms_reps: Vec::new(),
            on_front: false,
        });
        files.push(written.file);
    }
    let bounds = bases[0].1.bounds;
    drop(bases);
    let cams = cameras_of(&options.views, options.size, name, &bounds);
    let tracers: Vec<PacketTracer<'_, KdFile<AlignedBytes>>> =
        files.iter().map(PacketTracer::new).collect();
    let mut reference: Vec<Option<Vec<Hit>>> = vec![None; cams.len()];
    let n = tracers.len();
    for rep in 0..=options.reps {
        step(&format!(
            "{name}: timing round {rep} of {}{}",
            options.reps,
            if rep == 0 { " (warm-up)" } else { "" }
        ));
        for j in 0..n {
            let k = (rep + j) % n;
            let mut ms = 0.0;
            for (c, (id, cam)) in cams.iter().enumerate() {
                let buf = pool.install(|| render::trace_frame(&tracers[k], cam));
                ms += buf.seconds * 1e3;
                match &reference[c] {
                    Some(r) => check_hits(r, &buf, || {
                        format!("{name} view {id}: the {} tree", points[k].setting.label)
                    })?,
                    None => reference[c] = Some(buf.hits),
                }
            }
            if rep > 0 {
                points[k].trace_ms_reps.push(ms);
            }
        }
    }
    for p in &mut points {
        p.trace_ms = Spread::of(&p.trace_ms_reps);
    }
    let front = pareto_front(
        &points
            .iter()
            .map(|p| (p.tree_bytes, p.trace_ms.median))
            .collect::<Vec<_>>(),
    );
    for (p, f) in points.iter_mut().zip(front) {
        p.on_front = f;
    }
    Ok(SceneFront {
        name: name.to_string(),
        triangles: scene.len() as u64,
        views: cams.iter().map(|(id, _)| id.clone()).collect(),
        rays: cams
            .iter()
            .map(|(_, c)| u64::from(c.width) * u64::from(c.height))
            .sum(),
        points,
        families: grid.families.clone(),
    })
}

/// The Markdown file of a sweep written to a directory.
pub const FRONT_MARKDOWN: &str = "sweep.md";
/// The JSON file beside it.
pub const FRONT_JSON: &str = "sweep.json";

/// Bytes in a readable unit: `B`, `KiB` or `MiB`, chosen by the largest.
fn byte_unit(max: u64) -> (f64, &'static str) {
    if max >= 1 << 20 {
        (MIB, "MiB")
    } else if max >= 1 << 10 {
        (1024.0, "KiB")
    } else {
        (1.0, "B")
    }
}

impl FrontReport {
    /// The file names of the charts, by scene: `SCENE.sweep.svg` (a name
    /// given twice gets its position appended).
    pub fn figure_names(&self) -> Vec<String> {
        self.scenes
            .iter()
            .enumerate()
            .map(|(i, s)| {
                if self.scenes[..i].iter().any(|o| o.name == s.name) {
                    format!("{}-{}.sweep.svg", s.name, i + 1)
                } else {
                    format!("{}.sweep.svg", s.name)
                }
            })
            .collect()
    }

    /// The chart of scene `i`: tree bytes (y) against the median time of a
    /// round (x), min–max whiskers, a line per family, the presets ringed
    /// and named, the Pareto front dashed.
    pub fn svg(&self, i: usize) -> Result<String, plot::PlotError> {
        let s = &self.scenes[i];
        let (unit, unit_name) = byte_unit(s.points.iter().map(|p| p.tree_bytes).max().unwrap_or(0));
        let points: Vec<plot::TradeOffPoint> = s
            .points
            .iter()
            .map(|p| plot::TradeOffPoint {
                x: p.trace_ms.median,
                x_range: (p.trace_ms.min, p.trace_ms.max),
                y: p.tree_bytes as f64 / unit,
                label: p.setting.label.clone(),
                highlight: p.setting.preset.is_some(),
                on_front: p.on_front,
            })
            .collect();
        let lines: Vec<plot::TradeOffLine> = s
            .families
            .iter()
            .map(|f| plot::TradeOffLine {
                name: f.name.clone(),
                points: f.points.clone(),
            })
            .collect();
        plot::front_svg(
            &format!(
                "{}: tree bytes against trace time ({} views {}×{}, packets, {} threads, {} rounds)",
                s.name,
                s.views.len(),
                self.size.0,
                self.size.1,
                self.threads,
                self.reps
            ),
            "trace time of the views, ms (median; whiskers: min–max)",
            &format!("tree bytes ({unit_name}, reordered .kd)"),
            &points,
            &lines,
            (1000, 700),
        )
    }

    /// The Markdown: per scene a table of every point and which presets
    /// lie on the front; `figures` are the charts' file names, linked.
    pub fn markdown(&self, figures: &[String]) -> String {
        use std::fmt::Write as _;
        let mut md = String::new();
        let _ = writeln!(
            md,
            "# Trade-off front: tree bytes against trace time\n\n\
             Primary packets ({} kernel), {} threads, {}×{} frames of each view, \
             {} timed rounds after a warm-up (the trees interleaved within each round); \
             times are a round's frames of one tree, all views. Tree bytes of the \
             reordered `.kd` file. Build: the std build of the constants plus the slim pass. \
             `*`: on the Pareto front (no point both smaller and faster at the median).\n",
            self.simd, self.threads, self.size.0, self.size.1, self.reps
        );
        for (i, s) in self.scenes.iter().enumerate() {
            let std_bytes = s.preset(TreeKind::Std).map(|p| p.tree_bytes as f64);
            let std_ms = s.preset(TreeKind::Std).map(|p| p.trace_ms.median);
            let _ = writeln!(
                md,
                "## {} ({} triangles, views {}, {} rays a round)\n",
                s.name,
                s.triangles,
                s.views.join(", "),
                s.rays
            );
            if let Some(f) = figures.get(i) {
                let _ = writeln!(md, "![{}]({f})\n", s.name);
            }
            md.push_str(
                "| setting | families | tree bytes | vs std | hoisted | build s | ms median | min | max | vs std | front |\n\
                 |---|---|---:|---:|---:|---:|---:|---:|---:|---:|:-:|\n",
            );
            for (k, p) in s.points.iter().enumerate() {
                let fams: Vec<String> = s
                    .families
                    .iter()
                    .enumerate()
                    .filter(|(_, f)| f.points.contains(&k))
                    .map(|(j, _)| (j + 1).to_string())
                    .collect();
                // The change against std, `100·(x/std − 1)`.
                let pct = |x: f64, base: Option<f64>| match base {
                    Some(b) if x == b => "0".to_string(),
                    Some(b) if b != 0.0 => {
                        // A change that rounds to zero reads `+0.0`, never `-0.0`.
                        let d = 100.0 * (x / b - 1.0);
                        format!("{:+.1} %", if d.abs() < 0.05 { 0.0 } else { d })
                    }
                    _ => "–".to_string(),
                };
                let name = if p.setting.preset.is_some() {
                    format!("**{}**", p.setting.label)
                } else {
                    p.setting.label.clone()
                };
                let _ = writeln!(
                    md,
                    "| {name} | {} | {} | {} | {} | {:.3} | {:.2} | {:.2} | {:.2} | {} | {} |",
                    fams.join(", "),
                    p.tree_bytes,
                    pct(p.tree_bytes as f64, std_bytes),
                    p.hoisted,
                    p.build_s(),
                    p.trace_ms.median,
                    p.trace_ms.min,
                    p.trace_ms.max,
                    pct(p.trace_ms.median, std_ms),
                    if p.on_front { "*" } else { "" }
                );
            }
            let _ = writeln!(md);
            for (j, f) in s.families.iter().enumerate() {
                let labels: Vec<&str> = f
                    .points
                    .iter()
                    .map(|&k| s.points[k].setting.label.as_str())
                    .collect();
                let _ = writeln!(md, "{}. {}: {}", j + 1, f.name, labels.join(" → "));
            }
            let on: Vec<String> = TreeKind::ALL
                .iter()
                .filter_map(|&kind| {
                    s.preset(kind).map(|p| {
                        format!(
                            "{} {}",
                            kind.name(),
                            if p.on_front {
                                "is on the front"
                            } else {
                                "is not"
                            }
                        )
                    })
                })
                .collect();
            let _ = writeln!(md, "\nPresets: {}.\n", on.join(", "));
        }
        md
    }

    /// The JSON object (`docs/json-schema.md`, "sweep.json").
    pub fn json(&self) -> serde_json::Value {
        serde_json::to_value(FrontJson {
            schema: JSON_SCHEMA,
            threads: self.threads,
            width: self.size.0,
            height: self.size.1,
            reps: self.reps,
            simd: self.simd,
            scenes: self.scenes.iter().map(SceneFrontJson::of).collect(),
        })
        .unwrap_or(serde_json::Value::Null)
    }

    /// Writes `sweep.md`, `sweep.json` and the charts into `dir`, all or
    /// nothing (every file staged before the first rename); returns the
    /// paths written.
    pub fn write(&self, dir: &Path) -> std::io::Result<Vec<PathBuf>> {
        let figures = self.figure_names();
        let mut json = serde_json::to_string_pretty(&self.json()).map_err(std::io::Error::other)?;
        json.push('\n');
        let mut files = vec![
            (dir.join(FRONT_MARKDOWN), self.markdown(&figures)),
            (dir.join(FRONT_JSON), json),
        ];
        for (i, f) in figures.iter().enumerate() {
            files.push((dir.join(f), self.svg(i).map_err(std::io::Error::other)?));
        }
        write_all_atomically(&files)?;
        Ok(files.into_iter().map(|(p, _)| p).collect())
    }
}

#[derive(Serialize)]
struct FrontJson<'a> {
    schema: u32,
    threads: usize,
    width: u32,
    height: u32,
    reps: usize,
    simd: &'static str,
    scenes: Vec<SceneFrontJson<'a>>,
}

#[derive(Serialize)]
struct SceneFrontJson<'a> {
    name: &'a str,
    triangles: u64,
    views: &'a [String],
    rays: u64,
    points: Vec<FrontPointJson<'a>>,
    families: Vec<FamilyJson<'a>>,
    /// Labels of the points on the front, by median time.
    front: Vec<&'a str>,
}

#[derive(Serialize)]
struct FrontPointJson<'a> {
    label: &'a str,
    preset: Option<&'static str>,
    k_t: f64,
    k_i: f64,
    split_price: f64,
    tau_occu: Option<f64>,
    tau_freq: Option<f64>,
    max_t2rn: Option<u32>,
    coarsen: Option<f64>,
    cost_ratio: Option<f64>,
    hoist_rule: Option<&'static str>,
    tree_bytes: u64,
    nodes_total: u64,
    hoisted: usize,
    std_build_s: f64,
    slim_s: f64,
    build_s: f64,
    trace_ms_min: f64,
    trace_ms_median: f64,
    trace_ms_max: f64,
    trace_ms_reps: &'a [f64],
    on_front: bool,
}

#[derive(Serialize)]
struct FamilyJson<'a> {
    name: &'a str,
    points: Vec<&'a str>,
}

impl<'a> SceneFrontJson<'a> {
    fn of(s: &'a SceneFront) -> SceneFrontJson<'a> {
        let mut front: Vec<&FrontPoint> = s.points.iter().filter(|p| p.on_front).collect();
        front.sort_by(|a, b| a.trace_ms.median.total_cmp(&b.trace_ms.median));
        SceneFrontJson {
            name: &s.name,
            triangles: s.triangles,
            views: &s.views,
            rays: s.rays,
            points: s
                .points
                .iter()
                .map(|p| {
                    let slim = p.setting.slim.as_ref();
                    FrontPointJson {
                        label: &p.setting.label,
                        preset: p.setting.preset.map(TreeKind::name),
                        k_t: p.setting.k_t,
                        k_i: p.setting.k_i,
                        split_price: p.setting.split_price,
                        tau_occu: slim.map(|s| s.tau_occu),
                        tau_freq: slim.map(|s| s.tau_freq),
                        max_t2rn: slim.map(|s| s.max_t2rn),
                        coarsen: slim.map(|s| s.coarsen),
                        cost_ratio: slim.map(|s| s.cost_ratio).filter(|r| r.is_finite()),
                        hoist_rule: slim.map(|s| rule_name(s.rule)),
                        tree_bytes: p.tree_bytes,
                        nodes_total: p.nodes,
                        hoisted: p.hoisted,
                        std_build_s: p.std_build_s,
                        slim_s: p.slim_s,
                        build_s: p.build_s(),
                        trace_ms_min: p.trace_ms.min,
                        trace_ms_median: p.trace_ms.median,
                        trace_ms_max: p.trace_ms.max,
                        trace_ms_reps: &p.trace_ms_reps,
                        on_front: p.on_front,
                    }
                })
                .collect(),
            families: s
                .families
                .iter()
                .map(|f| FamilyJson {
                    name: &f.name,
                    points: f
                        .points
                        .iter()
                        .map(|&k| s.points[k].setting.label.as_str())
                        .collect(),
                })
                .collect(),
            front: front.iter().map(|p| p.setting.label.as_str()).collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_keeps_the_undominated() {
        let pts = [
            (100, 5.0),
            (80, 6.0),
            (120, 4.0),
            (100, 6.0), // dominated by (100, 5) and (80, 6)
            (90, 7.0),  // dominated by (80, 6)
            (80, 6.0),  // equal to a front point: both stay
            (50, f64::NAN),
        ];
        assert_eq!(
            pareto_front(&pts),
            [true, true, true, false, false, true, false]
        );
    }

    #[test]
    fn default_grid_has_the_presets_exactly_and_unique_labels() {
        let g = default_grid();
        assert_eq!(g.settings.len(), 20);
        let find = |k: TreeKind| {
            g.settings
                .iter()
                .filter(|s| s.preset == Some(k))
                .collect::<Vec<_>>()
        };
        let std = find(TreeKind::Std);
        assert_eq!(std.len(), 1);
        assert_eq!(std[0].slim, None);
        assert_eq!(std[0].k_t, build::sah::SahParams::default().k_t);
        assert_eq!(find(TreeKind::Fast)[0].slim, Some(SlimParams::FAST));
        assert_eq!(find(TreeKind::Small)[0].slim, Some(SlimParams::SMALL));
        let mut labels: Vec<&str> = g.settings.iter().map(|s| s.label.as_str()).collect();
        labels.sort_unstable();
        labels.dedup();
        assert_eq!(labels.len(), g.settings.len());
        assert_eq!(g.families.len(), 5);
        for f in &g.families {
            assert!(f.points.len() >= 4, "{}", f.name);
        }
    }
}
