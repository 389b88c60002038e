//! Scenes: loading triangle meshes into structure-of-arrays columns.
//!
//! Consumes Wavefront OBJ files (`obj`, one pass straight into the
//! columns), PLY files, ASCII or binary of either byte order (`ply`, through `ply-rs-bw`), glTF 2.0
//! files, `.gltf` with embedded or side buffers or `.glb` (`gltf`, through
//! the `gltf` crate), OBJ and PLY compressed with gzip (`.obj.gz`,
//! `.ply.gz`, through `flate2`), or the binary scene cache (`.kds`,
//! `cache`) that `slimkd convert` makes of any of them so that a huge scene
//! is parsed once. [`load`] picks the format by the file name
//! ([`SceneFormat::of_path`]); a name it does not know is an error that
//! lists the ones it does, and a slimkd `.kd` tree file given as a scene
//! is recognised (by its magic bytes or name) and named as such. Produces
//! [`TriangleColumns`]: one column of vertex positions and one column of
//! vertex-index triples, in file order.
//!
//! The rules below are those of OBJ; the other formats' modules say how
//! each maps onto them. What every format shares: bad input is an error
//! naming the file and the line (text formats) or the element, record or
//! mesh (binary ones); a NaN or infinite coordinate is an error; degenerate
//! triangles are dropped and counted; a scene without triangles is an
//! error; loading never panics.
//!
//! **What is read (OBJ).**
//! - `v x y z`, optionally followed by a weight `w` (the position is
//!   `(x/w, y/w, z/w)`, computed in `f32`) or by a colour `r g b` (ignored).
//! - `f` with every index form `v`, `v/vt`, `v//vn`, `v/vt/vn`, mixed
//!   freely. A negative index is relative: `-1` is the last vertex
//!   (texture coordinate, normal) defined before the line. A positive index
//!   may refer to a vertex defined later in the file. Polygons are
//!   fan-triangulated: `(v0, v1, v2), (v0, v2, v3), ...`. A face of one or
//!   two vertices is ignored.
//! - `vt` (1 to 3 numbers) and `vn` (3 numbers) lines are checked and
//!   counted, so that face indices into them can be checked, and otherwise
//!   unused.
//! - Everything else (`o`, `g`, `s`, `l`, `p`, `mtllib`, `usemtl`, ...) is
//!   ignored; objects and groups do not change the order of triangles, and
//!   no material file is opened. `#` starts a comment, at the start of a
//!   line or after a statement. Lines end in LF or CRLF; words are
//!   separated by any whitespace; a UTF-8 byte-order mark at the start of
//!   the file is skipped.
//!
//! **Input rule.** Bad input is an error that names the file and, where it
//! applies, the line (1-based): an unreadable file, text that is not UTF-8
//! (anywhere, comments included), a `v`, `vt`, `vn` or `f` line that does
//! not parse (a word that is not a number, the wrong number of values, an
//! index 0, a face vertex of more than three parts or without a vertex
//! index, an `f` line without vertices), a vertex weight of zero, a NaN or
//! infinite coordinate (including a number too large for `f32`, and one
//! made so by the weight), a face index out of range (a relative index
//! before the first element, or an index past the last element of the
//! file; reported at the face's line), and a file with no triangles.
//! Loading never panics.
//!
//! **Degenerate rule.** A triangle whose vertices are repeated or collinear
//! (twice its area, computed in `f64` from the `f32` positions, is exactly
//! zero) can never be hit by the watertight test, so it is *dropped and
//! counted* ([`LoadSummary::dropped_degenerate`]). The vertex column holds
//! the vertices the faces use, in the order of their first use (no
//! welding; vertices no face uses are left out).

mod cache;
mod column;
mod gltf;
mod obj;
mod ply;

pub use self::gltf::{load_gltf, load_gltf_bytes};
pub use cache::{is_scene_cache, load_scene_cache, read_scene_cache, write_scene_cache};
pub use obj::{embedded_name, load_obj, load_obj_bytes, load_obj_with_progress};
pub use ply::{load_ply, load_ply_bytes};

