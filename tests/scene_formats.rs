//! The scene formats beside OBJ (`slimkd::scene`): PLY (ASCII, binary
//! little- and big-endian), glTF (embedded and side buffers), GLB and
//! gzip-compressed OBJ and PLY load to the same triangles as the OBJ of the
//! same mesh, so build the same `.kd` bytes; glTF node transforms are
//! applied; malformed files of each format give errors naming the file and
//! the line or element; NaN coordinates are refused; degenerate triangles
//! dropped and counted; names are dispatched by extension, and a `.kd`
//! file given as a scene is named as such.
//!
//! Every fixture is written by the code here.

mod common;

use base64::Engine;
use common::{fresh_temp_dir, temp_dir};
use glam::Vec3;
use slimkd::accel::{Accel, BuildOptions};
use slimkd::scene::{self, LoadSummary, SceneError, SceneFormat, TriangleColumns};
use std::io::Write;
use std::path::{Path, PathBuf};

type Loaded = Result<(TriangleColumns, LoadSummary), SceneError>;

/// A small mesh: a slanted grid of quads split in two, plus a box, with
/// coordinates that are not integers (so rounding would show), every
/// vertex used, in order of first use.
fn mesh() -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let mut v = Vec::new();
    let mut f = Vec::new();
    for i in 0..4 {
        for j in 0..4 {
            let (x, y) = (i as f32 * 1.25, j as f32 * 0.75);
            let base = v.len() as u32;
            v.push([x, y, 0.1 * i as f32]);
            v.push([x + 1.0, y, 0.3]);
            v.push([x + 1.0, y + 0.5, 0.7]);
            v.push([x, y + 0.5, 1.0 / 3.0]);
            f.push([base, base + 1, base + 2]);
            f.push([base, base + 2, base + 3]);
        }
    }
    let base = v.len() as u32;
    for k in 0..8u32 {
        let c = |b: u32| if k >> b & 1 == 1 { 6.5 } else { -2.25 };
        v.push([c(0), c(1), c(2)]);
    }
    for q in [
        [0, 1, 3, 2],
        [4, 6, 7, 5],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 5, 7, 3],
    ] {
        f.push([base + q[0], base + q[1], base + q[2]]);
        f.push([base + q[0], base + q[2], base + q[3]]);
    }
    // Renumbered in order of first use, as the OBJ loader numbers them.
    let mut new = vec![u32::MAX; v.len()];
    let mut order = Vec::new();
    for i in f.iter_mut().flatten() {
        if new[*i as usize] == u32::MAX {
            new[*i as usize] = order.len() as u32;
            order.push(v[*i as usize]);
        }
        *i = new[*i as usize];
    }
    (order, f)
}

