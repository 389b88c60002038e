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
//! Reading checks, before trusting anything: the exact length implied by
//! the counts (so a corrupt count never makes a huge allocation), the
//! magic, the version, the checksum, then what an OBJ load guarantees:
//! finite coordinates, indices in range, no degenerate triangle, at least
//! one triangle. A failure is a [`SceneError`] naming the file. Writing is
//! atomic ([`crate::fsio::write_atomically`]).

use super::{LoadSummary, SceneError, TriangleColumns};
use glam::Vec3;
use std::io::{Read, Write};
use std::path::Path;

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

/// Reads a scene cache.
pub fn load_scene_cache(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let bad = |message: String| SceneError::Invalid {
        path: path.to_path_buf(),
        message: format!("not a valid scene cache: {message}"),
    };
    let mut file = crate::fsio::open_regular(path).map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    let mut header = [0u8; HEADER];
    if len < HEADER as u64 + 4 {
        return Err(bad(format!("{len} bytes is shorter than the header")));
    }
    file.read_exact(&mut header).map_err(io)?;
    if header[..8] != MAGIC {
        return Err(bad("wrong magic bytes".into()));
    }
    let word = |at: usize| u32::from_le_bytes(header[at..at + 4].try_into().expect("4 bytes"));
    let long = |at: usize| u64::from_le_bytes(header[at..at + 8].try_into().expect("8 bytes"));
    if word(8) != VERSION {
        return Err(bad(format!(
            "version {} (this build reads {VERSION})",
            word(8)
        )));
    }
    let (n_v, n_t) = (long(16), long(24));
    let want = n_v
        .checked_add(n_t)
        .and_then(|n| n.checked_mul(12))
        .and_then(|n| n.checked_add(HEADER as u64 + 4));
    if want != Some(len) {
        return Err(bad(format!(
            "{len} bytes, but {n_v} vertices and {n_t} triangles need {}",
            want.map_or("more than 2^64".to_string(), |w| w.to_string())
        )));
    }
    // The length check bounds both counts by the file size.
    let mut crc = crc32fast::Hasher::new();
    crc.update(&header);
    let positions: Vec<[f32; 3]> = read_triples(&mut file, n_v as usize, &mut crc).map_err(io)?;
    let indices: Vec<[u32; 3]> = read_triples(&mut file, n_t as usize, &mut crc).map_err(io)?;
    let mut stored = [0u8; 4];
    file.read_exact(&mut stored).map_err(io)?;
    if crc.finalize() != u32::from_le_bytes(stored) {
        return Err(bad("checksum mismatch (the file is corrupt)".into()));
    }
    let positions = positions.into_iter().map(Vec3::from_array).collect();
    let mut scene = TriangleColumns::new(positions, indices).map_err(|e| bad(e.to_string()))?;
    if scene.is_empty() {
        return Err(bad("no triangles".into()));
    }
    if scene.drop_degenerate() > 0 {
        return Err(bad("it holds degenerate triangles".into()));
    }
    let summary = LoadSummary {
        triangles: scene.len(),
        vertices: scene.positions.len(),
        dropped_degenerate: long(32) as usize,
        lines: long(40),
    };
    Ok((scene, summary))
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
        }
        for bit in 0..bytes.len() * 8 {
            let mut b = bytes.clone();
            b[bit / 8] ^= 1 << (bit % 8);
            std::fs::write(&bad, &b).unwrap();
            // The reserved word is not checked against a value, but the
            // checksum covers it.
            let e = load_scene_cache(&bad).expect_err("a flipped bit");
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
        s.positions[0].x = f32::NAN;
        write_scene_cache(&path, &s, &m).unwrap();
        let e = load_scene_cache(&path).unwrap_err().to_string();
        assert!(e.contains("non-finite"), "{e}");
        let (mut s, m) = scene();
        s.indices[0] = [0, 0, 1];
        write_scene_cache(&path, &s, &m).unwrap();
        let e = load_scene_cache(&path).unwrap_err().to_string();
        assert!(e.contains("degenerate"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
