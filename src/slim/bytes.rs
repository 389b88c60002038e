//! The byte model of [`HoistRule::Bytes`](super::HoistRule::Bytes): what
//! a subtree takes in the `.kd` file as the writer lays it out (format
//! version 2, [`ByteLayout::V2`]), for a built [`TreeIr`] and for a range
//! of the work tree, and the lower bound on a rebuilt subtree that lets
//! the pass skip a rebuild. [`tree_bytes`] counts a whole tree in either
//! [`ByteLayout`], for measurements of what hoisting saves.

use super::work::{Work, WorkNode};
use crate::format::node::fits_leaf16;
use crate::scene::TriangleColumns;
use crate::tree::{Node, TreeIr, TriId};

/// How the nodes of a tree are counted in bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ByteLayout {
    /// The `.kd` file's version-1 layout: every node, empty leaves
    /// included, is an 8-byte word, a hoisted triangle one more, and every
    /// leaf's triangles are indices (2 or 4 bytes each).
    V1,
    /// The `.kd` file of today (version 2), which the byte rule of the
    /// slim pass counts in: an empty leaf takes no word, except the left
    /// child of an inner node whose two children are empty (and an empty
    /// root); a leaf with one triangle holds it in its own word (no
    /// index); the rest as [`ByteLayout::V1`].
    V2,
}

/// The tree bytes of `tree` (nodes, T-references and leaf indices; no
/// geometry) in `layout`, with the file's triangle numbering (`reordered`:
/// the Morton ranks of `--reorder`, else the input ids). In
/// [`ByteLayout::V2`] this is the written file's `tree_bytes`
/// (`format::TreeFigures::tree_bytes`); in [`ByteLayout::V1`] what the
/// version-1 layout would take.
pub fn tree_bytes(
    tree: &TreeIr,
    scene: &TriangleColumns,
    reordered: bool,
    layout: ByteLayout,
) -> u64 {
    ByteModel::new(scene, reordered)
        .with_layout(layout)
        .tree(tree)
}

/// How [`HoistRule::Bytes`](super::HoistRule::Bytes) counts bytes.
pub(super) struct ByteModel {
    /// The file id of each triangle (`None`: the input id).
    rank: Option<Vec<u32>>,
    layout: ByteLayout,
}

impl ByteModel {
    pub(super) fn with_layout(self, layout: ByteLayout) -> ByteModel {
        ByteModel { layout, ..self }
    }

    /// The model of the file as written (version 2), with or without
    /// Morton reordering.
    pub(super) fn new(scene: &TriangleColumns, reordered: bool) -> ByteModel {
        ByteModel {
            layout: ByteLayout::V2,
            rank: reordered.then(|| {
                let perm = scene.morton_order();
                let mut rank = vec![0u32; perm.len()];
                for (new, &old) in perm.iter().enumerate() {
                    rank[old as usize] = new as u32;
                }
                rank
            }),
        }
    }

    /// The bytes of a leaf: its word and its indices. In version 2 an
    /// empty leaf counts none here (its parent's word says it is empty; the
    /// exception is counted with the parent, [`ByteModel::inner`]).
    pub(super) fn leaf(&self, tris: &[TriId]) -> u64 {
        match (self.layout, tris.len()) {
            (ByteLayout::V2, 0) => return 0,
            (ByteLayout::V2, 1) => return 8,
            _ => {}
        }
        let n = tris.len();
        let wide = match &self.rank {
            Some(r) => !fits_leaf16(n, tris.iter().map(|t| r[t.0 as usize])),
            None => !fits_leaf16(n, tris.iter().map(|t| t.0)),
        };
        8 + n as u64 * if wide { 4 } else { 2 }
    }

    /// The bytes of an inner node: its word, its T-reference word, and in
    /// version 2 the empty-leaf word its left child keeps when both
    /// children are empty leaves.
    pub(super) fn inner(&self, t_ref: bool, both_empty: bool) -> u64 {
        let kept = self.layout == ByteLayout::V2 && both_empty;
        8 + 8 * u64::from(t_ref) + 8 * u64::from(kept)
    }

    pub(super) fn tree(&self, t: &TreeIr) -> u64 {
        self.nodes(&t.nodes, &t.leaf_tris)
    }

    /// [`ByteModel::tree`] of a tree given as its pre-order nodes and leaf
    /// lists.
    pub(super) fn nodes(&self, nodes: &[Node], leaf_tris: &[TriId]) -> u64 {
        let empty = |i: usize| matches!(nodes.get(i), Some(Node::Leaf { count: 0, .. }));
        let words: u64 = nodes
            .iter()
            .enumerate()
            .map(|(i, n)| match *n {
                Node::Inner { t_ref, right, .. } => {
                    self.inner(t_ref.is_some(), empty(i + 1) && empty(right.0 as usize))
                }
                Node::Leaf { start, count } => {
                    self.leaf(&leaf_tris[start as usize..(start + count) as usize])
                }
            })
            .sum();
        words + if empty(0) { self.empty_root() } else { 0 }
    }

    /// The word an empty root keeps (in version 2; in version 1 it is
    /// counted as a leaf).
    pub(super) fn empty_root(&self) -> u64 {
        if self.layout == ByteLayout::V2 { 8 } else { 0 }
    }

    /// The bytes of the contiguous subtree `work.nodes[node..node + size]`
    /// (whose root is an inner node).
    pub(super) fn subtree(&self, work: &Work, node: u32, size: u32) -> u64 {
        let empty = |i: u32| matches!(work.nodes[i as usize], WorkNode::Leaf { count: 0, .. });
        work.nodes[node as usize..(node + size) as usize]
            .iter()
            .map(|n| match *n {
                WorkNode::Inner {
                    t_ref, left, right, ..
                } => self.inner(t_ref.is_some(), empty(left) && empty(right)),
                WorkNode::Leaf { start, count } => self.leaf(work.leaf(start, count)),
            })
            .sum()
    }
}

/// The fewest bytes (format version 2) a rebuilt subtree of `n_refs`
/// references that can hold a hoisted triangle takes: an inner node and
/// the one leaf holding every reference, the other child empty (two leaves
/// would take more: two words against one word and two bytes per index);
/// for no reference the kept empty-leaf word, for one a one-triangle leaf,
/// else 2 bytes per index.
pub fn min_subtree_bytes(n_refs: usize) -> u64 {
    let indices = if n_refs >= 2 { 2 * n_refs as u64 } else { 0 };
    8 + 8 + indices
}
