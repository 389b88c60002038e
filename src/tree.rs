//! The tree IR: what every builder produces and every later stage consumes.
//!
//! A kd-tree as two flat columns. `nodes` holds the nodes in depth-first
//! **pre-order**: an inner node's left child is the next node, its right
//! child is at `right`. `leaf_tris` holds the triangle lists of the leaves,
//! concatenated in the same pre-order, each list in ascending triangle id.
//!
//! This order is canonical, so two builders produce the *same* tree exactly
//! when their `TreeIr`s compare equal (split positions are compared by their
//! bits). The IR lives outside `build` so that `trace` can walk it without
//! depending on any builder (see ARCHITECTURE.md).

use crate::geom::{Aabb, clip_triangle};
use crate::scene::TriangleColumns;
use glam::Vec3;

/// The deepest a node may lie (root = 0). Builders clamp their depth limit
/// to it and [`TreeIr::validate`] checks it, so traversal stacks have a
/// fixed size.
pub const MAX_DEPTH: u32 = 100;

/// A triangle's index in [`TriangleColumns`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(transparent)]
pub struct TriId(pub u32);

/// A node's index in [`TreeIr::nodes`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(transparent)]
pub struct NodeId(pub u32);

impl NodeId {
    /// The root is always the first node.
    pub const ROOT: NodeId = NodeId(0);
}

/// A node of a [`TreeIr`]: an inner node or a leaf.
#[derive(Clone, Copy, Debug)]
pub enum Node {
    /// Split by the plane `axis = pos`; the left child (`< pos` side) is the
    /// next node in pre-order, the right child is `right`. `t_ref` is a
    /// triangle hoisted into this node (Choi et al. 2013, a "type II" inner
    /// node): it is tested whenever the node is visited, and the leaves
    /// below need not list it. Standard trees have none.
    Inner {
        /// The split axis: 0, 1, 2 for x, y, z.
        axis: u8,
        /// The split plane's coordinate on `axis`.
        pos: f32,
        /// The right child.
        right: NodeId,
        /// The hoisted triangle, if any.
        t_ref: Option<TriId>,
    },
    /// Triangles `leaf_tris[start .. start + count]`.
    Leaf {
        /// The first entry of the leaf's list in [`TreeIr::leaf_tris`].
        start: u32,
        /// The number of triangles; 0 for an empty leaf.
        count: u32,
    },
}

impl PartialEq for Node {
    fn eq(&self, other: &Node) -> bool {
        match (*self, *other) {
            (
                Node::Inner {
                    axis,
                    pos,
                    right,
                    t_ref,
                },
                Node::Inner {
                    axis: a2,
                    pos: p2,
                    right: r2,
                    t_ref: t2,
                },
            ) => axis == a2 && pos.to_bits() == p2.to_bits() && right == r2 && t_ref == t2,
            (
                Node::Leaf { start, count },
                Node::Leaf {
                    start: s2,
                    count: c2,
                },
            ) => start == s2 && count == c2,
            _ => false,
        }
    }
}

impl Eq for Node {}

/// A kd-tree over a scene. See the module docs for the layout.
#[derive(Clone, Debug, PartialEq)]
pub struct TreeIr {
    /// The root cell: the bounds of the scene.
    pub bounds: Aabb,
    /// Pre-order; never empty (an empty scene is one empty leaf).
    pub nodes: Vec<Node>,
    /// Leaf triangle lists in pre-order, each ascending.
    pub leaf_tris: Vec<TriId>,
}

impl TreeIr {
    /// Leaves, empty ones included.
    pub fn n_leaves(&self) -> usize {
        self.nodes
            .iter()
            .filter(|n| matches!(n, Node::Leaf { .. }))
            .count()
    }

    /// Inner nodes, with or without a hoisted triangle.
    pub fn n_inner(&self) -> usize {
        self.nodes.len() - self.n_leaves()
    }

    /// Inner nodes holding a hoisted triangle ("type II").
    pub fn n_t_inner(&self) -> usize {
        self.nodes
            .iter()
            .filter(|n| matches!(n, Node::Inner { t_ref: Some(_), .. }))
            .count()
    }

    /// The triangles of a leaf.
    pub fn leaf(&self, start: u32, count: u32) -> &[TriId] {
        &self.leaf_tris[start as usize..(start + count) as usize]
    }

