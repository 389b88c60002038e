//! The 8-byte node word, format version 2: encoding and decoding (Wald
//! 2004, extended by Choi, Chang & Ihm 2013 with type II inner nodes and
//! T-reference nodes).
//!
//! ```text
//! bit   63 ........ 32 31 ............ 16 15 ...... 5 4 3 2 1 0
//! I     split pos (f32) right child's slot R (bits 3-31)    0 a a   type I inner, axis aa
//! II    split pos (f32) right child's slot R (bits 3-31)    1 a a   type II inner, axis aa
//! T     triangle index  0 .................................  1 1 1   T-reference
//! L32   first in idx32  count (27 bits, 5-31)        0 0  0 1 1   leaf, 4-byte indices
//! L16   first in idx16  upper 16 bits | count (11, 5-15) 0 1  0 1 1 leaf, 2-byte indices
//! L1    triangle index  0 ........................... 1 0  0 1 1   leaf of one triangle
//! ```
//!
//! The nodes lie in pre-order: an inner node at slot `i` is followed by its
//! T-reference (type II), then by its left subtree; its right child lies at
//! slot `R`. **An empty child has no word**: `R = 0` says the right child is
//! empty (slot 0 is the root, never a child), and `R` equal to the first
//! child slot (`i + 1`, or `i + 2` for type II) says the left child is
//! empty, the right one taking its place. An inner node whose two children
//! are both empty (a hoist can leave one) writes its left child as an empty
//! leaf word (`L32` with count 0) and `R = 0`; no other empty leaf has a
//! word, except an empty root. A leaf of exactly one triangle holds its
//! index in its own word (`L1`), with no index entry. The empty leaves
//! without a word are 7–17 % of a tree's nodes, the one-triangle leaves
//! about a third of its leaves.
//!
//! Worked example: `0x4040_0000_0000_0011` is a type I inner node (A = 001,
//! split on y) at y = 3.0 (`0x40400000`) whose right child is at slot 2
//! (byte offset 0x10); if the node is the root, its left child is slot 1.
//! `0x0000_0007_0001_0C2B` is a leaf (A = 011) in 2-byte mode (E = 01)
//! holding 0x61 = 97 indices whose upper 16 bits are 0x0001, starting at
//! idx16 position 7. `0x0000_0005_0000_0013` is the leaf of triangle 5 alone.

/// Node type bits `A` (bits 0–2).
pub const A_MASK: u64 = 0b111;
/// `A` of a leaf word.
pub const A_LEAF: u64 = 0b011;
/// `A` of a T-reference word.
pub const A_TREF: u64 = 0b111;
/// Set in `A` for a type II inner node.
pub const A_TYPE2: u64 = 0b100;

/// Leaf mode `E` (bits 3–4).
pub const E_IDX32: u64 = 0b00;
/// `E` of a leaf in 2-byte mode.
pub const E_IDX16: u64 = 0b01;
/// `E` of a leaf of one triangle, held in the word.
pub const E_ONE: u64 = 0b10;

/// The largest count a 4-byte-mode leaf can hold (27 bits).
pub const MAX_LEAF32: u32 = (1 << 27) - 1;
/// A 2-byte-mode leaf holds fewer than this many indices (11 bits).
pub const LEAF16_LIMIT: u32 = 1 << 11;
/// The 29-bit slot field addresses 2^29 nodes (512 M, 4 GiB of words).
pub const MAX_NODES: u64 = 1 << 29;

/// A decoded node word. Offsets are node indices (byte offset / 8).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NodeWord {
    /// Type I (`t_ref == false`) or type II (the T-reference in the next
    /// slot); `right` is the slot field `R` ([`children`] reads it).
    Inner {
        /// Split axis (0, 1, 2 for x, y, z).
        axis: u8,
        /// Type II: a T-reference word follows the node.
        t_ref: bool,
        /// The slot field `R`.
        right: u32,
        /// Split position.
        pos: f32,
    },
    /// A leaf whose indices are `idx32[start..start + count]`.
    Leaf32 {
        /// Triangles in the leaf.
        count: u32,
        /// First entry in the index section.
        start: u32,
    },
    /// A leaf whose indices are `upper << 16 | idx16[i]`, `i` in `start..start + count`.
    Leaf16 {
        /// Triangles in the leaf.
        count: u32,
        /// The upper 16 bits of every index.
        upper: u16,
        /// First entry in the index section.
        start: u32,
    },
    /// A leaf of one triangle, held in the word.
    Leaf1 {
        /// A (file) triangle id.
        tri: u32,
    },
    /// The hoisted triangle of the type II node before it.
    TRef {
        /// A (file) triangle id.
        tri: u32,
    },
}

