//! The byte model of [`HoistRule::Bytes`](super::HoistRule::Bytes): what
//! a subtree takes in the `.kd` file (8 bytes per node and per hoisted
//! triangle, 2 or 4 per leaf index), for a built [`TreeIr`] and for a
//! range of the work tree, and the lower bound on a rebuilt subtree that
//! lets the pass skip a rebuild. [`tree_bytes`] counts a whole tree in
//! either [`ByteLayout`], for measurements of what hoisting saves.

use super::work::{WNode, Work};
use crate::format::node::fits_leaf16;
use crate::scene::TriangleColumns;
use crate::tree::{Node, TreeIr, TriId};

/// How the nodes of a tree are counted in bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ByteLayout {
    /// The `.kd` file's version-1 layout: every node, empty leaves
    /// included, is an 8-byte word, a hoisted triangle one more, and every
    /// leaf's triangles are indices (2 or 4 bytes each). The byte rule of
    /// the slim pass counts in it (its hand-worked tests do).
    V1,
    /// The `.kd` file of today (version 2): an empty leaf takes no word
    /// (but the left child of a node with two empty children, which this
    /// counts as none), and a leaf with one triangle holds it in its own
    /// word (no index); the rest as [`ByteLayout::V1`].
    V2,
}

/// The tree bytes of `tree` (nodes, T-references and leaf indices; no
/// geometry) in `layout`, with the file's triangle numbering (`reordered`:
/// the Morton ranks of `--reorder`, else the input ids). In
/// [`ByteLayout::V1`] this is the version-1 layout's bytes of the written
/// file; in [`ByteLayout::V2`] its `tree_bytes`, up to 8 bytes per node
/// whose two children are empty.
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

    pub(super) fn new(scene: &TriangleColumns, reordered: bool) -> ByteModel {
        ByteModel {
            layout: ByteLayout::V1,
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

    /// The bytes of a leaf: its word and its indices.
    fn leaf(&self, tris: &[TriId]) -> u64 {
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

    pub(super) fn tree(&self, t: &TreeIr) -> u64 {
        t.nodes
            .iter()
            .map(|n| match *n {
                Node::Inner { t_ref, .. } => 8 + 8 * u64::from(t_ref.is_some()),
                Node::Leaf { start, count } => self.leaf(t.leaf(start, count)),
            })
            .sum()
    }

    /// The bytes of the contiguous subtree `work.nodes[node..node + size]`.
    pub(super) fn subtree(&self, work: &Work, node: u32, size: u32) -> u64 {
        work.nodes[node as usize..(node + size) as usize]
            .iter()
            .map(|n| match *n {
                WNode::Inner { t_ref, .. } => 8 + 8 * u64::from(t_ref.is_some()),
                WNode::Leaf { start, count } => self.leaf(work.leaf(start, count)),
            })
            .sum()
    }
}

/// The fewest bytes a rebuilt subtree of `n_refs` references that can hold
/// a hoisted triangle takes: an inner node and two leaves, and every
/// reference in some leaf at 2 bytes at least.
pub fn min_subtree_bytes(n_refs: usize) -> u64 {
    3 * 8 + 2 * n_refs as u64
}
