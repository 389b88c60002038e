//! The Wavefront OBJ loader (`slimkd::scene`): every face index form,
//! polygons, objects, the lines that are ignored, the degenerate rule, every
//! error (right variant, file and line), and that no input makes it panic.
//!
//! Every text is loaded twice, from a file in a private temporary folder
//! (`load_obj`) and from memory (`load_obj_bytes`), and both must agree.

mod common;

use common::{TestDir, temp_dir};
use glam::Vec3;
use proptest::prelude::*;
use slimkd::geom::double_area;
use slimkd::scene::{LoadSummary, SceneError, TriangleColumns, load_obj, load_obj_bytes};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The directory the tests of this file write their scenes into, shared
/// (each file has a name of its own); a static guard is never dropped, so
/// it stays after the run.
fn scratch() -> &'static Path {
    static DIR: std::sync::OnceLock<TestDir> = std::sync::OnceLock::new();
    DIR.get_or_init(|| temp_dir("scratch"))
}

type Loaded = Result<(TriangleColumns, LoadSummary), SceneError>;

/// Writes `bytes` to a fresh file named after `name`.
fn write_temp(name: &str, bytes: &[u8]) -> PathBuf {
    static COUNTER: AtomicUsize = AtomicUsize::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let path = scratch().join(format!("{n}-{name}.obj"));
    std::fs::write(&path, bytes).expect("write the scratch file");
    path
}

/// Loads `text` from a file and from memory (under the same name), checks
/// that both agree, and returns the file's path and the result.
fn load(name: &str, text: impl AsRef<[u8]>) -> (PathBuf, Loaded) {
    let bytes = text.as_ref();
    let path = write_temp(name, bytes);
    let from_file = load_obj(&path);
    let from_memory = load_obj_bytes(&path, bytes);
    match (&from_file, &from_memory) {
        (Ok(a), Ok(b)) => assert_eq!(a, b, "file and memory loads differ"),
        (Err(a), Err(b)) => {
            assert_eq!(a.to_string(), b.to_string(), "file and memory loads differ")
        }
        (a, b) => panic!("file load {a:?} but memory load {b:?}"),
    }
    std::fs::remove_file(&path).ok();
    (path, from_file)
}

/// Checks the invariant of loaded columns and that the summary matches.
fn check_columns(columns: &TriangleColumns, summary: &LoadSummary) {
    let n = columns.positions().len();
    assert!(
        columns
            .indices()
            .iter()
            .flatten()
            .all(|&i| (i as usize) < n),
        "index out of range"
    );
    assert!(
        columns.positions().iter().all(|p| p.is_finite()),
        "non-finite position"
    );
    assert_eq!(summary.triangles, columns.len());
    assert_eq!(summary.vertices, n);
    for i in 0..columns.len() as u32 {
        let [a, b, c] = columns.indices()[i as usize];
        assert!(a != b && b != c && a != c, "triangle {i} repeats a vertex");
        assert!(
            double_area(&columns.tri(i)) != 0.0,
            "triangle {i} is degenerate"
        );
    }
}

/// Loads text that must load; returns the columns and the summary.
fn load_ok(name: &str, text: impl AsRef<[u8]>) -> (TriangleColumns, LoadSummary) {
    let (path, result) = load(name, text);
    match result {
        Ok((columns, summary)) => {
            check_columns(&columns, &summary);
            (columns, summary)
        }
        Err(e) => panic!("{} failed to load: {e}", path.display()),
    }
}

/// The triangles' vertex positions, in order.
fn tris(columns: &TriangleColumns) -> Vec<[Vec3; 3]> {
    (0..columns.len() as u32).map(|i| columns.tri(i)).collect()
}

fn v(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3::new(x, y, z)
}

/// Loads text that must fail at `line`; returns the message.
#[track_caller]
fn expect_line_error(name: &str, text: impl AsRef<[u8]>, line: u64) -> String {
    let (path, result) = load(name, text);
    let err = match result {
        Ok((c, s)) => panic!(
            "{name}: loaded {} triangles ({s}), expected an error at line {line}",
            c.len()
        ),
        Err(e) => e,
    };
    let shown = err.to_string();
    match err {
        SceneError::Line {
            path: p,
            line: l,
            message,
        } => {
            assert_eq!(p, path, "{name}: wrong path in {shown}");
            assert_eq!(l, line, "{name}: wrong line in {shown}");
            let prefix = format!("{}:{line}: ", path.display());
            assert!(
                shown.starts_with(&prefix),
                "{name}: `{shown}` does not start with `{prefix}`"
            );
            assert!(!message.is_empty());
            message
        }
        other => panic!("{name}: expected a line error at line {line}, got {other:?} ({shown})"),
    }
}

/// Loads text that must fail as a whole (not at one line); returns the
/// message.
#[track_caller]
fn expect_invalid(name: &str, text: impl AsRef<[u8]>) -> String {
    let (path, result) = load(name, text);
    let err = match result {
        Ok((c, s)) => panic!(
            "{name}: loaded {} triangles ({s}), expected an error",
            c.len()
        ),
        Err(e) => e,
    };
    let shown = err.to_string();
    match err {
        SceneError::Invalid { path: p, message } => {
            assert_eq!(p, path, "{name}: wrong path in {shown}");
            assert_eq!(shown, format!("{}: {message}", path.display()));
            message
        }
        other => panic!("{name}: expected an Invalid error, got {other:?} ({shown})"),
    }
}

/// Four vertices used by the index-form tests.
const FOUR: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n";
const P: [Vec3; 4] = [
    Vec3::new(0.0, 0.0, 0.0),
    Vec3::new(1.0, 0.0, 0.0),
    Vec3::new(0.0, 1.0, 0.0),
    Vec3::new(0.0, 0.0, 1.0),
];

