//! Builders of the standard SAH kd-tree. Every builder produces the same
//! [`TreeIr`] for the same scene and [`BuildConfig`]; they differ only in
//! how fast they get there.
//!
//! - [`naive`]: the reference; evaluates every candidate plane by counting
//!   triangles directly, O(N²) per node.
//! - [`wald_havran`]: Wald & Havran (2006), O(N log N): events sorted once,
//!   one sweep per axis, children inherit their event order.
//! - [`level`]: breadth-first, level by level, parallel over events (Wu,
//!   Zhao & Liu 2011), over columns that may live in mapped scratch files;
//!   small nodes are finished depth-first in parallel. The default.
//!
//! **The tree both build, defined once.** The root cell is the scene's
//! bounds and every triangle's box in it is its own bounds. At a node, the
//! candidate planes are the bounds of the triangles' boxes in that node
//! (perfect splits); [`sah`] prices them and picks one or makes a leaf. A
//! triangle whose box lies on one side of the chosen plane ([`classify`])
//! keeps its box in that child; a straddler's box in each child is the
//! bounds of `tri ∩ parent cell` on that side of the plane
//! (`geom::clip_split`) `∩ its box in the parent`, and a straddler
//! whose clipped box is empty (possible only by a rounding margin) is left
//! out of that child. Leaves list their triangles in ascending id, and the
//! nodes are emitted in pre-order.

pub mod level;
pub mod naive;
#[doc(hidden)] // the builders' shared cost function; its parameters are `SahParams`
pub mod sah;
pub mod wald_havran;

pub use crate::progress::Progress;
pub use sah::SahParams;

use crate::geom::{Aabb, clip_split};
use crate::scene::TriangleColumns;
use crate::tree::{Node, NodeId, TreeIr, TriId};
use glam::Vec3;
use sah::{LeafRule, Side, Split};

/// What every builder needs to know.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BuildConfig {
    /// The cost model and depth limit every builder prices splits with.
    pub sah: SahParams,
}

/// Which algorithm builds the tree (all build the same one).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Algorithm {
    /// The O(N²) reference ([`naive::build`]).
    Naive,
    /// The O(N log N) event sweep of Wald & Havran ([`wald_havran::build`]).
    WaldHavran,
    /// The level builder with default options (everything in RAM).
    Level,
}

/// Why a build failed: only the level builder can, with its columns
/// (with its default options, no scratch files, only when one level holds
/// more than 2³⁰ references).
pub use crate::columns::ColumnsError as BuildError;

/// Builds the standard tree with the chosen builder.
///
/// # Errors
///
/// With [`Algorithm::Level`], if the level builder fails (see
/// [`BuildError`]); [`Algorithm::Naive`] and [`Algorithm::WaldHavran`] always
/// succeed. Call [`level::build`] for a build with a report, a memory
/// budget and scratch files.
pub fn build(
    scene: &TriangleColumns,
    config: &BuildConfig,
    algorithm: Algorithm,
    progress: Option<&Progress>,
) -> Result<TreeIr, BuildError> {
    match algorithm {
        Algorithm::Naive => Ok(naive::build(scene, config, progress)),
        Algorithm::WaldHavran => Ok(wald_havran::build(scene, config, progress)),
        Algorithm::Level => level::build(scene, config, progress, &level::LevelOptions::default())
            .map(|(tree, _)| tree),
    }
}

/// A triangle in a node, with its (clipped) box in that node.
#[doc(hidden)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriRef {
    /// The triangle, in the scene's numbering.
    pub tri: TriId,
    /// The triangle's box clipped to the node's cell.
    pub bounds: Aabb,
}

/// Where a triangle goes when its node is split.
#[doc(hidden)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// Only into the left child.
    Left,
    /// Only into the right child.
    Right,
    /// Into both: the triangle straddles the plane and is clipped.
    Both,
}

/// The one classification rule: planar boxes go to the split's planar side,
/// boxes ending at or before the plane go left, boxes starting at or after it
/// go right, the rest straddle.
#[doc(hidden)]
#[inline]
pub fn classify(bounds: &Aabb, split: &Split) -> Placement {
    let k = split.axis as usize;
    let (lo, hi) = (bounds.min[k], bounds.max[k]);
    if lo == split.pos && hi == split.pos {
        match split.planar {
            Side::Left => Placement::Left,
            Side::Right => Placement::Right,
        }
    } else if hi <= split.pos {
        Placement::Left
    } else if lo >= split.pos {
        Placement::Right
    } else {
        Placement::Both
    }
}

