//! What a slim pass is asked to do and what it reports: the hoist rule,
//! the oracle's thresholds with the `fast` and `small` presets, the counts
//! of the pass's outcomes and its time per phase. Plain data, shared by the
//! driver, the CLI and the report.

/// Whether a picked triangle is hoisted (see the [module docs](super)).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HoistRule {
    /// The paper's Algorithm 1: every picked triangle is hoisted (unless
    /// the rebuilt subtree is a single leaf).
    Paper,
    /// A hoist is kept only if `bytes(rebuilt subtree) + 8 <
    /// bytes(replaced subtree)`, where a subtree's bytes are counted as the
    /// file stores them (the paper's tree memory,
    /// `8·(nodes + T-references) + 4·|idx32| + 2·|idx16|`): 8 per node, 8
    /// more per hoisted triangle, and per leaf 2 bytes per index if the
    /// leaf fits 2-byte mode, else 4 ([`leaf_index_bytes`]). Whether a leaf
    /// fits depends on the triangle ids in the file: with `reordered` they
    /// are the Morton ranks the writer gives with reordering
    /// ([`TriangleColumns::morton_order`]), else the input ids. The count
    /// is exact for a file written that way. The decision is greedy: it
    /// compares the two subtrees as they are when `I` is visited, before
    /// anything below is hoisted.
    ///
    /// [`leaf_index_bytes`]: crate::format::node::leaf_index_bytes
    /// [`TriangleColumns::morton_order`]: crate::scene::TriangleColumns::morton_order
    Bytes {
        /// The file is written with Morton-reordered triangle ids.
        reordered: bool,
    },
}

/// The thresholds of the oracle, the hoisting limit and the hoist rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlimParams {
    /// A triangle is picked only if its occupancy (share of the
    /// subtree's leaf surface area) exceeds this.
    pub tau_occu: f64,
    /// A triangle is picked only if it is in more than this share of the
    /// subtree's leaves.
    pub tau_freq: f64,
    /// Most hoisted triangles on any root path.
    pub max_t2rn: u32,
    /// Which picked triangles are hoisted.
    pub rule: HoistRule,
}

impl SlimParams {
    /// The `fast` preset: the paper's thresholds, with the byte rule for a
    /// reordered file.
    pub const FAST: SlimParams = SlimParams {
        tau_occu: 0.9,
        tau_freq: 0.7,
        max_t2rn: 4,
        rule: HoistRule::Bytes { reordered: true },
    };
    /// The `small` preset: the paper's thresholds, with the byte rule for
    /// a reordered file.
    pub const SMALL: SlimParams = SlimParams {
        tau_occu: 0.5,
        tau_freq: 0.4,
        max_t2rn: 4,
        rule: HoistRule::Bytes { reordered: true },
    };

    /// The same thresholds with another hoist rule.
    pub const fn with_rule(self, rule: HoistRule) -> SlimParams {
        SlimParams { rule, ..self }
    }
}

/// What the post-pass did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SlimReport {
    /// Triangles hoisted (type II nodes made).
    pub hoisted: usize,
    /// Hoists cancelled because the rebuilt subtree was a single leaf.
    pub cancelled: usize,
    /// Hoists rejected by [`HoistRule::Bytes`] (the rebuilt subtree was not
    /// smaller).
    pub rejected: usize,
    /// Hoists rejected by [`HoistRule::Bytes`] without a rebuild: the
    /// replaced subtree takes at most 8 bytes more than the smallest
    /// rebuilt subtree could ([`min_subtree_bytes`]), so no rebuild can
    /// pass the rule. (Such a pick would be rejected or cancelled.)
    ///
    /// [`min_subtree_bytes`]: super::min_subtree_bytes
    pub skipped: usize,
    /// Subtrees rebuilt (`hoisted + cancelled + rejected`).
    pub rebuilds: usize,
    /// Triangle references rebuilt (the work of the rebuilds).
    pub rebuilt_refs: usize,
}

/// Where the post-pass spent its time (seconds, wall clock).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SlimPhases {
    /// Passes over the pending subtrees.
    pub passes: u32,
    /// Analyses (the oracle for every node of a subtree) and the top-down
    /// search for picks, with the byte model's setup.
    pub analysis_s: f64,
    /// Rebuilding the picked subtrees and deciding.
    pub rebuild_s: f64,
    /// Putting the rebuilt subtrees into the work tree.
    pub apply_s: f64,
    /// The final tree in canonical pre-order.
    pub assemble_s: f64,
}
