//! The build in cells: the top of the tree cut into cells ([`build_top`])
//! and the subtree of one cell ([`build_node`]), which together make
//! [`build`](super::build)'s tree.

use super::assemble::assemble;
use super::{LevelOptions, LevelReport, Progress, run};
use crate::build::BuildConfig;
use crate::columns::ColumnsError;
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::{NodeId, TreeIr};

/// How [`build_top`] cuts the top of the tree into cells.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cut {
    /// At most this many cells (at least 1).
    pub max_cells: usize,
    /// An open node of at most this many references becomes a cell; a
    /// larger one is split further while the cell count allows.
    pub max_refs: usize,
    /// Open nodes with fewer references are finished in the top tree
    /// (depth-first, as [`build`](super::build) finishes its small nodes), not cut.
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

/// Builds the top of the tree breadth-first, as [`build`](super::build) does, but cuts
/// open nodes off as cells by the rule of `cut`: at each level, the open
/// nodes of `cut.min_refs` to `cut.max_refs` references become cells; of
/// the larger ones, the largest are split as long as the cells made so
/// far plus the open nodes stay within `cut.max_cells` (each split adds
/// at most one node to that count), and the rest become cells too. So
/// there are at most `cut.max_cells` cells, and a cell exceeds
/// `cut.max_refs` only where the count forces it. Replacing each cell's
/// leaf by [`build_node`]'s subtree of it gives [`build`](super::build)'s tree.
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
/// small nodes depth-first), as [`build`](super::build) builds it within the whole tree.
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
