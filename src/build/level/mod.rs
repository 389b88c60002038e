//! The breadth-first level builder: Wu, Zhao & Liu, "SAH KD-Tree
//! Construction on GPU" (HPG 2011), on CPU cores with rayon.
//!
//! Consumes a scene, the [`BuildConfig`] and [`LevelOptions`]. Produces the
//! standard tree as a [`TreeIr`] **equal** to [`super::wald_havran::build`]'s (the
//! same splits, the same leaves, the same order; see [`super`] for the one
//! definition every builder follows) and a [`LevelReport`] with per-phase
//! times and memory figures. The tree does not depend on the number of
//! threads: every decision is a function of the data, cut into pieces
//! whose bounds depend on the data alone, and every reduction (the best
//! split of a node) is over a total order.
//!
//! **One level** is the open nodes at one depth, stored as flat columns
//! (`crate::columns`: in RAM below `mem_budget`, in mapped scratch files
//! above it): each node's references (triangle id and clipped box,
//! ascending by triangle) and, per axis, its events sorted as in the sweep
//! builder (`events`). One call of `LevelBuilder::level` turns level `d`
//! into level `d + 1` (the paper's §4, Figure 2):
//!
//! 1. **Small nodes** (fewer than `small_threshold` references) are handed
//!    to the depth-first builder (`dfs`: the Wald-Havran builder's algorithm
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
//!    Every plane that can win is priced by `sah::split_cost` and the
//!    best kept by `Split::keep_best`, whose total order makes the
//!    reduction over pieces independent of their order. **Not in the
//!    paper:** a plane whose cost provably exceeds the best so far is not
//!    priced (`best_split::Pricer`); and a node at the depth limit is not swept, since
//!    `sah::is_leaf` makes it a leaf whatever its best split.
//! 3. **Leaves** (`sah::is_leaf`) stream out: their triangle lists are
//!    appended to the leaf list at once.
//! 4. **Classify and clip**: references go left, right or both
//!    ([`super::classify`]); straddlers are clipped to each child
//!    ([`super::clip_straddler`],
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
//! **Memory.** The finishers' working memory (`FINISHER_BYTES_PER_REF` a
//! reference of `small_threshold`, a thread) is set aside from
//! `mem_budget`, and the level columns obey the rest. Under a budget the
//! levels whose nodes are too large for RAM go through scratch files, so
//! the CLI raises the small-node threshold with the budget
//! ([`LevelOptions::small_threshold_for_budget`]: 49.7 M triangles under
//! 2 GiB wrote 66.6 GB of scratch at 2048 references, 44.4 GB at 65536),
//! and a level in scratch is cut into groups of nodes that fit in RAM,
//! each built to the end on its own (`LevelBuilder::levels`: 14.1 GB; 231 s at
//! 2048 references without groups, 177–182 s with). The breadth-first
//! records and leaf lists stay in RAM until the tree is assembled; the
//! depth-first subtrees, packed (12 bytes a node) in one stream per level
//! that the assembly reads front to back, unmapping each chunk once read
//! (`assemble`), are anonymous mappings, or under a budget unlinked
//! scratch files (on 4.3 M triangles they are 400 MiB, more than the top
//! levels' columns under a 256 MiB budget): the subtrees are never held
//! twice, and never as many small allocations that the allocator would
//! keep after they are freed. [`build_into`] hands the assembly to a
//! sink (the streamed file writer), so the tree need not exist whole.

mod assemble;
mod best_split;
mod classify;
mod dfs;
mod events;
mod options;
mod pieces;
mod placement;
mod report;
mod tiny;

pub use self::options::{
    DEFAULT_SMALL_THRESHOLD, DEFAULT_TINY_THRESHOLD, FINISHER_BYTES_PER_REF, LevelOptions,
    LevelStatus, MAX_BUDGET_SMALL_THRESHOLD, NewEvents,
};
pub use self::report::{LevelReport, Phases};
pub use crate::columns::ScratchStats;
pub use crate::sys::{cpu_seconds, rss};

