//! `slimkd build --cells`, `build-cell` and `stitch`: a build in cells
//! (`slimkd::cells`; the design is docs/cells.md).

use crate::args::{BuildArgs, BuilderArg, CellsArgs, OutputFlags, Usage, check_output_dir};
use crate::build::{PeakRss, build_config, load, pipeline_of, stitch_streamed};
use crate::json::{BuildCellJson, CellJson, CellsJson, print_json};
use crate::progress_bar::{si, with_bar};
use crate::{CmdResult, pool};
use slimkd::build::{BuildConfig, SahParams, level};
use slimkd::cells::{self, CellMismatch, CellsError, Plan};
use slimkd::format::SceneTag;
use slimkd::progress::Progress;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

/// The usage rules of `build --cells`, checked before any work.
fn check_cells_usage(
    args: &BuildArgs,
    output: Option<&Path>,
    reorder: bool,
    cells: &CellsArgs,
) -> CmdResult<PathBuf> {
    args.check()?;
    if args.slim(reorder).0.is_some() {
        return Err(Usage(
            "--cells builds the std tree only: the slim pass rebuilds subtrees across cell \
             boundaries with the whole tree and scene in memory (build without --cells for a \
             slim preset)"
                .into(),
        )
        .into());
    }
    if !matches!(args.builder, BuilderArg::Level) {
        return Err(Usage("--cells runs the level builder (omit --builder)".into()).into());
    }
    if let Some(out) = output {
        check_output_dir(out)?;
    }
    match (&cells.cells_dir, output) {
        (Some(d), _) => Ok(d.clone()),
        (None, Some(out)) => {
            let mut d = out.as_os_str().to_owned();
            d.push(".cells");
            Ok(PathBuf::from(d))
        }
        (None, None) => Err(Usage(
            "--cells needs -o (the .kd file) or --cells-dir (the work directory)".into(),
        )
        .into()),
    }
}

/// `slimkd build --cells K`.
pub(crate) fn cmd_build_cells(
    path: &Path,
    args: &BuildArgs,
    output: Option<&Path>,
    reorder: bool,
    k: usize,
    cells: &CellsArgs,
    ui: OutputFlags,
) -> CmdResult<()> {
    let dir = check_cells_usage(args, output, reorder, cells)?;
    if output.is_none() && !cells.plan_only {
        return Err(Usage("--cells needs -o (or --plan-only)".into()).into());
    }
    let pool = pool(args.threads)?;
    let watch = PeakRss::start();
    pool.install(|| {
        let loaded = load(path, ui.bars_off())?;
        let config = build_config(args);
        // The reordering does not enter the level build.
        let options = pipeline_of(args, &loaded, false).level_options();
        // The plan's cut depends on the small-node threshold, so the plan
        // takes the default one (or `--small`), not the budget's: a plan
        // then resumes under any budget. The cells build with `options`.
        let plan_options = level::LevelOptions {
            small_threshold: args.small.unwrap_or(level::DEFAULT_SMALL_THRESHOLD),
            ..options.clone()
        };
        let scene = &loaded.scene;
        let start = Instant::now();
        let progress = Progress::default();
        let prepared = with_bar(ui.bars_off(), "planning", &progress, &String::new, || {
            let hash = SceneTag::geometry_hash_of(scene);
            Ok(cells::prepare(&dir, scene, &config, &plan_options, k, hash, Some(&progress))?)
        })?;
        let plan_s = start.elapsed().as_secs_f64();
        let plan = &prepared.plan;
        let kept = prepared.done.iter().filter(|&&d| d).count();
        if !ui.quiet && !ui.json {
            let how = if prepared.planned { "planned" } else { "resumed" };
            eprintln!(
                "cells      {how} {} in {plan_s:.3} s: {} cells (at most {k}, bound {} references), {kept} parts kept",
                dir.display(),
                plan.cells.len(),
                plan.cut.max_refs
            );
        }
        let mut times: Vec<Option<f64>> = vec![None; plan.cells.len()];
        if !cells.plan_only {
            build_missing(&dir, plan, &prepared.done, &options, ui, &mut times)?;
        }
        let json = cells_json(&dir, plan, prepared.planned, plan_s, &prepared.done, &times);
        if cells.plan_only {
            if ui.json {
                print_json("plan", json)?;
            }
            return Ok(());
        }
        let Some(out) = output else {
            return Err(Usage("--cells needs -o (or --plan-only)".into()).into());
        };
        let seconds = start.elapsed().as_secs_f64();
        stitch_streamed(
            "build", &loaded, &dir, plan, config, out, reorder, ui, &watch, json, seconds,
        )
    })
}