/// The slots of the children of the inner node at slot `i` with slot field
/// `right`: `(left, right)`, `None` for an empty child (no word). Only
/// meaningful for a field that passed validation (`0`, the first child
/// slot, or a slot after it).
#[inline(always)]
pub fn children(i: u32, t_ref: bool, right: u32) -> (Option<u32>, Option<u32>) {
    let first = i + 1 + u32::from(t_ref);
    if right == 0 {
        (Some(first), None)
    } else if right == first {
        (None, Some(first))
    } else {
        (Some(first), Some(right))
    }
}

/// Encodes an inner node; `right` is its slot field `R` (see the module
/// docs).
pub fn encode_inner(axis: u8, t_ref: bool, right: u32, pos: f32) -> u64 {
    debug_assert!(axis < 3 && u64::from(right) < MAX_NODES);
    let a = u64::from(axis) | if t_ref { A_TYPE2 } else { 0 };
    (u64::from(pos.to_bits()) << 32) | (u64::from(right) << 3) | a
}

/// Encodes the leaf of the one (file) triangle `tri`.
pub fn encode_leaf1(tri: u32) -> u64 {
    (u64::from(tri) << 32) | (E_ONE << 3) | A_LEAF
}

/// Encodes a leaf of 4-byte indices `idx32[start..start + count]`.
pub fn encode_leaf32(count: u32, start: u32) -> u64 {
    debug_assert!(count <= MAX_LEAF32);
    (u64::from(start) << 32) | (u64::from(count) << 5) | (E_IDX32 << 3) | A_LEAF
}

/// Whether a leaf of `len` (file) triangle ids `ids` is stored in 2-byte
/// mode: fewer than [`LEAF16_LIMIT`] of them, all sharing their upper 16
/// bits.
pub fn fits_leaf16(len: usize, ids: impl IntoIterator<Item = u32>) -> bool {
    if len >= LEAF16_LIMIT as usize {
        return false;
    }
    let mut ids = ids.into_iter();
    let upper = ids.next().map_or(0, |t| t >> 16);
    ids.all(|t| t >> 16 == upper)
}

/// Bytes of the index list of a leaf of `len` (file) triangle ids `ids`,
/// as stored: none for one triangle (its word holds it), 2 per index in
/// 2-byte mode ([`fits_leaf16`]), else 4.
pub fn leaf_index_bytes(len: usize, ids: impl IntoIterator<Item = u32>) -> u64 {
    match len {
        1 => 0,
        _ => len as u64 * if fits_leaf16(len, ids) { 2 } else { 4 },
    }
}

/// Bytes of a leaf of `len` (file) triangle ids `ids`, word and index list:
/// none for an empty leaf (its parent's word says it is empty; the rare
/// left child of a node with two empty children is the exception), else 8
/// plus [`leaf_index_bytes`].
pub fn leaf_bytes(len: usize, ids: impl IntoIterator<Item = u32>) -> u64 {
    match len {
        0 => 0,
        _ => 8 + leaf_index_bytes(len, ids),
    }
}

/// Encodes a leaf of 2-byte indices (`count` < [`LEAF16_LIMIT`]).
pub fn encode_leaf16(count: u32, upper: u16, start: u32) -> u64 {
    debug_assert!(count < LEAF16_LIMIT);
    (u64::from(start) << 32)
        | (u64::from(upper) << 16)
        | (u64::from(count) << 5)
        | (E_IDX16 << 3)
        | A_LEAF
}

/// Encodes the T-reference word of (file) triangle `tri`.
pub fn encode_tref(tri: u32) -> u64 {
    (u64::from(tri) << 32) | A_TREF
}