use self::assemble::{NodeRecord, SubStore, SubStream, assemble, assemble_into};
use self::best_split::best_splits;
use self::classify::{Classified, SideCounts, classify_pass, piece_carries, write_children};
use self::dfs::Finisher;
use self::events::{
    MAX_REFS, PackedBox, events_of, merge_new_events, n_events, partition_events, push_events,
    radix_sort_by_position_and_kind, to_aabb, to_box,
};
use self::pieces::{PIECE, Piece, pieces};
use super::sah::{self, LeafRule, Split};
use super::{BuildConfig, Progress, root_cell};
use crate::columns::{Column, ColumnsError, Scratch, ScratchConfig};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::sys::lap;
use crate::tree::{Node, NodeId, PreOrderSink, SinkStop, TreeIr, TriId};
use rayon::prelude::*;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

/// Builds the standard tree breadth-first; see the module docs.
pub fn build(
    scene: &TriangleColumns,
    config: &BuildConfig,
    progress: Option<&Progress>,
    options: &LevelOptions,
) -> Result<(TreeIr, LevelReport), ColumnsError> {
    let (tree, _, report) = run(scene, config, progress, options, None, None, assemble)?;
    Ok((tree, report))
}

/// Builds the standard tree as [`build`] does, but hands it to `sink` in
/// pre-order instead of assembling a [`TreeIr`]: the depth-first subtrees
/// go to the sink straight from their packed streams, each chunk unmapped
/// once read, so the whole tree is never in memory as nodes. `Ok(None)`
/// when the sink stopped (it holds the reason).
pub fn build_into(
    scene: &TriangleColumns,
    config: &BuildConfig,
    progress: Option<&Progress>,
    options: &LevelOptions,
    sink: &mut impl PreOrderSink,
) -> Result<Option<LevelReport>, ColumnsError> {
    let (fed, _, report) = run(
        scene,
        config,
        progress,
        options,
        None,
        None,
        |bounds, recs, tris, subs| {
            Ok(match assemble_into(bounds, recs, tris, subs, sink) {
                Ok(cells) => (true, cells),
                Err(SinkStop) => (false, Vec::new()),
            })
        },
    )?;
    Ok(fed.then_some(report))
}

/// How [`build_top`] cuts the top of the tree into cells.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cut {
    /// At most this many cells (at least 1).
    pub max_cells: usize,
    /// An open node of at most this many references becomes a cell; a
    /// larger one is split further while the cell count allows.
    pub max_refs: usize,
    /// Open nodes with fewer references are finished in the top tree
    /// (depth-first, as [`build`] finishes its small nodes), not cut.
    pub min_refs: usize,
}

/// An open node cut off the top of the tree: all that the build of its
/// subtree needs ([`build_node`]).
#[derive(Clone, Debug, PartialEq)]
pub struct CutCell {
    /// The node's cell.
    pub cell: Aabb,
    /// The node's depth (root = 0).
    pub depth: u32,
    /// Its references: triangle ids, ascending.
    pub tris: Vec<u32>,
    /// Each reference's box (the triangle clipped to the cells above),
    /// inside `cell`.
    pub boxes: Vec<Aabb>,
}

/// The top of a tree cut into cells ([`build_top`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TopTree {
    /// The tree above the cells; each cell is an empty leaf here.
    pub tree: TreeIr,
    /// The cells in pre-order of the tree, each with the node that stands
    /// for it in `tree`.
    pub cells: Vec<(NodeId, CutCell)>,
}

/// Builds the top of the tree breadth-first, as [`build`] does, but cuts
/// open nodes off as cells by the rule of `cut`: at each level, the open
/// nodes of `cut.min_refs` to `cut.max_refs` references become cells; of
/// the larger ones, the largest are split as long as the cells made so
/// far plus the open nodes stay within `cut.max_cells` (each split adds
/// at most one node to that count), and the rest become cells too. So
/// there are at most `cut.max_cells` cells, and a cell exceeds
/// `cut.max_refs` only where the count forces it. Replacing each cell's
/// leaf by [`build_node`]'s subtree of it gives [`build`]'s tree.
pub fn build_top(
    scene: &TriangleColumns,
    config: &BuildConfig,
    progress: Option<&Progress>,
    options: &LevelOptions,
    cut: Cut,
) -> Result<(TopTree, LevelReport), ColumnsError> {
    assert!(cut.max_cells >= 1, "at least one cell");
    let (tree, cells, report) = run(scene, config, progress, options, None, Some(cut), assemble)?;
    Ok((TopTree { tree, cells }, report))
}