fn p(one_based: [usize; 3]) -> [Vec3; 3] {
    one_based.map(|i| P[i - 1])
}

// ---------------------------------------------------------------------------
// Face index forms.

#[test]
fn face_form_vertex_only() {
    let (c, s) = load_ok("plain", format!("{FOUR}f 1 2 3\nf 1 2 4\nf 4 3 2\n"));
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([1, 2, 4]), p([4, 3, 2])]);
    assert_eq!(s.dropped_degenerate, 0);
    assert_eq!(s.lines, 7);
}

#[test]
fn face_form_vertex_texcoord() {
    let text = format!("{FOUR}vt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\nf 4/3 2/1 1/2\n");
    let (c, _) = load_ok("vt", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([4, 2, 1])]);
}

#[test]
fn face_form_vertex_normal() {
    let text = format!("{FOUR}vn 0 0 1\nvn 1 0 0\nf 1//1 2//1 3//1\nf 2//2 3//2 4//1\n");
    let (c, _) = load_ok("vn", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([2, 3, 4])]);
}

#[test]
fn face_form_vertex_texcoord_normal() {
    let text = format!(
        "{FOUR}vt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\nf 1/1/1 2/2/1 3/3/1\nf 3/1/1 4/2/1 1/3/1\n"
    );
    let (c, _) = load_ok("vtvn", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([3, 4, 1])]);
}

#[test]
fn face_form_relative_indices() {
    // -1 is the last vertex defined so far.
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 0 0 1\nf -1 -2 -4\nf -4 -3 -1\n";
    let (c, _) = load_ok("relative", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([4, 3, 1]), p([1, 2, 4])]);
}

#[test]
fn face_form_relative_with_texcoords_and_normals() {
    let text = format!("{FOUR}vt 0 0\nvt 1 0\nvn 0 0 1\nf -4/-2/-1 -3/-1/-1 -1/-2/-1\n");
    let (c, _) = load_ok("relative-vtvn", text);
    assert_eq!(tris(&c), vec![p([1, 2, 4])]);
}

#[test]
fn face_forms_mixed_on_one_line_and_across_lines() {
    let text = format!(
        "{FOUR}vt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n\
         f 1 2/2 3//1\n\
         f 1/1/1 -3 4/3\n\
         f -1//1 2/-1/1 3\n\
         f 2 3 4 1/1\n"
    );
    let (c, _) = load_ok("mixed", text);
    assert_eq!(
        tris(&c),
        vec![
            p([1, 2, 3]),
            p([1, 2, 4]),
            p([4, 2, 3]),
            p([2, 3, 4]),
            p([2, 4, 1])
        ]
    );
}

#[test]
fn vertex_reused_across_faces_keeps_its_position() {
    // tobj re-indexes; positions must follow the file's indices anyway.
    let text = "v 5 0 0\nv 0 6 0\nv 0 0 7\nv 1 1 1\nf 4 1 2\nf 3 4 1\nf 2 3 4\n";
    let (c, _) = load_ok("reuse", text);
    let q = [
        v(5.0, 0.0, 0.0),
        v(0.0, 6.0, 0.0),
        v(0.0, 0.0, 7.0),
        v(1.0, 1.0, 1.0),
    ];
    assert_eq!(
        tris(&c),
        vec![[q[3], q[0], q[1]], [q[2], q[3], q[0]], [q[1], q[2], q[3]]]
    );
}

/// The vertex column is the used vertices numbered by first use (triangle
/// by triangle, corner by corner, fans included); `.kds` caches and `.kd`
/// files store this numbering, so it must not change.
#[test]
fn vertices_are_numbered_by_first_use_and_unused_ones_left_out() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 9 9 9\nv 1 1 0\nv 2 1 0\n\
                f 5 2 -4\nf 1 2 3 6\n";
    let (c, summary) = load_ok("first-use", text);
    let at = |i: usize| {
        [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [9.0, 9.0, 9.0],
            [1.0, 1.0, 0.0],
            [2.0, 1.0, 0.0],
        ][i - 1]
    };
    let want: Vec<Vec3> = [5, 2, 3, 1, 6]
        .iter()
        .map(|&i| Vec3::from_array(at(i)))
        .collect();
    assert_eq!(c.positions(), want.as_slice());
    assert_eq!(c.indices(), &[[0, 1, 2], [3, 1, 2], [3, 2, 4]]);
    assert_eq!(summary.vertices, 5);
}

#[test]
fn vertex_coordinates_are_read_exactly() {
    let text = "v 0.1 -2.5e3 +7\nv 3.4028235e38 -1e-38 1e-45\nv -0 0.000001 123456789\nf 1 2 3\n";
    let (c, _) = load_ok("exact", text);
    let expect = [
        v(0.1, -2.5e3, 7.0),
        v(3.402_823_5e38, -1e-38, 1e-45),
        v(0.0, 0.000_001, 123_456_789.0),
    ];
    assert_eq!(tris(&c), vec![expect]);
    // -0 is stored as +0 (equal split planes have equal bits).
    assert!(
        c.positions()
            .iter()
            .all(|q| q.x.to_bits() != (-0.0f32).to_bits())
    );
}

#[test]
fn vertex_weight_divides_the_position() {
    let text = "v 2 4 6 2\nv 1 0 0 0.5\nv 0 1 0 1\nf 1 2 3\n";
    let (c, _) = load_ok("weight", text);
    assert_eq!(
        tris(&c),
        vec![[v(1.0, 2.0, 3.0), v(2.0, 0.0, 0.0), v(0.0, 1.0, 0.0)]]
    );
}

#[test]
fn vertex_colours_are_ignored() {
    // A colour of 0 is not a weight; only some vertices have a colour.
    let text = "v 0 0 0 0 0 0\nv 1 0 0 1 0.5 0\nv 0 1 0\nv 0 0 1 0 0 0\nf 1 2 3\nf 1 2 4\n";
    let (c, _) = load_ok("colours", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([1, 2, 4])]);
}

