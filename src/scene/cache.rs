//! The binary scene cache (`.kds`): a loaded scene's columns exactly as
//! they are in memory, so that a huge scene's OBJ is parsed once
//! (`slimkd convert scene.obj -o scene.kds`) and every later command reads
//! the columns back with a few large reads instead of parsing text
//! (stk_all, 6.2 M triangles: about 10 s of OBJ parsing against well under
//! a second).
//!
//! Consumes a `.kds` path. Produces the same [`TriangleColumns`] and
//! [`LoadSummary`] as loading the OBJ it was converted from: the positions
//! and indices after dropping degenerate triangles, bit for bit, so every
//! builder builds the same tree from either.
//!
//! Layout (all little-endian; `V` vertices, `T` triangles):
//!
//! | offset | bytes | field |
//! |---|---|---|
//! | 0 | 8 | magic `b"SLIMKDS\0"` |
//! | 8 | 4 | version, 1 |
//! | 12 | 4 | reserved, 0 |
//! | 16 | 8 | `V` |
//! | 24 | 8 | `T` |
//! | 32 | 8 | degenerate triangles dropped from the source |
//! | 40 | 8 | lines of the source |
//! | 48 | 12·V | positions: `f32` x, y, z |
//! | 48 + 12·V | 12·T | indices: three `u32` per triangle |
//! | 48 + 12·(V + T) | 4 | CRC-32 ([`crc32fast`]) of every byte before it |
//!
//! The columns start at offsets that are multiples of 4 (48 and
//! 48 + 12·V), so in a mapping, which starts on a page, they are aligned
//! for `f32` and `u32` and [`load_scene_cache`] uses them in place (a cast,
//! no copy); [`read_scene_cache`] reads them into memory instead.
//!
//! Opening checks, before trusting anything: the exact length implied by
//! the counts (so a corrupt count never makes a huge allocation), the
//! magic, the version, the checksum, then what an OBJ load guarantees:
//! finite coordinates and no `-0.0`, indices in range, no degenerate
//! triangle, at least one triangle. A failure is a [`SceneError`] naming
//! the file. Writing is atomic ([`crate::fsio::write_atomically`]).

use super::{Column, LoadSummary, SceneError, TriangleColumns};
use glam::Vec3;
use std::io::{Read, Write};
use std::path::Path;
use std::sync::Arc;

/// The file name extension of scene caches.
pub const EXTENSION: &str = "kds";
pub(crate) const MAGIC: [u8; 8] = *b"SLIMKDS\0";
const VERSION: u32 = 1;
const HEADER: usize = 48;

/// Writes `scene` (and the `summary` of the load that produced it) to
/// `path` as a scene cache.
pub fn write_scene_cache(
    path: &Path,
    scene: &TriangleColumns,
    summary: &LoadSummary,
) -> Result<(), SceneError> {
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut header = Vec::with_capacity(HEADER);
    header.extend_from_slice(&MAGIC);
    header.extend_from_slice(&VERSION.to_le_bytes());
    header.extend_from_slice(&0u32.to_le_bytes());
    for x in [
        scene.positions.len(),
        scene.indices.len(),
        summary.dropped_degenerate,
    ] {
        header.extend_from_slice(&(x as u64).to_le_bytes());
    }
    header.extend_from_slice(&summary.lines.to_le_bytes());
    crate::fsio::write_atomically(path, io, |file| {
        let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
        let mut crc = crc32fast::Hasher::new();
        let mut put = |bytes: &[u8]| {
            crc.update(bytes);
            w.write_all(bytes)
        };
        put(&header).map_err(io)?;
        let mut buf = Vec::with_capacity(12 << 16);
        for chunk in scene.positions.chunks(1 << 16) {
            le_words(
                chunk.iter().flat_map(|p| p.to_array().map(f32::to_bits)),
                &mut buf,
            );
            put(&buf).map_err(io)?;
        }
        for chunk in scene.indices.chunks(1 << 16) {
            le_words(chunk.iter().flatten().copied(), &mut buf);
            put(&buf).map_err(io)?;
        }
        w.write_all(&crc.finalize().to_le_bytes()).map_err(io)?;
        w.flush().map_err(io)
    })
}

