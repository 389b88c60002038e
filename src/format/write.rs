//! Writing a tree and its geometry as a `.kd` file (layout in [`super`]).

use super::node::{self, LEAF16_LIMIT, MAX_LEAF32, MAX_NODES};
use super::{
    ENDIAN_CHECK, FLAG_REORDERED, FormatError, HEADER_CRC, HEADER_SIZE, MAGIC, SECTION_ALIGN,
    SECTION_ENTRY, SECTION_TABLE, Section, VERSION,
};
use crate::scene::TriangleColumns;
use crate::tree::{MAX_DEPTH, Node, TreeIr, TriId};
use std::io::{Seek, SeekFrom, Write};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

/// The build preset recorded in the header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preset {
    Std = 0,
    Fast = 1,
    Small = 2,
    Custom = 3,
}

impl Preset {
    pub fn from_u32(v: u32) -> Option<Preset> {
        [Preset::Std, Preset::Fast, Preset::Small, Preset::Custom]
            .get(v as usize)
            .copied()
    }

    pub fn name(self) -> &'static str {
        ["std", "fast", "small", "custom"][self as usize]
    }
}

/// The build configuration recorded in the header (for the record only:
/// traversal does not depend on it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FileConfig {
    pub k_t: f64,
    pub k_i: f64,
    pub lambda_empty: f64,
    pub depth_limit: u32,
    pub preset: Preset,
    pub tau_occu: f32,
    pub tau_freq: f32,
    pub max_t2rn: u32,
}

