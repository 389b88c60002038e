//! The sequential O(N log N) builder of Wald & Havran (2006), §4.
//!
//! Each node keeps, per axis, its events (the starts and ends of its
//! triangles' boxes, or one planar event for a flat box) sorted by
//! (position, kind, triangle), with `EventKind` declared in sweep order
//! End < Planar < Start. One sweep per axis finds the best plane. A child
//! inherits the events of the triangles that lie wholly on its side through
//! a stable partition (so they stay sorted); only the events of clipped
//! straddlers are created, sorted and merged in. The tree is the same as
//! [`super::naive`]'s (see [`super`] for the definition both follow).

use super::sah::{self, PlaneCounts, Split};
use super::{BuildConfig, Placement, Progress, TreeWriter, TriRef, classify, clip_straddler, root};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::{TreeIr, TriId};
use std::cmp::Ordering;

/// What an event marks, in sweep order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(u8)]
pub(crate) enum EventKind {
    End = 0,
    Planar = 1,
    Start = 2,
}

/// A box bound on one axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Event {
    pub pos: f32,
    pub kind: EventKind,
    pub tri: TriId,
}

impl Event {
    /// The sort order: (position, kind, triangle). Total, since a triangle
    /// has at most one event of each kind per axis.
    #[inline]
    pub(crate) fn cmp_order(&self, o: &Event) -> Ordering {
        self.pos
            .total_cmp(&o.pos)
            .then(self.kind.cmp(&o.kind))
            .then(self.tri.cmp(&o.tri))
    }
}

/// Appends the events of `r` on `axis`.
#[inline]
pub(crate) fn push_events(r: &TriRef, axis: usize, out: &mut Vec<Event>) {
    let (lo, hi) = (r.bounds.min[axis], r.bounds.max[axis]);
    if lo == hi {
        out.push(Event {
            pos: lo,
            kind: EventKind::Planar,
            tri: r.tri,
        });
    } else {
        out.push(Event {
            pos: lo,
            kind: EventKind::Start,
            tri: r.tri,
        });
        out.push(Event {
            pos: hi,
            kind: EventKind::End,
            tri: r.tri,
        });
    }
}

/// The sorted events of `refs` on `axis`.
pub(crate) fn sorted_events(refs: &[TriRef], axis: usize) -> Vec<Event> {
    let mut ev = Vec::with_capacity(refs.len() * 2);
    for r in refs {
        push_events(r, axis, &mut ev);
    }
    ev.sort_unstable_by(Event::cmp_order);
    ev
}

/// Merges two sorted event lists.
pub(crate) fn merge_events(a: Vec<Event>, b: &[Event]) -> Vec<Event> {
    if b.is_empty() {
        return a;
    }
    let mut out = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i].cmp_order(&b[j]) == Ordering::Less {
            out.push(a[i]);
            i += 1;
        } else {
            out.push(b[j]);
            j += 1;
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
    out
}

/// Sweeps the sorted events of one axis and keeps the best plane in `best`.
pub(crate) fn sweep_axis(
    params: &sah::SahParams,
    cell: &Aabb,
    sa: f64,
    axis: usize,
    events: &[Event],
    n: usize,
    best: &mut Option<Split>,
) {
    let (mut n_l, mut n_r) = (0usize, n);
    let mut i = 0;
    while i < events.len() {
        let pos = events[i].pos;
        let mut count = [0usize; 3];
        while i < events.len() && events[i].pos == pos {
            count[events[i].kind as usize] += 1;
            i += 1;
        }
        let [ends, planar, starts] = count;
        n_r -= planar + ends;
        let counts = PlaneCounts {
            left: n_l,
            right: n_r,
            planar,
        };
        sah::split_cost(params, cell, sa, axis, pos, counts).keep_best(best);
        n_l += starts + planar;
    }
}

/// Builds the standard tree of `scene` with the event sweep, depth-first
/// on one thread.
pub fn build(scene: &TriangleColumns, config: &BuildConfig, progress: Option<&Progress>) -> TreeIr {
    let (bounds, refs) = root(scene);
    build_subtree(scene, config, refs, bounds, 0, progress)
}

