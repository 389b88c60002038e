//! Opening a `.kd` file: [`KdFile::from_bytes`] checks what can be checked
//! in O(1) (the header, its checksum, the section table), so that a file of
//! any size opens without reading its sections; [`KdFile::validate`] checks
//! every node, index and vertex, and [`KdFile::verify`] every section's
//! checksum. The accessors hand out typed slices of the bytes without
//! copying; every read of a node, leaf range or index through them (and
//! through `trace::FileWalk`) is checked where it is made, so a file that
//! only passed `from_bytes` never makes a reader panic, read out of bounds
//! or loop (its results may be wrong).

use super::node::{self, LEAF16_LIMIT, MAX_NODES, NodeWord};
use super::write::{FileConfig, Preset, SceneTag};
use super::{
    ENDIAN_CHECK, FLAG_REORDERED, FormatError, HEADER_CRC, HEADER_SIZE, IMPLICIT_EMPTY_AT, MAGIC,
    ONE_LEAVES_AT, RESERVED_AT, SECTION_ALIGN, SECTION_ENTRY, SECTION_TABLE, SPLIT_PRICE_AT,
    Section, TAIL_CRC, VERSION, tail_crc_ok,
};
use crate::geom::Aabb;
use crate::tree::MAX_DEPTH;
use glam::Vec3;
use std::ops::Range;
use std::path::Path;

/// A `.kd` file over any byte source: a `Vec<u8>`, a `&[u8]`, or a memory
/// map ([`KdFile::open`]), its header and section table checked by
/// [`KdFile::from_bytes`].
///
/// What each check guarantees:
/// - [`KdFile::from_bytes`] (O(1), the default of [`KdFile::open`]): the
///   header is intact (its CRC), its counts add up, and every section lies
///   inside the bytes, aligned, with the size the counts give. Nothing in
///   the sections is read. Every reader stays memory-safe and ends on any
///   section contents: a child slot outside the node section or not after
///   its node, a leaf range outside its index array, reads as an empty
///   leaf; a triangle or vertex index out of range is a triangle that is
///   never hit; a traversal takes at most one step per node of a tree
///   ([`crate::trace::Walk::step_limit`]), which bounds it on a file whose
///   nodes share subtrees. Hits of such a file may be wrong.
/// - [`KdFile::validate`] (reads the node, index and geometry sections):
///   the nodes are one tree in pre-order, every split inside its cell,
///   depth at most [`MAX_DEPTH`], the leaves' ranges cover each index
///   array once, every index, vertex and the triangle map in range, the
///   header's counts those of the nodes. Hits are then brute force's, as
///   far as the leaves list the triangles their cells overlap.
/// - [`KdFile::verify`] (reads every byte): the sections' CRCs, so that a
///   flipped bit anywhere is found.
///
/// `D::as_ref` must return the same bytes every time it is called (every
/// ordinary byte container does).
pub struct KdFile<D> {
    data: D,
    /// Byte ranges of the sections; each starts 64-byte aligned and lies
    /// inside `data` with a whole number of elements, checked by
    /// `from_bytes`.
    ranges: [Range<usize>; 6],
    config: FileConfig,
    reordered: bool,
    bounds: Aabb,
    max_depth: u32,
    counts: TreeFigures,
}

/// The counts the paper reports for a tree (Choi et al. 2013, Table 3(a)).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TreeFigures {
    /// Type I inner nodes.
    pub inner: u64,
    /// Type II inner nodes (each with a T-reference word).
    pub t_inner: u64,
    /// Every leaf of the tree, with the empty ones that have no word.
    pub leaves: u64,
    /// Empty leaves without a word (all but the rare left child of a node
    /// whose two children are empty, and an empty root).
    pub implicit_empty: u64,
    /// Leaves of one triangle, held in their word (no index entry).
    pub one_leaves: u64,
    /// Entries of the idx32 section.
    pub idx32: u64,
    /// Entries of the idx16 section.
    pub idx16: u64,
    /// Triangles of the scene.
    pub triangles: u64,
    /// Vertices of the scene.
    pub vertices: u64,
    /// Node words in the file: inner + t-inner + T-references + the leaves
    /// that have a word.
    pub words: u64,
}

impl TreeFigures {
    /// Nodes as the paper counts them: inner, t-inner and leaves (empty
    /// ones too).
    pub fn nodes(&self) -> u64 {
        self.inner + self.t_inner + self.leaves
    }

    /// Triangle references of the leaves (index entries and one-triangle
    /// leaves).
    pub fn references(&self) -> u64 {
        self.idx32 + self.idx16 + self.one_leaves
    }

    /// Tree memory as stored: `8·words + 4·|idx32| + 2·|idx16|` bytes.
    pub fn tree_bytes(&self) -> u64 {
        8 * self.words + 4 * self.idx32 + 2 * self.idx16
    }

    /// Vertex positions and vertex-index triples as stored.
    pub fn geometry_bytes(&self) -> u64 {
        12 * self.vertices + 12 * self.triangles
    }
}