    /// Visits every node in pre-order with its cell and depth (root = 0).
    pub fn walk(&self, mut visit: impl FnMut(NodeId, &Node, &Aabb, u32)) {
        let mut stack = vec![(NodeId::ROOT, self.bounds, 0u32)];
        while let Some((id, cell, depth)) = stack.pop() {
            let node = &self.nodes[id.0 as usize];
            visit(id, node, &cell, depth);
            if let Node::Inner {
                axis, pos, right, ..
            } = *node
            {
                let (l, r) = cell.split(axis as usize, pos);
                stack.push((right, r, depth + 1));
                stack.push((NodeId(id.0 + 1), l, depth + 1));
            }
        }
    }

    /// The walk every check of a tree's structure makes: each node from
    /// the root, left subtree first, with its depth and a state `S` the
    /// caller derives for the children (`visit` returns the left and the
    /// right child's for an inner node, `None` for a leaf). Before `visit`
    /// sees a node, the walk refuses (through `fault`) a child outside the
    /// nodes, a node reached twice (a cycle or a shared child: so a
    /// malformed tree cannot make it run away) and a node deeper than
    /// [`MAX_DEPTH`]; the first error ends the walk.
    pub fn walk_checked<S, E>(
        &self,
        root: S,
        fault: impl Fn(WalkFault) -> E,
        mut visit: impl FnMut(usize, &Node, u32, S) -> Result<Option<(S, S)>, E>,
    ) -> Result<(), E> {
        // One bit per node.
        let mut visited = vec![0u64; self.nodes.len().div_ceil(64)];
        let mut stack = vec![(0usize, root, 0u32)];
        while let Some((i, state, depth)) = stack.pop() {
            let Some(node) = self.nodes.get(i) else {
                return Err(fault(WalkFault::Missing { node: i }));
            };
            let (word, bit) = (i / 64, 1u64 << (i % 64));
            if visited[word] & bit != 0 {
                return Err(fault(WalkFault::ReachedTwice { node: i }));
            }
            visited[word] |= bit;
            if depth > MAX_DEPTH {
                return Err(fault(WalkFault::TooDeep { node: i }));
            }
            if let Some((left, right)) = visit(i, node, depth, state)? {
                let Node::Inner { right: r, .. } = *node else {
                    unreachable!("only inner nodes have children")
                };
                stack.push((r.0 as usize, right, depth + 1));
                stack.push((i + 1, left, depth + 1));
            }
        }
        Ok(())
    }

