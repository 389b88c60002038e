//! Figures about a tree: node, leaf and reference counts, depths, the SAH
//! cost, and the leaf-depth histogram (the figures of Choi et al. 2013,
//! Table 3 and Figure 6, for the standard tree).

pub mod bytes;

use crate::build::sah::SahParams;
use crate::geom::Aabb;
use crate::tree::{PreOrderSink, SinkStop, TreeIr, TriId};

/// Summary figures of one tree.
#[derive(Clone, Debug, PartialEq)]
pub struct TreeStats {
    /// All nodes.
    pub nodes: usize,
    /// Inner nodes without a hoisted triangle (type I).
    pub inner: usize,
    /// Inner nodes holding a hoisted triangle (type II, "t-inner").
    pub t_inner: usize,
    /// Leaves, empty ones included.
    pub leaves: usize,
    /// Leaves with no triangle.
    pub empty_leaves: usize,
    /// Triangle references in leaves (`leaf_tris.len()`).
    pub refs: usize,
    /// The deepest leaf's depth (root = 0).
    pub max_depth: u32,
    /// Mean depth of the non-empty leaves.
    pub mean_leaf_depth: f64,
    /// `leaf_depths[d]` = number of leaves at depth `d`.
    pub leaf_depths: Vec<u64>,
    /// The SAH cost of the whole tree: `Σ_inner K_T·SA(n)/SA(root) +
    /// Σ_leaf K_I·N(n)·SA(n)/SA(root)`.
    pub sah_cost: f64,
}

impl TreeStats {
    /// The figures of `tree`, its SAH cost priced with `params`.
    pub fn of(tree: &TreeIr, params: &SahParams) -> TreeStats {
        let mut sink = StatsSink::new(params);
        tree.feed(&mut sink)
            .expect("the statistics take any one tree");
        TreeStats {
            // Every entry, listed by a leaf or not.
            refs: tree.leaf_tris.len(),
            ..sink.finish()
        }
    }
}

/// [`TreeStats`] of a tree handed over in pre-order (what a streamed build
/// prints without the tree in memory); [`TreeStats::of`] is this sink fed
/// with a [`TreeIr`].
#[derive(Clone, Debug)]
pub struct StatsSink {
    params: SahParams,
    sa_root: f64,
    /// Cells and depths of the nodes to come, the next on top.
    stack: Vec<(Aabb, u32)>,
    depth_sum: u64,
    s: TreeStats,
}

impl StatsSink {
    /// A sink pricing the SAH cost with `params`.
    pub fn new(params: &SahParams) -> StatsSink {
        StatsSink {
            params: *params,
            sa_root: 0.0,
            stack: Vec::new(),
            depth_sum: 0,
            s: TreeStats {
                nodes: 0,
                inner: 0,
                t_inner: 0,
                leaves: 0,
                empty_leaves: 0,
                refs: 0,
                max_depth: 0,
                mean_leaf_depth: 0.0,
                leaf_depths: Vec::new(),
                sah_cost: 0.0,
            },
        }
    }

    /// The next node's cell and depth, and its share of the root's area.
    fn next(&mut self) -> Result<(Aabb, u32, f64), SinkStop> {
        let (cell, depth) = self.stack.pop().ok_or(SinkStop)?;
        self.s.nodes += 1;
        self.s.max_depth = self.s.max_depth.max(depth);
        let p = if self.sa_root > 0.0 {
            cell.surface_area() / self.sa_root
        } else {
            1.0
        };
        Ok((cell, depth, p))
    }

    /// The figures of the nodes seen.
    pub fn finish(self) -> TreeStats {
        let mut s = self.s;
        let full = s.leaves - s.empty_leaves;
        s.mean_leaf_depth = if full > 0 {
            self.depth_sum as f64 / full as f64
        } else {
            0.0
        };
        s
    }
}

impl PreOrderSink for StatsSink {
    fn bounds(&mut self, bounds: Aabb) -> Result<(), SinkStop> {
        self.sa_root = bounds.surface_area();
        self.stack = vec![(bounds, 0)];
        Ok(())
    }

    fn inner(&mut self, axis: u8, pos: f32, t_ref: Option<TriId>) -> Result<(), SinkStop> {
        let (cell, depth, p) = self.next()?;
        if t_ref.is_some() {
            self.s.t_inner += 1;
        } else {
            self.s.inner += 1;
        }
        self.s.sah_cost += self.params.k_t * p;
        let (l, r) = cell.split(usize::from(axis), pos);
        self.stack.push((r, depth + 1));
        self.stack.push((l, depth + 1));
        Ok(())
    }

    fn leaf(&mut self, tris: &[TriId]) -> Result<(), SinkStop> {
        let (_, depth, p) = self.next()?;
        let s = &mut self.s;
        let count = tris.len() as u32;
        s.refs += tris.len();
        s.leaves += 1;
        if count == 0 {
            s.empty_leaves += 1;
        } else {
            self.depth_sum += u64::from(depth);
        }
        if s.leaf_depths.len() <= depth as usize {
            s.leaf_depths.resize(depth as usize + 1, 0);
        }
        s.leaf_depths[depth as usize] += 1;
        s.sah_cost += self.params.k_i * f64::from(count) * p;
        Ok(())
    }
}
