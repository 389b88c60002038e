//! What the process can read about itself: its processor time and
//! resident memory from `/proc` (the level builder's report samples them;
//! the CLI prints them; off Linux they read as unknown or zero), and the
//! wall-clock time of a phase ([`lap`], for the builder's and the slim
//! pass's phase times), and [`try_reserve`], the large allocations that
//! fail with an error instead of aborting.

use std::cell::Cell;
use std::time::Instant;

thread_local! {
    /// How many [`try_reserve`] calls this thread is inside: while it is
    /// above 0, a failed allocation is an error its caller handles.
    static FALLIBLE: Cell<u32> = const { Cell::new(0) };
}

/// Whether an allocation that fails now, on this thread, is one that its
/// caller handles ([`try_reserve`]). A global allocator that ends the
/// process on any other failed allocation (the CLI's) asks this first; it
/// reads a thread-local without a destructor, so it allocates nothing.
pub fn allocation_failure_is_handled() -> bool {
    FALLIBLE.try_with(|f| f.get() > 0).unwrap_or(false)
}

/// A large allocation that did not fit: what it was for and its size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "out of memory: {what} ({:.1} MiB) does not fit (a smaller --mem-budget, \
     e.g. --mem-budget 64M, keeps the builder's columns in scratch files)",
    *bytes as f64 / (1 << 20) as f64
)]
pub struct OutOfMemory {
    pub what: &'static str,
    pub bytes: u64,
}

/// Reserves room for `additional` more elements of `v` exactly, or says
/// that `what` did not fit.
pub fn try_reserve<T>(
    v: &mut Vec<T>,
    additional: usize,
    what: &'static str,
) -> Result<(), OutOfMemory> {
    FALLIBLE.with(|f| f.set(f.get() + 1));
    let result = v.try_reserve_exact(additional);
    FALLIBLE.with(|f| f.set(f.get() - 1));
    result.map_err(|_| OutOfMemory {
        what,
        bytes: (additional as u64).saturating_mul(std::mem::size_of::<T>() as u64),
    })
}

/// The seconds since `clock`, which is moved on to now: the time of the
/// phase that just ended.
pub fn lap(clock: &mut Instant) -> f64 {
    let now = Instant::now();
    let s = now.duration_since(*clock).as_secs_f64();
    *clock = now;
    s
}

/// This process's processor time so far (user and system, every thread),
/// in seconds, from `/proc/self/stat`; `None` where it cannot be read.
pub fn cpu_seconds() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name (field 2) is in parentheses and may hold spaces, so
    // the fields are counted from the last `)`: there `state` is field 3,
    // `utime` field 14 and `stime` field 15, in clock ticks (`USER_HZ`,
    // 100 a second on Linux whatever the kernel's own tick rate).
    let rest = &text[text.rfind(')')? + 1..];
    let mut fields = rest.split_whitespace().skip(11);
    let utime: u64 = fields.next()?.parse().ok()?;
    let stime: u64 = fields.next()?.parse().ok()?;
    Some((utime + stime) as f64 / 100.0)
}

/// This process's processor time so far (user and system, every thread),
/// in seconds, at the clock's resolution (`CLOCK_PROCESS_CPUTIME_ID`,
/// nanoseconds; [`cpu_seconds`] counts in 10 ms ticks); `None` where
/// there is no such clock.
pub fn process_cpu_seconds() -> Option<f64> {
    #[cfg(target_os = "linux")]
    {
        let mut ts = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `clock_gettime` writes the `timespec` it is given, which
        // lives for the call.
        let rc = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
        (rc == 0).then_some(ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9)
    }
    #[cfg(not(target_os = "linux"))]
    {
        None
    }
}

/// This process's `RssAnon` and `RssFile` in bytes, from
/// `/proc/self/status` (zeros where it cannot be read).
pub fn rss() -> (u64, u64) {
    let Ok(text) = std::fs::read_to_string("/proc/self/status") else {
        return (0, 0);
    };
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .map_or(0, |kb| kb * 1024)
    };
    (field("RssAnon:"), field("RssFile:"))
}

/// Returns the allocator's free memory to the system (glibc's
/// `malloc_trim`; nothing elsewhere). The level builder calls it between
/// the levels of a budgeted build: glibc raises its mmap threshold after a
/// large block is freed, so the next columns of a few MiB come from its
/// heap, and the pages of the freed ones stay resident (12.4 M triangles
/// under 1 GiB, groups of a level built apart: 196 MiB over the budget
/// without it).
pub fn release_free_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` takes no pointer and may be called at any
    // time; it only hands free pages of the allocator back.
    unsafe {
        libc::malloc_trim(0);
    }
}
