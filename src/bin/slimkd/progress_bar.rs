//! Long jobs on a worker thread while this thread draws their progress bar.

use crate::*;
use indicatif::{ProgressBar, ProgressStyle};
use slimkd::progress::Progress;
use std::time::{Duration, Instant};

/// Runs `work` on a scoped worker thread, in a rayon pool the size of the
/// caller's (the worker is outside the caller's pool), while this thread
/// draws a progress bar of `progress` with `label` and `message()` once the
/// work has run for a second, unless `quiet`. (indicatif draws nothing
/// when standard error is not a terminal.)
pub(crate) fn with_bar<T: Send>(
    quiet: bool,
    label: &str,
    progress: &Progress,
    message: &(dyn Fn() -> String + Sync),
    work: impl FnOnce() -> Res<T> + Send,
) -> Res<T> {
    let start = Instant::now();
    // Inside a pool, its size; outside, rayon's default, without starting
    // the global pool (which panics where it cannot start its threads).
    let pool_threads = match rayon::current_thread_index() {
        Some(_) => rayon::current_num_threads(),
        None => 0,
    };
    std::thread::scope(|s| {
        // The worker sends its result, so that this thread wakes the moment
        // it is done (a plain sleep between polls added up to a poll's
        // interval to every timed build).
        let (done, result) = std::sync::mpsc::channel::<Res<T>>();
        let worker = std::thread::Builder::new().spawn_scoped(s, move || {
            let run = || -> Res<T> {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(pool_threads)
                    .build()
                    .map_err(|e| format!("{label}: cannot start the worker threads: {e}"))?;
                pool.install(work)
            };
            // The receiver waits until this is sent (or the worker panics).
            let _ = done.send(run());
        });
        let worker = worker.map_err(|e| format!("{label}: cannot start a worker thread: {e}"))?;
        let mut bar: Option<ProgressBar> = None;
        let got = loop {
            match result.recv_timeout(Duration::from_millis(50)) {
                Ok(got) => break Some(got),
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break None,
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
            }
            if bar.is_none() && !quiet && start.elapsed() > Duration::from_secs(1) {
                let b = ProgressBar::new(1000);
                b.set_style(
                    ProgressStyle::with_template(&format!(
                        "{label} {{bar:40}} {{percent:>3}}% {{elapsed_precise}} {{msg}}"
                    ))
                    .expect("the template is valid"),
                );
                bar = Some(b);
            }
            if let Some(b) = &bar {
                b.set_position((progress.fraction() * 1000.0) as u64);
                b.set_message(message());
            }
        };
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        match (got, worker.join()) {
            (Some(got), Ok(())) => got,
            _ => Err(format!("{label}: a worker panicked").into()),
        }
    })
}