/// Replaces `out` with the little-endian bytes of `words`.
fn le_words(words: impl Iterator<Item = u32>, out: &mut Vec<u8>) {
    out.clear();
    for w in words {
        out.extend_from_slice(&w.to_le_bytes());
    }
}

/// Opens a scene cache: maps the file and uses its columns where they
/// lie, so they are file-backed pages the kernel can drop (and read
/// again), not anonymous memory; on a big-endian machine, where the
/// little-endian columns cannot be used as they are, reads them instead
/// ([`read_scene_cache`]).
///
/// The whole file is checked first, as [`read_scene_cache`] checks it:
/// length, magic, version, checksum, the column invariant, no degenerate
/// triangle. The checksum stays part of every open: the invariant checks
/// read every page anyway (mapping saves the copy, not the read), the
/// CRC-32 adds little to them (1 ms for stk_black_forest's 27.6 MB cache,
/// whose open takes about 0.1 s), and only the checksum catches a corrupt
/// index that is still in range, which would build a tree of the wrong
/// scene. The map is populated at once (`MAP_POPULATE`), since the checks
/// fault in every page anyway.
///
/// **Soundness.** As for a mapped `.kd` file (`KdFile::open`, one layer
/// up, in the file format): the file must not be modified or
/// truncated in place while the columns are alive. slimkd writes caches by
/// atomic rename, so rewriting one with `slimkd convert` leaves an open map
/// intact; a file changed in place by another program can change the
/// columns under the reader (every index into them is bounds-checked, so
/// that is a wrong result or a panic, not an out-of-bounds read), and a
/// truncated one ends the process with SIGBUS. Where that may happen, read
/// the file instead ([`read_scene_cache`], the CLI's `--no-mmap`).
pub fn load_scene_cache(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    if cfg!(target_endian = "big") {
        return read_scene_cache(path);
    }
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = crate::fsio::open_regular(path).map_err(io)?;
    // SAFETY: the map is read-only and private to this process; the
    // remaining precondition (nobody modifies or truncates the file in
    // place while it is mapped) is the caller's, documented above.
    let map = Arc::new(unsafe { memmap2::MmapOptions::new().populate().map(&file) }.map_err(io)?);
    let bytes: &[u8] = &map;
    let header = Header::parse(path, bytes.len() as u64, bytes.get(..HEADER))?;
    let body = bytes.len() - 4;
    let stored = u32::from_le_bytes(bytes[body..].try_into().expect("4 bytes"));
    if crc32fast::hash(&bytes[..body]) != stored {
        return Err(bad(path, "checksum mismatch (the file is corrupt)".into()));
    }
    // The length check bounds both counts by the file size, and the map
    // starts on a page, so both columns are 4-byte aligned.
    let (n_v, n_t) = (header.n_v as usize, header.n_t as usize);
    let misplaced = || bad(path, "a column is not aligned in memory".into());
    let positions = Column::mapped(map.clone(), HEADER, n_v).ok_or_else(misplaced)?;
    let indices = Column::mapped(map, HEADER + 12 * n_v, n_t).ok_or_else(misplaced)?;
    let scene =
        TriangleColumns::checked(positions, indices).map_err(|e| bad(path, e.to_string()))?;
    header.finish(path, scene)
}

/// The fixed-size start of a scene cache, checked against the file length.
struct Header {
    n_v: u64,
    n_t: u64,
    dropped: u64,
    lines: u64,
}

impl Header {
    /// Checks the header bytes (`None`: the file is shorter than a header)
    /// of a file of `len` bytes: magic, version, and the exact length the
    /// counts imply.
    fn parse(path: &Path, len: u64, header: Option<&[u8]>) -> Result<Header, SceneError> {
        let header = match header {
            Some(h) if len >= HEADER as u64 + 4 => h,
            _ => {
                return Err(bad(path, format!("{len} bytes is shorter than the header")));
            }
        };
        if header[..8] != MAGIC {
            return Err(bad(path, "wrong magic bytes".into()));
        }
        let word = |at: usize| u32::from_le_bytes(header[at..at + 4].try_into().expect("4 bytes"));
        let long = |at: usize| u64::from_le_bytes(header[at..at + 8].try_into().expect("8 bytes"));
        if word(8) != VERSION {
            return Err(bad(
                path,
                format!("version {} (this build reads {VERSION})", word(8)),
            ));
        }
        let (n_v, n_t) = (long(16), long(24));
        let want = n_v
            .checked_add(n_t)
            .and_then(|n| n.checked_mul(12))
            .and_then(|n| n.checked_add(HEADER as u64 + 4));
        if want != Some(len) {
            return Err(bad(
                path,
                format!(
                    "{len} bytes, but {n_v} vertices and {n_t} triangles need {}",
                    want.map_or("more than 2^64".to_string(), |w| w.to_string())
                ),
            ));
        }
        Ok(Header {
            n_v,
            n_t,
            dropped: long(32),
            lines: long(40),
        })
    }

