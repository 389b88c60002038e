//! Opening a `.kd` file: [`KdFile::from_bytes`] checks what can be checked
//! in O(1) (the header, its checksum, the section table), so that a file of
//! any size opens without reading its sections; [`KdFile::validate`] checks
//! every node, index and vertex, and [`KdFile::verify`] every section's
//! checksum. The accessors hand out typed slices of the bytes without
//! copying; every read of a node, leaf range or index through them (and
//! through `trace::FileWalk`) is checked where it is made, so a file that
//! only passed `from_bytes` never makes a reader panic, read out of bounds
//! or loop (its results may be wrong).

use super::header::{Header, section_crc};
use super::node::{self, NodeWord};
use super::{FileConfig, FormatError, Section, SectionError, TreeFigures};
use crate::geom::Aabb;
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
///   depth at most [`MAX_DEPTH`](crate::tree::MAX_DEPTH), the leaves' ranges cover each index
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
        Header::check_frame(b)?;
        if b.as_ptr().align_offset(8) != 0 {
            return Err(FormatError::Misaligned);
        }
        let header = Header::from_bytes(b)?;
        let (ranges, file_end) = header.section_ranges(b.len() as u64)?;
        // Every byte outside the checksummed header and sections is zero, so
        // that no byte of a file goes unchecked.
        header.check_tail(b)?;
        check_padding(b, &ranges, file_end)?;
        let Header {
            reordered,
            config,
            max_depth,
            counts,
            bounds,
            sections: _,
        } = header;
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

    /// Checks every section's checksum (reads the whole file; not the
    /// contents' structure, which [`KdFile::validate`] checks).
    pub fn verify(&self) -> Result<(), FormatError> {
        let b = self.data.as_ref();
        for s in Section::ALL {
            let stored = section_crc(self.data.as_ref(), s);
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
        (
            self.ranges[s as usize].clone(),
            section_crc(self.data.as_ref(), s),
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

/// Checks that the at most 63 bytes of padding after each section (up to
/// the next section, or to `file_end` after the last) are zero.
fn check_padding(b: &[u8], ranges: &[Range<usize>; 6], file_end: u64) -> Result<(), FormatError> {
    for s in Section::ALL {
        let pad_end = match Section::ALL.get(s as usize + 1) {
            Some(&next) => ranges[next as usize].start,
            None => file_end as usize,
        };
        if b[ranges[s as usize].end..pad_end].iter().any(|&x| x != 0) {
            return Err(FormatError::Section {
                section: s.name(),
                problem: SectionError::Padding,
            });
        }
    }
    Ok(())
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
