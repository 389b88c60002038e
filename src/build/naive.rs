//! The reference builder: for each node, every candidate plane is priced by
//! counting the node's triangles directly, O(N²) per node. Obviously correct
//! and slow; tests assert that every other builder produces the same tree.

use super::sah::{self, PlaneCounts, Split};
use super::{BuildConfig, Placement, Progress, TreeWriter, TriRef, classify, clip_straddler, root};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::TreeIr;

/// Builds the standard tree of `scene` by counting (the tests' reference),
/// advancing `progress` as leaves are written.
pub fn build(scene: &TriangleColumns, config: &BuildConfig, progress: Option<&Progress>) -> TreeIr {
    let (bounds, refs) = root(scene);
    let mut ctx = NaiveBuilder {
        scene,
        config,
        out: TreeWriter::new(bounds, scene, config, progress),
    };
    ctx.node(refs, bounds, 0, Progress::TOTAL);
    ctx.out.tree
}

struct NaiveBuilder<'a> {
    scene: &'a TriangleColumns,
    config: &'a BuildConfig,
    out: TreeWriter<'a>,
}

impl NaiveBuilder<'_> {
    fn best_split(&self, refs: &[TriRef], cell: &Aabb) -> Option<Split> {
        let sa = cell.surface_area();
        if refs.is_empty() || sa <= 0.0 {
            return None;
        }
        let mut best = None;
        for axis in 0..3 {
            for r in refs {
                for pos in [r.bounds.min[axis], r.bounds.max[axis]] {
                    let mut counts = PlaneCounts {
                        left: 0,
                        right: 0,
                        planar: 0,
                    };
                    for o in refs {
                        let (lo, hi) = (o.bounds.min[axis], o.bounds.max[axis]);
                        if lo == pos && hi == pos {
                            counts.planar += 1;
                        } else {
                            counts.left += usize::from(lo < pos);
                            counts.right += usize::from(hi > pos);
                        }
                    }
                    sah::split_cost(&self.config.sah, cell, sa, axis, pos, counts)
                        .keep_best(&mut best);
                }
            }
        }
        best
    }

    fn node(&mut self, refs: Vec<TriRef>, cell: Aabb, depth: u32, weight: u64) {
        let best = self.best_split(&refs, &cell);
        let Some((split, left_cell, right_cell)) =
            self.out.split_or_leaf(best, &refs, &cell, depth, weight)
        else {
            return;
        };
        let (mut left, mut right) = (Vec::new(), Vec::new());
        for r in &refs {
            match classify(&r.bounds, &split) {
                Placement::Left => left.push(*r),
                Placement::Right => right.push(*r),
                Placement::Both => {
                    let (lb, rb) = clip_straddler(self.scene, r, &split, &left_cell, &right_cell);
                    if let Some(bounds) = lb {
                        left.push(TriRef { tri: r.tri, bounds });
                    }
                    if let Some(bounds) = rb {
                        right.push(TriRef { tri: r.tri, bounds });
                    }
                }
            }
        }
        drop(refs);
        let (wl, wr) = Progress::share(weight, left.len(), right.len());
        let me = self.out.inner(&split);
        self.node(left, left_cell, depth + 1, wl);
        self.out.right_child_next(me);
        self.node(right, right_cell, depth + 1, wr);
    }
}
