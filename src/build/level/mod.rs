//! The breadth-first level builder: Wu, Zhao & Liu, "SAH KD-Tree
//! Construction on GPU" (HPG 2011), on CPU cores with rayon.
//!
//! Consumes a scene, the [`BuildConfig`] and [`LevelOptions`]. Produces the
//! standard tree as a [`TreeIr`] **equal** to [`super::sweep::build`]'s (the
//! same splits, the same leaves, the same order; see [`super`] for the one
//! definition every builder follows) and a [`LevelReport`] with per-phase
//! times and memory figures. The tree does not depend on the number of
//! threads: every decision is a function of the data, cut into pieces
//! whose bounds depend on the data alone, and every reduction (the best
//! split of a node) is over a total order.
//!
//! **One level** is the open nodes at one depth, stored as flat columns
//! ([`crate::columns`]: in RAM below `mem_budget`, in mapped scratch files
//! above it): each node's references (triangle id and clipped box,
//! ascending by triangle) and, per axis, its events sorted as in the sweep
//! builder (`event`). One call of `Builder::level` turns level `d`
//! into level `d + 1` (the paper's §4, Figure 2):
//!
//! 1. **Small nodes** (fewer than `small_threshold` references) are handed
//!    to the depth-first builder (`dfs`: the sweep builder's algorithm
//!    on the same flat encoding, without an allocation per node), in
//!    parallel across nodes (the paper's "small node stage", §4.3, which
//!    there uses a different algorithm; here it is the same SAH, so the
//!    tree is unchanged). This runs alongside steps 2–5 (`rayon::join`):
//!    both only read level `d`, and work stealing lets each fill the
//!    other's idle time (the passes have sequential stretches, and a
//!    level's last small subtrees would otherwise finish on one core).
//!    The phase times of the report are each phase's own wall time, so
//!    with more than one thread they overlap. Within the finisher, nodes
//!    of at most `tiny_threshold` references find their best split
//!    without events (`tiny`: every candidate plane counted and priced
//!    16 at a time in vector lanes) and get no event lists from their
//!    parent.
//! 2. **SAH**: every axis's events are cut into pieces (`pieces`) and
//!    swept in parallel; a piece that continues a node starts from counts
//!    carried over the node's earlier pieces (a segmented prefix count).
//!    Every plane that can win is priced by [`sah::split_cost`] and the
//!    best kept by [`Split::keep_best`], whose total order makes the
//!    reduction over pieces independent of their order. **Not in the
//!    paper:** a plane whose cost provably exceeds the best so far is not
//!    priced (`Pricer`); and a node at the depth limit is not swept, since
//!    [`sah::is_leaf`] makes it a leaf whatever its best split.
//! 3. **Leaves** ([`sah::is_leaf`]) stream out: their triangle lists are
//!    appended to the leaf list at once.
//! 4. **Classify and clip**: references go left, right or both
//!    ([`classify`]); straddlers are clipped to each child ([`clip_straddler`],
//!    perfect splits). Prefix counts place each child's references.
//! 5. **Child events**: inherited events keep their order through a stable
//!    parallel partition, with their reference renumbered; the events of
//!    clipped references are sorted per child and merged in (sort + merge,
//!    in place from the back of the child's segment, moving long runs of
//!    inherited events as blocks found by a galloping search). Wu et al.'s
//!    bucket sort, with the inherited events as buckets, gives the same
//!    lists ([`NewEvents::Bucket`], `slimkd build --new-events bucket`)
//!    but is slower on CPU cores: a binary search per new event and a
//!    block move per bucket cost more than one predictable comparison per
//!    moved event (stk_black_forest, 1 thread: events phase 1.27 s merge
//!    against 1.59 s bucket). Sort + merge is the default.
//!
//! The tree is assembled in pre-order at the end (`assemble`), from the
//! breadth-first records, leaf lists and depth-first subtrees.
//!
//! **Where the time goes.** On stk_black_forest (1.09 M triangles) about
//! 75% of a 1-thread build is the depth-first finishing of small nodes:
//! millions of nodes of about a dozen references, so per-node constants
//! count as much as per-event work. Hence the finisher's design (`dfs`, `tiny`): no
//! allocation per node, no events for tiny nodes, empty-space cuts worked
//! on in place. The small-node threshold (2048) lies in a broad optimum:
//! 1024 to 32768 build within the noise of each other. The measurements
//! behind these choices, and the alternatives measured and not taken, are
//! in `docs/perf-notes.md`.
//!
//! **Memory.** The level columns obey `mem_budget`. The breadth-first
//! records and leaf lists stay in RAM until the tree is assembled, and so
//! do the depth-first subtrees, packed (12 bytes a node) in one stream per
//! level that the assembly reads front to back, unmapping each chunk once
//! read (`assemble`): the subtrees are never held twice, and never as
//! many small allocations that the allocator would keep after they are
//! freed.

mod assemble;
mod dfs;
mod event;
mod pieces;
mod tiny;

use self::assemble::{Rec, SubStore, SubStream, assemble};
use self::dfs::Finisher;
use self::event::{
    Box6, MAX_REFS, ev_key, ev_kind, ev_ref, events_of, key_pos, n_events, push_events, to_aabb,
    to_box, with_ref,
};
use self::pieces::{Piece, carries, pieces};
use super::sah::{self, PlaneCounts, Split};
use super::{BuildConfig, Placement, Progress, TriRef, classify, clip_straddler, root_cell};
use crate::columns::{Column, ColumnsError, ScatterSlice, Scratch, ScratchConfig, ScratchStats};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::{TreeIr, TriId};
use rayon::prelude::*;
use std::ops::Add;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::time::Instant;

/// Nodes with fewer references than this are finished depth-first by
/// default (see [`LevelOptions::small_threshold`]).
pub const DEFAULT_SMALL_THRESHOLD: usize = 2048;

/// The finisher sweeps nodes of at most this many references without
/// events by default (see [`LevelOptions::tiny_threshold`]).
pub const DEFAULT_TINY_THRESHOLD: usize = 48;

/// Elements per work piece: large enough that a piece's fixed costs vanish,
/// small enough that the top levels split into many pieces per thread.
const PIECE: usize = 1 << 14;

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
/// sort + merge is faster on CPU cores (see the module docs).
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

impl NewEvents {
    /// `seg` holds sorted events followed by `new.len()` free slots; puts
    /// the sorted `new` in place.
    #[inline]
    pub(crate) fn merge(self, seg: &mut [u64], new: &[u64]) {
        match self {
            NewEvents::SortMerge => merge_back(seg, new),
            NewEvents::Bucket => bucket_merge(seg, new),
        }
    }
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
    pub level: AtomicU32,
    /// Open nodes processed breadth-first at this level.
    pub open_nodes: AtomicU64,
    /// References at this level.
    pub refs: AtomicU64,
}

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
    pub phases: Phases,
    /// Levels processed breadth-first.
    pub levels: u32,
    /// Nodes decided breadth-first (inner nodes and leaves).
    pub bfs_nodes: u64,
    /// Subtrees finished depth-first.
    pub small_nodes: u64,
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