/// Builds the subtree of one cell of [`build_top`] breadth-first (and its
/// small nodes depth-first), as [`build`] builds it within the whole tree.
/// `scene` holds at least the triangles `node.tris` names (a cell's
/// triangles alone, renumbered in the same order, do); `config.sah` must
/// give the whole scene's depth limit (`max_depth: Some(limit)`), since
/// the limit of `scene` alone may differ. The result's `bounds` is
/// `node.cell`.
pub fn build_node(
    scene: &TriangleColumns,
    config: &BuildConfig,
    progress: Option<&Progress>,
    options: &LevelOptions,
    node: &CutCell,
) -> Result<(TreeIr, LevelReport), ColumnsError> {
    let (tree, _, report) = run(scene, config, progress, options, Some(node), None, assemble)?;
    Ok((tree, report))
}

/// The build from the scene's root, or from `start`; cut into cells by
/// `cut` if given; the result made by `out` (from the bounds, records,
/// breadth-first leaf lists and subtrees: [`assemble`] or a sink) with the
/// pre-order positions of the cells' leaves.
#[allow(clippy::type_complexity)]
fn run<T>(
    scene: &TriangleColumns,
    config: &BuildConfig,
    progress: Option<&Progress>,
    options: &LevelOptions,
    start: Option<&CutCell>,
    cut: Option<Cut>,
    out: impl FnOnce(
        Aabb,
        &[NodeRecord],
        &[TriId],
        SubStore,
    ) -> Result<(T, Vec<(NodeId, u32)>), ColumnsError>,
) -> Result<(T, Vec<(NodeId, CutCell)>, LevelReport), ColumnsError> {
    let small_threshold = cut.map_or(options.small_threshold, |c| c.min_refs);
    // The finishers' working memory comes out of the budget first.
    let reserve =
        options.finisher_reserve(small_threshold, scene.len(), rayon::current_num_threads());
    let scratch = Scratch::new(ScratchConfig {
        mem_budget: options.mem_budget.saturating_sub(reserve),
        dir: options.scratch_dir.clone(),
        scratch_limit: options.scratch_limit,
    })?;
    let start_rss = rss();
    let start_cpu = cpu_seconds();
    let mut b = LevelBuilder {
        scene,
        config,
        progress,
        options,
        scratch: &scratch,
        // Replaced once the root cell is known.
        rule: config.sah.leaf_rule(scene.len(), || Aabb::EMPTY),
        small_threshold,
        cut: cut.map(|rule| (rule, Vec::new())),
        recs: vec![NodeRecord::Open],
        leaf_tris: Vec::new(),
        // Under a budget the subtrees, most of the tree, are scratch files
        // too: held in anonymous memory they would grow past any budget.
        subs: SubStore::new(
            (options.mem_budget != u64::MAX).then(|| Arc::from(options.scratch_dir.as_path())),
        ),
        report: LevelReport {
            small_threshold: small_threshold as u64,
            finisher_reserve_bytes: reserve,
            start_rss_anon_bytes: start_rss.0,
            peak_rss_anon_bytes: start_rss.0,
            peak_rss_file_bytes: start_rss.1,
            ..LevelReport::default()
        },
    };
    let mut clock = Instant::now();
    let (bounds, root_level) = match start {
        None => b.root()?,
        Some(node) => (node.cell, b.node_level(node)?),
    };
    // A build from a node (a cell of a cut) is priced as the whole scene's
    // when the configuration gives its price scale, as `cells` does.
    b.rule = config.sah.leaf_rule(scene.len(), || bounds);
    b.report.phases.setup_s = lap(&mut clock);
    b.sample_rss();
    b.levels(root_level)?;
    // The levels' memory kept for reuse is not needed from here.
    scratch.release_pool();
    clock = Instant::now();
    let (tree, slots) = out(
        bounds,
        &b.recs,
        &b.leaf_tris,
        std::mem::replace(&mut b.subs, SubStore::new(None)),
    )?;
    let mut cut_cells: Vec<Option<CutCell>> = b
        .cut
        .take()
        .map_or_else(Vec::new, |(_, c)| c.into_iter().map(Some).collect());
    let cells = slots
        .into_iter()
        .map(|(node, k)| {
            let cell = cut_cells[k as usize]
                .take()
                .expect("each cell has one leaf");
            (node, cell)
        })
        .collect();
    b.report.phases.assemble_s = lap(&mut clock);
    b.sample_rss();
    let mut report = b.report;
    report.scratch = scratch.stats();
    report.cpu_s = start_cpu
        .zip(cpu_seconds())
        .map_or(0.0, |(start, end)| end - start);
    Ok((tree, cells, report))
}

