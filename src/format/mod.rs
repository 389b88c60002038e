//! The `.kd` file: a kd-tree and its geometry in one little-endian file that
//! opens with `mmap` and is traversed in place (no parsing, no
//! deserialisation).
//!
//! Consumes a [`TreeIr`](crate::tree::TreeIr) and its
//! [`TriangleColumns`](crate::scene::TriangleColumns) ([`write_to_vec`],
//! [`write_file`]); produces a [`KdFile`] over any byte source
//! ([`KdFile::from_bytes`], [`KdFile::open`]). [`KdFile::from_bytes`]
//! checks the header and the section table in O(1), so that a file of any
//! size opens without reading its sections; every node, leaf range and
//! index is checked where a reader reads it, and every walk is bounded by
//! the node count, so that no byte string makes opening or traversal
//! panic, read out of bounds or loop (a corrupt section gives wrong hits at
//! worst). [`KdFile::validate`] checks every node, index and vertex (what
//! makes hits brute force's), [`KdFile::verify`] every section's checksum;
//! [`Check`] picks what [`KdFile::open`] runs (`slimkd verify`: all).
//!
//! # Layout, version 2
//!
//! The header (384 bytes) comes first; then the sections, in the order of
//! the section table, each starting at the first multiple of 64 bytes at or
//! after the end of the previous one (the header, for the first); the file
//! ends at the first multiple of 64 at or after the end of the last section.
//! The layout is thus canonical, and the reader checks it.
//!
//! Every byte is checked: the header by its CRC (bytes 0..336), each section
//! by its CRC in the section table ([`KdFile::verify`]), the counts of empty
//! leaves without a word and of one-triangle leaves (bytes 340..356, after
//! the CRC) against the nodes, and the reserved header bytes 356..384 and the
//! padding after each section must be zero ([`KdFile::from_bytes`]). So any
//! single corrupted bit makes `from_bytes`, `validate` or `verify` fail.
//!
//! | offset | size | field |
//! |---:|---:|---|
//! | 0 | 8 | magic `89 53 4C 4B 44 0D 0A 1A` (`\x89SLKD\r\n\x1a`) |
//! | 8 | 4 | format version (2) |
//! | 12 | 4 | endianness check `0x0A0B0C0D` |
//! | 16 | 4 | header size (384) |
//! | 20 | 4 | flags: bit 0 = triangles reordered (the `tri_map` section is present) |
//! | 24 | 8 | `K_T` (f64) |
//! | 32 | 8 | `K_I` (f64) |
//! | 40 | 8 | λ for empty space (f64) |
//! | 48 | 4 | depth limit used by the build |
//! | 52 | 4 | preset: 0 std, 1 fast, 2 small, 3 custom |
//! | 56 | 4 | τ_occu (f32) |
//! | 60 | 4 | τ_freq (f32) |
//! | 64 | 4 | `max_t2rn` |
//! | 68 | 4 | maximum node depth |
//! | 72 | 8 | node words (inner + t-inner + leaves + T-references − empty leaves without a word) |
//! | 80 | 8 | type I inner nodes |
//! | 88 | 8 | type II inner nodes (t-inner) |
//! | 96 | 8 | leaves (with the empty leaves that have no word) |
//! | 104 | 8 | idx32 entries |
//! | 112 | 8 | idx16 entries |
//! | 120 | 8 | triangles |
//! | 128 | 8 | vertices |
//! | 136 | 24 | scene bounds: min xyz, max xyz (f32) |
//! | 160 | 8 | geometry hash ([`SceneTag`]; 0: not recorded) |
//! | 168 | 24 | scene name ([`SceneTag`]): UTF-8, padded with zero bytes (all zero: not recorded) |
//! | 192 | 6 × 24 | section table: per section, byte offset (u64), byte length (u64), CRC-32 (u32), reserved (u32) |
//! | 336 | 4 | CRC-32 of bytes 0..336 |
//! | 340 | 8 | empty leaves without a word |
//! | 348 | 8 | one-triangle leaves (no index entry) |
//! | 356 | 8 | the SAH's split price `μ` (f64; 0: none, as in files written before it) |
//! | 364 | 16 | reserved (zero) |
//! | 380 | 4 | CRC-32 of bytes 356..380 (0 with all of 356..380 zero in files written before the split price) |
//!
//! Sections, in order: `nodes` (u64 node words, see [`node`]), `idx32`
//! (u32), `idx16` (u16), `vertices` (3 × f32), `triangles` (3 × u32 vertex
//! indices), `tri_map` (u32: file triangle id → input triangle id; empty
//! unless reordered). The root is node 0 and the nodes lie in pre-order
//! ([`node`]: the left child next, the right child at its slot, an empty
//! child without a word). [`KdFile::validate`] checks that order, which
//! makes every node the child of exactly one parent and every child lie
//! after its parent, so there are no cycles and no shared subtrees; a file
//! opened without it is read as a tree all the same (children only after
//! their node, at most `2 · words + 1` steps a walk).
//!
//! **Limits:** 2^29 node words (4 GiB; the 29-bit slot field), 2^32
//! triangles, vertices and entries of each index array, 2^27 − 1
//! triangles in a leaf, depth [`MAX_DEPTH`](crate::tree::MAX_DEPTH). The
//! writer refuses larger trees rather than wrap.
//!
//! **Version 1** (every empty leaf a word, children in blocks of two) is
//! not read: opening one is an error that says to rebuild the file.
//!
//! Hit ids reported by traversal are always input ids (through `tri_map`).
//!
//! Bytes 160..192 were reserved (zero) before they held the scene tag, so a
//! file written without one reads as having no tag: its name falls back to
//! the file's stem where a name is needed (views).

