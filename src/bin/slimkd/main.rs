//! The `slimkd` command line: build a kd-tree for a scene, store it as a
//! `.kd` file, inspect and verify files, render, and report figures.
//! Without arguments it runs the main job on the embedded default scene.
//! Exit codes: 0 success, 1 failure (bad input, invalid file, I/O), 2 bad
//! usage.

mod args;
mod build;
mod calibrate;
mod cells;
mod info;
mod json;
mod kd_file;
mod lab;
mod main_job;
mod progress_bar;
mod render;
mod report;
mod sweep;
mod trace;

use crate::args::{BuildArgs, Cli, Command, OutputFlags, Usage, check_output_dir};
use crate::build::cmd_build;
use crate::info::{cmd_convert, cmd_info, cmd_verify};
use crate::render::cmd_render;
use crate::report::cmd_report;
use clap::parser::ValueSource;
use clap::{Args, CommandFactory, FromArgMatches};
use std::process::ExitCode;

/// The embedded default scene: nexuiz_dieselpower (see scenes/README.md).
pub(crate) const DEFAULT_SCENE_NAME: &str = "nexuiz_dieselpower.obj";
pub(crate) const DEFAULT_SCENE: &[u8] = include_bytes!("../../../scenes/nexuiz_dieselpower.obj");
pub(crate) const DEFAULT_VIEWS: &str = include_str!("../../../scenes/views.txt");
/// The name that selects the embedded scene on the command line.
pub(crate) const DEFAULT_ARG: &str = "default";

/// What a command returns: its error, if any, is printed by `main`.
pub(crate) type CmdResult<T> = Result<T, Box<dyn std::error::Error + Send + Sync>>;

/// The views of a views file (errors name it), or the embedded ones.
pub(crate) fn read_views(file: Option<&std::path::Path>) -> CmdResult<Vec<slimkd::render::View>> {
    let Some(file) = file else {
        return Ok(slimkd::render::parse_views(DEFAULT_VIEWS)?);
    };
    let mut text = String::new();
    slimkd::fsio::open_regular(file)
        .and_then(|mut f| std::io::Read::read_to_string(&mut f, &mut text))
        .map_err(|e| format!("{}: {e}", file.display()))?;
    Ok(slimkd::render::parse_views(&text).map_err(|e| format!("{}: {e}", file.display()))?)
}

#[cfg(target_os = "linux")]
#[global_allocator]
static ALLOCATOR: ExitOnOom = ExitOnOom;

/// The system allocator, except that an allocation that fails where no
/// caller handles the failure ([`slimkd::sys::try_reserve`] does) ends the
/// process with exit status 1 and a message, instead of Rust's abort
/// (`SIGABRT`, status 134). Output files are unaffected: they are renamed
/// into place only when complete.
#[cfg(target_os = "linux")]
struct ExitOnOom;

// SAFETY: every method hands its arguments to `System` unchanged and
// returns what `System` returned; a null result either goes back to the
// caller (who handles it) or ends the process.
#[cfg(target_os = "linux")]
unsafe impl std::alloc::GlobalAlloc for ExitOnOom {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `layout` is `System`'s.
        checked(unsafe { std::alloc::System.alloc(layout) }, layout.size())
    }
    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: as for `alloc`.
        checked(
            unsafe { std::alloc::System.alloc_zeroed(layout) },
            layout.size(),
        )
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new_size: usize) -> *mut u8 {
        // SAFETY: `ptr` and `layout` come from this allocator, which is
        // `System`'s; the caller's contract is `System`'s.
        checked(
            unsafe { std::alloc::System.realloc(ptr, layout, new_size) },
            new_size,
        )
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: `ptr` and `layout` come from this allocator.
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }
}

/// `ptr`, unless it is null where the failure is not handled: then the
/// process ends, with a message written without allocating.
#[cfg(target_os = "linux")]
fn checked(ptr: *mut u8, size: usize) -> *mut u8 {
    if !ptr.is_null() || slimkd::sys::allocation_failure_is_handled() {
        return ptr;
    }
    let mut msg = [0u8; 200];
    let mut n = 0;
    let mut put = |bytes: &[u8]| {
        let k = bytes.len().min(msg.len() - n);
        msg[n..n + k].copy_from_slice(&bytes[..k]);
        n += k;
    };
    put(b"slimkd: error: out of memory: an allocation of ");
    let mut digits = [0u8; 20];
    let mut d = digits.len();
    let mut v = size;
    loop {
        d -= 1;
        digits[d] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    put(&digits[d..]);
    put(b" bytes failed (allow more memory, or give a smaller --mem-budget)\n");
    // SAFETY: `msg[..n]` is initialised memory that outlives the call;
    // `_exit` ends the process without running anything that allocates.
    unsafe {
        libc::write(2, msg.as_ptr().cast(), n);
        libc::_exit(1)
    }
}

/// Under an address-space limit (`ulimit -v`), every thread shares the
/// main `malloc` arena. glibc otherwise reserves 64 MiB of address space
/// for each thread's arena; where the limit refuses that, the thread's
/// every allocation falls back to an `mmap` of its own (many times slower)
/// and, with the space gone, glibc aborts in thread start-up.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn share_malloc_arena_under_a_limit() {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: `getrlimit` writes the struct it is given; `mallopt` is
    // called at start-up, before any thread is spawned.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_AS, &mut limit) == 0
            && limit.rlim_cur != libc::RLIM_INFINITY
        {
            libc::mallopt(libc::M_ARENA_MAX, 1);
        }
    }
}

