//! Turns the level builder's records into the canonical [`TreeIr`].
//!
//! Consumes one record per node, made in breadth-first order (an inner
//! node names its children's records; a leaf names its triangle list; a
//! small node names the subtree the depth-first builder made for it).
//! Produces the nodes in depth-first pre-order with the leaf lists
//! concatenated in the same order, which is the order every builder emits
//! (see [`crate::tree`]), so the result compares equal to the sweep
//! builder's tree.

use crate::tree::{Node, NodeId, TreeIr, TriId};

/// What became of one node of a level.
#[derive(Clone, Copy, Debug)]
pub enum Rec {
    /// Not decided yet (only while building).
    Open,
    Inner {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
    },
    /// `tris[start .. start + count]` of the breadth-first leaves.
    Leaf { start: usize, count: u32 },
    /// A subtree finished depth-first.
    Sub(u32),
}

/// The tree, in pre-order from record 0; consumes the subtrees.
pub fn assemble(
    bounds: crate::geom::Aabb,
    recs: &[Rec],
    tris: &[TriId],
    subs: Vec<TreeIr>,
) -> TreeIr {
    let n_nodes: usize = recs
        .iter()
        .map(|r| match r {
            Rec::Sub(s) => subs[*s as usize].nodes.len(),
            _ => 1,
        })
        .sum();
    let n_tris = tris.len() + subs.iter().map(|s| s.leaf_tris.len()).sum::<usize>();
    let mut subs: Vec<Option<TreeIr>> = subs.into_iter().map(Some).collect();
    let mut nodes = Vec::with_capacity(n_nodes);
    let mut leaf_tris = Vec::with_capacity(n_tris);
    // (record, inner node whose right child it is)
    let mut stack = vec![(0u32, None::<usize>)];
    while let Some((r, parent)) = stack.pop() {
        if let Some(p) = parent {
            let next = NodeId(nodes.len() as u32);
            if let Node::Inner { right, .. } = &mut nodes[p] {
                *right = next;
            }
        }
        match recs[r as usize] {
            Rec::Open => unreachable!("every record is decided before assembly"),
            Rec::Inner {
                axis,
                pos,
                left,
                right,
            } => {
                nodes.push(Node::Inner {
                    axis,
                    pos,
                    right: NodeId(u32::MAX),
                    t_ref: None,
                });
                stack.push((right, Some(nodes.len() - 1)));
                stack.push((left, None));
            }
            Rec::Leaf { start, count } => {
                let at = leaf_tris.len() as u32;
                leaf_tris.extend_from_slice(&tris[start..start + count as usize]);
                nodes.push(Node::Leaf { start: at, count });
            }
            Rec::Sub(s) => {
                // Each subtree is copied once and freed at once, so the
                // subtrees and the tree are not all held together.
                let sub = subs[s as usize]
                    .take()
                    .expect("each subtree hangs below one record");
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
            }
        }
    }
    TreeIr {
        bounds,
        nodes,
        leaf_tris,
    }
}
