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
    /// file (format version 2) stores them, so that the sum over the tree
    /// is the file's `tree_bytes`, `8·words + 4·|idx32| + 2·|idx16|`: 8 per
    /// inner node, 8 more per hoisted triangle, nothing for an empty leaf
    /// (but 8 for the left child of a node whose two children are empty),
    /// 8 for a leaf of one triangle (held in its word), and per other leaf
    /// 8 and 2 bytes per index if it fits 2-byte mode, else 4
    /// ([`leaf_index_bytes`]). Whether a leaf
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

/// How a pick's subtree is made without its triangle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rebuild {
    /// The paper's: the subtree's triangles less the picked one, each
    /// clipped to the node's cell, built anew by the SAH builder at the
    /// node's depth with `K_T` × [`SlimParams::coarsen`].
    Sah,
    /// The subtree's splits are kept: the picked triangle leaves its
    /// leaves, and bottom-up two sibling leaves become one where the
    /// rebuild's leaf rule (`K_T` × [`SlimParams::coarsen`], the split
    /// price) prefers a leaf to their parent's split. Linear in the
    /// subtree (no sweep, no clipping): the slim build takes 1.35–1.85×
    /// the std build on the shared scenes against 2.7–4.5×, for 1–7
    /// points less of the bytes saved.
    Prune,
}

/// The thresholds of the oracle, the hoisting limit, the hoist rule and
/// the traversal cost of rebuilt subtrees.
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
    /// How a picked subtree is remade without its triangle.
    pub rebuild: Rebuild,
    /// The factor on `K_T` of the SAH that rebuilds a picked subtree
    /// ([`SlimParams::rebuild_config`]); 1 is the paper's rebuild. Above 1
    /// a rebuilt subtree stops splitting sooner, so with
    /// [`HoistRule::Bytes`] a hoist trades a little SAH cost for nodes:
    /// without it a rebuilt subtree has as many nodes as the one it
    /// replaces (−0.03 nodes per hoist on dieselpower, `small` thresholds,
    /// paper rule; the triangle removed straddles both children of most
    /// splits, which makes splitting *more* attractive).
    pub coarsen: f64,
    /// The price rule, with [`HoistRule::Bytes`]: a hoist is kept only
    /// if it raises the tree's SAH cost by at most this many times the
    /// share of the tree's bytes it saves, `ΔC / C_std ≤ cost_ratio ·
    /// ΔB / B_std`. `C` is the SAH cost of the std build's `K_T` and `K_I`
    /// (a hoisted triangle a test at its node, see `slim::cost`), `C_std`
    /// and `B_std` those of the std tree. Infinity keeps every hoist that
    /// saves bytes. Why: a hoist near the root is tested by every ray
    /// through its node, and the bytes it saves are a few indices in
    /// leaves most rays never reach (on stk_candela_city the `fast` tree
    /// without it tested 4.4 hoisted triangles a primary ray to save 0.13
    /// leaf tests, 4.5 % slower packets than std; at 0.01, with rebuilds
    /// at 1.5 × `K_T`, it is within 1.3 % of std there and 35 % smaller).
    pub cost_ratio: f64,
    /// The split price `μ` of the preset's tree (`build::sah::SahParams::
    /// split_price`): [`Pipeline::slimmed`] puts it into the build
    /// configuration, so that the std tree the pass starts from and its
    /// rebuilds are built with it. `None`: the configuration's. The pass
    /// itself ([`super::slim`]) takes the configuration the tree was built
    /// with and does not read it. Why the presets raise it: the default
    /// price (0.5) has taken much of the duplication hoisting removes, and
    /// a higher price removes nodes where primary packets lose least
    /// (ravenbridge at μ 2 alone: 29 % fewer bytes for 1.4 % of its
    /// primary packets' speed, but 14 % of its single rays').
    ///
    /// [`Pipeline::slimmed`]: crate::pipeline::Pipeline::slimmed
    pub split_price: Option<f64>,
}

