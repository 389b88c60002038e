//! Writing a tree and its geometry as a `.kd` file (layout in [`super`]).

use super::header::{Header, HeaderError, SectionEntry, is_finite_box};
use super::node::{self, MAX_LEAF32, MAX_NODES};
use super::{
    FileConfig, FormatError, HEADER_SIZE, Limit, NodeFault, SECTION_ALIGN, Section, TreeFigures,
};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::{Node, TreeIr, TriId, WalkFault};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::Path;

#[derive(Clone, Copy, Debug, Default, PartialEq)]
/// How [`write_file`] writes a tree.
pub struct WriteOptions {
    /// Renumber triangles in Morton order of their centroids, so that the
    /// triangles of a leaf have nearby ids and most leaves fit 2-byte mode.
    pub reorder: bool,
    /// What the header records of the build.
    pub config: FileConfig,
}

/// Node words per window of [`Words`] (8 MiB).
pub(super) const WINDOW: usize = 1 << 20;

/// The node words as the layout makes them, streamed out in windows of
/// [`WINDOW`] words. A word is set when its node is laid out, which for a
/// right child is after its whole left sibling subtree; a word set after
/// its window has gone out is kept in `late` and patched in afterwards
/// (a few per window: the right children waiting on the layout stack).
pub(super) struct Words<'f> {
    /// Words per window ([`WINDOW`] but in tests).
    pub(super) window: usize,
    /// Words already handed to `flush`.
    pub(super) base: usize,
    pub(super) buf: Vec<u64>,
    /// `(slot, word)` of the words set after their window went out.
    pub(super) late: Vec<(usize, u64)>,
    pub(super) flush: &'f mut dyn FnMut(&[u64]) -> Result<(), FormatError>,
}

impl<'f> Words<'f> {
    /// No words yet; `flush` takes each window as it fills.
    pub(super) fn new(
        window: usize,
        flush: &'f mut dyn FnMut(&[u64]) -> Result<(), FormatError>,
    ) -> Words<'f> {
        Words {
            window,
            base: 0,
            buf: Vec::with_capacity(window),
            late: Vec::new(),
            flush,
        }
    }

    pub(super) fn len(&self) -> usize {
        self.base + self.buf.len()
    }

    pub(super) fn push(&mut self, w: u64) -> Result<(), FormatError> {
        self.buf.push(w);
        if self.buf.len() >= self.window {
            (self.flush)(&self.buf)?;
            self.base += self.buf.len();
            self.buf.clear();
        }
        Ok(())
    }

    pub(super) fn set(&mut self, slot: usize, w: u64) {
        match slot.checked_sub(self.base) {
            Some(i) => self.buf[i] = w,
            None => self.late.push((slot, w)),
        }
    }

    /// Hands out the last words; returns the late ones.
    pub(super) fn finish(self) -> Result<Vec<(usize, u64)>, FormatError> {
        (self.flush)(&self.buf)?;
        Ok(self.late)
    }
}

/// The triangles' new numbering with `options.reorder` (else `None`):
/// the Morton order of the scene (new id to old) and its inverse (old id
/// to new).
pub(super) fn renumbering(
    scene: &TriangleColumns,
    options: &WriteOptions,
) -> (Option<Vec<u32>>, Option<Vec<u32>>) {
    let perm: Option<Vec<u32>> = options.reorder.then(|| scene.morton_order());
    let inverse = perm.as_ref().map(|p| {
        let mut inv = vec![0u32; p.len()];
        for (new, &old) in p.iter().enumerate() {
            inv[old as usize] = new as u32;
        }
        inv
    });
    (perm, inverse)
}

/// The new id of triangle `t` under `inverse` (old id to new; `None`:
/// not renumbered).
pub(super) fn new_id(inverse: Option<&[u32]>, t: TriId) -> u32 {
    inverse.map_or(t.0, |inv| inv[t.0 as usize])
}