use crate::geom::{Aabb, double_area};
use crate::progress::Progress;
use column::Column;
use glam::Vec3;
use rayon::prelude::*;
use std::fmt;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

/// Triangles as columns.
///
/// Invariant: every index in `indices` is `< positions.len()`, every
/// position is finite, and `indices.len() < u32::MAX` (triangle ids fit a
/// `u32`), and no coordinate is `-0.0`. The columns are in memory, or
/// mapped from a `.kds` scene cache ([`load_scene_cache`]); they read the
/// same either way.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleColumns {
    positions: Column<Vec3>,
    indices: Column<[u32; 3]>,
}

impl TriangleColumns {
    /// Builds columns from positions and index triples, checking the
    /// invariant. A coordinate of -0.0 becomes +0.0, so that equal split
    /// planes always have equal bits.
    pub fn new(
        mut positions: Vec<Vec3>,
        indices: Vec<[u32; 3]>,
    ) -> Result<TriangleColumns, InvalidColumns> {
        for p in &mut positions {
            *p += 0.0;
        }
        TriangleColumns::checked(Column::Owned(positions), Column::Owned(indices))
    }

    /// Columns whose storage is given, checked for the invariant (a
    /// `-0.0` is an error here: mapped columns cannot be changed).
    fn checked(
        positions: Column<Vec3>,
        indices: Column<[u32; 3]>,
    ) -> Result<TriangleColumns, InvalidColumns> {
        if let Some(i) = positions.iter().position(|p| !p.is_finite()) {
            return Err(InvalidColumns::NonFiniteVertex { vertex: i });
        }
        let negative_zero = |p: &Vec3| p.to_array().iter().any(|c| c.to_bits() == 0x8000_0000);
        if let Some(i) = positions.iter().position(negative_zero) {
            return Err(InvalidColumns::NegativeZero { vertex: i });
        }
        let n = positions.len() as u64;
        if let Some(t) = indices
            .iter()
            .position(|t| t.iter().any(|&i| u64::from(i) >= n))
        {
            return Err(InvalidColumns::IndexOutOfRange { triangle: t });
        }
        if indices.len() >= u32::MAX as usize {
            return Err(InvalidColumns::TooManyTriangles);
        }
        Ok(TriangleColumns { positions, indices })
    }

    /// Whether the columns are mapped from a file rather than in memory.
    pub fn is_mapped(&self) -> bool {
        self.positions.is_mapped() && self.indices.is_mapped()
    }

    /// One vertex column per corner, for tests and generators: triangle `i`
    /// is `tris[i]`.
    pub fn from_triangles(tris: &[[Vec3; 3]]) -> Result<TriangleColumns, InvalidColumns> {
        let positions = tris.iter().flatten().copied().collect();
        let indices = (0..tris.len() as u32)
            .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
            .collect();
        TriangleColumns::new(positions, indices)
    }

    /// Columns already known to hold the invariant (and no `-0.0`), such
    /// as those of a validated `.kd` file; nothing is checked.
    pub(crate) fn from_valid_parts(
        positions: Vec<Vec3>,
        indices: Vec<[u32; 3]>,
    ) -> TriangleColumns {
        TriangleColumns {
            positions: Column::Owned(positions),
            indices: Column::Owned(indices),
        }
    }

    /// The vertex positions.
    pub fn positions(&self) -> &[Vec3] {
        &self.positions
    }

    /// The vertex-index triples, one per triangle.
    pub fn indices(&self) -> &[[u32; 3]] {
        &self.indices
    }

