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
/// How the level builder runs. None of it changes the tree.
#[derive(Clone, Debug)]
pub struct LevelOptions {
    /// Nodes with fewer references are finished depth-first by the sweep
    /// builder. 0 (or 1) keeps every node breadth-first down to the
    /// leaves; `usize::MAX` builds everything depth-first.
    pub small_threshold: usize,
    /// Bytes of level columns kept in RAM; above it they are mapped
    /// scratch files. `u64::MAX` keeps everything in RAM.
    pub mem_budget: u64,
    /// Where scratch files go; it must exist when `mem_budget` is finite.
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

impl Default for LevelOptions {
    fn default() -> Self {
        LevelOptions {
            small_threshold: DEFAULT_SMALL_THRESHOLD,
            mem_budget: u64::MAX,
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