    /// The checks of what an OBJ load guarantees beyond the invariant, and
    /// the load's summary.
    fn finish(
        &self,
        path: &Path,
        mut scene: TriangleColumns,
    ) -> Result<(TriangleColumns, LoadSummary), SceneError> {
        if scene.is_empty() {
            return Err(bad(path, "no triangles".into()));
        }
        if scene.drop_degenerate() > 0 {
            return Err(bad(path, "it holds degenerate triangles".into()));
        }
        let summary = LoadSummary {
            triangles: scene.len(),
            vertices: scene.positions.len(),
            dropped_degenerate: self.dropped as usize,
            lines: self.lines,
        };
        Ok((scene, summary))
    }
}

/// A scene cache that failed a check.
fn bad(path: &Path, message: String) -> SceneError {
    SceneError::Invalid {
        path: path.to_path_buf(),
        message: format!("not a valid scene cache: {message}"),
    }
}

/// Reads a scene cache into memory (anonymous pages, as large as its
/// columns), with the checks of [`load_scene_cache`], so that nothing done
/// to the file afterwards reaches the columns.
pub fn read_scene_cache(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = crate::fsio::open_regular(path).map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    let mut head = [0u8; HEADER];
    let got = if len >= HEADER as u64 + 4 {
        file.read_exact(&mut head).map_err(io)?;
        Some(&head[..])
    } else {
        None
    };
    let header = Header::parse(path, len, got)?;
    let mut crc = crc32fast::Hasher::new();
    crc.update(&head);
    let positions: Vec<[f32; 3]> =
        read_triples(&mut file, header.n_v as usize, &mut crc).map_err(io)?;
    let indices: Vec<[u32; 3]> =
        read_triples(&mut file, header.n_t as usize, &mut crc).map_err(io)?;
    let mut stored = [0u8; 4];
    file.read_exact(&mut stored).map_err(io)?;
    if crc.finalize() != u32::from_le_bytes(stored) {
        return Err(bad(path, "checksum mismatch (the file is corrupt)".into()));
    }
    let positions = positions.into_iter().map(Vec3::from_array).collect();
    let scene = TriangleColumns::checked(Column::Owned(positions), Column::Owned(indices))
        .map_err(|e| bad(path, e.to_string()))?;
    header.finish(path, scene)
}

/// Reads `n` triples of little-endian 4-byte values, feeding the bytes to
/// `crc`.
fn read_triples<T: bytemuck::Pod + Default>(
    r: &mut impl Read,
    n: usize,
    crc: &mut crc32fast::Hasher,
) -> std::io::Result<Vec<[T; 3]>> {
    let mut out = Vec::new();
    crate::sys::try_reserve(&mut out, n, "a column of the scene cache")
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::OutOfMemory, e.to_string()))?;
    out.resize(n, [T::default(); 3]);
    for chunk in out.chunks_mut(1 << 16) {
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(chunk);
        r.read_exact(bytes)?;
        crc.update(bytes);
        for word in bytemuck::cast_slice_mut::<u8, [u8; 4]>(bytes) {
            *word = u32::from_le_bytes(*word).to_ne_bytes();
        }
    }
    Ok(out)
}

