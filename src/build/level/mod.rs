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
//! ascending by triangle) and, per axis, its events sorted as in the
//! Wald-Havran builder (`events`). One call of `LevelBuilder::level` turns level `d`
//! into level `d + 1` (the paper's §4, Figure 2):
//!
//! 1. **Small nodes** (fewer than `small_threshold` references) are handed
//!    to the depth-first builder (`finish`, `dfs`: the Wald-Havran builder's algorithm
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
//! 4. **Classify and clip** (`children`, `classify`): references go left,
//!    right or both ([`super::classify`]); straddlers are clipped to each child
//!    ([`super::clip_straddler`],
//!    perfect splits). Prefix counts place each child's references.
//! 5. **Child events** (`children`, `events`): inherited events keep their order through a stable
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
mod children;
mod classify;
mod cut;
mod dfs;
mod events;
mod finish;
mod options;
mod pieces;
mod placement;
mod report;
mod tiny;

pub use self::cut::{Cut, CutCell, TopTree, build_node, build_top};
pub(crate) use self::finish::SubtreeBuilder;
pub use self::options::{
    DEFAULT_SMALL_THRESHOLD, DEFAULT_TINY_THRESHOLD, FINISHER_BYTES_PER_REF, LevelOptions,
    LevelStatus, MAX_BUDGET_SMALL_THRESHOLD, NewEvents,
};
pub use self::report::{LevelReport, Phases};
pub use crate::columns::ScratchStats;
pub use crate::sys::{cpu_seconds, rss};

use self::assemble::{NodeRecord, SubStore, SubStream, assemble, assemble_into};
use self::best_split::best_splits;
use self::events::{
    MAX_REFS, PackedBox, events_of, n_events, radix_sort_by_position_and_kind, to_aabb, to_box,
};
use self::finish::Finish;
use self::pieces::PIECE;
use super::sah::{self, LeafRule, Split};
use super::{BuildConfig, Progress, root_cell};
use crate::columns::{Column, ColumnsError, Scratch, ScratchConfig};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::sys::lap;
use crate::tree::{NodeId, PreOrderSink, SinkStop, TreeIr, TriId};
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
        mem_budget: options.mem_budget.map(|b| b.saturating_sub(reserve)),
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
            (options.mem_budget.is_some()).then(|| Arc::from(options.scratch_dir.as_path())),
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
            if self.scratch.mem_budget().is_some() {
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
        let budget = budget?;
        if self.cut.is_some() || l.nodes.len() < 2 || !mapped || !any_big {
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
