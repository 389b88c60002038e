//! A build in cells: the top of the tree is built breadth-first and cut
//! into at most K cells ([`crate::build::level::build_top`]), each cell's
//! subtree is built as an independent step from a file of its own (on
//! this machine or another), and the parts are stitched into the tree the
//! monolithic build gives, node for node.
//!
//! Consumes a scene, the build parameters and K. Produces, in a work
//! directory, a **plan** (`plan.kdplan`: the top tree, the cut, and each
//! cell's identity), one **cell file** per cell (`cell-NNNNN.kdcell`:
//! everything its build needs, the triangles included, so a worker needs
//! no other input) and, once built, one **part** per cell
//! (`cell-NNNNN.kdpart`: the cell's subtree); [`stitch`] puts the top tree
//! and the parts together in canonical pre-order. Every file is written
//! atomically ([`crate::fsio`]); the plan goes last, so a plan on disk
//! means every cell file was written.
//!
//! **Identity and resume.** A cell's identity ([`CellId`]) is the CRC-32
//! and length of its cell file. The plan records each cell's; a part
//! records the identity of the cell file it was built from, and is kept on
//! resume only if it reads back whole (length, checksum, structure) and
//! names the plan's identity. Planning is deterministic, so planning again
//! writes the same cell files, and the parts already built stay valid.
//!
//! **The cut.** The cell bound is `⌈N/K⌉` references ([`cut_for`]), so
//! a cell holds about a K-th of the scene. Nodes below
//! `min(small threshold, bound / 8)` references are finished in the top
//! tree (as the monolithic build finishes its small nodes), so a cell is
//! never a handful of triangles.
//!
//! Layouts (little-endian; each file ends in the CRC-32 of every byte
//! before it, and its length is checked against its counts before
//! anything is allocated):
//!
//! | file | header | then |
//! |---|---|---|
//! | plan | magic `SLIMKPL\0`, version 2, reserved 0, scene hash `u64`, triangles `u64`, `K_T`, `K_I`, `λ`, `μ`, price scale (`f64`), depth limit `u32`, K `u32`, cell bound `u64`, minimum `u64`, root box (6 `f32`), nodes `u64`, leaf entries `u64`, cells `u64` | nodes (3 `u32` each), leaf entries (`u32`), per cell: node `u32`, references `u64`, CRC `u32`, length `u64` |
//! | cell | magic `SLIMKDC\0`, version 2, reserved 0, cell number `u32`, cells `u32`, `K_T`, `K_I`, `λ`, `μ`, price scale (`f64`), depth limit `u32`, depth `u32`, cell box (6 `f32`), references `u64` | triangle ids (`u32`, ascending), boxes (6 `f32`), triangles (9 `f32`) |
//! | part | magic `SLIMKPT\0`, version 2, reserved 0, cell CRC `u32`, reserved 0, cell length `u64`, cell box (6 `f32`), nodes `u64`, leaf entries `u64` | nodes (3 `u32` each), leaf entries (`u32`, the scene's triangle ids) |
//!
//! A node is `[axis, position bits, right child]` or `[3, start, count]`
//! for a leaf (the level builder's packed form).

mod files;

pub use files::{
    CellId, CellInput, PLAN_NAME, Plan, PlanCell, cell_id, cell_path, part_path, plan_path,
    read_cell, read_part, read_plan, write_cell, write_part, write_plan,
};

use crate::build::level::{self, CutCell, LevelOptions, TopTree};
use crate::build::{BuildConfig, BuildError, SahParams};
use crate::scene::{InvalidColumns, TriangleColumns};
use crate::tree::{Node, NodeId, PreOrderSink, TreeIr, TriId};
use std::fmt;
use std::path::{Path, PathBuf};