// ---------------------------------------------------------------------------
// Polygons.

#[test]
fn quad_is_fan_triangulated() {
    let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";
    let (c, _) = load_ok("quad", text);
    let q = [
        v(0.0, 0.0, 0.0),
        v(1.0, 0.0, 0.0),
        v(1.0, 1.0, 0.0),
        v(0.0, 1.0, 0.0),
    ];
    assert_eq!(tris(&c), vec![[q[0], q[1], q[2]], [q[0], q[2], q[3]]]);
}

#[test]
fn pentagon_and_hexagon_are_fan_triangulated() {
    let q = [
        v(0.0, 0.0, 0.0),
        v(2.0, 0.0, 0.0),
        v(3.0, 2.0, 0.0),
        v(1.0, 3.0, 0.0),
        v(-1.0, 2.0, 0.0),
        v(-1.0, 1.0, 0.5),
    ];
    let mut text = String::new();
    for x in q {
        text += &format!("v {} {} {}\n", x.x, x.y, x.z);
    }
    // The pentagon starts at vertex 2, the hexagon uses relative indices
    // and slashes.
    text += "f 2 3 4 5 1\nvt 0 0\nf -6/1 -5/1 -4/1 -3/1 -2/1 -1/1\n";
    let (c, s) = load_ok("polygons", text);
    assert_eq!(
        tris(&c),
        vec![
            [q[1], q[2], q[3]],
            [q[1], q[3], q[4]],
            [q[1], q[4], q[0]],
            [q[0], q[1], q[2]],
            [q[0], q[2], q[3]],
            [q[0], q[3], q[4]],
            [q[0], q[4], q[5]],
        ]
    );
    assert_eq!(s.triangles, 7);
}

#[test]
fn polygon_fan_drops_only_its_degenerate_triangles() {
    // The first fan triangle (0,1,2) is collinear; (0,2,3) is kept.
    let text = "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 1 1 0\nf 1 2 3 4\n";
    let (c, s) = load_ok("fan-degenerate", text);
    assert_eq!(
        tris(&c),
        vec![[v(0.0, 0.0, 0.0), v(2.0, 0.0, 0.0), v(1.0, 1.0, 0.0)]]
    );
    assert_eq!(s.dropped_degenerate, 1);
}

// ---------------------------------------------------------------------------
// Objects and groups.

#[test]
fn objects_and_groups_keep_file_order() {
    let text = "\
o first
v 0 0 0
v 1 0 0
v 0 1 0
f 1 2 3
g second part
v 0 0 1
v 1 0 1
v 0 1 1
f 4 5 6
f -1 -3 -2
o third
f 1 5 6
g
f 3 2 1
o
usemtl none
f 2 4 6
";
    let (c, s) = load_ok("objects", text);
    let q = [
        v(0.0, 0.0, 0.0),
        v(1.0, 0.0, 0.0),
        v(0.0, 1.0, 0.0),
        v(0.0, 0.0, 1.0),
        v(1.0, 0.0, 1.0),
        v(0.0, 1.0, 1.0),
    ];
    assert_eq!(
        tris(&c),
        vec![
            [q[0], q[1], q[2]],
            [q[3], q[4], q[5]],
            [q[5], q[3], q[4]],
            [q[0], q[4], q[5]],
            [q[2], q[1], q[0]],
            [q[1], q[3], q[5]],
        ]
    );
    assert_eq!(s.triangles, 6);
    assert_eq!(s.dropped_degenerate, 0);
}

#[test]
fn faces_before_any_object_and_empty_objects() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\no empty\no also-empty\ng g1\nf 3 1 2\no tail\n";
    let (c, _) = load_ok("empty-objects", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([3, 1, 2])]);
}

// ---------------------------------------------------------------------------
// Materials, comments and other ignored lines.

#[test]
fn missing_material_libraries_do_not_fail() {
    let text = "\
mtllib does-not-exist.mtl
mtllib ../nowhere/else.mtl other.mtl
mtllib with space.mtl
v 0 0 0
v 1 0 0
v 0 1 0
v 0 0 1
usemtl red
f 1 2 3
usemtl blue
f 1 2 4
usemtl red
f 1 3 4
";
    let (c, _) = load_ok("mtllib", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([1, 2, 4]), p([1, 3, 4])]);
}

#[test]
fn material_lines_without_names_or_with_tabs_are_ignored() {
    let text =
        format!("{FOUR}mtllib\nusemtl\nusemtl\tred\nmtllib\tx.mtl\nf 1 2 3\nusemtl \nf 2 3 4\n");
    let (c, _) = load_ok("mtl-odd", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([2, 3, 4])]);
}

#[test]
fn comments_blank_lines_crlf_tabs_and_ignored_statements() {
    let text = "# a comment\r\n\
                \r\n\
                \t  \r\n\
                #v 9 9 9\r\n\
                v\t0 0 0\r\n\
                v  1\t0   0\r\n\
                vt 0.5 0.5\r\n\
                vn 0 0 1\r\n\
                s 1\r\n\
                s off\r\n\
                vp 0.5\r\n\
                v 0 1 0\r\n\
                l 1 2\r\n\
                l 1 2 3\r\n\
                l 1/1 3/1 2/1\r\n\
                p 1\r\n\
                p 1 2 3\r\n\
                cstype bezier\r\n\
                \tf 1 2 3 \r\n\
                #f 1 2 3\r\n\
                # f 3 1 2\r\n\
                f\t3 2\t1";
    let (c, s) = load_ok("ignored", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([3, 2, 1])]);
    assert_eq!(s.lines, 22);
    assert_eq!(s.dropped_degenerate, 0);
}

