//! Wavefront OBJ, parsed once, line by line, straight into the columns,
//! with the line number in every error.
//!
//! Consumes OBJ text from any `BufRead` (a file, a gzip stream, bytes in
//! memory). Each line is checked and parsed by the rules of
//! [`crate::scene`]: `v` lines append to the file's vertex list (the
//! weight `w` applied in `f32`, colours dropped), `vt` and `vn` lines are
//! checked and counted, and an `f` line of three or more vertices is
//! fan-triangulated (`(v0, v1, v2), (v0, v2, v3), ...`) into triangles of
//! absolute vertex indices. The first bad line stops the parse and is
//! reported with its number. Indices beyond the vertices read so far are
//! legal if the file defines the vertex later; they are checked at the end
//! of the file and reported at the line of the face.
//!
//! Produces the columns with the vertices the faces use, numbered in the
//! order of their first use (triangle by triangle, corner by corner);
//! vertices no face uses are left out. This is the numbering `.kds`
//! caches and `.kd` files of OBJ scenes store, so it must not change.

use super::{LoadSummary, SceneError, TriangleColumns};
use crate::progress::Progress;
use glam::Vec3;
use std::io::BufRead;
use std::path::{Path, PathBuf};

/// Loads an OBJ file. See the module docs of [`crate::scene`] for the rules.
pub fn load_obj(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    load_obj_with_progress(path, None)
}

/// [`load_obj`], advancing `progress` with the bytes of the file read (to
/// 1 when the whole file has been read).
pub fn load_obj_with_progress(
    path: &Path,
    progress: Option<&Progress>,
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    load_obj_reader(path, super::counted_file(path, progress)?)
}

/// Loads OBJ text held in memory; `name` is used in error messages.
pub fn load_obj_bytes(
    name: &Path,
    bytes: &[u8],
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    load_obj_reader(name, bytes)
}

pub(crate) fn load_obj_reader<R: BufRead>(
    path: &Path,
    mut reader: R,
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let line_error = |line, message: String| SceneError::Line {
        path: path.to_path_buf(),
        line,
        message: crate::text::escape_controls(&message).into_owned(),
    };
    let mut parser = ObjParser::default();
    let mut raw = Vec::new();
    loop {
        raw.clear();
        match reader.read_until(b'\n', &mut raw) {
            Ok(0) => break,
            Ok(_) => {
                parser.line += 1;
                parser
                    .parse_line(&raw)
                    .map_err(|message| line_error(parser.line, message))?;
            }
            Err(source) => {
                return Err(SceneError::Io {
                    path: path.to_path_buf(),
                    source,
                });
            }
        }
    }
    parser
        .check_forward_refs()
        .map_err(|(line, message)| line_error(line, message))?;
    let lines = parser.line;
    let (positions, indices) = parser
        .into_columns()
        .map_err(|message| SceneError::Invalid {
            path: path.to_path_buf(),
            message,
        })?;
    super::finish(
        path,
        positions,
        indices,
        lines,
        "no `f` line with three or more vertices",
    )
}

/// What a face index refers to.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Kind {
    Position,
    Texcoord,
    Normal,
}

impl Kind {
    const ALL: [Kind; 3] = [Kind::Position, Kind::Texcoord, Kind::Normal];

    /// What an index of this kind points at, in the plural.
    fn plural(self) -> &'static str {
        match self {
            Kind::Position => "vertices",
            Kind::Texcoord => "texture coordinates (`vt`)",
            Kind::Normal => "normals (`vn`)",
        }
    }

    fn name(self) -> &'static str {
        match self {
            Kind::Position => "vertex",
            Kind::Texcoord => "texture coordinate",
            Kind::Normal => "normal",
        }
    }
}

/// The state of one OBJ parse: the file's vertices and triangles so far.
#[derive(Default)]
struct ObjParser {
    /// The 1-based number of the line being parsed (0 before the first).
    line: u64,
    /// `v`, `vt` and `vn` lines seen so far, by [`Kind`].
    counts: [u64; 3],
    /// Every `v` line's position, in file order.
    positions: Vec<Vec3>,
    /// The fan triangles of the faces, as 0-based indices into the file's
    /// vertices. An index is only meaningful once `check_forward_refs`
    /// and the vertex count check of `into_columns` have passed.
    triangles: Vec<[u32; 3]>,
    /// The largest index of each kind beyond those defined so far, by line:
    /// legal only if the file defines that many later.
    forward_refs: Vec<(u64, Kind, u64)>,
    /// The corners of the face being read (absolute, 1-based).
    corners: Vec<u64>,
}