/// Why a step of a build in cells failed; every variant names its file.
#[derive(Debug, thiserror::Error)]
pub enum CellsError {
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        source: std::io::Error,
    },
    /// A plan, cell or part file is not one, or is corrupt or truncated.
    #[error("{}: {what}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        what: Corruption,
    },
    /// A file that reads back whole does not belong here (a part of
    /// another cell, a plan of another scene).
    #[error("{}: {what}", path.display())]
    Mismatch {
        /// The file.
        path: PathBuf,
        /// What does not match.
        what: CellMismatch,
    },
    /// The level builder failed (its columns).
    #[error("{0}")]
    Build(BuildError),
}

/// The three files of a build in cells, as their errors name them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileKind {
    /// The plan (`plan.kdplan`).
    Plan,
    /// A cell's input.
    Cell,
    /// A cell's built subtree.
    Part,
}

impl fmt::Display for FileKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FileKind::Plan => "plan",
            FileKind::Cell => "cell",
            FileKind::Part => "part",
        })
    }
}

/// What is wrong with a plan, cell or part file ([`CellsError::Corrupt`]).
#[derive(Debug, thiserror::Error)]
pub enum Corruption {
    /// The file does not start with its kind's magic.
    #[error("not a {kind} file (wrong magic)")]
    Magic {
        /// The kind of file expected.
        kind: FileKind,
    },
    /// The file is shorter than its header and checksum.
    #[error("truncated {kind} file ({len} bytes, the header alone is {needed})")]
    Header {
        /// The kind of file.
        kind: FileKind,
        /// Its length.
        len: usize,
        /// The header's and the checksum's bytes.
        needed: usize,
    },
    /// A format version this slimkd does not read.
    #[error(
        "{kind} file version {version}, this slimkd reads version {}",
        files::VERSION
    )]
    Version {
        /// The kind of file.
        kind: FileKind,
        /// The version the file states.
        version: u32,
    },
    /// The file's length is not the one its counts give.
    #[error("truncated or overlong {kind} file ({len} bytes, its counts say {expected})")]
    Length {
        /// The kind of file.
        kind: FileKind,
        /// Its length.
        len: u64,
        /// The length its counts give.
        expected: u64,
    },
    /// The header's counts give no length that fits in 64 bits.
    #[error("corrupt {kind} file (impossible counts)")]
    Counts {
        /// The kind of file.
        kind: FileKind,
    },
    /// The stored checksum is not the contents'.
    #[error("corrupt {kind} file (checksum mismatch)")]
    Checksum {
        /// The kind of file.
        kind: FileKind,
    },
    /// The SAH parameters are out of range.
    #[error("corrupt SAH parameters")]
    SahParams,
    /// A node's words are no node.
    #[error("corrupt node {0}")]
    Node(usize),
    /// The nodes are not in pre-order.
    #[error("nodes not in pre-order at node {0}")]
    PreOrder(usize),
    /// A node lies deeper than the depth limit.
    #[error("too deep at node {0}")]
    TooDeep(usize),
    /// An inner node's right child is not after its left subtree.
    #[error("right child out of place at node {0}")]
    RightChild(usize),
    /// A leaf's list does not follow the previous leaf's.
    #[error("leaf list out of place at node {0}")]
    LeafList(usize),
    /// A leaf's triangles are not ascending.
    #[error("leaf list not ascending at node {0}")]
    LeafOrder(usize),
    /// Nodes or leaf entries that the tree does not reach.
    #[error("nodes or leaf entries outside the tree")]
    OutsideTree,
    /// A cell's index is not below the plan's cell count.
    #[error("cell {index} of {n_cells}")]
    CellIndex {
        /// The cell's index.
        index: u32,
        /// The plan's cell count.
        n_cells: u32,
    },
    /// A cell's depth exceeds the depth limit, or the limit the format's.
    #[error("depth {depth} under the limit {limit}")]
    Depth {
        /// The cell's depth.
        depth: u32,
        /// The depth limit.
        limit: u32,
    },
    /// A cell's box is not finite.
    #[error("corrupt cell box")]
    CellBox,
    /// A cell's triangle ids are not ascending.
    #[error("triangle ids not ascending")]
    TriangleOrder,
    /// A reference's box is not finite.
    #[error("corrupt box of reference {0}")]
    RefBox(usize),
    /// A cell's triangles are no scene.
    #[error("invalid triangles: {0}")]
    Triangles(InvalidColumns),
    /// A part's header is out of range.
    #[error("corrupt part header")]
    PartHeader,
    /// A plan's header is out of range.
    #[error("corrupt plan header")]
    PlanHeader,
    /// A plan's cell stands at a node that is not an empty leaf.
    #[error("cell {0} at a node that is no empty leaf")]
    CellNode(usize),
    /// A plan's top tree names a triangle beyond the scene.
    #[error("a triangle out of range")]
    PlanTriangle,
    /// A part names a triangle beyond the scene.
    #[error("triangle {tri} out of range (the scene has {n_tris})")]
    PartTriangle {
        /// The triangle.
        tri: u32,
        /// The scene's triangle count.
        n_tris: u64,
    },
    /// A part to write holds a standard tree, not a slim one.
    #[error("a part holds a standard tree (no hoisted triangles)")]
    StandardTree,
}