#[test]
fn crlf_and_lf_give_the_same_scene() {
    let lf = format!("{FOUR}vt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 3/1/1\nf 4 3 2 1\n");
    let crlf = lf.replace('\n', "\r\n");
    let (a, sa) = load_ok("lf", &lf);
    let (b, sb) = load_ok("crlf", &crlf);
    assert_eq!(a, b);
    assert_eq!(sa, sb);
}

#[test]
fn trailing_comments_are_ignored() {
    let text = "v 0 0 0 # origin\nv 1 0 0#x\nv 0 1 0\t# y\nf 1 2 3 # the triangle\no a # name\n";
    let (c, _) = load_ok("trailing-comment", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3])]);
}

#[test]
fn byte_order_mark_is_skipped() {
    let text = "\u{feff}v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
    let (c, _) = load_ok("bom", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3])]);
}

#[test]
fn faces_with_fewer_than_three_vertices_are_ignored() {
    let text = format!("{FOUR}f 1\nf 1 2\nf 1 2 3\nf 4/1\n");
    let (c, s) = load_ok("short-faces", format!("vt 0 0\n{text}"));
    assert_eq!(tris(&c), vec![p([1, 2, 3])]);
    assert_eq!(s.dropped_degenerate, 0);
}

#[test]
fn forward_references_to_later_vertices_are_allowed() {
    let text = "f 1 2 3\nv 0 0 0\nv 1 0 0\no next\nf 1 3 4\nv 0 1 0\nv 0 0 1\n";
    let (c, _) = load_ok("forward", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([1, 3, 4])]);
}

// ---------------------------------------------------------------------------
// The degenerate rule.

#[test]
fn degenerate_triangles_are_dropped_and_counted() {
    let text = "\
v 0 0 0
v 1 0 0
v 0 1 0
v 2 0 0
v 0 0 0
f 1 2 3
f 1 1 2
f 1 2 4
f 2 3 1
f 1 5 2
f 3 3 3
f 2 -4 3
";
    let (c, s) = load_ok("degenerate", text);
    assert_eq!(tris(&c), vec![p([1, 2, 3]), p([2, 3, 1])]);
    assert_eq!(s.dropped_degenerate, 5);
    assert_eq!(s.triangles, 2);
    assert_eq!(
        s.to_string(),
        format!(
            "2 triangles, {} vertices, 5 degenerate triangles dropped",
            s.vertices
        )
    );
}

// ---------------------------------------------------------------------------
// Errors.

#[test]
fn error_nonexistent_file() {
    let path = scratch().join("there-is-no-such-file.obj");
    let err = load_obj(&path).unwrap_err();
    let shown = err.to_string();
    match err {
        SceneError::Io { path: p, source } => {
            assert_eq!(p, path);
            assert_eq!(source.kind(), std::io::ErrorKind::NotFound);
        }
        other => panic!("expected an Io error, got {other:?}"),
    }
    assert!(
        shown.starts_with(&format!("{}: ", path.display())),
        "{shown}"
    );
    assert!(std::error::Error::source(&load_obj(&path).unwrap_err()).is_some());
}

#[test]
fn error_reading_a_folder() {
    let dir = scratch().join("a-folder.obj");
    std::fs::create_dir_all(&dir).unwrap();
    let err = load_obj(&dir).unwrap_err();
    let shown = err.to_string();
    assert!(
        matches!(&err, SceneError::Io { path, .. } if *path == dir),
        "{err:?}"
    );
    assert!(
        shown.starts_with(&format!("{}: ", dir.display())),
        "{shown}"
    );
}

const TAIL: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n";

#[test]
fn error_nan_coordinate() {
    let m = expect_line_error("nan", format!("v 0 0 0\nv nan 0 0\n{TAIL}"), 2);
    assert!(m.contains("non-finite"), "{m}");
    expect_line_error("nan-z", format!("{TAIL}# c\nv 0 0 NaN\n{TAIL}"), 6);
    expect_line_error("nan-neg", format!("v 0 -nan 0\n{TAIL}"), 1);
}

#[test]
fn error_infinite_coordinate() {
    expect_line_error("inf", format!("{TAIL}v inf 0 0\n{TAIL}"), 5);
    expect_line_error("neg-inf", format!("v 0 -inf 0\n{TAIL}"), 1);
    expect_line_error("infinity", format!("\n\nv 0 0 infinity\n{TAIL}"), 3);
    expect_line_error("inf-crlf", format!("v 0 0 0\r\nv 0 0 inf\r\n{TAIL}"), 2);
}

#[test]
fn error_coordinate_overflows_f32() {
    let m = expect_line_error("1e40", format!("v 0 0 0\nv 1e40 0 0\n{TAIL}"), 2);
    assert!(m.contains("non-finite"), "{m}");
    expect_line_error("-1e39", format!("{TAIL}v 0 0 -1e39\n"), 5);
    let long = format!("v 0 {}0 0\n{TAIL}", "9".repeat(40));
    expect_line_error("long-numeral", long, 1);
}

#[test]
fn error_zero_or_bad_weight() {
    expect_line_error("w-zero", format!("v 0 0 0\nv 1 2 3 0\n{TAIL}"), 2);
    expect_line_error("w-zero-origin", format!("v 0 0 0 0\n{TAIL}"), 1);
    expect_line_error("w-tiny", format!("{TAIL}v 1 2 3 1e-45\n"), 5);
    expect_line_error("w-nan", format!("v 1 2 3 nan\n{TAIL}"), 1);
}

