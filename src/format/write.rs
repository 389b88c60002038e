//! Writing a tree and its geometry as a `.kd` file (layout in [`super`]).

use super::node::{self, MAX_LEAF32, MAX_NODES};
use super::{
    ENDIAN_CHECK, FLAG_REORDERED, FormatError, HEADER_CRC, HEADER_SIZE, MAGIC, SECTION_ALIGN,
    SECTION_ENTRY, SECTION_TABLE, Section, VERSION,
};
use crate::scene::TriangleColumns;
use crate::tree::{MAX_DEPTH, Node, TreeIr, TriId};
use std::io::Write;
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
    // shared children) cannot make the loop run away.
    let mut visited = vec![false; tree.nodes.len()];
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
        if std::mem::replace(&mut visited[i], true) {
            return Err(bad_node(i, "reached twice (not a tree)".into()));
        }
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
                out.words[slot] = if node::fits_leaf16(ids.len(), ids.iter().copied()) {
                    let upper = ids.first().map_or(0, |&t| t >> 16);
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
    let perm: Option<Vec<u32>> = options.reorder.then(|| scene.morton_order());
    let inverse: Option<Vec<u32>> = perm.as_ref().map(|p| {
        let mut inv = vec![0u32; p.len()];
        for (new, &old) in p.iter().enumerate() {
            inv[old as usize] = new as u32;
        }
        inv
    });
    let new_id = |t: TriId| inverse.as_ref().map_or(t.0, |inv| inv[t.0 as usize]);
    let lay = layout(tree, n_tris, &new_id)?;

    let mut sections: [Vec<u8>; 6] = Default::default();
    sections[Section::Nodes as usize] = lay.words.iter().flat_map(|w| w.to_le_bytes()).collect();
    sections[Section::Idx32 as usize] = lay.idx32.iter().flat_map(|w| w.to_le_bytes()).collect();
    sections[Section::Idx16 as usize] = lay.idx16.iter().flat_map(|w| w.to_le_bytes()).collect();
    sections[Section::Vertices as usize] = scene
        .positions
        .iter()
        .flat_map(|p| [p.x, p.y, p.z])
        .flat_map(f32::to_le_bytes)
        .collect();
    sections[Section::Triangles as usize] = (0..n_tris)
        .map(|new| perm.as_ref().map_or(new, |p| p[new] as usize))
        .flat_map(|old| scene.indices[old])
        .flat_map(u32::to_le_bytes)
        .collect();
    if let Some(p) = &perm {
        sections[Section::TriMap as usize] = p.iter().flat_map(|w| w.to_le_bytes()).collect();
    }

    let mut header = vec![0u8; HEADER_SIZE];
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
    put_u64(&mut header, 128, scene.positions.len() as u64);
    for (k, v) in [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z]
        .into_iter()
        .enumerate()
    {
        put_u32(&mut header, 136 + 4 * k, v.to_bits());
    }
    let mut offset = HEADER_SIZE;
    for (s, bytes) in sections.iter().enumerate() {
        let entry = SECTION_TABLE + s * SECTION_ENTRY;
        put_u64(&mut header, entry, offset as u64);
        put_u64(&mut header, entry + 8, bytes.len() as u64);
        put_u32(&mut header, entry + 16, crc32fast::hash(bytes));
        offset = (offset + bytes.len()).next_multiple_of(SECTION_ALIGN);
    }
    let crc = crc32fast::hash(&header[..HEADER_CRC]);
    put_u32(&mut header, HEADER_CRC, crc);

    let mut out = Vec::with_capacity(offset);
    out.extend_from_slice(&header);
    for bytes in &sections {
        out.extend_from_slice(bytes);
        out.resize(out.len().next_multiple_of(SECTION_ALIGN), 0);
    }
    Ok(out)
}

/// Distinguishes the temporary files of concurrent writes in one process.
static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes a `.kd` file atomically: a temporary file in the same directory
/// (a fresh name per call, so concurrent writes to one path never share
/// it), fsync, rename, then a best-effort fsync of the directory. A failed
/// or killed write leaves no file at `path` (and never a half-written one
/// that could pass for valid); a failed write removes its temporary file.
pub fn write_file(
    path: &Path,
    tree: &TreeIr,
    scene: &TriangleColumns,
    options: &WriteOptions,
) -> Result<(), FormatError> {
    let bytes = write_to_vec(tree, scene, options)?;
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
        f.write_all(&bytes)?;
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