/// How a file that reads back whole does not belong
/// ([`CellsError::Mismatch`]).
#[derive(Debug, thiserror::Error)]
pub enum CellMismatch {
    /// A part built from another cell file.
    #[error("a part of another cell file (its cell's checksum differs)")]
    PartOfAnotherCell,
    /// A cell file that is not the plan's cell of its index.
    #[error("not cell {index} of the plan {} (plan again: slimkd build --cells)", plan.display())]
    NotPlannedCell {
        /// The cell's index.
        index: usize,
        /// The plan.
        plan: PathBuf,
    },
    /// A plan made for another scene.
    #[error("the plan of another scene than {} (its triangles or geometry hash differ)", scene.display())]
    AnotherScene {
        /// The scene given.
        scene: PathBuf,
    },
}

impl From<BuildError> for CellsError {
    fn from(e: BuildError) -> CellsError {
        CellsError::Build(e)
    }
}

/// The cut for at most `k` cells of a scene of `n` triangles: cells of up
/// to `⌈n/k⌉` references, none below `min(small_threshold, bound / 8)`.
pub fn cut_for(n: usize, k: usize, small_threshold: usize) -> level::Cut {
    let k = k.max(1);
    let max_refs = n.div_ceil(k).max(1);
    level::Cut {
        max_cells: k,
        max_refs,
        min_refs: small_threshold.min(max_refs / 8).max(1),
    }
}

/// The top tree and the cells of a build in `k` cells, in memory.
pub fn plan(
    scene: &TriangleColumns,
    config: &BuildConfig,
    options: &LevelOptions,
    k: usize,
    progress: Option<&crate::progress::Progress>,
) -> Result<TopTree, CellsError> {
    let cut = cut_for(scene.len(), k, options.small_threshold);
    let (top, _) = level::build_top(scene, config, progress, options, cut)?;
    Ok(top)
}

/// Writes the plan of `top` and its cell files into `dir` (which must
/// exist): the cell files first, the plan last. Returns the plan.
pub fn write_plan_dir(
    dir: &Path,
    scene: &TriangleColumns,
    config: &BuildConfig,
    k: usize,
    small_threshold: usize,
    scene_hash: u64,
    top: TopTree,
) -> Result<Plan, CellsError> {
    let n_cells = top.cells.len() as u32;
    let depth_limit = config.sah.depth_limit(scene.len());
    // Each cell's nodes are priced as nodes of the whole tree.
    let sah = SahParams {
        max_depth: None,
        price_scale: Some(
            config
                .sah
                .price_scale
                .unwrap_or_else(|| crate::build::sah::price_scale(&top.tree.bounds, scene.len())),
        ),
        ..config.sah
    };
    let mut cells = Vec::with_capacity(top.cells.len());
    for (i, (node, cell)) in top.cells.iter().enumerate() {
        let id = write_cell(
            &cell_path(dir, i),
            scene,
            &sah,
            depth_limit,
            i as u32,
            n_cells,
            cell,
        )?;
        cells.push(PlanCell {
            node: *node,
            refs: cell.tris.len() as u64,
            id,
        });
    }
    let plan = Plan {
        scene_hash,
        n_tris: scene.len() as u64,
        sah,
        depth_limit,
        cut: cut_for(scene.len(), k, small_threshold),
        top: top.tree,
        cells,
    };
    write_plan(&plan_path(dir), &plan)?;
    Ok(plan)
}

