//! What the process can read about itself: its processor time and
//! resident memory from `/proc` (the level builder's report samples them;
//! the CLI prints them; off Linux they read as unknown or zero), and the
//! wall-clock time of a phase ([`lap`], for the builder's and the slim
//! pass's phase times).

use std::time::Instant;

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