/// The triangle ids of one leaf, in the file's numbering.
#[derive(Clone, Copy, Debug)]
pub enum LeafIndices<'a> {
    /// 4-byte indices.
    Idx32(&'a [u32]),
    /// 2-byte indices: each is `upper | low[i]`.
    Idx16 {
        /// The upper 16 bits of every index.
        upper: u32,
        /// The low 16 bits of each index.
        low: &'a [u16],
    },
    /// A leaf of one triangle (its word holds the index).
    One(u32),
}

impl LeafIndices<'_> {
    /// The number of triangles.
    pub fn len(&self) -> usize {
        match self {
            LeafIndices::Idx32(s) => s.len(),
            LeafIndices::Idx16 { low, .. } => low.len(),
            LeafIndices::One(_) => 1,
        }
    }

    /// Whether the leaf holds none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    #[inline]
    /// Calls `f` with each (file) triangle id.
    pub fn for_each(&self, mut f: impl FnMut(u32)) {
        match *self {
            LeafIndices::Idx32(s) => s.iter().for_each(|&t| f(t)),
            LeafIndices::Idx16 { upper, low } => low.iter().for_each(|&t| f(upper | u32::from(t))),
            LeafIndices::One(t) => f(t),
        }
    }
}

/// Which positions of an index array leaves have claimed: one bit each,
/// claimed a 64-bit word at a time.
struct Coverage {
    bits: Vec<u64>,
    len: u64,
    claimed: u64,
}

impl Coverage {
    fn new(len: u64) -> Coverage {
        Coverage {
            bits: vec![0; len.div_ceil(64) as usize],
            len,
            claimed: 0,
        }
    }

    /// Claims `start..start + count` (inside the array); `false` if a
    /// position in it was claimed before.
    fn claim(&mut self, start: u64, count: u64) -> bool {
        let end = start + count;
        let mut at = start;
        while at < end {
            let word = (at / 64) as usize;
            let lo = at % 64;
            let hi = (end - word as u64 * 64).min(64);
            let mask = (u64::MAX >> (64 - (hi - lo))) << lo;
            if self.bits[word] & mask != 0 {
                return false;
            }
            self.bits[word] |= mask;
            at = word as u64 * 64 + hi;
        }
        self.claimed += count;
        true
    }

