//! The file header (layout in [`super`]): [`Header::to_bytes`] for the
//! writer, [`Header::from_bytes`] and its companion checks for the reader,
//! so that every byte offset of a header field is written down once, here.

use super::{
    ENDIAN_CHECK, FLAG_REORDERED, FormatError, HEADER_SIZE, MAGIC, SECTION_ALIGN, Section,
    SectionError, VERSION,
};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::MAX_DEPTH;
use glam::Vec3;
use std::ops::Range;

/// Where the fields of the header lie (see the table in [`super`]).
mod at {
    pub(super) const VERSION: usize = 8;
    pub(super) const ENDIAN: usize = 12;
    pub(super) const HEADER_SIZE: usize = 16;
    pub(super) const FLAGS: usize = 20;
    pub(super) const K_T: usize = 24;
    pub(super) const K_I: usize = 32;
    pub(super) const LAMBDA_EMPTY: usize = 40;
    pub(super) const DEPTH_LIMIT: usize = 48;
    pub(super) const PRESET: usize = 52;
    pub(super) const TAU_OCCU: usize = 56;
    pub(super) const TAU_FREQ: usize = 60;
    pub(super) const MAX_T2RN: usize = 64;
    pub(super) const MAX_DEPTH: usize = 68;
    pub(super) const WORDS: usize = 72;
    pub(super) const INNER: usize = 80;
    pub(super) const T_INNER: usize = 88;
    pub(super) const LEAVES: usize = 96;
    pub(super) const IDX32: usize = 104;
    pub(super) const IDX16: usize = 112;
    pub(super) const TRIANGLES: usize = 120;
    pub(super) const VERTICES: usize = 128;
    /// Min xyz, max xyz (f32).
    pub(super) const BOUNDS: usize = 136;
    /// The scene tag: the geometry hash (u64), then the name
    /// ([`SCENE_NAME_LEN`](super::SCENE_NAME_LEN) bytes).
    pub(super) const SCENE_HASH: usize = 160;
    pub(super) const SCENE_NAME: usize = 168;
    /// Per section: byte offset (u64), byte length (u64), CRC-32 (u32),
    /// reserved (u32).
    pub(super) const SECTION_TABLE: usize = 192;
    pub(super) const SECTION_ENTRY: usize = 24;
    /// The CRC-32 of bytes `0..HEADER_CRC`.
    pub(super) const HEADER_CRC: usize = 336;
    /// The counts of empty leaves without a word and of one-triangle
    /// leaves, after the checksummed part (checked against the nodes).
    pub(super) const IMPLICIT_EMPTY: usize = 340;
    pub(super) const ONE_LEAVES: usize = 348;
    /// The tail, `SPLIT_PRICE..TAIL_CRC`, under its own CRC-32.
    pub(super) const SPLIT_PRICE: usize = 356;
    pub(super) const RESERVED: usize = 364;
    pub(super) const TAIL_CRC: usize = 380;
}

// The section table fills the bytes up to the header checksum.
const _: () = assert!(at::SECTION_TABLE + 6 * at::SECTION_ENTRY == at::HEADER_CRC);
const _: () =
    assert!(at::HEADER_CRC + 4 <= HEADER_SIZE && HEADER_SIZE.is_multiple_of(SECTION_ALIGN));
const _: () = assert!(at::TAIL_CRC + 4 == HEADER_SIZE);
// The scene tag fills the bytes between the bounds and the section table.
const _: () = assert!(at::SCENE_HASH == at::BOUNDS + 24 && at::SCENE_NAME == at::SCENE_HASH + 8);
const _: () = assert!(at::SCENE_NAME + SCENE_NAME_LEN == at::SECTION_TABLE);