    /// The number of triangles.
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// Whether there are no triangles.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// The three vertices of triangle `i`.
    #[inline]
    pub fn tri(&self, i: u32) -> [Vec3; 3] {
        let [a, b, c] = self.indices[i as usize];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// The bounds of every triangle (empty for an empty scene).
    pub fn bounds(&self) -> Aabb {
        (0..self.len() as u32).fold(Aabb::EMPTY, |b, i| {
            b.union(&Aabb::of_triangle(&self.tri(i)))
        })
    }

    /// The Morton order of triangle centroids: `perm[new] = old` (the
    /// order in which `format` writes a reordered file).
    pub fn morton_order(&self) -> Vec<u32> {
        let b = self.bounds();
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
        let mut keyed: Vec<(u64, u32)> = (0..self.len() as u32)
            .into_par_iter()
            .map(|i| {
                let [a, b2, c] = self.tri(i);
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
        // The pairs are distinct, so the order does not depend on the sort.
        keyed.par_sort_unstable();
        keyed.into_par_iter().map(|(_, i)| i).collect()
    }

    /// The geometric normal of triangle `i` (not normalised).
    pub fn normal(&self, i: u32) -> Vec3 {
        let [a, b, c] = self.tri(i);
        (b - a).cross(c - a)
    }

    /// Drops degenerate triangles (see the module docs); returns how many.
    /// Columns without any are left as they are (mapped ones stay mapped).
    pub fn drop_degenerate(&mut self) -> usize {
        let positions: &[Vec3] = &self.positions;
        let keep = |t: &[u32; 3]| {
            let tri = [
                positions[t[0] as usize],
                positions[t[1] as usize],
                positions[t[2] as usize],
            ];
            t[0] != t[1] && t[1] != t[2] && t[0] != t[2] && double_area(&tri) != 0.0
        };
        let dropped = self.indices.iter().filter(|t| !keep(t)).count();
        if dropped > 0 {
            self.indices.to_mut().retain(keep);
        }
        dropped
    }
}

/// Why [`TriangleColumns::new`] refused its columns.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum InvalidColumns {
    /// A position with a NaN or infinite coordinate.
    #[error("vertex {vertex} has a non-finite coordinate")]
    NonFiniteVertex {
        /// Its index in the position column.
        vertex: usize,
    },
    /// A triangle naming a vertex past the position column.
    #[error("triangle {triangle} has a vertex index out of range")]
    IndexOutOfRange {
        /// Its index in the index column.
        triangle: usize,
    },
    /// `u32::MAX` triangles or more (ids are `u32`, one value reserved).
    #[error("too many triangles for 32-bit ids")]
    TooManyTriangles,
    /// A coordinate `-0.0` in columns that cannot be changed (a mapped
    /// scene cache; its writer writes `+0.0`).
    #[error("vertex {vertex} has a coordinate -0.0 (columns hold +0.0)")]
    NegativeZero {
        /// Its index in the position column.
        vertex: usize,
    },
}

/// What a load did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LoadSummary {
    /// Triangles kept (after fan triangulation and dropping).
    pub triangles: usize,
    /// Vertex positions kept.
    pub vertices: usize,
    /// Triangles dropped because they have zero area or repeat a vertex.
    pub dropped_degenerate: usize,
    /// Lines read (of the text formats; 0 for glTF, the header and ASCII
    /// data lines of PLY).
    pub lines: u64,
}

impl fmt::Display for LoadSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} triangles, {} vertices, {} degenerate triangles dropped",
            self.triangles, self.vertices, self.dropped_degenerate
        )
    }
}

/// A scene that could not be loaded. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file (or a file it names, such as a glTF side buffer) could not
    /// be read, or its compressed stream is corrupt.
    #[error("{}: {source}", path.display())]
    Io {
        /// The scene file.
        path: PathBuf,
        /// What the read said.
        source: std::io::Error,
    },
    /// A problem with one line (1-based).
    #[error("{}:{line}: {message}", path.display())]
    Line {
        /// The scene file.
        path: PathBuf,
        /// The line, 1-based.
        line: u64,
        /// What is wrong with it.
        message: String,
    },
    /// A problem with one element, record or mesh of a binary or
    /// structured format: `what` names it (`vertex 17`, `mesh 2
    /// primitive 0`).
    #[error("{}: {what}: {message}", path.display())]
    Element {
        /// The scene file.
        path: PathBuf,
        /// The element, record or mesh part.
        what: String,
        /// What is wrong with it.
        message: String,
    },
    /// A problem not tied to one line or element.
    #[error("{}: {message}", path.display())]
    Invalid {
        /// The scene file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// The scene formats [`load`] reads, told apart by the file name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneFormat {
    /// Wavefront OBJ (`.obj`).
    Obj,
    /// OBJ compressed with gzip (`.obj.gz`).
    ObjGz,
    /// PLY, ASCII or binary (`.ply`).
    Ply,
    /// PLY compressed with gzip (`.ply.gz`).
    PlyGz,
    /// glTF 2.0 JSON (`.gltf`), its buffers embedded or beside it.
    Gltf,
    /// Binary glTF 2.0 (`.glb`).
    Glb,
    /// The binary scene cache `slimkd convert` writes (`.kds`).
    Cache,
}

