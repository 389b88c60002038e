//! PLY (Stanford polygon files), ASCII and binary of either byte order,
//! through `ply-rs-bw`.
//!
//! Consumes a PLY file whose `vertex` element has scalar `x`, `y` and `z`
//! properties (of any numeric type) and whose `face` element has a list
//! property `vertex_indices` (or `vertex_index`) of integers. Produces the
//! same [`TriangleColumns`] as an OBJ file with those vertices as `v` lines
//! and those faces as `f` lines, in the same order: coordinates rounded to
//! `f32` (a `double` too large for `f32` is infinite, so an error, as in
//! OBJ), faces of three or more vertices fan-triangulated, faces of one or
//! two ignored. Every other property and element (normals, colours, `edge`
//! elements, ...) is read past and ignored.
//!
//! Errors name the file and, in the header and in ASCII data, the line the
//! parser stopped at (1-based, counted from `ply`); in binary data, the
//! element (`vertex 17`, `face 3`, 0-based as stored). A NaN or infinite
//! coordinate, a negative or out-of-range vertex index, a missing `vertex`
//! or `face` element, a `vertex` element without `x`, `y` or `z`, and a
//! file without triangles are errors; degenerate triangles are dropped and
//! counted, as for OBJ. [`LoadSummary::lines`] counts the lines of the
//! header and of ASCII data.

use super::{LoadSummary, SceneError, TriangleColumns};
use glam::Vec3;
use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{
    ElementDef, Encoding, Header, Property, PropertyAccess, PropertyAccessResult, PropertyType,
    ScalarType,
};
use std::io::BufRead;
use std::path::Path;

/// Loads a PLY file. See the module docs for the rules.
pub fn load_ply(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    load_ply_reader(path, super::counted_file(path, None)?)
}

/// Loads PLY data held in memory; `name` is used in error messages.
pub fn load_ply_bytes(
    name: &Path,
    bytes: &[u8],
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    load_ply_reader(name, bytes)
}

/// The names a face's vertex list goes by (the first is the standard's).
const FACE_LISTS: [&str; 2] = ["vertex_indices", "vertex_index"];

/// One `vertex` element: its position as stored (any numeric type is
/// exact in `f64` except 64-bit integers, which PLY does not have).
#[derive(Default)]
struct PlyVertex {
    p: [f64; 3],
}

impl PropertyAccess for PlyVertex {
    fn new() -> Self {
        PlyVertex::default()
    }

    fn set_property(&mut self, name: &str, property: Property) -> PropertyAccessResult {
        let k = match name {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            _ => return PropertyAccessResult::Ignored,
        };
        match scalar(&property) {
            Some(v) => {
                self.p[k] = v;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::UnsupportedType,
        }
    }
}

/// One `face` element: its vertex list, widened to `i64` so that a
/// negative `int` index is seen (and refused) rather than wrapped.
#[derive(Default)]
struct PlyFace {
    corners: Vec<i64>,
}

impl PropertyAccess for PlyFace {
    fn new() -> Self {
        PlyFace::default()
    }