/// What is wrong with a header field, or with a count of the header
/// against the file ([`FormatError::Header`]).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum HeaderError {
    /// The header-size field is not [`HEADER_SIZE`].
    #[error("header size {0}")]
    Size(u32),
    /// Flag bits this build does not know.
    #[error("unknown flags {0:#x}")]
    Flags(u32),
    /// A preset number this build does not know.
    #[error("unknown preset {0}")]
    Preset(u32),
    /// The scene name is not UTF-8 followed by zero bytes.
    #[error(
        "the scene name (bytes {}..{}) is not UTF-8 padded with zero bytes",
        at::SCENE_NAME,
        at::SCENE_NAME + SCENE_NAME_LEN
    )]
    SceneName,
    /// The scene bounds are not a finite box (min ≤ max).
    #[error("scene bounds are not a finite box")]
    Bounds,
    /// No node words, or more than the format holds.
    #[error("{0} node words")]
    Words(u64),
    /// More than 2^32 triangles or vertices.
    #[error("more than 2^32 triangles or vertices")]
    TooManyTriangles,
    /// The header's node counts do not add up to its node words.
    #[error("node counts do not add up")]
    Counts,
    /// The maximum node depth is over [`MAX_DEPTH`].
    #[error("depth {0} over {MAX_DEPTH}")]
    Depth(u32),
    /// Bytes after the padding of the last section.
    #[error("{extra} bytes after the end of the file at byte {end}")]
    TrailingBytes {
        /// Bytes too many.
        extra: u64,
        /// Where the file ends.
        end: u64,
    },
    /// A reserved field that is not zero.
    #[error("reserved {what} {}..{} are not zero", bytes.start, bytes.end)]
    Reserved {
        /// The field.
        what: &'static str,
        /// Its bytes.
        bytes: Range<usize>,
    },
    /// The tail (the split price and the reserved bytes) does not match
    /// its CRC-32.
    #[error(
        "header bytes {}..{} do not match their CRC-32 at byte {}",
        at::SPLIT_PRICE,
        at::TAIL_CRC,
        at::TAIL_CRC
    )]
    TailChecksum,
    /// The split price is negative or not finite.
    #[error("split price {0} is not a finite number ≥ 0")]
    SplitPrice(f64),
    /// The header's node counts are not those of the nodes
    /// ([`KdFile::validate`](super::KdFile::validate)).
    #[error("node counts do not match the nodes")]
    NodeCounts,
    /// A streamed tree's node came before its bounds.
    #[error("a node before the tree's bounds")]
    NodeBeforeBounds,
    /// A streamed tree's bounds came twice.
    #[error("the tree's bounds given twice")]
    BoundsTwice,
}

impl From<HeaderError> for FormatError {
    fn from(e: HeaderError) -> FormatError {
        FormatError::Header(e)
    }
}

/// The build preset recorded in the header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preset {
    /// No hoisting.
    Std,
    /// The `fast` slim preset.
    Fast,
    /// The `small` slim preset.
    Small,
    /// Hoisting with thresholds of the caller's choice.
    Custom,
}

impl Preset {
    /// The preset of a header value.
    pub fn from_u32(v: u32) -> Option<Preset> {
        [Preset::Std, Preset::Fast, Preset::Small, Preset::Custom]
            .get(v as usize)
            .copied()
    }

    /// The preset's name, as the CLI spells it.
    pub fn name(self) -> &'static str {
        ["std", "fast", "small", "custom"][self as usize]
    }
}

/// Bytes of the header's scene-name field.
pub const SCENE_NAME_LEN: usize = 24;

/// The scene a file was built from, as its header records it: the scene's
/// name (what a views file calls it, so that a renamed file keeps its
/// views) and a hash of its geometry (to tell whether two files, or a file
/// and a scene, hold the same triangles). The default records neither.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SceneTag {
    /// UTF-8, padded with zero bytes; all zero when not recorded.
    name: [u8; SCENE_NAME_LEN],
    /// [`SceneTag::geometry_hash_of`] of the scene; 0 when not recorded.
    pub geometry_hash: u64,
}