/// One node of a level.
#[derive(Clone, Copy, Debug)]
struct LevelNode {
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
/// `u64` ([`events`]).
struct Level<'s> {
    /// The depth of every node of the level (root = 0).
    depth: u32,
    nodes: Vec<LevelNode>,
    tri: Column<'s, u32>,
    bounds: Column<'s, PackedBox>,
    ev: [Column<'s, u64>; 3],
}

struct LevelBuilder<'a> {
    scene: &'a TriangleColumns,
    config: &'a BuildConfig,
    progress: Option<&'a Progress>,
    options: &'a LevelOptions,
    scratch: &'a Scratch,
    /// The leaf rule; its price scale is the root's, set once the root
    /// cell is known ([`LevelBuilder::root`]) unless the configuration gives it.
    rule: LeafRule,
    /// Open nodes with fewer references are finished depth-first.
    small_threshold: usize,
    /// The rule of a cut into cells, and the cells cut so far.
    cut: Option<(Cut, Vec<CutCell>)>,
    /// One per node, in the order nodes were opened; record 0 is the root.
    recs: Vec<NodeRecord>,
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
    rule: LeafRule,
    progress: Option<&'a Progress>,
    chunk_words: usize,
    chunk_dir: Option<Arc<std::path::Path>>,
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
                        Finisher::new(self.scene, &self.params, self.rule, self.progress)
                            .with_new_events(self.mode)
                            .with_tiny(self.tiny),
                        Ok(SubStream::new(self.chunk_words, self.chunk_dir.clone())),
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
/// node): the subtree is the one [`super::wald_havran::build_subtree`] builds for
/// the same references, cell and depth. The slim post-pass rebuilds its
/// subtrees with it. One per worker; its scratch is reused across builds.
pub(crate) struct SubtreeBuilder<'a> {
    finisher: Finisher<'a>,
    tri: Vec<u32>,
    boxes: Vec<PackedBox>,
    ev: [Vec<u64>; 3],
}

impl<'a> SubtreeBuilder<'a> {
    pub fn new(scene: &'a TriangleColumns, config: &'a BuildConfig) -> SubtreeBuilder<'a> {
        // The scene's bounds are its root cell ([`root_cell`]); the slim pass
        // gives the price scale in `config`, so that workers skip this pass.
        let rule = config
            .sah
            .leaf_rule(scene.len(), || root_cell(scene.bounds()));
        SubtreeBuilder {
            finisher: Finisher::new(scene, &config.sah, rule, None)
                .with_tiny(DEFAULT_TINY_THRESHOLD),
            tri: Vec::new(),
            boxes: Vec::new(),
            ev: Default::default(),
        }
    }

    /// The subtree of a node at `depth` with cell `cell` and the triangle
    /// references `refs` (ascending ids, boxes inside `cell`, fewer than
    /// 2³⁰), under the depth limit of the whole scene: its nodes and leaf
    /// lists in pre-order (the [`TreeIr`] of bounds `cell`), borrowed until
    /// the next build, so that the slim pass copies out only the subtrees
    /// it keeps. `None` if the build stopped because the subtree takes at
    /// least `byte_limit` bytes in the file ([`Finisher::with_byte_limit`];
    /// `u64::MAX`: never).
    pub fn build(
        &mut self,
        refs: impl IntoIterator<Item = (TriId, Aabb)>,
        cell: Aabb,
        depth: u32,
        byte_limit: u64,
    ) -> Option<(&[Node], &[TriId])> {
        self.tri.clear();
        self.boxes.clear();
        for (t, b) in refs {
            debug_assert!(self.tri.last().is_none_or(|&last| last < t.0));
            self.tri.push(t.0);
            self.boxes.push(to_box(&b));
        }
        assert!(self.tri.len() < MAX_REFS, "too many references");
        // The finisher sweeps a node of at most the tiny threshold without
        // events, so they are made only for a larger one (98 % of the slim
        // pass's rebuilds on dieselpower are tiny).
        let tiny = self.tri.len() <= DEFAULT_TINY_THRESHOLD.min(tiny::MAX_TINY);
        for (axis, ev) in self.ev.iter_mut().enumerate() {
            ev.clear();
            if tiny {
                continue;
            }
            for (r, b) in self.boxes.iter().enumerate() {
                push_events(b, axis, r as u32, ev);
            }
            ev.sort_unstable();
        }
        let ev = [0, 1, 2].map(|k| self.ev[k].as_slice());
        let finisher = self.finisher.with_byte_limit(byte_limit);
        finisher.build(&self.tri, &self.boxes, ev, 0, cell, depth, Progress::TOTAL);
        if finisher.stopped() {
            return None;
        }
        Some(finisher.output())
    }
}