    /// Checks the invariants; returns the first violation.
    ///
    /// - the nodes form one tree in pre-order (left child next, right child
    ///   after the left subtree, every node reached once);
    /// - split planes lie inside their cells, so children nest;
    /// - leaf lists are contiguous in pre-order, ascending, and list only
    ///   triangles that overlap the leaf's cell (up to a rounding margin of
    ///   2⁻²⁰ of the scene's largest coordinate);
    /// - hoisted triangles overlap their node's cell;
    /// - every triangle is reachable from the root (lies in some leaf or is
    ///   hoisted into some inner node).
    pub fn validate(&self, scene: &TriangleColumns) -> Result<(), TreeError> {
        let n = self.nodes.len();
        if n == 0 {
            return Err(TreeError::NoNodes);
        }
        if n > u32::MAX as usize {
            return Err(TreeError::TooManyNodes);
        }
        // "Overlaps" is checked against the cell grown by a rounding margin:
        // a triangle that only touches a cell's face may be computed just
        // outside it when clipped afresh against that small cell, while the
        // builder (correctly) kept it from a clip against a larger one.
        let scale = self
            .bounds
            .min
            .abs()
            .max(self.bounds.max.abs())
            .max_element();
        let margin = Vec3::splat(scale * (1.0 / (1u32 << 20) as f32) + f32::MIN_POSITIVE);
        let grown = |c: &Aabb| Aabb::new(c.min - margin, c.max + margin);
        // Structure: walk over (node, end of its pre-order range, cell).
        let mut expected_next = 0usize;
        let mut next_leaf_start = 0u32;
        let mut seen = vec![false; scene.len()];
        // Of the walk's own faults only the depth can occur here: every
        // child is checked to lie inside its parent's range before it is
        // pushed, and the ranges on the stack are disjoint.
        let walk_fault = |fault: WalkFault| match fault {
            WalkFault::TooDeep { node } => TreeError::TooDeep { node },
            WalkFault::Missing { .. } | WalkFault::ReachedTwice { .. } => {
                unreachable!("children are checked against their ranges")
            }
        };
        self.walk_checked((n, self.bounds), walk_fault, |i, node, _, (end, cell)| {
            if i != expected_next {
                return Err(TreeError::NotInPreOrder {
                    node: i,
                    expected: expected_next,
                });
            }
            expected_next += 1;
            match *node {
                Node::Inner {
                    axis,
                    pos,
                    right,
                    t_ref,
                } => {
                    let r = right.0 as usize;
                    if axis > 2 {
                        return Err(TreeError::BadAxis { node: i, axis });
                    }
                    if let Some(t) = t_ref {
                        if t.0 as usize >= scene.len() {
                            return Err(TreeError::HoistedOutOfRange { node: i, tri: t.0 });
                        }
                        seen[t.0 as usize] = true;
                        if clip_triangle(&scene.tri(t.0), &grown(&cell)).is_none() {
                            return Err(TreeError::HoistedOutsideCell { node: i, tri: t.0 });
                        }
                    }
                    if r <= i + 1 || r >= end {
                        return Err(TreeError::RightChildOutside {
                            node: i,
                            right: r,
                            end,
                        });
                    }
                    let k = axis as usize;
                    if !(pos >= cell.min[k] && pos <= cell.max[k]) {
                        return Err(TreeError::SplitOutsideCell {
                            node: i,
                            pos,
                            axis: k,
                        });
                    }
                    let (lc, rc) = cell.split(k, pos);
                    Ok(Some(((r, lc), (end, rc))))
                }
                Node::Leaf { start, count } => {
                    if i + 1 != end {
                        return Err(TreeError::LeafNotLast { node: i });
                    }
                    if start != next_leaf_start {
                        return Err(TreeError::LeafListStart {
                            node: i,
                            start,
                            expected: next_leaf_start,
                        });
                    }
                    let stop = start as u64 + count as u64;
                    if stop > self.leaf_tris.len() as u64 {
                        return Err(TreeError::LeafListOutOfRange { node: i });
                    }
                    next_leaf_start = stop as u32;
                    let list = self.leaf(start, count);
                    for w in list.windows(2) {
                        if w[0] >= w[1] {
                            return Err(TreeError::LeafListNotAscending { node: i });
                        }
                    }
                    for &t in list {
                        if t.0 as usize >= scene.len() {
                            return Err(TreeError::LeafTriOutOfRange { node: i, tri: t.0 });
                        }
                        seen[t.0 as usize] = true;
                        if clip_triangle(&scene.tri(t.0), &grown(&cell)).is_none() {
                            return Err(TreeError::LeafTriOutsideCell { node: i, tri: t.0 });
                        }
                    }
                    Ok(None)
                }
            }
        })?;
        if expected_next != n {
            return Err(TreeError::Unreachable {
                count: n - expected_next,
            });
        }
        if next_leaf_start as usize != self.leaf_tris.len() {
            return Err(TreeError::UnlistedLeafTris);
        }
        if let Some(t) = seen.iter().position(|s| !s) {
            return Err(TreeError::TriangleInNoLeaf { tri: t });
        }
        Ok(())
    }
}

/// What [`TreeIr::walk_checked`] refuses before visiting a node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WalkFault {
    /// A child index at or past the end of the nodes.
    Missing {
        /// The parent whose child is missing.
        node: usize,
    },
    /// A node reached a second time (not a tree).
    ReachedTwice {
        /// The node, by pre-order index.
        node: usize,
    },
    /// A node deeper than [`MAX_DEPTH`].
    TooDeep {
        /// The node, by pre-order index.
        node: usize,
    },
}