/// Builds the cells of `plan` whose parts are not `done`, in parallel;
/// each one's seconds go to `times`.
fn build_missing(
    dir: &Path,
    plan: &Plan,
    done: &[bool],
    options: &level::LevelOptions,
    ui: OutputFlags,
    times: &mut [Option<f64>],
) -> CmdResult<()> {
    use rayon::prelude::*;
    let todo: Vec<usize> = (0..plan.cells.len()).filter(|&i| !done[i]).collect();
    let finished = AtomicUsize::new(0);
    let results: Vec<(usize, Result<f64, CellsError>)> = todo
        .par_iter()
        .map(|&i| {
            let start = Instant::now();
            let r = cells::read_planned_cell(dir, plan, i).and_then(|input| {
                let tree = cells::build_cell(&input, options)?;
                cells::write_part(&cells::part_path(dir, i), plan.cells[i].id, &tree)
            });
            let secs = start.elapsed().as_secs_f64();
            if r.is_ok() && !ui.quiet && !ui.json {
                let n = finished.fetch_add(1, Ordering::Relaxed) + 1;
                eprintln!(
                    "cell       {} built: {} references in {secs:.3} s ({n} of {} to build)",
                    cells::cell_path(dir, i).display(),
                    si(plan.cells[i].refs),
                    todo.len()
                );
            }
            (i, r.map(|()| secs))
        })
        .collect();
    for (i, r) in results {
        times[i] = Some(r?);
    }
    Ok(())
}

fn cells_json(
    dir: &Path,
    plan: &Plan,
    planned: bool,
    plan_s: f64,
    done: &[bool],
    times: &[Option<f64>],
) -> CellsJson {
    CellsJson {
        cells_dir: dir.display().to_string(),
        planned,
        plan_s,
        cell_list: (0..plan.cells.len())
            .map(|i| CellJson {
                cell: cells::cell_path(dir, i).display().to_string(),
                part: cells::part_path(dir, i).display().to_string(),
                refs: plan.cells[i].refs,
                kept: done[i],
                build_s: times[i],
            })
            .collect(),
    }
}

/// `slimkd build-cell CELL [-o PART]`.
pub(crate) fn cmd_build_cell(
    cell: &Path,
    output: Option<&Path>,
    threads: Option<usize>,
    ui: OutputFlags,
) -> CmdResult<()> {
    let output = output.map_or_else(|| cell.with_extension("kdpart"), Path::to_path_buf);
    check_output_dir(&output)?;
    let pool = pool(threads)?;
    pool.install(|| {
        let start = Instant::now();
        let (input, id) = cells::read_cell(cell)?;
        let read_s = start.elapsed().as_secs_f64();
        // No build flag changes the tree, so `build-cell` takes none.
        let tree = cells::build_cell(&input, &level::LevelOptions::default())?;
        let build_s = start.elapsed().as_secs_f64() - read_s;
        cells::write_part(&output, id, &tree)?;
        let total_s = start.elapsed().as_secs_f64();
        if ui.json {
            print_json(
                "build-cell",
                BuildCellJson {
                    cell: cell.display().to_string(),
                    part: output.display().to_string(),
                    refs: input.tris.len() as u64,
                    nodes: tree.nodes.len() as u64,
                    read_s,
                    build_s,
                    total_s,
                    threads: rayon::current_num_threads(),
                },
            )?;
        } else if !ui.quiet {
            println!(
                "cell       {} (cell {} of {}, {} references, depth {})",
                cell.display(),
                input.index,
                input.n_cells,
                si(input.tris.len() as u64),
                input.depth
            );
            println!(
                "built      {} nodes in {build_s:.3} s (read {read_s:.3} s); wrote {} ({total_s:.3} s in all)",
                si(tree.nodes.len() as u64),
                output.display()
            );
        }
        Ok(())
    })
}

/// `slimkd stitch SCENE --cells-dir DIR -o OUT`.
pub(crate) fn cmd_stitch(
    scene: &Path,
    dir: &Path,
    output: &Path,
    reorder: bool,
    threads: Option<usize>,
    ui: OutputFlags,
) -> CmdResult<()> {
    check_output_dir(output)?;
    let pool = pool(threads)?;
    let watch = PeakRss::start();
    pool.install(|| {
        let plan_path = cells::plan_path(dir);
        let plan = cells::read_plan(&plan_path)?;
        let loaded = load(scene, ui.bars_off())?;
        if plan.n_tris != loaded.scene.len() as u64
            || plan.scene_hash != SceneTag::geometry_hash_of(&loaded.scene)
        {
            return Err(CellsError::Mismatch {
                path: plan_path,
                what: CellMismatch::AnotherScene {
                    scene: scene.to_path_buf(),
                },
            }
            .into());
        }
        let start = Instant::now();
        let missing: Vec<String> = (0..plan.cells.len())
            .filter_map(|i| {
                cells::read_part(&cells::part_path(dir, i), plan.cells[i].id)
                    .err()
                    .map(|e| e.to_string())
            })
            .collect();
        if !missing.is_empty() {
            return Err(format!(
                "{}: {} of {} cells have no valid part (build them with slimkd build-cell): {}",
                dir.display(),
                missing.len(),
                plan.cells.len(),
                missing.join("; ")
            )
            .into());
        }
        let secs = start.elapsed().as_secs_f64();
        let config = BuildConfig {
            sah: SahParams {
                max_depth: Some(plan.depth_limit),
                ..plan.sah
            },
        };
        let json = cells_json(
            dir,
            &plan,
            false,
            0.0,
            &vec![true; plan.cells.len()],
            &vec![None; plan.cells.len()],
        );
        stitch_streamed(
            "stitch", &loaded, dir, &plan, config, output, reorder, ui, &watch, json, secs,
        )
    })
}