/// The boxes of a straddler in the two children (see the module docs):
/// `left_cell` and `right_cell` are the parent's cell split by `split`.
/// The triangle is clipped to the parent's cell once and the polygon split
/// by the plane ([`clip_split`]), with the reference's box as the known
/// bounds of `triangle ∩ cell`, so only the faces it reaches are clipped.
/// Every builder clips through here, so all make the same boxes.
#[doc(hidden)]
pub fn clip_straddler(
    scene: &TriangleColumns,
    r: &TriRef,
    split: &Split,
    left_cell: &Aabb,
    right_cell: &Aabb,
) -> (Option<Aabb>, Option<Aabb>) {
    let tri = scene.tri(r.tri.0);
    let cell = Aabb::new(left_cell.min, right_cell.max);
    let [l, r2] = clip_split(&tri, &cell, &r.bounds, split.axis as usize, split.pos);
    let keep = |b: Option<Aabb>| {
        b.map(|b| b.intersection(&r.bounds))
            .filter(|b| !b.is_empty())
    };
    (keep(l), keep(r2))
}

/// The root cell and the root's triangle references.
#[doc(hidden)]
pub fn root(scene: &TriangleColumns) -> (Aabb, Vec<TriRef>) {
    let refs: Vec<TriRef> = (0..scene.len() as u32)
        .map(|i| TriRef {
            tri: TriId(i),
            bounds: Aabb::of_triangle(&scene.tri(i)),
        })
        .collect();
    let bounds = refs.iter().fold(Aabb::EMPTY, |b, r| b.union(&r.bounds));
    (root_cell(bounds), refs)
}

/// The root cell of a scene whose triangles' boxes have the union
/// `union`: that union, or a point at the origin for a scene with no
/// triangle. Every builder's root cell comes from here.
pub(crate) fn root_cell(union: Aabb) -> Aabb {
    if union.is_empty() {
        Aabb::new(Vec3::ZERO, Vec3::ZERO)
    } else {
        union
    }
}

/// Appends nodes in pre-order, deciding with the SAH rules of the build
/// which nodes are leaves (the naive and Wald-Havran builders).
struct TreeWriter<'a> {
    tree: TreeIr,
    sah: &'a SahParams,
    rule: LeafRule,
    progress: Option<&'a Progress>,
}

impl<'a> TreeWriter<'a> {
    fn new(
        bounds: Aabb,
        scene: &TriangleColumns,
        config: &'a BuildConfig,
        progress: Option<&'a Progress>,
    ) -> TreeWriter<'a> {
        TreeWriter {
            tree: TreeIr {
                bounds,
                nodes: Vec::new(),
                leaf_tris: Vec::new(),
            },
            sah: &config.sah,
            rule: config.sah.leaf_rule(scene.len(), || bounds),
            progress,
        }
    }

    fn leaf(&mut self, tris: impl Iterator<Item = TriId>) {
        let start = self.tree.leaf_tris.len() as u32;
        self.tree.leaf_tris.extend(tris);
        let count = self.tree.leaf_tris.len() as u32 - start;
        self.tree.nodes.push(Node::Leaf { start, count });
    }

    /// The decision for a node at `depth` (`weight` of the build's
    /// progress): when [`sah::is_leaf`] says `best` does not pay, writes
    /// the leaf of `refs`, counts `weight` as done and returns `None`;
    /// otherwise returns the split and the cells of its two children.
    fn split_or_leaf(
        &mut self,
        best: Option<Split>,
        refs: &[TriRef],
        cell: &Aabb,
        depth: u32,
        weight: u64,
    ) -> Option<(Split, Aabb, Aabb)> {
        let n = refs.len();
        if sah::is_leaf(self.sah, best.as_ref(), n, depth, &self.rule, cell, |s| {
            let k = s.axis as usize;
            refs.iter()
                .filter(|r| sah::straddles(r.bounds.min[k], r.bounds.max[k], s.pos))
                .count()
        }) {
            self.leaf(refs.iter().map(|r| r.tri));
            Progress::add(self.progress, weight);
            return None;
        }
        let split = best.expect("a split exists when the node is not a leaf");
        let (left_cell, right_cell) = cell.split(split.axis as usize, split.pos);
        Some((split, left_cell, right_cell))
    }

    /// Pushes an inner node whose right child is not known yet.
    fn inner(&mut self, split: &Split) -> usize {
        self.tree.nodes.push(Node::Inner {
            axis: split.axis,
            pos: split.pos,
            right: NodeId(u32::MAX),
            t_ref: None,
        });
        self.tree.nodes.len() - 1
    }

    /// Marks the next node as the right child of `inner`.
    fn right_child_next(&mut self, inner: usize) {
        let next = NodeId(self.tree.nodes.len() as u32);
        if let Node::Inner { right, .. } = &mut self.tree.nodes[inner] {
            *right = next;
        }
    }
}

/// The unit tests' random numbers: Marsaglia's xorshift64 from `seed`
/// (not 0), small and reproducible on every platform.
#[cfg(test)]
pub(crate) fn xorshift(seed: u64) -> impl FnMut() -> u64 {
    let mut x = seed;
    move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    }
}