/// The `flush` of [`Words`] that writes each window of node words to
/// `out` (little-endian), through a buffer of `window` words.
pub(super) fn flush_to<'a>(
    out: &'a mut impl Write,
    io: &'a dyn Fn(std::io::Error) -> FormatError,
    window: usize,
) -> impl FnMut(&[u64]) -> Result<(), FormatError> + 'a {
    let mut bytes = Vec::with_capacity(8 * window);
    move |ws: &[u64]| {
        bytes.clear();
        bytes.extend(ws.iter().flat_map(|w| w.to_le_bytes()));
        out.write_all(&bytes).map_err(io)
    }
}

/// What the layout pass produces besides the node words.
struct Layout {
    idx32: Vec<u32>,
    idx16: Vec<u16>,
    /// The node counts (`words`, `inner`, `t_inner`, `leaves`,
    /// `implicit_empty`, `one_leaves`; the others are filled in later).
    figures: TreeFigures,
    max_depth: u32,
}

/// What a node of the layout walk knows of its place: its cell, and, for
/// a right child, its parent's slot and word without the slot field (which
/// the right child fills in: its own slot, or 0 when it is empty), or,
/// for a left child, whether it must have a word even when empty (its
/// right sibling is empty too).
#[derive(Clone, Copy)]
struct Place {
    cell: crate::geom::Aabb,
    parent: Option<(usize, u64)>,
    keep_empty: bool,
}

/// Lays out the node words (format version 2, see [`node`]: pre-order,
/// empty children without a word, one-triangle leaves in their word) and
/// the index arrays. Refuses, rather than writing a file the reader would
/// reject, a tree that does not fit the format (too many nodes, a leaf over
/// [`MAX_LEAF32`] triangles, deeper than [`MAX_DEPTH`](crate::tree::MAX_DEPTH)) or that is
/// malformed (a child or leaf list out of range, a node reached twice, an
/// axis over 2, a split that is not finite or lies outside its node's cell,
/// a triangle id of `n_tris` or more).
fn layout(
    tree: &TreeIr,
    n_tris: usize,
    new_id: &dyn Fn(TriId) -> u32,
    words: &mut Words<'_>,
) -> Result<Layout, FormatError> {
    let mut out = Layout {
        idx32: Vec::new(),
        idx16: Vec::new(),
        figures: TreeFigures::default(),
        max_depth: 0,
    };
    let bad_node = |i: usize, fault: NodeFault| FormatError::Node {
        index: i as u64,
        fault,
    };
    let bad_tri = |i: usize, t: TriId| FormatError::Index {
        section: "tree",
        position: i as u64,
        message: format!("node {i} lists triangle {} of {n_tris}", t.0),
    };
    // Each IR node is laid out at most once (the walk refuses a node
    // reached twice), so a malformed tree (a cycle, shared children) cannot
    // make the loop run away.
    let n_nodes = tree.nodes.len();
    let walk_fault = |fault: WalkFault| match fault {
        WalkFault::Missing { node } => bad_node(node, NodeFault::ChildOutside(n_nodes as u64)),
        WalkFault::ReachedTwice { node } => bad_node(node, NodeFault::ReachedTwice),
        WalkFault::TooDeep { .. } => FormatError::TooLarge(Limit::Depth),
    };
    let is_empty_leaf = |i: usize| matches!(tree.nodes.get(i), Some(Node::Leaf { count: 0, .. }));
    let mut ids = Vec::new();
    let root = Place {
        cell: tree.bounds,
        parent: None,
        keep_empty: true,
    };
    tree.walk_checked(root, walk_fault, |i, &node, depth, place| {
        out.max_depth = out.max_depth.max(depth);
        let empty = matches!(node, Node::Leaf { count: 0, .. });
        let has_word = !empty || place.keep_empty;
        let slot = words.len();
        // A right child completes its parent's word: its own slot, or 0
        // when it has none.
        if let Some((parent, word)) = place.parent {
            let field = if has_word { slot as u64 } else { 0 };
            words.set(parent, word | field << 3);
        }
        if !has_word {
            out.figures.leaves += 1;
            out.figures.implicit_empty += 1;
            return Ok(None);
        }
        if slot as u64 >= MAX_NODES {
            return Err(FormatError::TooLarge(Limit::NodeWords));
        }
        match node {
            Node::Inner {
                axis,
                pos,
                t_ref,
                right,
            } => {
                if axis > 2 {
                    return Err(bad_node(i, NodeFault::Axis(axis)));
                }
                if !pos.is_finite() {
                    return Err(bad_node(i, NodeFault::SplitNotFinite));
                }
                let k = usize::from(axis);
                let cell = place.cell;
                if !(pos >= cell.min[k] && pos <= cell.max[k]) {
                    return Err(bad_node(
                        i,
                        NodeFault::SplitOutsideCell {
                            pos,
                            axis: k,
                            min: cell.min[k],
                            max: cell.max[k],
                        },
                    ));
                }
                // The slot field is filled in by the right child.
                let word = node::encode_inner(axis, t_ref.is_some(), 0, pos);
                words.push(word)?;
                match t_ref {
                    Some(t) => {
                        if t.0 as usize >= n_tris {
                            return Err(bad_tri(i, t));
                        }
                        out.figures.t_inner += 1;
                        words.push(node::encode_tref(new_id(t)))?;
                    }
                    None => out.figures.inner += 1,
                }
                let (left, right_cell) = cell.split(k, pos);
                Ok(Some((
                    Place {
                        cell: left,
                        parent: None,
                        keep_empty: is_empty_leaf(right.0 as usize),
                    },
                    Place {
                        cell: right_cell,
                        parent: Some((slot, word)),
                        keep_empty: false,
                    },
                )))
            }
            Node::Leaf { start, count } => {
                // Checked before the list is read: a leaf this large is
                // always in 4-byte mode, whose count field has 27 bits.
                if count > MAX_LEAF32 {
                    return Err(FormatError::TooLarge(Limit::Leaf(u64::from(count))));
                }
                let list = tree
                    .leaf_tris
                    .get(start as usize..start as usize + count as usize)
                    .ok_or_else(|| {
                        bad_node(
                            i,
                            NodeFault::LeafListOutside {
                                start: u64::from(start),
                                count: u64::from(count),
                                listed: tree.leaf_tris.len() as u64,
                            },
                        )
                    })?;
                if let Some(&t) = list.iter().find(|t| t.0 as usize >= n_tris) {
                    return Err(bad_tri(i, t));
                }
                let word = leaf_word(
                    &mut ids,
                    list.iter().map(|&t| new_id(t)),
                    &mut out.idx32,
                    &mut out.idx16,
                    &mut out.figures,
                )?;
                words.push(word)?;
                Ok(None)
            }
        }
    })?;
    out.figures.words = words.len() as u64;
    if out.figures.words > MAX_NODES {
        return Err(FormatError::TooLarge(Limit::NodeWords));
    }
    Ok(out)
}

