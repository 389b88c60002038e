//! The placement code of a reference of a split node, which the classify
//! pass writes ([`super::classify`]) and the event partition and the
//! depth-first finisher read: three bits, read only through
//! [`is_clipped`], [`side_of`], [`goes_to`] and [`SLOT`], and the
//! renumbering's [`DROPPED`] mark.

/// Where a reference of a split node goes: bit 0 left, bit 1 right, bit 2
/// clipped (a straddler; its boxes are in the classify pass's list).
pub(super) const TO_LEFT: u8 = 1;
pub(super) const TO_RIGHT: u8 = 2;
pub(super) const CLIPPED: u8 = 4;

/// Whether a placement code is a straddler's (clipped; its boxes are in
/// the classify pass's list).
#[inline]
pub(super) fn is_clipped(code: u8) -> bool {
    code & CLIPPED != 0
}

/// The side (0 left, 1 right) of an unclipped reference's placement code.
#[inline]
pub(super) fn side_of(code: u8) -> usize {
    usize::from(code == TO_RIGHT)
}

/// Whether the reference of placement code `code` goes to `side` (0 left,
/// 1 right), clipped or not.
#[inline]
pub(super) fn goes_to(code: u8, side: usize) -> bool {
    if !is_clipped(code) {
        side_of(code) == side
    } else {
        code & (1 << side) != 0
    }
}

/// `new_idx` of a clipped straddler, whose events are not inherited. A
/// one-sided reference's entry is its index in the next level (below
/// [`MAX_REFS`](super::events::MAX_REFS), so bit 31 is free) with bit 31
/// set when it goes right.
pub(super) const DROPPED: u32 = u32::MAX;

/// The partition slot of a placement code: 0 left, 1 right, 2 dropped (a
/// clipped straddler, whose events are made anew).
pub(super) const SLOT: [usize; 8] = {
    let mut t = [2; 8];
    t[TO_LEFT as usize] = 0;
    t[TO_RIGHT as usize] = 1;
    t
};