/// Builds the standard tree breadth-first; see the module docs.
pub fn build(
    scene: &TriangleColumns,
    config: &BuildConfig,
    progress: Option<&Progress>,
    options: &LevelOptions,
) -> Result<(TreeIr, LevelReport), ColumnsError> {
    let scratch = Scratch::new(ScratchConfig {
        mem_budget: options.mem_budget,
        dir: options.scratch_dir.clone(),
        scratch_limit: options.scratch_limit,
    })?;
    let start_rss = rss();
    let start_cpu = cpu_seconds();
    let mut b = Builder {
        scene,
        config,
        progress,
        options,
        scratch: &scratch,
        depth_limit: config.sah.depth_limit(scene.len()),
        recs: vec![Rec::Open],
        leaf_tris: Vec::new(),
        subs: SubStore::default(),
        report: LevelReport {
            start_rss_anon_bytes: start_rss.0,
            peak_rss_anon_bytes: start_rss.0,
            peak_rss_file_bytes: start_rss.1,
            ..LevelReport::default()
        },
    };
    let mut clock = Instant::now();
    let (bounds, root_level) = b.root()?;
    b.report.phases.setup_s = lap(&mut clock);
    b.sample_rss();
    let mut level = Some(root_level);
    let mut depth = 0;
    while let Some(l) = level {
        level = b.level(l, depth)?;
        depth += 1;
    }
    // The levels' memory kept for reuse is not needed from here.
    scratch.release_pool();
    clock = Instant::now();
    let tree = assemble(bounds, &b.recs, &b.leaf_tris, std::mem::take(&mut b.subs));
    b.report.phases.assemble_s = lap(&mut clock);
    b.sample_rss();
    let mut report = b.report;
    report.scratch = scratch.stats();
    report.cpu_s = start_cpu
        .zip(cpu_seconds())
        .map_or(0.0, |(start, end)| end - start);
    Ok((tree, report))
}

fn lap(clock: &mut Instant) -> f64 {
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

/// One node of a level.
#[derive(Clone, Copy, Debug)]
struct LNode {
    cell: Aabb,
    /// References `refs .. refs + n` of the level's columns.
    refs: usize,
    n: usize,
    /// Events `ev[k] .. ev[k] + nev[k]` of axis `k`'s column.
    ev: [usize; 3],
    nev: [usize; 3],
    /// Its share of [`Progress::TOTAL`].
    weight: u64,
    /// Its record.
    rec: u32,
}

/// The open nodes of one depth and their columns.
///
/// Invariant: the nodes' reference ranges tile the reference columns in
/// node order, and their event ranges tile each axis's column likewise;
/// within a node, references ascend by triangle and events ascend as
/// `u64` ([`event`]).
struct Level<'s> {
    /// The depth of every node of the level (root = 0).
    depth: u32,
    nodes: Vec<LNode>,
    tri: Column<'s, u32>,
    bounds: Column<'s, Box6>,
    ev: [Column<'s, u64>; 3],
}

struct Builder<'a> {
    scene: &'a TriangleColumns,
    config: &'a BuildConfig,
    progress: Option<&'a Progress>,
    options: &'a LevelOptions,
    scratch: &'a Scratch,
    depth_limit: u32,
    /// One per node, in the order nodes were opened; record 0 is the root.
    recs: Vec<Rec>,
    /// The triangle lists of the breadth-first leaves.
    leaf_tris: Vec<TriId>,
    /// The subtrees finished depth-first.
    subs: SubStore,
    report: LevelReport,
}

/// What finishing small nodes needs of the builder (copied out, so that it
/// runs alongside the passes that change the builder).
struct Finish<'a> {
    scene: &'a TriangleColumns,
    params: sah::SahParams,
    depth_limit: u32,
    progress: Option<&'a Progress>,
    chunk_words: usize,
    mode: NewEvents,
    tiny: usize,
}

impl Finish<'_> {
    /// Finishes the small nodes depth-first, in parallel across nodes.
    /// Their subtrees are packed into runs, in the level's node order:
    /// each fold of rayon's covers a run of consecutive nodes, returned
    /// with the index in `small` of its first node.
    fn runs(
        &self,
        l: &Level<'_>,
        small: &[usize],
        depth: u32,
    ) -> Vec<(usize, Result<SubStream, ColumnsError>)> {
        small
            .par_iter()
            .enumerate()
            .fold(
                || {
                    (
                        usize::MAX,
                        Finisher::new(self.scene, &self.params, self.depth_limit, self.progress)
                            .with_new_events(self.mode)
                            .with_tiny(self.tiny),
                        Ok(SubStream::new(self.chunk_words)),
                    )
                },
                |(first, mut fin, out), (k, &j)| {
                    let out = out.and_then(|mut out| {
                        let nd = &l.nodes[j];
                        let ev = [0, 1, 2].map(|k| &l.ev[k][nd.ev[k]..nd.ev[k] + nd.nev[k]]);
                        let (nodes, leaf_tris) = fin.build(
                            &l.tri[nd.refs..nd.refs + nd.n],
                            &l.bounds[nd.refs..nd.refs + nd.n],
                            ev,
                            nd.refs as u32,
                            nd.cell,
                            depth,
                            nd.weight,
                        );
                        out.push(nd.rec, nodes, leaf_tris)?;
                        Ok(out)
                    });
                    (first.min(k), fin, out)
                },
            )
            .map(|(first, _, out)| (first, out))
            .filter(|(first, _)| *first != usize::MAX)
            .collect()
    }
}

/// Builds subtrees of single nodes depth-first, with the finisher the
/// level builder uses for its small nodes (`dfs`, no heap allocation per
/// node): the subtree is the one [`super::sweep::build_subtree`] builds for
/// the same references, cell and depth. The slim post-pass rebuilds its
/// subtrees with it. One per worker; its scratch is reused across builds.
pub struct SubtreeBuilder<'a> {
    finisher: Finisher<'a>,
    tri: Vec<u32>,
    boxes: Vec<Box6>,
    ev: [Vec<u64>; 3],
}

impl<'a> SubtreeBuilder<'a> {
    pub fn new(scene: &'a TriangleColumns, config: &'a BuildConfig) -> SubtreeBuilder<'a> {
        let depth_limit = config.sah.depth_limit(scene.len());
        SubtreeBuilder {
            finisher: Finisher::new(scene, &config.sah, depth_limit, None)
                .with_tiny(DEFAULT_TINY_THRESHOLD),
            tri: Vec::new(),
            boxes: Vec::new(),
            ev: Default::default(),
        }
    }

    /// The subtree of a node at `depth` with cell `cell` and the triangle
    /// references `refs` (ascending ids, boxes inside `cell`, fewer than
    /// 2³⁰), under the depth limit of the whole scene. The result's
    /// `bounds` is `cell`.
    pub fn build(
        &mut self,
        refs: impl IntoIterator<Item = (TriId, Aabb)>,
        cell: Aabb,
        depth: u32,
    ) -> TreeIr {
        self.tri.clear();
        self.boxes.clear();
        for (t, b) in refs {
            debug_assert!(self.tri.last().is_none_or(|&last| last < t.0));
            self.tri.push(t.0);
            self.boxes.push(to_box(&b));
        }
        assert!(self.tri.len() < MAX_REFS, "too many references");
        for (axis, ev) in self.ev.iter_mut().enumerate() {
            ev.clear();
            for (r, b) in self.boxes.iter().enumerate() {
                push_events(b, axis, r as u32, ev);
            }
            ev.sort_unstable();
        }
        let ev = [0, 1, 2].map(|k| self.ev[k].as_slice());
        let (nodes, leaf_tris) =
            self.finisher
                .build(&self.tri, &self.boxes, ev, 0, cell, depth, Progress::TOTAL);
        TreeIr {
            bounds: cell,
            nodes: nodes.to_vec(),
            leaf_tris: leaf_tris.to_vec(),
        }
    }
}

