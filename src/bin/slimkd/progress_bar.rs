//! Long jobs on a worker thread while this thread draws their progress bar.
//!
//! The bar is `indicatif`'s: it draws only on a terminal, fits the
//! terminal's width (the message is cut, never wrapped), and estimates the
//! time left; what is ours is when it appears and what it counts.

use crate::CmdResult;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use slimkd::progress::Progress;
use std::sync::mpsc::{self, RecvTimeoutError};
use std::time::{Duration, Instant};

/// How long a job runs before its bar appears (shorter jobs show none).
const BAR_DELAY: Duration = Duration::from_secs(1);

/// The bar's positions: per mille of the job.
const BAR_LEN: u64 = 1000;

/// The bar of a job that started at `start`: its clock counts from the
/// start, not from when the bar appears, and the message is cut to the
/// width the terminal leaves it.
fn new_bar(label: &str, start: Instant, target: ProgressDrawTarget) -> ProgressBar {
    let bar = ProgressBar::with_draw_target(Some(BAR_LEN), target)
        .with_style(
            ProgressStyle::with_template(
                "{prefix} {bar:20} {percent:>3}% {elapsed:>4} ETA {eta:<4} {wide_msg}",
            )
            .expect("the template is valid"),
        )
        .with_prefix(label.to_string())
        .with_elapsed(start.elapsed());
    // A time left before any progress is a guess; indicatif shows 0s.
    bar.set_position(0);
    bar
}

/// Where long jobs tell what they are doing: the worker's side of
/// [`with_bar_lines`].
#[derive(Clone)]
pub(crate) struct Lines(mpsc::Sender<String>);

impl Lines {
    /// A line printed above the bar (on standard error).
    pub(crate) fn line(&self, line: String) {
        // The receiver lives until the worker is joined.
        let _ = self.0.send(line);
    }
}

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
    work: impl FnOnce() -> CmdResult<T> + Send,
) -> CmdResult<T> {
    with_bar_lines(quiet, label, progress, message, |_| work())
}

/// [`with_bar_lines`] for a job of announced steps (`report`, `sweep`):
/// one bar over all of them; each line `work` logs goes above it with the
/// seconds since the start, and the last one is the bar's message.
pub(crate) fn with_step_log<T: Send>(
    quiet: bool,
    label: &str,
    work: impl FnOnce(&Progress, &mut dyn FnMut(&str)) -> CmdResult<T> + Send,
) -> CmdResult<T> {
    let start = Instant::now();
    let progress = Progress::default();
    let current = std::sync::Mutex::new(String::new());
    let message = || current.lock().map(|m| m.clone()).unwrap_or_default();
    with_bar_lines(quiet, label, &progress, &message, |lines| {
        work(&progress, &mut |line| {
            if let Ok(mut m) = current.lock() {
                line.clone_into(&mut m);
            }
            lines.line(format!("[{:7.1} s] {line}", start.elapsed().as_secs_f64()));
        })
    })
}