mod header;
pub mod node;
mod read;
mod stream;
mod validate;
mod write;

pub use header::{FileConfig, HeaderError, Preset, SCENE_NAME_LEN, SceneTag, TreeFigures};
pub use read::{AlignedBytes, Check, KdFile, LeafIndices, Mapped, aligned_copy};
pub use stream::{StreamWriter, write_file_streamed};
pub use write::{WriteOptions, write_file, write_to_vec};

use std::path::PathBuf;

/// Refuses a triangle with a vertex index of `n_vertices` or more: the
/// writer's check of its scene and the reader's of its file.
fn check_vertex_indices(triangles: &[[u32; 3]], n_vertices: u64) -> Result<(), FormatError> {
    match triangles
        .iter()
        .position(|t| t.iter().any(|&v| u64::from(v) >= n_vertices))
    {
        Some(p) => Err(FormatError::Index {
            section: "triangles",
            position: p as u64,
            message: format!("vertex index out of {n_vertices}"),
        }),
        None => Ok(()),
    }
}

/// The file's first 8 bytes (PNG-style: a high byte, the name, CR LF, ^Z).
pub const MAGIC: [u8; 8] = [0x89, b'S', b'L', b'K', b'D', b'\r', b'\n', 0x1a];
// The scene layer tells a tree file by these bytes without naming this
// module (it lies below it).
const _: () = {
    let mut i = 0;
    while i < MAGIC.len() {
        assert!(MAGIC[i] == crate::scene::KD_MAGIC[i]);
        i += 1;
    }
};
/// The format version this build writes and reads.
pub const VERSION: u32 = 2;
/// Written in the machine's byte order; reads back equal only on a little-endian reader.
pub const ENDIAN_CHECK: u32 = 0x0A0B_0C0D;
/// Bytes of the header (a multiple of [`SECTION_ALIGN`]).
pub const HEADER_SIZE: usize = 384;
/// Every section starts at a multiple of this many bytes (a cache line).
pub const SECTION_ALIGN: usize = 64;
/// Header flag: triangles renumbered, the `tri_map` section present.
pub const FLAG_REORDERED: u32 = 1;

