//! The space-efficient ("slim") kd-tree of Choi, Chang & Ihm (2013):
//! triangles that are duplicated into many leaves of a subtree are hoisted
//! into the subtree's root, and the subtree is rebuilt without them.
//!
//! Consumes a standard [`TreeIr`] (from any builder) and produces a
//! `TreeIr` whose inner nodes may hold one triangle (`t_ref`, a "type II"
//! node). Traversers test that triangle whenever they visit the node, so the
//! slim tree returns exactly the hits of the standard tree.
//!
//! **Measures** (§4.1). For a subtree `T_I` with leaves `L`:
//! `f_occu(t) = Σ SA(l ∈ L holding t) / Σ SA(l ∈ L)` and
//! `f_freq(t) = |{l ∈ L holding t}| / |L|` (empty leaves count).
//!
//! **Oracle.** `pick_triangle(T_I)`: among the triangles with
//! `f_occu > τ_occu`, in non-increasing occupancy order (ties: smaller id
//! first), the first with `f_freq > τ_freq`; or none.
//!
//! **Algorithm 1** (run in parallel passes, see [`slim`]). From the root of
//! the standard tree, with an explicit stack: if a triangle `t` is picked at inner node `I`, the subtree is
//! rebuilt from its triangles minus `t` ([`rebuild`], the sweep builder
//! inside `I`'s cell at `I`'s depth) and `t` is stored at `I`; the new
//! subtree's children are skipped once the hoisted triangles on the path
//! from `I` to the root number `max_t2rn`; otherwise the non-leaf children
//! are pushed. Leaves are never given a triangle.
//!
//! *Deviation from the paper:* when the rebuilt subtree would be a single
//! leaf (the SAH prefers not to split the remaining triangles), the hoist is
//! cancelled and `I` keeps its original subtree, since a leaf cannot hold a
//! hoisted triangle in the file format.
//!
//! **Exact arithmetic.** Leaf surface areas enter the occupancy as integers
//! (`SA(leaf)/SA(root)` in units of 2⁻⁴⁰), so sums are exact and
//! independent of summation order; the fast implementation here and the
//! literal one in the tests therefore make identical decisions.
//!
//! **Speed** (what makes this faster than the literal algorithm, with the
//! same result). A triangle frequent in `I` is frequent in one of `I`'s
//! children (a weighted average exceeds τ only if one of its terms does),
//! so each node's candidates are the frequent triangles of its children,
//! merged bottom-up. Counts and occupancies in a subtree come from
//! per-triangle sorted lists of pre-order leaf numbers and prefix sums of
//! their weights (two binary searches), not from rescanning leaves.

use crate::build::sweep;
use crate::build::{BuildConfig, TriRef};
use crate::geom::{Aabb, clip_triangle};
use crate::scene::TriangleColumns;
use crate::tree::{Node, NodeId, TreeIr, TriId};
use std::collections::HashMap;

/// The thresholds of the oracle and the hoisting limit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlimParams {
    pub tau_occu: f64,
    pub tau_freq: f64,
    /// Most hoisted triangles on any root path.
    pub max_t2rn: u32,
}

impl SlimParams {
    /// The paper's `fast` preset.
    pub const FAST: SlimParams = SlimParams {
        tau_occu: 0.9,
        tau_freq: 0.7,
        max_t2rn: 4,
    };
    /// The paper's `small` preset.
    pub const SMALL: SlimParams = SlimParams {
        tau_occu: 0.5,
        tau_freq: 0.4,
        max_t2rn: 4,
    };
}

/// What the post-pass did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SlimReport {
    /// Triangles hoisted (type II nodes made).
    pub hoisted: usize,
    /// Hoists cancelled because the rebuilt subtree was a single leaf.
    pub cancelled: usize,
    /// Subtrees rebuilt.
    pub rebuilds: usize,
    /// Triangle references rebuilt (the work of the rebuilds).
    pub rebuilt_refs: usize,
}

/// Occupancy weight of a leaf: `SA(leaf)/SA(root)` in units of 2⁻⁴⁰.
pub fn occupancy_weight(cell: &Aabb, sa_root: f64) -> u64 {
    if sa_root > 0.0 {
        (cell.surface_area() / sa_root * (1u64 << 40) as f64).round() as u64
    } else {
        0
    }
}

/// Whether `count` of `leaves` leaves exceeds `tau` (the one formula).
#[inline]
pub fn above(part: f64, whole: f64, tau: f64) -> bool {
    whole > 0.0 && part / whole > tau
}

