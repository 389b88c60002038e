//! The level builder's event encoding: one `u64` per event, whose integer
//! order is the sweep order of [`crate::build::wald_havran::Event::cmp_order`].
//!
//! | bits  | field |
//! |-------|-------|
//! | 63–32 | the position, as order-preserving bits of the `f32` ([`pos_key`]) |
//! | 31–30 | the kind: End = 0, Planar = 1, Start = 2 ([`EventKind`] as `u8`) |
//! | 29–0  | the reference: its index in the level's reference columns |
//!
//! Example: a Start event at `x = 1.5` of reference 7 is
//! `(0xBFC0_0000 << 32) | (2 << 30) | 7`, since `1.5f32` is `0x3FC0_0000`
//! and positive floats get the sign bit set.
//!
//! Within a node the references are ascending by triangle id, so ordering
//! by reference index is ordering by triangle id: a node's events sorted as
//! integers are sorted by (position, kind, triangle), as in the sweep
//! builder. A plain `u64` sort or merge keeps that order.
//!
//! Also here, step 5 of a level: the children's event lists. Inherited
//! events keep their order through a stable parallel partition
//! ([`partition_events`]); the clipped references' events are made anew,
//! sorted per child and merged in from the back of the child's segment
//! ([`NewEvents::merge`]). And the root's first sort
//! ([`radix_sort_by_position_and_kind`]).

use super::pieces::{PIECE, Pair, Piece, element_carries, pieces};
use super::placement::{DROPPED, SLOT};
use super::{Level, LevelNode, NewEvents};
use crate::build::sah::Split;
use crate::build::wald_havran::EventKind;
use crate::columns::{Column, ScatterSlice};
use crate::geom::Aabb;
use glam::Vec3;
use rayon::prelude::*;

/// References per level must fit the 30 reference bits.
pub const MAX_REFS: usize = 1 << 30;
pub const REF_MASK: u64 = (1 << 30) - 1;

/// A reference's box: `min` x, y, z then `max` x, y, z (a `Pod` column
/// element; `Aabb` itself is not `Pod`).
pub type PackedBox = [f32; 6];

#[inline]
pub fn to_box(b: &Aabb) -> PackedBox {
    [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z]
}

#[inline]
pub fn to_aabb(b: &PackedBox) -> Aabb {
    Aabb::new(Vec3::new(b[0], b[1], b[2]), Vec3::new(b[3], b[4], b[5]))
}

/// The order-preserving bits of a position: for floats that are not NaN,
/// `pos_key(a) < pos_key(b)` exactly when `a.total_cmp(&b)` is `Less`.
/// Builders never see `-0.0` (scenes and clipped boxes turn it into
/// `+0.0`), so equal keys are equal positions.
#[inline]
pub fn pos_key(p: f32) -> u32 {
    let b = p.to_bits();
    if b >> 31 == 1 { !b } else { b | 0x8000_0000 }
}

/// The position of a key: the inverse of [`pos_key`].
#[inline]
pub fn key_pos(k: u32) -> f32 {
    f32::from_bits(if k >> 31 == 1 { k & 0x7fff_ffff } else { !k })
}

#[inline]
pub fn event(pos: f32, kind: EventKind, r: u32) -> u64 {
    debug_assert!((r as u64) <= REF_MASK);
    debug_assert!(pos.to_bits() != (-0.0f32).to_bits());
    (u64::from(pos_key(pos)) << 32) | ((kind as u64) << 30) | u64::from(r)
}

#[inline]
pub fn ev_key(e: u64) -> u32 {
    (e >> 32) as u32
}

/// 0 = End, 1 = Planar, 2 = Start.
#[inline]
pub fn ev_kind(e: u64) -> usize {
    ((e >> 30) & 3) as usize
}

#[inline]
pub fn ev_ref(e: u64) -> u32 {
    (e & REF_MASK) as u32
}

/// The same event for another reference index.
#[inline]
pub fn with_ref(e: u64, r: u32) -> u64 {
    (e & !REF_MASK) | u64::from(r)
}

