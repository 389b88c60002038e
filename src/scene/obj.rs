//! Wavefront OBJ through `tobj`, with line numbers for every error.
//!
//! `tobj` reports *what* went wrong but not *where*, and it checks face
//! indices only when a whole object is exported. So the reader handed to
//! `tobj` is a [`LineInspector`]: it counts lines as `tobj` pulls them,
//! checks each `v` line for non-finite coordinates and each `f` line for
//! indices out of range, and stops the parse (with an I/O error that `tobj`
//! passes through) at the first bad line. Any other `tobj` error is reported
//! at the line `tobj` was reading.

use super::{LoadSummary, SceneError, TriangleColumns};
use glam::Vec3;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

/// Loads an OBJ file. See the module docs of [`crate::scene`] for the rules.
pub fn load_obj(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let file = std::fs::File::open(path).map_err(|source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    load_obj_reader(path, BufReader::with_capacity(1 << 20, file))
}

/// Loads OBJ text held in memory; `name` is used in error messages.
pub fn load_obj_bytes(name: &Path, bytes: &[u8]) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    load_obj_reader(name, bytes)
}

fn load_obj_reader<R: BufRead>(path: &Path, reader: R) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let mut inspector = LineInspector::new(reader);
    let options = tobj::LoadOptions {
        single_index: false,
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
    };
    // Materials are not used: every `mtllib` is answered with "not found",
    // which tobj records and ignores.
    let result = tobj::load_obj_buf(&mut inspector, &options, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    });
    let line_err = |line: u64, message: String| SceneError::Line {
        path: path.to_path_buf(),
        line,
        message,
    };
    if let Some(found) = inspector.problem.take() {
        return Err(match found {
            Problem::Io(source) => SceneError::Io {
                path: path.to_path_buf(),
                source,
            },
            Problem::Line(line, message) => line_err(line, message),
        });
    }
    let models = match result {
        Ok((models, _materials)) => models,
        Err(e) => {
            // A forward reference past the last vertex is only detected by
            // tobj when the object is exported; name its line.
            if let Some(&(line, index)) = inspector
                .forward_refs
                .iter()
                .find(|&&(_, index)| index > inspector.n_vertices)
            {
                return Err(line_err(
                    line,
                    format!(
                        "face index {index} is out of range (the file has {} vertices)",
                        inspector.n_vertices
                    ),
                ));
            }
            return Err(line_err(inspector.line, format!("{e}")));
        }
    };
    let mut positions = Vec::new();
    let mut indices = Vec::new();
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
    let mut columns = TriangleColumns::new(positions, indices).map_err(|message| SceneError::Invalid {
        path: path.to_path_buf(),
        message,
    })?;
    let dropped = columns.drop_degenerate();
    if columns.is_empty() {
        let message = if dropped > 0 {
            format!("no triangles: all {dropped} faces are degenerate")
        } else {
            "no triangles (no `f` line with three or more vertices)".to_string()
        };
        return Err(SceneError::Invalid {
            path: path.to_path_buf(),
            message,
        });
    }
    let summary = LoadSummary {
        triangles: columns.len(),
        vertices: columns.positions.len(),
        dropped_degenerate: dropped,
        lines: inspector.line,
    };
    Ok((columns, summary))
}

enum Problem {
    Io(std::io::Error),
    Line(u64, String),
}

/// A `BufRead` that hands `tobj` one line at a time and inspects it first.
struct LineInspector<R> {
    inner: R,
    buf: Vec<u8>,
    pos: usize,
    /// The 1-based number of the line in `buf` (0 before the first).
    line: u64,
    /// `v` lines seen so far.
    n_vertices: u64,
    /// Positive face indices beyond the vertices seen so far: legal only if
    /// the vertex is defined later in the file.
    forward_refs: Vec<(u64, u64)>,
    problem: Option<Problem>,
}

impl<R: BufRead> LineInspector<R> {
    fn new(inner: R) -> Self {
        LineInspector {
            inner,
            buf: Vec::new(),
            pos: 0,
            line: 0,
            n_vertices: 0,
            forward_refs: Vec::new(),
            problem: None,
        }
    }

    fn fail(&mut self, message: String) -> std::io::Error {
        self.problem = Some(Problem::Line(self.line, message));
        std::io::Error::other("stopped at a bad line")
    }

    /// Checks the line in `buf`.
    fn inspect(&mut self) -> std::io::Result<()> {
        let Ok(text) = std::str::from_utf8(&self.buf) else {
            return Err(self.fail("the line is not UTF-8 text".into()));
        };
        let mut words = text.split_whitespace();
        match words.next() {
            Some("v") => {
                self.n_vertices += 1;
                let coords: Vec<&str> = words.take(4).collect();
                // Only text that could spell a non-finite value is parsed
                // here: a letter (nan, inf, an exponent), a long numeral, or
                // a w component that divides the position.
                let suspicious = coords.len() == 4
                    || coords
                        .iter()
                        .any(|w| w.len() > 24 || w.bytes().any(|b| b.is_ascii_alphabetic()));
                if suspicious && coords.len() >= 3 {
                    let parsed: Vec<f32> = coords.iter().filter_map(|w| w.parse().ok()).collect();
                    if parsed.len() == coords.len() {
                        let w = if parsed.len() == 4 { parsed[3] } else { 1.0 };
                        if parsed[..3].iter().any(|&c| !(c / w).is_finite()) {
                            return Err(self.fail(format!(
                                "vertex {} has a non-finite coordinate: {}",
                                self.n_vertices,
                                text.trim()
                            )));
                        }
                    }
                }
            }
            Some("f") => {
                for word in words {
                    let first = word.split('/').next().unwrap_or("");
                    let Ok(index) = first.parse::<i64>() else {
                        return Err(self.fail(format!("cannot parse face vertex `{word}`")));
                    };
                    if index == 0 {
                        return Err(self.fail("face index 0 is invalid (OBJ indices start at 1)".into()));
                    }
                    if index < 0 && index.unsigned_abs() > self.n_vertices {
                        return Err(self.fail(format!(
                            "relative face index {index} is out of range ({} vertices so far)",
                            self.n_vertices
                        )));
                    }
                    if index > 0 && index as u64 > self.n_vertices {
                        self.forward_refs.push((self.line, index as u64));
                    }
                }
            }
            _ => {}
        }
        Ok(())
    }
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
        if self.pos == self.buf.len() {
            self.buf.clear();
            self.pos = 0;
            match self.inner.read_until(b'\n', &mut self.buf) {
                Ok(0) => {}
                Ok(_) => {
                    self.line += 1;
                    self.inspect()?;
                }
                Err(e) => {
                    let kind = e.kind();
                    self.problem = Some(Problem::Io(e));
                    return Err(std::io::Error::from(kind));
                }
            }
        }
        Ok(&self.buf[self.pos..])
    }

    fn consume(&mut self, amt: usize) {
        self.pos = (self.pos + amt).min(self.buf.len());
    }
}

/// The path to show for an embedded scene.
pub fn embedded_name(name: &str) -> PathBuf {
    PathBuf::from(format!("<embedded>/{name}"))
}
