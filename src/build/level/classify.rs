//! Step 4 of a level (and the finisher's classification): where each
//! reference of a split node goes, the straddlers clipped to both
//! children, and the child references written into the next level's
//! columns at places found by prefix counts.
//!
//! A reference's placement is a code of three bits
//! ([`super::placement`]); [`classify_ref`] is the one
//! classification the level passes and the depth-first finisher share, so
//! they cannot classify differently.

use super::events::{PackedBox, n_events, to_aabb, to_box};
use super::pieces::{Piece, carries};
use super::placement::{CLIPPED, DROPPED, TO_LEFT, TO_RIGHT};
use super::{Level, LevelNode};
use crate::build::sah::Split;
use crate::build::{Placement, TriRef, classify, clip_straddler};
use crate::columns::ScatterSlice;
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::TriId;
use rayon::prelude::*;
use std::ops::Add;

/// Counts of a pass over one node's references, per child side.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct SideCounts {
    /// References going to each side (clipped ones included).
    pub(super) n: [usize; 2],
    /// Inherited events per side and axis (references wholly on one side).
    pub(super) inherited: [[usize; 3]; 2],
    /// Events of clipped references per side and axis.
    pub(super) new: [[usize; 3]; 2],
}

impl Add for SideCounts {
    type Output = SideCounts;
    fn add(mut self, o: SideCounts) -> SideCounts {
        for s in 0..2 {
            self.n[s] += o.n[s];
            for k in 0..3 {
                self.inherited[s][k] += o.inherited[s][k];
                self.new[s][k] += o.new[s][k];
            }
        }
        self
    }
}

/// A straddler's clipped boxes in the left and right child.
type ChildBoxes = (Option<Aabb>, Option<Aabb>);

/// Classifies one reference (box `b` of triangle `tri`) against `split`,
/// clips it if it straddles, and adds what each side inherits or gains to
/// `c`. Returns the placement code and, for a straddler, its clipped boxes
/// in the two children. The breadth-first pass and the depth-first
/// finisher share it, so they cannot classify differently.
pub(super) fn classify_ref(
    scene: &TriangleColumns,
    tri: u32,
    b: &PackedBox,
    split: &Split,
    lc: &Aabb,
    rc: &Aabb,
    c: &mut SideCounts,
) -> (u8, Option<ChildBoxes>) {
    let bx = to_aabb(b);
    match classify(&bx, split) {
        Placement::Left => {
            c.n[0] += 1;
            for k in 0..3 {
                c.inherited[0][k] += n_events(b, k);
            }
            (TO_LEFT, None)
        }
        Placement::Right => {
            c.n[1] += 1;
            for k in 0..3 {
                c.inherited[1][k] += n_events(b, k);
            }
            (TO_RIGHT, None)
        }
        Placement::Both => {
            let r = TriRef {
                tri: TriId(tri),
                bounds: bx,
            };
            let (lb, rb) = clip_straddler(scene, &r, split, lc, rc);
            let mut code = CLIPPED;
            for (side, cb) in [lb, rb].iter().enumerate() {
                if let Some(cb) = cb {
                    code |= 1 << side;
                    c.n[side] += 1;
                    let cb = to_box(cb);
                    for k in 0..3 {
                        c.new[side][k] += n_events(&cb, k);
                    }
                }
            }
            (code, Some((lb, rb)))
        }
    }
}

/// What the classify pass found in one piece.
pub(super) struct Classified {
    /// Per node of the piece.
    pub(super) counts: Vec<SideCounts>,
    /// The straddlers in reference order: (reference, left box, right box).
    pub(super) clipped: Vec<(u32, Option<Aabb>, Option<Aabb>)>,
}