#[test]
fn error_unparsable_vertex() {
    let m = expect_line_error("v-x", format!("v 0 0 0\nv 1 x 3\n{TAIL}"), 2);
    assert!(m.contains('x'), "{m}");
    expect_line_error("v-two", format!("{TAIL}v 1 2\n"), 5);
    expect_line_error("v-none", format!("{TAIL}v\n"), 5);
    expect_line_error("v-five", format!("v 1 2 3 4 5\n{TAIL}"), 1);
    expect_line_error("v-eight", format!("v 1 2 3 4 5 6 7 8\n{TAIL}"), 1);
    expect_line_error("v-comma", format!("v 1,0 2 3\n{TAIL}"), 1);
    expect_line_error("v-colour", format!("v 1 2 3 red 0 0\n{TAIL}"), 1);
}

#[test]
fn error_face_index_zero() {
    let m = expect_line_error("zero", format!("{FOUR}f 1 2 3\nf 0 1 2\nf 1 2 4\n"), 6);
    assert!(m.contains('0'), "{m}");
    expect_line_error("zero-slash", format!("{FOUR}vt 0 0\nf 1/1 2/1 0/1\n"), 6);
    expect_line_error("zero-texcoord", format!("{FOUR}vt 0 0\nf 1/1 2/0 3/1\n"), 6);
    expect_line_error(
        "zero-normal",
        format!("{FOUR}vn 0 0 1\nf 1//1 2//1 3//0\n"),
        6,
    );
}

