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
//! the standard tree, with an explicit stack: if a triangle `t` is picked
//! at inner node `I`, the subtree is rebuilt from its triangles minus `t`
//! (the SAH builder inside `I`'s cell at `I`'s depth, see [`rebuild`]) and
//! `t` is stored at `I`; the new subtree's children are skipped once the
//! hoisted triangles on the path from `I` to the root number `max_t2rn`;
//! otherwise the non-leaf children are pushed. Leaves are never given a
//! triangle.
//!
//! *Deviation from the paper (always):* when the rebuilt subtree would be a
//! single leaf (the SAH prefers not to split the remaining triangles), the
//! hoist is *cancelled* and `I` keeps its original subtree, since a leaf
//! cannot hold a hoisted triangle in the file format.
//!
//! *Deviation from the paper ([`HoistRule::Bytes`], the rule of the `fast`
//! and `small` presets):* a hoist is kept only if it makes the tree
//! smaller. The rebuilt subtree plus the hoisted triangle's T-reference
//! word must take fewer bytes than the subtree it replaces, counted as the
//! file stores them (see [`HoistRule::Bytes`]); otherwise the hoist is
//! *rejected*: `I` keeps its original subtree and the algorithm goes on
//! with `I`'s children as if no triangle had been picked (as for a
//! cancelled hoist). Why: in the `.kd` format a node is 8 bytes and a
//! leaf index 2 (with 2-byte leaves; a one-triangle leaf has none, an
//! empty leaf no word), so a hoist pays an 8-byte word to save a few
//! indices, and the rebuilt subtree often has more nodes; with
//! the paper's rule the `fast` and `small` trees of the shared scenes came
//! out up to 7% *larger* than the standard tree. [`HoistRule::Paper`]
//! gives the paper's literal behaviour.
//!
//! *Deviation from the paper ([`SlimParams::coarsen`], the `fast` and
//! `small` presets):* a picked subtree may be rebuilt with a larger `K_T` than the
//! std tree's, so that the rebuilt subtree stops splitting sooner; the
//! byte rule then keeps the hoist only where that, with the triangle
//! hoisted, makes the subtree smaller. Removing a hoisted triangle alone
//! leaves the rebuilt subtree's node count as it was (see the field's
//! docs), so this is where a hoist's nodes are saved.
//!
//! *Deviation from the paper ([`SlimParams::cost_ratio`], the `fast` and
//! `small` presets):* the byte rule's hoist is also priced. A hoist that saves
//! `ΔB` bytes is kept only if it raises the SAH cost (the std build's
//! `K_T` and `K_I`, the hoisted triangle one test at its node) by at most
//! `cost_ratio · ΔB · C_std / B_std`. The costs of a hoist's old and new
//! subtrees are summed in pre-order in `f64` (`cost.rs`), so the literal
//! algorithm in the tests prices it identically. Why: a hoist high in the
//! tree is tested by every ray through its node for a few bytes of leaf
//! indices; priced, and with rebuilds at 1.5 × `K_T`, `fast` is both
//! smaller and faster (see the preset's docs).
//!
//! *Deviation from the paper ([`Rebuild::Prune`]):* a picked subtree may
//! be remade from itself instead of rebuilt: its splits are kept, the
//! triangle is taken out of its leaves, and bottom-up two sibling leaves
//! become one where the rebuild's leaf rule (`K_T` × `coarsen`, the split
//! price) prefers a leaf to their parent's split ([`joins`]). The hoist
//! rule then decides as after a rebuild. Why: the SAH rebuilds make the
//! slim build several times the std build, and pruning is linear in the
//! subtree (see the variant's docs for what it keeps of the bytes).
//!
//! *The presets' split price ([`SlimParams::split_price`]):* the presets
//! start from a std tree built at a higher split price than std's (1.5
//! and 2 against 0.5), since the default price already removes much of
//! the duplication hoisting removes; the pass takes the tree and the
//! configuration it was built with and does not read the field.
//!
//! **Exact arithmetic.** Leaf surface areas enter the occupancy as integers
//! (`SA(leaf)/SA(root)` in units of 2⁻⁴⁰), so sums are exact and
//! independent of summation order; the fast implementation here and the
//! literal one in the tests therefore make identical decisions.
//!
//! **Speed** (what makes this faster than the literal algorithm, with the
//! same result).
//! - *Bottom-up candidates.* A triangle frequent in `I` is frequent in one
//!   of `I`'s children (a weighted average exceeds τ only if one of its
//!   terms does), so each node's candidates are the frequent triangles of
//!   its children, merged bottom-up with their counts and occupancies
//!   (which add up). A triangle frequent in one child only is counted in
//!   the other child's leaves from the subtree's (triangle, leaf) pairs,
//!   sorted once, with prefix sums of their leaf weights (two binary
//!   searches), and only if it could still be frequent; leaves are never
//!   rescanned. One analysis gives the pick of every node of a subtree;
//!   it is computed in parallel over subtrees for large trees.
//! - *Skips.* Under the byte rule, a pick whose subtree takes at most 8
//!   bytes more than the least any rebuilt subtree of its references could
//!   take ([`min_subtree_bytes`]) is rejected without a rebuild; it could
//!   not pass the rule (with [`Rebuild::Prune`] the test follows the
//!   prune, whose walk counts the subtree's bytes). A rebuild stops,
//!   rejected, as soon as a lower bound of its bytes (the finished nodes'
//!   bytes, 8 to 16 per pending node with references) reaches the
//!   replaced subtree's bytes less 8,
//!   which the rule rejects (`SubtreeBuilder::build`'s byte limit).
//! - *Passes.* Each pass finds, in every pending subtree, the highest nodes
//!   where a triangle is picked, rebuilds those (disjoint) subtrees in
//!   parallel, and queues their children. A node's pick depends only on
//!   its own subtree, so the order does not change the tree. Below a
//!   cancelled or rejected hoist the subtree is unchanged, so its analysis
//!   is reused.
//! - *Rebuilds* use the level builder's depth-first finisher
//!   (`level::SubtreeBuilder`, no allocation per node), which builds the same
//!   subtree as the sweep builder of [`rebuild`].
//! - *Flat work tree.* Every subtree that is analysed or rebuilt is a
//!   contiguous pre-order range of nodes (and of leaf triangles) of the
//!   work tree, because rebuilt subtrees are appended whole and only the
//!   children of hoisting nodes are redirected.
//!
//! **Memory: not bounded by a budget.** The pass holds the whole std
//! `TreeIr` (20 bytes a node and 4 a reference), its work tree and the
//! slimmed tree, so `build --preset fast|small` holds several trees
//! whatever `--mem-budget` says (a std `build -o` streams the tree into
//! the file instead). Why: Algorithm 1 runs top down, and a hoist high in
//! the tree rebuilds everything below it, while the picks themselves are
//! decided from bottom-up analyses of whole subtrees; so no finished part
//! of the tree is final before the levels above it are decided. Bounding
//! it would take two streamed passes: the subtrees' analyses (a few
//! candidates a subtree root) to decide the top, then each depth-first
//! subtree slimmed on its own under the decided top.

