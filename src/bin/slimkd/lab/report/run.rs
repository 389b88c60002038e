//! The experiment driver: build, slim, write and trace every scene.

use super::tables::{Pools, duplication, measure_views, sweep_point, write_tree};
use super::*;
use slimkd::pipeline::Pipeline;
use slimkd::progress::Progress;
use std::borrow::Cow;

/// The views of a scene among [`VIEW_IDS`], found by its name (or, for a
/// file name or path, by its stem).
fn view_ids<'v>(options: &'v ReportOptions, name: &str) -> Vec<(&'static str, &'v View)> {
    views_of(&options.views, name)
}

/// [`view_ids`] in a list of views.
fn views_of<'v>(views: &'v [View], name: &str) -> Vec<(&'static str, &'v View)> {
    VIEW_IDS
        .iter()
        .filter_map(|&id| {
            render::find_view_named(views, name, id)
                .or_else(|| render::find_view(views, Path::new(name), id))
                .map(|v| (id, v))
        })
        .collect()
}

/// The cameras of a scene: its views 1–3, or the default camera.
fn cameras(options: &ReportOptions, name: &str, bounds: &Aabb) -> Vec<(String, Camera)> {
    cameras_of(&options.views, options.size, name, bounds)
}

/// [`cameras`] from a list of views, at `(width, height)`.
pub(super) fn cameras_of(
    views: &[View],
    (w, h): (u32, u32),
    name: &str,
    bounds: &Aabb,
) -> Vec<(String, Camera)> {
    let found: Vec<(String, Camera)> = views_of(views, name)
        .into_iter()
        .map(|(id, v)| (id.to_string(), Camera::from_view(v, w, h)))
        .collect();
    if found.is_empty() {
        vec![("default".to_string(), Camera::default_for(bounds, w, h))]
    } else {
        found
    }
}

/// The steps of a report, each announced by a line: the share of the
/// report done (in a [`Progress`], one step per line) and the lines.
struct Steps<'p> {
    bar: Option<&'p Progress>,
    done: u64,
    total: u64,
    log: &'p mut dyn FnMut(&str),
}

impl Steps<'_> {
    /// Starts a step (the one before it is done).
    fn step(&mut self, line: &str) {
        self.finish_step();
        (self.log)(line);
    }

    /// Ends the step in progress, if any.
    fn finish_step(&mut self) {
        if self.done > 0 && self.done <= self.total {
            Progress::advance(self.bar, self.done - 1, self.done, self.total);
        }
        self.done += 1;
    }

    /// A line that starts no step (a warning).
    fn note(&mut self, line: &str) {
        (self.log)(line);
    }
}

/// The options every timed run needs: at least one rep and one thread,
/// and frames of some size (the report's and the sweep's rule).
pub(crate) fn check_timing_options(
    reps: usize,
    threads: usize,
    size: (u32, u32),
) -> Result<(), ReportError> {
    if reps == 0 {
        return Err(ReportError::Options("reps must be at least 1".into()));
    }
    if threads == 0 {
        return Err(ReportError::Options("threads must be at least 1".into()));
    }
    if size.0 == 0 || size.1 == 0 {
        return Err(ReportError::Options(
            "the image size must not be zero".into(),
        ));
    }
    Ok(())
}

/// Builds, writes and traces every scene; `progress` gets one line per
/// step (what the tests run; the command shows a bar too).
#[cfg(test)]
pub fn run(options: &ReportOptions, progress: &mut dyn FnMut(&str)) -> Result<Report, ReportError> {
    run_with_progress(options, None, progress)
}

/// [`run()`], advancing `bar` by one equal share per step, over all scenes
/// (a step is what one line of `log` announces: a build, a slim pass, a
/// file written, one view traced in one mode and thread count, or a sweep
/// point). A line that starts with `warning:` announces no step.
pub fn run_with_progress(
    options: &ReportOptions,
    bar: Option<&Progress>,
    log: &mut dyn FnMut(&str),
) -> Result<Report, ReportError> {
    check_timing_options(options.reps, options.all_threads, options.size)?;
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
    let base = Pipeline::new(config);
    let mut scenes = Vec::new();
    // Per scene: the std build, two slim passes, three files, four
    // measurements per view and the sweep's points.
    let sweep_points = if options.sweep {
        grid_occu.len() * grid_freq.len()
    } else {
        0
    };
    let total = options
        .scenes
        .iter()
        .map(|(name, _, _)| 6 + 4 * view_ids(options, name).len().max(1) + sweep_points)
        .sum::<usize>() as u64;
    let mut steps = Steps {
        bar,
        done: 0,
        total,
        log,
    };
    for (name, scene, load_s) in &options.scenes {
        steps.step(&format!("{name}: building std tree"));
        let start = Instant::now();
        // The level builder is the fastest (the same tree as every other
        // builder), so the slim ratios of Table 4 are against the best std
        // build; the slim passes run on the same pool.
        let pipeline = Pipeline {
            scene_name: Some(name.clone()),
            ..base.clone()
        };
        let build_error = |source| ReportError::Build {
            scene: name.clone(),
            source,
        };
        let (std_tree, _) = pools
            .all
            .install(|| pipeline.build(scene, None))
            .map_err(build_error)?;
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
            let kind_pipeline = pipeline.slimmed(kind.params(options.rule), kind.preset());
            let slimmed = match kind_pipeline.slim {
                None => None,
                Some(_) => {
                    steps.step(&format!("{name}: {}'s std tree", kind.name()));
                    let start = Instant::now();
                    let base = pools
                        .all
                        .install(|| kind_pipeline.base_tree(&std_tree, &pipeline, scene))
                        .map_err(build_error)?;
                    if let Cow::Owned(_) = base {
                        times.base_s[k - 1] = start.elapsed().as_secs_f64();
                    }
                    steps.step(&format!("{name}: slim pass ({})", kind.name()));
                    let start = Instant::now();
                    let slimmed = pools.all.install(|| kind_pipeline.slim(&base, scene, None));
                    let (t, r, _) = slimmed.expect("the pipeline has a slim pass");
                    times.slim_s[k - 1] = start.elapsed().as_secs_f64();
                    hoisted[k] = r.hoisted;
                    Some(t)
                }
            };
            steps.step(&format!("{name}: writing {} file", kind.name()));
            let tree = slimmed.as_ref().unwrap_or(&std_tree);
            let w = write_tree(name, kind.name(), tree, scene, &kind_pipeline)?;
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
        if cams[0].0 == "default" {
            steps.note(&format!(
                "warning: {name} has no views (views are matched by the scene's name); \
                 Table 3(b) times it from the default camera"
            ));
        }
        let table3b = measure_views(name, &cams, &files, &pools, options.reps, &mut |line| {
            steps.step(line)
        })?;
        let mut sweep = Vec::new();
        if options.sweep {
            for &tau_occu in &grid_occu {
                for &tau_freq in &grid_freq {
                    steps.step(&format!(
                        "{name}: sweep τ_occu {tau_occu} τ_freq {tau_freq}"
                    ));
                    let params = SlimParams {
                        tau_occu,
                        tau_freq,
                        max_t2rn: SWEEP_MAX_T2RN,
                        rule: options.rule,
                        // The paper's rebuild: Figure 5 sweeps its thresholds.
                        rebuild: slimkd::slim::Rebuild::Sah,
                        coarsen: 1.0,
                        cost_ratio: f64::INFINITY,
                        split_price: None,
                    };
                    sweep.push(sweep_point(
                        name,
                        scene,
                        &std_tree,
                        files[0],
                        &pipeline,
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
    steps.finish_step();
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
