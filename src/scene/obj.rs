//! Wavefront OBJ through `tobj`, with line numbers for every error.
//!
//! `tobj` reports *what* went wrong but not *where*; it checks face indices
//! only when a whole object is exported, some of those checks overflow (and
//! panic in debug builds) on relative indices that are too negative, it
//! reads an `l` line of three points as a triangle, and it fails on lines
//! that this loader ignores (vertex colours on only some vertices, `usemtl`
//! without a name). So the reader handed to `tobj` is a [`LineInspector`]:
//! it reads the file line by line, parses and checks every line itself, and
//! hands `tobj` only what it needs, in a form `tobj` cannot misread: one
//! `v x y z` line per vertex (the weight `w` already applied, colours
//! dropped) and one `f` line of absolute, 1-based position indices per face
//! of three or more vertices. Every other line is checked (where the rules
//! say so) and then withheld. The first bad line stops the parse, with an
//! I/O error that `tobj` passes through, and is reported with its number.
//! Indices beyond the vertices read so far are legal if the file defines
//! the vertex later; they are checked at the end of the file and reported at
//! the line of the face.

use super::{LoadSummary, SceneError, TriangleColumns};
use crate::progress::Progress;
use glam::Vec3;
use std::io::{BufRead, Read, Write};
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
    reader: R,
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let mut inspector = LineInspector::new(reader);
    let options = tobj::LoadOptions {
        single_index: false,
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
    };
    // Materials are not used (and `mtllib` lines never reach tobj).
    let result = tobj::load_obj_buf(&mut inspector, &options, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    });
    if let Some(found) = inspector.problem.take() {
        return Err(match found {
            Problem::Io(source) => SceneError::Io {
                path: path.to_path_buf(),
                source,
            },
            Problem::Line(line, message) => SceneError::Line {
                path: path.to_path_buf(),
                line,
                message,
            },
        });
    }
    let models = match result {
        Ok((models, _materials)) => models,
        // The inspector hands tobj only lines it accepts; should tobj
        // refuse one anyway, name the line it was reading.
        Err(e) => {
            return Err(SceneError::Line {
                path: path.to_path_buf(),
                line: inspector.line,
                message: crate::text::escape_controls(&e.to_string()).into_owned(),
            });
        }
    };
    let oom = |e: crate::sys::OutOfMemory| SceneError::Invalid {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    let n_positions = models.iter().map(|m| m.mesh.positions.len() / 3).sum();
    let n_tris = models.iter().map(|m| m.mesh.indices.len() / 3).sum();
    crate::sys::try_reserve(&mut positions, n_positions, "the scene's vertex positions")
        .map_err(oom)?;
    crate::sys::try_reserve(&mut indices, n_tris, "the scene's triangles").map_err(oom)?;
    for model in &models {
        let base = positions.len() as u64;
        let mesh = &model.mesh;
        positions.extend(
            mesh.positions
                .chunks_exact(3)
                .map(|p| Vec3::new(p[0], p[1], p[2])),
        );
        for t in mesh.indices.chunks_exact(3) {
            let tri = [0, 1, 2].map(|k| base + u64::from(t[k]));
            if tri.iter().any(|&i| i > u64::from(u32::MAX)) {
                return Err(SceneError::Invalid {
                    path: path.to_path_buf(),
                    message: "more than 2^32 vertices".into(),
                });
            }
            indices.push(tri.map(|i| i as u32));
        }
    }
    super::finish(
        path,
        positions,
        indices,
        inspector.line,
        "no `f` line with three or more vertices",
    )
}

enum Problem {
    Io(std::io::Error),
    Line(u64, String),
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

/// A `BufRead` that reads the OBJ text one line at a time, checks each line
/// and hands `tobj` the part of it that `tobj` needs (see the module docs).
struct LineInspector<R> {
    inner: R,
    /// The line as read.
    raw: Vec<u8>,
    /// What `tobj` sees of it (empty: nothing).
    out: Vec<u8>,
    /// How much of `out` `tobj` has consumed.
    pos: usize,
    /// The 1-based number of the line in `raw` (0 before the first).
    line: u64,
    /// `v`, `vt` and `vn` lines seen so far, by [`Kind`].
    counts: [u64; 3],
    /// The largest index of each kind beyond those defined so far, by line:
    /// legal only if the file defines that many later.
    forward_refs: Vec<(u64, Kind, u64)>,
    /// The corners of the face being read (absolute, 1-based).
    corners: Vec<u64>,
    at_end: bool,
    problem: Option<Problem>,
}

impl<R: BufRead> LineInspector<R> {
    fn new(inner: R) -> Self {
        LineInspector {
            inner,
            raw: Vec::new(),
            out: Vec::new(),
            pos: 0,
            line: 0,
            counts: [0; 3],
            forward_refs: Vec::new(),
            corners: Vec::new(),
            at_end: false,
            problem: None,
        }
    }

    /// Records the problem of line `line`; `message` may quote the line,
    /// so its control characters are escaped.
    fn stop(&mut self, line: u64, message: String) -> std::io::Error {
        let message = crate::text::escape_controls(&message).into_owned();
        self.problem = Some(Problem::Line(line, message));
        std::io::Error::other("stopped at a bad line")
    }

    fn count(&self, kind: Kind) -> u64 {
        self.counts[kind as usize]
    }

    /// Checks the line `raw` and fills `out` with what `tobj` gets.
    fn inspect(&mut self, raw: &[u8]) -> Result<(), String> {
        self.out.clear();
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
            // As tobj would: each coordinate divided by w, in f32.
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
        // `{:e}` is the shortest text that reads back as the same f32.
        writeln!(self.out, "v {:e} {:e} {:e}", p[0], p[1], p[2]).expect("write to a Vec");
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
            _ => {
                self.out.push(b'f');
                for &i in &self.corners {
                    write!(self.out, " {i}").expect("write to a Vec");
                }
                self.out.push(b'\n');
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

impl<R: BufRead> Read for LineInspector<R> {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        let available = self.fill_buf()?;
        let n = available.len().min(out.len());
        out[..n].copy_from_slice(&available[..n]);
        self.consume(n);
        Ok(n)
    }
}

impl<R: BufRead> BufRead for LineInspector<R> {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        if self.problem.is_some() {
            return Err(std::io::Error::other("stopped at a bad line"));
        }
        // Read on until a line gives tobj something, or the file ends.
        while self.pos == self.out.len() && !self.at_end {
            self.out.clear();
            self.pos = 0;
            self.raw.clear();
            match self.inner.read_until(b'\n', &mut self.raw) {
                Ok(0) => {
                    self.at_end = true;
                    if let Err((line, message)) = self.check_forward_refs() {
                        return Err(self.stop(line, message));
                    }
                }
                Ok(_) => {
                    self.line += 1;
                    let raw = std::mem::take(&mut self.raw);
                    let inspected = self.inspect(&raw);
                    self.raw = raw;
                    if let Err(message) = inspected {
                        return Err(self.stop(self.line, message));
                    }
                }
                Err(e) => {
                    let kind = e.kind();
                    self.problem = Some(Problem::Io(e));
                    return Err(std::io::Error::from(kind));
                }
            }
        }
        Ok(&self.out[self.pos..])
    }

    fn consume(&mut self, amt: usize) {
        self.pos = (self.pos + amt).min(self.out.len());
    }
}

/// The path to show for an embedded scene.
pub fn embedded_name(name: &str) -> PathBuf {
    PathBuf::from(format!("<embedded>/{name}"))
}