impl ObjParser {
    fn count(&self, kind: Kind) -> u64 {
        self.counts[kind as usize]
    }

    /// Parses the line `raw` (its line end included).
    fn parse_line(&mut self, raw: &[u8]) -> Result<(), String> {
        let mut bytes = raw;
        if self.line == 1 {
            bytes = bytes.strip_prefix("\u{feff}".as_bytes()).unwrap_or(bytes);
        }
        let Ok(text) = std::str::from_utf8(bytes) else {
            return Err("the line is not UTF-8 text".into());
        };
        // `#` starts a comment, at the start of a line or after a statement.
        let text = text.split('#').next().unwrap_or("");
        let mut words = text.split_whitespace();
        match words.next() {
            Some("v") => self.vertex(words),
            Some("vt") => {
                let n = numbers(words, "texture coordinate")?;
                if !(1..=3).contains(&n) {
                    return Err(format!(
                        "a texture coordinate needs 1 to 3 numbers, not {n}"
                    ));
                }
                self.counts[Kind::Texcoord as usize] += 1;
                Ok(())
            }
            Some("vn") => {
                let n = numbers(words, "normal")?;
                if n != 3 {
                    return Err(format!("a normal needs 3 numbers, not {n}"));
                }
                self.counts[Kind::Normal as usize] += 1;
                Ok(())
            }
            Some("f") => self.face(words),
            // Everything else (`o`, `g`, `l`, `p`, `s`, `mtllib`, `usemtl`,
            // ...) is ignored.
            _ => Ok(()),
        }
    }

