//! Depth-first finishing of small nodes: the Wald-Havran builder's algorithm
//! (Wald & Havran 2006, §4; [`crate::build::wald_havran`]) on the level
//! builder's flat encoding, without a heap allocation per node. It
//! follows the Wald-Havran builder rather than the paper's small-node stage
//! (Wu et al. §4.3), so that the tree stays the same.
//!
//! Consumes one small node of a level: its references (ascending by
//! triangle), its sorted events per axis ([`super::events`]), its cell,
//! depth and progress weight. Produces the node's subtree as nodes and
//! leaf lists of its own (indices from 0), borrowed from the finisher
//! until its next node, equal to
//! what [`crate::build::wald_havran::build_subtree`] builds for the same node: the
//! same sweep ([`super::best_split::sweep_events`], pricing through
//! [`crate::build::sah`]), the same [`classify`] and [`clip_straddler`],
//! children inheriting their events by stable partition with the clipped
//! references' events sorted and merged in.
//!
//! Nodes of at most [`Finisher::with_tiny`] references find the same
//! split without events ([`super::tiny`]: every candidate plane counted
//! and priced in vector lanes), and a child that small gets no event
//! lists from its parent.
//!
//! A split that sends every reference, unclipped, to one side (it cuts off
//! empty space) gives that child the node's own references and events, in
//! the same order, so the child works on them in place; a tiny child then
//! prices its parent's candidate counts again ([`tiny::Boxes::Same`]).
//!
//! A [`Finisher`] is a worker's scratch: references and events live on
//! stacks that grow to the deepest path's needs once and are reused for
//! every node it finishes. A node's children are pushed above it, built
//! one after the other, and popped.

use super::NewEvents;
use super::best_split::{Alone, sweep_events};
use super::classify::{SideCounts, classify_ref};
use super::events::{PackedBox, ev_ref, push_events, to_aabb, to_box, with_ref};
use super::placement::{DROPPED, goes_to, is_clipped, side_of};
use super::tiny::{self, MAX_TINY};
use crate::build::sah::{self, LeafRule, SahParams, Split};
use crate::build::{Placement, Progress, TriRef, classify, clip_straddler};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::simd::SimdLevel;
use crate::tree::{Node, NodeId, TriId};

/// A worker's scratch for finishing small nodes.
pub struct Finisher<'a> {
    scene: &'a TriangleColumns,
    params: &'a SahParams,
    rule: LeafRule,
    progress: Option<&'a Progress>,
    /// Reference stacks: each open node's references are a range below
    /// `ref_top`. The vectors only grow (to the deepest path's needs), so
    /// pushing a node's children writes into memory that is already there
    /// instead of resizing (and zero-filling) for every node.
    tri: Vec<u32>,
    boxes: Vec<PackedBox>,
    ref_top: usize,
    /// Event stacks, one per axis, used like the reference stacks; an
    /// event's reference is its index relative to the first reference of
    /// its node.
    ev: [Vec<u64>; 3],
    ev_top: [usize; 3],
    /// Per reference of the node being split: its placement code.
    place: Vec<u8>,
    /// Per one-sided reference of the node being split: its index in its
    /// child.
    new_idx: Vec<u32>,
    /// The straddlers of the node being split, in order: their boxes in
    /// the children.
    clipped: Vec<(Option<Aabb>, Option<Aabb>)>,
    /// The clipped copies of the node being split: (side, index in child).
    copies: Vec<(u8, u32)>,
    /// The sorted events of each side's clipped copies on one axis.
    new_ev: [Vec<u64>; 2],
    nodes: Vec<Node>,
    leaf_tris: Vec<TriId>,
    new_events: NewEvents,
    /// Nodes of at most this many references are swept without events
    /// ([`super::tiny`]).
    tiny: usize,
    simd: SimdLevel,
    tiny_scratch: Box<tiny::Scratch>,
    /// A tiny node's right child's references while its left child's are
    /// written.
    right_tri: Vec<u32>,
    right_boxes: Vec<PackedBox>,
    /// A lower bound on the bytes the subtree being built takes in the
    /// file ([`pending_bytes`], [`leaf_bytes`]), kept while `byte_limit` is
    /// set: the finished leaves' and inner nodes' bytes plus the pending
    /// nodes' bounds.
    bytes_lb: u64,
    /// The build stops once `bytes_lb` reaches this at a split
    /// ([`Finisher::with_byte_limit`]); `u64::MAX`: never.
    byte_limit: u64,
    stopped: bool,
}