impl Default for FileConfig {
    fn default() -> Self {
        FileConfig {
            k_t: 15.0,
            k_i: 20.0,
            lambda_empty: 0.8,
            depth_limit: 0,
            preset: Preset::Std,
            tau_occu: 0.0,
            tau_freq: 0.0,
            max_t2rn: 0,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WriteOptions {
    /// Renumber triangles in Morton order of their centroids, so that the
    /// triangles of a leaf have nearby ids and most leaves fit 2-byte mode.
    pub reorder: bool,
    pub config: FileConfig,
}

/// The Morton order of triangle centroids: `perm[new] = old`.
fn morton_order(scene: &TriangleColumns) -> Vec<u32> {
    let b = scene.bounds();
    let lo = b.min.as_dvec3();
    let ext = (b.max - b.min).as_dvec3();
    let spread = |mut v: u64| {
        // Spread 21 bits to every third bit.
        v &= 0x1f_ffff;
        v = (v | (v << 32)) & 0x1f_0000_0000_ffff;
        v = (v | (v << 16)) & 0x1f_0000_ff00_00ff;
        v = (v | (v << 8)) & 0x100f_00f0_0f00_f00f;
        v = (v | (v << 4)) & 0x10c3_0c30_c30c_30c3;
        v = (v | (v << 2)) & 0x1249_2492_4924_9249;
        v
    };
    let mut keyed: Vec<(u64, u32)> = (0..scene.len() as u32)
        .map(|i| {
            let [a, b2, c] = scene.tri(i);
            let centroid = (a.as_dvec3() + b2.as_dvec3() + c.as_dvec3()) / 3.0;
            let mut code = 0;
            for k in 0..3 {
                let u = if ext[k] > 0.0 {
                    ((centroid[k] - lo[k]) / ext[k]).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                code |= spread((u * f64::from((1u32 << 21) - 1)) as u64) << k;
            }
            (code, i)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// What the layout pass produces.
struct Layout {
    words: Vec<u64>,
    idx32: Vec<u32>,
    idx16: Vec<u16>,
    n_inner: u64,
    n_t_inner: u64,
    n_leaves: u64,
    max_depth: u32,
}

/// Lays out the node words and index arrays. Refuses, rather than writing
/// a file the reader would reject, a tree that does not fit the format
/// (too many nodes, a leaf over [`MAX_LEAF32`] triangles, deeper than
/// [`MAX_DEPTH`]) or that is malformed (a child or leaf list out of range,
/// a node reached twice, an axis over 2, a non-finite split, a triangle id
/// of `n_tris` or more).
fn layout(
    tree: &TreeIr,
    n_tris: usize,
    new_id: &dyn Fn(TriId) -> u32,
) -> Result<Layout, FormatError> {
    let mut out = Layout {
        words: vec![0],
        idx32: Vec::new(),
        idx16: Vec::new(),
        n_inner: 0,
        n_t_inner: 0,
        n_leaves: 0,
        max_depth: 0,
    };
    let too_large = |what: &str| FormatError::TooLarge(what.to_string());
    let bad_node = |i: usize, message: String| FormatError::Node {
        index: i as u64,
        message,
    };
    let bad_tri = |i: usize, t: TriId| FormatError::Index {
        section: "tree",
        position: i as u64,
        message: format!("node {i} lists triangle {} of {n_tris}", t.0),
    };
    // Each IR node is laid out at most once, so a malformed tree (a cycle,
    // shared children) cannot make the loop run away. One bit per node.
    let mut visited = vec![0u64; tree.nodes.len().div_ceil(64)];
    // (IR node, slot in `words`, depth), processed left subtree first.
    let mut stack = vec![(0usize, 0usize, 0u32)];
    let mut ids = Vec::new();
    while let Some((i, slot, depth)) = stack.pop() {
        let Some(&node) = tree.nodes.get(i) else {
            return Err(bad_node(
                i,
                format!("a child outside the {} nodes", tree.nodes.len()),
            ));
        };
        let (word, bit) = (i / 64, 1u64 << (i % 64));
        if visited[word] & bit != 0 {
            return Err(bad_node(i, "reached twice (not a tree)".into()));
        }
        visited[word] |= bit;
        if depth > MAX_DEPTH {
            return Err(too_large(&format!("a node deeper than {MAX_DEPTH}")));
        }
        out.max_depth = out.max_depth.max(depth);
        match node {
            Node::Inner {
                axis,
                pos,
                right,
                t_ref,
            } => {
                if axis > 2 {
                    return Err(bad_node(i, format!("axis {axis}")));
                }
                if !pos.is_finite() {
                    return Err(bad_node(i, "split position is not finite".into()));
                }
                let block = out.words.len();
                let first_child = match t_ref {
                    Some(t) => {
                        if t.0 as usize >= n_tris {
                            return Err(bad_tri(i, t));
                        }
                        out.n_t_inner += 1;
                        out.words.push(node::encode_tref(new_id(t)));
                        block + 1
                    }
                    None => {
                        out.n_inner += 1;
                        block
                    }
                };
                out.words.extend([0, 0]);
                if out.words.len() as u64 > MAX_NODES {
                    return Err(too_large(
                        "more than 2^29 node words (the 4 GiB offset limit)",
                    ));
                }
                out.words[slot] = node::encode_inner(axis, t_ref.is_some(), block as u32, pos);
                stack.push((right.0 as usize, first_child + 1, depth + 1));
                stack.push((i + 1, first_child, depth + 1));
            }
            Node::Leaf { start, count } => {
                // Checked before the list is read: a leaf this large is
                // always in 4-byte mode, whose count field has 27 bits.
                if count > MAX_LEAF32 {
                    return Err(too_large(&format!(
                        "a leaf with {count} triangles (at most 2^27 - 1)"
                    )));
                }
                let list = tree
                    .leaf_tris
                    .get(start as usize..start as usize + count as usize)
                    .ok_or_else(|| {
                        bad_node(
                            i,
                            format!(
                                "leaf list {start}+{count} outside the {} listed triangles",
                                tree.leaf_tris.len()
                            ),
                        )
                    })?;
                if let Some(&t) = list.iter().find(|t| t.0 as usize >= n_tris) {
                    return Err(bad_tri(i, t));
                }
                out.n_leaves += 1;
                ids.clear();
                ids.extend(list.iter().map(|&t| new_id(t)));
                ids.sort_unstable();
                let upper = ids.first().map_or(0, |&t| t >> 16);
                let two_byte =
                    (ids.len() as u32) < LEAF16_LIMIT && ids.iter().all(|&t| t >> 16 == upper);
                out.words[slot] = if two_byte {
                    let first = u32::try_from(out.idx16.len())
                        .map_err(|_| too_large("idx16 over 2^32 entries"))?;
                    out.idx16.extend(ids.iter().map(|&t| t as u16));
                    node::encode_leaf16(ids.len() as u32, upper as u16, first)
                } else {
                    let first = u32::try_from(out.idx32.len())
                        .map_err(|_| too_large("idx32 over 2^32 entries"))?;
                    out.idx32.extend_from_slice(&ids);
                    node::encode_leaf32(ids.len() as u32, first)
                };
            }
        }
    }
    Ok(out)
}

fn put_u32(b: &mut [u8], at: usize, v: u32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

fn put_u64(b: &mut [u8], at: usize, v: u64) {
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
}

/// A file ready to be written: everything checked, the tree laid out, the
/// header filled in but for the section checksums.
struct Prepared<'a> {
    scene: &'a TriangleColumns,
    lay: Layout,
    /// `perm[new] = old` when reordered.
    perm: Option<Vec<u32>>,
    header: [u8; HEADER_SIZE],
    /// Byte length of each section.
    lens: [u64; 6],
}

/// Checks the tree and the scene and lays the tree out (see
/// [`write_to_vec`] for what is refused).
fn prepare<'a>(
    tree: &TreeIr,
    scene: &'a TriangleColumns,
    options: &WriteOptions,
) -> Result<Prepared<'a>, FormatError> {
    let n_tris = scene.len();
    // Refuse what the reader would reject.
    let b = tree.bounds;
    if !(b.min.is_finite() && b.max.is_finite() && b.min.cmple(b.max).all()) {
        return Err(FormatError::Header(
            "scene bounds are not a finite box".into(),
        ));
    }
    if n_tris > u32::MAX as usize || scene.positions.len() > u32::MAX as usize {
        return Err(FormatError::TooLarge(
            "more than 2^32 triangles or vertices".into(),
        ));
    }
    if let Some(p) = scene.positions.iter().position(|p| !p.is_finite()) {
        return Err(FormatError::Index {
            section: "vertices",
            position: p as u64,
            message: "non-finite coordinate".into(),
        });
    }
    let n_vertices = scene.positions.len() as u64;
    if let Some(p) = scene
        .indices
        .iter()
        .position(|t| t.iter().any(|&v| u64::from(v) >= n_vertices))
    {
        return Err(FormatError::Index {
            section: "triangles",
            position: p as u64,
            message: format!("vertex index out of {n_vertices}"),
        });
    }
    let perm: Option<Vec<u32>> = options.reorder.then(|| morton_order(scene));
    let lay = {
        let inverse: Option<Vec<u32>> = perm.as_ref().map(|p| {
            let mut inv = vec![0u32; p.len()];
            for (new, &old) in p.iter().enumerate() {
                inv[old as usize] = new as u32;
            }
            inv
        });
        let new_id = |t: TriId| inverse.as_ref().map_or(t.0, |inv| inv[t.0 as usize]);
        layout(tree, n_tris, &new_id)?
    };

    let mut lens = [0u64; 6];
    lens[Section::Nodes as usize] = lay.words.len() as u64 * 8;
    lens[Section::Idx32 as usize] = lay.idx32.len() as u64 * 4;
    lens[Section::Idx16 as usize] = lay.idx16.len() as u64 * 2;
    lens[Section::Vertices as usize] = n_vertices * 12;
    lens[Section::Triangles as usize] = n_tris as u64 * 12;
    lens[Section::TriMap as usize] = perm.as_ref().map_or(0, |p| p.len() as u64 * 4);

    let mut header = [0u8; HEADER_SIZE];
    header[0..8].copy_from_slice(&MAGIC);
    put_u32(&mut header, 8, VERSION);
    put_u32(&mut header, 12, ENDIAN_CHECK);
    put_u32(&mut header, 16, HEADER_SIZE as u32);
    put_u32(
        &mut header,
        20,
        if perm.is_some() { FLAG_REORDERED } else { 0 },
    );
    let c = &options.config;
    put_u64(&mut header, 24, c.k_t.to_bits());
    put_u64(&mut header, 32, c.k_i.to_bits());
    put_u64(&mut header, 40, c.lambda_empty.to_bits());
    put_u32(&mut header, 48, c.depth_limit);
    put_u32(&mut header, 52, c.preset as u32);
    put_u32(&mut header, 56, c.tau_occu.to_bits());
    put_u32(&mut header, 60, c.tau_freq.to_bits());
    put_u32(&mut header, 64, c.max_t2rn);
    put_u32(&mut header, 68, lay.max_depth);
    put_u64(&mut header, 72, lay.words.len() as u64);
    put_u64(&mut header, 80, lay.n_inner);
    put_u64(&mut header, 88, lay.n_t_inner);
    put_u64(&mut header, 96, lay.n_leaves);
    put_u64(&mut header, 104, lay.idx32.len() as u64);
    put_u64(&mut header, 112, lay.idx16.len() as u64);
    put_u64(&mut header, 120, n_tris as u64);
    put_u64(&mut header, 128, n_vertices);
    for (k, v) in [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z]
        .into_iter()
        .enumerate()
    {
        put_u32(&mut header, 136 + 4 * k, v.to_bits());
    }
    let mut offset = HEADER_SIZE as u64;
    for (s, &len) in lens.iter().enumerate() {
        let entry = SECTION_TABLE + s * SECTION_ENTRY;
        put_u64(&mut header, entry, offset);
        put_u64(&mut header, entry + 8, len);
        offset = (offset + len).next_multiple_of(SECTION_ALIGN as u64);
    }
    Ok(Prepared {
        scene,
        lay,
        perm,
        header,
        lens,
    })
}

impl Prepared<'_> {
    /// Bytes of the whole file.
    fn file_len(&self) -> u64 {
        self.lens.iter().fold(HEADER_SIZE as u64, |at, &len| {
            (at + len).next_multiple_of(SECTION_ALIGN as u64)
        })
    }

    /// Streams the file to `out`, the header as zeros (its checksums are
    /// known only at the end); returns the header, which belongs at
    /// offset 0. Each section is encoded in small pieces, so nothing the
    /// size of a section is held besides the layout itself.
    fn emit(&self, out: &mut impl Write) -> std::io::Result<[u8; HEADER_SIZE]> {
        let mut header = self.header;
        out.write_all(&[0u8; HEADER_SIZE])?;
        let mut sink = SectionSink {
            out,
            buf: Vec::with_capacity(SINK_BUF + 16),
            crc: crc32fast::Hasher::new(),
            len: 0,
        };
        for section in Section::ALL {
            let scene = self.scene;
            match section {
                Section::Nodes => self
                    .lay
                    .words
                    .iter()
                    .try_for_each(|w| sink.put(&w.to_le_bytes())),
                Section::Idx32 => self
                    .lay
                    .idx32
                    .iter()
                    .try_for_each(|w| sink.put(&w.to_le_bytes())),
                Section::Idx16 => self
                    .lay
                    .idx16
                    .iter()
                    .try_for_each(|w| sink.put(&w.to_le_bytes())),
                Section::Vertices => scene.positions.iter().try_for_each(|p| {
                    [p.x, p.y, p.z]
                        .iter()
                        .try_for_each(|v| sink.put(&v.to_le_bytes()))
                }),
                Section::Triangles => (0..scene.len()).try_for_each(|new| {
                    let old = self.perm.as_ref().map_or(new, |p| p[new] as usize);
                    scene.indices[old]
                        .iter()
                        .try_for_each(|v| sink.put(&v.to_le_bytes()))
                }),
                Section::TriMap => self
                    .perm
                    .iter()
                    .flatten()
                    .try_for_each(|w| sink.put(&w.to_le_bytes())),
            }?;
            let (crc, len) = sink.finish_section()?;
            debug_assert_eq!(len, self.lens[section as usize]);
            let entry = SECTION_TABLE + section as usize * SECTION_ENTRY;
            put_u32(&mut header, entry + 16, crc);
        }
        let crc = crc32fast::hash(&header[..HEADER_CRC]);
        put_u32(&mut header, HEADER_CRC, crc);
        Ok(header)
    }
}

/// Bytes buffered per write by [`SectionSink`].
const SINK_BUF: usize = 1 << 20;

/// Writes one section after another, each checksummed and padded to
/// [`SECTION_ALIGN`].
struct SectionSink<'w, W: Write> {
    out: &'w mut W,
    buf: Vec<u8>,
    crc: crc32fast::Hasher,
    /// Bytes of the current section so far.
    len: u64,
}

impl<W: Write> SectionSink<'_, W> {
    #[inline]
    fn put(&mut self, bytes: &[u8]) -> std::io::Result<()> {
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
        // The sections start at HEADER_SIZE, a multiple of SECTION_ALIGN,
        // and every one is padded, so the section's own length decides.
        let pad = len.next_multiple_of(SECTION_ALIGN as u64) - len;
        self.out.write_all(&[0u8; SECTION_ALIGN][..pad as usize])?;
        Ok((crc, len))
    }
}

/// Serialises a tree and its scene into the bytes of a `.kd` file.
///
/// Never writes a file that [`KdFile::from_bytes`](super::KdFile::from_bytes)
/// would reject: a tree that does not fit the format
/// ([`FormatError::TooLarge`]), a malformed tree (a child or leaf list out of
/// range, a node reached twice, an axis over 2, a non-finite split, a
/// triangle id out of range) or scene (non-finite bounds or vertices, a
/// vertex index out of range) is an error, never a panic. The tree need not
/// pass [`TreeIr::validate`] otherwise: leaves may repeat a triangle.
pub fn write_to_vec(
    tree: &TreeIr,
    scene: &TriangleColumns,
    options: &WriteOptions,
) -> Result<Vec<u8>, FormatError> {
    let file = prepare(tree, scene, options)?;
    let mut out = Vec::with_capacity(file.file_len() as usize);
    let header = file.emit(&mut out).expect("writing to a Vec cannot fail");
    out[..HEADER_SIZE].copy_from_slice(&header);
    debug_assert_eq!(out.len() as u64, file.file_len());
    Ok(out)
}

/// Distinguishes the temporary files of concurrent writes in one process.
static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes a `.kd` file atomically: a temporary file in the same directory
/// (a fresh name per call, so concurrent writes to one path never share
/// it), fsync, rename, then a best-effort fsync of the directory. A failed
/// or killed write leaves no file at `path` (and never a half-written one
/// that could pass for valid); a failed write removes its temporary file.
/// The bytes are those of [`write_to_vec`], streamed to the file rather
/// than built in memory: the header goes last, at offset 0, once the
/// section checksums are known.
pub fn write_file(
    path: &Path,
    tree: &TreeIr,
    scene: &TriangleColumns,
    options: &WriteOptions,
) -> Result<(), FormatError> {
    let file = prepare(tree, scene, options)?;
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    let name = path
        .file_name()
        .ok_or_else(|| io(std::io::Error::other("not a file name")))?;
    // A name left behind by a killed writer is skipped, never reused.
    let mut attempt = 0;
    let (tmp, mut f) = loop {
        let tmp = dir.join(format!(
            ".{}.tmp.{}.{}",
            name.to_string_lossy(),
            std::process::id(),
            TMP_COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(f) => break (tmp, f),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && attempt < 100 => {
                attempt += 1;
            }
            Err(e) => return Err(io(e)),
        }
    };
    let result = (|| {
        // `emit` writes in pieces of about `SINK_BUF` bytes.
        let header = file.emit(&mut f)?;
        f.seek(SeekFrom::Start(0))?;
        f.write_all(&header)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(io(e));
    }
    // Make the rename durable; not every platform can open a directory.
    if let Ok(d) = std::fs::File::open(&dir) {
        let _ = d.sync_all();
    }
    Ok(())
}