/// Rebuilds a subtree from scratch: the triangles `tris` (ascending), each
/// clipped to `cell`, built by the sweep builder at `depth`. Triangles that
/// do not meet `cell` are left out.
pub fn rebuild(
    scene: &TriangleColumns,
    config: &BuildConfig,
    tris: &[TriId],
    cell: &Aabb,
    depth: u32,
) -> TreeIr {
    let refs: Vec<TriRef> = tris
        .iter()
        .filter_map(|&tri| {
            clip_triangle(&scene.tri(tri.0), cell).map(|bounds| TriRef { tri, bounds })
        })
        .collect();
    sweep::build_subtree(scene, config, refs, *cell, depth, None)
}

/// A mutable tree with explicit children, so that subtrees can be replaced
/// without renumbering; turned back into canonical pre-order at the end.
#[derive(Clone, Debug)]
enum WNode {
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

struct Work {
    nodes: Vec<WNode>,
    tris: Vec<TriId>,
}

impl Work {
    /// Appends a pre-order tree; returns the index of its root.
    fn append(&mut self, t: &TreeIr) -> u32 {
        let base = self.nodes.len() as u32;
        let tri_base = self.tris.len() as u32;
        self.tris.extend_from_slice(&t.leaf_tris);
        for (i, n) in t.nodes.iter().enumerate() {
            self.nodes.push(match *n {
                Node::Inner {
                    axis,
                    pos,
                    right,
                    t_ref,
                } => WNode::Inner {
                    axis,
                    pos,
                    left: base + i as u32 + 1,
                    right: base + right.0,
                    t_ref,
                },
                Node::Leaf { start, count } => WNode::Leaf {
                    start: tri_base + start,
                    count,
                },
            });
        }
        base
    }

    fn leaf(&self, start: u32, count: u32) -> &[TriId] {
        &self.tris[start as usize..(start + count) as usize]
    }

    /// The canonical pre-order form of the tree under `root`.
    fn to_ir(&self, root: u32, bounds: Aabb) -> TreeIr {
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
                WNode::Inner {
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
                WNode::Leaf { start, count } => {
                    let s = out.leaf_tris.len() as u32;
                    out.leaf_tris.extend_from_slice(self.leaf(start, count));
                    out.nodes.push(Node::Leaf { start: s, count });
                }
            }
        }
        out
    }
}

/// Per-subtree analysis: the triangle each inner node would pick.
struct Analysis {
    picks: HashMap<u32, TriId>,
}