fn obj_text(v: &[[f32; 3]], f: &[[u32; 3]]) -> String {
    let mut s = String::new();
    for p in v {
        s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    for t in f {
        s += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

fn ply_ascii(v: &[[f32; 3]], f: &[[u32; 3]]) -> Vec<u8> {
    let mut s = format!(
        "ply\nformat ascii 1.0\ncomment written by tests/scene_formats.rs\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nelement face {}\nproperty list uchar int vertex_indices\n\
         element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n",
        v.len(),
        f.len()
    );
    for p in v {
        s += &format!("{} {} {} 200\n", p[0], p[1], p[2]);
    }
    for t in f {
        s += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    s += "0 1\n";
    s.into_bytes()
}

/// Binary PLY; `big`: big-endian; `double`: coordinates as `double`.
fn ply_binary(v: &[[f32; 3]], f: &[[u32; 3]], big: bool, double: bool) -> Vec<u8> {
    let ty = if double { "double" } else { "float" };
    let mut out = format!(
        "ply\nformat binary_{}_endian 1.0\nelement vertex {}\n\
         property {ty} x\nproperty {ty} y\nproperty {ty} z\n\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        if big { "big" } else { "little" },
        v.len(),
        f.len()
    )
    .into_bytes();
    let word4 = |out: &mut Vec<u8>, w: u32| {
        out.extend_from_slice(&if big {
            w.to_be_bytes()
        } else {
            w.to_le_bytes()
        })
    };
    for p in v {
        for c in p {
            if double {
                let d = f64::from(*c).to_bits();
                out.extend_from_slice(&if big {
                    d.to_be_bytes()
                } else {
                    d.to_le_bytes()
                });
            } else {
                word4(&mut out, c.to_bits());
            }
        }
    }
    for t in f {
        out.push(3);
        for &i in t {
            word4(&mut out, i);
        }
    }
    out
}

/// One node, its children and transform, in a glTF document.
struct GltfNode {
    mesh: Option<usize>,
    children: Vec<usize>,
    /// `"translation": [...], "scale": [...]` or empty.
    transform: String,
}

/// The binary buffer and the JSON of a glTF document of one mesh
/// (`v`, `f`) under `nodes` (the scene's roots: `roots`); `uri`: the
/// buffer's URI (`None` for the GLB binary chunk).
fn gltf_json(
    v: &[[f32; 3]],
    f: &[[u32; 3]],
    nodes: &[GltfNode],
    roots: &[usize],
    uri: Option<&str>,
) -> (String, Vec<u8>) {
    let mut bin = Vec::new();
    for p in v {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let pos_len = bin.len();
    for t in f {
        for i in t {
            bin.extend_from_slice(&i.to_le_bytes());
        }
    }
    let lo = (0..3).map(|k| v.iter().map(|p| p[k]).fold(f32::INFINITY, f32::min));
    let hi = (0..3).map(|k| v.iter().map(|p| p[k]).fold(f32::NEG_INFINITY, f32::max));
    let list = |it: &mut dyn Iterator<Item = f32>| {
        it.map(|x| format!("{x:?}")).collect::<Vec<_>>().join(",")
    };
    let nodes_json: Vec<String> = nodes
        .iter()
        .map(|n| {
            let mut parts = Vec::new();
            if let Some(m) = n.mesh {
                parts.push(format!("\"mesh\":{m}"));
            }
            if !n.children.is_empty() {
                let c: Vec<String> = n.children.iter().map(|c| c.to_string()).collect();
                parts.push(format!("\"children\":[{}]", c.join(",")));
            }
            if !n.transform.is_empty() {
                parts.push(n.transform.clone());
            }
            format!("{{{}}}", parts.join(","))
        })
        .collect();
    let uri = uri.map_or(String::new(), |u| format!("\"uri\":\"{u}\","));
    let roots: Vec<String> = roots.iter().map(|r| r.to_string()).collect();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[{roots}]}}],
"nodes":[{nodes}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
"buffers":[{{{uri}"byteLength":{len}}}],
"bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":{pos_len}}},{{"buffer":0,"byteOffset":{pos_len},"byteLength":{idx_len}}}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":{nv},"type":"VEC3","min":[{lo}],"max":[{hi}]}},
{{"bufferView":1,"componentType":5125,"count":{ni},"type":"SCALAR"}}]}}"#,
        roots = roots.join(","),
        nodes = nodes_json.join(","),
        len = bin.len(),
        idx_len = bin.len() - pos_len,
        nv = v.len(),
        ni = 3 * f.len(),
        lo = list(&mut lo.into_iter()),
        hi = list(&mut hi.into_iter()),
    );
    (json, bin)
}

/// One node holding the mesh, no transform.
fn plain() -> Vec<GltfNode> {
    vec![GltfNode {
        mesh: Some(0),
        children: vec![],
        transform: String::new(),
    }]
}

fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut j = json.as_bytes().to_vec();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + j.len() + 8 + b.len();
    let mut out = Vec::new();
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(j.len() as u32).to_le_bytes());
    out.extend_from_slice(&0x4E4F_534Au32.to_le_bytes());
    out.extend_from_slice(&j);
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(&0x004E_4942u32.to_le_bytes());
    out.extend_from_slice(&b);
    out
}

fn data_uri(bin: &[u8]) -> String {
    format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(bin)
    )
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

