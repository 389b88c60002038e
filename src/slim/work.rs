//! The flat mutable work tree of the pass: pre-order blocks with explicit
//! children, so that a rebuilt subtree is appended whole and only the
//! hoisting node is redirected; every subtree the pass analyses or rebuilds
//! is a contiguous range of nodes and of leaf triangles. Turned back into a
//! canonical [`TreeIr`] at the end.

use crate::geom::Aabb;
use crate::tree::{Node, NodeId, TreeIr, TriId};
use rayon::prelude::*;
use std::borrow::Borrow;

/// A mutable tree with explicit children, so that subtrees can be replaced
/// without renumbering; turned back into canonical pre-order at the end.
#[derive(Clone, Copy, Debug)]
pub(super) enum WorkNode {
    Inner {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
        t_ref: Option<TriId>,
    },
    Leaf {
        start: u32,
        count: u32,
    },
}

/// The work tree: pre-order blocks (the standard tree, then each rebuilt
/// subtree) appended one after the other. Within a block an inner node's
/// left child is the next node and its subtree is a contiguous range of
/// nodes whose leaves' triangles are a contiguous range of `tris`; only a
/// hoisting node's children lie in another block.
pub(super) struct Work {
    pub(super) nodes: Vec<WorkNode>,
    pub(super) tris: Vec<TriId>,
}

impl Work {
    pub(super) fn leaf(&self, start: u32, count: u32) -> &[TriId] {
        &self.tris[start as usize..(start + count) as usize]
    }

    /// Appends pre-order trees in parallel; returns the index of each root.
    pub(super) fn append_all<T: Borrow<TreeIr> + Send>(&mut self, trees: Vec<T>) -> Vec<u32> {
        let mut bases = Vec::with_capacity(trees.len());
        let (mut n, mut t) = (self.nodes.len(), self.tris.len());
        for tree in trees.iter().map(Borrow::borrow) {
            bases.push((n as u32, t as u32));
            n += tree.nodes.len();
            t += tree.leaf_tris.len();
        }
        let (n0, t0) = (self.nodes.len(), self.tris.len());
        self.nodes.resize(n, WorkNode::Leaf { start: 0, count: 0 });
        self.tris.resize(t, TriId(0));
        // Cut the new tails into one slice per tree.
        let mut slices = Vec::with_capacity(trees.len());
        let (mut nodes, mut tris) = (&mut self.nodes[n0..], &mut self.tris[t0..]);
        for tree in trees.iter().map(Borrow::borrow) {
            let (a, rest) = std::mem::take(&mut nodes).split_at_mut(tree.nodes.len());
            let (b, rest_t) = std::mem::take(&mut tris).split_at_mut(tree.leaf_tris.len());
            slices.push((a, b));
            nodes = rest;
            tris = rest_t;
        }
        trees
            .into_par_iter()
            .zip(slices)
            .zip(bases.par_iter())
            .with_min_len(64)
            .for_each(|((tree, (nodes, tris)), &(base, tri_base))| {
                let tree: &TreeIr = tree.borrow();
                tris.copy_from_slice(&tree.leaf_tris);
                for (i, (out, n)) in nodes.iter_mut().zip(&tree.nodes).enumerate() {
                    *out = match *n {
                        Node::Inner {
                            axis,
                            pos,
                            right,
                            t_ref,
                        } => WorkNode::Inner {
                            axis,
                            pos,
                            left: base + i as u32 + 1,
                            right: base + right.0,
                            t_ref,
                        },
                        Node::Leaf { start, count } => WorkNode::Leaf {
                            start: tri_base + start,
                            count,
                        },
                    };
                }
            });
        bases.into_iter().map(|(b, _)| b).collect()
    }

    /// The range of `tris` holding the leaves of the contiguous subtree
    /// `nodes[node..node + size]`: from its leftmost leaf to its last node
    /// (its rightmost leaf).
    pub(super) fn tri_range(&self, node: u32, size: u32) -> (usize, usize) {
        let mut n = node;
        let start = loop {
            match self.nodes[n as usize] {
                WorkNode::Inner { left, .. } => n = left,
                WorkNode::Leaf { start, .. } => break start,
            }
        };
        let WorkNode::Leaf { start: s, count } = self.nodes[(node + size - 1) as usize] else {
            unreachable!("the last node of a subtree in pre-order is a leaf");
        };
        (start as usize, (s + count) as usize)
    }

    /// The canonical pre-order form of the tree under `root`.
    pub(super) fn to_ir(&self, root: u32, bounds: Aabb) -> TreeIr {
        let mut out = TreeIr {
            bounds,
            nodes: Vec::with_capacity(self.nodes.len()),
            leaf_tris: Vec::new(),
        };
        // (work node, index of the inner node whose `right` it becomes).
        let mut stack = vec![(root, None::<usize>)];
        while let Some((w, parent)) = stack.pop() {
            let me = out.nodes.len();
            if let Some(p) = parent
                && let Node::Inner { right, .. } = &mut out.nodes[p]
            {
                *right = NodeId(me as u32);
            }
            match self.nodes[w as usize] {
                WorkNode::Inner {
                    axis,
                    pos,
                    left,
                    right,
                    t_ref,
                } => {
                    out.nodes.push(Node::Inner {
                        axis,
                        pos,
                        right: NodeId(u32::MAX),
                        t_ref,
                    });
                    stack.push((right, Some(me)));
                    stack.push((left, None));
                }
                WorkNode::Leaf { start, count } => {
                    let s = out.leaf_tris.len() as u32;
                    out.leaf_tris.extend_from_slice(self.leaf(start, count));
                    out.nodes.push(Node::Leaf { start: s, count });
                }
            }
        }
        out
    }
}