/// Computes `pick_triangle` for every inner node of the subtree under
/// `root` (the fast way; see the module docs).
fn analyze(work: &Work, root: u32, cell: Aabb, sa_root: f64, p: &SlimParams) -> Analysis {
    // Pre-order leaves with weights, and each node's leaf range.
    struct Frame {
        node: u32,
        cell: Aabb,
        first_leaf: u32,
        visited: bool,
    }
    let mut leaf_weight: Vec<u64> = Vec::new();
    // Triangle occurrences as (triangle, leaf number).
    let mut occ: Vec<(TriId, u32)> = Vec::new();
    let mut range: HashMap<u32, (u32, u32)> = HashMap::new();
    let mut post_order: Vec<u32> = Vec::new();
    let mut stack = vec![Frame {
        node: root,
        cell,
        first_leaf: 0,
        visited: false,
    }];
    while let Some(mut f) = stack.pop() {
        match work.nodes[f.node as usize] {
            WNode::Leaf { start, count } => {
                let l = leaf_weight.len() as u32;
                leaf_weight.push(occupancy_weight(&f.cell, sa_root));
                occ.extend(work.leaf(start, count).iter().map(|&t| (t, l)));
            }
            WNode::Inner {
                axis,
                pos,
                left,
                right,
                ..
            } => {
                if f.visited {
                    range.insert(f.node, (f.first_leaf, leaf_weight.len() as u32));
                    post_order.push(f.node);
                } else {
                    f.visited = true;
                    f.first_leaf = leaf_weight.len() as u32;
                    let (lc, rc) = f.cell.split(axis as usize, pos);
                    let (node, first_leaf) = (f.node, f.first_leaf);
                    stack.push(Frame {
                        node,
                        cell: f.cell,
                        first_leaf,
                        visited: true,
                    });
                    stack.push(Frame {
                        node: right,
                        cell: rc,
                        first_leaf: 0,
                        visited: false,
                    });
                    stack.push(Frame {
                        node: left,
                        cell: lc,
                        first_leaf: 0,
                        visited: false,
                    });
                }
            }
        }
    }
    // Per-triangle sorted leaf lists (CSR) with prefix sums of weights.
    occ.sort_unstable();
    let mut tri_start: HashMap<TriId, (usize, usize)> = HashMap::new();
    let mut prefix: Vec<u128> = Vec::with_capacity(occ.len() + 1);
    let mut i = 0;
    while i < occ.len() {
        let t = occ[i].0;
        let j = i + occ[i..].iter().take_while(|o| o.0 == t).count();
        tri_start.insert(t, (i, j));
        i = j;
    }
    prefix.push(0);
    for &(_, l) in &occ {
        let last = *prefix.last().expect("non-empty");
        prefix.push(last + u128::from(leaf_weight[l as usize]));
    }
    let mut leaf_prefix: Vec<u128> = Vec::with_capacity(leaf_weight.len() + 1);
    leaf_prefix.push(0);
    for &w in &leaf_weight {
        let last = *leaf_prefix.last().expect("non-empty");
        leaf_prefix.push(last + u128::from(w));
    }
    // Count and occupancy of triangle t in the leaf range [a, b).
    let stats = |t: TriId, a: u32, b: u32| -> (u64, u128) {
        let (s, e) = tri_start[&t];
        let list = &occ[s..e];
        let lo = s + list.partition_point(|o| o.1 < a);
        let hi = s + list.partition_point(|o| o.1 < b);
        ((hi - lo) as u64, prefix[hi] - prefix[lo])
    };
    // Bottom-up frequent candidates.
    let mut cands: HashMap<u32, Vec<TriId>> = HashMap::new();
    let mut picks = HashMap::new();
    let leaf_cands = |n: u32, work: &Work| -> Vec<TriId> {
        match work.nodes[n as usize] {
            WNode::Leaf { start, count } => work.leaf(start, count).to_vec(),
            WNode::Inner { .. } => Vec::new(),
        }
    };
    for &n in &post_order {
        let WNode::Inner { left, right, .. } = work.nodes[n as usize] else {
            continue;
        };
        let mut merged = cands
            .remove(&left)
            .unwrap_or_else(|| leaf_cands(left, work));
        merged.extend(
            cands
                .remove(&right)
                .unwrap_or_else(|| leaf_cands(right, work)),
        );
        merged.sort_unstable();
        merged.dedup();
        let (a, b) = range[&n];
        let n_leaves = f64::from(b - a);
        let total = (leaf_prefix[b as usize] - leaf_prefix[a as usize]) as f64;
        let mut best: Option<(u128, TriId)> = None;
        merged.retain(|&t| {
            let (count, occu) = stats(t, a, b);
            let frequent = above(count as f64, n_leaves, p.tau_freq);
            if frequent && above(occu as f64, total, p.tau_occu) {
                let better = match best {
                    None => true,
                    Some((bo, bt)) => occu > bo || (occu == bo && t < bt),
                };
                if better {
                    best = Some((occu, t));
                }
            }
            frequent
        });
        if let Some((_, t)) = best {
            picks.insert(n, t);
        }
        cands.insert(n, merged);
    }
    Analysis { picks }
}

/// The triangles of the subtree under `root`, ascending, without `except`.
fn subtree_tris(work: &Work, root: u32, except: TriId) -> Vec<TriId> {
    let mut out = Vec::new();
    let mut stack = vec![root];
    while let Some(n) = stack.pop() {
        match work.nodes[n as usize] {
            WNode::Inner {
                left, right, t_ref, ..
            } => {
                out.extend(t_ref);
                stack.push(left);
                stack.push(right);
            }
            WNode::Leaf { start, count } => out.extend_from_slice(work.leaf(start, count)),
        }
    }
    out.sort_unstable();
    out.dedup();
    out.retain(|&t| t != except);
    out
}

/// A subtree to process: its root, cell, depth, and the hoisted triangles
/// on the path above it.
#[derive(Clone, Copy)]
struct Todo {
    node: u32,
    cell: Aabb,
    depth: u32,
    t2rn: u32,
}

/// A node where the oracle picked a triangle.
struct Pick {
    at: Todo,
    tri: TriId,
}

/// Walks a subtree top-down and returns the highest nodes where a triangle
/// is picked (their subtrees are not walked further in this pass).
fn find_picks(work: &Work, sub: Todo, sa_root: f64, params: &SlimParams) -> Vec<Pick> {
    let mut picks = Vec::new();
    if sub.t2rn >= params.max_t2rn || !matches!(work.nodes[sub.node as usize], WNode::Inner { .. })
    {
        return picks;
    }
    let analysis = analyze(work, sub.node, sub.cell, sa_root, params);
    let mut stack = vec![sub];
    while let Some(at) = stack.pop() {
        if !matches!(work.nodes[at.node as usize], WNode::Inner { .. }) {
            continue;
        }
        if let Some(&tri) = analysis.picks.get(&at.node) {
            picks.push(Pick { at, tri });
            continue;
        }
        let [l, r] = children(work, &at, at.t2rn);
        stack.push(r);
        stack.push(l);
    }
    picks
}