    fn is_full(&self) -> bool {
        self.claimed == self.len
    }
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

impl<D: AsRef<[u8]>> KdFile<D> {
    /// Checks the header and section table of `data` and wraps it, in
    /// O(1): the magic, version, byte order, header checksum, every count
    /// (and that they add up) and section offset, the canonical placement
    /// of the sections and the file length, and that every byte outside
    /// the header and the sections (reserved header bytes, the at most 63
    /// bytes of padding after each section) is zero. The sections are not
    /// read: [`KdFile::validate`] checks their contents, [`KdFile::verify`]
    /// their checksums. Never panics.
    pub fn from_bytes(data: D) -> Result<KdFile<D>, FormatError> {
        let b = data.as_ref();
        let got = b.len() as u64;
        // The magic first, on as much of it as there is: a file of another
        // kind is named as such, not as a truncated `.kd` file.
        let have = b.len().min(MAGIC.len());
        if b[..have] != MAGIC[..have] {
            return Err(FormatError::BadMagic);
        }
        if b.len() < HEADER_SIZE {
            return Err(FormatError::Truncated {
                needed: HEADER_SIZE as u64,
                got,
            });
        }
        if b[0..8] != MAGIC {
            return Err(FormatError::BadMagic);
        }
        let version = u32_at(b, 8);
        if version != VERSION {
            return Err(FormatError::Version {
                expected: VERSION,
                got: version,
            });
        }
        if u32_at(b, 12) != ENDIAN_CHECK {
            return Err(FormatError::Endianness);
        }
        let stored = u32_at(b, HEADER_CRC);
        let computed = crc32fast::hash(&b[..HEADER_CRC]);
        if stored != computed {
            return Err(FormatError::HeaderChecksum {
                expected: stored,
                got: computed,
            });
        }
        if u32_at(b, 16) as usize != HEADER_SIZE {
            return Err(FormatError::Header(format!(
                "header size {}",
                u32_at(b, 16)
            )));
        }
        if b.as_ptr().align_offset(8) != 0 {
            return Err(FormatError::Misaligned);
        }
        let flags = u32_at(b, 20);
        if flags & !FLAG_REORDERED != 0 {
            return Err(FormatError::Header(format!("unknown flags {flags:#x}")));
        }
        let reordered = flags & FLAG_REORDERED != 0;
        let preset = Preset::from_u32(u32_at(b, 52))
            .ok_or_else(|| FormatError::Header(format!("unknown preset {}", u32_at(b, 52))))?;
        let config = FileConfig {
            k_t: f64::from_bits(u64_at(b, 24)),
            k_i: f64::from_bits(u64_at(b, 32)),
            lambda_empty: f64::from_bits(u64_at(b, 40)),
            depth_limit: u32_at(b, 48),
            split_price: f64::from_bits(u64_at(b, SPLIT_PRICE_AT)),
            preset,
            tau_occu: f32::from_bits(u32_at(b, 56)),
            tau_freq: f32::from_bits(u32_at(b, 60)),
            max_t2rn: u32_at(b, 64),
            scene: SceneTag::from_header(b)?,
        };
        let max_depth = u32_at(b, 68);
        let counts = TreeFigures {
            words: u64_at(b, 72),
            inner: u64_at(b, 80),
            t_inner: u64_at(b, 88),
            leaves: u64_at(b, 96),
            implicit_empty: u64_at(b, IMPLICIT_EMPTY_AT),
            one_leaves: u64_at(b, ONE_LEAVES_AT),
            idx32: u64_at(b, 104),
            idx16: u64_at(b, 112),
            triangles: u64_at(b, 120),
            vertices: u64_at(b, 128),
        };
        let f = |k: usize| f32::from_bits(u32_at(b, 136 + 4 * k));
        let bounds = Aabb::new(Vec3::new(f(0), f(1), f(2)), Vec3::new(f(3), f(4), f(5)));
        if !(bounds.min.is_finite() && bounds.max.is_finite() && bounds.min.cmple(bounds.max).all())
        {
            return Err(FormatError::Header(
                "scene bounds are not a finite box".into(),
            ));
        }
        if counts.words == 0 || counts.words > MAX_NODES {
            return Err(FormatError::Header(format!("{} node words", counts.words)));
        }
        if counts.triangles > u64::from(u32::MAX) || counts.vertices > u64::from(u32::MAX) {
            return Err(FormatError::Header(
                "more than 2^32 triangles or vertices".into(),
            ));
        }
        // The node counts must add up: a binary tree has one more leaf than
        // inner nodes, each type II node adds one T-reference word, and
        // the empty leaves without a word take none. At most one leaf per
        // inner node is empty and wordless (both empty: the left has one).
        let inner_all = counts.inner.checked_add(counts.t_inner);
        if inner_all.and_then(|n| n.checked_add(1)) != Some(counts.leaves)
            || counts.implicit_empty > counts.leaves - 1
            || counts.one_leaves > counts.leaves - counts.implicit_empty
            || inner_all
                .and_then(|n| n.checked_add(counts.leaves - counts.implicit_empty))
                .and_then(|n| n.checked_add(counts.t_inner))
                != Some(counts.words)
        {
            return Err(FormatError::Header("node counts do not add up".into()));
        }
        if max_depth > MAX_DEPTH {
            return Err(FormatError::Header(format!(
                "depth {max_depth} over {MAX_DEPTH}"
            )));
        }

        // Section table.
        let expected_len = |s: Section| {
            match s {
                Section::Nodes => Some(counts.words),
                Section::Idx32 => Some(counts.idx32),
                Section::Idx16 => Some(counts.idx16),
                Section::Vertices => Some(counts.vertices),
                Section::Triangles => Some(counts.triangles),
                Section::TriMap => Some(if reordered { counts.triangles } else { 0 }),
            }
            .and_then(|n| n.checked_mul(s.elem_size()))
        };
        let mut ranges: [Range<usize>; 6] = Default::default();
        let mut end_prev = HEADER_SIZE as u64;
        for s in Section::ALL {
            let e = SECTION_TABLE + s as usize * SECTION_ENTRY;
            let (ofs, len) = (u64_at(b, e), u64_at(b, e + 8));
            let bad = |message: String| FormatError::Section {
                section: s.name(),
                message,
            };
            if Some(len) != expected_len(s) {
                return Err(bad(format!("{len} bytes do not match the header's count")));
            }
            // The layout is canonical: each section starts at the first
            // multiple of 64 at or after the end of the previous one.
            let want = end_prev.next_multiple_of(SECTION_ALIGN as u64);
            if ofs != want {
                return Err(bad(format!(
                    "offset {ofs} misplaced (expected {want}: 64-aligned, right after the previous section)"
                )));
            }
            let end = ofs
                .checked_add(len)
                .ok_or_else(|| bad("offset overflows".into()))?;
            if end > got {
                return Err(FormatError::Truncated { needed: end, got });
            }
            ranges[s as usize] = ofs as usize..end as usize;
            end_prev = end;
        }
        // The file ends with the padding of the last section.
        let file_end = end_prev.next_multiple_of(SECTION_ALIGN as u64);
        if got < file_end {
            return Err(FormatError::Truncated {
                needed: file_end,
                got,
            });
        }
        if got > file_end {
            return Err(FormatError::Header(format!(
                "{} bytes after the end of the file at byte {file_end}",
                got - file_end
            )));
        }
        // Every byte outside the checksummed header and sections is zero, so
        // that no byte of a file goes unchecked; so are the reserved fields
        // inside the header, so that a later version can give them a meaning.
        // (Header bytes 160..192 are the scene tag, read by `SceneTag`.)
        let reserved = Section::ALL
            .map(|s| {
                let e = SECTION_TABLE + s as usize * SECTION_ENTRY + 20;
                (e..e + 4, "the section table's reserved word, bytes")
            })
            .into_iter()
            .chain([(RESERVED_AT..TAIL_CRC, "header bytes")]);
        for (range, what) in reserved {
            if b[range.clone()].iter().any(|&x| x != 0) {
                return Err(FormatError::Header(format!(
                    "reserved {what} {}..{} are not zero",
                    range.start, range.end
                )));
            }
        }
        if !tail_crc_ok(b) {
            return Err(FormatError::Header(format!(
                "header bytes {SPLIT_PRICE_AT}..{TAIL_CRC} do not match their CRC-32 at byte {TAIL_CRC}"
            )));
        }
        let mu = config.split_price;
        if !(mu.is_finite() && mu >= 0.0) {
            return Err(FormatError::Header(format!(
                "split price {mu} is not a finite number ≥ 0"
            )));
        }
        for s in Section::ALL {
            let pad_end = match Section::ALL.get(s as usize + 1) {
                Some(&next) => ranges[next as usize].start,
                None => file_end as usize,
            };
            if b[ranges[s as usize].end..pad_end].iter().any(|&x| x != 0) {
                return Err(FormatError::Section {
                    section: s.name(),
                    message: "non-zero padding after the section".into(),
                });
            }
        }
        Ok(KdFile {
            data,
            ranges,
            config,
            reordered,
            bounds,
            max_depth,
            counts,
        })
    }