/// The sections, in file order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Section {
    /// u64 node words ([`node`]).
    Nodes = 0,
    /// u32 leaf indices.
    Idx32 = 1,
    /// u16 leaf indices (the low halves; the leaf word holds the upper).
    Idx16 = 2,
    /// Vertex positions, 3 × f32.
    Vertices = 3,
    /// Vertex-index triples, 3 × u32, in the file's triangle numbering.
    Triangles = 4,
    /// u32: file triangle id → input triangle id (empty unless reordered).
    TriMap = 5,
}

impl Section {
    /// Every section, in file order.
    pub const ALL: [Section; 6] = [
        Section::Nodes,
        Section::Idx32,
        Section::Idx16,
        Section::Vertices,
        Section::Triangles,
        Section::TriMap,
    ];

    /// The section's name in messages.
    pub fn name(self) -> &'static str {
        [
            "nodes",
            "idx32",
            "idx16",
            "vertices",
            "triangles",
            "tri_map",
        ][self as usize]
    }

    /// Bytes per element.
    pub fn elem_size(self) -> u64 {
        [8, 4, 2, 12, 12, 4][self as usize]
    }
}

/// Why a file could not be written or opened. Every variant says what is
/// wrong; `Io` names the file.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// Reading or writing the file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The error of the operating system.
        source: std::io::Error,
    },
    /// Shorter than the header or than a section it announces.
    #[error("truncated file: needs {needed} bytes, has {got}")]
    Truncated {
        /// Bytes the file needs.
        needed: u64,
        /// What the file has.
        got: u64,
    },
    /// Not a `.kd` file (the first 8 bytes are not [`MAGIC`]).
    #[error("not a slimkd .kd file (bad magic)")]
    BadMagic,
    /// A format version this build does not read.
    #[error("{}", version_message(*expected, *got))]
    Version {
        /// The version this build reads.
        expected: u32,
        /// The file's version.
        got: u32,
    },
    /// Written on a machine of the other byte order.
    #[error("the file's byte order does not match this machine")]
    Endianness,
    /// The byte source is not 8-byte aligned (mmap always is).
    #[error("the byte buffer is not 8-byte aligned")]
    Misaligned,
    /// The header's CRC-32 does not match its bytes.
    #[error("header checksum mismatch (stored {expected:#010x}, computed {got:#010x})")]
    HeaderChecksum {
        /// The CRC-32 stored in the file.
        expected: u32,
        /// The CRC-32 computed.
        got: u32,
    },
    /// A header field out of range.
    #[error("bad header: {0}")]
    Header(HeaderError),
    /// A section's placement or size.
    #[error("section {section}: {problem}")]
    Section {
        /// The section.
        section: &'static str,
        /// What is wrong.
        problem: SectionError,
    },
    /// A node word that is malformed or points outside the file.
    #[error("node {index}: {fault}")]
    Node {
        /// The node's slot.
        index: u64,
        /// What is wrong.
        fault: NodeFault,
    },
    /// A section's CRC-32 does not match the section table's.
    #[error("section {section}: checksum mismatch (stored {expected:#010x}, computed {got:#010x})")]
    ChecksumMismatch {
        /// The section.
        section: &'static str,
        /// The CRC-32 stored in the file.
        expected: u32,
        /// The CRC-32 computed.
        got: u32,
    },
    /// An index or vertex reference out of range.
    #[error("section {section}, entry {position}: {message}")]
    Index {
        /// The section.
        section: &'static str,
        /// The entry's position in the section.
        position: u64,
        /// What is wrong.
        message: String,
    },
    /// The tree does not fit the format (e.g. more than 2^29 nodes).
    #[error("tree too large for the format: {0}")]
    TooLarge(Limit),
}