fn write(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

/// Every format of the mesh `v`, `f` written into `dir`, by name.
fn every_format(dir: &Path, v: &[[f32; 3]], f: &[[u32; 3]]) -> Vec<PathBuf> {
    let (side_json, bin) = gltf_json(v, f, &plain(), &[0], Some("mesh.bin"));
    write(dir, "mesh.bin", &bin);
    let (embedded_json, _) = gltf_json(v, f, &plain(), &[0], Some(&data_uri(&bin)));
    let (glb_json, _) = gltf_json(v, f, &plain(), &[0], None);
    vec![
        write(dir, "mesh.ply", ply_ascii(v, f)),
        write(dir, "mesh-le.ply", ply_binary(v, f, false, false)),
        write(dir, "mesh-be.ply", ply_binary(v, f, true, false)),
        write(dir, "mesh-double.ply", ply_binary(v, f, false, true)),
        write(dir, "mesh-side.gltf", side_json),
        write(dir, "mesh-embedded.gltf", embedded_json),
        write(dir, "mesh.glb", glb(&glb_json, &bin)),
        write(dir, "mesh.obj.gz", gzip(obj_text(v, f).as_bytes())),
        write(dir, "mesh.PLY.GZ", gzip(&ply_binary(v, f, false, false))),
    ]
}

fn tree_bytes(scene: &TriangleColumns) -> Vec<u8> {
    Accel::build(scene, &BuildOptions::default())
        .unwrap()
        .as_bytes()
        .to_vec()
}

fn loaded(path: &Path) -> (TriangleColumns, LoadSummary) {
    scene::load(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn err(loaded: Loaded) -> String {
    match loaded {
        Ok((s, m)) => panic!("loaded {} triangles ({m:?}), expected an error", s.len()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn every_format_loads_the_triangles_of_the_obj_and_builds_its_tree() {
    let dir = fresh_temp_dir("formats-same");
    let (v, f) = mesh();
    let obj = write(&dir, "mesh.obj", obj_text(&v, &f));
    let (reference, ref_summary) = loaded(&obj);
    assert_eq!(reference.len(), f.len());
    let reference_bytes = tree_bytes(&reference);
    for path in every_format(&dir, &v, &f) {
        let (scene, summary) = loaded(&path);
        assert_eq!(scene, reference, "{}", path.display());
        assert_eq!(summary.triangles, ref_summary.triangles);
        assert_eq!(summary.vertices, ref_summary.vertices);
        assert_eq!(summary.dropped_degenerate, 0);
        assert_eq!(tree_bytes(&scene), reference_bytes, "{}", path.display());
    }
}

#[test]
fn a_scene_cache_of_every_format_holds_its_columns() {
    let dir = fresh_temp_dir("formats-cache");
    let (v, f) = mesh();
    for path in every_format(&dir, &v, &f) {
        let (scene, summary) = loaded(&path);
        let kds = dir.join("cache.kds");
        scene::write_scene_cache(&kds, &scene, &summary).unwrap();
        assert_eq!(loaded(&kds), (scene, summary), "{}", path.display());
    }
}

#[test]
fn gltf_node_transforms_are_applied_from_the_root_down() {
    let dir = fresh_temp_dir("formats-transform");
    let (v, f) = mesh();
    // Node 0: scale 2, then translate (1, 2, 3), holding the mesh; its
    // child node 1: translate (0, 0, 10), holding the mesh again. Node 2,
    // under a matrix (a translation by (-5, 0, 0)), holds it a third time.
    let nodes = vec![
        GltfNode {
            mesh: Some(0),
            children: vec![1],
            transform: r#""translation":[1,2,3],"scale":[2,2,2]"#.into(),
        },
        GltfNode {
            mesh: Some(0),
            children: vec![],
            transform: r#""translation":[0,0,10]"#.into(),
        },
        GltfNode {
            mesh: Some(0),
            children: vec![],
            transform: r#""matrix":[1,0,0,0, 0,1,0,0, 0,0,1,0, -5,0,0,1]"#.into(),
        },
    ];
    let (json, bin) = gltf_json(&v, &f, &nodes, &[0, 2], None);
    let path = write(&dir, "moved.glb", glb(&json, &bin));
    let (scene, _) = loaded(&path);
    let moved = |m: &dyn Fn(f64, usize) -> f64| -> Vec<[f32; 3]> {
        v.iter()
            .map(|p| [0, 1, 2].map(|k| m(f64::from(p[k]), k) as f32))
            .collect()
    };
    let t = [1.0, 2.0, 3.0];
    let mut all_v = moved(&|x, k| 2.0 * x + t[k]);
    all_v.extend(moved(&|x, k| {
        2.0 * (x + if k == 2 { 10.0 } else { 0.0 }) + t[k]
    }));
    all_v.extend(moved(&|x, k| x + if k == 0 { -5.0 } else { 0.0 }));
    let n = v.len() as u32;
    let all_f: Vec<[u32; 3]> = (0..3)
        .flat_map(|c| f.iter().map(move |t| t.map(|i| i + c * n)))
        .collect();
    let expected =
        TriangleColumns::new(all_v.iter().map(|p| Vec3::from_array(*p)).collect(), all_f).unwrap();
    assert_eq!(scene, expected);
}

#[test]
fn degenerate_triangles_are_dropped_and_counted_in_every_format() {
    let dir = fresh_temp_dir("formats-degenerate");
    let (mut v, mut f) = mesh();
    // A triangle repeating a vertex and a collinear one.
    let n = v.len() as u32;
    v.extend([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]);
    f.insert(3, [0, 0, 1]);
    f.push([n, n + 1, n + 2]);
    let (reference, summary) = loaded(&write(&dir, "mesh.obj", obj_text(&v, &f)));
    assert_eq!(summary.dropped_degenerate, 2);
    for path in every_format(&dir, &v, &f) {
        let (scene, summary) = loaded(&path);
        assert_eq!(summary.dropped_degenerate, 2, "{}", path.display());
        assert_eq!(scene, reference, "{}", path.display());
    }
}

#[test]
fn a_nan_coordinate_is_refused_in_every_format() {
    let dir = fresh_temp_dir("formats-nan");
    let (mut v, f) = mesh();
    v[5][1] = f32::NAN;
    for path in every_format(&dir, &v, &f) {
        let e = err(scene::load(&path));
        assert!(e.contains(path.to_str().unwrap()), "{e}");
        let named = match SceneFormat::of_path(&path).unwrap() {
            // ASCII PLY: the parser refuses `NaN` as a number, at its line.
            SceneFormat::Ply if path.ends_with("mesh.ply") => e.contains("mesh.ply:20:"),
            SceneFormat::Ply | SceneFormat::PlyGz => e.contains("vertex 5: coordinate"),
            SceneFormat::Gltf | SceneFormat::Glb => e.contains("vertex 5: coordinate"),
            // The OBJ line of the sixth vertex.
            _ => e.contains(":6:") && e.contains("non-finite"),
        };
        assert!(named, "{e}");
    }
}

#[test]
fn an_infinite_coordinate_is_refused() {
    let dir = temp_dir("formats-inf");
    let (mut v, f) = mesh();
    v[2][0] = f32::INFINITY;
    let e = err(scene::load(&write(
        &dir,
        "inf.ply",
        ply_binary(&v, &f, true, false),
    )));
    assert!(e.contains("inf.ply: vertex 2: "), "{e}");
    // A double beyond the range of f32 is infinite once rounded.
    let mut bytes = ply_binary(&mesh().0, &f, false, true);
    let at = bytes.len() - (f.len() * 13) - mesh().0.len() * 24;
    bytes[at..at + 8].copy_from_slice(&1e300f64.to_le_bytes());
    let e = err(scene::load(&write(&dir, "huge.ply", bytes)));
    assert!(e.contains("huge.ply: vertex 0: "), "{e}");
}

#[test]
fn malformed_ply_files_give_errors_naming_the_file_and_line_or_element() {
    let dir = fresh_temp_dir("formats-bad-ply");
    let (v, f) = mesh();
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("not-ply.ply", b"solid stl\n".to_vec(), "not-ply.ply:1:"),
        (
            "bad-header.ply",
            b"ply\nformat ascii 1.0\nelement vertex many\nend_header\n".to_vec(),
            "bad-header.ply:3:",
        ),
        (
            "no-face.ply",
            {
                let text = String::from_utf8(ply_ascii(&v, &f)).unwrap();
                text.replace("element face", "element facet").into_bytes()
            },
            "no-face.ply: no `face` element",
        ),
        (
            "no-z.ply",
            {
                let text = String::from_utf8(ply_ascii(&v, &f)).unwrap();
                text.replace("property float z", "property float w")
                    .into_bytes()
            },
            "no-z.ply: the `vertex` element has no `z` property",
        ),
        (
            "bad-number.ply",
            {
                let text = String::from_utf8(ply_ascii(&v, &f)).unwrap();
                text.replacen(" 200\n", " 200\n1 2 x 200\n", 1).into_bytes()
            },
            "bad-number.ply:16:",
        ),
        (
            "truncated.ply",
            {
                let b = ply_binary(&v, &f, false, false);
                b[..b.len() - 7].to_vec()
            },
            "truncated.ply: `face` elements: ",
        ),
        (
            "truncated-vertices.ply",
            {
                let b = ply_binary(&v, &f, true, false);
                let header = b.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
                b[..header + 20].to_vec()
            },
            "truncated-vertices.ply: `vertex` elements: ",
        ),
        (
            "index.ply",
            {
                let mut f = f.clone();
                f[7][1] = v.len() as u32;
                ply_binary(&v, &f, false, false)
            },
            "index.ply: face 7: vertex index 72 out of range",
        ),
        (
            "negative.ply",
            {
                let text = String::from_utf8(ply_ascii(&v, &f)).unwrap();
                text.replacen("3 0 1 2\n", "3 0 -1 2\n", 1).into_bytes()
            },
            "negative.ply: face 0: vertex index -1 out of range",
        ),
        (
            "float-list.ply",
            {
                let text = String::from_utf8(ply_ascii(&v, &f)).unwrap();
                text.replace("list uchar int", "list uchar float")
                    .into_bytes()
            },
            "float-list.ply: the `face` property `vertex_indices` is not a list of integers",
        ),
        (
            "no-faces.ply",
            {
                let text = String::from_utf8(ply_ascii(&v, &[])).unwrap();
                text.into_bytes()
            },
            "no-faces.ply: no triangles",
        ),
    ];
    for (name, bytes, expected) in cases {
        let e = err(scene::load(&write(&dir, name, &bytes)));
        assert!(e.contains(expected), "{name}: {e}");
        // The same from memory.
        let e2 = err(scene::load_ply_bytes(&dir.join(name), &bytes));
        assert_eq!(e, e2);
    }
}

#[test]
fn malformed_gltf_files_give_errors_naming_the_file_and_part() {
    let dir = fresh_temp_dir("formats-bad-gltf");
    let (v, f) = mesh();
    let (json, bin) = gltf_json(&v, &f, &plain(), &[0], Some("side.bin"));
    write(&dir, "side.bin", &bin);
    let (glb_json, _) = gltf_json(&v, &f, &plain(), &[0], None);
    let good_glb = glb(&glb_json, &bin);
    let mut bad_index = bin.clone();
    let at = v.len() * 12 + 4 * 10;
    bad_index[at..at + 4].copy_from_slice(&999u32.to_le_bytes());
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        (
            "syntax.gltf",
            json.replacen("\"nodes\"", "\"nodes\" oops", 1).into_bytes(),
            "syntax.gltf: not a valid glTF file: ",
        ),
        (
            "missing.gltf",
            json.replace("side.bin", "nowhere.bin").into_bytes(),
            "missing.gltf: buffer 0: ",
        ),
        (
            "short.gltf",
            json.replace(
                &format!("\"byteLength\":{}}}]", bin.len()),
                &format!("\"byteLength\":{}}}]", bin.len() + 4),
            )
            .into_bytes(),
            "short.gltf: buffer 0: ",
        ),
        (
            "outside.gltf",
            json.replacen(
                &format!("\"count\":{}", v.len()),
                &format!("\"count\":{}", v.len() + 1),
                1,
            )
            .into_bytes(),
            "outside.gltf: node 0 mesh 0 primitive 0: the POSITION accessor",
        ),
        (
            "range.gltf",
            json.replacen(
                &format!("\"count\":{}", 3 * f.len()),
                &format!("\"count\":{}", 3 * f.len() + 1),
                1,
            )
            .into_bytes(),
            "range.gltf: node 0 mesh 0 primitive 0: the index accessor",
        ),
        (
            "ref.gltf",
            json.replace("\"POSITION\":0", "\"POSITION\":7")
                .into_bytes(),
            "ref.gltf: not a valid glTF file: ",
        ),
        (
            "truncated.glb",
            good_glb[..good_glb.len() - 40].to_vec(),
            "truncated.glb: ",
        ),
        (
            "index.glb",
            glb(&glb_json, &bad_index),
            "index.glb: node 0 mesh 0 primitive 0: index 10: vertex 999 out of range",
        ),
        (
            "cycle.gltf",
            json.replace("{\"mesh\":0}", "{\"mesh\":0,\"children\":[0]}")
                .into_bytes(),
            "cycle.gltf: ",
        ),
    ];
    for (name, bytes, expected) in cases {
        eprintln!("{name}");
        let e = err(scene::load(&write(&dir, name, &bytes)));
        assert!(e.contains(expected), "{name}: {e}");
        let e2 = err(scene::load_gltf_bytes(&dir.join(name), &bytes));
        assert_eq!(e, e2);
    }
}

#[test]
fn malformed_gzip_files_give_errors_naming_the_file() {
    let dir = fresh_temp_dir("formats-bad-gz");
    let (v, f) = mesh();
    let good = gzip(obj_text(&v, &f).as_bytes());
    let e = err(scene::load(&write(
        &dir,
        "cut.obj.gz",
        &good[..good.len() / 2],
    )));
    assert!(e.contains("cut.obj.gz"), "{e}");
    let e = err(scene::load(&write(&dir, "plain.ply.gz", ply_ascii(&v, &f))));
    assert!(e.contains("plain.ply.gz"), "{e}");
    // The OBJ rules inside: the line of the bad `v`.
    let e = err(scene::load(&write(
        &dir,
        "bad.obj.gz",
        gzip(b"v 0 0 0\nv 1 x 0\n"),
    )));
    assert!(e.contains("bad.obj.gz:2:"), "{e}");
}

#[test]
fn an_unknown_extension_names_the_supported_ones() {
    let dir = temp_dir("formats-unknown");
    let path = write(&dir, "mesh.stl", b"solid x\n");
    let e = err(scene::load(&path));
    assert!(
        e.contains("mesh.stl") && e.contains("unknown scene format"),
        "{e}"
    );
    for ext in [
        ".obj", ".obj.gz", ".ply", ".ply.gz", ".gltf", ".glb", ".kds",
    ] {
        assert!(e.contains(ext), "{e}");
    }
}

#[test]
fn a_kd_file_given_as_a_scene_is_named_as_one() {
    let dir = fresh_temp_dir("formats-kd");
    let (v, f) = mesh();
    let (scene, _) = loaded(&write(&dir, "mesh.obj", obj_text(&v, &f)));
    let kd = dir.join("tree.kd");
    Accel::build(&scene, &BuildOptions::default())
        .unwrap()
        .write(&kd)
        .unwrap();
    // By its name, and by its magic bytes under a scene's name.
    let disguised = dir.join("tree.obj");
    std::fs::copy(&kd, &disguised).unwrap();
    for path in [kd, disguised] {
        let e = err(scene::load(&path));
        assert!(e.contains("this is a slimkd tree file (.kd)"), "{e}");
        assert!(e.contains(path.to_str().unwrap()), "{e}");
    }
}

#[test]
fn formats_are_told_by_their_names() {
    use SceneFormat::*;
    for (name, format) in [
        ("a.obj", Some(Obj)),
        ("a.OBJ", Some(Obj)),
        ("a.obj.gz", Some(ObjGz)),
        ("a.ply", Some(Ply)),
        ("a.Ply.Gz", Some(PlyGz)),
        ("a.gltf", Some(Gltf)),
        ("a.glb", Some(Glb)),
        ("a.kds", Some(Cache)),
        ("a.gz", None),
        ("a.glb.gz", None),
        ("a.kd", None),
        ("obj", None),
    ] {
        assert_eq!(SceneFormat::of_path(Path::new(name)), format, "{name}");
    }
}

/// A primitive whose POSITION names an accessor that does not exist: the
/// `gltf` crate's own validation indexes with it unchecked and panics.
#[test]
fn a_position_index_out_of_range_is_an_error_not_a_panic() {
    let (v, f) = mesh();
    let (json, _) = gltf_json(&v, &f, &plain(), &[0], Some("side.bin"));
    let bad = json.replace("\"POSITION\":0", "\"POSITION\":7");
    let e = err(scene::load_gltf_bytes(
        Path::new("bad.gltf"),
        bad.as_bytes(),
    ));
    assert!(
        e.contains(
            "bad.gltf: not a valid glTF file: meshes[0].primitives[0].attributes: accessor 7"
        ),
        "{e}"
    );
}

/// No truncation of a binary PLY or a GLB file, and no flipped byte in
/// one, makes a loader panic (each is an error or a load).
#[test]
fn damaged_binary_files_never_panic() {
    let (v, f) = mesh();
    let (glb_json, bin) = gltf_json(&v, &f, &plain(), &[0], None);
    for (name, good) in [
        ("d.glb", glb(&glb_json, &bin)),
        ("d.ply", ply_binary(&v, &f, false, false)),
    ] {
        let path = Path::new(name);
        let load = |b: &[u8]| {
            if name.ends_with(".glb") {
                scene::load_gltf_bytes(path, b)
            } else {
                scene::load_ply_bytes(path, b)
            }
        };
        for n in 0..good.len() {
            let _ = load(&good[..n]);
        }
        for i in 0..good.len() {
            for bit in [0x01, 0x80] {
                let mut b = good.clone();
                b[i] ^= bit;
                if let Err(e) = load(&b) {
                    assert!(e.to_string().starts_with(name), "{e}");
                }
            }
        }
    }
}

fn slimkd(args: &[&std::ffi::OsStr]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_slimkd"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn stdout_json(out: &std::process::Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("one JSON object")
}

/// `build` and `convert` take every format, and build the tree of the OBJ.
#[test]
fn the_cli_builds_and_converts_every_format() {
    let dir = fresh_temp_dir("formats-cli");
    let (v, f) = mesh();
    let obj = write(&dir, "mesh.obj", obj_text(&v, &f));
    let figures = |path: &Path| {
        let j = stdout_json(&slimkd(&[
            "build".as_ref(),
            path.as_os_str(),
            "--json".as_ref(),
        ]));
        (
            j["triangles"].clone(),
            j["tree_bytes"].clone(),
            j["nodes_total"].clone(),
        )
    };
    let reference = figures(&obj);
    assert_eq!(reference.0, f.len());
    for path in every_format(&dir, &v, &f) {
        assert_eq!(figures(&path), reference, "{}", path.display());
        let kds = dir.join("converted.kds");
        let out = slimkd(&[
            "convert".as_ref(),
            path.as_os_str(),
            "-o".as_ref(),
            kds.as_os_str(),
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(figures(&kds), reference, "{}", path.display());
    }
}

/// A tree file where a scene is expected, a scene where a tree file is
/// expected, and an unknown name: each error says what was given and what
/// was expected (before, `build x.ply` said there was no `f` line and
/// `info x.kds` that the magic bytes were wrong).
#[test]
fn the_cli_names_what_was_given_and_what_was_expected() {
    let dir = fresh_temp_dir("formats-cli-kinds");
    let (v, f) = mesh();
    let obj = write(&dir, "mesh.obj", obj_text(&v, &f));
    let kds = dir.join("mesh.kds");
    let kd = dir.join("mesh.kd");
    for (cmd, out) in [("convert", &kds), ("build", &kd)] {
        let o = slimkd(&[
            cmd.as_ref(),
            obj.as_os_str(),
            "-o".as_ref(),
            out.as_os_str(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let ply = write(&dir, "mesh.ply", ply_ascii(&v, &f));
    let stl = write(&dir, "mesh.stl", b"solid x\n");
    let disguised = dir.join("tree.dat");
    std::fs::copy(&kd, &disguised).unwrap();
    let x_kds = dir.join("x.kds");
    let cache_as_kd = dir.join("cache.kd.bak");
    std::fs::copy(&kds, &cache_as_kd).unwrap();
    let cases: Vec<(Vec<&std::ffi::OsStr>, String)> = vec![
        (
            vec!["info".as_ref(), kds.as_os_str()],
            "this is a slimkd scene cache (.kds), info expects a .kd tree file".into(),
        ),
        (
            vec!["info".as_ref(), cache_as_kd.as_os_str()],
            "this is a slimkd scene cache (.kds), info expects a .kd tree file".into(),
        ),
        (
            vec!["verify".as_ref(), ply.as_os_str()],
            "this is a PLY scene, verify expects a .kd tree file".into(),
        ),
        (
            vec!["info".as_ref(), obj.as_os_str()],
            "this is an OBJ scene, info expects a .kd tree file".into(),
        ),
        (
            vec!["build".as_ref(), kd.as_os_str()],
            "this is a slimkd tree file (.kd), but a scene was expected".into(),
        ),
        (
            vec![
                "convert".as_ref(),
                disguised.as_os_str(),
                "-o".as_ref(),
                x_kds.as_os_str(),
            ],
            "this is a slimkd tree file (.kd), but a scene was expected".into(),
        ),
        (
            vec!["build".as_ref(), stl.as_os_str()],
            format!(
                "unknown scene format (by its name); supported: {}",
                SceneFormat::SUPPORTED
            ),
        ),
    ];
    for (args, expected) in cases {
        let out = slimkd(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains(&expected), "{args:?}: {err}");
        assert!(err.contains(args[1].to_str().unwrap()), "{args:?}: {err}");
    }
    // A PLY scene builds (it used to be read as OBJ text).
    let j = stdout_json(&slimkd(&[
        "build".as_ref(),
        ply.as_os_str(),
        "--json".as_ref(),
    ]));
    assert_eq!(j["triangles"], f.len());
}