    /// [`KdFile::from_bytes`] and then [`KdFile::validate`]: a file whose
    /// every node, index and vertex is checked (not its checksums).
    pub fn from_bytes_checked(data: D) -> Result<KdFile<D>, FormatError> {
        let file = KdFile::from_bytes(data)?;
        file.validate()?;
        Ok(file)
    }

    /// Checks the contents of the sections, in one pass over the nodes
    /// and one over the geometry (reads all but the padding): every node
    /// word (known type and mode bits, the nodes one tree in pre-order with
    /// every child where its parent's slot field says, splits inside their
    /// cells, depth at most the header's maximum and [`MAX_DEPTH`]), every
    /// leaf range and index (the ranges covering each index array once),
    /// the header's counts against the nodes, and the geometry
    /// ([`KdFile::validate_geometry`]). Never panics.
    pub fn validate(&self) -> Result<(), FormatError> {
        let words = self.nodes();
        let n = words.len() as u64;
        let n_tris = self.counts.triangles;
        let node_err = |index: u64, message: String| FormatError::Node { index, message };
        let (mut inner, mut t_inner, mut leaves, mut implicit, mut ones) =
            (0u64, 0u64, 0u64, 0u64, 0u64);
        // The leaves' index ranges cover each index array exactly once, as
        // the writer lays them out: so the work of any traversal (and of
        // `info`) is bounded by the file's size, whatever its splits.
        let mut cover32 = Coverage::new(self.counts.idx32);
        let mut cover16 = Coverage::new(self.counts.idx16);
        let overlap = |i: usize, array: &str| {
            node_err(
                i as u64,
                format!("leaf range overlaps another leaf's range in {array}"),
            )
        };
        // One pass in pre-order: the node expected next (its slot, cell,
        // depth, and whether it may be an empty leaf word) must be the word
        // at `i`, so every word is one node of one tree, reached once, each
        // child after its parent; the cells carry every split's bounds.
        struct Expect {
            slot: u64,
            cell: Aabb,
            depth: u32,
            may_be_empty: bool,
        }
        let mut pending = vec![Expect {
            slot: 0,
            cell: self.bounds,
            depth: 0,
            may_be_empty: true,
        }];
        let mut i = 0usize;
        while let Some(e) = pending.pop() {
            if e.slot != i as u64 {
                return Err(node_err(
                    i as u64,
                    format!(
                        "not in pre-order: the next node is expected at {i}, its parent's slot field says {}",
                        e.slot
                    ),
                ));
            }
            let Some(&w) = words.get(i) else {
                return Err(node_err(
                    i as u64,
                    format!("a child slot outside the {n} node words"),
                ));
            };
            let decoded = node::decode(w).map_err(|m| node_err(i as u64, m.to_string()))?;
            match decoded {
                NodeWord::Inner {
                    axis,
                    t_ref,
                    right,
                    pos,
                } => {
                    if axis > 2 {
                        return Err(node_err(i as u64, "axis 3".into()));
                    }
                    let k = usize::from(axis);
                    let cell = e.cell;
                    if !(pos >= cell.min[k] && pos <= cell.max[k]) {
                        return Err(node_err(
                            i as u64,
                            format!(
                                "split {pos:?} on axis {k} outside the node's cell [{:?}, {:?}]",
                                cell.min[k], cell.max[k]
                            ),
                        ));
                    }
                    let depth = e.depth + 1;
                    if depth > MAX_DEPTH || depth > self.max_depth {
                        return Err(node_err(
                            i as u64,
                            "deeper than the header's maximum depth".into(),
                        ));
                    }
                    if t_ref {
                        match words.get(i + 1).map(|&t| node::decode(t)) {
                            Some(Ok(NodeWord::TRef { tri })) if u64::from(tri) < n_tris => {}
                            Some(Ok(NodeWord::TRef { tri })) => {
                                return Err(node_err(
                                    i as u64 + 1,
                                    format!("T-reference to triangle {tri} of {n_tris}"),
                                ));
                            }
                            _ => {
                                return Err(node_err(
                                    i as u64,
                                    "type II node without its T-reference".into(),
                                ));
                            }
                        }
                        t_inner += 1;
                    } else {
                        inner += 1;
                    }
                    let first = i as u64 + 1 + u64::from(t_ref);
                    let (left_cell, right_cell) = cell.split(k, pos);
                    let child = |slot: u64, cell: Aabb, may_be_empty: bool| Expect {
                        slot,
                        cell,
                        depth,
                        may_be_empty,
                    };
                    let right = u64::from(right);
                    if right == 0 {
                        // The right child is empty; the left one has a word,
                        // which may be an empty leaf (both children empty).
                        leaves += 1;
                        implicit += 1;
                        pending.push(child(first, left_cell, true));
                    } else if right == first {
                        leaves += 1;
                        implicit += 1;
                        pending.push(child(first, right_cell, false));
                    } else if right > first {
                        pending.push(child(right, right_cell, false));
                        pending.push(child(first, left_cell, false));
                    } else {
                        return Err(node_err(
                            i as u64,
                            format!("right child slot {right} is not after the node"),
                        ));
                    }
                    i = first as usize;
                    continue;
                }
                NodeWord::TRef { .. } => {
                    return Err(node_err(
                        i as u64,
                        "a T-reference where a child is expected".into(),
                    ));
                }
                NodeWord::Leaf1 { tri } => {
                    if u64::from(tri) >= n_tris {
                        return Err(node_err(i as u64, format!("triangle {tri} of {n_tris}")));
                    }
                    ones += 1;
                }
                NodeWord::Leaf32 { count, start } => {
                    let end = u64::from(start) + u64::from(count);
                    if end > self.counts.idx32 {
                        return Err(node_err(
                            i as u64,
                            format!("leaf range {start}+{count} outside idx32"),
                        ));
                    }
                    if count == 0 && (start != 0 || !e.may_be_empty) {
                        return Err(node_err(
                            i as u64,
                            "an empty leaf with a word (its parent's slot field says it is empty)"
                                .into(),
                        ));
                    }
                    if count == 1 {
                        return Err(node_err(
                            i as u64,
                            "a one-triangle leaf with an index entry".into(),
                        ));
                    }
                    if !cover32.claim(u64::from(start), u64::from(count)) {
                        return Err(overlap(i, "idx32"));
                    }
                }
                NodeWord::Leaf16 {
                    count,
                    upper,
                    start,
                } => {
                    let end = u64::from(start) + u64::from(count);
                    if count >= LEAF16_LIMIT || end > self.counts.idx16 {
                        return Err(node_err(
                            i as u64,
                            format!("leaf range {start}+{count} outside idx16"),
                        ));
                    }
                    if count < 2 {
                        return Err(node_err(
                            i as u64,
                            format!("a 2-byte-mode leaf of {count} triangles"),
                        ));
                    }
                    if !cover16.claim(u64::from(start), u64::from(count)) {
                        return Err(overlap(i, "idx16"));
                    }
                    // Every index of the leaf is `upper << 16 | low`.
                    let idx16 = self.idx16();
                    let base = u64::from(upper) << 16;
                    if let Some(&low) = idx16[start as usize..end as usize]
                        .iter()
                        .find(|&&low| base + u64::from(low) >= n_tris)
                    {
                        return Err(node_err(
                            i as u64,
                            format!("triangle {} of {n_tris}", base + u64::from(low)),
                        ));
                    }
                }
            }
            // A leaf.
            leaves += 1;
            i += 1;
        }
        if i as u64 != n {
            return Err(node_err(
                i as u64,
                "not referenced by any inner node (words after the tree)".into(),
            ));
        }
        for (cover, array) in [(&cover32, "idx32"), (&cover16, "idx16")] {
            if !cover.is_full() {
                return Err(FormatError::Index {
                    section: array,
                    position: cover.claimed,
                    message: "indices that no leaf lists".into(),
                });
            }
        }
        let c = &self.counts;
        if (inner, t_inner, leaves, implicit, ones)
            != (c.inner, c.t_inner, c.leaves, c.implicit_empty, c.one_leaves)
        {
            return Err(FormatError::Header(
                "node counts do not match the nodes".into(),
            ));
        }
        if let Some(p) = self.idx32().iter().position(|&t| u64::from(t) >= n_tris) {
            return Err(FormatError::Index {
                section: "idx32",
                position: p as u64,
                message: format!("triangle {} of {n_tris}", self.idx32()[p]),
            });
        }
        self.validate_geometry()
    }

