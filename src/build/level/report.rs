//! What one build of the level builder did: phase times, counts and
//! memory figures ([`LevelReport`]).

use crate::columns::ScratchStats;

/// Seconds spent in each phase, summed over the levels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Phases {
    /// Root references and the first event sort.
    pub setup_s: f64,
    /// The SAH sweeps and the choice of splits.
    pub sah_s: f64,
    /// Classification, clipping and writing the child references.
    pub classify_clip_s: f64,
    /// Child events: stable partition, sort and merge of new events.
    pub events_s: f64,
    /// Leaf output.
    pub leaves_s: f64,
    /// Small nodes finished depth-first.
    pub small_s: f64,
    /// Pre-order assembly of the tree.
    pub assemble_s: f64,
}

impl Phases {
    /// The whole build's time: the sum of the phases.
    pub fn total(&self) -> f64 {
        self.setup_s
            + self.sah_s
            + self.classify_clip_s
            + self.events_s
            + self.leaves_s
            + self.small_s
            + self.assemble_s
    }
}

/// What one build did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LevelReport {
    /// Where the build's time went.
    pub phases: Phases,
    /// Levels processed breadth-first (a level cut into groups counts
    /// once a group).
    pub levels: u32,
    /// Groups of a level in scratch files built apart, in RAM where they
    /// fit (`LevelBuilder::levels`).
    pub groups: u64,
    /// Nodes decided breadth-first (inner nodes and leaves).
    pub bfs_nodes: u64,
    /// Subtrees finished depth-first.
    pub small_nodes: u64,
    /// Nodes of fewer references than this were finished depth-first
    /// (the options' threshold, or a cut's).
    pub small_threshold: u64,
    /// Bytes of the budget kept for the finishers
    /// ([`super::FINISHER_BYTES_PER_REF`] a reference a thread).
    pub finisher_reserve_bytes: u64,
    /// The most references of one level.
    pub max_level_refs: u64,
    /// The most nodes processed breadth-first in one level.
    pub max_open_nodes: u64,
    /// Straddlers clipped breadth-first.
    pub clipped: u64,
    /// The largest `RssAnon` seen (sampled from `/proc/self/status` after
    /// every phase of every level; 0 where there is no such file). It
    /// includes what the process held before the build: see
    /// `start_rss_anon_bytes`.
    pub peak_rss_anon_bytes: u64,
    /// `RssAnon` when the build started (the scene, and whatever the
    /// process kept from loading it).
    pub start_rss_anon_bytes: u64,
    /// The largest `RssFile` seen, sampled likewise (mapped scratch files
    /// count here, as does the mapped executable).
    pub peak_rss_file_bytes: u64,
    /// Bytes of RAM columns and scratch files.
    pub scratch: ScratchStats,
    /// Processor time (user and system, all threads) the process spent
    /// during the build, from `/proc/self/stat` (0 where it cannot be
    /// read; the kernel counts it in ticks of 10 ms). Divided by the
    /// build's wall time, it is the number of cores kept busy on average:
    /// how far a build on more threads is from perfect scaling.
    pub cpu_s: f64,
}