#[test]
fn error_face_index_beyond_vertex_count() {
    // All vertices defined before the bad face.
    let m = expect_line_error("beyond", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99\n", 4);
    assert!(m.contains("99"), "{m}");
    // The bad face is followed by more lines, vertices and objects.
    let text = "\
v 0 0 0
v 1 0 0
v 0 1 0
f 1 2 3
f 1 2 99
v 0 0 1
# more
o next
v 1 1 1
f -1 -2 -3
g other
f 1 2 3
";
    expect_line_error("beyond-then-more", text, 5);
    // The bad face is in the last object, after good objects.
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\no a\nf 1 2 3\no b\nf 3 2 1\nf 3 4 1\n# end\n\n";
    expect_line_error("beyond-last-object", text, 8);
    // Vertices defined only after the bad face, but not enough of them.
    expect_line_error(
        "beyond-forward",
        "f 1 2 5\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n",
        1,
    );
    // Two bad faces: the first one is named.
    expect_line_error(
        "beyond-two",
        format!("{FOUR}f 1 2 3\nf 7 1 2\nf 1 8 2\n"),
        6,
    );
    // A huge index.
    expect_line_error(
        "beyond-huge",
        format!("{FOUR}f 1 2 18446744073709551615\n"),
        5,
    );
}

#[test]
fn error_texcoord_or_normal_index_out_of_range() {
    expect_line_error(
        "vt-relative",
        format!("{FOUR}vt 0 0\nf 1/-1 2/-3 3/-1\n"),
        6,
    );
    expect_line_error(
        "vt-beyond",
        format!("{FOUR}vt 0 0\nf 1/1 2/2 3/1\nf 1 2 4\n"),
        6,
    );
    expect_line_error(
        "vn-beyond",
        format!("{FOUR}vn 0 0 1\nf 1//1 2//1 3//3\nf 1 2 4\n"),
        6,
    );
    expect_line_error(
        "vn-relative",
        format!("{FOUR}vn 0 0 1\nf 1//-1 2//-1 3//-2\n"),
        6,
    );
    expect_line_error("vt-none", format!("{FOUR}f 1/1 2/1 3/1\n"), 5);
}

#[test]
fn error_relative_index_too_negative() {
    let m = expect_line_error("too-negative", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -5 -1 -2\n", 4);
    assert!(m.contains("-5"), "{m}");
    expect_line_error(
        "too-negative-by-one",
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n",
        4,
    );
    // Relative indices count only the vertices before the face.
    expect_line_error(
        "too-negative-early",
        "v 0 0 0\nv 1 0 0\nf -3 -2 -1\nv 0 1 0\n",
        3,
    );
    expect_line_error(
        "too-negative-huge",
        format!("{FOUR}f 1 2 -9223372036854775808\n"),
        5,
    );
}

#[test]
fn error_unparsable_face() {
    let m = expect_line_error("f-a", format!("{FOUR}f 1 a 3\n"), 5);
    assert!(m.contains('a'), "{m}");
    expect_line_error("f-float", format!("{FOUR}f 1 2 3.5\n"), 5);
    expect_line_error(
        "f-four-parts",
        format!("{FOUR}vt 0 0\nvn 0 0 1\nf 1/1/1/1 2 3\n"),
        7,
    );
    expect_line_error("f-no-vertex", format!("{FOUR}vt 0 0\nf /1 2/1 3/1\n"), 6);
    expect_line_error("f-suffix", format!("{FOUR}f 1 2 3x\n"), 5);
    expect_line_error(
        "f-bad-texcoord",
        format!("{FOUR}vt 0 0\nf 1/x 2/1 3/1\n"),
        6,
    );
    expect_line_error(
        "f-overflow",
        format!("{FOUR}f 1 2 99999999999999999999999\n"),
        5,
    );
    expect_line_error("f-empty", format!("{FOUR}f\nf 1 2 3\n"), 5);
}

#[test]
fn error_unparsable_texcoord_or_normal_line() {
    expect_line_error("vt-x", format!("{FOUR}vt 0 x\nf 1 2 3\n"), 5);
    expect_line_error("vt-empty", format!("{FOUR}vt\nf 1 2 3\n"), 5);
    expect_line_error("vn-short", format!("{FOUR}vn 0 0\nf 1 2 3\n"), 5);
    expect_line_error("vn-x", format!("vn 0 1 z\n{FOUR}f 1 2 3\n"), 1);
}

#[test]
fn error_invalid_utf8() {
    let mut text = b"v 0 0 0\nv 1 0 0\n# caf".to_vec();
    text.extend_from_slice(b"\xe9\nv 0 1 0\nf 1 2 3\n");
    let m = expect_line_error("latin1-comment", &text, 3);
    assert!(m.contains("UTF-8"), "{m}");
    let mut text = b"v 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nf 1 2 3\r\no \xff\xfe\r\n".to_vec();
    text.extend_from_slice(b"f 1 2 3\r\n");
    expect_line_error("bad-utf8-object", &text, 5);
    expect_line_error(
        "bad-utf8-vertex",
        b"v 0 0 0\nv 1 \x80 0\nv 0 1 0\nf 1 2 3\n",
        2,
    );
    // A lone surrogate half encoded in UTF-8 style is not UTF-8 either.
    expect_line_error(
        "surrogate",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n#\xed\xa0\x80",
        5,
    );
}

#[test]
fn error_no_triangles() {
    let m = expect_invalid("vertices-only", "v 0 0 0\nv 1 0 0\nv 0 1 0\n");
    assert!(m.contains("no triangles"), "{m}");
    let m = expect_invalid(
        "short-faces-only",
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\nf 3\nl 1 2 3\np 1 2 3\n",
    );
    assert!(m.contains("no triangles"), "{m}");
    let m = expect_invalid("comments-only", "# nothing\n\n# at all\r\n");
    assert!(m.contains("no triangles"), "{m}");
}

#[test]
fn error_empty_file() {
    let m = expect_invalid("empty", "");
    assert!(m.contains("no triangles"), "{m}");
    let m = expect_invalid("newline", "\n");
    assert!(m.contains("no triangles"), "{m}");
}

#[test]
fn error_only_degenerate_faces() {
    let text = "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nf 1 1 2\nf 3 3 3\n";
    let m = expect_invalid("all-degenerate", text);
    assert!(
        m.contains("no triangles") && m.contains('3') && m.contains("degenerate"),
        "{m}"
    );
}

#[test]
fn error_display_names_file_and_line() {
    let name = Path::new("scenes/some thing.obj");
    let err = load_obj_bytes(name, b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 x\n").unwrap_err();
    assert!(
        err.to_string().starts_with("scenes/some thing.obj:5: "),
        "{err}"
    );
    let err = load_obj_bytes(name, b"").unwrap_err();
    assert!(
        err.to_string().starts_with("scenes/some thing.obj: "),
        "{err}"
    );
}

#[test]
fn shipped_scenes_load() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
    for name in ["bunny_npm.obj", "nexuiz_dieselpower.obj"] {
        let path = dir.join(name);
        if !path.exists() {
            continue;
        }
        let (c, s) = load_obj(&path).unwrap_or_else(|e| panic!("{e}"));
        check_columns(&c, &s);
        assert!(c.len() > 1000, "{name}: {s}");
    }
}

// ---------------------------------------------------------------------------
// Properties.

/// The number of lines in `bytes` (a last line need not end in `\n`).
fn line_count(bytes: &[u8]) -> u64 {
    bytes.split(|&b| b == b'\n').count() as u64
        - u64::from(bytes.last().is_none_or(|&b| b == b'\n'))
}

/// Checks that loading returns without panicking, and that what it returns
/// obeys the rules.
fn check_returns(bytes: &[u8]) -> Result<(), TestCaseError> {
    let name = Path::new("fuzz/input.obj");
    let result = std::panic::catch_unwind(|| load_obj_bytes(name, bytes));
    let lines = line_count(bytes);
    match result {
        Err(_) => {
            prop_assert!(
                false,
                "the loader panicked on {:?}",
                String::from_utf8_lossy(bytes)
            );
        }
        Ok(Ok((columns, summary))) => {
            let n = columns.positions().len();
            prop_assert!(!columns.is_empty());
            prop_assert!(
                columns
                    .indices()
                    .iter()
                    .flatten()
                    .all(|&i| (i as usize) < n)
            );
            prop_assert!(columns.positions().iter().all(|q| q.is_finite()));
            prop_assert_eq!(summary.triangles, columns.len());
            prop_assert_eq!(summary.lines, lines);
        }
        Ok(Err(e)) => {
            let shown = e.to_string();
            prop_assert!(shown.contains("fuzz/input.obj"), "{}", shown);
            if let SceneError::Line { line, .. } = e {
                prop_assert!(
                    line >= 1 && line <= lines,
                    "line {} of {}: {}",
                    line,
                    lines,
                    shown
                );
            }
        }
    }
    Ok(())
}

const BASE: &str = "\
# base
mtllib base.mtl
o cube
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0 1
v 0 0 1 0.5 0.5 0.5
vt 0 0
vt 1 0
vn 0 0 1
usemtl red
s 1
f 1 2 3
f 1/1 3/2 4/1
f 1//1 2//1 5//1
f -5/-2/-1 -4/-1/-1 -1/-1/-1
g side
f 1 2 3 4 5
l 1 2 3
p 4
";

#[derive(Clone, Debug)]
enum Edit {
    Delete(usize),
    Duplicate(usize),
    Swap(usize, usize),
    Replace(usize, usize, String),
    Insert(usize, String),
}

/// A replacement word: a number, an index form or a keyword.
fn word() -> impl Strategy<Value = String> {
    prop_oneof![
        any::<f32>().prop_map(|x| x.to_string()),
        any::<f64>().prop_map(|x| format!("{x:e}")),
        any::<i64>().prop_map(|x| x.to_string()),
        (-12i64..12).prop_map(|x| x.to_string()),
        ((-8i64..8), (-3i64..3), (-3i64..3)).prop_map(|(a, b, c)| format!("{a}/{b}/{c}")),
        ((-8i64..8), (-3i64..3)).prop_map(|(a, b)| format!("{a}//{b}")),
        prop::sample::select(vec![
            "nan",
            "inf",
            "-inf",
            "1e40",
            "-1e39",
            "1e-45",
            "0",
            "-0",
            "x",
            "",
            "/",
            "//",
            "#",
            "v",
            "vt",
            "vn",
            "f",
            "o",
            "g",
            "l",
            "p",
            "usemtl",
            "mtllib",
            "\t",
            "\r",
            "\u{feff}",
            "é",
            "99999999999999999999",
        ])
        .prop_map(str::to_string),
        "[ -~]{0,8}",
    ]
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        any::<prop::sample::Index>().prop_map(|i| Edit::Delete(i.index(64))),
        any::<prop::sample::Index>().prop_map(|i| Edit::Duplicate(i.index(64))),
        (0usize..64, 0usize..64).prop_map(|(a, b)| Edit::Swap(a, b)),
        (0usize..64, 0usize..8, word()).prop_map(|(l, w, s)| Edit::Replace(l, w, s)),
        (0usize..64, prop::collection::vec(word(), 0..6))
            .prop_map(|(l, ws)| Edit::Insert(l, ws.join(" "))),
    ]
}

/// Applies edits to `BASE`, then cuts the bytes at `cut` (if any).
fn mutate(edits: &[Edit], cut: Option<prop::sample::Index>, crlf: bool) -> Vec<u8> {
    let mut lines: Vec<String> = BASE.lines().map(str::to_string).collect();
    for e in edits {
        let n = lines.len();
        match e {
            Edit::Delete(i) if n > 0 => {
                lines.remove(i % n);
            }
            Edit::Duplicate(i) if n > 0 => {
                let l = lines[i % n].clone();
                lines.insert(i % n, l);
            }
            Edit::Swap(a, b) if n > 0 => lines.swap(a % n, b % n),
            Edit::Replace(i, w, s) if n > 0 => {
                let mut words: Vec<String> = lines[i % n].split(' ').map(str::to_string).collect();
                let k = w % words.len();
                words[k] = s.clone();
                lines[i % n] = words.join(" ");
            }
            Edit::Insert(i, s) => lines.insert(i % (n + 1), s.clone()),
            _ => {}
        }
    }
    let mut bytes = lines.join(if crlf { "\r\n" } else { "\n" }).into_bytes();
    if let Some(cut) = cut {
        bytes.truncate(cut.index(bytes.len() + 1));
    }
    bytes
}

/// A small valid scene, as events: vertices, faces over the vertices so
/// far (each corner a choice and an index form), and ignored lines.
#[derive(Clone, Debug)]
enum Event {
    Vertex(i8, i8, i8),
    Face(Vec<(prop::sample::Index, u8)>),
    Other(u8),
}

fn event() -> impl Strategy<Value = Event> {
    prop_oneof![
        4 => (-3i8..=3, -3i8..=3, -3i8..=3).prop_map(|(x, y, z)| Event::Vertex(x, y, z)),
        3 => prop::collection::vec((any::<prop::sample::Index>(), 0u8..8), 3..7).prop_map(Event::Face),
        1 => (0u8..10).prop_map(Event::Other),
    ]
}

/// The text of a scene and its triangles by the loader's rules (fan
/// triangulation, file order, degenerate triangles dropped).
fn render(events: &[Event]) -> (Vec<String>, Vec<[Vec3; 3]>, usize) {
    let mut lines = vec![
        "vt 0 0".to_string(),
        "vt 1 1".to_string(),
        "vn 0 0 1".to_string(),
    ];
    let mut positions: Vec<Vec3> = Vec::new();
    let mut expected = Vec::new();
    let mut dropped = 0;
    for e in events {
        match e {
            Event::Vertex(x, y, z) => {
                positions.push(v(f32::from(*x), f32::from(*y), f32::from(*z)));
                lines.push(format!("v {x} {y} {z}"));
            }
            Event::Face(corners) if !positions.is_empty() => {
                let n = positions.len();
                let mut words = Vec::new();
                let mut abs = Vec::new();
                for (choice, form) in corners {
                    let i = choice.index(n) + 1; // 1-based
                    abs.push(i);
                    let shown = if form & 4 != 0 {
                        format!("-{}", n + 1 - i)
                    } else {
                        i.to_string()
                    };
                    words.push(match form & 3 {
                        0 => shown,
                        1 => format!("{shown}/2"),
                        2 => format!("{shown}//1"),
                        _ => format!("{shown}/-1/-1"),
                    });
                }
                lines.push(format!("f {}", words.join(" ")));
                for k in 1..abs.len() - 1 {
                    let t = [abs[0], abs[k], abs[k + 1]];
                    let tri = t.map(|i| positions[i - 1]);
                    if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] || double_area(&tri) == 0.0 {
                        dropped += 1;
                    } else {
                        expected.push(tri);
                    }
                }
            }
            Event::Face(_) => {}
            Event::Other(k) => lines.push(
                [
                    "# comment",
                    "",
                    "o object",
                    "g group",
                    "s 1",
                    "usemtl m",
                    "mtllib m.mtl",
                    "l 1 1",
                    "vt 0.5 0.5",
                    "vn 1 0 0",
                ][usize::from(*k)]
                .to_string(),
            ),
        }
    }
    (lines, expected, dropped)
}

