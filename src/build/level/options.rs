//! How the level builder runs ([`LevelOptions`]) and what a progress
//! display can read while it runs ([`LevelStatus`]). None of it changes
//! the tree.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64};

/// Nodes with fewer references than this are finished depth-first by
/// default (see [`LevelOptions::small_threshold`]).
pub const DEFAULT_SMALL_THRESHOLD: usize = 2048;

/// The finisher sweeps nodes of at most this many references without
/// events by default (see [`LevelOptions::tiny_threshold`]).
pub const DEFAULT_TINY_THRESHOLD: usize = 48;
/// The most references a node finished depth-first gets from
/// [`LevelOptions::small_threshold_for_budget`].
pub const MAX_BUDGET_SMALL_THRESHOLD: usize = 1 << 16;

/// Bytes of anonymous memory the depth-first finisher holds per reference
/// of the node it works on (its event lists and the children's columns
/// on its stack); the builder keeps this much of `mem_budget` for each
/// thread's finisher. Measured: stk_black_forest under a 16 MiB budget,
/// 2 threads, peak RssAnon 30.8 / 86.4 / 256.2 MiB with thresholds of
/// 2048 / 65536 / 262144 references, 455–460 bytes a reference a thread.
pub const FINISHER_BYTES_PER_REF: u64 = 512;

/// How the level builder runs. None of it changes the tree.
#[derive(Clone, Debug)]
pub struct LevelOptions {
    /// Nodes with fewer references are finished depth-first by the sweep
    /// builder. 0 (or 1) keeps every node breadth-first down to the
    /// leaves; `usize::MAX` builds everything depth-first. Under a budget,
    /// [`LevelOptions::small_threshold_for_budget`] is the better choice.
    pub small_threshold: usize,
    /// Bytes of anonymous memory the build may hold: the finishers'
    /// working memory ([`FINISHER_BYTES_PER_REF`] a reference of
    /// `small_threshold`, a thread) and the level columns kept in RAM;
    /// above it the columns are mapped scratch files. `None` keeps
    /// everything in RAM.
    pub mem_budget: Option<u64>,
    /// Where scratch files go; it must exist when there is a `mem_budget`.
    pub scratch_dir: PathBuf,
    /// At most this many bytes of scratch files at once.
    pub scratch_limit: Option<u64>,
    /// Where a progress display can read the current level.
    pub status: Option<Arc<LevelStatus>>,
    /// How clipped references' events join their child's list.
    pub new_events: NewEvents,
    /// The depth-first finisher sweeps nodes of at most this many
    /// references without events (`tiny`; clamped to 64). 0 sweeps
    /// every node's events.
    pub tiny_threshold: usize,
}

/// How the events of clipped references (created, unsorted) join the
/// inherited events of their child (sorted). Both give the same list;
/// sort + merge is faster on CPU cores (see [`super`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum NewEvents {
    /// Sort the new events, then merge them in from the back of the
    /// child's segment, one comparison per moved event (`merge_back`).
    #[default]
    SortMerge,
    /// The bucket sort of Wu et al.: the child's inherited events are the
    /// buckets. The new events are sorted; each one's bucket is found by a
    /// binary search among the inherited events, and the inherited events
    /// between two buckets move up as one block (`bucket_merge`).
    Bucket,
}

impl LevelOptions {
    /// The small-node threshold for a build under `mem_budget` on
    /// `threads` threads: as many references as let the finishers of all
    /// threads hold a sixteenth of the budget, between
    /// [`DEFAULT_SMALL_THRESHOLD`] and [`MAX_BUDGET_SMALL_THRESHOLD`]
    /// (`DEFAULT_SMALL_THRESHOLD` without a budget). Every level above the
    /// threshold is written to scratch and read back under a budget, so
    /// a larger threshold saves whole levels of scratch traffic: on 12.4 M
    /// triangles under 1 GiB, 9.3 GB of scratch and 36.9 s at 2048, 6.4 GB
    /// and 32.9 s at 32768 (the same tree).
    pub fn small_threshold_for_budget(mem_budget: Option<u64>, threads: usize) -> usize {
        let Some(mem_budget) = mem_budget else {
            return DEFAULT_SMALL_THRESHOLD;
        };
        let per_thread = FINISHER_BYTES_PER_REF * threads.max(1) as u64;
        let fit = usize::try_from(mem_budget / 16 / per_thread).unwrap_or(usize::MAX);
        fit.clamp(DEFAULT_SMALL_THRESHOLD, MAX_BUDGET_SMALL_THRESHOLD)
    }

    /// The part of `mem_budget` the finishers of `threads` threads keep
    /// for nodes of up to `small` (and at most `n`) references; the level
    /// columns get the rest. Nothing without a budget.
    pub(crate) fn finisher_reserve(&self, small: usize, n: usize, threads: usize) -> u64 {
        if self.mem_budget.is_none() {
            return 0;
        }
        let refs = small.min(n) as u64;
        refs.saturating_mul(FINISHER_BYTES_PER_REF)
            .saturating_mul(threads.max(1) as u64)
    }
}

impl Default for LevelOptions {
    fn default() -> Self {
        LevelOptions {
            small_threshold: DEFAULT_SMALL_THRESHOLD,
            mem_budget: None,
            scratch_dir: std::env::temp_dir(),
            scratch_limit: None,
            status: None,
            new_events: NewEvents::default(),
            tiny_threshold: DEFAULT_TINY_THRESHOLD,
        }
    }
}

/// The level being built, for progress displays.
#[derive(Debug, Default)]
pub struct LevelStatus {
    /// The depth being built breadth-first (root = 0).
    pub level: AtomicU32,
    /// Open nodes processed breadth-first at this level.
    pub open_nodes: AtomicU64,
    /// References at this level.
    pub refs: AtomicU64,
    /// Nodes handed to the depth-first finisher so far (below the small
    /// threshold): once no node is open, the finisher is what runs.
    pub small_nodes: AtomicU64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_budget_threshold_grows_with_the_budget_within_its_bounds() {
        let t = LevelOptions::small_threshold_for_budget;
        assert_eq!(t(None, 2), DEFAULT_SMALL_THRESHOLD);
        assert_eq!(t(Some(16 << 20), 2), DEFAULT_SMALL_THRESHOLD);
        assert_eq!(t(Some(0), 2), DEFAULT_SMALL_THRESHOLD);
        // A sixteenth of 256 MiB over two finishers of 512 bytes a reference.
        assert_eq!(t(Some(256 << 20), 2), 16384);
        assert_eq!(t(Some(256 << 20), 1), 32768);
        assert_eq!(t(Some(64 << 30), 2), MAX_BUDGET_SMALL_THRESHOLD);
        assert_eq!(t(Some(256 << 20), 0), t(Some(256 << 20), 1));
    }

    #[test]
    fn the_finishers_reserve_covers_every_thread() {
        let budgeted = LevelOptions {
            mem_budget: Some(1 << 30),
            ..LevelOptions::default()
        };
        let r = |small, n, threads| budgeted.finisher_reserve(small, n, threads);
        assert_eq!(r(2048, 1 << 20, 2), 2 * 2048 * FINISHER_BYTES_PER_REF);
        // Never more references than the scene has.
        assert_eq!(r(usize::MAX, 1000, 1), 1000 * FINISHER_BYTES_PER_REF);
        // Nothing to keep without a budget.
        assert_eq!(
            LevelOptions::default().finisher_reserve(2048, 1 << 20, 2),
            0
        );
    }
}