/// Decodes a word; `Err` names what is malformed (unknown mode bits, or
/// non-zero bits a T-reference does not use).
#[inline]
pub fn decode(w: u64) -> Result<NodeWord, &'static str> {
    let hi = (w >> 32) as u32;
    match w & A_MASK {
        A_LEAF => match (w >> 3) & 0b11 {
            E_IDX32 => Ok(NodeWord::Leaf32 {
                count: ((w as u32) >> 5) & MAX_LEAF32,
                start: hi,
            }),
            E_IDX16 => Ok(NodeWord::Leaf16 {
                count: ((w as u32) >> 5) & (LEAF16_LIMIT - 1),
                upper: (w >> 16) as u16,
                start: hi,
            }),
            E_ONE if w as u32 == (E_ONE << 3 | A_LEAF) as u32 => Ok(NodeWord::Leaf1 { tri: hi }),
            E_ONE => Err("one-triangle leaf with unused bits set"),
            _ => Err("unknown leaf mode"),
        },
        A_TREF => {
            if w as u32 != A_TREF as u32 {
                Err("T-reference with unused bits set")
            } else {
                Ok(NodeWord::TRef { tri: hi })
            }
        }
        a => Ok(NodeWord::Inner {
            axis: (a & 0b11) as u8,
            t_ref: a & A_TYPE2 != 0,
            right: (w as u32) >> 3,
            pos: f32::from_bits(hi),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn worked_examples() {
        assert_eq!(encode_inner(1, false, 2, 3.0), 0x4040_0000_0000_0011);
        assert_eq!(encode_leaf16(97, 1, 7), 0x0000_0007_0001_0C2B);
        assert_eq!(encode_leaf1(5), 0x0000_0005_0000_0013);
        assert_eq!(
            decode(0x0000_0005_0000_0013),
            Ok(NodeWord::Leaf1 { tri: 5 })
        );
        assert_eq!(
            decode(0x0000_0007_0001_0C2B),
            Ok(NodeWord::Leaf16 {
                count: 97,
                upper: 1,
                start: 7
            })
        );
    }

    #[test]
    fn round_trips_at_the_limits() {
        let cases = [
            NodeWord::Inner {
                axis: 2,
                t_ref: true,
                right: (MAX_NODES - 1) as u32,
                pos: -1.5,
            },
            NodeWord::Inner {
                axis: 0,
                t_ref: false,
                right: 1,
                pos: f32::MAX,
            },
            NodeWord::Leaf32 {
                count: MAX_LEAF32,
                start: u32::MAX,
            },
            NodeWord::Leaf32 { count: 0, start: 0 },
            NodeWord::Leaf16 {
                count: LEAF16_LIMIT - 1,
                upper: u16::MAX,
                start: u32::MAX,
            },
            NodeWord::TRef { tri: u32::MAX },
            NodeWord::Leaf1 { tri: u32::MAX },
        ];
        for c in cases {
            let w = match c {
                NodeWord::Inner {
                    axis,
                    t_ref,
                    right,
                    pos,
                } => encode_inner(axis, t_ref, right, pos),
                NodeWord::Leaf32 { count, start } => encode_leaf32(count, start),
                NodeWord::Leaf16 {
                    count,
                    upper,
                    start,
                } => encode_leaf16(count, upper, start),
                NodeWord::TRef { tri } => encode_tref(tri),
                NodeWord::Leaf1 { tri } => encode_leaf1(tri),
            };
            assert_eq!(decode(w), Ok(c));
        }
        assert_eq!(decode(0b1_0011), Ok(NodeWord::Leaf1 { tri: 0 }));
        assert!(decode(0b1_1011).is_err());
        assert!(decode(0b100_0111).is_err());
        assert!(decode(0b11_1011).is_err());
        assert!(decode(0b1_0001_0011).is_err());
    }

    #[test]
    fn children_read_the_slot_field() {
        // Both children, right empty, left empty; type I and II.
        assert_eq!(children(4, false, 9), (Some(5), Some(9)));
        assert_eq!(children(4, false, 0), (Some(5), None));
        assert_eq!(children(4, false, 5), (None, Some(5)));
        assert_eq!(children(4, true, 9), (Some(6), Some(9)));
        assert_eq!(children(4, true, 6), (None, Some(6)));
        assert_eq!(children(0, true, 0), (Some(2), None));
    }
}