/// Where a leaf's index list goes: an index array in memory, or one
/// streamed through a file (`super::stream`).
pub(super) trait Entries {
    /// Entries so far.
    fn count(&self) -> u64;
    /// Appends `ids` (cut to the array's width).
    fn put(&mut self, ids: &[u32]) -> Result<(), FormatError>;
}

impl Entries for Vec<u32> {
    fn count(&self) -> u64 {
        self.len() as u64
    }
    fn put(&mut self, ids: &[u32]) -> Result<(), FormatError> {
        self.extend_from_slice(ids);
        Ok(())
    }
}

impl Entries for Vec<u16> {
    fn count(&self) -> u64 {
        self.len() as u64
    }
    fn put(&mut self, ids: &[u32]) -> Result<(), FormatError> {
        self.extend(ids.iter().map(|&t| t as u16));
        Ok(())
    }
}

/// The word of a leaf of the triangles `tris` (new ids, sorted into
/// `ids`, a buffer kept from leaf to leaf): one triangle in the word, an
/// empty leaf, or a list appended to `idx16` when it fits 2-byte mode,
/// else to `idx32`; `figures` counts the leaf (and the leaves of one
/// triangle).
pub(super) fn leaf_word(
    ids: &mut Vec<u32>,
    tris: impl Iterator<Item = u32>,
    idx32: &mut impl Entries,
    idx16: &mut impl Entries,
    figures: &mut TreeFigures,
) -> Result<u64, FormatError> {
    figures.leaves += 1;
    ids.clear();
    ids.extend(tris);
    ids.sort_unstable();
    Ok(if let [t] = ids[..] {
        figures.one_leaves += 1;
        node::encode_leaf1(t)
    } else if ids.is_empty() {
        // The one form of an empty leaf with a word.
        node::encode_leaf32(0, 0)
    } else if node::fits_leaf16(ids.len(), ids.iter().copied()) {
        let upper = ids.first().map_or(0, |&t| t >> 16);
        let first =
            u32::try_from(idx16.count()).map_err(|_| FormatError::TooLarge(Limit::Idx16Entries))?;
        idx16.put(ids)?;
        node::encode_leaf16(ids.len() as u32, upper as u16, first)
    } else {
        let first =
            u32::try_from(idx32.count()).map_err(|_| FormatError::TooLarge(Limit::Idx32Entries))?;
        idx32.put(ids)?;
        node::encode_leaf32(ids.len() as u32, first)
    })
}