/// Bad lines that fail wherever they are put in a valid scene.
const BAD_LINES: &[&[u8]] = &[
    b"v nan 0 0",
    b"v 0 inf 0",
    b"v 1e40 0 0",
    b"v 1 2 3 0",
    b"v 1 x 3",
    b"v 1 2",
    b"f 1 a 3",
    b"f 0 1 1",
    b"f 1 1 -100000",
    b"f 1 1 100000",
    b"f 1/1/1/1 1 1",
    b"f",
    b"vn 0 0",
    b"# \xff",
    b"o \xc3",
];

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 2048,
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    #[test]
    fn never_panics_on_random_bytes(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
        check_returns(&bytes)?;
    }

    #[test]
    fn never_panics_on_obj_like_bytes(
        bytes in prop::collection::vec(
            prop::sample::select(b"vftonlpg/-+0123456789.eE#x \t\r\n\n\n".to_vec()), 0..400)
    ) {
        check_returns(&bytes)?;
    }

    #[test]
    fn never_panics_on_mutated_obj(
        edits in prop::collection::vec(edit(), 0..10),
        cut in prop::option::weighted(0.3, any::<prop::sample::Index>()),
        crlf in any::<bool>(),
    ) {
        check_returns(&mutate(&edits, cut, crlf))?;
    }

    #[test]
    fn random_valid_scenes_load_as_written(events in prop::collection::vec(event(), 0..40)) {
        let (lines, expected, dropped) = render(&events);
        let text = lines.join("\n");
        let result = load_obj_bytes(Path::new("valid.obj"), text.as_bytes());
        if expected.is_empty() {
            prop_assert!(matches!(result, Err(SceneError::Invalid { .. })), "{:?}\n{}", result, text);
        } else {
            let (columns, summary) = result.map_err(|e| TestCaseError::fail(format!("{e}\n{text}")))?;
            prop_assert_eq!(tris(&columns), expected, "{}", text);
            prop_assert_eq!(summary.dropped_degenerate, dropped);
            prop_assert_eq!(summary.lines, line_count(text.as_bytes()));
        }
    }

    #[test]
    fn a_bad_line_is_named_wherever_it_is(
        events in prop::collection::vec(event(), 0..30),
        at in any::<prop::sample::Index>(),
        bad in prop::sample::select(BAD_LINES),
        crlf in any::<bool>(),
    ) {
        let (lines, _, _) = render(&events);
        let k = at.index(lines.len() + 1);
        let mut bytes = Vec::new();
        for (i, l) in lines.iter().enumerate() {
            if i == k {
                bytes.extend_from_slice(bad);
                bytes.extend_from_slice(if crlf { b"\r\n" } else { b"\n" });
            }
            bytes.extend_from_slice(l.as_bytes());
            bytes.extend_from_slice(if crlf { b"\r\n" } else { b"\n" });
        }
        if k == lines.len() {
            bytes.extend_from_slice(bad);
        }
        let shown = String::from_utf8_lossy(&bytes).into_owned();
        match load_obj_bytes(Path::new("bad.obj"), &bytes) {
            Err(SceneError::Line { line, message, .. }) => {
                prop_assert_eq!(line, k as u64 + 1, "{}\n{}", message, shown);
            }
            other => prop_assert!(false, "expected a line error at line {}, got {:?}\n{}", k + 1, other, shown),
        }
    }
}