impl<'a> Finisher<'a> {
    pub fn new(
        scene: &'a TriangleColumns,
        params: &'a SahParams,
        rule: LeafRule,
        progress: Option<&'a Progress>,
    ) -> Finisher<'a> {
        Finisher {
            scene,
            params,
            rule,
            progress,
            tri: Vec::new(),
            boxes: Vec::new(),
            ref_top: 0,
            ev: Default::default(),
            ev_top: [0; 3],
            place: Vec::new(),
            new_idx: Vec::new(),
            clipped: Vec::new(),
            copies: Vec::new(),
            new_ev: Default::default(),
            nodes: Vec::new(),
            leaf_tris: Vec::new(),
            new_events: NewEvents::default(),
            tiny: 0,
            simd: SimdLevel::detect(),
            tiny_scratch: Box::default(),
            right_tri: Vec::new(),
            right_boxes: Vec::new(),
            bytes_lb: 0,
            byte_limit: u64::MAX,
            stopped: false,
        }
    }

    /// The next [`Finisher::build`] stops once the subtree is known to take
    /// at least `limit` bytes in the file (format version 2; the bound is
    /// checked where a node splits, so a subtree that is a single leaf is
    /// always built whole); [`Finisher::stopped`] then says so and the
    /// returned nodes are incomplete. `u64::MAX`: never (the default). The
    /// slim pass stops a rebuild whose hoist the byte rule must reject.
    pub fn with_byte_limit(&mut self, limit: u64) -> &mut Self {
        self.byte_limit = limit;
        self
    }

    /// The nodes and leaf lists of the last build.
    pub fn output(&self) -> (&[Node], &[TriId]) {
        (&self.nodes, &self.leaf_tris)
    }

    /// Whether the last build stopped at its byte limit.
    pub fn stopped(&self) -> bool {
        self.stopped
    }

    /// Nodes of at most `tiny` references (clamped to [`MAX_TINY`]) are
    /// swept without events, and get none from their parent.
    pub fn with_tiny(mut self, tiny: usize) -> Self {
        self.tiny = tiny.min(MAX_TINY);
        self
    }

    /// How clipped references' events join their child's list.
    pub fn with_new_events(mut self, mode: NewEvents) -> Self {
        self.new_events = mode;
        self
    }

    /// The subtree of one node: references `tri`/`boxes`, events `ev` per
    /// axis whose references count from `ref_base`. Returns its nodes and
    /// leaf lists.
    #[allow(clippy::too_many_arguments)]
    pub fn build(
        &mut self,
        tri: &[u32],
        boxes: &[PackedBox],
        ev: [&[u64]; 3],
        ref_base: u32,
        cell: Aabb,
        depth: u32,
        weight: u64,
    ) -> (&[Node], &[TriId]) {
        self.nodes.clear();
        self.leaf_tris.clear();
        grow(&mut self.tri, tri.len());
        self.tri[..tri.len()].copy_from_slice(tri);
        grow(&mut self.boxes, boxes.len());
        self.boxes[..boxes.len()].copy_from_slice(boxes);
        self.ref_top = tri.len();
        // A node the tiny path takes needs no events (nor do its children).
        let ev = if tri.len() <= self.tiny {
            [&[][..]; 3]
        } else {
            ev
        };
        for ((stack, src), top) in self.ev.iter_mut().zip(ev).zip(&mut self.ev_top) {
            grow(stack, src.len());
            for (d, &e) in stack.iter_mut().zip(src) {
                *d = with_ref(e, ev_ref(e) - ref_base);
            }
            *top = src.len();
        }
        let nev = [0, 1, 2].map(|k| ev[k].len());
        self.bytes_lb = pending_bytes(tri.len());
        self.stopped = false;
        self.node(0, tri.len(), [0; 3], nev, cell, depth);
        // The whole subtree's share at once: its leaves' shares sum to it,
        // and one shared counter updated per leaf by every worker cost
        // more than it showed.
        Progress::add(self.progress, weight);
        (&self.nodes, &self.leaf_tris)
    }

    fn node(
        &mut self,
        r0: usize,
        n: usize,
        e0: [usize; 3],
        ne: [usize; 3],
        cell: Aabb,
        depth: u32,
    ) {
        if self.stopped {
            return;
        }
        if n <= self.tiny {
            self.tiny_node(r0, n, cell, depth, tiny::Boxes::Count);
            return;
        }
        let sa = cell.surface_area();
        let mut best = None;
        // At the depth limit the node is a leaf whatever its best split
        // ([`sah::is_leaf`]), so the sweep is skipped.
        if sa > 0.0 && depth < self.rule.depth_limit {
            let cap = self.params.leaf_cost(n);
            for (axis, ev) in self.ev.iter().enumerate() {
                let ev = &ev[e0[axis]..e0[axis] + ne[axis]];
                sweep_events(
                    self.params,
                    &cell,
                    sa,
                    axis,
                    ev,
                    0,
                    n,
                    cap,
                    &mut best,
                    &Alone,
                );
            }
        }
        if self.is_leaf(best.as_ref(), r0, n, depth, &cell) {
            self.leaf(r0, n);
            return;
        }
        let split: Split = best.expect("a split exists when the node is not a leaf");
        let (lc, rc) = cell.split(split.axis as usize, split.pos);
        let c = self.classify(r0, n, &split, &lc, &rc);
        if depth + 1 >= self.rule.depth_limit {
            // Both children lie at the depth limit, so they are leaves: they
            // need their triangle lists (the clipping above decided which
            // straddlers stay), not their events.
            self.nodes.push(Node::Inner {
                axis: split.axis,
                pos: split.pos,
                right: NodeId(self.nodes.len() as u32 + 2),
                t_ref: None,
            });
            for side in 0..2 {
                let start = self.leaf_tris.len() as u32;
                let mut straddler = 0;
                for i in 0..n {
                    let code = self.place[i];
                    let goes = goes_to(code, side);
                    straddler += usize::from(is_clipped(code));
                    if goes {
                        self.leaf_tris.push(TriId(self.tri[r0 + i]));
                    }
                }
                debug_assert_eq!(straddler, self.clipped.len());
                let count = self.leaf_tris.len() as u32 - start;
                self.nodes.push(Node::Leaf { start, count });
                self.bytes_lb += leaf_bytes(count as usize);
            }
            self.bytes_lb = self.bytes_lb + 8 - pending_bytes(n);
            return;
        }

        // A split that cuts off empty space: every reference goes,
        // unclipped, to one side, so that child's references and events
        // are this node's, in the same order, and it works on them in
        // place (no copy, no partition); the other child is an empty leaf.
        if self.clipped.is_empty() && (c.n[0] == 0 || c.n[1] == 0) {
            if self.split_bytes(n, c.n) {
                return;
            }
            let me = self.open_inner(&split);
            if c.n[0] == 0 {
                self.leaf(r0, 0);
                self.right_child_next(me);
                self.node(r0, n, e0, ne, rc, depth + 1);
            } else {
                self.node(r0, n, e0, ne, lc, depth + 1);
                self.right_child_next(me);
                self.leaf(r0, 0);
            }
            return;
        }

        if self.split_bytes(n, c.n) {
            return;
        }
        // Child references: left at [c0[0], c0[1]), right at [c0[1], end).
        let l0 = self.ref_top;
        let c0 = [l0, l0 + c.n[0]];
        let end = c0[1] + c.n[1];
        grow(&mut self.tri, end);
        grow(&mut self.boxes, end);
        self.ref_top = end;
        // Which children need events: tiny ones are swept without.
        let need = [0, 1].map(|side| c.n[side] > self.tiny);
        // Per reference: its index in its child with the side in bit 31,
        // or `DROPPED` for a straddler (whose events are made anew) and a
        // reference of a child that needs no events, so that the partition
        // needs one lookup per event.
        grow(&mut self.new_idx, n);
        self.copies.clear();
        let mut at = c0;
        let mut straddler = 0;
        for i in 0..n {
            let code = self.place[i];
            if !is_clipped(code) {
                let side = side_of(code);
                let d = at[side];
                at[side] += 1;
                self.tri[d] = self.tri[r0 + i];
                self.boxes[d] = self.boxes[r0 + i];
                self.new_idx[i] = if need[side] {
                    (d - c0[side]) as u32 | (side as u32) << 31
                } else {
                    DROPPED
                };
            } else {
                self.new_idx[i] = DROPPED;
                let (lb, rb) = self.clipped[straddler];
                straddler += 1;
                for (side, cb) in [lb, rb].into_iter().enumerate() {
                    if let Some(cb) = cb {
                        let d = at[side];
                        at[side] += 1;
                        self.tri[d] = self.tri[r0 + i];
                        self.boxes[d] = to_box(&cb);
                        if need[side] {
                            self.copies.push((side as u8, (d - c0[side]) as u32));
                        }
                    }
                }
            }
        }

        // Child events: inherited by a stable partition, then each side's
        // sorted new events merged in. Tiny children get none.
        let mut ce0 = [self.ev_top; 2];
        let mut cne = [[0usize; 3]; 2];
        for axis in (0..3).filter(|_| need[0] || need[1]) {
            let inherited = [0, 1].map(|side| {
                if need[side] {
                    c.inherited[side][axis]
                } else {
                    0
                }
            });
            for (side, new) in self.new_ev.iter_mut().enumerate() {
                new.clear();
                if need[side] && c.new[side][axis] > 0 {
                    for &(s, r) in &self.copies {
                        if s as usize == side {
                            let b = &self.boxes[c0[side] + r as usize];
                            push_events(b, axis, r, new);
                        }
                    }
                    new.sort_unstable();
                }
            }
            let stack = &mut self.ev[axis];
            let base = self.ev_top[axis];
            let nl = inherited[0] + self.new_ev[0].len();
            let nr = inherited[1] + self.new_ev[1].len();
            ce0[0][axis] = base;
            ce0[1][axis] = base + nl;
            cne[0][axis] = nl;
            cne[1][axis] = nr;
            // One slot past both children takes the straddlers' events,
            // which are dropped: the partition writes every event somewhere
            // and only advances the cursor of a side that keeps it, so it
            // has no data-dependent branch.
            grow(stack, base + nl + nr + 1);
            self.ev_top[axis] = base + nl + nr;
            // The cursors stay in registers: the destination is a select,
            // not an index into an array of cursors (whose store and reload
            // per event made a chain through memory).
            let (src, dst) = stack.split_at_mut(base);
            let dst = &mut dst[..nl + nr + 1];
            let (mut at_l, mut at_r, sink) = (0, nl, nl + nr);
            for &e in &src[e0[axis]..e0[axis] + ne[axis]] {
                let v = self.new_idx[ev_ref(e) as usize];
                let keep = v != DROPPED;
                let right = keep & (v >> 31 != 0);
                let at = if right { at_r } else { at_l };
                let at = if keep { at } else { sink };
                dst[at] = with_ref(e, v & !(1 << 31));
                at_l += usize::from(keep & !right);
                at_r += usize::from(right);
            }
            debug_assert_eq!(at_l, inherited[0]);
            debug_assert_eq!(at_r, nl + inherited[1]);
            // Each side's sorted new events merge in from the back: only the
            // inherited events above the smallest new one move.
            for (side, start) in [(0, base), (1, base + nl)] {
                let new = &self.new_ev[side];
                let len = inherited[side] + new.len();
                self.new_events.merge(&mut stack[start..start + len], new);
            }
        }

        let me = self.open_inner(&split);
        self.node(c0[0], c.n[0], ce0[0], cne[0], lc, depth + 1);
        self.right_child_next(me);
        self.node(c0[1], c.n[1], ce0[1], cne[1], rc, depth + 1);
        self.ref_top = l0;
        self.ev_top = ce0[0];
    }

    /// Appends an inner node for `split` whose right child is not placed
    /// yet; returns its index (for [`Finisher::right_child_next`]).
    fn open_inner(&mut self, split: &Split) -> usize {
        self.nodes.push(Node::Inner {
            axis: split.axis,
            pos: split.pos,
            right: NodeId(u32::MAX),
            t_ref: None,
        });
        self.nodes.len() - 1
    }

    /// The inner node `me`'s right child is the next node appended (its
    /// left subtree is complete).
    fn right_child_next(&mut self, me: usize) {
        let next = NodeId(self.nodes.len() as u32);
        if let Node::Inner { right, .. } = &mut self.nodes[me] {
            *right = next;
        }
    }

    /// [`sah::is_leaf`] for the references `r0..r0 + n` in `cell` with
    /// their best split.
    fn is_leaf(&self, best: Option<&Split>, r0: usize, n: usize, depth: u32, cell: &Aabb) -> bool {
        sah::is_leaf(self.params, best, n, depth, &self.rule, cell, |s| {
            straddlers(&self.boxes[r0..r0 + n], s)
        })
    }

    /// A leaf of the references `r0..r0 + n`.
    fn leaf(&mut self, r0: usize, n: usize) {
        self.bytes_lb = self.bytes_lb + leaf_bytes(n) - pending_bytes(n);
        let start = self.leaf_tris.len() as u32;
        self.leaf_tris
            .extend(self.tri[r0..r0 + n].iter().map(|&t| TriId(t)));
        self.nodes.push(Node::Leaf {
            start,
            count: n as u32,
        });
    }

    /// [`Finisher::node`] for a node of at most `tiny` references, whose
    /// subtree has no events: the split from [`tiny::best_split`], then one
    /// pass that classifies, clips and writes the children's references
    /// (the left child's in place above the node, the right child's
    /// through `right_tri`/`right_boxes`), in the same order as `node`.
    ///
    /// `which` is [`tiny::Boxes::Same`] when the node's boxes are those its
    /// parent counted (the parent's split sent them all, unclipped, to
    /// this side).
    fn tiny_node(&mut self, r0: usize, n: usize, cell: Aabb, depth: u32, which: tiny::Boxes) {
        if self.stopped {
            return;
        }
        let sa = cell.surface_area();
        let mut best = None;
        if n > 0 && sa > 0.0 && depth < self.rule.depth_limit {
            let boxes = &self.boxes[r0..r0 + n];
            let scratch = &mut self.tiny_scratch;
            let (simd, params) = (self.simd, self.params);
            tiny::best_split(simd, params, &cell, sa, boxes, which, scratch, &mut best);
        }
        if self.is_leaf(best.as_ref(), r0, n, depth, &cell) {
            self.leaf(r0, n);
            return;
        }
        let split: Split = best.expect("a split exists when the node is not a leaf");
        let (lc, rc) = cell.split(split.axis as usize, split.pos);
        let l0 = self.ref_top;
        grow(&mut self.tri, l0 + 2 * n);
        grow(&mut self.boxes, l0 + 2 * n);
        grow(&mut self.right_tri, n);
        grow(&mut self.right_boxes, n);
        let (mut n_l, mut n_r) = (0, 0);
        let mut clipped = false;
        for i in r0..r0 + n {
            let (t, b) = (self.tri[i], self.boxes[i]);
            let bx = to_aabb(&b);
            let (to_left, to_right) = match classify(&bx, &split) {
                Placement::Left => (Some(b), None),
                Placement::Right => (None, Some(b)),
                Placement::Both => {
                    clipped = true;
                    let r = TriRef {
                        tri: TriId(t),
                        bounds: bx,
                    };
                    let (lb, rb) = clip_straddler(self.scene, &r, &split, &lc, &rc);
                    (lb.map(|b| to_box(&b)), rb.map(|b| to_box(&b)))
                }
            };
            if let Some(b) = to_left {
                self.tri[l0 + n_l] = t;
                self.boxes[l0 + n_l] = b;
                n_l += 1;
            }
            if let Some(b) = to_right {
                self.right_tri[n_r] = t;
                self.right_boxes[n_r] = b;
                n_r += 1;
            }
        }
        let r1 = l0 + n_l;
        self.tri[r1..r1 + n_r].copy_from_slice(&self.right_tri[..n_r]);
        self.boxes[r1..r1 + n_r].copy_from_slice(&self.right_boxes[..n_r]);
        self.ref_top = r1 + n_r;
        if self.split_bytes(n, [n_l, n_r]) {
            self.ref_top = l0;
            return;
        }

        // A split that moves every box unchanged to one side (cutting off
        // empty space): that child prices this node's counts again. The
        // other child is empty, so nothing counts in between.
        let which = if !clipped && (n_l == 0 || n_r == 0) {
            tiny::Boxes::Same
        } else {
            tiny::Boxes::Count
        };
        let me = self.open_inner(&split);
        self.tiny_node(l0, n_l, lc, depth + 1, which);
        self.right_child_next(me);
        self.tiny_node(r1, n_r, rc, depth + 1, which);
        self.ref_top = l0;
    }

    /// Accounts a node of `n` references split into children of `counts`
    /// references in the byte bound: its word, and the children pending.
    /// Returns whether the build stops here (the bound reached the limit).
    #[inline]
    fn split_bytes(&mut self, n: usize, counts: [usize; 2]) -> bool {
        self.bytes_lb = self.bytes_lb + 8 + pending_bytes(counts[0]) + pending_bytes(counts[1])
            - pending_bytes(n);
        self.stopped = self.bytes_lb >= self.byte_limit;
        self.stopped
    }

    /// Fills `place` and `clipped` for the node's references; returns the
    /// counts per side.
    fn classify(&mut self, r0: usize, n: usize, split: &Split, lc: &Aabb, rc: &Aabb) -> SideCounts {
        let mut c = SideCounts::default();
        self.place.clear();
        self.clipped.clear();
        for i in r0..r0 + n {
            let (code, straddler) = classify_ref(
                self.scene,
                self.tri[i],
                &self.boxes[i],
                split,
                lc,
                rc,
                &mut c,
            );
            if let Some(boxes) = straddler {
                self.clipped.push(boxes);
            }
            self.place.push(code);
        }
        c
    }
}

