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

#[derive(Clone, Copy, Debug)]
pub enum Node {
    /// Split by the plane `axis = pos`; the left child (`< pos` side) is the
    /// next node in pre-order, the right child is `right`. `t_ref` is a
    /// triangle hoisted into this node (Choi et al. 2013, a "type II" inner
    /// node): it is tested whenever the node is visited, and the leaves
    /// below need not list it. Standard trees have none.
    Inner {
        axis: u8,
        pos: f32,
        right: NodeId,
        t_ref: Option<TriId>,
    },
    /// Triangles `leaf_tris[start .. start + count]`.
    Leaf { start: u32, count: u32 },
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
    pub fn n_leaves(&self) -> usize {
        self.nodes
            .iter()
            .filter(|n| matches!(n, Node::Leaf { .. }))
            .count()
    }

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
    pub fn validate(&self, scene: &TriangleColumns) -> Result<(), String> {
        let n = self.nodes.len();
        if n == 0 {
            return Err("no nodes".into());
        }
        if n > u32::MAX as usize {
            return Err("too many nodes".into());
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
        // Structure: recurse over (node, end of its pre-order range).
        let mut expected_next = 0usize;
        let mut next_leaf_start = 0u32;
        let mut seen = vec![false; scene.len()];
        let mut stack = vec![(0usize, n, self.bounds, 0u32)];
        while let Some((i, end, cell, depth)) = stack.pop() {
            if depth > MAX_DEPTH {
                return Err(format!("node {i} lies deeper than {MAX_DEPTH}"));
            }
            if i != expected_next {
                return Err(format!(
                    "node {i} is not next in pre-order (expected {expected_next})"
                ));
            }
            expected_next += 1;
            match self.nodes[i] {
                Node::Inner {
                    axis,
                    pos,
                    right,
                    t_ref,
                } => {
                    let r = right.0 as usize;
                    if axis > 2 {
                        return Err(format!("node {i}: axis {axis}"));
                    }
                    if let Some(t) = t_ref {
                        if t.0 as usize >= scene.len() {
                            return Err(format!("node {i}: hoisted triangle {} out of range", t.0));
                        }
                        seen[t.0 as usize] = true;
                        if clip_triangle(&scene.tri(t.0), &grown(&cell)).is_none() {
                            return Err(format!(
                                "node {i}: hoisted triangle {} does not overlap the cell",
                                t.0
                            ));
                        }
                    }
                    if r <= i + 1 || r >= end {
                        return Err(format!(
                            "node {i}: right child {r} outside ({}, {end})",
                            i + 1
                        ));
                    }
                    let k = axis as usize;
                    if !(pos >= cell.min[k] && pos <= cell.max[k]) {
                        return Err(format!(
                            "node {i}: split {pos} outside its cell on axis {k}"
                        ));
                    }
                    let (lc, rc) = cell.split(k, pos);
                    stack.push((r, end, rc, depth + 1));
                    stack.push((i + 1, r, lc, depth + 1));
                }
                Node::Leaf { start, count } => {
                    if i + 1 != end {
                        return Err(format!("leaf {i} does not end its range"));
                    }
                    if start != next_leaf_start {
                        return Err(format!(
                            "leaf {i}: list starts at {start}, expected {next_leaf_start}"
                        ));
                    }
                    let stop = start as u64 + count as u64;
                    if stop > self.leaf_tris.len() as u64 {
                        return Err(format!("leaf {i}: list out of range"));
                    }
                    next_leaf_start = stop as u32;
                    let list = self.leaf(start, count);
                    for w in list.windows(2) {
                        if w[0] >= w[1] {
                            return Err(format!("leaf {i}: list not strictly ascending"));
                        }
                    }
                    for &t in list {
                        if t.0 as usize >= scene.len() {
                            return Err(format!("leaf {i}: triangle {} out of range", t.0));
                        }
                        seen[t.0 as usize] = true;
                        if clip_triangle(&scene.tri(t.0), &grown(&cell)).is_none() {
                            return Err(format!(
                                "leaf {i}: triangle {} does not overlap the cell",
                                t.0
                            ));
                        }
                    }
                }
            }
        }
        if expected_next != n {
            return Err(format!("{} nodes unreachable", n - expected_next));
        }
        if next_leaf_start as usize != self.leaf_tris.len() {
            return Err("leaf_tris has entries no leaf lists".into());
        }
        if let Some(t) = seen.iter().position(|s| !s) {
            return Err(format!("triangle {t} is in no leaf"));
        }
        Ok(())
    }
}
