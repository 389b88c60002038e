//! A build in cells (`slimkd::cells`, `slimkd build --cells`,
//! `build-cell`, `stitch`) gives the monolithic build's tree and file,
//! byte for byte: on generated scenes and the two bundled ones, for
//! K = 1, 2, 7 and 64, with and without `--reorder`; a missing or corrupt
//! part is rebuilt on resume; a corrupt plan, cell or part file is an
//! error naming it.

mod common;

use common::kd::{Rng, load_scene, random_small_scene};
use common::*;
use slimkd::build::BuildConfig;
use slimkd::build::level::{self, LevelOptions};
use slimkd::cells;
use slimkd::scene::TriangleColumns;
use slimkd::tree::TreeIr;
use std::path::Path;

/// The tree stitched from a plan of `k` cells written to `dir`, each cell
/// read back from its file and built as `build-cell` builds it.
fn via_files(scene: &TriangleColumns, k: usize, dir: &Path) -> (TreeIr, usize) {
    let config = BuildConfig::default();
    let options = LevelOptions::default();
    let hash = slimkd::format::SceneTag::geometry_hash_of(scene);
    let prepared = cells::prepare(dir, scene, &config, &options, k, hash, None).unwrap();
    assert!(prepared.planned);
    let plan = prepared.plan;
    assert!(
        plan.cells.len() <= k,
        "{} cells for K = {k}",
        plan.cells.len()
    );
    for i in 0..plan.cells.len() {
        let input = cells::read_planned_cell(dir, &plan, i).unwrap();
        let tree = cells::build_cell(&input, &options).unwrap();
        cells::write_part(&cells::part_path(dir, i), plan.cells[i].id, &tree).unwrap();
    }
    let tree = cells::stitch_dir(dir, &plan).unwrap();
    // Handed over node by node (as to the streamed writer), the same tree.
    let mut sink = slimkd::tree::TreeIrSink::default();
    assert!(cells::stitch_dir_into(dir, &plan, &mut sink).unwrap());
    assert!(sink.finish().unwrap() == tree, "stitch_dir_into differs");
    (tree, plan.cells.len())
}

fn scenes() -> Vec<(String, TriangleColumns)> {
    let mut rng = Rng(21);
    vec![
        ("small-4000".into(), random_small_scene(&mut rng, 4000, 40)),
        ("dense-1500".into(), random_small_scene(&mut rng, 1500, 8)),
        ("bunny_npm".into(), load_scene("bunny_npm.obj")),
    ]
}

#[test]
fn the_stitched_tree_is_the_monolithic_tree() {
    for (name, scene) in scenes() {
        let (whole, _) = level::build(
            &scene,
            &BuildConfig::default(),
            None,
            &LevelOptions::default(),
        )
        .unwrap();
        for k in [1, 2, 7, 64] {
            let dir = fresh_temp_dir(&format!("tree-{name}-{k}"));
            let (stitched, n) = via_files(&scene, k, &dir);
            assert!(
                stitched == whole,
                "{name}, K = {k} ({n} cells): the trees differ"
            );
            if k > 1 {
                assert!(n > 1, "{name}, K = {k}: only {n} cells");
            }
        }
    }
}

/// Writes `scene` as an OBJ file (one vertex line per corner).
fn write_obj(scene: &TriangleColumns, path: &Path) {
    let mut text = String::new();
    for i in 0..scene.len() as u32 {
        for p in scene.tri(i) {
            text.push_str(&format!("v {} {} {}\n", p.x, p.y, p.z));
        }
    }
    for i in 0..scene.len() {
        text.push_str(&format!("f {} {} {}\n", 3 * i + 1, 3 * i + 2, 3 * i + 3));
    }
    std::fs::write(path, text).unwrap();
}

/// The scenes of the CLI tests as files: two generated, two bundled.
fn scene_files(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    for (name, scene) in scenes().into_iter().take(2) {
        let path = dir.join(format!("{name}.obj"));
        write_obj(&scene, &path);
        out.push(path.display().to_string());
    }
    let bundled = common::kd::manifest_dir().join("scenes");
    for name in ["bunny_npm.obj", "nexuiz_dieselpower.obj"] {
        out.push(bundled.join(name).display().to_string());
    }
    out
}

