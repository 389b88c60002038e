//! Where a tree's bytes go, and how much any hoisting could save in this
//! format (the analysis behind the slim presets' size figures).
//!
//! Tree memory is counted as stored ([`TreeFigures::tree_bytes`]):
//! `8·words + 4·|idx32| + 2·|idx16|`. [`ByteSplit::of`] splits it into
//! inner nodes (type I and II), T-references, non-empty leaves, the empty
//! leaves that have a word, and the two index lists,
//! and bounds what hoisting could save on the index side, with the nodes
//! as they are. (A rebuilt subtree can also have fewer nodes than the one
//! it replaces, or more: removing a triangle that filled a cell lets the
//! SAH cut off the empty space it leaves. These bounds say how much the
//! indices alone can give.)
//!
//! - `duplicate_bytes`: every duplicate reference vanishes (each triangle
//!   keeps only its cheapest reference) and costs nothing;
//! - `hoist_bound_bytes`: a triangle can only leave its leaves by being
//!   hoisted, which costs at least one 8-byte T-reference word, so triangle
//!   `t` with references costing `c_t` bytes in all saves at most
//!   `max(0, c_t − 8)`.
//!
//! A reference costs its index entry (4 or 2 bytes), or, in a leaf of one
//! triangle, the leaf's word (8 bytes), which goes with it.
//!
//! [`TreeFigures::tree_bytes`]: crate::format::TreeFigures::tree_bytes

use crate::format::node::{self, NodeWord};
use crate::format::{KdFile, TreeFigures};

/// A tree's bytes in the paper's std layout (Wald 2004, as Choi et al.'s
/// std tree is stored): an 8-byte word for every node, empty leaves
/// included, and for every T-reference, and a 4-byte index for every leaf
/// reference, with no reordering (so no 2-byte leaves):
/// `8·(nodes + t_refs) + 4·refs`. It is computed from the tree's shape,
/// whatever the `.kd` format stores, so that it stays the paper's baseline.
pub fn paper_layout_bytes(nodes: u64, t_refs: u64, refs: u64) -> u64 {
    8 * (nodes + t_refs) + 4 * refs
}

/// [`paper_layout_bytes`] of a stored tree: its nodes as the paper counts
/// them (inner, t-inner and leaves, empty ones included), one T-reference
/// per t-inner node, and its leaf references.
pub fn paper_layout_bytes_of(f: &TreeFigures) -> u64 {
    paper_layout_bytes(f.nodes(), f.t_inner, f.references())
}

/// A tree's bytes by kind, and the bounds on what hoisting can save.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ByteSplit {
    /// Type I inner nodes (8 bytes each).
    pub inner_bytes: u64,
    /// Type II inner nodes and their T-reference words (16 bytes each).
    pub t_inner_bytes: u64,
    /// Leaves with at least one triangle (8 bytes each).
    pub leaf_bytes: u64,
    /// Empty leaves that have a word (8 bytes each; most have none).
    pub empty_leaf_bytes: u64,
    /// 4-byte leaf indices.
    pub idx32_bytes: u64,
    /// 2-byte leaf indices.
    pub idx16_bytes: u64,
    /// What would be saved if every triangle kept only its cheapest leaf
    /// reference (nodes unchanged, nothing hoisted).
    pub duplicate_bytes: u64,
    /// What hoisting could save at most with the nodes unchanged:
    /// `Σ_t max(0, c_t − 8)` over triangles `t` whose leaf references cost
    /// `c_t` bytes.
    pub hoist_bound_bytes: u64,
}

impl ByteSplit {
    /// The tree's bytes: node words and indices.
    pub fn total(&self) -> u64 {
        self.inner_bytes
            + self.t_inner_bytes
            + self.leaf_bytes
            + self.empty_leaf_bytes
            + self.idx32_bytes
            + self.idx16_bytes
    }

    /// All node words.
    pub fn node_bytes(&self) -> u64 {
        self.inner_bytes + self.t_inner_bytes + self.leaf_bytes + self.empty_leaf_bytes
    }

    /// All leaf index entries, 4- and 2-byte.
    pub fn index_bytes(&self) -> u64 {
        self.idx32_bytes + self.idx16_bytes
    }