/// Counts of a pass over one node's references, per child side.
#[derive(Clone, Copy, Debug, Default)]
struct SideCounts {
    /// References going to each side (clipped ones included).
    n: [usize; 2],
    /// Inherited events per side and axis (references wholly on one side).
    inherited: [[usize; 3]; 2],
    /// Events of clipped references per side and axis.
    new: [[usize; 3]; 2],
}

impl Add for SideCounts {
    type Output = SideCounts;
    fn add(mut self, o: SideCounts) -> SideCounts {
        for s in 0..2 {
            self.n[s] += o.n[s];
            for k in 0..3 {
                self.inherited[s][k] += o.inherited[s][k];
                self.new[s][k] += o.new[s][k];
            }
        }
        self
    }
}

/// A pair of counts with `+`, for carries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Pair([usize; 2]);

impl Add for Pair {
    type Output = Pair;
    fn add(self, o: Pair) -> Pair {
        Pair([self.0[0] + o.0[0], self.0[1] + o.0[1]])
    }
}

/// Where a reference of a split node goes: bit 0 left, bit 1 right, bit 2
/// clipped (a straddler; its boxes are in the classify pass's list).
const TO_LEFT: u8 = 1;
const TO_RIGHT: u8 = 2;
const CLIPPED: u8 = 4;

/// A straddler's clipped boxes in the left and right child.
type ChildBoxes = (Option<Aabb>, Option<Aabb>);

/// Classifies one reference (box `b` of triangle `tri`) against `split`,
/// clips it if it straddles, and adds what each side inherits or gains to
/// `c`. Returns the placement code and, for a straddler, its clipped boxes
/// in the two children. The breadth-first pass and the depth-first
/// finisher share it, so they cannot classify differently.
fn classify_ref(
    scene: &TriangleColumns,
    tri: u32,
    b: &Box6,
    split: &Split,
    lc: &Aabb,
    rc: &Aabb,
    c: &mut SideCounts,
) -> (u8, Option<ChildBoxes>) {
    let bx = to_aabb(b);
    match classify(&bx, split) {
        Placement::Left => {
            c.n[0] += 1;
            for k in 0..3 {
                c.inherited[0][k] += n_events(b, k);
            }
            (TO_LEFT, None)
        }
        Placement::Right => {
            c.n[1] += 1;
            for k in 0..3 {
                c.inherited[1][k] += n_events(b, k);
            }
            (TO_RIGHT, None)
        }
        Placement::Both => {
            let r = TriRef {
                tri: TriId(tri),
                bounds: bx,
            };
            let (lb, rb) = clip_straddler(scene, &r, split, lc, rc);
            let mut code = CLIPPED;
            for (side, cb) in [lb, rb].iter().enumerate() {
                if let Some(cb) = cb {
                    code |= 1 << side;
                    c.n[side] += 1;
                    let cb = to_box(cb);
                    for k in 0..3 {
                        c.new[side][k] += n_events(&cb, k);
                    }
                }
            }
            (code, Some((lb, rb)))
        }
    }
}

/// `new_idx` of a clipped straddler, whose events are not inherited. A
/// one-sided reference's entry is its index in the next level (below
/// [`MAX_REFS`], so bit 31 is free) with bit 31 set when it goes right.
const DROPPED: u32 = u32::MAX;

/// The partition slot of a placement code: 0 left, 1 right, 2 dropped (a
/// clipped straddler, whose events are made anew).
const SLOT: [usize; 8] = {
    let mut t = [2; 8];
    t[TO_LEFT as usize] = 0;
    t[TO_RIGHT as usize] = 1;
    t
};

/// What the classify pass found in one piece.
struct Classified {
    /// Per node of the piece.
    counts: Vec<SideCounts>,
    /// The straddlers in reference order: (reference, left box, right box).
    clipped: Vec<(u32, Option<Aabb>, Option<Aabb>)>,
}

impl<'a> Builder<'a> {
    fn sample_rss(&mut self) {
        let (anon, file) = rss();
        self.report.peak_rss_anon_bytes = self.report.peak_rss_anon_bytes.max(anon);
        self.report.peak_rss_file_bytes = self.report.peak_rss_file_bytes.max(file);
    }

    fn capacity(n: usize) -> Result<(), ColumnsError> {
        if n >= MAX_REFS {
            Err(ColumnsError::Capacity {
                what: "references in one level",
                limit: MAX_REFS as u64 - 1,
            })
        } else {
            Ok(())
        }
    }