/// Why [`TreeIr::validate`] refused a tree; the message names the node.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TreeError {
    /// The tree has no node (an empty scene is one empty leaf).
    #[error("no nodes")]
    NoNodes,
    /// More nodes than a [`NodeId`] can number.
    #[error("too many nodes")]
    TooManyNodes,
    /// A node lies deeper than [`MAX_DEPTH`].
    #[error("node {node} lies deeper than {MAX_DEPTH}")]
    TooDeep {
        /// The node, by pre-order index.
        node: usize,
    },
    /// A node is reached out of pre-order.
    #[error("node {node} is not next in pre-order (expected {expected})")]
    NotInPreOrder {
        /// The node, by pre-order index.
        node: usize,
        /// The index pre-order puts next.
        expected: usize,
    },
    /// An inner node's axis is not 0, 1 or 2.
    #[error("node {node}: axis {axis}")]
    BadAxis {
        /// The node, by pre-order index.
        node: usize,
        /// The axis it holds.
        axis: u8,
    },
    /// A hoisted triangle is not in the scene.
    #[error("node {node}: hoisted triangle {tri} out of range")]
    HoistedOutOfRange {
        /// The node, by pre-order index.
        node: usize,
        /// The triangle's id.
        tri: u32,
    },
    /// A hoisted triangle does not overlap its node's cell.
    #[error("node {node}: hoisted triangle {tri} does not overlap the cell")]
    HoistedOutsideCell {
        /// The node, by pre-order index.
        node: usize,
        /// The triangle's id.
        tri: u32,
    },
    /// The right child is not in `(node + 1, end)`.
    #[error("node {node}: right child {right} outside ({}, {end})", .node + 1)]
    RightChildOutside {
        /// The node, by pre-order index.
        node: usize,
        /// Its right child.
        right: usize,
        /// The end of the node's subtree range.
        end: usize,
    },
    /// A split plane lies outside its node's cell.
    #[error("node {node}: split {pos} outside its cell on axis {axis}")]
    SplitOutsideCell {
        /// The node, by pre-order index.
        node: usize,
        /// The plane's coordinate.
        pos: f32,
        /// The split axis.
        axis: usize,
    },
    /// A leaf is not the last node of its subtree range.
    #[error("leaf {node} does not end its range")]
    LeafNotLast {
        /// The node, by pre-order index.
        node: usize,
    },
    /// A leaf's list does not start where the previous leaf's ends.
    #[error("leaf {node}: list starts at {start}, expected {expected}")]
    LeafListStart {
        /// The node, by pre-order index.
        node: usize,
        /// Where its list starts.
        start: u32,
        /// Where the previous list ends.
        expected: u32,
    },
    /// A leaf's list runs past the end of [`TreeIr::leaf_tris`].
    #[error("leaf {node}: list out of range")]
    LeafListOutOfRange {
        /// The node, by pre-order index.
        node: usize,
    },
    /// A leaf's list is not strictly ascending.
    #[error("leaf {node}: list not strictly ascending")]
    LeafListNotAscending {
        /// The node, by pre-order index.
        node: usize,
    },
    /// A leaf lists a triangle that is not in the scene.
    #[error("leaf {node}: triangle {tri} out of range")]
    LeafTriOutOfRange {
        /// The node, by pre-order index.
        node: usize,
        /// The triangle's id.
        tri: u32,
    },
    /// A leaf lists a triangle that does not overlap its cell.
    #[error("leaf {node}: triangle {tri} does not overlap the cell")]
    LeafTriOutsideCell {
        /// The node, by pre-order index.
        node: usize,
        /// The triangle's id.
        tri: u32,
    },
    /// Nodes that no path from the root reaches.
    #[error("{count} nodes unreachable")]
    Unreachable {
        /// How many.
        count: usize,
    },
    /// [`TreeIr::leaf_tris`] has entries after the last leaf's list.
    #[error("leaf_tris has entries no leaf lists")]
    UnlistedLeafTris,
    /// A triangle that no leaf or inner node holds.
    #[error("triangle {tri} is in no leaf")]
    TriangleInNoLeaf {
        /// The triangle's id.
        tri: usize,
    },
}

/// A consumer of a tree in canonical pre-order, one node at a time: what
/// a builder hands its tree to when the whole [`TreeIr`] need not exist
/// (the streamed `.kd` writer, the statistics, [`TreeIrSink`]).
/// `bounds` comes first, then every node: an inner node is followed by its
/// left subtree, then its right subtree. A sink that cannot go on returns
/// [`SinkStop`] and keeps the reason itself; the producer then stops.
pub trait PreOrderSink {
    /// The root cell, before any node.
    fn bounds(&mut self, bounds: Aabb) -> Result<(), SinkStop>;
    /// An inner node split by the plane `axis = pos`, with its hoisted
    /// triangle if any.
    fn inner(&mut self, axis: u8, pos: f32, t_ref: Option<TriId>) -> Result<(), SinkStop>;
    /// A leaf and its triangles (ascending; none for an empty leaf).
    fn leaf(&mut self, tris: &[TriId]) -> Result<(), SinkStop>;
}

/// A [`PreOrderSink`]'s refusal of further nodes; the sink holds the
/// reason.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SinkStop;