/// The children of an inner node as subtrees to process.
fn children(work: &Work, at: &Todo, t2rn: u32) -> [Todo; 2] {
    let WNode::Inner {
        axis,
        pos,
        left,
        right,
        ..
    } = work.nodes[at.node as usize]
    else {
        unreachable!("children() is called on inner nodes only");
    };
    let (lc, rc) = at.cell.split(axis as usize, pos);
    [(left, lc), (right, rc)].map(|(node, cell)| Todo {
        node,
        cell,
        depth: at.depth + 1,
        t2rn,
    })
}

/// Applies Algorithm 1 to a standard tree.
///
/// The algorithm runs in passes: each pass finds, in every pending subtree,
/// the highest nodes where a triangle is picked, rebuilds those (disjoint)
/// subtrees in parallel on the current rayon pool, and queues their
/// children. A node's pick depends only on its own subtree, so this order
/// gives the same tree as the sequential stack of the paper (the tests
/// assert it against a literal implementation), for any thread count.
pub fn slim(
    tree: &TreeIr,
    scene: &TriangleColumns,
    config: &BuildConfig,
    params: &SlimParams,
) -> (TreeIr, SlimReport) {
    use rayon::prelude::*;
    let mut work = Work {
        nodes: Vec::new(),
        tris: Vec::new(),
    };
    let root = work.append(tree);
    let sa_root = tree.bounds.surface_area();
    let mut report = SlimReport::default();
    let mut todo = vec![Todo {
        node: root,
        cell: tree.bounds,
        depth: 0,
        t2rn: 0,
    }];
    while !todo.is_empty() {
        let picks: Vec<Pick> = todo
            .par_iter()
            .flat_map_iter(|&sub| find_picks(&work, sub, sa_root, params))
            .collect();
        let rebuilt: Vec<(Vec<TriId>, TreeIr)> = picks
            .par_iter()
            .map(|p| {
                let tris = subtree_tris(&work, p.at.node, p.tri);
                let fresh = rebuild(scene, config, &tris, &p.at.cell, p.at.depth);
                (tris, fresh)
            })
            .collect();
        todo.clear();
        for (p, (tris, fresh)) in picks.iter().zip(rebuilt) {
            report.rebuilds += 1;
            report.rebuilt_refs += tris.len();
            if let Node::Inner {
                axis, pos, right, ..
            } = fresh.nodes[0]
            {
                let base = work.append(&fresh);
                work.nodes[p.at.node as usize] = WNode::Inner {
                    axis,
                    pos,
                    left: base + 1,
                    right: base + right.0,
                    t_ref: Some(p.tri),
                };
                report.hoisted += 1;
                todo.extend(children(&work, &p.at, p.at.t2rn + 1));
            } else {
                // Cancelled: the original subtree stays, and its children
                // are processed as if nothing was picked here.
                report.cancelled += 1;
                todo.extend(children(&work, &p.at, p.at.t2rn));
            }
        }
    }
    (work.to_ir(root, tree.bounds), report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::{self, Builder};
    use glam::Vec3;

    #[test]
    fn huge_triangle_is_hoisted() {
        // A big triangle spanning a grid of small ones lies in most leaves:
        // it is hoisted into the root.
        let mut tris = vec![[
            Vec3::new(-1.0, -1.0, 0.5),
            Vec3::new(30.0, -1.0, 0.5),
            Vec3::new(-1.0, 30.0, 0.5),
        ]];
        for i in 0..8 {
            for j in 0..8 {
                let (x, y) = (i as f32 * 2.0, j as f32 * 2.0);
                tris.push([
                    Vec3::new(x, y, 0.0),
                    Vec3::new(x + 1.0, y, 1.0),
                    Vec3::new(x, y + 1.0, 1.0),
                ]);
            }
        }
        let scene = TriangleColumns::from_triangles(&tris).unwrap();
        let config = BuildConfig::default();
        let std_tree = build::build(&scene, &config, Builder::Sweep, None);
        let (slim_tree, report) = slim(&std_tree, &scene, &config, &SlimParams::SMALL);
        slim_tree.validate(&scene).unwrap();
        assert!(report.hoisted >= 1, "{report:?}");
        assert!(matches!(
            slim_tree.nodes[0],
            Node::Inner {
                t_ref: Some(TriId(0)),
                ..
            }
        ));
        assert!(slim_tree.leaf_tris.len() < std_tree.leaf_tris.len());
    }
}