/// Builds the subtree of a node at `depth` with cell `cell` and triangle
/// references `refs` (ascending ids, boxes inside `cell`), under the depth
/// limit of the whole scene. The result's `bounds` is `cell`. This is how
/// the literal slim algorithm rebuilds a subtree without a hoisted triangle
/// ([`crate::slim::rebuild`]; the slim pass itself uses the level
/// builder's [`crate::build::level::SubtreeBuilder`], which builds the
/// same subtree).
pub(crate) fn build_subtree(
    scene: &TriangleColumns,
    config: &BuildConfig,
    refs: Vec<TriRef>,
    cell: Aabb,
    depth: u32,
    progress: Option<&Progress>,
) -> TreeIr {
    let events = [0, 1, 2].map(|axis| sorted_events(&refs, axis));
    // The placement scratch is indexed by triangle id. It is kept per
    // thread and never cleared: a node writes the entry of each of its
    // triangles before reading any, so stale entries are never read. (The
    // slim pass rebuilds many small subtrees; a fresh scene-sized array per
    // rebuild cost more than the rebuild.)
    let mut place = PLACE.with(|p| std::mem::take(&mut *p.borrow_mut()));
    if place.len() < scene.len() {
        place.resize(scene.len(), Placement::Left);
    }
    let mut ctx = WaldHavranBuilder {
        scene,
        config,
        out: TreeWriter::new(cell, scene, config, progress),
        place,
    };
    ctx.node(refs, events, cell, depth, Progress::TOTAL);
    PLACE.with(|p| *p.borrow_mut() = std::mem::take(&mut ctx.place));
    ctx.out.tree
}

thread_local! {
    static PLACE: std::cell::RefCell<Vec<Placement>> = const { std::cell::RefCell::new(Vec::new()) };
}

struct WaldHavranBuilder<'a> {
    scene: &'a TriangleColumns,
    config: &'a BuildConfig,
    out: TreeWriter<'a>,
    /// Scratch, indexed by triangle id: where each triangle of the node
    /// being split goes. Only entries of that node's triangles are valid.
    place: Vec<Placement>,
}

impl WaldHavranBuilder<'_> {
    fn node(
        &mut self,
        refs: Vec<TriRef>,
        events: [Vec<Event>; 3],
        cell: Aabb,
        depth: u32,
        weight: u64,
    ) {
        let sa = cell.surface_area();
        let mut best = None;
        if !refs.is_empty() && sa > 0.0 {
            for (axis, ev) in events.iter().enumerate() {
                sweep_axis(&self.config.sah, &cell, sa, axis, ev, refs.len(), &mut best);
            }
        }
        let Some((split, left_cell, right_cell)) =
            self.out.split_or_leaf(best, &refs, &cell, depth, weight)
        else {
            return;
        };

        // Classify; clip the straddlers.
        let mut left = Vec::new();
        let mut right = Vec::new();
        let mut left_new = Vec::new();
        let mut right_new = Vec::new();
        for r in &refs {
            let p = classify(&r.bounds, &split);
            self.place[r.tri.0 as usize] = p;
            match p {
                Placement::Left => left.push(*r),
                Placement::Right => right.push(*r),
                Placement::Both => {
                    let (lb, rb) = clip_straddler(self.scene, r, &split, &left_cell, &right_cell);
                    if let Some(bounds) = lb {
                        let c = TriRef { tri: r.tri, bounds };
                        left.push(c);
                        left_new.push(c);
                    }
                    if let Some(bounds) = rb {
                        let c = TriRef { tri: r.tri, bounds };
                        right.push(c);
                        right_new.push(c);
                    }
                }
            }
        }
        drop(refs);

        // Child events: inherited ones by stable partition, new ones sorted
        // and merged.
        let mut left_events: [Vec<Event>; 3] = Default::default();
        let mut right_events: [Vec<Event>; 3] = Default::default();
        for (axis, ev) in events.into_iter().enumerate() {
            let mut l = Vec::with_capacity(ev.len());
            let mut r = Vec::with_capacity(ev.len());
            for e in ev {
                match self.place[e.tri.0 as usize] {
                    Placement::Left => l.push(e),
                    Placement::Right => r.push(e),
                    Placement::Both => {}
                }
            }
            left_events[axis] = merge_events(l, &sorted_events(&left_new, axis));
            right_events[axis] = merge_events(r, &sorted_events(&right_new, axis));
        }

        let (wl, wr) = Progress::share(weight, left.len(), right.len());
        let me = self.out.inner(&split);
        self.node(left, left_events, left_cell, depth + 1, wl);
        self.out.right_child_next(me);
        self.node(right, right_events, right_cell, depth + 1, wr);
    }
}