impl SceneTag {
    /// The tag of `scene` under `name`. A name that does not fit the field
    /// (over [`SCENE_NAME_LEN`] bytes) or holds a zero byte is not
    /// recorded, rather than cut to a name no views file uses.
    pub fn new(name: &str, scene: &TriangleColumns) -> SceneTag {
        let mut tag = SceneTag {
            geometry_hash: SceneTag::geometry_hash_of(scene),
            ..SceneTag::default()
        };
        if name.len() <= SCENE_NAME_LEN && !name.as_bytes().contains(&0) {
            tag.name[..name.len()].copy_from_slice(name.as_bytes());
        }
        tag
    }

    /// The recorded name, if any.
    pub fn name(&self) -> Option<&str> {
        let len = self
            .name
            .iter()
            .position(|&b| b == 0)
            .unwrap_or(SCENE_NAME_LEN);
        // Both constructors hold the field to UTF-8.
        std::str::from_utf8(&self.name[..len])
            .ok()
            .filter(|n| !n.is_empty())
    }

    /// The geometry hash: the CRC-32 of the vertex positions (x, y, z as
    /// little-endian `f32`, in input order) in the high 32 bits, the CRC-32
    /// of the triangles' vertex indices (little-endian `u32`, in input
    /// order) in the low 32 bits. It does not depend on the tree or on the
    /// file's triangle numbering.
    pub fn geometry_hash_of(scene: &TriangleColumns) -> u64 {
        let mut pos = crc32fast::Hasher::new();
        for p in scene.positions() {
            for v in [p.x, p.y, p.z] {
                pos.update(&v.to_le_bytes());
            }
        }
        let mut idx = crc32fast::Hasher::new();
        for t in scene.indices() {
            for v in t {
                idx.update(&v.to_le_bytes());
            }
        }
        (u64::from(pos.finalize()) << 32) | u64::from(idx.finalize())
    }

    /// Reads the tag from its header bytes; an error unless the name is
    /// UTF-8 followed by zero bytes only.
    fn from_header(header: &[u8]) -> Result<SceneTag, HeaderError> {
        let mut name = [0u8; SCENE_NAME_LEN];
        name.copy_from_slice(&header[at::SCENE_NAME..at::SCENE_NAME + SCENE_NAME_LEN]);
        let len = name.iter().position(|&b| b == 0).unwrap_or(SCENE_NAME_LEN);
        if name[len..].iter().any(|&b| b != 0) || std::str::from_utf8(&name[..len]).is_err() {
            return Err(HeaderError::SceneName);
        }
        Ok(SceneTag {
            name,
            geometry_hash: u64_at(header, at::SCENE_HASH),
        })
    }

    fn put(&self, header: &mut [u8]) {
        put_u64(header, at::SCENE_HASH, self.geometry_hash);
        header[at::SCENE_NAME..at::SCENE_NAME + SCENE_NAME_LEN].copy_from_slice(&self.name);
    }
}

/// The build configuration recorded in the header (for the record only:
/// traversal does not depend on it), and the scene's tag.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FileConfig {
    /// SAH cost of a traversal step.
    pub k_t: f64,
    /// SAH cost of a triangle test.
    pub k_i: f64,
    /// The SAH's bonus factor for cutting off empty space.
    pub lambda_empty: f64,
    /// The depth limit the build used.
    pub depth_limit: u32,
    /// The SAH's split price `μ` (0: none).
    pub split_price: f64,
    /// The slim preset, or `Std`.
    pub preset: Preset,
    /// The hoisting occupancy threshold (0 for `Std`).
    pub tau_occu: f32,
    /// The hoisting frequency threshold (0 for `Std`).
    pub tau_freq: f32,
    /// The most hoisted triangles on a root path (0 for `Std`).
    pub max_t2rn: u32,
    /// The scene the tree was built for.
    pub scene: SceneTag,
}