/// Classifies the references of the split nodes, clips the straddlers
/// and writes each reference's placement into `place`.
pub(super) fn classify_pass(
    scene: &TriangleColumns,
    l: &Level<'_>,
    splits: &[(usize, Split)],
    rsegs: &[(usize, usize)],
    rpieces: &[Piece],
    place: &mut [u8],
) -> Vec<Classified> {
    let place = ScatterSlice::new(place);
    // Sliced once: a column's `Deref` matches on where it lives.
    let (tris, bounds): (&[u32], &[PackedBox]) = (&l.tri, &l.bounds);
    rpieces
        .par_iter()
        .map(|p| {
            let mut counts = Vec::with_capacity(p.nodes.len());
            let mut clipped = Vec::new();
            for si in p.nodes.clone() {
                let (j, split) = splits[si];
                let (lc, rc) = l.nodes[j].cell.split(split.axis as usize, split.pos);
                let mut c = SideCounts::default();
                for i in p.range(rsegs[si]) {
                    let (code, straddler) =
                        classify_ref(scene, tris[i], &bounds[i], &split, &lc, &rc, &mut c);
                    if let Some((lb, rb)) = straddler {
                        clipped.push((i as u32, lb, rb));
                    }
                    // SAFETY: the pieces cover disjoint reference
                    // ranges, so position `i` is this piece's alone.
                    unsafe { place.write(i, code) };
                }
                counts.push(c);
            }
            Classified { counts, clipped }
        })
        .collect()
}

/// The counts each piece of the split nodes' references carries over from
/// the earlier pieces of its node (a segmented prefix count over the pieces'
/// [`SideCounts`]).
pub(super) fn piece_carries(rpieces: &[Piece], classified: &[Classified]) -> Vec<SideCounts> {
    let part_counts: Vec<SideCounts> = rpieces
        .iter()
        .zip(classified)
        .map(|(p, c)| {
            if p.part.is_some() {
                c.counts[0]
            } else {
                SideCounts::default()
            }
        })
        .collect();
    carries(rpieces, &part_counts)
}

/// Writes the child references (kept boxes and clipped boxes) into the
/// next level's columns, and into `new_idx` each one-sided reference's new
/// index and side and each straddler's [`DROPPED`] (so that the event
/// partition needs one lookup per event). Returns the clipped copies as
/// `(child node << 32) | new reference`, whose events are not inherited.
#[allow(clippy::too_many_arguments)]
pub(super) fn write_children(
    l: &Level<'_>,
    place: &[u8],
    rsegs: &[(usize, usize)],
    rpieces: &[Piece],
    classified: &[Classified],
    rcarry: &[SideCounts],
    next: &[LevelNode],
    tri: &mut [u32],
    boxes: &mut [PackedBox],
    new_idx: &mut [u32],
) -> Vec<u64> {
    let tri = ScatterSlice::new(tri);
    let boxes = ScatterSlice::new(boxes);
    let new_idx = ScatterSlice::new(new_idx);
    // Sliced once: a column's `Deref` matches on where it lives.
    let (l_tri, l_bounds): (&[u32], &[PackedBox]) = (&l.tri, &l.bounds);
    let copies: Vec<Vec<u64>> = rpieces
        .par_iter()
        .zip(classified.par_iter())
        .zip(rcarry.par_iter())
        .map(|((p, c), carry)| {
            let mut copies = Vec::new();
            let mut clipped = c.clipped.iter();
            for si in p.nodes.clone() {
                let seg = rsegs[si];
                let (cl, cr) = (2 * si, 2 * si + 1);
                let carry = if p.continues(seg) {
                    *carry
                } else {
                    SideCounts::default()
                };
                let mut at = [next[cl].refs + carry.n[0], next[cr].refs + carry.n[1]];
                for i in p.range(seg) {
                    let code = place[i];
                    if code & CLIPPED == 0 {
                        let side = usize::from(code == TO_RIGHT);
                        let d = at[side];
                        at[side] += 1;
                        // SAFETY: `d` is this reference's rank among the
                        // node's references going to `side`, offset by the
                        // child's start: distinct for every reference of
                        // every piece. `i` lies in this piece's range.
                        unsafe {
                            tri.write(d, l_tri[i]);
                            boxes.write(d, l_bounds[i]);
                            new_idx.write(i, d as u32 | (side as u32) << 31);
                        }
                    } else {
                        // SAFETY: as above.
                        unsafe { new_idx.write(i, DROPPED) };
                        let &(ci, lb, rb) = clipped.next().expect("one entry per straddler");
                        debug_assert_eq!(ci as usize, i);
                        for (side, cb) in [lb, rb].into_iter().enumerate() {
                            if let Some(cb) = cb {
                                let d = at[side];
                                at[side] += 1;
                                // SAFETY: as above.
                                unsafe {
                                    tri.write(d, l_tri[i]);
                                    boxes.write(d, to_box(&cb));
                                }
                                let child = [cl, cr][side];
                                copies.push(((child as u64) << 32) | d as u64);
                            }
                        }
                    }
                }
            }
            copies
        })
        .collect();
    copies.concat()
}