/// What is wrong with a section's placement, size or padding
/// ([`FormatError::Section`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SectionError {
    /// A byte length that is not the header's count times the element size.
    #[error("{0} bytes do not match the header's count")]
    Length(u64),
    /// Not at the first multiple of 64 after the previous section.
    #[error(
        "offset {offset} misplaced (expected {expected}: 64-aligned, right after the previous section)"
    )]
    Misplaced {
        /// The offset in the section table.
        offset: u64,
        /// Where the section must start.
        expected: u64,
    },
    /// Offset plus length past 2^64.
    #[error("offset overflows")]
    Overflow,
    /// A non-zero byte between the section's end and the next section
    /// (or the end of the file).
    #[error("non-zero padding after the section")]
    Padding,
}

/// What is wrong with a node ([`FormatError::Node`]): of a file's word
/// (the validator, the streaming writer) or of a tree being written.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum NodeFault {
    /// A word no node type decodes to ([`node::decode`]'s reason).
    #[error("{0}")]
    Word(&'static str),
    /// A split axis other than 0, 1, 2.
    #[error("axis {0}")]
    Axis(u8),
    /// A NaN or infinite split position.
    #[error("split position is not finite")]
    SplitNotFinite,
    /// A split outside the cell the splits above make.
    #[error("split {pos:?} on axis {axis} outside the node's cell [{min:?}, {max:?}]")]
    SplitOutsideCell {
        /// The split position.
        pos: f32,
        /// Its axis.
        axis: usize,
        /// The cell's extent on that axis.
        min: f32,
        /// The cell's extent on that axis.
        max: f32,
    },
    /// Deeper than the header's maximum depth.
    #[error("deeper than the header's maximum depth")]
    TooDeep,
    /// A right child slot at or before its parent.
    #[error("right child slot {0} is not after the node")]
    RightChildNotAfter(u64),
    /// A T-reference to a triangle the file does not hold.
    #[error("T-reference to triangle {tri} of {n_tris}")]
    TRefOutOfRange {
        /// The triangle.
        tri: u64,
        /// The file's triangles.
        n_tris: u64,
    },
    /// A type II node whose next word is not a T-reference.
    #[error("type II node without its T-reference")]
    MissingTRef,
    /// A T-reference word where a child is expected.
    #[error("a T-reference where a child is expected")]
    TRefAsChild,
    /// A leaf triangle the file does not hold.
    #[error("triangle {tri} of {n_tris}")]
    TriangleOutOfRange {
        /// The triangle.
        tri: u64,
        /// The file's triangles.
        n_tris: u64,
    },
    /// A leaf's index range past its index section.
    #[error("leaf range {start}+{count} outside {array}")]
    LeafRangeOutside {
        /// The range's first entry.
        start: u64,
        /// Its entries.
        count: u64,
        /// The section (`idx32`, `idx16`).
        array: &'static str,
    },
    /// A leaf's index range overlapping another leaf's.
    #[error("leaf range overlaps another leaf's range in {0}")]
    LeafRangeOverlap(&'static str),
    /// A word for an empty leaf whose parent says it has none.
    #[error("an empty leaf with a word (its parent's slot field says it is empty)")]
    EmptyLeafWithWord,
    /// A one-triangle leaf stored with an index entry.
    #[error("a one-triangle leaf with an index entry")]
    OneTriangleLeafWithIndex,
    /// A 2-byte-mode leaf of a count that mode does not store.
    #[error("a 2-byte-mode leaf of {0} triangles")]
    Leaf16Count(u64),
    /// A node away from the slot its parent names.
    #[error(
        "not in pre-order: the next node is expected at {expected}, its parent's slot field says {slot}"
    )]
    NotPreOrder {
        /// The slot the pre-order pass reached.
        expected: u64,
        /// The slot the parent names.
        slot: u64,
    },
    /// A child slot past the node words.
    #[error("a child slot outside the {0} node words")]
    ChildSlotOutside(u64),
    /// A word no inner node reaches.
    #[error("not referenced by any inner node (words after the tree)")]
    Unreferenced,
    /// A streamed node after the tree is complete.
    #[error("a node after the whole tree")]
    AfterTree,
    /// A streamed tree that ended with children still expected.
    #[error("the tree ended before it was complete")]
    Incomplete,
    /// A tree being written: a child index past its nodes.
    #[error("a child outside the {0} nodes")]
    ChildOutside(u64),
    /// A tree being written: a node two parents name.
    #[error("reached twice (not a tree)")]
    ReachedTwice,
    /// A tree being written: a leaf's list past the listed triangles.
    #[error("leaf list {start}+{count} outside the {listed} listed triangles")]
    LeafListOutside {
        /// The list's first entry.
        start: u64,
        /// Its entries.
        count: u64,
        /// The tree's listed triangles.
        listed: u64,
    },
}

