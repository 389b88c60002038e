//! The byte model of [`HoistRule::Bytes`](super::HoistRule::Bytes): what
//! a subtree takes in the `.kd` file's version-1 layout (8 bytes per node,
//! empty leaves included, and per hoisted triangle, 2 or 4 per leaf index;
//! format version 2 stores empty leaves in no word and one triangle in its
//! leaf's word, which the rule does not count yet), for a built [`TreeIr`] and for a
//! range of the work tree, and the lower bound on a rebuilt subtree that
//! lets the pass skip a rebuild.

use super::work::{WNode, Work};
use crate::format::node::fits_leaf16;
use crate::scene::TriangleColumns;
use crate::tree::{Node, TreeIr, TriId};

/// How [`HoistRule::Bytes`](super::HoistRule::Bytes) counts bytes.
pub(super) struct ByteModel {
    /// The file id of each triangle (`None`: the input id).
    rank: Option<Vec<u32>>,
}

impl ByteModel {
    pub(super) fn new(scene: &TriangleColumns, reordered: bool) -> ByteModel {
        ByteModel {
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

    /// A leaf's index bytes in the version-1 layout.
    fn leaf(&self, tris: &[TriId]) -> u64 {
        match &self.rank {
            Some(r) => v1_index_bytes(tris.len(), tris.iter().map(|t| r[t.0 as usize])),
            None => v1_index_bytes(tris.len(), tris.iter().map(|t| t.0)),
        }
    }

    pub(super) fn tree(&self, t: &TreeIr) -> u64 {
        t.nodes
            .iter()
            .map(|n| match *n {
                Node::Inner { t_ref, .. } => 8 + 8 * u64::from(t_ref.is_some()),
                Node::Leaf { start, count } => 8 + self.leaf(t.leaf(start, count)),
            })
            .sum()
    }

    /// The bytes of the contiguous subtree `work.nodes[node..node + size]`.
    pub(super) fn subtree(&self, work: &Work, node: u32, size: u32) -> u64 {
        work.nodes[node as usize..(node + size) as usize]
            .iter()
            .map(|n| match *n {
                WNode::Inner { t_ref, .. } => 8 + 8 * u64::from(t_ref.is_some()),
                WNode::Leaf { start, count } => 8 + self.leaf(work.leaf(start, count)),
            })
            .sum()
    }
}

/// 2 bytes per index if the leaf fits 2-byte mode, else 4.
fn v1_index_bytes(len: usize, ids: impl IntoIterator<Item = u32>) -> u64 {
    len as u64 * if fits_leaf16(len, ids) { 2 } else { 4 }
}

/// The fewest bytes a rebuilt subtree of `n_refs` references that can hold
/// a hoisted triangle takes: an inner node and two leaves, and every
/// reference in some leaf at 2 bytes at least.
pub fn min_subtree_bytes(n_refs: usize) -> u64 {
    3 * 8 + 2 * n_refs as u64
}