/// Loading an OBJ file advances its progress (the CLI's bar) to exactly 1,
/// and watching it changes nothing loaded; a scene cache finishes at once.
#[test]
fn load_progress_ends_at_one() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/nexuiz_dieselpower.obj");
    let progress = slimkd::progress::Progress::default();
    let (watched, _) = slimkd::scene::load_with_progress(&path, Some(&progress)).unwrap();
    assert_eq!(progress.fraction(), 1.0);
    let (plain, _) = load_obj(&path).unwrap();
    assert_eq!(tris(&watched), tris(&plain));
    let cache = scratch().join("progress.kds");
    let (_, summary) = load_obj(&path).unwrap();
    slimkd::scene::write_scene_cache(&cache, &plain, &summary).unwrap();
    let progress = slimkd::progress::Progress::default();
    slimkd::scene::load_with_progress(&cache, Some(&progress)).unwrap();
    assert_eq!(progress.fraction(), 1.0);
    std::fs::remove_file(&cache).unwrap();
}

/// An error that quotes the line carries none of its control bytes: a
/// terminal escape sequence (`ESC [31m`) is shown escaped, not sent to
/// the terminal; so is a quoted word of a views file.
#[test]
fn error_messages_escape_control_bytes() {
    let m = expect_line_error("escape", format!("v 1\x1b[31mX 2 3\n{TAIL}"), 1);
    assert!(m.contains("1\\u{1b}[31mX"), "{m}");
    let m = expect_line_error("face-escape", format!("{TAIL}f 1 2 3\x07\x1b]0;t\n"), 5);
    assert!(m.contains("\\u{7}\\u{1b}]0;t"), "{m}");
    let views =
        slimkd::render::parse_views("scene v1 eye=0,0,1 at=0,0,0 up=0,1,0 fov=40 b\x1bc=1\n");
    let shown = views.unwrap_err().to_string();
    assert!(shown.contains("b\\u{1b}c"), "{shown}");
    for m in [m, shown] {
        assert!(!m.chars().any(char::is_control), "{m:?}");
    }
}

/// A FIFO is refused at once, named as one (an `open` of it would wait for
/// a writer forever).
#[cfg(target_os = "linux")]
#[test]
fn error_reading_a_fifo() {
    let fifo = scratch().join("a-fifo.obj");
    let _ = std::fs::remove_file(&fifo);
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    if !made.is_ok_and(|s| s.success()) {
        common::skip("mkfifo is not available");
        return;
    }
    let err = load_obj(&fifo).unwrap_err();
    assert!(
        matches!(&err, SceneError::Io { path, .. } if *path == fifo),
        "{err:?}"
    );
    assert!(
        err.to_string().ends_with("not a regular file (a FIFO)"),
        "{err}"
    );
    let err = slimkd::scene::load_scene_cache(&fifo).unwrap_err();
    assert!(
        err.to_string().contains("not a regular file (a FIFO)"),
        "{err}"
    );
    std::fs::remove_file(&fifo).ok();
}