/// The children of a level's split nodes after step 4, for step 5.
struct Children<'s> {
    /// The next level's nodes: per split node, left then right.
    nodes: Vec<LevelNode>,
    /// The next level's events per axis.
    ev_len: [usize; 3],
    tri: Column<'s, u32>,
    bounds: Column<'s, PackedBox>,
    /// Per reference of the level: its placement code.
    place: Column<'s, u8>,
    /// Per reference of the level: its index in the next level and side,
    /// or [`placement::DROPPED`] (see [`write_children`]).
    new_idx: Column<'s, u32>,
    /// The clipped copies, `(child node << 32) | new reference`.
    copies: Vec<u64>,
}

impl<'a> LevelBuilder<'a> {
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
        let mut boxes = self
            .scratch
            .column_for_overwrite::<PackedBox>("bounds", n)?;
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
        Ok((bounds, self.first_level(tri, boxes, bounds, 0)?))
    }

    /// The level of one node: `node`'s references and their events.
    fn node_level(&mut self, node: &CutCell) -> Result<Level<'a>, ColumnsError> {
        let n = node.tris.len();
        Self::capacity(n)?;
        let mut tri = self.scratch.column_for_overwrite::<u32>("tri", n)?;
        let mut boxes = self
            .scratch
            .column_for_overwrite::<PackedBox>("bounds", n)?;
        tri.copy_from_slice(&node.tris);
        for (b, a) in boxes.iter_mut().zip(&node.boxes) {
            *b = to_box(a);
        }
        self.first_level(tri, boxes, node.cell, node.depth)
    }

    /// The level of one node at `depth` with cell `cell` and the
    /// references `tri` with boxes `boxes`: their events sorted.
    fn first_level(
        &mut self,
        tri: Column<'a, u32>,
        boxes: Column<'a, PackedBox>,
        cell: Aabb,
        depth: u32,
    ) -> Result<Level<'a>, ColumnsError> {
        let n = tri.len();
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
        let node = LevelNode {
            cell,
            refs: 0,
            n,
            ev: [0; 3],
            nev,
            weight: Progress::TOTAL,
            rec: 0,
        };
        Ok(Level {
            depth,
            nodes: vec![node],
            tri,
            bounds: boxes,
            ev,
        })
    }

    /// Processes `first` and the levels below it until no node is left
    /// open. A level that went to scratch files is cut into groups of
    /// consecutive nodes that fit in RAM ([`LevelBuilder::groups`]), and each
    /// group's levels run to the end, one group after another, left to
    /// right. So under a budget only the top levels, whose nodes are too
    /// large, go through scratch (49.7 M triangles under 2 GiB: the level
    /// columns wrote 44 GB when every level above the small-node threshold
    /// did). The tree is the same: a node's subtree depends on its own
    /// references alone, and groups taken left to right file their
    /// depth-first subtrees in each level's node order, as the assembly
    /// reads them.
    fn levels(&mut self, first: Level<'a>) -> Result<(), ColumnsError> {
        let mut level = Some(first);
        while let Some(l) = level {
            if let Some(groups) = self.groups(&l) {
                self.report.groups += groups.len() as u64;
                for range in groups {
                    let sub = self.sub_level(&l, range)?;
                    self.levels(sub)?;
                }
                return Ok(());
            }
            let depth = l.depth;
            level = self.level(l, depth)?;
            if self.scratch.mem_budget() != u64::MAX {
                crate::sys::release_free_heap();
            }
        }
        Ok(())
    }

    /// The groups of a level worth building apart ([`LevelBuilder::levels`]):
    /// `None` unless some of the level's columns are scratch files, it has
    /// more than one node, some node that is not finished depth-first,
    /// and more bytes than a group may hold (a third of the columns'
    /// budget, so that a group and its children fit in RAM together), and
    /// some group holds more than one node or fits.
    /// Otherwise consecutive nodes, each group as large as fits; a node
    /// larger than that is a group of its own (copied once more, into
    /// scratch: its children are cut into groups in turn). Not under a cut
    /// into cells, whose rule counts the cells of the whole level.
    fn groups(&self, l: &Level<'a>) -> Option<Vec<std::ops::Range<usize>>> {
        let budget = self.scratch.mem_budget();
        let mapped =
            l.tri.is_mapped() || l.bounds.is_mapped() || l.ev.iter().any(|c| c.is_mapped());
        // A level of small nodes alone is finished from its columns
        // where they are: copying it would only add a read and a write.
        let any_big = l.nodes.iter().any(|nd| nd.n >= self.small_threshold);
        if self.cut.is_some() || budget == u64::MAX || l.nodes.len() < 2 || !mapped || !any_big {
            return None;
        }
        let max = budget / 3;
        let bytes = |nd: &LevelNode| {
            (nd.n * (size_of::<u32>() + size_of::<PackedBox>())
                + nd.nev.iter().sum::<usize>() * size_of::<u64>()) as u64
        };
        let mut groups = Vec::new();
        let (mut start, mut held) = (0, 0u64);
        for (j, nd) in l.nodes.iter().enumerate() {
            let b = bytes(nd);
            if j > start && held + b > max {
                groups.push((start..j, held));
                (start, held) = (j, 0);
            }
            held += b;
        }
        groups.push((start..l.nodes.len(), held));
        let useful = groups.len() > 1 && groups.iter().any(|(r, b)| r.len() > 1 || *b <= max);
        useful.then(|| groups.into_iter().map(|(r, _)| r).collect())
    }

    /// The level of the nodes `range` of `l` alone: their references and
    /// events copied into columns of their own (in RAM when they fit),
    /// renumbered from 0. A node's events name its references by their
    /// index in the level's columns, so each loses the group's first
    /// reference index, which keeps every node's events in order.
    fn sub_level(
        &self,
        l: &Level<'a>,
        range: std::ops::Range<usize>,
    ) -> Result<Level<'a>, ColumnsError> {
        let nodes = &l.nodes[range];
        let (first, last) = (nodes[0], nodes[nodes.len() - 1]);
        let refs = first.refs..last.refs + last.n;
        let mut tri = self
            .scratch
            .column_for_overwrite::<u32>("tri", refs.len())?;
        let mut bounds = self
            .scratch
            .column_for_overwrite::<PackedBox>("bounds", refs.len())?;
        tri.par_chunks_mut(PIECE)
            .zip(l.tri[refs.clone()].par_chunks(PIECE))
            .for_each(|(d, s)| d.copy_from_slice(s));
        bounds
            .par_chunks_mut(PIECE)
            .zip(l.bounds[refs.clone()].par_chunks(PIECE))
            .for_each(|(d, s)| d.copy_from_slice(s));
        let base = refs.start as u64;
        let mut ev = Vec::with_capacity(3);
        for k in 0..3 {
            let evs = first.ev[k]..last.ev[k] + last.nev[k];
            let mut c = self.scratch.column_for_overwrite::<u64>("ev", evs.len())?;
            c.par_chunks_mut(PIECE)
                .zip(l.ev[k][evs].par_chunks(PIECE))
                .for_each(|(d, s)| {
                    for (d, &e) in d.iter_mut().zip(s) {
                        *d = e - base;
                    }
                });
            ev.push(c);
        }
        let nodes = nodes
            .iter()
            .map(|nd| LevelNode {
                refs: nd.refs - refs.start,
                ev: [0, 1, 2].map(|k| nd.ev[k] - first.ev[k]),
                ..*nd
            })
            .collect();
        Ok(Level {
            depth: l.depth,
            nodes,
            tri,
            bounds,
            ev: ev.try_into().expect("three axes"),
        })
    }

    /// Processes level `depth`; returns the next one, or `None` when no
    /// node is left open.
    fn level(&mut self, l: Level<'a>, depth: u32) -> Result<Option<Level<'a>>, ColumnsError> {
        let threshold = self.small_threshold;
        let (small, big): (Vec<usize>, Vec<usize>) =
            (0..l.nodes.len()).partition(|&j| l.nodes[j].n < threshold);
        let big = self.cut_cells(&l, big, depth);
        if let Some(s) = &self.options.status {
            s.level.store(depth, Ordering::Relaxed);
            s.open_nodes.store(big.len() as u64, Ordering::Relaxed);
            s.refs.store(l.tri.len() as u64, Ordering::Relaxed);
            s.small_nodes
                .fetch_add(small.len() as u64, Ordering::Relaxed);
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
            rule: self.rule,
            progress: self.progress,
            chunk_words: self.subs.chunk_words(),
            chunk_dir: self.subs.dir.clone(),
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

    /// Under a cut ([`build_top`]): turns the big nodes that become cells
    /// into cells, and returns the others.
    fn cut_cells(&mut self, l: &Level<'a>, big: Vec<usize>, depth: u32) -> Vec<usize> {
        let Some((rule, cells)) = self.cut.as_mut() else {
            return big;
        };
        // The largest first, ties in node order (a stable sort).
        let mut large: Vec<usize> = big
            .iter()
            .copied()
            .filter(|&j| l.nodes[j].n > rule.max_refs)
            .collect();
        large.sort_by_key(|&j| std::cmp::Reverse(l.nodes[j].n));
        let splits = rule.max_cells.saturating_sub(cells.len() + big.len());
        let mut split = vec![false; l.nodes.len()];
        for &j in large.iter().take(splits) {
            split[j] = true;
        }
        let mut open = Vec::with_capacity(big.len());
        for j in big {
            if split[j] {
                open.push(j);
                continue;
            }
            let nd = &l.nodes[j];
            self.recs[nd.rec as usize] = NodeRecord::Cell(cells.len() as u32);
            cells.push(CutCell {
                cell: nd.cell,
                depth,
                tris: l.tri[nd.refs..nd.refs + nd.n].to_vec(),
                boxes: l.bounds[nd.refs..nd.refs + nd.n]
                    .iter()
                    .map(to_aabb)
                    .collect(),
            });
            Progress::add(self.progress, nd.weight);
        }
        open
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
        let best = best_splits(&self.config.sah, self.rule.depth_limit, l, big);
        self.report.phases.sah_s += lap(&mut clock);

        // 3. Leaves out; splits kept.
        let splits = self.leaves(l, big, &best, depth);
        self.report.phases.leaves_s += lap(&mut clock);
        self.sample_rss();
        if splits.is_empty() {
            return Ok(None);
        }

        // 4. Classify and clip.
        let children = self.children(l, &splits)?;
        self.report.phases.classify_clip_s += lap(&mut clock);
        self.sample_rss();

        // 5. Child events.
        let next = self.child_events(l, &splits, children, depth)?;
        self.report.phases.events_s += lap(&mut clock);
        self.sample_rss();
        Ok(Some(next))
    }

    /// Step 3: the big nodes that are leaves ([`sah::is_leaf`]) append
    /// their triangle lists to the leaf list; returns the others with
    /// their splits.
    fn leaves(
        &mut self,
        l: &Level<'a>,
        big: &[usize],
        best: &[Option<Split>],
        depth: u32,
    ) -> Vec<(usize, Split)> {
        let mut splits: Vec<(usize, Split)> = Vec::new();
        for (bi, &j) in big.iter().enumerate() {
            let nd = &l.nodes[j];
            self.report.bfs_nodes += 1;
            if sah::is_leaf(
                &self.config.sah,
                best[bi].as_ref(),
                nd.n,
                depth,
                &self.rule,
                &nd.cell,
                |s| dfs::straddlers(&l.bounds[nd.refs..nd.refs + nd.n], s),
            ) {
                let start = self.leaf_tris.len();
                self.leaf_tris
                    .extend(l.tri[nd.refs..nd.refs + nd.n].iter().map(|&t| TriId(t)));
                self.recs[nd.rec as usize] = NodeRecord::Leaf {
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
        splits
    }

    /// Step 4: classifies the split nodes' references and clips the
    /// straddlers, opens the children (per split node, left then right)
    /// and writes their references into the next level's columns.
    fn children(
        &mut self,
        l: &Level<'a>,
        splits: &[(usize, Split)],
    ) -> Result<Children<'a>, ColumnsError> {
        let rsegs: Vec<(usize, usize)> = splits
            .iter()
            .map(|&(j, _)| (l.nodes[j].refs, l.nodes[j].n))
            .collect();
        let rpieces = pieces(&rsegs, PIECE, |_| true);
        let mut place = self
            .scratch
            .column_for_overwrite::<u8>("place", l.tri.len())?;
        let classified = classify_pass(self.scene, l, splits, &rsegs, &rpieces, &mut place);
        self.report.clipped += classified
            .iter()
            .map(|c| c.clipped.len() as u64)
            .sum::<u64>();

        let rcarry = piece_carries(&rpieces, &classified);
        let (next_nodes, refs_at, ev_at) = self.open_children(l, splits, &rpieces, &classified);
        Self::capacity(refs_at)?;
        let mut tri = self.scratch.column_for_overwrite::<u32>("tri", refs_at)?;
        let mut boxes = self
            .scratch
            .column_for_overwrite::<PackedBox>("bounds", refs_at)?;
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
        Ok(Children {
            nodes: next_nodes,
            ev_len: ev_at,
            tri,
            bounds: boxes,
            place,
            new_idx,
            copies,
        })
    }

    /// The children of the split nodes as the next level's nodes (per
    /// split node, left then right), their records opened and their
    /// reference and event ranges laid out in order; returns them with the
    /// next level's reference and per-axis event counts.
    fn open_children(
        &mut self,
        l: &Level<'a>,
        splits: &[(usize, Split)],
        rpieces: &[Piece],
        classified: &[Classified],
    ) -> (Vec<LevelNode>, usize, [usize; 3]) {
        let mut totals = vec![SideCounts::default(); splits.len()];
        for (p, c) in rpieces.iter().zip(classified) {
            for (k, si) in p.nodes.clone().enumerate() {
                totals[si] = totals[si] + c.counts[k];
            }
        }
        let mut next_nodes = Vec::with_capacity(2 * splits.len());
        let (mut refs_at, mut ev_at) = (0usize, [0usize; 3]);
        for (si, &(j, split)) in splits.iter().enumerate() {
            let nd = &l.nodes[j];
            let t = &totals[si];
            let (lc, rc) = nd.cell.split(split.axis as usize, split.pos);
            let (wl, wr) = Progress::share(nd.weight, t.n[0], t.n[1]);
            let left = self.recs.len() as u32;
            self.recs[nd.rec as usize] = NodeRecord::Inner {
                axis: split.axis,
                pos: split.pos,
                left,
                right: left + 1,
            };
            for (side, (cell, weight)) in [(lc, wl), (rc, wr)].into_iter().enumerate() {
                let nev = [0, 1, 2].map(|k| t.inherited[side][k] + t.new[side][k]);
                next_nodes.push(LevelNode {
                    cell,
                    refs: refs_at,
                    n: t.n[side],
                    ev: ev_at,
                    nev,
                    weight,
                    rec: self.recs.len() as u32,
                });
                self.recs.push(NodeRecord::Open);
                refs_at += t.n[side];
                for k in 0..3 {
                    ev_at[k] += nev[k];
                }
            }
        }
        (next_nodes, refs_at, ev_at)
    }

    /// Step 5: the children's event lists (the inherited events
    /// partitioned, the clipped copies' events sorted and merged in);
    /// returns the next level.
    fn child_events(
        &self,
        l: &Level<'a>,
        splits: &[(usize, Split)],
        children: Children<'a>,
        depth: u32,
    ) -> Result<Level<'a>, ColumnsError> {
        let Children {
            nodes,
            ev_len,
            tri,
            bounds,
            place,
            new_idx,
            copies,
        } = children;
        let mut ev = Vec::with_capacity(3);
        for &len in &ev_len {
            ev.push(self.scratch.column_for_overwrite::<u64>("ev", len)?);
        }
        let mut ev: [Column<'a, u64>; 3] = ev.try_into().expect("three axes");
        partition_events(l, splits, &place, &new_idx, &nodes, &mut ev);
        drop(place);
        drop(new_idx);
        merge_new_events(copies, &bounds, &nodes, &mut ev, self.options.new_events);
        Ok(Level {
            depth: depth + 1,
            nodes,
            tri,
            bounds,
            ev,
        })
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
            self.recs[l.nodes[j].rec as usize] = NodeRecord::Sub(depth);
        }
        self.report.small_nodes += small.len() as u64;
        Ok(())
    }
}