/// Refuses a scene the reader would reject (see [`write_to_vec`]).
pub(super) fn check_scene(b: Aabb, scene: &TriangleColumns) -> Result<(), FormatError> {
    if !is_finite_box(b) {
        return Err(HeaderError::Bounds.into());
    }
    if scene.len() > u32::MAX as usize || scene.positions().len() > u32::MAX as usize {
        return Err(FormatError::TooLarge(Limit::TrianglesOrVertices));
    }
    if let Some(p) = scene.positions().iter().position(|p| !p.is_finite()) {
        return Err(FormatError::Index {
            section: "vertices",
            position: p as u64,
            message: "non-finite coordinate".into(),
        });
    }
    super::check_vertex_indices(scene.indices(), scene.positions().len() as u64)?;
    let p = scene.positions();
    for (t, tri) in scene.indices().iter().enumerate() {
        if let Some(&i) = tri
            .iter()
            .find(|&&i| !(p[i as usize].cmpge(b.min).all() && p[i as usize].cmple(b.max).all()))
        {
            return Err(FormatError::Index {
                section: "vertices",
                position: u64::from(i),
                message: format!(
                    "vertex {} of triangle {t} lies outside the tree's bounds",
                    p[i as usize]
                ),
            });
        }
    }
    Ok(())
}

/// Bytes encoded per write by [`SectionSink`].
const SINK_BUF: usize = 1 << 20;

/// Writes one section after another, each checksummed and padded to
/// [`SECTION_ALIGN`].
pub(super) struct SectionSink<'w, W: Write> {
    out: &'w mut W,
    buf: Vec<u8>,
    crc: crc32fast::Hasher,
    /// Bytes of the current section so far.
    len: u64,
}

impl<W: Write> SectionSink<'_, W> {
    #[inline]
    pub(super) fn put(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.buf.extend_from_slice(bytes);
        if self.buf.len() >= SINK_BUF {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.crc.update(&self.buf);
        self.len += self.buf.len() as u64;
        self.out.write_all(&self.buf)?;
        self.buf.clear();
        Ok(())
    }

    /// Ends a section: its CRC and length; writes the padding after it.
    fn finish_section(&mut self) -> std::io::Result<(u32, u64)> {
        self.flush()?;
        let crc = std::mem::take(&mut self.crc).finalize();
        let len = std::mem::take(&mut self.len);
        // Sections start at multiples of SECTION_ALIGN (the header's size
        // is one), so the section's own length decides the padding.
        write_padding(self.out, len)?;
        Ok((crc, len))
    }
}

/// The zeros after a section of `len` bytes, up to a multiple of
/// [`SECTION_ALIGN`].
fn write_padding(out: &mut impl Write, len: u64) -> std::io::Result<()> {
    let pad = len.next_multiple_of(SECTION_ALIGN as u64) - len;
    out.write_all(&[0u8; SECTION_ALIGN][..pad as usize])
}

