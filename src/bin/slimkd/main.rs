//! The `slimkd` command line: build a kd-tree for a scene, store it as a
//! `.kd` file, inspect and verify files, render, and report figures.
//! Without arguments it runs the main job on the embedded default scene.
//! Exit codes: 0 success, 1 failure (bad input, invalid file, I/O), 2 bad
//! usage.

mod args;
mod build;
mod info;
mod progress_bar;
mod render;
mod report;
mod trace;

use clap::Parser;
use slimkd::build::level;
use std::path::PathBuf;
use std::process::ExitCode;

use args::*;
use build::*;
use info::*;
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
    let cli = Cli::parse();
    let result = match cli.command {
        None => main_job(),
        Some(Command::Build {
            scene,
            build,
            output,
            reorder,
            json,
        }) => cmd_build(&scene, &build, output.as_deref(), reorder, json),
        Some(Command::Render(args)) => cmd_render(&args),
        Some(Command::Info { file, json }) => cmd_info(&file, json),
        Some(Command::Verify { file }) => cmd_verify(&file),
        Some(Command::Convert { scene, output }) => cmd_convert(&scene, &output),
        Some(Command::Report(args)) => cmd_report(&args),
        Some(Command::Trace(args)) => pool(args.threads).and_then(|p| trace::cmd_trace(&args, p)),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("slimkd: error: {e}");
            ExitCode::FAILURE
        }
    }
}

pub(crate) fn pool(threads: Option<usize>) -> Res<rayon::ThreadPool> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        if n == 0 {
            return Err("--threads must be at least 1".into());
        }
        b = b.num_threads(n);
    }
    Ok(b.build()?)
}

/// `slimkd` without arguments: the embedded scene, its first view, an image.
fn main_job() -> Res<()> {
    let args = RenderArgs {
        scene: PathBuf::from(DEFAULT_ARG),
        build: BuildArgs {
            builder: BuilderArg::Level,
            mem_budget: None,
            scratch: None,
            new_events: NewEventsArg::Merge,
            tiny: level::DEFAULT_TINY_THRESHOLD as u8,
            threads: None,
            max_depth: None,
            preset: PresetArg::Std,
            tau_occu: None,
            tau_freq: None,
            max_t2rn: None,
            hoist_rule: HoistRuleArg::Bytes,
        },
        eye: None,
        at: None,
        up: None,
        fov: None,
        size: (1024, 1024),
        views: None,
        view: Some("1".into()),
        mode: ModeArg::Packet,
        reps: 3,
        output: Some(PathBuf::from("slimkd.png")),
        dump_t: None,
        shading: ShadingArg::EyeLight,
        json: false,
    };
    cmd_render(&args)
}