    /// Checks the geometry sections: every vertex index in range, every
    /// coordinate finite, not `-0.0` and inside the header's scene bounds,
    /// and the triangle map a permutation. What [`KdFile::to_columns`]
    /// needs; part of [`KdFile::validate`].
    pub fn validate_geometry(&self) -> Result<(), FormatError> {
        let n_tris = self.counts.triangles;
        super::check_vertex_indices(self.triangles(), self.counts.vertices)?;
        if let Some(p) = self
            .vertices()
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(FormatError::Index {
                section: "vertices",
                position: p as u64,
                message: "non-finite coordinate".into(),
            });
        }
        // The scene bounds are the root cell: a vertex outside it would make
        // a triangle that brute force hits and no traversal can reach (and
        // a default camera aimed from the bounds miss the scene). `-0.0`
        // never leaves the scene's columns (`TriangleColumns` holds none),
        // so a file holding one was not written from them.
        let v = self.vertices();
        let bounds = self.bounds;
        for (t, tri) in self.triangles().iter().enumerate() {
            for &i in tri {
                let p = Vec3::from_array(v[i as usize]);
                if !(p.cmpge(bounds.min).all() && p.cmple(bounds.max).all()) {
                    return Err(FormatError::Index {
                        section: "vertices",
                        position: u64::from(i),
                        message: format!(
                            "vertex {p} of triangle {t} lies outside the header's scene bounds"
                        ),
                    });
                }
            }
        }
        if let Some(p) = v
            .iter()
            .position(|v| v.iter().any(|c| c.to_bits() == (-0.0f32).to_bits()))
        {
            return Err(FormatError::Index {
                section: "vertices",
                position: p as u64,
                message: "coordinate -0.0 (the scene's columns hold +0.0)".into(),
            });
        }
        if let Some(map) = self.tri_map() {
            let mut seen = vec![false; map.len()];
            for (p, &t) in map.iter().enumerate() {
                if u64::from(t) >= n_tris || std::mem::replace(&mut seen[t as usize], true) {
                    return Err(FormatError::Index {
                        section: "tri_map",
                        position: p as u64,
                        message: "not a permutation of the triangles".into(),
                    });
                }
            }
        }
        Ok(())
    }