impl SceneFormat {
    /// The names [`load`] recognises, for error messages.
    pub const SUPPORTED: &'static str = ".obj, .obj.gz, .ply, .ply.gz, .gltf, .glb or .kds";

    /// The format a file name says (its extension, case-insensitive), or
    /// `None` for one [`load`] does not read.
    pub fn of_path(path: &Path) -> Option<SceneFormat> {
        let name = path.file_name()?.to_str()?.to_ascii_lowercase();
        let format = if name.ends_with(".obj.gz") {
            SceneFormat::ObjGz
        } else if name.ends_with(".ply.gz") {
            SceneFormat::PlyGz
        } else {
            match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
                "obj" => SceneFormat::Obj,
                "ply" => SceneFormat::Ply,
                "gltf" => SceneFormat::Gltf,
                "glb" => SceneFormat::Glb,
                cache::EXTENSION => SceneFormat::Cache,
                _ => return None,
            }
        };
        Some(format)
    }

    /// The format of the file at `path`: a scene cache by its magic bytes
    /// (whatever its name), else as [`SceneFormat::of_path`] says.
    pub fn detect(path: &Path) -> Option<SceneFormat> {
        if starts_with(path, &cache::MAGIC) {
            return Some(SceneFormat::Cache);
        }
        SceneFormat::of_path(path)
    }

    /// What a file of this format is, for messages.
    pub fn describe(self) -> &'static str {
        match self {
            SceneFormat::Obj => "an OBJ scene",
            SceneFormat::ObjGz => "a gzip-compressed OBJ scene",
            SceneFormat::Ply => "a PLY scene",
            SceneFormat::PlyGz => "a gzip-compressed PLY scene",
            SceneFormat::Gltf => "a glTF scene",
            SceneFormat::Glb => "a binary glTF (GLB) scene",
            SceneFormat::Cache => "a slimkd scene cache (.kds)",
        }
    }
}

/// Whether `path` looks like a slimkd `.kd` tree file: its name ends in
/// `.kd`, or it starts with the `.kd` magic bytes.
pub fn is_kd_file(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("kd"))
        || starts_with(path, &KD_MAGIC)
}

/// The first 8 bytes of a slimkd tree file, so that one handed over as a
/// scene is named as such. The scene layer lies below the file format and
/// does not depend on it: the format's own `MAGIC` is checked, where it is
/// defined, to be these bytes.
pub(crate) const KD_MAGIC: [u8; 8] = [0x89, b'S', b'L', b'K', b'D', b'\r', b'\n', 0x1a];

/// Whether the file at `path` starts with `magic` (false if it cannot be
/// read).
pub(crate) fn starts_with(path: &Path, magic: &[u8]) -> bool {
    let mut head = vec![0u8; magic.len()];
    crate::fsio::open_regular(path)
        .and_then(|mut f| f.read_exact(&mut head))
        .is_ok_and(|()| head == magic)
}

/// Loads a scene file in the format its name says ([`SceneFormat`]).
pub fn load(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    load_with_progress(path, None)
}