fn main() -> ExitCode {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    share_malloc_arena_under_a_limit();
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
    kd_file::NO_MMAP.store(cli.no_mmap, std::sync::atomic::Ordering::Relaxed);
    let result = match cli.command {
        // In a pool of its own: rayon's global pool panics where it cannot
        // start its threads, a pool built here is an error.
        None => pool(None).and_then(|p| p.install(|| main_job::main_job(ui))),
        Some(Command::Build {
            scene,
            build,
            output,
            reorder,
            cells,
        }) => match cells.cells {
            Some(k) => {
                cells::cmd_build_cells(&scene, &build, output.as_deref(), reorder, k, &cells, ui)
            }
            None => cmd_build(&scene, &build, output.as_deref(), reorder, ui),
        },
        Some(Command::BuildCell {
            cell,
            output,
            threads,
        }) => cells::cmd_build_cell(&cell, output.as_deref(), threads, ui),
        Some(Command::Stitch {
            scene,
            cells_dir,
            output,
            reorder,
            threads,
        }) => cells::cmd_stitch(&scene, &cells_dir, &output, reorder, threads, ui),
        Some(Command::Render(args)) => cmd_render(&args, ui),
        Some(Command::Info { file }) => cmd_info(&file, ui),
        Some(Command::Verify { file }) => cmd_verify(&file, ui),
        Some(Command::Convert { scene, output }) => cmd_convert(&scene, &output, ui),
        Some(Command::Report(args)) => cmd_report(&args, ui),
        Some(Command::Trace(args)) => cmd_trace(&args, ui),
        Some(Command::Calibrate(args)) => calibrate::cmd_calibrate(&args, ui),
        Some(Command::Sweep(args)) => sweep::cmd_sweep(&args, ui),
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
fn cmd_trace(args: &args::TraceArgs, ui: OutputFlags) -> CmdResult<()> {
    if args.reps == 0 {
        return Err(Usage("--reps must be at least 1".into()).into());
    }
    if args.threads == Some(0) {
        return Err(Usage("--threads must be at least 1 (omit it for all cores)".into()).into());
    }
    if let Some(d) = &args.dump {
        check_output_dir(d)?;
    }
    kd_file::expect_kd(&args.file, "trace")?;
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

/// Address space a worker thread is to find free when it starts: its
/// stack (Rust's default, 2 MiB), its signal stack, and what it and its
/// siblings allocate while they start (a pool's first worker runs while
/// the next one's stack is mapped). With 3 MiB, `ulimit -v` still found
/// limits at which a worker's signal stack did not fit.
const THREAD_ROOM: usize = 8 << 20;

/// Whether `n` threads can start now: their room ([`THREAD_ROOM`] each)
/// reserved and given back. A caller that starts threads waits until they
/// run before it allocates more (see [`pool`]).
pub(crate) fn room_for_threads(n: usize) -> bool {
    Vec::<u8>::new()
        .try_reserve_exact(n.saturating_mul(THREAD_ROOM))
        .is_ok()
}

/// A thread pool of `threads` workers; `None` or 0: one per core.
pub(crate) fn pool(threads: Option<usize>) -> CmdResult<rayon::ThreadPool> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        b = b.num_threads(n);
    }
    // A thread whose stack maps but whose signal stack does not aborts
    // the process in Rust's runtime, before any error can be reported
    // (seen under `ulimit -v` at 20 MB): the room for every thread's
    // stack and signal stack is reserved and given back first, so that
    // too little memory is a clear error here, and the pool is returned
    // once every worker runs, so that this thread's next allocations do
    // not take that room while they start.
    let n = match threads {
        Some(k) if k > 0 => k,
        _ => std::thread::available_parallelism().map_or(1, |k| k.get()),
    };
    if !room_for_threads(n) {
        return Err(format!(
            "cannot start {n} worker threads: not enough memory for their stacks ({} MiB)",
            (n * THREAD_ROOM) >> 20
        )
        .into());
    }
    let pool = b.build().map_err(|e| {
        format!("cannot start the worker threads (not enough memory or too many threads): {e}")
    })?;
    pool.broadcast(|_| ());
    Ok(pool)
}