    /// The root level: every triangle with its own bounds, events sorted.
    /// The cell is [`super::root`]'s ([`root_cell`] of the union of the
    /// boxes), reduced in parallel here: minima and maxima, which the order
    /// of the reduction cannot change (scenes hold no NaN or `-0.0`).
    fn root(&mut self) -> Result<(Aabb, Level<'a>), ColumnsError> {
        let scene = self.scene;
        let n = scene.len();
        Self::capacity(n)?;
        let mut tri = self.scratch.column_for_overwrite::<u32>("tri", n)?;
        let mut boxes = self.scratch.column_for_overwrite::<Box6>("bounds", n)?;
        tri.par_iter_mut()
            .zip(boxes.par_iter_mut())
            .enumerate()
            .for_each(|(i, (t, b))| {
                *t = i as u32;
                *b = to_box(&Aabb::of_triangle(&scene.tri(i as u32)));
            });
        let bounds = root_cell(
            boxes
                .par_iter()
                .map(to_aabb)
                .reduce(|| Aabb::EMPTY, |a, b| a.union(&b)),
        );
        // Each axis's events, generated in reference order and sorted by
        // (position, kind) with a stable radix sort, which leaves them in
        // (position, kind, reference) order. The sort ping-pongs between
        // two columns, so above the budget it runs in scratch files too.
        // The three axes are sorted in parallel.
        let mut nev = [0; 3];
        let mut cols = Vec::with_capacity(3);
        for (axis, nev) in nev.iter_mut().enumerate() {
            *nev = boxes.par_iter().map(|b| n_events(b, axis)).sum();
            let a = self.scratch.column_for_overwrite::<u64>("ev", *nev)?;
            let b = self.scratch.column_for_overwrite::<u64>("ev", *nev)?;
            cols.push((a, b));
        }
        let boxes_ref = &boxes;
        let ev: Vec<Column<'a, u64>> = cols
            .into_par_iter()
            .enumerate()
            .map(|(axis, (mut a, mut b))| {
                let mut at = 0;
                for (i, bx) in boxes_ref.iter().enumerate() {
                    let (ev, k) = events_of(bx, axis, i as u32);
                    a[at..at + k].copy_from_slice(&ev[..k]);
                    at += k;
                }
                let in_b = radix_sort_by_position_and_kind(&mut a, &mut b);
                if in_b { b } else { a }
            })
            .collect();
        let ev: [Column<'a, u64>; 3] = ev.try_into().expect("three axes");
        let node = LNode {
            cell: bounds,
            refs: 0,
            n,
            ev: [0; 3],
            nev,
            weight: Progress::TOTAL,
            rec: 0,
        };
        Ok((
            bounds,
            Level {
                depth: 0,
                nodes: vec![node],
                tri,
                bounds: boxes,
                ev,
            },
        ))
    }

    /// Processes level `depth`; returns the next one, or `None` when no
    /// node is left open.
    fn level(&mut self, l: Level<'a>, depth: u32) -> Result<Option<Level<'a>>, ColumnsError> {
        let threshold = self.options.small_threshold;
        let (small, big): (Vec<usize>, Vec<usize>) =
            (0..l.nodes.len()).partition(|&j| l.nodes[j].n < threshold);
        if let Some(s) = &self.options.status {
            s.level.store(depth, Ordering::Relaxed);
            s.open_nodes.store(big.len() as u64, Ordering::Relaxed);
            s.refs.store(l.tri.len() as u64, Ordering::Relaxed);
        }
        self.report.max_level_refs = self.report.max_level_refs.max(l.tri.len() as u64);
        self.report.max_open_nodes = self.report.max_open_nodes.max(big.len() as u64);
        if !big.is_empty() {
            self.report.levels += 1;
        }

        // 1. Small nodes, depth-first, while the big ones go through the
        // passes below: the two are independent (both only read the
        // level), and rayon's work stealing lets each fill the other's
        // idle time (the passes have sequential stretches, and the last
        // small subtrees of a level would otherwise finish on one core).
        let finish = Finish {
            scene: self.scene,
            params: self.config.sah,
            depth_limit: self.depth_limit,
            progress: self.progress,
            chunk_words: self.subs.chunk_words(),
            mode: self.options.new_events,
            tiny: self.options.tiny_threshold,
        };
        let (runs, next) = rayon::join(
            || {
                let start = Instant::now();
                let runs = finish.runs(&l, &small, depth);
                (runs, start.elapsed().as_secs_f64())
            },
            || self.split_big(&l, &big, depth),
        );
        let (runs, small_s) = runs;
        self.store_runs(&l, &small, depth, runs)?;
        self.report.phases.small_s += small_s;
        self.sample_rss();
        next
    }

    /// The passes over the big nodes of a level (steps 2 to 5 of the module
    /// docs); returns the next level.
    fn split_big(
        &mut self,
        l: &Level<'a>,
        big: &[usize],
        depth: u32,
    ) -> Result<Option<Level<'a>>, ColumnsError> {
        if big.is_empty() {
            return Ok(None);
        }
        let mut clock = Instant::now();

        // 2. SAH.
        let best = self.best_splits(l, big);
        self.report.phases.sah_s += lap(&mut clock);

        // 3. Leaves out; splits kept.
        let mut splits: Vec<(usize, Split)> = Vec::new();
        for (bi, &j) in big.iter().enumerate() {
            let nd = &l.nodes[j];
            self.report.bfs_nodes += 1;
            if sah::is_leaf(
                &self.config.sah,
                best[bi].as_ref(),
                nd.n,
                depth,
                self.depth_limit,
            ) {
                let start = self.leaf_tris.len();
                self.leaf_tris
                    .extend(l.tri[nd.refs..nd.refs + nd.n].iter().map(|&t| TriId(t)));
                self.recs[nd.rec as usize] = Rec::Leaf {
                    start,
                    count: nd.n as u32,
                };
                Progress::add(self.progress, nd.weight);
            } else {
                splits.push((
                    j,
                    best[bi].expect("a split exists when the node is not a leaf"),
                ));
            }
        }
        self.report.phases.leaves_s += lap(&mut clock);
        self.sample_rss();
        if splits.is_empty() {
            return Ok(None);
        }

        // 4. Classify and clip.
        let rsegs: Vec<(usize, usize)> = splits
            .iter()
            .map(|&(j, _)| (l.nodes[j].refs, l.nodes[j].n))
            .collect();
        let rpieces = pieces(&rsegs, PIECE, |_| true);
        let mut place = self
            .scratch
            .column_for_overwrite::<u8>("place", l.tri.len())?;
        let classified = self.classify_pass(l, &splits, &rsegs, &rpieces, &mut place);
        self.report.clipped += classified
            .iter()
            .map(|c| c.clipped.len() as u64)
            .sum::<u64>();

        // The children: per split node, left then right.
        let mut totals = vec![SideCounts::default(); splits.len()];
        for (p, c) in rpieces.iter().zip(&classified) {
            for (k, si) in p.nodes.clone().enumerate() {
                totals[si] = totals[si] + c.counts[k];
            }
        }
        let part_counts: Vec<SideCounts> = rpieces
            .iter()
            .zip(&classified)
            .map(|(p, c)| {
                if p.part.is_some() {
                    c.counts[0]
                } else {
                    SideCounts::default()
                }
            })
            .collect();
        let rcarry = carries(&rpieces, &part_counts);
        let mut next_nodes = Vec::with_capacity(2 * splits.len());
        let (mut refs_at, mut ev_at) = (0usize, [0usize; 3]);
        for (si, &(j, split)) in splits.iter().enumerate() {
            let nd = &l.nodes[j];
            let t = &totals[si];
            let (lc, rc) = nd.cell.split(split.axis as usize, split.pos);
            let (wl, wr) = Progress::share(nd.weight, t.n[0], t.n[1]);
            let left = self.recs.len() as u32;
            self.recs[nd.rec as usize] = Rec::Inner {
                axis: split.axis,
                pos: split.pos,
                left,
                right: left + 1,
            };
            for (side, (cell, weight)) in [(lc, wl), (rc, wr)].into_iter().enumerate() {
                let nev = [0, 1, 2].map(|k| t.inherited[side][k] + t.new[side][k]);
                next_nodes.push(LNode {
                    cell,
                    refs: refs_at,
                    n: t.n[side],
                    ev: ev_at,
                    nev,
                    weight,
                    rec: self.recs.len() as u32,
                });
                self.recs.push(Rec::Open);
                refs_at += t.n[side];
                for k in 0..3 {
                    ev_at[k] += nev[k];
                }
            }
        }
        Self::capacity(refs_at)?;
        let mut tri = self.scratch.column_for_overwrite::<u32>("tri", refs_at)?;
        let mut boxes = self
            .scratch
            .column_for_overwrite::<Box6>("bounds", refs_at)?;
        let mut new_idx = self
            .scratch
            .column_for_overwrite::<u32>("new-idx", l.tri.len())?;
        let copies = write_children(
            l,
            &place,
            &rsegs,
            &rpieces,
            &classified,
            &rcarry,
            &next_nodes,
            &mut tri,
            &mut boxes,
            &mut new_idx,
        );
        drop(classified);
        self.report.phases.classify_clip_s += lap(&mut clock);
        self.sample_rss();

        // 5. Child events.
        let mut ev = Vec::with_capacity(3);
        for &len in &ev_at {
            ev.push(self.scratch.column_for_overwrite::<u64>("ev", len)?);
        }
        let mut ev: [Column<'a, u64>; 3] = ev.try_into().expect("three axes");
        partition_events(l, &splits, &place, &new_idx, &next_nodes, &mut ev);
        drop(place);
        drop(new_idx);
        merge_new_events(
            copies,
            &boxes,
            &next_nodes,
            &mut ev,
            self.options.new_events,
        );
        self.report.phases.events_s += lap(&mut clock);
        self.sample_rss();
        Ok(Some(Level {
            depth: depth + 1,
            nodes: next_nodes,
            tri,
            bounds: boxes,
            ev,
        }))
    }

    /// Files the subtrees of a level's small nodes ([`Finish::runs`]) into
    /// the level's stream of `subs`.
    fn store_runs(
        &mut self,
        l: &Level<'a>,
        small: &[usize],
        depth: u32,
        runs: Vec<(usize, Result<SubStream, ColumnsError>)>,
    ) -> Result<(), ColumnsError> {
        let mut next = 0;
        for (first, run) in runs {
            let run = run?;
            // Runs tile `small` in order; the assembly relies on it.
            assert_eq!(first, next, "the runs of small nodes are in order");
            next += run.len();
            self.subs.add(depth, run);
        }
        assert_eq!(next, small.len());
        for &j in small {
            self.recs[l.nodes[j].rec as usize] = Rec::Sub(depth);
        }
        self.report.small_nodes += small.len() as u64;
        Ok(())
    }

    /// The best split of each of the `big` nodes (`None` for an empty node
    /// or a flat cell, as in the sweep builder).
    fn best_splits(&self, l: &Level<'a>, big: &[usize]) -> Vec<Option<Split>> {
        let sah = &self.config.sah;
        let sa: Vec<f64> = big
            .iter()
            .map(|&j| l.nodes[j].cell.surface_area())
            .collect();
        // Nodes at the depth limit are leaves whatever their best split
        // ([`sah::is_leaf`]): they are not swept.
        let valid: Vec<usize> = (0..big.len())
            .filter(|&bi| l.nodes[big[bi]].n > 0 && sa[bi] > 0.0 && l.depth < self.depth_limit)
            .collect();
        let mut tasks: Vec<(usize, Piece, Pair)> = Vec::new();
        for (axis, ev) in l.ev.iter().enumerate() {
            let segs: Vec<(usize, usize)> = valid
                .iter()
                .map(|&bi| {
                    let nd = &l.nodes[big[bi]];
                    (nd.ev[axis], nd.nev[axis])
                })
                .collect();
            let ev: &[u64] = ev;
            // A run of equal positions is priced as one plane, so it must
            // not be cut.
            let ps = pieces(&segs, PIECE, |i| ev_key(ev[i]) != ev_key(ev[i - 1]));
            // Counts of (starts + planars, ends + planars) in each part
            // (but a node's last, which no carry needs).
            let counts: Vec<Pair> = ps
                .par_iter()
                .map(|p| match &p.part {
                    Some(r) if r.end != segs[p.nodes.start].0 + segs[p.nodes.start].1 => {
                        let mut c = [0usize; 3];
                        for &e in &ev[r.clone()] {
                            c[ev_kind(e)] += 1;
                        }
                        Pair([c[2] + c[1], c[0] + c[1]])
                    }
                    _ => Pair::default(),
                })
                .collect();
            let carry = carries(&ps, &counts);
            // Piece node indices refer to `valid`.
            tasks.extend(ps.into_iter().zip(carry).map(|(p, c)| (axis, p, c)));
        }
        // Each node's least cost so far, shared by its tasks (every axis,
        // every part), so that each prunes against the others' planes too.
        let shared: Vec<AtomicU64> = valid
            .iter()
            .map(|&bi| AtomicU64::new(sah.leaf_cost(l.nodes[big[bi]].n).to_bits()))
            .collect();
        let found: Vec<Vec<(usize, Split)>> = tasks
            .par_iter()
            .map(|(axis, p, carry)| {
                let mut out = Vec::new();
                for vi in p.nodes.clone() {
                    let bi = valid[vi];
                    let nd = &l.nodes[big[bi]];
                    let seg = (nd.ev[*axis], nd.nev[*axis]);
                    let (n_l, n_r) = if p.continues(seg) {
                        (carry.0[0], nd.n - carry.0[1])
                    } else {
                        (0, nd.n)
                    };
                    let mut best = None;
                    sweep_events(
                        sah,
                        &nd.cell,
                        sa[bi],
                        *axis,
                        &l.ev[*axis][p.range(seg)],
                        n_l,
                        n_r,
                        sah.leaf_cost(nd.n),
                        &mut best,
                        &shared[vi],
                    );
                    if let Some(s) = best {
                        out.push((bi, s));
                    }
                }
                out
            })
            .collect();
        let mut best = vec![None; big.len()];
        for (bi, s) in found.into_iter().flatten() {
            s.keep_best(&mut best[bi]);
        }
        best
    }

    /// Classifies the references of the split nodes, clips the straddlers
    /// and writes each reference's placement into `place`.
    fn classify_pass(
        &self,
        l: &Level<'a>,
        splits: &[(usize, Split)],
        rsegs: &[(usize, usize)],
        rpieces: &[Piece],
        place: &mut [u8],
    ) -> Vec<Classified> {
        let scene = self.scene;
        let place = ScatterSlice::new(place);
        // Sliced once: a column's `Deref` matches on where it lives.
        let (tris, bounds): (&[u32], &[Box6]) = (&l.tri, &l.bounds);
        rpieces
            .par_iter()
            .map(|p| {
                let mut counts = Vec::with_capacity(p.nodes.len());
                let mut clipped = Vec::new();
                for si in p.nodes.clone() {
                    let (j, split) = splits[si];
                    let (lc, rc) = l.nodes[j].cell.split(split.axis as usize, split.pos);
                    let mut c = SideCounts::default();
                    for i in p.range(rsegs[si]) {
                        let (code, straddler) =
                            classify_ref(scene, tris[i], &bounds[i], &split, &lc, &rc, &mut c);
                        if let Some((lb, rb)) = straddler {
                            clipped.push((i as u32, lb, rb));
                        }
                        // SAFETY: the pieces cover disjoint reference
                        // ranges, so position `i` is this piece's alone.
                        unsafe { place.write(i, code) };
                    }
                    counts.push(c);
                }
                Classified { counts, clipped }
            })
            .collect()
    }
}

/// Sweeps one node's sorted events (all of them, or one piece starting with
/// `n_l` references left and `n_r` right of its first plane) and keeps the
/// best plane: the sweep of [`super::sweep::sweep_axis`], with carried
/// counts.
///
/// Every plane that could win is priced by [`sah::split_cost`]. A plane is
/// skipped only when a lower bound of its cost ([`Pricer`]) exceeds the
/// best cost found so far: then its exact cost does too, it would lose the
/// comparison of [`Split::cmp_order`] on cost alone, and the result is the
/// same as pricing it. Or when the bound exceeds `cap`, the node's leaf
/// cost: a split that costs at least that much never matters, since if
/// the best split does, [`sah::is_leaf`] makes the node a leaf whatever
/// the split (so `best` may stay `None` where pricing every plane would
/// have found a split, only for nodes that become leaves either way).
/// (An optimisation the paper does not have; it halves the sweep on large
/// scenes, where most planes are far from the best.)
///
/// Whole blocks of [`SKIP_BLOCK`] events are passed over, their counts
/// added without looking at their planes, when one bound for all of their
/// planes ([`Pricer::block_bound`]) already exceeds the best cost: the
/// same reasoning, so the same result. On stk_black_forest this passes
/// over 61% of the events swept.
///
/// The best cost pruned against is also `shared`'s: the least cost found
/// by the other sweeps of the same node ([`SharedBest`]). The level
/// passes sweep a node's three axes, and each part of a large node, as
/// separate tasks; without the shared cost each would start from the leaf
/// cost alone and price every plane of a stretch where the cost falls
/// towards a best plane in another part or on another axis (sharing it
/// takes about a quarter off the level passes' SAH phase on
/// black_forest). The split found is the same: a plane is still skipped
/// only when its cost exceeds that of a plane of the node.
#[allow(clippy::too_many_arguments)]
#[inline]
fn sweep_events(
    params: &sah::SahParams,
    cell: &Aabb,
    sa: f64,
    axis: usize,
    events: &[u64],
    mut n_l: usize,
    mut n_r: usize,
    cap: f64,
    best: &mut Option<Split>,
    shared: &impl SharedBest,
) {
    let exact = sah::AxisPricer::new(cell, sa, axis);
    let pricer = Pricer::new(params, &exact, cell, sa, axis);
    let mut best_cost = best
        .map_or(f64::INFINITY, |b| b.cost)
        .min(cap)
        .min(shared.get());
    let len = events.len();
    let mut i = 0;
    while i < len {
        best_cost = best_cost.min(shared.get());
        // Blocks of events whose planes all cost more than the best so far
        // are passed over with their counts added up: see
        // [`Pricer::block_bound`]. The block stops before its last run of
        // equal positions, which may go on past it (a plane is priced with
        // all of its run's events counted).
        let mut until = i + 1;
        if i + SKIP_BLOCK <= len {
            let blk: &[u64; SKIP_BLOCK] = events[i..i + SKIP_BLOCK]
                .try_into()
                .expect("SKIP_BLOCK long");
            let last_key = ev_key(blk[SKIP_BLOCK - 1]);
            let mut g = SKIP_BLOCK - 1;
            while g > 0 && ev_key(blk[g - 1]) == last_key {
                g -= 1;
            }
            if g > 0 {
                // Ends and planars (they leave the right side), starts and
                // planars (they join the left side), in the first `g`.
                let (mut out, mut into) = (0usize, 0usize);
                for (c, &e) in blk.iter().enumerate() {
                    let k = ev_kind(e);
                    let inb = c < g;
                    out += usize::from(inb & (k <= 1));
                    into += usize::from(inb & (k >= 1));
                }
                let x0 = key_pos(ev_key(blk[0]));
                let x1 = key_pos(ev_key(blk[g - 1]));
                if pricer.block_bound(x0, x1, n_l, n_r - out) > best_cost {
                    n_l += into;
                    n_r -= out;
                    i += g;
                    continue;
                }
                until = i + g;
            }
        }
        while i < until {
            let e = events[i];
            let key = ev_key(e);
            let k = ev_kind(e);
            let (mut ends, mut planar) = (usize::from(k == 0), usize::from(k == 1));
            let mut j = i + 1;
            while j < len && ev_key(events[j]) == key {
                let k = ev_kind(events[j]);
                ends += usize::from(k == 0);
                planar += usize::from(k == 1);
                j += 1;
            }
            let starts = (j - i) - ends - planar;
            i = j;
            n_r -= planar + ends;
            let pos = key_pos(key);
            // With no best yet, `best_cost` is +∞ and nothing is skipped.
            if pricer.lower_bound(pos, n_l, n_r, planar) <= best_cost {
                let counts = PlaneCounts {
                    left: n_l,
                    right: n_r,
                    planar,
                };
                let cost = exact.cost(params, pos, counts);
                cost.keep_best(best);
                if cost.cost < best_cost {
                    best_cost = cost.cost;
                    shared.offer(cost.cost);
                }
            }
            n_l += starts + planar;
        }
    }
}

/// The least cost found so far by every sweep of one node (the level
/// passes sweep a node's axes, and the parts of a large node, as separate
/// tasks), which [`sweep_events`] prunes against: a plane whose bound
/// exceeds a cost some plane of the node has is not its best split,
/// whichever task found that plane, so the split found is the same
/// whatever the tasks' timing.
trait SharedBest: Sync {
    /// The least cost offered so far (`+∞` when none).
    fn get(&self) -> f64;
    /// Offers the cost of a plane of the node.
    fn offer(&self, cost: f64);
}

/// A sweep that is the only one of its node (the finisher's).
struct Alone;

impl SharedBest for Alone {
    #[inline]
    fn get(&self) -> f64 {
        f64::INFINITY
    }
    #[inline]
    fn offer(&self, _: f64) {}
}

/// The bits of a cost, which order as the costs do: costs are sums of
/// non-negative terms when the SAH constants are (the only case in which
/// the sweep prunes at all, see [`Pricer`]), and the bits of non-negative
/// `f64`s order as their values.
impl SharedBest for AtomicU64 {
    #[inline]
    fn get(&self) -> f64 {
        f64::from_bits(self.load(Ordering::Relaxed))
    }
    #[inline]
    fn offer(&self, cost: f64) {
        if cost >= 0.0 {
            self.fetch_min(cost.to_bits(), Ordering::Relaxed);
        }
    }
}

/// Events [`sweep_events`] tries to pass over at once.
const SKIP_BLOCK: usize = 16;

/// A lower bound of [`sah::split_cost`] for one node and axis, cheaper
/// than the cost itself: the surface areas as `2(A + d·B)` for the other
/// two extents' product `A` and sum `B`, divided by one multiplication;
/// `λ` and the planar side decided as `split_cost` decides them (a bound
/// with `λ = min(1, λ_empty)` throughout would need no branch, but prunes
/// so much less that the sweep is slower).
///
/// Both this and `split_cost` sum non-negative `f64` terms, so each is
/// within a relative 2⁻⁴⁸ of the true value; the bound is shrunk by a
/// relative 10⁻¹⁰, far more than both errors together. With a negative or
/// non-finite constant the bound would not be valid, and it is `-∞`
/// (nothing is skipped).
struct Pricer {
    valid: bool,
    k_t: f64,
    k_i: f64,
    lambda_empty: f64,
    /// `2A / SA(V)` and `2B / SA(V)`.
    a2: f64,
    b2: f64,
    lo: f64,
    hi: f64,
    lo32: f32,
    hi32: f32,
}

impl Pricer {
    #[inline]
    fn new(
        params: &sah::SahParams,
        exact: &sah::AxisPricer,
        cell: &Aabb,
        sa: f64,
        axis: usize,
    ) -> Pricer {
        let d = exact.extents();
        let (u, v) = (d[(axis + 1) % 3], d[(axis + 2) % 3]);
        let inv = 1.0 / sa;
        let valid = params.k_t >= 0.0
            && params.k_i >= 0.0
            && params.lambda_empty >= 0.0
            && params.k_t.is_finite()
            && params.k_i.is_finite()
            && params.lambda_empty.is_finite()
            && inv.is_finite();
        Pricer {
            valid,
            k_t: params.k_t,
            k_i: params.k_i,
            lambda_empty: params.lambda_empty,
            a2: 2.0 * u * v * inv,
            b2: 2.0 * (u + v) * inv,
            lo: f64::from(cell.min[axis]),
            hi: f64::from(cell.max[axis]),
            lo32: cell.min[axis],
            hi32: cell.max[axis],
        }
    }

    /// A lower bound of the cost of every plane of a block of events
    /// from position `x0` to `x1`, where `n_l` references are left of the
    /// first plane and `n_r` right of the last: counts only grow to the
    /// left and shrink to the right along the sweep, `P_L` grows with the
    /// position and `P_R` shrinks, planar references only add terms, and
    /// `λ` is 1 at every plane when both counts are non-zero (both sides
    /// stay occupied), else at least `min(1, λ_empty)`. (With that
    /// minimum throughout, the bound would pass over 13% of black_forest's
    /// events instead of 61%.) Shrunk like [`Pricer::lower_bound`]; `-∞`
    /// when the constants make it invalid.
    #[inline]
    fn block_bound(&self, x0: f32, x1: f32, n_l: usize, n_r: usize) -> f64 {
        if !self.valid {
            return f64::NEG_INFINITY;
        }
        let p_l = self.a2 + (f64::from(x0) - self.lo) * self.b2;
        let p_r = self.a2 + (self.hi - f64::from(x1)) * self.b2;
        // Both sides occupied at every plane: λ = 1.
        let lambda = if n_l > 0 && n_r > 0 {
            1.0
        } else {
            self.lambda_empty.min(1.0)
        };
        let c = self.k_t + self.k_i * lambda * (p_l * n_l as f64 + p_r * n_r as f64);
        c * (1.0 - 1e-10)
    }

    #[inline]
    fn lower_bound(&self, pos: f32, n_l: usize, n_r: usize, n_p: usize) -> f64 {
        if !self.valid {
            return f64::NEG_INFINITY;
        }
        let x = f64::from(pos);
        let p_l = self.a2 + (x - self.lo) * self.b2;
        let p_r = self.a2 + (self.hi - x) * self.b2;
        if n_p == 0 && n_l != 0 && n_r != 0 {
            // The common case: no planar triangles, both sides occupied, so
            // λ = 1 and the planar side does not matter.
            let c = self.k_t + self.k_i * (p_l * n_l as f64 + p_r * n_r as f64);
            return c * (1.0 - 1e-10);
        }
        let on_face = pos == self.lo32 || pos == self.hi32;
        let cost = |nl: usize, nr: usize| {
            let lambda = if (nl == 0 || nr == 0) && !on_face {
                self.lambda_empty
            } else {
                1.0
            };
            self.k_t + self.k_i * lambda * (p_l * nl as f64 + p_r * nr as f64)
        };
        let c = cost(n_l + n_p, n_r).min(cost(n_l, n_r + n_p));
        c * (1.0 - 1e-10)
    }
}

/// Writes the child references (kept boxes and clipped boxes) into the
/// next level's columns, and into `new_idx` each one-sided reference's new
/// index and side and each straddler's [`DROPPED`] (so that the event
/// partition needs one lookup per event). Returns the clipped copies as `(child node << 32) | new
/// reference`, whose events are not inherited.
#[allow(clippy::too_many_arguments)]
fn write_children(
    l: &Level<'_>,
    place: &[u8],
    rsegs: &[(usize, usize)],
    rpieces: &[Piece],
    classified: &[Classified],
    rcarry: &[SideCounts],
    next: &[LNode],
    tri: &mut [u32],
    boxes: &mut [Box6],
    new_idx: &mut [u32],
) -> Vec<u64> {
    let tri = ScatterSlice::new(tri);
    let boxes = ScatterSlice::new(boxes);
    let new_idx = ScatterSlice::new(new_idx);
    // Sliced once: a column's `Deref` matches on where it lives.
    let (l_tri, l_bounds): (&[u32], &[Box6]) = (&l.tri, &l.bounds);
    let copies: Vec<Vec<u64>> = rpieces
        .par_iter()
        .zip(classified.par_iter())
        .zip(rcarry.par_iter())
        .map(|((p, c), carry)| {
            let mut copies = Vec::new();
            let mut clipped = c.clipped.iter();
            for si in p.nodes.clone() {
                let seg = rsegs[si];
                let (cl, cr) = (2 * si, 2 * si + 1);
                let carry = if p.continues(seg) {
                    *carry
                } else {
                    SideCounts::default()
                };
                let mut at = [next[cl].refs + carry.n[0], next[cr].refs + carry.n[1]];
                for i in p.range(seg) {
                    let code = place[i];
                    if code & CLIPPED == 0 {
                        let side = usize::from(code == TO_RIGHT);
                        let d = at[side];
                        at[side] += 1;
                        // SAFETY: `d` is this reference's rank among the
                        // node's references going to `side`, offset by the
                        // child's start: distinct for every reference of
                        // every piece. `i` lies in this piece's range.
                        unsafe {
                            tri.write(d, l_tri[i]);
                            boxes.write(d, l_bounds[i]);
                            new_idx.write(i, d as u32 | (side as u32) << 31);
                        }
                    } else {
                        // SAFETY: as above.
                        unsafe { new_idx.write(i, DROPPED) };
                        let &(ci, lb, rb) = clipped.next().expect("one entry per straddler");
                        debug_assert_eq!(ci as usize, i);
                        for (side, cb) in [lb, rb].into_iter().enumerate() {
                            if let Some(cb) = cb {
                                let d = at[side];
                                at[side] += 1;
                                // SAFETY: as above.
                                unsafe {
                                    tri.write(d, l_tri[i]);
                                    boxes.write(d, to_box(&cb));
                                }
                                let child = [cl, cr][side];
                                copies.push(((child as u64) << 32) | d as u64);
                            }
                        }
                    }
                }
            }
            copies
        })
        .collect();
    copies.concat()
}

/// The stable partition of the inherited events: each event of a
/// one-sided reference goes, renumbered, to its child's segment, in the
/// order it had; the clipped references' events are dropped (they are
/// made anew in [`merge_new_events`]). A child's inherited events fill the
/// front of its segment.
fn partition_events(
    l: &Level<'_>,
    splits: &[(usize, Split)],
    place: &[u8],
    new_idx: &[u32],
    next: &[LNode],
    ev: &mut [Column<'_, u64>; 3],
) {
    let [e0, e1, e2] = ev;
    let dst = [
        ScatterSlice::new(&mut e0[..]),
        ScatterSlice::new(&mut e1[..]),
        ScatterSlice::new(&mut e2[..]),
    ];
    let mut tasks: Vec<(usize, Piece, Pair)> = Vec::new();
    let mut segs_by_axis = Vec::with_capacity(3);
    for axis in 0..3 {
        let segs: Vec<(usize, usize)> = splits
            .iter()
            .map(|&(j, _)| (l.nodes[j].ev[axis], l.nodes[j].nev[axis]))
            .collect();
        let src: &[u64] = &l.ev[axis];
        let ps = pieces(&segs, PIECE, |_| true);
        let counts: Vec<Pair> = ps
            .par_iter()
            .map(|p| match &p.part {
                // A node's last part: no carry needs its counts.
                Some(r) if r.end != segs[p.nodes.start].0 + segs[p.nodes.start].1 => {
                    // Counted by slot, without a branch on the side.
                    let mut c = [0usize; 3];
                    for &e in &src[r.clone()] {
                        c[SLOT[usize::from(place[ev_ref(e) as usize])]] += 1;
                    }
                    Pair([c[0], c[1]])
                }
                _ => Pair::default(),
            })
            .collect();
        let carry = carries(&ps, &counts);
        tasks.extend(ps.into_iter().zip(carry).map(|(p, c)| (axis, p, c)));
        segs_by_axis.push(segs);
    }
    tasks.par_iter().for_each(|(axis, p, carry)| {
        let axis = *axis;
        let src: &[u64] = &l.ev[axis];
        let dst = &dst[axis];
        for si in p.nodes.clone() {
            let seg = segs_by_axis[axis][si];
            let carry = if p.continues(seg) {
                *carry
            } else {
                Pair::default()
            };
            // The two cursors stay in registers (a select, not an array
            // indexed by the side, whose store and reload per event made a
            // chain through memory).
            let mut at_l = next[2 * si].ev[axis] + carry.0[0];
            let mut at_r = next[2 * si + 1].ev[axis] + carry.0[1];
            for &e in &src[p.range(seg)] {
                // One lookup per event: `new_idx` carries the side too
                // (`write_children`).
                let dest = new_idx[ev_ref(e) as usize];
                if dest != DROPPED {
                    let right = dest >> 31 != 0;
                    let at = if right { at_r } else { at_l };
                    // SAFETY: `at` is the event's rank among the node's
                    // events going to its side (carried over the node's
                    // earlier pieces), offset by the child's segment
                    // start: distinct for every event.
                    unsafe { dst.write(at, with_ref(e, dest & !(1 << 31))) };
                    at_l += usize::from(!right);
                    at_r += usize::from(right);
                }
            }
        }
    });
}

/// Sorts the events of each child's clipped references and merges them
/// into the child's segments, behind the inherited events.
fn merge_new_events(
    mut copies: Vec<u64>,
    boxes: &[Box6],
    next: &[LNode],
    ev: &mut [Column<'_, u64>; 3],
    mode: NewEvents,
) {
    copies.par_sort_unstable();
    // Runs of copies of the same child.
    let mut runs = Vec::new();
    let mut s = 0;
    for i in 1..=copies.len() {
        if i == copies.len() || copies[i] >> 32 != copies[s] >> 32 {
            runs.push(s..i);
            s = i;
        }
    }
    let [e0, e1, e2] = ev;
    let dst = [
        ScatterSlice::new(&mut e0[..]),
        ScatterSlice::new(&mut e1[..]),
        ScatterSlice::new(&mut e2[..]),
    ];
    runs.par_iter().for_each_init(Vec::new, |tmp, run| {
        let child = &next[(copies[run.start] >> 32) as usize];
        for (axis, dst) in dst.iter().enumerate() {
            tmp.clear();
            for &c in &copies[run.clone()] {
                let r = c as u32;
                push_events(&boxes[r as usize], axis, r, tmp);
            }
            tmp.sort_unstable();
            // SAFETY: child segments are disjoint, and each child is one
            // run.
            let seg = unsafe { dst.range_mut(child.ev[axis], child.ev[axis] + child.nev[axis]) };
            mode.merge(seg, tmp);
        }
    });
}

/// Sorts events generated in reference order: a stable least-significant
/// digit radix sort on bits 30–63 (position and kind; the reference bits
/// are already in order), three passes of 11, 11 and 12 bits, from `a`
/// through `b` (of the same length). Returns whether the result is in `b`.
/// About four times faster than a comparison sort of the root's events.
fn radix_sort_by_position_and_kind(a: &mut [u64], b: &mut [u64]) -> bool {
    let (mut src, mut dst) = (a, b);
    let mut in_b = false;
    for (shift, bits) in [(30u32, 11u32), (41, 11), (52, 12)] {
        let mask = (1u64 << bits) - 1;
        let mut count = vec![0usize; (1 << bits) + 1];
        for &e in src.iter() {
            count[((e >> shift) & mask) as usize + 1] += 1;
        }
        for d in 1..count.len() {
            count[d] += count[d - 1];
        }
        for &e in src.iter() {
            let d = ((e >> shift) & mask) as usize;
            dst[count[d]] = e;
            count[d] += 1;
        }
        std::mem::swap(&mut src, &mut dst);
        in_b = !in_b;
    }
    in_b
}

/// `seg` holds sorted events followed by `new.len()` free slots; merges the
/// sorted `new` in, from the back, so no element is overwritten before it
/// is read.
///
/// Each step writes the larger of the two candidates and advances the
/// cursor it came from, without a branch on the comparison (a coin flip
/// where the two lists interleave). Where at least [`GALLOP`] inherited
/// events lie above the next new one, which is most of the list when the
/// new events are few (the clipped copies' events on the other axes) or
/// bunched (on the split axis, at the child's face by the plane), the
/// block of them is found by a binary search and moved at once.
fn merge_back(seg: &mut [u64], new: &[u64]) {
    let (mut i, mut j) = (seg.len() - new.len(), new.len());
    let mut w = seg.len();
    while j > 0 {
        let b = new[j - 1];
        if i >= GALLOP && seg[i - GALLOP] > b {
            // `seg[hi..i]` are all above `b`. Steps doubling downwards
            // find a `lo` at or below `b` (or the start), then a binary
            // search between: the probes stay near `i`, where a search of
            // the whole list would miss the cache on a long segment.
            let (mut lo, mut hi, mut step) = (0, i - GALLOP, GALLOP);
            while hi > step {
                let probe = hi - step;
                if seg[probe] <= b {
                    lo = probe;
                    break;
                }
                hi = probe;
                step *= 2;
            }
            let p = lo + seg[lo..hi].partition_point(|&x| x <= b);
            seg.copy_within(p..i, p + j);
            w = p + j;
            i = p;
        }
        let a = seg[i.saturating_sub(1)];
        let take_a = i > 0 && a > b;
        seg[w - 1] = if take_a { a } else { b };
        i -= usize::from(take_a);
        j -= usize::from(!take_a);
        w -= 1;
    }
}

/// Inherited events above a new one from which [`merge_back`] moves them
/// as a block.
const GALLOP: usize = 16;

/// [`merge_back`]'s result by Wu et al.'s buckets: for each new event,
/// last first, the binary search of its bucket among the inherited events
/// not yet moved, one block move of the inherited events above it, and
/// one write.
fn bucket_merge(seg: &mut [u64], new: &[u64]) {
    let mut hi = seg.len() - new.len();
    for (j, &e) in new.iter().enumerate().rev() {
        let b = seg[..hi].partition_point(|&x| x < e);
        seg.copy_within(b..hi, b + j + 1);
        seg[b + j] = e;
        hi = b;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_sort_sorts_like_a_comparison_sort() {
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let mut v = Vec::new();
        for r in 0..5000u64 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Few distinct positions, so kinds and references decide ties.
            v.push((x % 97) << 35 | ((x >> 20) % 3) << 30 | r);
        }
        let mut want = v.clone();
        want.sort_unstable();
        let mut b = vec![0; v.len()];
        let in_b = radix_sort_by_position_and_kind(&mut v, &mut b);
        assert_eq!(if in_b { b } else { v }, want);
    }

    #[test]
    fn merge_back_merges() {
        let mut seg = vec![1, 4, 6, 9, 0, 0, 0];
        merge_back(&mut seg, &[0, 5, 10]);
        assert_eq!(seg, vec![0, 1, 4, 5, 6, 9, 10]);
        let mut seg = vec![0, 0];
        merge_back(&mut seg, &[2, 3]);
        assert_eq!(seg, vec![2, 3]);
    }

    #[test]
    fn bucket_merge_equals_merge_back() {
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        for case in 0..500 {
            let (h, m) = ((next() % 200) as usize, (next() % 12) as usize);
            let range = 1 + next() % if case % 2 == 0 { 8 } else { 1000 };
            let mut old: Vec<u64> = (0..h).map(|_| next() % range).collect();
            let mut new: Vec<u64> = (0..m).map(|_| next() % range).collect();
            old.sort_unstable();
            new.sort_unstable();
            let mut a = old.clone();
            a.resize(h + m, 0);
            let mut b = a.clone();
            merge_back(&mut a, &new);
            bucket_merge(&mut b, &new);
            let mut want = [old, new].concat();
            want.sort_unstable();
            assert_eq!(a, want);
            assert_eq!(b, want);
        }
    }
}
