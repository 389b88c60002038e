//! `slimkd report`: the paper's tables and figures.

use crate::CmdResult;
use crate::args::{OutputFlags, ReportArgs, Usage, check_output_dir};
use crate::build::load_all;
use crate::json::print_json;
use crate::lab::report;
use crate::progress_bar::with_step_log;

/// `slimkd report --json`: the files written; the figures are in the
/// report's own JSON file.
#[derive(serde::Serialize)]
struct ReportCmdJson {
    written: Vec<String>,
    scenes: Vec<String>,
    all_threads: usize,
    reps: usize,
}

pub(crate) fn cmd_report(args: &ReportArgs, ui: OutputFlags) -> CmdResult<()> {
    // The output's name and directory, before any work.
    report::ReportPaths::for_markdown(&args.output).map_err(|e| Usage(e.to_string()))?;
    check_output_dir(&args.output)?;
    let views = crate::read_views(args.timed.views.as_deref())?;
    let scenes: Vec<_> = load_all(&args.timed.scenes, ui)?
        .into_iter()
        .map(|loaded| (loaded.name(), loaded.scene, loaded.seconds))
        .collect();
    let all_threads = match args.threads {
        Some(0) => return Err(Usage("--threads must be at least 1".into()).into()),
        Some(n) => n,
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    let options = report::ReportOptions {
        scenes,
        views,
        size: args.timed.size,
        reps: args.timed.reps,
        sweep: args.sweep,
        all_threads,
        sweep_grid: None,
        rule: args.hoist_rule.rule(true),
    };
    let report = with_step_log(ui.bars_off(), "report", |progress, log| {
        Ok(report::run_with_progress(&options, Some(progress), log)?)
    })?;
    let written = report
        .write(&args.output)
        // Its errors name the file.
        .map_err(|e| format!("cannot write the report: {e}"))?;
    if ui.json {
        return print_json(
            "report",
            ReportCmdJson {
                written: written.iter().map(|p| p.display().to_string()).collect(),
                scenes: report.scenes.iter().map(|s| s.name.clone()).collect(),
                all_threads: report.all_threads,
                reps: report.reps,
            },
        );
    }
    if ui.quiet {
        return Ok(());
    }
    if ui.verbose {
        print!("{}", report.markdown_for(&args.output));
    }
    for p in written {
        println!("wrote {}", p.display());
    }
    Ok(())
}