    /// Checks every section's checksum (reads the whole file; not the
    /// contents' structure, which [`KdFile::validate`] checks).
    pub fn verify(&self) -> Result<(), FormatError> {
        let b = self.data.as_ref();
        for s in Section::ALL {
            let e = SECTION_TABLE + s as usize * SECTION_ENTRY;
            let stored = u32_at(b, e + 16);
            let computed = crc32fast::hash(&b[self.ranges[s as usize].clone()]);
            if stored != computed {
                return Err(FormatError::ChecksumMismatch {
                    section: s.name(),
                    expected: stored,
                    got: computed,
                });
            }
        }
        Ok(())
    }

    /// A section's byte range in the file and its stored CRC-32 (what
    /// [`KdFile::verify`] checks).
    pub fn section_range(&self, s: Section) -> (Range<usize>, u32) {
        let e = SECTION_TABLE + s as usize * SECTION_ENTRY;
        (
            self.ranges[s as usize].clone(),
            u32_at(self.data.as_ref(), e + 16),
        )
    }

    fn section<T: bytemuck::Pod>(&self, s: Section) -> &[T] {
        let bytes = &self.data.as_ref()[self.ranges[s as usize].clone()];
        // from_bytes checked that the data is 8-byte aligned and that every
        // section starts at a multiple of 64 with a whole number of
        // elements, so the cast cannot fail for a stable `AsRef`.
        bytemuck::try_cast_slice(bytes).unwrap_or(&[])
    }

    /// The node words; the root is `nodes()[0]`.
    pub fn nodes(&self) -> &[u64] {
        self.section(Section::Nodes)
    }

    /// The 4-byte leaf indices.
    pub fn idx32(&self) -> &[u32] {
        self.section(Section::Idx32)
    }

    /// The 2-byte leaf indices (low halves).
    pub fn idx16(&self) -> &[u16] {
        self.section(Section::Idx16)
    }

    /// The vertex positions.
    pub fn vertices(&self) -> &[[f32; 3]] {
        self.section(Section::Vertices)
    }

    /// Vertex-index triples, in the file's triangle numbering.
    pub fn triangles(&self) -> &[[u32; 3]] {
        self.section(Section::Triangles)
    }

    /// File triangle id → input triangle id, when the triangles were
    /// reordered.
    pub fn tri_map(&self) -> Option<&[u32]> {
        self.reordered.then(|| self.section(Section::TriMap))
    }

    /// The input id of file triangle `t` (`t` itself where the map has no
    /// entry `t`, as `trace::FileWalk` reads it).
    #[inline]
    pub fn input_id(&self, t: u32) -> u32 {
        match self.tri_map() {
            Some(map) => map.get(t as usize).copied().unwrap_or(t),
            None => t,
        }
    }

    /// The vertices of *file* triangle `t` (the file's numbering, which
    /// differs from the input's when reordered): a hit's triangle id is an
    /// input id, whose vertices [`Accel::triangle`](crate::Accel::triangle)
    /// gives; [`KdFile::input_id`] maps file ids to input ids. A vertex
    /// index out of range (a file not [validated](KdFile::validate)) reads
    /// as the origin.
    ///
    /// # Panics
    ///
    /// If `t` is not below the number of triangles.
    #[inline]
    pub fn triangle(&self, t: u32) -> [Vec3; 3] {
        let v = self.vertices();
        self.triangles()[t as usize].map(|i| v.get(i as usize).map_or(Vec3::ZERO, |&p| p.into()))
    }