/// Both sinks get every call (the first that stops ends it).
impl<A: PreOrderSink, B: PreOrderSink> PreOrderSink for (A, B) {
    fn bounds(&mut self, bounds: Aabb) -> Result<(), SinkStop> {
        self.0.bounds(bounds)?;
        self.1.bounds(bounds)
    }
    fn inner(&mut self, axis: u8, pos: f32, t_ref: Option<TriId>) -> Result<(), SinkStop> {
        self.0.inner(axis, pos, t_ref)?;
        self.1.inner(axis, pos, t_ref)
    }
    fn leaf(&mut self, tris: &[TriId]) -> Result<(), SinkStop> {
        self.0.leaf(tris)?;
        self.1.leaf(tris)
    }
}

impl<S: PreOrderSink + ?Sized> PreOrderSink for &mut S {
    fn bounds(&mut self, bounds: Aabb) -> Result<(), SinkStop> {
        (**self).bounds(bounds)
    }
    fn inner(&mut self, axis: u8, pos: f32, t_ref: Option<TriId>) -> Result<(), SinkStop> {
        (**self).inner(axis, pos, t_ref)
    }
    fn leaf(&mut self, tris: &[TriId]) -> Result<(), SinkStop> {
        (**self).leaf(tris)
    }
}

impl TreeIr {
    /// Hands the tree to `sink` in pre-order (a well-formed tree: one
    /// that [`TreeIr::validate`] accepts, or at least one whose children
    /// and leaf lists are in range and form a tree).
    pub fn feed(&self, sink: &mut impl PreOrderSink) -> Result<(), SinkStop> {
        sink.bounds(self.bounds)?;
        self.feed_nodes(sink)
    }

    /// [`TreeIr::feed`] without the bounds: the nodes alone, as a subtree
    /// of a larger stream (a cell's part in a stitch).
    pub fn feed_nodes(&self, sink: &mut impl PreOrderSink) -> Result<(), SinkStop> {
        let mut stack = vec![NodeId::ROOT];
        while let Some(id) = stack.pop() {
            match self.nodes[id.0 as usize] {
                Node::Inner {
                    axis,
                    pos,
                    right,
                    t_ref,
                } => {
                    sink.inner(axis, pos, t_ref)?;
                    stack.push(right);
                    stack.push(NodeId(id.0 + 1));
                }
                Node::Leaf { start, count } => sink.leaf(self.leaf(start, count))?,
            }
        }
        Ok(())
    }
}

/// Where the next node of a pre-order stream goes: the root, a left child
/// (the next node after its parent) or the right child of an inner node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PreOrderPlace {
    /// The first node.
    Root,
    /// The left child of the node before it.
    Left,
    /// The right child of the inner node at this pre-order position.
    Right(usize),
}

/// The places of a pre-order stream's nodes: the stack of the right
/// children still to come, which every [`PreOrderSink`] keeps.
#[derive(Clone, Debug, Default)]
pub struct PreOrderStack {
    /// `(place, depth)` of the nodes to come, the next on top.
    stack: Vec<(PreOrderPlace, u32)>,
    /// Nodes seen.
    count: usize,
}

impl PreOrderStack {
    /// The place and depth of the next node, and its pre-order position;
    /// `None` once the tree is complete. `inner`: whether that node is an
    /// inner node (its children then come next).
    pub fn next(&mut self, inner: bool) -> Option<(PreOrderPlace, u32, usize)> {
        let (place, depth) = if self.count == 0 {
            (PreOrderPlace::Root, 0)
        } else {
            self.stack.pop()?
        };
        let at = self.count;
        self.count += 1;
        if inner {
            self.stack.push((PreOrderPlace::Right(at), depth + 1));
            self.stack.push((PreOrderPlace::Left, depth + 1));
        }
        Some((place, depth, at))
    }

    /// Whether a whole tree has been seen.
    pub fn complete(&self) -> bool {
        self.count > 0 && self.stack.is_empty()
    }

    /// Nodes seen.
    pub fn count(&self) -> usize {
        self.count
    }
}

/// A [`PreOrderSink`] that collects the [`TreeIr`]. [`TreeIrSink::finish`]
/// refuses a stream that is not one whole tree.
#[derive(Debug, Default)]
pub struct TreeIrSink {
    /// The tree so far.
    pub tree: TreeIr,
    places: PreOrderStack,
}

impl Default for TreeIr {
    fn default() -> TreeIr {
        TreeIr {
            bounds: Aabb::EMPTY,
            nodes: Vec::new(),
            leaf_tris: Vec::new(),
        }
    }
}