mod bytes;
mod cost;
mod oracle;
mod params;
mod pass;
mod prune;
mod work;

pub use bytes::{ByteLayout, min_subtree_bytes, tree_bytes};
#[doc(hidden)] // the literal Algorithm 1 of tests/slim.rs shares the oracle's formulas
pub use oracle::{above, occupancy_weight};
pub use params::{HoistRule, Rebuild, SlimParams, SlimPhases, SlimReport};
#[doc(hidden)] // the literal pass of tests/slim.rs joins leaves with it
pub use prune::joins;

use crate::build::level::SubtreeBuilder;
use crate::build::{BuildConfig, TriRef, wald_havran};
use crate::geom::{Aabb, clip_triangle};
use crate::progress::Progress;
use crate::scene::TriangleColumns;
use crate::sys::lap;
use crate::tree::{Node, TreeIr, TriId};
use bytes::ByteModel;
use oracle::analyze;
use pass::{Outcome, Pick, Rebuilder, SlimInputs, Todo, find_picks, rebuild_pick};
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Instant;
use work::{Work, WorkNode};

/// Rebuilds a subtree from scratch, as Algorithm 1 does: the triangles
/// `tris` (ascending), each clipped to `cell`, built by the sweep builder
/// at `depth`, its splits priced as nodes of the whole scene's tree.
/// Triangles that do not meet `cell` are left out. (The pass itself builds
/// the same subtree with the level builder's `SubtreeBuilder`.)
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
    let mut config = *config;
    (config.sah.price_scale).get_or_insert_with(|| {
        crate::build::sah::price_scale(&crate::build::root_cell(scene.bounds()), scene.len())
    });
    wald_havran::build_subtree(scene, &config, refs, *cell, depth, None)
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
    let (tree, report, _) = slim_with_phases(tree, scene, config, params);
    (tree, report)
}