/// [`load`], advancing `progress` to 1 as the file is read (a text or
/// compressed file by its bytes; the others at once when read).
pub fn load_with_progress(
    path: &Path,
    progress: Option<&Progress>,
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let invalid = |message: String| SceneError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    if is_kd_file(path) {
        return Err(invalid(format!(
            "this is a slimkd tree file (.kd), but a scene was expected ({})",
            SceneFormat::SUPPORTED
        )));
    }
    let Some(format) = SceneFormat::of_path(path) else {
        return Err(invalid(format!(
            "unknown scene format (by its name); supported: {}",
            SceneFormat::SUPPORTED
        )));
    };
    let loaded = match format {
        SceneFormat::Obj => return load_obj_with_progress(path, progress),
        SceneFormat::ObjGz => obj::load_obj_reader(path, BufReader::new(gunzip(path, progress)?)),
        SceneFormat::Ply => ply::load_ply_reader(path, counted_file(path, progress)?),
        SceneFormat::PlyGz => ply::load_ply_reader(path, BufReader::new(gunzip(path, progress)?)),
        SceneFormat::Gltf | SceneFormat::Glb => load_gltf(path),
        SceneFormat::Cache => load_scene_cache(path),
    };
    Progress::add_all(progress);
    loaded
}

/// The file at `path`, buffered, advancing `progress` with its bytes read.
pub(crate) fn counted_file<'a>(
    path: &Path,
    progress: Option<&'a Progress>,
) -> Result<BufReader<Counted<'a, std::fs::File>>, SceneError> {
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = crate::fsio::open_regular(path).map_err(io)?;
    let size = file.metadata().map_err(io)?.len();
    let counted = Counted {
        inner: file,
        read: 0,
        size,
        progress,
    };
    Ok(BufReader::with_capacity(1 << 20, counted))
}

/// The decompressed bytes of the gzip file at `path` (every member, as
/// `gzip -d` does), advancing `progress` with the compressed bytes read.
/// A corrupt stream is an I/O error naming the file when read.
fn gunzip<'a>(
    path: &Path,
    progress: Option<&'a Progress>,
) -> Result<flate2::bufread::MultiGzDecoder<BufReader<Counted<'a, std::fs::File>>>, SceneError> {
    Ok(flate2::bufread::MultiGzDecoder::new(counted_file(
        path, progress,
    )?))
}

/// A reader that advances a [`Progress`] with the share of `size` bytes
/// read (a file that grows while read stops advancing at its old size).
pub(crate) struct Counted<'a, R> {
    inner: R,
    read: u64,
    size: u64,
    progress: Option<&'a Progress>,
}

impl<R: Read> Read for Counted<'_, R> {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(out)?;
        let after = (self.read + n as u64).min(self.size);
        if self.size > 0 {
            Progress::advance(self.progress, self.read, after, self.size);
        }
        self.read = after;
        Ok(n)
    }
}

/// Columns from a loader's positions and triangles, by the rules every
/// format shares: the invariant checked, degenerate triangles dropped and
/// counted, and no triangles left an error (`none` says why there were
/// none to begin with).
pub(crate) fn finish(
    path: &Path,
    positions: Vec<Vec3>,
    indices: Vec<[u32; 3]>,
    lines: u64,
    none: &str,
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let invalid = |message: String| SceneError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    let mut columns =
        TriangleColumns::new(positions, indices).map_err(|e| invalid(e.to_string()))?;
    let dropped = columns.drop_degenerate();
    if columns.is_empty() {
        return Err(invalid(if dropped > 0 {
            format!("no triangles: all {dropped} triangles are degenerate")
        } else {
            format!("no triangles ({none})")
        }));
    }
    let summary = LoadSummary {
        triangles: columns.len(),
        vertices: columns.positions.len(),
        dropped_degenerate: dropped,
        lines,
    };
    Ok((columns, summary))
}

/// A synthetic scene for tests: an `n`×`n` grid of small slanted triangles
/// 2 apart (corner `(2i, 2j, 0)`, the others one unit along x and y and
/// one up), row by row (`i` outer).
pub fn slanted_grid(n: usize) -> Vec<[Vec3; 3]> {
    let mut tris = Vec::with_capacity(n * n);
    for i in 0..n {
        for j in 0..n {
            let (x, y) = (i as f32 * 2.0, j as f32 * 2.0);
            tris.push([
                Vec3::new(x, y, 0.0),
                Vec3::new(x + 1.0, y, 1.0),
                Vec3::new(x, y + 1.0, 1.0),
            ]);
        }
    }
    tris
}
