//! The level builder's event encoding: one `u64` per event, whose integer
//! order is the sweep order of [`crate::build::sweep::Event::cmp_order`].
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

use crate::build::sweep::EventKind;
use crate::geom::Aabb;
use glam::Vec3;

/// References per level must fit the 30 reference bits.
pub const MAX_REFS: usize = 1 << 30;
pub const REF_MASK: u64 = (1 << 30) - 1;

/// A reference's box: `min` x, y, z then `max` x, y, z (a `Pod` column
/// element; `Aabb` itself is not `Pod`).
pub type Box6 = [f32; 6];

#[inline]
pub fn to_box(b: &Aabb) -> Box6 {
    [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z]
}

#[inline]
pub fn to_aabb(b: &Box6) -> Aabb {
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
pub fn n_events(b: &Box6, axis: usize) -> usize {
    if b[axis] == b[axis + 3] { 1 } else { 2 }
}

/// Appends the events of reference `r` with box `b` on `axis`.
#[inline]
pub fn push_events(b: &Box6, axis: usize, r: u32, out: &mut Vec<u64>) {
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
pub fn events_of(b: &Box6, axis: usize, r: u32) -> ([u64; 2], usize) {
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
}