/// Whether `plan` is the plan of this build: the same scene, parameters
/// and cut.
pub fn plan_matches(
    plan: &Plan,
    scene: &TriangleColumns,
    config: &BuildConfig,
    k: usize,
    small_threshold: usize,
    scene_hash: u64,
) -> bool {
    plan.scene_hash == scene_hash
        && plan.n_tris == scene.len() as u64
        && plan.sah.k_t.to_bits() == config.sah.k_t.to_bits()
        && plan.sah.k_i.to_bits() == config.sah.k_i.to_bits()
        && plan.sah.lambda_empty.to_bits() == config.sah.lambda_empty.to_bits()
        && plan.sah.split_price.to_bits() == config.sah.split_price.to_bits()
        && config
            .sah
            .price_scale
            .is_none_or(|s| Some(s) == plan.sah.price_scale)
        && plan.depth_limit == config.sah.depth_limit(scene.len())
        && plan.cut == cut_for(scene.len(), k, small_threshold)
}

/// Builds the subtree of a cell: the level builder from the cell's node,
/// over the cell's own triangles; the result names the scene's triangle
/// ids, as the monolithic build's subtree of that node does.
pub fn build_cell(input: &CellInput, options: &LevelOptions) -> Result<TreeIr, CellsError> {
    let config = BuildConfig {
        sah: SahParams {
            max_depth: Some(input.depth_limit),
            ..input.sah
        },
    };
    let local = CutCell {
        cell: input.cell,
        depth: input.depth,
        tris: (0..input.tris.len() as u32).collect(),
        boxes: input.boxes.clone(),
    };
    let (mut tree, _) = level::build_node(&input.scene, &config, None, options, &local)?;
    for t in &mut tree.leaf_tris {
        *t = TriId(input.tris[t.0 as usize]);
    }
    Ok(tree)
}

/// The whole tree: `top` with its cell leaves `slots` (in pre-order)
/// replaced by the subtrees `part(i)` of cell `i`, in canonical pre-order.
pub fn stitch<E>(
    top: &TreeIr,
    slots: &[NodeId],
    mut part: impl FnMut(usize) -> Result<TreeIr, E>,
) -> Result<TreeIr, E> {
    let mut nodes: Vec<Node> = Vec::with_capacity(top.nodes.len());
    let mut leaf_tris: Vec<TriId> = Vec::with_capacity(top.leaf_tris.len());
    // Where each node of `top` went.
    let mut at = vec![0u32; top.nodes.len()];
    let mut next_slot = 0;
    for (i, node) in top.nodes.iter().enumerate() {
        at[i] = nodes.len() as u32;
        if slots.get(next_slot).is_some_and(|s| s.0 as usize == i) {
            let sub = part(next_slot)?;
            next_slot += 1;
            let base = nodes.len() as u32;
            let tbase = leaf_tris.len() as u32;
            nodes.extend(sub.nodes.iter().map(|n| match *n {
                Node::Inner {
                    axis,
                    pos,
                    right,
                    t_ref,
                } => Node::Inner {
                    axis,
                    pos,
                    right: NodeId(right.0 + base),
                    t_ref,
                },
                Node::Leaf { start, count } => Node::Leaf {
                    start: start + tbase,
                    count,
                },
            }));
            leaf_tris.extend_from_slice(&sub.leaf_tris);
            continue;
        }
        match *node {
            Node::Inner { .. } => nodes.push(*node),
            Node::Leaf { start, count } => {
                nodes.push(Node::Leaf {
                    start: leaf_tris.len() as u32,
                    count,
                });
                leaf_tris.extend_from_slice(top.leaf(start, count));
            }
        }
    }
    assert_eq!(
        next_slot,
        slots.len(),
        "every cell's leaf is a node of the top"
    );
    for (i, node) in top.nodes.iter().enumerate() {
        if let Node::Inner { right, .. } = *node
            && let Node::Inner { right: r, .. } = &mut nodes[at[i] as usize]
        {
            *r = NodeId(at[right.0 as usize]);
        }
    }
    Ok(TreeIr {
        bounds: top.bounds,
        nodes,
        leaf_tris,
    })
}