/// [`slim`], with the time spent in each phase.
pub fn slim_with_phases(
    tree: &TreeIr,
    scene: &TriangleColumns,
    config: &BuildConfig,
    params: &SlimParams,
) -> (TreeIr, SlimReport, SlimPhases) {
    slim_with_progress(tree, scene, config, params, None)
}

/// [`slim_with_phases`], advancing `progress` from 0 to 1 as it goes
/// (for a progress bar). Each subtree to process carries a share of the
/// progress in proportion to its node count; the share of a node is done
/// when the pass decides it (no pick there, or the pick's rebuild taken or
/// not), and a rebuilt subtree hands its share on to its children.
pub fn slim_with_progress(
    tree: &TreeIr,
    scene: &TriangleColumns,
    config: &BuildConfig,
    params: &SlimParams,
    progress: Option<&Progress>,
) -> (TreeIr, SlimReport, SlimPhases) {
    let mut report = SlimReport::default();
    let mut phases = SlimPhases::default();
    if params.max_t2rn == 0 {
        Progress::add_all(progress);
        return (tree.clone(), report, phases);
    }
    let mut clock = Instant::now();
    let mut work = Work {
        nodes: Vec::new(),
        tris: Vec::new(),
    };
    let root = work.append_all(vec![tree])[0];
    phases.apply_s += lap(&mut clock);
    let (bytes, analysis) = rayon::join(
        || match params.rule {
            HoistRule::Paper => None,
            HoistRule::Bytes { reordered } => Some(ByteModel::new(scene, reordered)),
        },
        || {
            analyze(
                &work,
                root,
                tree.nodes.len() as u32,
                tree.bounds,
                tree.bounds.surface_area(),
                params,
                scene.len(),
            )
        },
    );
    let price = match (&bytes, params.cost_ratio.is_finite()) {
        (Some(b), true) => {
            let model = cost::CostModel::new(&config.sah);
            let per_byte = params.cost_ratio * model.tree(tree) / b.tree(tree) as f64;
            Some((model, per_byte))
        }
        _ => None,
    };
    let inputs = SlimInputs {
        scene,
        params,
        sa_root: tree.bounds.surface_area(),
        bytes,
        price,
        progress,
    };
    phases.analysis_s += lap(&mut clock);
    // Rebuilt subtrees are priced as nodes of the whole tree.
    let mut rebuild_config = params.rebuild_config(config);
    (rebuild_config.sah.price_scale)
        .get_or_insert_with(|| crate::build::sah::price_scale(&tree.bounds, scene.len()));
    let leaf_rule = rebuild_config
        .sah
        .leaf_rule(scene.len(), || unreachable!("the price scale is set"));
    let mut todo = vec![Todo {
        node: root,
        size: tree.nodes.len() as u32,
        cell: tree.bounds,
        depth: 0,
        t2rn: 0,
        analysis: Some(Arc::new(analysis)),
        weight: Progress::TOTAL,
    }];
    while !todo.is_empty() {
        phases.passes += 1;
        let picks: Vec<Pick> = todo
            .par_drain(..)
            .flat_map_iter(|sub| find_picks(&work, sub, &inputs))
            .collect();
        phases.analysis_s += lap(&mut clock);
        let outcomes: Vec<(Outcome, usize)> = picks
            .par_iter()
            .map_init(
                || Rebuilder {
                    builder: SubtreeBuilder::new(scene, &rebuild_config),
                    pruner: prune::Pruner::new(rebuild_config.sah, leaf_rule),
                    tris: Vec::new(),
                    refs: Vec::new(),
                },
                |r, p| rebuild_pick(&work, p, &inputs, r),
            )
            .collect();
        phases.rebuild_s += lap(&mut clock);
        let mut fresh = Vec::new();
        for (p, (outcome, n)) in picks.iter().zip(outcomes) {
            if !matches!(outcome, Outcome::Skipped) {
                report.rebuilds += 1;
                report.rebuilt_refs += n;
            }
            match outcome {
                Outcome::Hoisted(t) => {
                    report.hoisted += 1;
                    fresh.push((p, t));
                }
                // The original subtree stays, and its children are
                // processed as if nothing was picked here, with the same
                // analysis.
                Outcome::Cancelled | Outcome::Rejected | Outcome::Priced | Outcome::Skipped => {
                    match outcome {
                        Outcome::Cancelled => report.cancelled += 1,
                        Outcome::Rejected => report.rejected += 1,
                        Outcome::Priced => report.priced += 1,
                        _ => report.skipped += 1,
                    }
                    todo.extend(p.at.children(&work, p.at.t2rn, p.at.analysis.clone(), progress));
                }
            }
        }
        let (at, trees): (Vec<&Pick>, Vec<TreeIr>) = fresh.into_iter().unzip();
        let sizes: Vec<(u32, u32)> = trees
            .iter()
            .map(|t| match t.nodes[0] {
                Node::Inner { right, .. } => (right.0, t.nodes.len() as u32),
                Node::Leaf { .. } => unreachable!("hoisted subtrees have an inner root"),
            })
            .collect();
        let bases = work.append_all(trees);
        for ((p, base), (right, size)) in at.into_iter().zip(bases).zip(sizes) {
            let WorkNode::Inner { axis, pos, .. } = work.nodes[base as usize] else {
                unreachable!("hoisted subtrees have an inner root");
            };
            // The fresh root's split, with the hoisted triangle, at the
            // pick's node; the fresh root itself stays unreachable.
            work.nodes[p.at.node as usize] = WorkNode::Inner {
                axis,
                pos,
                left: base + 1,
                right: base + right,
                t_ref: Some(p.tri),
            };
            let here = Todo {
                size,
                analysis: None,
                ..p.at.clone()
            };
            if p.at.t2rn + 1 < params.max_t2rn {
                todo.extend(here.children(&work, p.at.t2rn + 1, None, progress));
            } else {
                Progress::add(progress, here.weight);
            }
        }
        phases.apply_s += lap(&mut clock);
    }
    let out = work.to_ir(root, tree.bounds);
    phases.assemble_s = lap(&mut clock);
    (out, report, phases)
}

