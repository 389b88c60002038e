//! The `slimkd` command line: build a kd-tree for a scene, store it as a
//! `.kd` file, inspect and verify files, render, and report figures.
//! Without arguments it runs the main job on the embedded default scene.
//! Exit codes: 0 success, 1 failure (bad input, invalid file, I/O), 2 bad
//! usage.

mod args;
mod build;
mod info;
mod json;
mod main_job;
mod progress_bar;
mod render;
mod report;
mod trace;

use clap::parser::ValueSource;
use clap::{Args, CommandFactory, FromArgMatches};
use std::process::ExitCode;

use args::*;
use build::*;
use info::*;
use json::*;
use progress_bar::*;
use render::*;
use report::*;

/// The embedded default scene: nexuiz_dieselpower (see scenes/README.md).
pub(crate) const DEFAULT_SCENE_NAME: &str = "nexuiz_dieselpower.obj";
pub(crate) const DEFAULT_SCENE: &[u8] = include_bytes!("../../../scenes/nexuiz_dieselpower.obj");
pub(crate) const DEFAULT_VIEWS: &str = include_str!("../../../scenes/views.txt");
/// The name that selects the embedded scene on the command line.
pub(crate) const DEFAULT_ARG: &str = "default";

pub(crate) type Res<T> = Result<T, Box<dyn std::error::Error + Send + Sync>>;

fn main() -> ExitCode {
    // A closed pipe (`slimkd info x.kd | head`) ends the process quietly,
    // as it does other command-line tools, instead of a panic on the next
    // print: the Rust runtime ignores SIGPIPE, so restore its default.
    #[cfg(target_os = "linux")]
    // SAFETY: setting a signal's disposition to its default at start-up,
    // before any thread is spawned, has no precondition.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let matches = Cli::command().get_matches();
    let mut cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    if let Some((_, sub)) = matches.subcommand() {
        match &mut cli.command {
            Some(Command::Build { build, .. }) => build.given = given_build_flags(sub),
            Some(Command::Render(args)) => args.build.given = given_build_flags(sub),
            _ => {}
        }
    }
    let ui = cli.out;
    let result = match cli.command {
        None => main_job::main_job(ui),
        Some(Command::Build {
            scene,
            build,
            output,
            reorder,
        }) => cmd_build(&scene, &build, output.as_deref(), reorder, ui),
        Some(Command::Render(args)) => cmd_render(&args, ui),
        Some(Command::Info { file }) => cmd_info(&file, ui),
        Some(Command::Verify { file }) => cmd_verify(&file, ui),
        Some(Command::Convert { scene, output }) => cmd_convert(&scene, &output, ui),
        Some(Command::Report(args)) => cmd_report(&args, ui),
        Some(Command::Trace(args)) => cmd_trace(&args, ui),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("slimkd: error: {e}");
            if e.downcast_ref::<Usage>().is_some() {
                ExitCode::from(2)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}

/// The long names of the build flags (all of [`BuildArgs`] but
/// `--threads`) given on the command line of a subcommand.
fn given_build_flags(sub: &clap::ArgMatches) -> Vec<String> {
    BuildArgs::augment_args(clap::Command::new("build"))
        .get_arguments()
        .filter(|a| a.get_id() != "threads")
        .filter(|a| sub.value_source(a.get_id().as_str()) == Some(ValueSource::CommandLine))
        .filter_map(|a| a.get_long().map(|l| format!("--{l}")))
        .collect()
}

/// `slimkd trace`, its usage checked first.
fn cmd_trace(args: &trace::TraceArgs, ui: Out) -> Res<()> {
    if args.reps == 0 {
        return Err(Usage("--reps must be at least 1".into()).into());
    }
    if args.threads == Some(0) {
        return Err(Usage("--threads must be at least 1 (omit it for all cores)".into()).into());
    }
    if let Some(d) = &args.dump {
        check_output_dir(d)?;
    }
    let pool = pool(args.threads)?;
    trace::cmd_trace(args, ui, pool).map_err(|e| {
        match e.downcast::<slimkd::format::FormatError>() {
            // Opening the .kd file is the only source of a format error; all
            // but an I/O error leave the file to the caller to name.
            Ok(fe) => match *fe {
                slimkd::format::FormatError::Io { .. } => fe.to_string().into(),
                _ => format!("{}: {fe}", args.file.display()).into(),
            },
            Err(e) => e,
        }
    })
}

/// A thread pool of `threads` workers; `None` or 0: one per core.
pub(crate) fn pool(threads: Option<usize>) -> Res<rayon::ThreadPool> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        b = b.num_threads(n);
    }
    Ok(b.build()?)
}
