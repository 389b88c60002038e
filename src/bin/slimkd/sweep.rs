//! `slimkd sweep`: the trade-off front of tree bytes against trace time
//! over families of settings ([`crate::lab::report::front::run_front`]).

use crate::CmdResult;
use crate::args::{OutputFlags, SweepArgs};
use crate::build::load_all;
use crate::json::print_json;
use crate::lab::report;
use crate::progress_bar::with_step_log;

/// `slimkd sweep --json`: the files written and the sweep's own JSON
/// (what `sweep.json` holds).
#[derive(serde::Serialize)]
struct SweepCmdJson {
    written: Vec<String>,
    #[serde(flatten)]
    sweep: serde_json::Value,
}

pub(crate) fn cmd_sweep(args: &SweepArgs, ui: OutputFlags) -> CmdResult<()> {
    match std::fs::metadata(&args.output) {
        Ok(m) if m.is_dir() => {}
        Ok(_) => return Err(format!("{}: not a directory", args.output.display()).into()),
        Err(e) => return Err(format!("{}: {e}", args.output.display()).into()),
    }
    let views = crate::read_views(args.timed.views.as_deref())?;
    let scenes: Vec<_> = load_all(&args.timed.scenes, ui)?
        .into_iter()
        .map(|loaded| (loaded.name(), loaded.scene))
        .collect();
    let options = report::front::FrontOptions {
        scenes,
        views,
        size: args.timed.size,
        reps: args.timed.reps,
        threads: args.threads,
        grid: None,
    };
    let sweep = with_step_log(ui.bars_off(), "sweep", |progress, log| {
        Ok(report::front::run_front(&options, Some(progress), log)?)
    })?;
    let written = sweep
        .write(&args.output)
        // Its errors name the file.
        .map_err(|e| format!("cannot write the sweep: {e}"))?;
    if ui.json {
        let mut body = sweep.json();
        if let Some(o) = body.as_object_mut() {
            // print_json writes the schema first.
            o.remove("schema");
        }
        return print_json(
            "sweep",
            SweepCmdJson {
                written: written.iter().map(|p| p.display().to_string()).collect(),
                sweep: body,
            },
        );
    }
    if ui.quiet {
        return Ok(());
    }
    if ui.verbose {
        print!("{}", sweep.markdown(&sweep.figure_names()));
    }
    for s in &sweep.scenes {
        let on: Vec<String> = report::TreeKind::ALL
            .iter()
            .filter_map(|&k| {
                s.preset(k).map(|p| {
                    format!(
                        "{} {}",
                        k.name(),
                        if p.on_front { "on the front" } else { "off it" }
                    )
                })
            })
            .collect();
        println!(
            "{}: {} points, {} on the front; {}",
            s.name,
            s.points.len(),
            s.points.iter().filter(|p| p.on_front).count(),
            on.join(", ")
        );
    }
    for p in written {
        println!("wrote {}", p.display());
    }
    Ok(())
}