/// Writes the `.kd` file to `out` (positioned at its start), which must
/// read back what was written: the node words stream out as the layout
/// makes them, the few set late are patched in, their section is read
/// back for its checksum, the other sections stream out from the layout's
/// index arrays and the scene, and the header goes last, at offset 0.
/// Nothing the size of the file or of the node section is held; `io`
/// names `out` in errors.
fn write_kd<W: Read + Write + Seek>(
    out: &mut W,
    tree: &TreeIr,
    scene: &TriangleColumns,
    options: &WriteOptions,
    io: &dyn Fn(std::io::Error) -> FormatError,
    window: usize,
) -> Result<(), FormatError> {
    check_scene(tree.bounds, scene)?;
    let n_tris = scene.len();
    let (perm, inverse) = renumbering(scene, options);
    out.write_all(&[0u8; HEADER_SIZE]).map_err(io)?;

    // The node section.
    let (lay, late) = {
        let new_id = |t: TriId| new_id(inverse.as_deref(), t);
        let mut flush = flush_to(out, io, window);
        let mut words = Words::new(window, &mut flush);
        let lay = layout(tree, n_tris, &new_id, &mut words)?;
        (lay, words.finish()?)
    };
    let figures = TreeFigures {
        idx32: lay.idx32.len() as u64,
        idx16: lay.idx16.len() as u64,
        ..lay.figures
    };
    let mut put_idx = |section: Section, sink: &mut SectionSink<'_, W>| match section {
        Section::Idx32 => lay
            .idx32
            .iter()
            .try_for_each(|w| sink.put(&w.to_le_bytes())),
        _ => lay
            .idx16
            .iter()
            .try_for_each(|w| sink.put(&w.to_le_bytes())),
    };
    finish_kd(
        out,
        late,
        figures,
        lay.max_depth,
        &mut put_idx,
        scene,
        perm.as_deref(),
        options,
        tree.bounds,
        io,
    )
}