/// The fewest bytes (format version 2) a leaf of `n` references takes: no
/// word when empty, one word for one triangle, else a word and at least 2
/// bytes per index.
#[inline]
fn leaf_bytes(n: usize) -> u64 {
    match n {
        0 => 0,
        1 => 8,
        n => 8 + 2 * n as u64,
    }
}

/// The fewest bytes the subtree of a node of `n` references can take,
/// whatever it becomes: a leaf takes [`leaf_bytes`]; an inner node its
/// word, and either a child with a reference (at least 8 bytes more) or
/// the word an inner node with two empty children keeps (clipping may
/// leave a straddler in neither child, so the children need not hold `n`
/// references between them).
#[inline]
fn pending_bytes(n: usize) -> u64 {
    leaf_bytes(n).min(16)
}

/// Makes `v` at least `len` long (new entries are zero; existing ones are
/// kept, stale or not).
#[inline]
fn grow<T: Copy + Default>(v: &mut Vec<T>, len: usize) {
    if v.len() < len {
        v.resize(len.max(v.len() * 2), T::default());
    }
}

/// How many of `boxes` straddle `split`'s plane ([`sah::is_leaf`]).
pub(super) fn straddlers(boxes: &[PackedBox], split: &Split) -> usize {
    let k = split.axis as usize;
    boxes
        .iter()
        .filter(|b| sah::straddles(b[k], b[k + 3], split.pos))
        .count()
}