/// Which limit of the format a tree is over ([`FormatError::TooLarge`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Limit {
    /// More node words than the 29-bit slot field addresses.
    #[error("more than 2^29 node words (the 29-bit slot field)")]
    NodeWords,
    /// A node deeper than [`MAX_DEPTH`](crate::tree::MAX_DEPTH).
    #[error("a node deeper than {}", crate::tree::MAX_DEPTH)]
    Depth,
    /// A leaf of this many triangles, over [`node::MAX_LEAF32`].
    #[error("a leaf with {0} triangles (at most 2^27 - 1)")]
    Leaf(u64),
    /// More idx16 entries than 32-bit positions address.
    #[error("idx16 over 2^32 entries")]
    Idx16Entries,
    /// More idx32 entries than 32-bit positions address.
    #[error("idx32 over 2^32 entries")]
    Idx32Entries,
    /// More triangles or vertices than 32-bit ids number.
    #[error("more than 2^32 triangles or vertices")]
    TrianglesOrVertices,
}

/// The message of [`FormatError::Version`]: an older version says to
/// rebuild the file.
fn version_message(expected: u32, got: u32) -> String {
    if got < expected {
        format!(
            "format version {got}, which this build no longer reads (it reads {expected}): \
             rebuild the tree with `slimkd build`"
        )
    } else {
        format!("unsupported format version {got} (this build reads {expected})")
    }
}

/// What the writers' unit tests share: a small scene and its tree, and
/// the bytes [`write_to_vec`] makes of them, which every other way of
/// writing them must give.
#[cfg(test)]
mod testing {
    use super::{WriteOptions, write_to_vec};
    use crate::build::{self, Algorithm, BuildConfig};
    use crate::scene::TriangleColumns;
    use crate::tree::TreeIr;
    use glam::Vec3;

    /// `n` small triangles `[p, p + a·x, p + b·y]`, `p = (i % 20, i / rows,
    /// i % 7)`, and their tree (the sweep builder's).
    pub(super) fn grid_tree(
        n: usize,
        rows: usize,
        (a, b): (f32, f32),
    ) -> (TriangleColumns, TreeIr) {
        let tris: Vec<[Vec3; 3]> = (0..n)
            .map(|i| {
                let p = Vec3::new((i % 20) as f32, (i / rows) as f32, (i % 7) as f32);
                [p, p + Vec3::X * a, p + Vec3::Y * b]
            })
            .collect();
        let scene = TriangleColumns::from_triangles(&tris).unwrap();
        let tree =
            build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
        (scene, tree)
    }

    /// The options without and with `reorder`, each with the bytes
    /// [`write_to_vec`] writes under them.
    pub(super) fn whole_files(
        scene: &TriangleColumns,
        tree: &TreeIr,
    ) -> Vec<(WriteOptions, Vec<u8>)> {
        [false, true]
            .map(|reorder| {
                let options = WriteOptions {
                    reorder,
                    ..WriteOptions::default()
                };
                (options, write_to_vec(tree, scene, &options).unwrap())
            })
            .into()
    }
}