#[cfg(test)]
pub fn kind_of(e: u64) -> EventKind {
    match ev_kind(e) {
        0 => EventKind::End,
        1 => EventKind::Planar,
        _ => EventKind::Start,
    }
}

/// How many events a box has on `axis`: one planar event when it is flat
/// there, else a start and an end.
#[inline]
pub fn n_events(b: &PackedBox, axis: usize) -> usize {
    if b[axis] == b[axis + 3] { 1 } else { 2 }
}

/// Appends the events of reference `r` with box `b` on `axis`.
#[inline]
pub fn push_events(b: &PackedBox, axis: usize, r: u32, out: &mut Vec<u64>) {
    let (ev, n) = events_of(b, axis, r);
    out.push(ev[0]);
    if n == 2 {
        out.push(ev[1]);
    }
}

/// The events of reference `r` with box `b` on `axis`, in order: the
/// first `n` of the array ([`n_events`]), a planar event when the box is
/// flat there, else a start and an end.
#[inline]
pub fn events_of(b: &PackedBox, axis: usize, r: u32) -> ([u64; 2], usize) {
    let (lo, hi) = (b[axis], b[axis + 3]);
    if lo == hi {
        ([event(lo, EventKind::Planar, r), 0], 1)
    } else {
        (
            [event(lo, EventKind::Start, r), event(hi, EventKind::End, r)],
            2,
        )
    }
}