impl TreeIrSink {
    /// A sink whose tree reserves `nodes` nodes and `tris` leaf entries.
    pub fn with_capacity(nodes: Vec<Node>, leaf_tris: Vec<TriId>) -> TreeIrSink {
        TreeIrSink {
            tree: TreeIr {
                bounds: Aabb::EMPTY,
                nodes,
                leaf_tris,
            },
            places: PreOrderStack::default(),
        }
    }

    fn place(&mut self, inner: bool) -> Result<(), SinkStop> {
        let (place, _, at) = self.places.next(inner).ok_or(SinkStop)?;
        if let PreOrderPlace::Right(parent) = place
            && let Node::Inner { right, .. } = &mut self.tree.nodes[parent]
        {
            *right = NodeId(at as u32);
        }
        Ok(())
    }

    /// The tree, if the stream was one whole tree.
    pub fn finish(self) -> Option<TreeIr> {
        self.places.complete().then_some(self.tree)
    }
}

impl PreOrderSink for TreeIrSink {
    fn bounds(&mut self, bounds: Aabb) -> Result<(), SinkStop> {
        self.tree.bounds = bounds;
        Ok(())
    }
    fn inner(&mut self, axis: u8, pos: f32, t_ref: Option<TriId>) -> Result<(), SinkStop> {
        self.place(true)?;
        self.tree.nodes.push(Node::Inner {
            axis,
            pos,
            right: NodeId(u32::MAX),
            t_ref,
        });
        Ok(())
    }
    fn leaf(&mut self, tris: &[TriId]) -> Result<(), SinkStop> {
        self.place(false)?;
        let start = self.tree.leaf_tris.len() as u32;
        self.tree.leaf_tris.extend_from_slice(tris);
        self.tree.nodes.push(Node::Leaf {
            start,
            count: tris.len() as u32,
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaf() -> Node {
        Node::Leaf { start: 0, count: 0 }
    }

    fn inner(right: u32) -> Node {
        Node::Inner {
            axis: 0,
            pos: 0.5,
            right: NodeId(right),
            t_ref: None,
        }
    }

    fn tree(nodes: Vec<Node>) -> TreeIr {
        TreeIr {
            bounds: Aabb::new(Vec3::ZERO, Vec3::ONE),
            nodes,
            leaf_tris: Vec::new(),
        }
    }

    /// The nodes `walk_checked` visits, with their depths and states (the
    /// state counts the path: left adds 1, right adds 10), or its fault.
    fn visits(t: &TreeIr) -> Result<Vec<(usize, u32, u32)>, WalkFault> {
        let mut seen = Vec::new();
        t.walk_checked(
            0u32,
            |f| f,
            |i, node, depth, s| {
                seen.push((i, depth, s));
                Ok(matches!(node, Node::Inner { .. }).then_some((s + 1, s + 10)))
            },
        )?;
        Ok(seen)
    }

    #[test]
    fn walk_checked_visits_in_pre_order_with_states() {
        let t = tree(vec![inner(4), inner(3), leaf(), leaf(), leaf()]);
        assert_eq!(
            visits(&t),
            Ok(vec![
                (0, 0, 0),
                (1, 1, 1),
                (2, 2, 2),
                (3, 2, 11),
                (4, 1, 10)
            ])
        );
    }

    #[test]
    fn walk_checked_refuses_missing_shared_and_deep_nodes() {
        assert_eq!(visits(&tree(vec![])), Err(WalkFault::Missing { node: 0 }));
        assert_eq!(
            visits(&tree(vec![inner(9), leaf()])),
            Err(WalkFault::Missing { node: 9 })
        );
        // The right child is the left one: reached twice.
        assert_eq!(
            visits(&tree(vec![inner(1), leaf()])),
            Err(WalkFault::ReachedTwice { node: 1 })
        );
        // A cycle back to the root (after its left child).
        assert_eq!(
            visits(&tree(vec![inner(0), leaf()])),
            Err(WalkFault::ReachedTwice { node: 0 })
        );
        // A caterpillar one level deeper than MAX_DEPTH.
        let d = MAX_DEPTH as usize + 1;
        let mut nodes: Vec<Node> = (0..d).map(|i| inner((2 * d - i) as u32)).collect();
        nodes.extend((0..=d).map(|_| leaf()));
        assert_eq!(visits(&tree(nodes)), Err(WalkFault::TooDeep { node: d }));
    }
}