/// Whether `path` names a scene cache (by its extension).
pub fn is_scene_cache(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case(EXTENSION))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh directory for one test.
    fn tmp(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("slimkd-kds-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn scene() -> (TriangleColumns, LoadSummary) {
        let text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 2 2 2\nf 1 2 3\nf 1 2 4\nf 1 1 5\n";
        super::super::load_obj_bytes(Path::new("t.obj"), text).unwrap()
    }

    #[test]
    fn round_trip_is_exact() {
        let dir = tmp("rt");
        let path = dir.join("a.kds");
        let (s, m) = scene();
        assert_eq!(m.dropped_degenerate, 1);
        write_scene_cache(&path, &s, &m).unwrap();
        let (s2, m2) = load_scene_cache(&path).unwrap();
        assert_eq!(s2, s);
        assert_eq!(m2, m);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_cache_is_mapped_and_reads_like_the_copy() {
        let dir = tmp("map");
        let path = dir.join("a.kds");
        let (s, m) = scene();
        write_scene_cache(&path, &s, &m).unwrap();
        let (mapped, m1) = load_scene_cache(&path).unwrap();
        let (read, m2) = read_scene_cache(&path).unwrap();
        assert_eq!(mapped.is_mapped(), cfg!(target_endian = "little"));
        assert!(!read.is_mapped());
        assert_eq!((&mapped, &m1), (&s, &m));
        assert_eq!((&read, &m2), (&s, &m));
        // A change copies the mapped column out; the file is untouched.
        let mut changed = mapped.clone();
        changed.positions.to_mut()[0].x = 7.0;
        assert!(!changed.positions.is_mapped());
        assert_eq!(mapped, s);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A mapped column cannot be changed, so a `-0.0` (which the writer
    /// never writes, as columns hold `+0.0`) must be refused at open, not
    /// reach a builder whose equal split planes need equal bits.
    #[test]
    fn a_negative_zero_in_a_cache_is_an_error() {
        let dir = tmp("nz");
        let path = dir.join("nz.kds");
        let (mut s, m) = scene();
        s.positions.to_mut()[4].y = -0.0;
        write_scene_cache(&path, &s, &m).unwrap();
        for e in [
            load_scene_cache(&path).unwrap_err(),
            read_scene_cache(&path).unwrap_err(),
        ] {
            let e = e.to_string();
            assert!(e.contains("nz.kds") && e.contains("-0.0"), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn every_truncation_and_bit_flip_is_an_error() {
        let dir = tmp("bad");
        let good = dir.join("good.kds");
        let (s, m) = scene();
        write_scene_cache(&good, &s, &m).unwrap();
        let bytes = std::fs::read(&good).unwrap();
        assert_eq!(bytes.len(), HEADER + 12 * (5 + 2) + 4);
        let bad = dir.join("bad.kds");
        for cut in 0..bytes.len() {
            std::fs::write(&bad, &bytes[..cut]).unwrap();
            let e = load_scene_cache(&bad).expect_err("a truncated file");
            assert!(e.to_string().contains("bad.kds"), "{e}");
            let e = read_scene_cache(&bad).expect_err("a truncated file");
            assert!(e.to_string().contains("bad.kds"), "{e}");
        }
        for bit in 0..bytes.len() * 8 {
            let mut b = bytes.clone();
            b[bit / 8] ^= 1 << (bit % 8);
            std::fs::write(&bad, &b).unwrap();
            // The reserved word is not checked against a value, but the
            // checksum covers it.
            let e = load_scene_cache(&bad).expect_err("a flipped bit");
            assert!(e.to_string().contains("bad.kds"), "{e}");
            let e = read_scene_cache(&bad).expect_err("a flipped bit");
            assert!(e.to_string().contains("bad.kds"), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_valid_checksum_does_not_admit_bad_geometry() {
        let dir = tmp("geo");
        let path = dir.join("nan.kds");
        let (mut s, m) = scene();
        // Written through the writer, so the checksum is right.
        s.positions.to_mut()[0].x = f32::NAN;
        write_scene_cache(&path, &s, &m).unwrap();
        let e = load_scene_cache(&path).unwrap_err().to_string();
        assert!(e.contains("non-finite"), "{e}");
        let e = read_scene_cache(&path).unwrap_err().to_string();
        assert!(e.contains("non-finite"), "{e}");
        let (mut s, m) = scene();
        s.indices.to_mut()[0] = [0, 0, 1];
        write_scene_cache(&path, &s, &m).unwrap();
        let e = load_scene_cache(&path).unwrap_err().to_string();
        assert!(e.contains("degenerate"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