    fn set_property(&mut self, name: &str, property: Property) -> PropertyAccessResult {
        if !FACE_LISTS.contains(&name) {
            return PropertyAccessResult::Ignored;
        }
        let corners: Vec<i64> = match property {
            Property::ListChar(v) => v.into_iter().map(i64::from).collect(),
            Property::ListUChar(v) => v.into_iter().map(i64::from).collect(),
            Property::ListShort(v) => v.into_iter().map(i64::from).collect(),
            Property::ListUShort(v) => v.into_iter().map(i64::from).collect(),
            Property::ListInt(v) => v.into_iter().map(i64::from).collect(),
            Property::ListUInt(v) => v.into_iter().map(i64::from).collect(),
            _ => return PropertyAccessResult::UnsupportedType,
        };
        self.corners = corners;
        PropertyAccessResult::Set
    }
}

/// An element of a kind this loader does not use: read and dropped.
struct Skipped;

impl PropertyAccess for Skipped {
    fn new() -> Self {
        Skipped
    }
}

/// A scalar property as `f64` (`None` for a list).
fn scalar(property: &Property) -> Option<f64> {
    Some(match *property {
        Property::Char(v) => f64::from(v),
        Property::UChar(v) => f64::from(v),
        Property::Short(v) => f64::from(v),
        Property::UShort(v) => f64::from(v),
        Property::Int(v) => f64::from(v),
        Property::UInt(v) => f64::from(v),
        Property::Float(v) => f64::from(v),
        Property::Double(v) => v,
        _ => return None,
    })
}

pub(crate) fn load_ply_reader<R: BufRead>(
    path: &Path,
    reader: R,
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let invalid = |message: String| SceneError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    let mut reader = Reader::new(reader);
    let header = Parser::<Skipped>::new()
        .read_header(&mut reader)
        .map_err(|e| parse_error(path, &e, None))?;
    check_header(&header).map_err(invalid)?;
    let binary = header.encoding != Encoding::Ascii;
    let mut vertices = Vec::new();
    let mut faces = Vec::new();
    for (name, def) in &header.elements {
        let during = binary.then_some(name.as_str());
        match name.as_str() {
            "vertex" => {
                vertices = Parser::<PlyVertex>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(|e| parse_error(path, &e, during))?;
            }
            "face" => {
                faces = Parser::<PlyFace>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(|e| parse_error(path, &e, during))?;
            }
            _ => {
                skip(&mut reader, def, &header).map_err(|e| parse_error(path, &e, during))?;
            }
        }
    }
    let element = |what: String, message: String| SceneError::Element {
        path: path.to_path_buf(),
        what,
        message,
    };
    let mut positions = Vec::with_capacity(vertices.len());
    for (i, v) in vertices.iter().enumerate() {
        let p = Vec3::new(v.p[0] as f32, v.p[1] as f32, v.p[2] as f32);
        if !p.is_finite() {
            return Err(element(
                format!("vertex {i}"),
                format!(
                    "coordinate ({}, {}, {}) is not finite in f32",
                    v.p[0], v.p[1], v.p[2]
                ),
            ));
        }
        positions.push(p);
    }
    if positions.len() > u32::MAX as usize {
        return Err(invalid("more than 2^32 vertices".into()));
    }
    let n = positions.len() as i64;
    let mut indices = Vec::with_capacity(faces.len());
    for (j, f) in faces.iter().enumerate() {
        if let Some(&bad) = f.corners.iter().find(|&&c| c < 0 || c >= n) {
            return Err(element(
                format!("face {j}"),
                format!("vertex index {bad} out of range (the file has {n} vertices)"),
            ));
        }
        // In range, so below n <= 2^32: every corner fits a u32.
        let c: Vec<u32> = f.corners.iter().map(|&c| c as u32).collect();
        for k in 2..c.len() {
            indices.push([c[0], c[k - 1], c[k]]);
        }
    }
    super::finish(
        path,
        positions,
        indices,
        reader.line() as u64,
        "no face with three or more vertices",
    )
}

/// What the loader needs of the header (see the module docs).
fn check_header(header: &Header) -> Result<(), String> {
    let vertex = header
        .elements
        .get("vertex")
        .ok_or("no `vertex` element in the header")?;
    for axis in ["x", "y", "z"] {
        match vertex.properties.get(axis).map(|p| &p.data_type) {
            Some(PropertyType::Scalar(_)) => {}
            Some(PropertyType::List(..)) => {
                return Err(format!("the `vertex` property `{axis}` is a list"));
            }
            None => return Err(format!("the `vertex` element has no `{axis}` property")),
        }
    }
    let face = header
        .elements
        .get("face")
        .ok_or("no `face` element in the header (a point cloud has no triangles)")?;
    let list = FACE_LISTS
        .iter()
        .find_map(|name| face.properties.get(*name))
        .ok_or("the `face` element has no `vertex_indices` list")?;
    match list.data_type {
        PropertyType::List(_, ScalarType::Float | ScalarType::Double) | PropertyType::Scalar(_) => {
            Err(format!(
                "the `face` property `{}` is not a list of integers",
                list.name
            ))
        }
        PropertyType::List(..) => Ok(()),
    }
}

/// Reads past the elements of `def`.
fn skip<R: BufRead>(
    reader: &mut Reader<R>,
    def: &ElementDef,
    header: &Header,
) -> Result<(), ply_rs_bw::parser::ParseError> {
    Parser::<Skipped>::new()
        .read_payload_for_element(reader, def, header)
        .map(drop)
}

/// A parser error as a [`SceneError`]: at its line where it has one (the
/// header, ASCII data), else at the elements being read (`during`).
fn parse_error(path: &Path, e: &ply_rs_bw::parser::ParseError, during: Option<&str>) -> SceneError {
    // The crate's message repeats its line number in front; it is shown
    // once, as the loader's own.
    let message = e.to_string();
    match (e.line(), during) {
        (Some(line), None) => {
            let prefix = format!("Line {line}: ");
            SceneError::Line {
                path: path.to_path_buf(),
                line: line as u64,
                message: message
                    .strip_prefix(&prefix)
                    .unwrap_or(&message)
                    .to_string(),
            }
        }
        (_, Some(element)) => SceneError::Element {
            path: path.to_path_buf(),
            what: format!("`{element}` elements"),
            message,
        },
        (None, None) => SceneError::Invalid {
            path: path.to_path_buf(),
            message,
        },
    }
}