    /// The indices of a leaf word; a range outside its index array (a file
    /// not [validated](KdFile::validate)) reads as an empty leaf.
    #[inline]
    pub fn leaf(&self, w: NodeWord) -> LeafIndices<'_> {
        let range = |start: u32, count: u32| start as usize..start as usize + count as usize;
        match w {
            NodeWord::Leaf32 { count, start } => {
                LeafIndices::Idx32(self.idx32().get(range(start, count)).unwrap_or(&[]))
            }
            NodeWord::Leaf16 {
                count,
                upper,
                start,
            } => LeafIndices::Idx16 {
                upper: u32::from(upper) << 16,
                low: self.idx16().get(range(start, count)).unwrap_or(&[]),
            },
            NodeWord::Leaf1 { tri } => LeafIndices::One(tri),
            _ => LeafIndices::Idx32(&[]),
        }
    }

    /// How the tree was built (the header's record).
    pub fn config(&self) -> &FileConfig {
        &self.config
    }

    /// The scene bounds: the root's cell.
    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// The depth of the deepest node (root = 0).
    pub fn max_depth(&self) -> u32 {
        self.max_depth
    }

    /// The header's counts (checked against the nodes by
    /// [`KdFile::validate`]).
    pub fn figures(&self) -> TreeFigures {
        self.counts
    }

    /// Whether the triangles were renumbered (a `tri_map` is present).
    pub fn is_reordered(&self) -> bool {
        self.reordered
    }

    /// The most nodes (words and empty children without one) a tree of
    /// this file's node words has, `2 · words + 1`: a walk that visits more
    /// is on nodes that share subtrees (a file not validated), and the
    /// traversers and readers stop there.
    pub fn node_limit(&self) -> usize {
        2 * self.nodes().len() + 1
    }

    /// Leaves per depth (root = 0), empty ones too.
    ///
    /// Of a file not [validated](KdFile::validate), the walk reads its nodes
    /// as the traversers do (a child slot outside the node section or not
    /// after its node is an empty leaf, a malformed word a leaf) and counts
    /// at most [`KdFile::node_limit`] nodes, so nodes that share subtrees
    /// cannot make it take exponential time; the counts are then what it
    /// reached.
    pub fn leaf_depth_histogram(&self) -> Vec<u64> {
        let words = self.nodes();
        let mut hist = Vec::new();
        let mut budget = self.node_limit();
        // `None`: an empty child without a word.
        let mut stack = vec![(Some(0u32), 0usize)];
        while let Some((i, d)) = stack.pop() {
            if budget == 0 {
                break;
            }
            budget -= 1;
            let word = i.and_then(|i| Some((i, node::decode(*words.get(i as usize)?))));
            if let Some((i, Ok(NodeWord::Inner { t_ref, right, .. }))) = word {
                let (l, r) = node::children(i, t_ref, right);
                let after = |c: Option<u32>| c.filter(|&c| c > i);
                stack.push((after(r), d + 1));
                stack.push((after(l), d + 1));
                continue;
            }
            if hist.len() <= d {
                hist.resize(d + 1, 0);
            }
            hist[d] += 1;
        }
        hist
    }

    /// The whole file.
    pub fn as_bytes(&self) -> &[u8] {
        self.data.as_ref()
    }
    /// The geometry back in input order, as columns (for brute force and
    /// shading by input id): a copy, after
    /// [`validate_geometry`](KdFile::validate_geometry), whose error it
    /// returns.
    pub fn to_columns(&self) -> Result<crate::scene::TriangleColumns, FormatError> {
        self.validate_geometry()?;
        let positions = self
            .vertices()
            .iter()
            .map(|&v| Vec3::from_array(v))
            .collect();
        let tris = self.triangles();
        let mut indices = vec![[0u32; 3]; tris.len()];
        for (t, tri) in tris.iter().enumerate() {
            indices[self.input_id(t as u32) as usize] = *tri;
        }
        Ok(crate::scene::TriangleColumns::from_valid_parts(
            positions, indices,
        ))
    }
}

/// The bytes of an opened `.kd` file: a read-only memory map
/// ([`KdFile::open`]) or, for files that may change under the reader, a
/// copy in memory ([`KdFile::read`]).
pub struct Mapped(Backing);

enum Backing {
    Map(memmap2::Mmap),
    Heap(AlignedBytes),
}

impl AsRef<[u8]> for Mapped {
    fn as_ref(&self) -> &[u8] {
        match &self.0 {
            Backing::Map(m) => m,
            Backing::Heap(h) => h.as_ref(),
        }
    }
}

/// How much of a file [`KdFile::open`] and [`KdFile::read`] check before
/// handing it out (see [`KdFile`] for what each guarantees).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Check {
    /// [`KdFile::from_bytes`]: the header and section table, in O(1); no
    /// page of the sections is read (0.1 ms for a 984 MB file, against
    /// 2.5–3.5 s and the whole file paged in for [`Check::Full`]).
    #[default]
    Header,
    /// Also [`KdFile::validate`]: every node, index and vertex.
    Full,
    /// Also [`KdFile::verify`]: every section's checksum (`slimkd verify`).
    Verify,
}