/// [`with_bar`] for a job that also prints lines: what `work` sends to its
/// [`Lines`] goes to standard error, above the bar once it is drawn (and
/// nowhere if `quiet`).
pub(crate) fn with_bar_lines<T: Send>(
    quiet: bool,
    label: &str,
    progress: &Progress,
    message: &(dyn Fn() -> String + Sync),
    work: impl FnOnce(&Lines) -> CmdResult<T> + Send,
) -> CmdResult<T> {
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
        let (done, result) = mpsc::channel::<CmdResult<T>>();
        let (line_tx, line_rx) = mpsc::channel::<String>();
        if !crate::room_for_threads(1) {
            return Err(
                format!("{label}: cannot start a worker thread (not enough memory)").into(),
            );
        }
        // The worker says when its pool runs: until then this thread
        // allocates nothing (see `crate::pool`).
        let (up_tx, up_rx) = mpsc::channel::<()>();
        let worker = std::thread::Builder::new().spawn_scoped(s, move || {
            let lines = Lines(line_tx);
            let run = || -> CmdResult<T> {
                let pool = crate::pool(Some(pool_threads));
                let _ = up_tx.send(());
                let pool = pool.map_err(|e| format!("{label}: {e}"))?;
                pool.install(|| work(&lines))
            };
            // The receiver waits until this is sent (or the worker panics).
            let _ = done.send(run());
        });
        let worker = worker.map_err(|e| {
            format!(
                "{label}: cannot start a worker thread (not enough memory or too many threads): {e}"
            )
        })?;
        let _ = up_rx.recv();
        let mut bar: Option<ProgressBar> = None;
        let print = |bar: &Option<ProgressBar>, line: String| match bar {
            Some(b) if !b.is_hidden() => b.println(line),
            _ => eprintln!("{line}"),
        };
        let got = loop {
            let got = match result.recv_timeout(Duration::from_millis(50)) {
                Ok(got) => Some(Some(got)),
                Err(RecvTimeoutError::Disconnected) => Some(None),
                Err(RecvTimeoutError::Timeout) => None,
            };
            for line in line_rx.try_iter() {
                if !quiet {
                    print(&bar, line);
                }
            }
            if let Some(got) = got {
                break got;
            }
            if bar.is_none() && !quiet && start.elapsed() > BAR_DELAY {
                bar = Some(new_bar(label, start, ProgressDrawTarget::stderr()));
            }
            if let Some(b) = &bar {
                b.set_position((progress.fraction() * BAR_LEN as f64) as u64);
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

/// A count in about three significant figures with an SI suffix
/// (`12.3M`), so that a bar's message stays short.
pub(crate) fn si(n: u64) -> String {
    let (x, suffix) = match n {
        0..1_000 => return n.to_string(),
        1_000..1_000_000 => (n as f64 / 1e3, "k"),
        1_000_000..1_000_000_000 => (n as f64 / 1e6, "M"),
        _ => (n as f64 / 1e9, "G"),
    };
    let decimals = if x < 10.0 {
        2
    } else if x < 100.0 {
        1
    } else {
        0
    };
    format!("{x:.decimals$}{suffix}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use indicatif::TermLike;
    use std::sync::{Arc, Mutex};

    /// An 80-column terminal that keeps what is written on its lines.
    #[derive(Debug, Default, Clone)]
    struct Screen(Arc<Mutex<Vec<String>>>);

    impl TermLike for Screen {
        fn width(&self) -> u16 {
            80
        }
        fn move_cursor_up(&self, _: usize) -> std::io::Result<()> {
            Ok(())
        }
        fn move_cursor_down(&self, _: usize) -> std::io::Result<()> {
            Ok(())
        }
        fn move_cursor_right(&self, _: usize) -> std::io::Result<()> {
            Ok(())
        }
        fn move_cursor_left(&self, _: usize) -> std::io::Result<()> {
            Ok(())
        }
        fn write_line(&self, s: &str) -> std::io::Result<()> {
            self.0.lock().unwrap().push(s.to_string());
            Ok(())
        }
        fn write_str(&self, s: &str) -> std::io::Result<()> {
            self.write_line(s)
        }
        fn clear_line(&self) -> std::io::Result<()> {
            Ok(())
        }
        fn flush(&self) -> std::io::Result<()> {
            Ok(())
        }
    }

    /// The bar's clock runs from the job's start (here 7 s before the bar
    /// appears), it shows the time left, and its line fits 80 columns
    /// however long the message.
    #[test]
    fn bar_counts_from_the_start_shows_eta_and_fits_80_columns() {
        let screen = Screen::default();
        let start = Instant::now() - Duration::from_secs(7);
        let bar = new_bar(
            "building",
            start,
            ProgressDrawTarget::term_like(Box::new(screen.clone())),
        );
        bar.set_position(500);
        bar.set_message("level 9: 12.3k open nodes, 45.6M refs; ".repeat(5));
        bar.force_draw();
        let lines = screen.0.lock().unwrap().clone();
        let line = lines
            .iter()
            .rev()
            .find(|l| l.contains("building"))
            .expect("the bar was drawn");
        // The template has no styles, so the line is plain text.
        let text = line.trim_end();
        assert!(
            text.chars().count() <= 80,
            "{} columns: {text}",
            text.chars().count()
        );
        assert!(text.contains("ETA"), "{text}");
        assert!(text.contains("7s"), "the clock starts with the job: {text}");
        assert!(text.contains("level 9"), "{text}");
    }

    #[test]
    fn si_counts_are_short() {
        assert_eq!(si(999), "999");
        assert_eq!(si(12_345), "12.3k");
        assert_eq!(si(45_600_000), "45.6M");
        assert_eq!(si(1_234_567_890), "1.23G");
    }
}