impl SlimParams {
    /// The `fast` preset: the split price at 1.5, low thresholds (τ_occu
    /// 0.1, τ_freq 0.05, max_t2rn 16) with the byte rule for a reordered
    /// file, rebuilt subtrees priced with 1.5 × `K_T`, and the price rule
    /// at 0.01: 21–35 % fewer tree bytes than std on the six shared
    /// scenes, tracing primary packets at 0.97–1.08× std's speed and
    /// single rays at 0.82–1.14× (the split price costs single rays on
    /// ravenbridge and black_forest; `docs/perf-notes.md`, "The presets on
    /// the priced std tree").
    pub const FAST: SlimParams = SlimParams {
        tau_occu: 0.1,
        tau_freq: 0.05,
        max_t2rn: 16,
        rule: HoistRule::Bytes { reordered: true },
        rebuild: Rebuild::Sah,
        coarsen: 1.5,
        cost_ratio: 0.01,
        split_price: Some(1.5),
    };
    /// The `small` preset: the split price at 2, the thresholds of `fast`,
    /// the rebuilt subtrees priced with twice `K_T`, the price rule at
    /// 0.05: 32–46 % fewer tree bytes than std on the same scenes, at
    /// 0.93–1.08× std's speed in packets and 0.71–1.04× in single rays
    /// (`docs/perf-notes.md`, "The presets on the priced std tree").
    pub const SMALL: SlimParams = SlimParams {
        coarsen: 2.0,
        cost_ratio: 0.05,
        split_price: Some(2.0),
        ..SlimParams::FAST
    };
    /// The paper's `f` setting (τ_occu 0.9, τ_freq 0.7, max_t2rn 4) with
    /// its Algorithm 1 ([`HoistRule::Paper`], the literal rebuild).
    pub const PAPER_FAST: SlimParams = SlimParams {
        tau_occu: 0.9,
        tau_freq: 0.7,
        max_t2rn: 4,
        rule: HoistRule::Paper,
        rebuild: Rebuild::Sah,
        coarsen: 1.0,
        cost_ratio: f64::INFINITY,
        split_price: None,
    };
    /// The paper's `s` setting (τ_occu 0.5, τ_freq 0.4, max_t2rn 4) with
    /// its Algorithm 1.
    pub const PAPER_SMALL: SlimParams = SlimParams {
        tau_occu: 0.5,
        tau_freq: 0.4,
        ..SlimParams::PAPER_FAST
    };

    /// The same thresholds with another hoist rule.
    pub const fn with_rule(self, rule: HoistRule) -> SlimParams {
        SlimParams { rule, ..self }
    }

    /// The build configuration of rebuilt subtrees: `config` with `K_T`
    /// times [`SlimParams::coarsen`] (the same depth limit, so the
    /// rebuilt subtrees stay inside the std tree's depth, and the same
    /// split price).
    pub fn rebuild_config(&self, config: &crate::build::BuildConfig) -> crate::build::BuildConfig {
        let mut c = *config;
        c.sah.k_t *= self.coarsen;
        c
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
    /// Hoists that saved bytes but were rejected by the price rule
    /// ([`SlimParams::cost_ratio`]).
    pub priced: usize,
    /// Hoists rejected by [`HoistRule::Bytes`] without a rebuild: the
    /// replaced subtree takes at most 8 bytes more than the smallest
    /// rebuilt subtree could ([`min_subtree_bytes`]), so no rebuild can
    /// pass the rule. (Such a pick would be rejected or cancelled.)
    ///
    /// [`min_subtree_bytes`]: super::min_subtree_bytes
    pub skipped: usize,
    /// Subtrees rebuilt (`hoisted + cancelled + rejected + priced`).
    pub rebuilds: usize,
    /// Triangle references rebuilt (the work of the rebuilds): with
    /// [`Rebuild::Sah`] the triangles of each rebuild, with
    /// [`Rebuild::Prune`] the references of each pruned subtree.
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