impl Default for FileConfig {
    fn default() -> Self {
        FileConfig {
            k_t: 15.0,
            k_i: 20.0,
            lambda_empty: 0.8,
            depth_limit: 0,
            split_price: 0.0,
            preset: Preset::Std,
            tau_occu: 0.0,
            tau_freq: 0.0,
            max_t2rn: 0,
            scene: SceneTag::default(),
        }
    }
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

    /// The element count the header gives section `s`.
    fn elements(&self, s: Section, reordered: bool) -> u64 {
        match s {
            Section::Nodes => self.words,
            Section::Idx32 => self.idx32,
            Section::Idx16 => self.idx16,
            Section::Vertices => self.vertices,
            Section::Triangles => self.triangles,
            Section::TriMap if reordered => self.triangles,
            Section::TriMap => 0,
        }
    }

    /// Whether the node counts add up: a binary tree has one more leaf
    /// than inner nodes, each type II node adds one T-reference word, and
    /// the empty leaves without a word take none. At most one leaf per
    /// inner node is empty and wordless (both empty: the left has one).
    fn add_up(&self) -> bool {
        let inner_all = self.inner.checked_add(self.t_inner);
        inner_all.and_then(|n| n.checked_add(1)) == Some(self.leaves)
            && self.implicit_empty < self.leaves
            && self.one_leaves <= self.leaves - self.implicit_empty
            && inner_all
                .and_then(|n| n.checked_add(self.leaves - self.implicit_empty))
                .and_then(|n| n.checked_add(self.t_inner))
                == Some(self.words)
    }
}

/// One entry of the section table.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct SectionEntry {
    /// Byte offset in the file.
    pub(crate) offset: u64,
    /// Byte length.
    pub(crate) len: u64,
    /// CRC-32 of the section's bytes.
    pub(crate) crc: u32,
}

/// The header's fields, decoded.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Header {
    /// Flag bit [`FLAG_REORDERED`]: the `tri_map` section is present.
    pub reordered: bool,
    pub config: FileConfig,
    /// The depth of the deepest node (root = 0).
    pub max_depth: u32,
    pub counts: TreeFigures,
    /// The scene bounds: the root's cell.
    pub bounds: Aabb,
    /// The section table, in [`Section::ALL`] order.
    pub sections: [SectionEntry; 6],
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