impl<D: AsRef<[u8]>> KdFile<D> {
    /// The checks of `check` beyond [`KdFile::from_bytes`].
    pub fn check(&self, check: Check) -> Result<(), FormatError> {
        if check != Check::Header {
            self.validate()?;
        }
        if check == Check::Verify {
            self.verify()?;
        }
        Ok(())
    }
}

impl KdFile<Mapped> {
    /// Maps a file and checks it as `check` says: [`Check::Header`], the
    /// default, reads the header alone, so a file of any size opens at once
    /// and only the pages a traversal touches are ever read.
    ///
    /// **Soundness.** A memory map is only as immutable as the file behind
    /// it: as `memmap2` documents, the file must not be modified or
    /// truncated while it is mapped, or reads through the map may change
    /// under the program (or fault on truncation). slimkd writes `.kd` files
    /// by atomic rename, never in place, so a map of a file slimkd wrote
    /// stays valid when the file is rewritten; the caller must not let any
    /// other process modify it in place. If one does all the same, the
    /// traversers still end and never read out of bounds (see
    /// [`crate::trace::FileWalk`]), but a truncation makes the kernel send
    /// SIGBUS on the next read of a lost page, which ends the process.
    /// Where files may be changed under the reader, read the file into
    /// memory instead ([`KdFile::read`], the CLI's `--no-mmap`).
    pub fn open(path: &Path, check: Check) -> Result<KdFile<Mapped>, FormatError> {
        let io = |source| FormatError::Io {
            path: path.to_path_buf(),
            source,
        };
        // Only a regular file: a directory opens, but its map fails with
        // an obscure `ENODEV`, and a FIFO's `open` waits for a writer.
        let file = crate::fsio::open_regular(path).map_err(io)?;
        // SAFETY: the map is read-only and private to this process; the
        // remaining precondition (nobody modifies the file in place while
        // it is mapped) is the caller's, documented above.
        let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io)?;
        if check == Check::Header {
            // A traversal reads a word here and a leaf there: readahead
            // would page in (and map) whole windows around each (a 256x256
            // frame of a 984 MB file not in the page cache: 31 MB resident
            // without, 135 MB with). A hint, so an error is ignored; the
            // full checks read every byte in order and keep the default,
            // and `read_ahead` restores it for readers that walk it all.
            #[cfg(unix)]
            let _ = map.advise(memmap2::Advice::Random);
        }
        let kd = KdFile::from_bytes(Mapped(Backing::Map(map)))?;
        kd.check(check)?;
        Ok(kd)
    }

    /// Restores the kernel's readahead on a map that [`KdFile::open`] made
    /// with [`Check::Header`] (which turns it off, as traversal reads at
    /// random), for a reader that walks every node (`slimkd info`: 4–6 s
    /// on a 984 MB file not in the page cache, 19 s without readahead). A
    /// hint: nothing changes for a file read into memory, and an error is
    /// ignored.
    pub fn read_ahead(&self) {
        #[cfg(unix)]
        if let Backing::Map(m) = &self.data.0 {
            let _ = m.advise(memmap2::Advice::Normal);
        }
    }

    /// [`KdFile::open`] without a map: the whole file is read into memory
    /// (anonymous pages, as large as the file) and checked as `check` says,
    /// so nothing another process does to the file afterwards reaches the
    /// reader.
    pub fn read(path: &Path, check: Check) -> Result<KdFile<Mapped>, FormatError> {
        let io = |source| FormatError::Io {
            path: path.to_path_buf(),
            source,
        };
        let mut bytes = Vec::new();
        std::io::Read::read_to_end(
            &mut crate::fsio::open_regular(path).map_err(io)?,
            &mut bytes,
        )
        .map_err(io)?;
        let kd = KdFile::from_bytes(Mapped(Backing::Heap(aligned_copy(&bytes))))?;
        kd.check(check)?;
        Ok(kd)
    }
}

/// Copies arbitrary bytes into an 8-byte-aligned buffer, for
/// [`KdFile::from_bytes`] on data of unknown alignment (e.g. `fs::read`).
pub fn aligned_copy(bytes: &[u8]) -> AlignedBytes {
    let mut words = vec![0u64; bytes.len().div_ceil(8)];
    bytemuck::cast_slice_mut::<u64, u8>(&mut words)[..bytes.len()].copy_from_slice(bytes);
    AlignedBytes {
        words,
        len: bytes.len(),
    }
}

/// Bytes stored in a `Vec<u64>` (so 8-byte aligned).
pub struct AlignedBytes {
    words: Vec<u64>,
    len: usize,
}

impl AsRef<[u8]> for AlignedBytes {
    fn as_ref(&self) -> &[u8] {
        &bytemuck::cast_slice::<u64, u8>(&self.words)[..self.len]
    }
}

#[allow(dead_code)]
fn _assert_sizes() {
    const _: () = assert!(std::mem::size_of::<[f32; 3]>() == 12);
    const _: () = assert!(std::mem::size_of::<[u32; 3]>() == 12);
}
