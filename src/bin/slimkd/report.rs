//! `slimkd report`: the paper's tables and figures.

use crate::*;
use slimkd::render::{self};
use slimkd::stats::report;
use std::time::Instant;

pub(crate) fn cmd_report(args: &ReportArgs) -> Res<()> {
    // The output's name and directory, before any work.
    report::ReportPaths::for_markdown(&args.output).map_err(|e| Usage(e.to_string()))?;
    check_output_dir(&args.output)?;
    let views = match &args.views {
        Some(file) => {
            let mut text = String::new();
            slimkd::fsio::open_regular(file)
                .and_then(|mut f| std::io::Read::read_to_string(&mut f, &mut text))
                .map_err(|e| format!("{}: {e}", file.display()))?;
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
        Some(0) => return Err(Usage("--threads must be at least 1".into()).into()),
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