    /// `v x y z`, `v x y z w` or `v x y z r g b`.
    fn vertex<'a>(&mut self, words: impl Iterator<Item = &'a str>) -> Result<(), String> {
        let mut values = [0.0f32; 6];
        let mut n = 0;
        for word in words {
            if n == values.len() {
                n += 1;
                break;
            }
            values[n] = word
                .parse()
                .map_err(|_| format!("cannot parse vertex coordinate `{word}`"))?;
            n += 1;
        }
        if !matches!(n, 3 | 4 | 6) {
            return Err(
                "a vertex needs x y z, optionally followed by a weight w or a colour r g b".into(),
            );
        }
        let mut p = [values[0], values[1], values[2]];
        if n == 4 {
            let w = values[3];
            if w == 0.0 {
                return Err("the vertex weight w is zero".into());
            }
            // Each coordinate divided by w, in f32.
            p = p.map(|c| c / w);
        }
        self.counts[Kind::Position as usize] += 1;
        if p.iter().any(|c| !c.is_finite()) {
            return Err(format!(
                "vertex {} has a non-finite coordinate: {} {} {}",
                self.count(Kind::Position),
                p[0],
                p[1],
                p[2]
            ));
        }
        reserve_more(&mut self.positions, 1, "the scene's vertex positions")?;
        self.positions.push(Vec3::from_array(p));
        Ok(())
    }

    /// `f` followed by corners `v`, `v/vt`, `v//vn` or `v/vt/vn`.
    fn face<'a>(&mut self, words: impl Iterator<Item = &'a str>) -> Result<(), String> {
        self.corners.clear();
        let mut beyond = [0u64; 3];
        for word in words {
            let mut parts = word.split('/');
            let v = parts.next().unwrap_or("");
            let vt = parts.next().unwrap_or("");
            let vn = parts.next().unwrap_or("");
            if parts.next().is_some() {
                return Err(format!("face vertex `{word}` has more than three parts"));
            }
            if v.is_empty() {
                return Err(format!("face vertex `{word}` has no vertex index"));
            }
            for (kind, text) in Kind::ALL.into_iter().zip([v, vt, vn]) {
                if text.is_empty() {
                    continue;
                }
                let index = self.resolve(kind, text, word)?;
                if index > self.count(kind) {
                    let b = &mut beyond[kind as usize];
                    *b = (*b).max(index);
                }
                if kind == Kind::Position {
                    self.corners.push(index);
                }
            }
        }
        for kind in Kind::ALL {
            if beyond[kind as usize] > 0 {
                self.forward_refs
                    .push((self.line, kind, beyond[kind as usize]));
            }
        }
        match self.corners.len() {
            0 => Err("a face without vertices".into()),
            // A point or a line: not a triangle, ignored.
            1 | 2 => Ok(()),
            n => {
                let fan = n - 2;
                reserve_more(&mut self.triangles, fan, "the scene's triangles")?;
                // Indices are >= 1. One past `u32::MAX` wraps here, but
                // only in a file that `check_forward_refs` or the vertex
                // count check of `into_columns` refuses.
                let at = |k: usize| (self.corners[k] - 1) as u32;
                let v0 = at(0);
                for k in 1..n - 1 {
                    self.triangles.push([v0, at(k), at(k + 1)]);
                }
                Ok(())
            }
        }
    }

    /// The absolute, 1-based index that `text` (one part of the face vertex
    /// `word`) refers to.
    fn resolve(&self, kind: Kind, text: &str, word: &str) -> Result<u64, String> {
        let Ok(index) = text.parse::<i64>() else {
            return Err(format!("cannot parse face vertex `{word}`"));
        };
        let count = self.count(kind);
        if index == 0 {
            return Err(format!(
                "face vertex `{word}`: {} index 0 is invalid (OBJ indices start at 1)",
                kind.name()
            ));
        }
        if index > 0 {
            return Ok(index as u64);
        }
        let back = index.unsigned_abs();
        if back > count {
            return Err(format!(
                "face vertex `{word}`: relative {} index {index} is out of range ({count} {} so far)",
                kind.name(),
                kind.plural()
            ));
        }
        Ok(count - back + 1)
    }

    /// At the end of the file: the first face that refers beyond the last
    /// vertex (texture coordinate, normal) of the file.
    fn check_forward_refs(&self) -> Result<(), (u64, String)> {
        match self
            .forward_refs
            .iter()
            .find(|&&(_, kind, index)| index > self.count(kind))
        {
            None => Ok(()),
            Some(&(line, kind, index)) => Err((
                line,
                format!(
                    "face {} index {index} is out of range (the file has {} {})",
                    kind.name(),
                    self.count(kind),
                    kind.plural()
                ),
            )),
        }
    }

    /// The used vertices, numbered by first use, and the triangles in that
    /// numbering (see the module docs). Called after `check_forward_refs`
    /// passed, so every index is below the vertex count.
    fn into_columns(self) -> Result<(Vec<Vec3>, Vec<[u32; 3]>), String> {
        if self.positions.len() > u32::MAX as usize {
            return Err("more than 2^32 vertices".into());
        }
        let mut triangles = self.triangles;
        let mut number = Vec::new();
        crate::sys::try_reserve(
            &mut number,
            self.positions.len(),
            "the scene's vertex numbers",
        )
        .map_err(|e| e.to_string())?;
        number.resize(self.positions.len(), u32::MAX);
        let mut used = Vec::new();
        for tri in &mut triangles {
            for corner in tri.iter_mut() {
                let n = &mut number[*corner as usize];
                if *n == u32::MAX {
                    *n = used.len() as u32;
                    reserve_more(&mut used, 1, "the scene's vertex positions")?;
                    used.push(self.positions[*corner as usize]);
                }
                *corner = *n;
            }
        }
        Ok((used, triangles))
    }
}

/// Makes room for `n` more elements of `v`, growing it geometrically (so
/// pushing N elements costs O(N)); a failed allocation is an error saying
/// what did not fit.
fn reserve_more<T>(v: &mut Vec<T>, n: usize, what: &'static str) -> Result<(), String> {
    if v.capacity() - v.len() >= n {
        return Ok(());
    }
    let more = n.max(v.len()).max(1 << 12);
    crate::sys::try_reserve(v, more, what).map_err(|e| e.to_string())
}

/// How many words there are, after checking that each parses as a number.
fn numbers<'a>(words: impl Iterator<Item = &'a str>, what: &str) -> Result<usize, String> {
    let mut n = 0;
    for word in words {
        if word.parse::<f32>().is_err() {
            return Err(format!("cannot parse {what} `{word}`"));
        }
        n += 1;
    }
    Ok(n)
}

/// The path to show for an embedded scene.
pub fn embedded_name(name: &str) -> PathBuf {
    PathBuf::from(format!("<embedded>/{name}"))
}