/// The file after its node words (which `out` holds from [`HEADER_SIZE`]
/// on, up to where it stands): the `late` words patched in, the node
/// section read back for its checksum and padded, the index sections
/// (written by `put_idx` for `Section::Idx32` and `Section::Idx16`), the
/// geometry (renumbered by `perm`, new to old id), and the header, at
/// offset 0.
#[allow(clippy::too_many_arguments)]
pub(super) fn finish_kd<W: Read + Write + Seek>(
    out: &mut W,
    late: Vec<(usize, u64)>,
    figures: TreeFigures,
    max_depth: u32,
    put_idx: &mut dyn FnMut(Section, &mut SectionSink<'_, W>) -> std::io::Result<()>,
    scene: &TriangleColumns,
    perm: Option<&[u32]>,
    options: &WriteOptions,
    b: Aabb,
    io: &dyn Fn(std::io::Error) -> FormatError,
) -> Result<(), FormatError> {
    let n_tris = scene.len();
    let nodes_len = figures.words * 8;
    let crc_nodes = (|| {
        for (slot, w) in late {
            out.seek(SeekFrom::Start(HEADER_SIZE as u64 + 8 * slot as u64))?;
            out.write_all(&w.to_le_bytes())?;
        }
        out.seek(SeekFrom::Start(HEADER_SIZE as u64))?;
        let mut crc = crc32fast::Hasher::new();
        let mut buf = vec![0u8; SINK_BUF];
        let mut left = nodes_len;
        while left > 0 {
            let n = left.min(buf.len() as u64) as usize;
            out.read_exact(&mut buf[..n])?;
            crc.update(&buf[..n]);
            left -= n as u64;
        }
        write_padding(out, nodes_len)?;
        Ok(crc.finalize())
    })()
    .map_err(io)?;

    // The other sections.
    let mut lens = [0u64; 6];
    let mut crcs = [0u32; 6];
    lens[Section::Nodes as usize] = nodes_len;
    crcs[Section::Nodes as usize] = crc_nodes;
    let mut sink = SectionSink {
        out,
        buf: Vec::with_capacity(SINK_BUF + 16),
        crc: crc32fast::Hasher::new(),
        len: 0,
    };
    for section in &Section::ALL[1..] {
        match section {
            Section::Nodes => unreachable!("written above"),
            Section::Idx32 | Section::Idx16 => put_idx(*section, &mut sink),
            Section::Vertices => scene.positions().iter().try_for_each(|p| {
                [p.x, p.y, p.z]
                    .iter()
                    .try_for_each(|v| sink.put(&v.to_le_bytes()))
            }),
            Section::Triangles => (0..n_tris).try_for_each(|new| {
                let old = perm.map_or(new, |p| p[new] as usize);
                scene.indices()[old]
                    .iter()
                    .try_for_each(|v| sink.put(&v.to_le_bytes()))
            }),
            Section::TriMap => perm
                .into_iter()
                .flatten()
                .try_for_each(|w| sink.put(&w.to_le_bytes())),
        }
        .map_err(io)?;
        let (crc, len) = sink.finish_section().map_err(io)?;
        lens[*section as usize] = len;
        crcs[*section as usize] = crc;
    }

    let mut offset = HEADER_SIZE as u64;
    let sections: [SectionEntry; 6] = std::array::from_fn(|s| {
        let entry = SectionEntry {
            offset,
            len: lens[s],
            crc: crcs[s],
        };
        offset = (offset + lens[s]).next_multiple_of(SECTION_ALIGN as u64);
        entry
    });
    let header = Header {
        reordered: perm.is_some(),
        config: options.config,
        max_depth,
        counts: TreeFigures {
            triangles: n_tris as u64,
            vertices: scene.positions().len() as u64,
            ..figures
        },
        bounds: b,
        sections,
    }
    .to_bytes();
    (|| {
        let end = out.stream_position()?;
        debug_assert_eq!(end, offset);
        out.seek(SeekFrom::Start(0))?;
        out.write_all(&header)?;
        out.seek(SeekFrom::Start(end))?;
        Ok(())
    })()
    .map_err(io)
}

/// Serialises a tree and its scene into the bytes of a `.kd` file.
///
/// Never writes a file that [`KdFile::from_bytes_checked`](super::KdFile::from_bytes_checked)
/// would reject: a tree that does not fit the format
/// ([`FormatError::TooLarge`]), a malformed tree (a child or leaf list out of
/// range, a node reached twice, an axis over 2, a split that is not finite
/// or lies outside its node's cell, a triangle id out of range) or scene
/// (non-finite bounds or vertices, a vertex index out of range, a triangle's
/// vertex outside the tree's bounds) is an error, never a panic. The tree need not
/// pass [`TreeIr::validate`] otherwise: leaves may repeat a triangle.
pub fn write_to_vec(
    tree: &TreeIr,
    scene: &TriangleColumns,
    options: &WriteOptions,
) -> Result<Vec<u8>, FormatError> {
    let mut out = std::io::Cursor::new(Vec::new());
    write_kd(
        &mut out,
        tree,
        scene,
        options,
        &|e| unreachable!("writing to a Vec cannot fail: {e}"),
        WINDOW,
    )?;
    Ok(out.into_inner())
}

/// Writes a `.kd` file atomically ([`crate::fsio::write_atomically`]: a
/// temporary file in the same directory, fsync, rename, a best-effort fsync
/// of the directory). A failed or killed write leaves no file at `path`
/// (and never a half-written one that could pass for valid); a failed
/// write removes its temporary file. The bytes are those of
/// [`write_to_vec`], streamed to the file rather than built in memory (see
/// `write_kd`).
pub fn write_file(
    path: &Path,
    tree: &TreeIr,
    scene: &TriangleColumns,
    options: &WriteOptions,
) -> Result<(), FormatError> {
    // Refuse a bad scene before any file is made.
    check_scene(tree.bounds, scene)?;
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    };
    // `write_kd` writes in pieces of about a MiB, except for the header and
    // the padding.
    crate::fsio::write_atomically(path, io, |f| write_kd(f, tree, scene, options, &io, WINDOW))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::testing::{grid_tree, whole_files};

    /// Windows of a few words send many words out before they are set;
    /// the file is the same as with one window for the whole section.
    #[test]
    fn late_words_are_patched_in() {
        // A grid of small triangles, one per unit cell.
        let (scene, tree) = grid_tree(400, 20, (1.0, 1.0));
        assert!(tree.nodes.len() > 100);
        for (options, whole) in whole_files(&scene, &tree) {
            for window in [1, 2, 3, 7, 64] {
                let mut out = std::io::Cursor::new(Vec::new());
                write_kd(
                    &mut out,
                    &tree,
                    &scene,
                    &options,
                    &|e| panic!("{e}"),
                    window,
                )
                .unwrap();
                assert!(out.into_inner() == whole, "window {window}");
            }
        }
    }
}