/// A test scene: triangle 0 is big and spans an 8×8 grid of small
/// slanted triangles 2 apart, so the standard tree lists it in many leaves.
#[cfg(test)]
pub(crate) fn huge_over_grid() -> TriangleColumns {
    use glam::Vec3;
    let mut tris = vec![[
        Vec3::new(-1.0, -1.0, 0.5),
        Vec3::new(30.0, -1.0, 0.5),
        Vec3::new(-1.0, 30.0, 0.5),
    ]];
    tris.extend(crate::scene::slanted_grid(8));
    TriangleColumns::from_triangles(&tris).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::{self, Algorithm};
    use std::collections::BTreeSet;

    /// The end of the subtree of node `i` in pre-order.
    fn subtree_end(tree: &TreeIr, i: usize) -> usize {
        match tree.nodes[i] {
            Node::Leaf { .. } => i + 1,
            Node::Inner { right, .. } => subtree_end(tree, right.0 as usize),
        }
    }

    #[test]
    fn a_rebuild_stops_only_where_the_byte_rule_rejects() {
        // Every inner node of two std trees (the root of the second takes
        // the event sweep, the rest the tiny one) rebuilt, as a pick is,
        // without its smallest triangle, under every byte limit up to its
        // bytes + 1: a build that stops is one whose whole subtree takes at
        // least the limit, and one that does not is the whole subtree.
        let mut tris = crate::scene::slanted_grid(9);
        tris.push([
            glam::Vec3::new(-1.0, 0.5, -1.0),
            glam::Vec3::new(19.0, 0.5, -1.0),
            glam::Vec3::new(-1.0, 0.5, 19.0),
        ]);
        let config = BuildConfig::default();
        for scene in [
            huge_over_grid(),
            TriangleColumns::from_triangles(&tris).unwrap(),
        ] {
            let std_tree = build::build(&scene, &config, Algorithm::WaldHavran, None).unwrap();
            let model = ByteModel::new(&scene, false);
            let mut builder = SubtreeBuilder::new(&scene, &config);
            let (mut stops, mut rebuilt) = (0, 0);
            let mut stack = vec![(0, std_tree.bounds, 0)];
            while let Some((i, cell, depth)) = stack.pop() {
                let Node::Inner {
                    axis, pos, right, ..
                } = std_tree.nodes[i]
                else {
                    continue;
                };
                let (lc, rc) = cell.split(axis as usize, pos);
                stack.push((i + 1, lc, depth + 1));
                stack.push((right.0 as usize, rc, depth + 1));
                let under: BTreeSet<u32> = std_tree.nodes[i..subtree_end(&std_tree, i)]
                    .iter()
                    .flat_map(|n| match *n {
                        Node::Leaf { start, count } => std_tree.leaf(start, count).to_vec(),
                        Node::Inner { .. } => Vec::new(),
                    })
                    .map(|t| t.0)
                    .collect();
                let refs: Vec<(TriId, Aabb)> = under
                    .iter()
                    .skip(1)
                    .filter_map(|&t| clip_triangle(&scene.tri(t), &cell).map(|b| (TriId(t), b)))
                    .collect();
                let (nodes, leaf_tris) = builder
                    .build(refs.iter().copied(), cell, depth, u64::MAX)
                    .map(|(n, l)| (n.to_vec(), l.to_vec()))
                    .unwrap();
                let bytes = model.nodes(&nodes, &leaf_tris);
                rebuilt += 1;
                for limit in 0..=bytes + 1 {
                    match builder.build(refs.iter().copied(), cell, depth, limit) {
                        None => {
                            assert!(bytes >= limit, "node {i}: stopped at {limit} of {bytes}");
                            assert!(matches!(nodes[0], Node::Inner { .. }));
                            stops += 1;
                        }
                        Some((n, l)) => assert_eq!((n, l), (&nodes[..], &leaf_tris[..])),
                    }
                }
            }
            assert!(
                rebuilt > 10 && stops > rebuilt,
                "{rebuilt} rebuilds, {stops} stops"
            );
        }
    }

    #[test]
    fn huge_triangle_is_hoisted() {
        // A big triangle spanning a grid of small ones lies in most leaves:
        // with the paper's rule it is hoisted into the root. With the byte
        // rule it is not (the rebuilt tree cuts the empty space around the
        // small triangles and takes more nodes), and the tree never grows.
        let scene = huge_over_grid();
        let config = BuildConfig::default();
        let std_tree = build::build(&scene, &config, Algorithm::WaldHavran, None).unwrap();
        let paper = SlimParams::SMALL.with_rule(HoistRule::Paper);
        let (slim_tree, report) = slim(&std_tree, &scene, &config, &paper);
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
        for reordered in [false, true] {
            // The byte rule alone: no price rule to reject first.
            let p = SlimParams {
                cost_ratio: f64::INFINITY,
                ..SlimParams::SMALL.with_rule(HoistRule::Bytes { reordered })
            };
            let (slim_tree, report) = slim(&std_tree, &scene, &config, &p);
            slim_tree.validate(&scene).unwrap();
            let m = ByteModel::new(&scene, reordered);
            assert!(m.tree(&slim_tree) <= m.tree(&std_tree), "{report:?}");
            assert!(report.rejected + report.skipped > 0, "{report:?}");
        }
    }
}