fn ok(out: std::process::Output) -> std::process::Output {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn bytes(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn build_cells_writes_the_file_of_build_o() {
    let dir = fresh_temp_dir("identical");
    for scene in scene_files(&dir) {
        for reorder in [false, true] {
            let extra: &[&str] = if reorder { &["--reorder"] } else { &[] };
            let mono = build_mono(&dir, &scene, extra);
            for k in ["1", "2", "7", "64"] {
                let out = dir.join(format!("c{k}.kd"));
                let o = out.display().to_string();
                let cells_dir = dir.join(format!("c{k}-{reorder}.cells"));
                let d = cells_dir.display().to_string();
                let args = ["build", &scene, "--cells", k, "--cells-dir", &d, "-o", &o];
                let doc = json(&ok(slimkd(&[&args[..], extra, &["--json"]].concat())));
                let n = doc["cell_list"].as_array().unwrap().len();
                assert!(n <= k.parse().unwrap(), "{scene}: {n} cells for K = {k}");
                assert!(
                    bytes(&out) == bytes(&mono),
                    "{scene}, K = {k}, reorder {reorder}: the files differ"
                );
            }
        }
    }
}

/// The JSON of `build --cells` in `dir`, which must succeed.
fn build_cells(scene: &str, k: &str, dir: &Path, out: &Path) -> serde_json::Value {
    let (d, o) = (dir.display().to_string(), out.display().to_string());
    json(&ok(slimkd(&[
        "build",
        scene,
        "--cells",
        k,
        "--cells-dir",
        &d,
        "-o",
        &o,
        "--json",
    ])))
}

/// The monolithic `build -o` of `scene` (with `extra` flags) in `dir`.
fn build_mono(dir: &std::path::Path, scene: &str, extra: &[&str]) -> std::path::PathBuf {
    let mono = dir.join("mono.kd");
    let m = mono.display().to_string();
    ok(slimkd(&[&["build", scene, "-q", "-o", &m], extra].concat()));
    mono
}

fn kept(doc: &serde_json::Value) -> Vec<bool> {
    doc["cell_list"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["kept"].as_bool().unwrap())
        .collect()
}

#[test]
fn a_deleted_or_corrupt_part_is_rebuilt_on_resume() {
    let dir = fresh_temp_dir("resume");
    let scene = scene_files(&dir)[3].clone();
    let mono = build_mono(&dir, &scene, &[]);
    let work = dir.join("work");
    let out = dir.join("cells.kd");
    let first = build_cells(&scene, "7", &work, &out);
    assert_eq!(first["planned"], true);
    let n = kept(&first).len();
    assert!(n >= 4, "{n} cells");
    assert!(kept(&first).iter().all(|k| !k));
    std::fs::remove_file(cells::part_path(&work, 1)).unwrap();
    let mut part = bytes(&cells::part_path(&work, 3));
    let mid = part.len() / 2;
    part[mid] ^= 0x10;
    std::fs::write(cells::part_path(&work, 3), part).unwrap();
    std::fs::remove_file(&out).unwrap();
    let second = build_cells(&scene, "7", &work, &out);
    assert_eq!(second["planned"], false, "the plan is kept");
    let expect: Vec<bool> = (0..n).map(|i| i != 1 && i != 3).collect();
    assert_eq!(kept(&second), expect);
    assert!(bytes(&out) == bytes(&mono));
    // A damaged cell file of a missing part: planned again, the same
    // cells, the other parts still kept.
    std::fs::remove_file(cells::part_path(&work, 2)).unwrap();
    let cell = cells::cell_path(&work, 2);
    let len = bytes(&cell).len();
    std::fs::write(&cell, &bytes(&cell)[..len - 9]).unwrap();
    let third = build_cells(&scene, "7", &work, &out);
    assert_eq!(third["planned"], true);
    let expect: Vec<bool> = (0..n).map(|i| i != 2).collect();
    assert_eq!(kept(&third), expect);
    assert!(bytes(&out) == bytes(&mono));
}

#[test]
fn cells_built_elsewhere_are_kept_and_stitched() {
    let dir = fresh_temp_dir("elsewhere");
    let scene = scene_files(&dir)[3].clone();
    let mono = build_mono(&dir, &scene, &["--reorder"]);
    let work = dir.join("work");
    let d = work.display().to_string();
    let plan = json(&ok(slimkd(&[
        "build",
        &scene,
        "--cells",
        "5",
        "--cells-dir",
        &d,
        "--plan-only",
        "--json",
    ])));
    assert_eq!(plan["command"], "plan");
    let list = plan["cell_list"].as_array().unwrap().clone();
    assert!(list.len() >= 2);
    assert!(
        !cells::part_path(&work, 0).exists(),
        "--plan-only builds no cell"
    );
    // Stitching before every part is built names the cells left.
    let out = dir.join("stitched.kd");
    let o = out.display().to_string();
    let early = slimkd(&["stitch", &scene, "--cells-dir", &d, "-o", &o, "--reorder"]);
    assert_eq!(early.status.code(), Some(1));
    let err = String::from_utf8_lossy(&early.stderr);
    assert!(err.contains("cell-00000.kdpart"), "{err}");
    assert!(!out.exists());
    for (i, c) in list.iter().enumerate() {
        let cell = c["cell"].as_str().unwrap();
        let doc = json(&ok(slimkd(&["build-cell", cell, "--json", "-j", "1"])));
        assert_eq!(doc["command"], "build-cell");
        assert_eq!(doc["part"], c["part"]);
        assert_eq!(doc["refs"], c["refs"]);
        assert!(cells::part_path(&work, i).exists());
    }
    let doc = json(&ok(slimkd(&[
        "stitch",
        &scene,
        "--cells-dir",
        &d,
        "-o",
        &o,
        "--reorder",
        "--json",
    ])));
    assert_eq!(doc["command"], "stitch");
    assert!(bytes(&out) == bytes(&mono));
    // `build --cells` now only stitches.
    let again = dir.join("again.kd");
    let ad = build_cells(&scene, "5", &work, &again);
    assert!(kept(&ad).iter().all(|&k| k));
    let with_reorder = ok(slimkd(&[
        "build",
        &scene,
        "--cells",
        "5",
        "--cells-dir",
        &d,
        "-o",
        &again.display().to_string(),
        "--reorder",
        "-q",
    ]));
    drop(with_reorder);
    assert!(bytes(&again) == bytes(&mono));
}

#[test]
fn a_build_killed_while_building_cells_finishes_with_the_same_file() {
    use std::io::BufRead;
    let dir = fresh_temp_dir("killed");
    let scene = scene_files(&dir)[3].clone();
    let mono = build_mono(&dir, &scene, &[]);
    let work = dir.join("work");
    let out = dir.join("cells.kd");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_slimkd"))
        .args(["build", &scene, "--cells", "64", "-j", "1", "-o"])
        .arg(&out)
        .arg("--cells-dir")
        .arg(&work)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = std::io::BufReader::new(child.stderr.take().unwrap());
    for line in stderr.lines() {
        if line.unwrap().contains(" built: ") {
            break;
        }
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let _ = std::fs::remove_file(&out);
    let doc = build_cells(&scene, "64", &work, &out);
    assert_eq!(
        doc["planned"], false,
        "the plan written before the kill is kept"
    );
    assert!(
        kept(&doc).iter().any(|&k| k),
        "the part built before the kill is kept"
    );
    assert!(bytes(&out) == bytes(&mono));
}

/// Every truncation and many single-byte changes of a plan, cell and part
/// file are errors that name the file (and never a panic).
#[test]
fn corrupt_plan_cell_and_part_files_name_the_file() {
    let dir = fresh_temp_dir("corrupt");
    let mut rng = Rng(5);
    let obj = dir.join("scene.obj");
    write_obj(&random_small_scene(&mut rng, 600, 10), &obj);
    let (scene, _) = slimkd::scene::load(&obj).unwrap();
    let (_, n) = via_files(&scene, 3, &dir);
    assert!(n >= 2);
    let plan = cells::read_plan(&cells::plan_path(&dir)).unwrap();
    let files = [
        cells::plan_path(&dir),
        cells::cell_path(&dir, 1),
        cells::part_path(&dir, 1),
    ];
    for path in &files {
        let good = bytes(path);
        let bad = dir.join("bad");
        let mut variants: Vec<Vec<u8>> = (0..good.len())
            .step_by(7)
            .map(|l| good[..l].to_vec())
            .collect();
        for at in (0..good.len()).step_by(good.len() / 97 + 1) {
            let mut b = good.clone();
            b[at] ^= 0x41;
            variants.push(b);
        }
        let mut longer = good.clone();
        longer.push(0);
        variants.push(longer);
        for b in variants {
            std::fs::write(&bad, &b).unwrap();
            let err = match path.extension().unwrap().to_str().unwrap() {
                "kdplan" => cells::read_plan(&bad).map(|_| ()),
                "kdcell" => cells::read_cell(&bad).map(|_| ()),
                _ => cells::read_part(&bad, plan.cells[1].id).map(|_| ()),
            }
            .expect_err("a damaged file is refused");
            let msg = err.to_string();
            assert!(msg.starts_with(&bad.display().to_string()), "{msg}");
        }
    }
    // A part of another cell.
    let err = cells::read_part(&cells::part_path(&dir, 1), plan.cells[0].id).unwrap_err();
    assert!(matches!(err, cells::CellsError::Mismatch { .. }), "{err}");
    // The CLI names them too, exit 1.
    let d = dir.display().to_string();
    let mut part = bytes(&cells::part_path(&dir, 1));
    part[40] ^= 1;
    std::fs::write(cells::part_path(&dir, 1), &part).unwrap();
    let o = dir.join("out.kd").display().to_string();
    let obj = obj.display().to_string();
    let stitch = || slimkd(&["stitch", &obj, "--cells-dir", &d, "-o", &o]);
    let st = stitch();
    assert_eq!(st.status.code(), Some(1));
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(
        err.contains("cell-00001.kdpart: corrupt part file (checksum mismatch)"),
        "{err}"
    );
    let cell = cells::cell_path(&dir, 0);
    let mut c = bytes(&cell);
    c.truncate(c.len() - 1);
    std::fs::write(&cell, &c).unwrap();
    let bc = slimkd(&["build-cell", &cell.display().to_string()]);
    assert_eq!(bc.status.code(), Some(1));
    let err = String::from_utf8_lossy(&bc.stderr);
    assert!(
        err.contains(&format!(
            "{}: truncated or overlong cell file",
            cell.display()
        )),
        "{err}"
    );
    std::fs::write(cells::plan_path(&dir), b"SLIMKPL\0").unwrap();
    let st = stitch();
    assert_eq!(st.status.code(), Some(1));
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("plan.kdplan: truncated plan file"), "{err}");
}

#[test]
fn a_plan_of_another_scene_is_refused_by_stitch() {
    let dir = fresh_temp_dir("other-scene");
    let files = scene_files(&dir);
    let d = dir.join("work").display().to_string();
    ok(slimkd(&[
        "build",
        &files[0],
        "--cells",
        "3",
        "--cells-dir",
        &d,
        "-o",
        &dir.join("a.kd").display().to_string(),
        "-q",
    ]));
    let o = dir.join("b.kd").display().to_string();
    let st = slimkd(&["stitch", &files[1], "--cells-dir", &d, "-o", &o]);
    assert_eq!(st.status.code(), Some(1));
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(
        err.contains("plan.kdplan: the plan of another scene"),
        "{err}"
    );
}

#[test]
fn usage_errors_of_a_build_in_cells() {
    let dir = fresh_temp_dir("usage");
    let o = dir.join("x.kd").display().to_string();
    for (args, says) in [
        (
            vec!["build", "default", "--cells", "0", "-o", &o],
            "at least 1",
        ),
        (
            vec![
                "build", "default", "--cells", "4", "--preset", "fast", "-o", &o,
            ],
            "std tree only",
        ),
        (
            vec![
                "build",
                "default",
                "--cells",
                "4",
                "--builder",
                "sweep",
                "-o",
                &o,
            ],
            "level builder",
        ),
        (vec!["build", "default", "--cells", "4"], "needs -o"),
        (
            vec!["build", "default", "--cells-dir", "w", "-o", &o],
            "--cells",
        ),
        (vec!["build", "default", "--plan-only", "-o", &o], "--cells"),
    ] {
        let out = slimkd(&args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(says), "{args:?}: {err}");
        assert!(!Path::new(&o).exists());
    }
}

#[test]
fn the_cut_makes_at_most_k_cells_none_below_its_minimum() {
    let config = BuildConfig::default();
    let options = LevelOptions::default();
    for (name, scene) in scenes() {
        for k in [1, 2, 7, 64] {
            let cut = cells::cut_for(scene.len(), k, options.small_threshold);
            let top = cells::plan(&scene, &config, &options, k, None).unwrap();
            assert!(
                top.cells.len() <= k,
                "{name}, K = {k}: {} cells",
                top.cells.len()
            );
            for (node, cell) in &top.cells {
                assert!(cell.tris.len() >= cut.min_refs, "{name}, K = {k}");
                assert!(
                    matches!(
                        top.tree.nodes[node.0 as usize],
                        slimkd::tree::Node::Leaf { count: 0, .. }
                    ),
                    "{name}, K = {k}: a cell stands at an empty leaf"
                );
            }
            let nodes: Vec<_> = top.cells.iter().map(|c| c.0).collect();
            assert!(nodes.windows(2).all(|w| w[0] < w[1]), "cells in pre-order");
        }
    }
}