fn put_u32(b: &mut [u8], at: usize, v: u32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

fn put_u64(b: &mut [u8], at: usize, v: u64) {
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
}

/// Whether `b` (min, max) is a finite box, as the header's scene bounds
/// must be (the writer's check of its tree and the reader's of its file).
pub(crate) fn is_finite_box(b: Aabb) -> bool {
    b.min.is_finite() && b.max.is_finite() && b.min.cmple(b.max).all()
}

impl Header {
    /// The header's bytes: every field, the header's CRC-32 and the
    /// tail's; reserved bytes zero.
    pub(crate) fn to_bytes(&self) -> [u8; HEADER_SIZE] {
        let mut h = [0u8; HEADER_SIZE];
        h[0..8].copy_from_slice(&MAGIC);
        put_u32(&mut h, at::VERSION, VERSION);
        put_u32(&mut h, at::ENDIAN, ENDIAN_CHECK);
        put_u32(&mut h, at::HEADER_SIZE, HEADER_SIZE as u32);
        let flags = if self.reordered { FLAG_REORDERED } else { 0 };
        put_u32(&mut h, at::FLAGS, flags);
        let c = &self.config;
        put_u64(&mut h, at::K_T, c.k_t.to_bits());
        put_u64(&mut h, at::K_I, c.k_i.to_bits());
        put_u64(&mut h, at::LAMBDA_EMPTY, c.lambda_empty.to_bits());
        put_u32(&mut h, at::DEPTH_LIMIT, c.depth_limit);
        put_u32(&mut h, at::PRESET, c.preset as u32);
        put_u32(&mut h, at::TAU_OCCU, c.tau_occu.to_bits());
        put_u32(&mut h, at::TAU_FREQ, c.tau_freq.to_bits());
        put_u32(&mut h, at::MAX_T2RN, c.max_t2rn);
        put_u32(&mut h, at::MAX_DEPTH, self.max_depth);
        let n = &self.counts;
        for (field, v) in [
            (at::WORDS, n.words),
            (at::INNER, n.inner),
            (at::T_INNER, n.t_inner),
            (at::LEAVES, n.leaves),
            (at::IMPLICIT_EMPTY, n.implicit_empty),
            (at::ONE_LEAVES, n.one_leaves),
            (at::SPLIT_PRICE, c.split_price.to_bits()),
            (at::IDX32, n.idx32),
            (at::IDX16, n.idx16),
            (at::TRIANGLES, n.triangles),
            (at::VERTICES, n.vertices),
        ] {
            put_u64(&mut h, field, v);
        }
        let b = self.bounds;
        for (k, v) in [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z]
            .into_iter()
            .enumerate()
        {
            put_u32(&mut h, at::BOUNDS + 4 * k, v.to_bits());
        }
        c.scene.put(&mut h);
        for (s, entry) in self.sections.iter().enumerate() {
            let e = at::SECTION_TABLE + s * at::SECTION_ENTRY;
            put_u64(&mut h, e, entry.offset);
            put_u64(&mut h, e + 8, entry.len);
            put_u32(&mut h, e + 16, entry.crc);
        }
        let crc = crc32fast::hash(&h[..at::HEADER_CRC]);
        put_u32(&mut h, at::HEADER_CRC, crc);
        let tail = crc32fast::hash(&h[at::SPLIT_PRICE..at::TAIL_CRC]);
        put_u32(&mut h, at::TAIL_CRC, tail);
        h
    }

    /// Checks what tells a `.kd` file of this version from anything else,
    /// on the file's bytes `b`: the magic (first on as much of it as there
    /// is, so that a file of another kind is named as such, not as a
    /// truncated `.kd` file), the length of the header, the version, the
    /// byte order, the header's CRC-32 and its size field.
    pub(crate) fn check_frame(b: &[u8]) -> Result<(), FormatError> {
        let have = b.len().min(MAGIC.len());
        if b[..have] != MAGIC[..have] {
            return Err(FormatError::BadMagic);
        }
        if b.len() < HEADER_SIZE {
            return Err(FormatError::Truncated {
                needed: HEADER_SIZE as u64,
                got: b.len() as u64,
            });
        }
        if b[0..8] != MAGIC {
            return Err(FormatError::BadMagic);
        }
        let version = u32_at(b, at::VERSION);
        if version != VERSION {
            return Err(FormatError::Version {
                expected: VERSION,
                got: version,
            });
        }
        if u32_at(b, at::ENDIAN) != ENDIAN_CHECK {
            return Err(FormatError::Endianness);
        }
        let stored = u32_at(b, at::HEADER_CRC);
        let computed = crc32fast::hash(&b[..at::HEADER_CRC]);
        if stored != computed {
            return Err(FormatError::HeaderChecksum {
                expected: stored,
                got: computed,
            });
        }
        let size = u32_at(b, at::HEADER_SIZE);
        if size as usize != HEADER_SIZE {
            return Err(HeaderError::Size(size).into());
        }
        Ok(())
    }

    /// Reads the fields of a header that passed [`Header::check_frame`]
    /// and checks them on their own: the flags, the preset, the scene tag,
    /// the bounds, the counts (and that they add up) and the depth. The
    /// section table is read, not checked ([`Header::section_ranges`]).
    pub(crate) fn from_bytes(b: &[u8]) -> Result<Header, HeaderError> {
        let flags = u32_at(b, at::FLAGS);
        if flags & !FLAG_REORDERED != 0 {
            return Err(HeaderError::Flags(flags));
        }
        let preset = u32_at(b, at::PRESET);
        let preset = Preset::from_u32(preset).ok_or(HeaderError::Preset(preset))?;
        let f64_at = |at: usize| f64::from_bits(u64_at(b, at));
        let f32_at = |at: usize| f32::from_bits(u32_at(b, at));
        let config = FileConfig {
            k_t: f64_at(at::K_T),
            k_i: f64_at(at::K_I),
            lambda_empty: f64_at(at::LAMBDA_EMPTY),
            depth_limit: u32_at(b, at::DEPTH_LIMIT),
            split_price: f64_at(at::SPLIT_PRICE),
            preset,
            tau_occu: f32_at(at::TAU_OCCU),
            tau_freq: f32_at(at::TAU_FREQ),
            max_t2rn: u32_at(b, at::MAX_T2RN),
            scene: SceneTag::from_header(b)?,
        };
        let counts = TreeFigures {
            words: u64_at(b, at::WORDS),
            inner: u64_at(b, at::INNER),
            t_inner: u64_at(b, at::T_INNER),
            leaves: u64_at(b, at::LEAVES),
            implicit_empty: u64_at(b, at::IMPLICIT_EMPTY),
            one_leaves: u64_at(b, at::ONE_LEAVES),
            idx32: u64_at(b, at::IDX32),
            idx16: u64_at(b, at::IDX16),
            triangles: u64_at(b, at::TRIANGLES),
            vertices: u64_at(b, at::VERTICES),
        };
        let f = |k: usize| f32_at(at::BOUNDS + 4 * k);
        let bounds = Aabb::new(Vec3::new(f(0), f(1), f(2)), Vec3::new(f(3), f(4), f(5)));
        if !is_finite_box(bounds) {
            return Err(HeaderError::Bounds);
        }
        if counts.words == 0 || counts.words > super::node::MAX_NODES {
            return Err(HeaderError::Words(counts.words));
        }
        if counts.triangles > u64::from(u32::MAX) || counts.vertices > u64::from(u32::MAX) {
            return Err(HeaderError::TooManyTriangles);
        }
        if !counts.add_up() {
            return Err(HeaderError::Counts);
        }
        let max_depth = u32_at(b, at::MAX_DEPTH);
        if max_depth > MAX_DEPTH {
            return Err(HeaderError::Depth(max_depth));
        }
        let sections = Section::ALL.map(|s| {
            let e = at::SECTION_TABLE + s as usize * at::SECTION_ENTRY;
            SectionEntry {
                offset: u64_at(b, e),
                len: u64_at(b, e + 8),
                crc: u32_at(b, e + 16),
            }
        });
        Ok(Header {
            reordered: flags & FLAG_REORDERED != 0,
            config,
            max_depth,
            counts,
            bounds,
            sections,
        })
    }

    /// The sections' byte ranges in a file of `file_len` bytes, and where
    /// the file ends: each section as long as the counts say, starting at
    /// the first multiple of 64 at or after the end of the previous one
    /// (the layout is canonical), inside the file; the file ending with
    /// the padding of the last.
    pub(crate) fn section_ranges(
        &self,
        file_len: u64,
    ) -> Result<([Range<usize>; 6], u64), FormatError> {
        let mut ranges: [Range<usize>; 6] = Default::default();
        let mut end_prev = HEADER_SIZE as u64;
        for s in Section::ALL {
            let SectionEntry { offset, len, .. } = self.sections[s as usize];
            let bad = |problem: SectionError| FormatError::Section {
                section: s.name(),
                problem,
            };
            let expected = self
                .counts
                .elements(s, self.reordered)
                .checked_mul(s.elem_size());
            if Some(len) != expected {
                return Err(bad(SectionError::Length(len)));
            }
            let want = end_prev.next_multiple_of(SECTION_ALIGN as u64);
            if offset != want {
                return Err(bad(SectionError::Misplaced {
                    offset,
                    expected: want,
                }));
            }
            let end = offset
                .checked_add(len)
                .ok_or_else(|| bad(SectionError::Overflow))?;
            if end > file_len {
                return Err(FormatError::Truncated {
                    needed: end,
                    got: file_len,
                });
            }
            ranges[s as usize] = offset as usize..end as usize;
            end_prev = end;
        }
        let file_end = end_prev.next_multiple_of(SECTION_ALIGN as u64);
        if file_len < file_end {
            return Err(FormatError::Truncated {
                needed: file_end,
                got: file_len,
            });
        }
        if file_len > file_end {
            return Err(HeaderError::TrailingBytes {
                extra: file_len - file_end,
                end: file_end,
            }
            .into());
        }
        Ok((ranges, file_end))
    }

    /// Checks the bytes of the header `b` that no field holds, and the
    /// tail: the reserved words of the section table and the reserved
    /// header bytes are zero (so that a later version can give them a
    /// meaning), the tail matches its CRC-32, and the split price is a
    /// finite number ≥ 0.
    pub(crate) fn check_tail(&self, b: &[u8]) -> Result<(), HeaderError> {
        let reserved = Section::ALL
            .map(|s| {
                let e = at::SECTION_TABLE + s as usize * at::SECTION_ENTRY + 20;
                (e..e + 4, "the section table's reserved word, bytes")
            })
            .into_iter()
            .chain([(at::RESERVED..at::TAIL_CRC, "header bytes")]);
        for (bytes, what) in reserved {
            if b[bytes.clone()].iter().any(|&x| x != 0) {
                return Err(HeaderError::Reserved { what, bytes });
            }
        }
        if !tail_crc_ok(b) {
            return Err(HeaderError::TailChecksum);
        }
        let mu = self.config.split_price;
        if !(mu.is_finite() && mu >= 0.0) {
            return Err(HeaderError::SplitPrice(mu));
        }
        Ok(())
    }
}

/// The CRC-32 the section table of the header at the start of `b` gives
/// section `s` (what [`KdFile::verify`](super::KdFile::verify) checks).
pub(crate) fn section_crc(b: &[u8], s: Section) -> u32 {
    u32_at(b, at::SECTION_TABLE + s as usize * at::SECTION_ENTRY + 16)
}

/// Whether the header's tail (bytes 356..380, after the checksummed part
/// and the two counts, which are checked against the nodes) matches its
/// CRC-32 at byte 380. Files written before the tail held the split price
/// have zero there and in the whole tail: those pass. Otherwise the stored
/// CRC must be the computed one, so a changed split price cannot go
/// unnoticed.
fn tail_crc_ok(header: &[u8]) -> bool {
    let stored = u32_at(header, at::TAIL_CRC);
    let legacy = stored == 0
        && header[at::SPLIT_PRICE..at::TAIL_CRC]
            .iter()
            .all(|&x| x == 0);
    legacy || stored == crc32fast::hash(&header[at::SPLIT_PRICE..at::TAIL_CRC])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A header reads back as written.
    #[test]
    fn to_bytes_and_from_bytes_agree() {
        let counts = TreeFigures {
            inner: 2,
            t_inner: 1,
            leaves: 4,
            implicit_empty: 1,
            one_leaves: 1,
            idx32: 5,
            idx16: 0,
            triangles: 7,
            vertices: 9,
            words: 7,
        };
        let mut sections = [SectionEntry::default(); 6];
        sections[0] = SectionEntry {
            offset: HEADER_SIZE as u64,
            len: 56,
            crc: 17,
        };
        let header = Header {
            reordered: true,
            config: FileConfig {
                split_price: 0.5,
                preset: Preset::Small,
                ..FileConfig::default()
            },
            max_depth: 3,
            counts,
            bounds: Aabb::new(Vec3::ZERO, Vec3::ONE),
            sections,
        };
        let bytes = header.to_bytes();
        Header::check_frame(&bytes).unwrap();
        let back = Header::from_bytes(&bytes).unwrap();
        assert_eq!(back, header);
        back.check_tail(&bytes).unwrap();
    }
}