    /// The split of a file's tree: each node word counted once, in file
    /// order (of a file not validated, whatever its words say).
    pub fn of<D: AsRef<[u8]>>(file: &KdFile<D>) -> ByteSplit {
        let f = file.figures();
        let mut s = ByteSplit {
            idx32_bytes: 4 * f.idx32,
            idx16_bytes: 2 * f.idx16,
            ..ByteSplit::default()
        };
        // Per triangle: bytes of its references, and its cheapest one.
        let n = f.triangles as usize;
        let mut cost = vec![0u64; n];
        let mut cheapest = vec![u8::MAX; n];
        for &w in file.nodes() {
            let Ok(word) = node::decode(w) else { continue };
            let (c, leaf) = match word {
                NodeWord::Inner { t_ref: false, .. } => {
                    s.inner_bytes += 8;
                    continue;
                }
                // The T-reference word is counted with its node.
                NodeWord::Inner { t_ref: true, .. } => {
                    s.t_inner_bytes += 16;
                    continue;
                }
                NodeWord::TRef { .. } => continue,
                NodeWord::Leaf32 { .. } => (4u8, file.leaf(word)),
                NodeWord::Leaf16 { .. } => (2u8, file.leaf(word)),
                // The word is the reference: it goes when the triangle does.
                NodeWord::Leaf1 { .. } => (8u8, file.leaf(word)),
            };
            if leaf.is_empty() {
                s.empty_leaf_bytes += 8;
            } else {
                s.leaf_bytes += 8;
            }
            // A triangle index out of range (a file not validated) is
            // skipped.
            leaf.for_each(|t| {
                if let (Some(cost), Some(m)) =
                    (cost.get_mut(t as usize), cheapest.get_mut(t as usize))
                {
                    *cost += u64::from(c);
                    *m = (*m).min(c);
                }
            });
        }
        for (&c, &m) in cost.iter().zip(&cheapest) {
            if c > 0 {
                s.duplicate_bytes += c - u64::from(m);
                s.hoist_bound_bytes += c.saturating_sub(8);
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::{self, Algorithm, BuildConfig};
    use crate::format::{self, WriteOptions};
    use crate::slim::{self, SlimParams};

    #[test]
    fn split_adds_up_to_the_tree_bytes() {
        let scene = slim::huge_over_grid();
        let config = BuildConfig::default();
        let std_tree = build::build(&scene, &config, Algorithm::WaldHavran, None).unwrap();
        let (slim_tree, _) = slim::slim(&std_tree, &scene, &config, &SlimParams::SMALL);
        for tree in [&std_tree, &slim_tree] {
            let bytes = format::write_to_vec(tree, &scene, &WriteOptions::default()).unwrap();
            let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
            let s = ByteSplit::of(&file);
            let f = file.figures();
            assert_eq!(s.total(), f.tree_bytes());
            assert_eq!(s.t_inner_bytes, 16 * f.t_inner);
            assert_eq!(s.idx16_bytes, 2 * f.idx16);
            assert!(s.hoist_bound_bytes <= s.duplicate_bytes);
            assert!(s.duplicate_bytes < s.index_bytes());
        }
        // The paper's layout from the tree's shape: the IR's nodes (empty
        // leaves included) and references, one T-reference per t-inner.
        for tree in [&std_tree, &slim_tree] {
            let bytes = format::write_to_vec(tree, &scene, &WriteOptions::default()).unwrap();
            let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
            let t_inner = tree
                .nodes
                .iter()
                .filter(|n| matches!(n, crate::tree::Node::Inner { t_ref: Some(_), .. }))
                .count() as u64;
            let want = 8 * (tree.nodes.len() as u64 + t_inner) + 4 * tree.leaf_tris.len() as u64;
            assert_eq!(paper_layout_bytes_of(&file.figures()), want);
        }
        // The big triangle lies in many leaves of the standard tree: its
        // references but one are duplicates (2 bytes each here).
        let bytes = format::write_to_vec(&std_tree, &scene, &WriteOptions::default()).unwrap();
        let s = ByteSplit::of(&KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap());
        let refs_of_0 = std_tree.leaf_tris.iter().filter(|t| t.0 == 0).count() as u64;
        assert!(refs_of_0 > 4);
        assert!(s.duplicate_bytes >= 2 * (refs_of_0 - 1));
        assert!(s.hoist_bound_bytes >= 2 * refs_of_0 - 8);
    }
}