/// [`stitch`] handed to `sink` node by node in canonical pre-order, one
/// part in memory at a time, so that the stitched tree never is (the
/// streamed writer takes it into the file). `Ok(false)` where the sink
/// stopped (it holds the reason) or where `slots` are not leaves of `top`
/// in pre-order (then nothing is fed, and a writer refuses the stream).
pub fn stitch_into<E>(
    top: &TreeIr,
    slots: &[NodeId],
    mut part: impl FnMut(usize) -> Result<TreeIr, E>,
    sink: &mut impl PreOrderSink,
) -> Result<bool, E> {
    let in_order = slots.windows(2).all(|w| w[0].0 < w[1].0)
        && slots
            .iter()
            .all(|s| matches!(top.nodes.get(s.0 as usize), Some(Node::Leaf { .. })));
    if !in_order || sink.bounds(top.bounds).is_err() {
        return Ok(false);
    }
    let mut next_slot = 0;
    // A canonical tree's node order is its pre-order.
    for (i, node) in top.nodes.iter().enumerate() {
        let fed = if slots.get(next_slot).is_some_and(|s| s.0 as usize == i) {
            let sub = part(next_slot)?;
            next_slot += 1;
            sub.feed_nodes(sink)
        } else {
            match *node {
                Node::Inner {
                    axis, pos, t_ref, ..
                } => sink.inner(axis, pos, t_ref),
                Node::Leaf { start, count } => sink.leaf(top.leaf(start, count)),
            }
        };
        if fed.is_err() {
            return Ok(false);
        }
    }
    Ok(true)
}

/// The state of a work directory before the cells are built: the plan
/// and, per cell, whether its part is built already.
pub struct Prepared {
    /// The plan (read back, or made now).
    pub plan: Plan,
    /// Whether the plan was made now (false: resumed).
    pub planned: bool,
    /// Per cell: its part reads back whole and names the cell's identity.
    pub done: Vec<bool>,
}