/// The stable partition of the inherited events: each event of a
/// one-sided reference goes, renumbered, to its child's segment, in the
/// order it had; the clipped references' events are dropped (they are
/// made anew in [`merge_new_events`]). A child's inherited events fill the
/// front of its segment.
pub(super) fn partition_events(
    l: &Level<'_>,
    splits: &[(usize, Split)],
    place: &[u8],
    new_idx: &[u32],
    next: &[LevelNode],
    ev: &mut [Column<'_, u64>; 3],
) {
    let [e0, e1, e2] = ev;
    let dst = [
        ScatterSlice::new(&mut e0[..]),
        ScatterSlice::new(&mut e1[..]),
        ScatterSlice::new(&mut e2[..]),
    ];
    let mut tasks: Vec<(usize, Piece, Pair)> = Vec::new();
    let mut segs_by_axis = Vec::with_capacity(3);
    for axis in 0..3 {
        let segs: Vec<(usize, usize)> = splits
            .iter()
            .map(|&(j, _)| (l.nodes[j].ev[axis], l.nodes[j].nev[axis]))
            .collect();
        let src: &[u64] = &l.ev[axis];
        let ps = pieces(&segs, PIECE, |_| true);
        // Counted by slot, without a branch on the side.
        let carry = element_carries(
            &ps,
            &segs,
            src,
            |e| SLOT[usize::from(place[ev_ref(e) as usize])],
            |c| Pair([c[0], c[1]]),
        );
        tasks.extend(ps.into_iter().zip(carry).map(|(p, c)| (axis, p, c)));
        segs_by_axis.push(segs);
    }
    tasks.par_iter().for_each(|(axis, p, carry)| {
        let axis = *axis;
        let src: &[u64] = &l.ev[axis];
        let dst = &dst[axis];
        for si in p.nodes.clone() {
            let seg = segs_by_axis[axis][si];
            let carry = if p.continues(seg) {
                *carry
            } else {
                Pair::default()
            };
            // The two cursors stay in registers (a select, not an array
            // indexed by the side, whose store and reload per event made a
            // chain through memory).
            let mut at_l = next[2 * si].ev[axis] + carry.0[0];
            let mut at_r = next[2 * si + 1].ev[axis] + carry.0[1];
            for &e in &src[p.range(seg)] {
                // One lookup per event: `new_idx` carries the side too
                // (`write_children`).
                let dest = new_idx[ev_ref(e) as usize];
                if dest != DROPPED {
                    let right = dest >> 31 != 0;
                    let at = if right { at_r } else { at_l };
                    // SAFETY: `at` is the event's rank among the node's
                    // events going to its side (carried over the node's
                    // earlier pieces), offset by the child's segment
                    // start: distinct for every event.
                    unsafe { dst.write(at, with_ref(e, dest & !(1 << 31))) };
                    at_l += usize::from(!right);
                    at_r += usize::from(right);
                }
            }
        }
    });
}

/// Sorts the events of each child's clipped references and merges them
/// into the child's segments, behind the inherited events.
pub(super) fn merge_new_events(
    mut copies: Vec<u64>,
    boxes: &[PackedBox],
    next: &[LevelNode],
    ev: &mut [Column<'_, u64>; 3],
    mode: NewEvents,
) {
    copies.par_sort_unstable();
    // Runs of copies of the same child.
    let mut runs = Vec::new();
    let mut s = 0;
    for i in 1..=copies.len() {
        if i == copies.len() || copies[i] >> 32 != copies[s] >> 32 {
            runs.push(s..i);
            s = i;
        }
    }
    let [e0, e1, e2] = ev;
    let dst = [
        ScatterSlice::new(&mut e0[..]),
        ScatterSlice::new(&mut e1[..]),
        ScatterSlice::new(&mut e2[..]),
    ];
    runs.par_iter().for_each_init(Vec::new, |tmp, run| {
        let child = &next[(copies[run.start] >> 32) as usize];
        for (axis, dst) in dst.iter().enumerate() {
            tmp.clear();
            for &c in &copies[run.clone()] {
                let r = c as u32;
                push_events(&boxes[r as usize], axis, r, tmp);
            }
            tmp.sort_unstable();
            // SAFETY: child segments are disjoint, and each child is one
            // run.
            let seg = unsafe { dst.range_mut(child.ev[axis], child.ev[axis] + child.nev[axis]) };
            mode.merge(seg, tmp);
        }
    });
}

/// Sorts events generated in reference order: a stable least-significant
/// digit radix sort on bits 30–63 (position and kind; the reference bits
/// are already in order), three passes of 11, 11 and 12 bits, from `a`
/// through `b` (of the same length). Returns whether the result is in `b`.
/// About four times faster than a comparison sort of the root's events.
///
/// A pass over more than [`RADIX_CHUNK`] events runs in parallel: each
/// chunk counts its digits, the counts are laid out digit by digit and
/// chunk by chunk within a digit, and each chunk scatters its events to
/// its own slots. That is the order of the serial pass, so the result is
/// the same; the root's sort was a serial stretch of the build (three
/// axes on two cores: 13.9 s of setup on 49.7 M triangles, one core busy).
pub(super) fn radix_sort_by_position_and_kind(a: &mut [u64], b: &mut [u64]) -> bool {
    let (mut src, mut dst) = (a, b);
    let mut in_b = false;
    for (shift, bits) in [(30u32, 11u32), (41, 11), (52, 12)] {
        if src.len() > RADIX_CHUNK {
            radix_pass_parallel(src, dst, shift, bits);
        } else {
            radix_pass(src, dst, shift, bits);
        }
        std::mem::swap(&mut src, &mut dst);
        in_b = !in_b;
    }
    in_b
}

/// Events a chunk of a parallel radix pass; fixed, so that the work of a
/// pass is cut the same way on any number of threads.
const RADIX_CHUNK: usize = 1 << 18;

/// One stable counting pass on the digit `(e >> shift) & (2^bits − 1)`.
fn radix_pass(src: &[u64], dst: &mut [u64], shift: u32, bits: u32) {
    let mask = (1u64 << bits) - 1;
    let mut count = vec![0usize; (1 << bits) + 1];
    for &e in src {
        count[((e >> shift) & mask) as usize + 1] += 1;
    }
    for d in 1..count.len() {
        count[d] += count[d - 1];
    }
    for &e in src {
        let d = ((e >> shift) & mask) as usize;
        dst[count[d]] = e;
        count[d] += 1;
    }
}

/// [`radix_pass`] over chunks of [`RADIX_CHUNK`] events in parallel.
fn radix_pass_parallel(src: &[u64], dst: &mut [u64], shift: u32, bits: u32) {
    let mask = (1u64 << bits) - 1;
    let digits = 1usize << bits;
    let mut counts: Vec<Vec<usize>> = src
        .par_chunks(RADIX_CHUNK)
        .map(|chunk| {
            let mut c = vec![0usize; digits];
            for &e in chunk {
                c[((e >> shift) & mask) as usize] += 1;
            }
            c
        })
        .collect();
    // Each chunk's first slot for each digit: all events of smaller
    // digits, then this digit's events of earlier chunks.
    let mut at = 0usize;
    for d in 0..digits {
        for c in counts.iter_mut() {
            let k = c[d];
            c[d] = at;
            at += k;
        }
    }
    debug_assert_eq!(at, src.len());
    let out = ScatterSlice::new(dst);
    src.par_chunks(RADIX_CHUNK)
        .zip(counts.par_iter_mut())
        .for_each(|(chunk, slot)| {
            for &e in chunk {
                let d = ((e >> shift) & mask) as usize;
                // SAFETY: the slots of a (chunk, digit) pair are a range of
                // their own (laid out above), one slot per event of the
                // chunk with that digit, so no two writes share a slot.
                unsafe { out.write(slot[d], e) };
                slot[d] += 1;
            }
        });
}

/// `seg` holds sorted events followed by `new.len()` free slots; merges the
/// sorted `new` in, from the back, so no element is overwritten before it
/// is read.
///
/// Each step writes the larger of the two candidates and advances the
/// cursor it came from, without a branch on the comparison (a coin flip
/// where the two lists interleave). Where at least [`GALLOP`] inherited
/// events lie above the next new one, which is most of the list when the
/// new events are few (the clipped copies' events on the other axes) or
/// bunched (on the split axis, at the child's face by the plane), the
/// block of them is found by a binary search and moved at once.
fn merge_back(seg: &mut [u64], new: &[u64]) {
    let (mut i, mut j) = (seg.len() - new.len(), new.len());
    let mut w = seg.len();
    while j > 0 {
        let b = new[j - 1];
        if i >= GALLOP && seg[i - GALLOP] > b {
            // `seg[hi..i]` are all above `b`. Steps doubling downwards
            // find a `lo` at or below `b` (or the start), then a binary
            // search between: the probes stay near `i`, where a search of
            // the whole list would miss the cache on a long segment.
            let (mut lo, mut hi, mut step) = (0, i - GALLOP, GALLOP);
            while hi > step {
                let probe = hi - step;
                if seg[probe] <= b {
                    lo = probe;
                    break;
                }
                hi = probe;
                step *= 2;
            }
            let p = lo + seg[lo..hi].partition_point(|&x| x <= b);
            seg.copy_within(p..i, p + j);
            w = p + j;
            i = p;
        }
        let a = seg[i.saturating_sub(1)];
        let take_a = i > 0 && a > b;
        seg[w - 1] = if take_a { a } else { b };
        i -= usize::from(take_a);
        j -= usize::from(!take_a);
        w -= 1;
    }
}

/// Inherited events above a new one from which [`merge_back`] moves them
/// as a block.
const GALLOP: usize = 16;

/// [`merge_back`]'s result by Wu et al.'s buckets: for each new event,
/// last first, the binary search of its bucket among the inherited events
/// not yet moved, one block move of the inherited events above it, and
/// one write.
fn bucket_merge(seg: &mut [u64], new: &[u64]) {
    let mut hi = seg.len() - new.len();
    for (j, &e) in new.iter().enumerate().rev() {
        let b = seg[..hi].partition_point(|&x| x < e);
        seg.copy_within(b..hi, b + j + 1);
        seg[b + j] = e;
        hi = b;
    }
}

impl NewEvents {
    /// `seg` holds sorted events followed by `new.len()` free slots; puts
    /// the sorted `new` in place.
    #[inline]
    pub(super) fn merge(self, seg: &mut [u64], new: &[u64]) {
        match self {
            NewEvents::SortMerge => merge_back(seg, new),
            NewEvents::Bucket => bucket_merge(seg, new),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_order_is_total_cmp_order() {
        let xs = [
            f32::NEG_INFINITY,
            -3.5,
            -1.0,
            -f32::MIN_POSITIVE,
            0.0,
            f32::MIN_POSITIVE,
            1.0,
            1.5,
            f32::MAX,
            f32::INFINITY,
        ];
        for a in xs {
            assert_eq!(key_pos(pos_key(a)).to_bits(), a.to_bits());
            for b in xs {
                assert_eq!(pos_key(a).cmp(&pos_key(b)), a.total_cmp(&b));
            }
        }
        assert_eq!(pos_key(1.5), 0xBFC0_0000);
    }

    #[test]
    fn event_fields_round_trip() {
        let e = event(-2.25, EventKind::Start, 12345);
        assert_eq!(key_pos(ev_key(e)), -2.25);
        assert_eq!(kind_of(e), EventKind::Start);
        assert_eq!(ev_ref(e), 12345);
        assert_eq!(ev_ref(with_ref(e, 9)), 9);
        assert!(event(1.0, EventKind::End, 9) < event(1.0, EventKind::Planar, 0));
        assert!(event(1.0, EventKind::Planar, 9) < event(1.0, EventKind::Start, 0));
    }

    #[test]
    fn radix_sort_sorts_like_a_comparison_sort() {
        let mut next = crate::build::xorshift(0x9E37_79B9_7F4A_7C15);
        let mut v = Vec::new();
        for r in 0..5000u64 {
            let x = next();
            // Few distinct positions, so kinds and references decide ties.
            v.push((x % 97) << 35 | ((x >> 20) % 3) << 30 | r);
        }
        let mut want = v.clone();
        want.sort_unstable();
        let mut b = vec![0; v.len()];
        let in_b = radix_sort_by_position_and_kind(&mut v, &mut b);
        assert_eq!(if in_b { b } else { v }, want);
    }

    #[test]
    fn parallel_radix_pass_equals_the_serial_one() {
        let mut next = crate::build::xorshift(0x2545_F491_4F6C_DD1D);
        let n = 3 * RADIX_CHUNK + 12_345;
        let v: Vec<u64> = (0..n as u64)
            .map(|r| {
                let x = next();
                // Few distinct digits in the top bits, so that stability
                // decides the order of most events.
                (x % 5000) << 35 | ((x >> 20) % 3) << 30 | r
            })
            .collect();
        for (shift, bits) in [(30u32, 11u32), (41, 11), (52, 12)] {
            let (mut want, mut got) = (vec![0; n], vec![0; n]);
            radix_pass(&v, &mut want, shift, bits);
            radix_pass_parallel(&v, &mut got, shift, bits);
            assert_eq!(got, want, "pass at bit {shift}");
        }
        let (mut a, mut b) = (v.clone(), vec![0; n]);
        let in_b = radix_sort_by_position_and_kind(&mut a, &mut b);
        let mut want = v;
        want.sort_unstable();
        assert_eq!(if in_b { b } else { a }, want);
    }

    #[test]
    fn merge_back_merges() {
        let mut seg = vec![1, 4, 6, 9, 0, 0, 0];
        merge_back(&mut seg, &[0, 5, 10]);
        assert_eq!(seg, vec![0, 1, 4, 5, 6, 9, 10]);
        let mut seg = vec![0, 0];
        merge_back(&mut seg, &[2, 3]);
        assert_eq!(seg, vec![2, 3]);
    }

    #[test]
    fn bucket_merge_equals_merge_back() {
        let mut next = crate::build::xorshift(0x9E37_79B9_7F4A_7C15);
        for case in 0..500 {
            let (h, m) = ((next() % 200) as usize, (next() % 12) as usize);
            let range = 1 + next() % if case % 2 == 0 { 8 } else { 1000 };
            let mut old: Vec<u64> = (0..h).map(|_| next() % range).collect();
            let mut new: Vec<u64> = (0..m).map(|_| next() % range).collect();
            old.sort_unstable();
            new.sort_unstable();
            let mut a = old.clone();
            a.resize(h + m, 0);
            let mut b = a.clone();
            merge_back(&mut a, &new);
            bucket_merge(&mut b, &new);
            let mut want = [old, new].concat();
            want.sort_unstable();
            assert_eq!(a, want);
            assert_eq!(b, want);
        }
    }
}