/// Opens or makes the plan of a build in `k` cells in `dir` (made if
/// missing): a plan there that reads back and matches the scene and
/// parameters is kept, and so is every part that reads back whole with
/// its cell's identity; otherwise the directory is planned anew (the same
/// cell files again, so built parts stay valid).
#[allow(clippy::too_many_arguments)]
pub fn prepare(
    dir: &Path,
    scene: &TriangleColumns,
    config: &BuildConfig,
    options: &LevelOptions,
    k: usize,
    scene_hash: u64,
    progress: Option<&crate::progress::Progress>,
) -> Result<Prepared, CellsError> {
    std::fs::create_dir_all(dir).map_err(|source| CellsError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let small = options.small_threshold;
    let kept = match read_plan(&plan_path(dir)) {
        Ok(p) if plan_matches(&p, scene, config, k, small, scene_hash) => Some(p),
        _ => None,
    };
    let (plan, planned) = match kept {
        Some(p) => (p, false),
        None => {
            let top = self::plan(scene, config, options, k, progress)?;
            (
                write_plan_dir(dir, scene, config, k, small, scene_hash, top)?,
                true,
            )
        }
    };
    let done: Vec<bool> = (0..plan.cells.len())
        .map(|i| read_part(&part_path(dir, i), plan.cells[i].id).is_ok())
        .collect();
    // A cell to build whose file is missing or damaged: plan again (the
    // same files; the parts kept stay valid).
    let damaged = (0..plan.cells.len())
        .any(|i| !done[i] && cell_id(&cell_path(dir, i)).ok() != Some(plan.cells[i].id));
    if damaged && !planned {
        let top = self::plan(scene, config, options, k, progress)?;
        let plan = write_plan_dir(dir, scene, config, k, small, scene_hash, top)?;
        let done = (0..plan.cells.len())
            .map(|i| read_part(&part_path(dir, i), plan.cells[i].id).is_ok())
            .collect();
        return Ok(Prepared {
            plan,
            planned: true,
            done,
        });
    }
    Ok(Prepared {
        plan,
        planned,
        done,
    })
}

/// Reads cell `i` of `plan` from `dir` and checks that it is the plan's
/// cell (its identity).
pub fn read_planned_cell(dir: &Path, plan: &Plan, i: usize) -> Result<CellInput, CellsError> {
    let path = cell_path(dir, i);
    let (input, id) = read_cell(&path)?;
    if id != plan.cells[i].id || input.index as usize != i {
        return Err(CellsError::Mismatch {
            path,
            what: CellMismatch::NotPlannedCell {
                index: i,
                plan: plan_path(dir),
            },
        });
    }
    Ok(input)
}

/// The whole tree from the plan and parts of `dir`: every part must read
/// back whole and name its cell's identity.
pub fn stitch_dir(dir: &Path, plan: &Plan) -> Result<TreeIr, CellsError> {
    let slots: Vec<NodeId> = plan.cells.iter().map(|c| c.node).collect();
    stitch(&plan.top, &slots, |i| read_checked_part(dir, plan, i))
}

/// [`stitch_dir`] handed to `sink` ([`stitch_into`]): `Ok(false)` where
/// the sink stopped.
pub fn stitch_dir_into(
    dir: &Path,
    plan: &Plan,
    sink: &mut impl PreOrderSink,
) -> Result<bool, CellsError> {
    let slots: Vec<NodeId> = plan.cells.iter().map(|c| c.node).collect();
    stitch_into(&plan.top, &slots, |i| read_checked_part(dir, plan, i), sink)
}

/// Cell `i`'s part, read back and its triangles checked against the scene.
fn read_checked_part(dir: &Path, plan: &Plan, i: usize) -> Result<TreeIr, CellsError> {
    let path = part_path(dir, i);
    let tree = read_part(&path, plan.cells[i].id)?;
    if let Some(&t) = tree
        .leaf_tris
        .iter()
        .find(|t| u64::from(t.0) >= plan.n_tris)
    {
        return Err(CellsError::Corrupt {
            path,
            what: Corruption::PartTriangle {
                tri: t.0,
                n_tris: plan.n_tris,
            },
        });
    }
    Ok(tree)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_messages() {
        let corrupt = |what| CellsError::Corrupt {
            path: PathBuf::from("/w/cell-0.kdcell"),
            what,
        };
        let cases = [
            (
                corrupt(Corruption::Version {
                    kind: FileKind::Cell,
                    version: 1,
                }),
                "/w/cell-0.kdcell: cell file version 1, this slimkd reads version 2",
            ),
            (
                corrupt(Corruption::Length {
                    kind: FileKind::Plan,
                    len: 10,
                    expected: 12,
                }),
                "/w/cell-0.kdcell: truncated or overlong plan file (10 bytes, its counts say 12)",
            ),
            (
                corrupt(Corruption::LeafOrder(7)),
                "/w/cell-0.kdcell: leaf list not ascending at node 7",
            ),
            (
                CellsError::Mismatch {
                    path: PathBuf::from("/w/cell-3.kdcell"),
                    what: CellMismatch::NotPlannedCell {
                        index: 3,
                        plan: PathBuf::from("/w/plan.kdplan"),
                    },
                },
                "/w/cell-3.kdcell: not cell 3 of the plan /w/plan.kdplan (plan again: slimkd build --cells)",
            ),
        ];
        for (e, want) in cases {
            assert_eq!(e.to_string(), want);
        }
    }
}
