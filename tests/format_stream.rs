//! The streamed writer (`format::write_file_streamed`): the tree handed
//! over in pre-order, straight from the level builder (`level::build_into`)
//! or from a `TreeIr` (`TreeIr::feed`), gives the bytes of `write_to_vec`,
//! with and without `--reorder`, for std and slim trees and under a memory
//! budget; its figures (`StatsSink`) are `TreeStats::of`'s; a stream that
//! is not one tree, or a bad node, is an error that leaves no file.

mod common;

use common::kd::*;
use common::*;
use slimkd::build::BuildConfig;
use slimkd::build::level::{self, LevelOptions};
use slimkd::format::{self, FormatError, WriteOptions};
use slimkd::geom::Aabb;
use slimkd::scene::TriangleColumns;
use slimkd::slim::{self, SlimParams};
use slimkd::stats::{StatsSink, TreeStats};
use slimkd::tree::{Node, NodeId, PreOrderSink, TreeIr, TriId};
use std::path::Path;

fn options(reorder: bool) -> WriteOptions {
    WriteOptions {
        reorder,
        ..WriteOptions::default()
    }
}

/// The bytes `write_file_streamed` writes at `path` for what `produce`
/// feeds it.
fn streamed(
    path: &Path,
    scene: &TriangleColumns,
    reorder: bool,
    produce: impl FnOnce(&mut format::StreamWriter<'_>) -> Result<(), FormatError>,
) -> Vec<u8> {
    format::write_file_streamed(path, scene, &options(reorder), produce).unwrap();
    std::fs::read(path).unwrap()
}

/// Each scene's tree, straight from the level builder and fed from its
/// `TreeIr`, std and slim, in files equal to `write_to_vec`'s bytes.
fn assert_streams_equal(scene: &TriangleColumns, dir: &Path, level_options: &LevelOptions) {
    let config = BuildConfig::default();
    let (tree, _) = level::build(scene, &config, None, level_options).unwrap();
    let path = dir.join("t.kd");
    for reorder in [false, true] {
        let whole = format::write_to_vec(&tree, scene, &options(reorder)).unwrap();
        let mut stats = StatsSink::new(&config.sah);
        let bytes = streamed(&path, scene, reorder, |w| {
            let fed = level::build_into(scene, &config, None, level_options, &mut (w, &mut stats))
                .unwrap();
            assert!(fed.is_some(), "the writer took the whole tree");
            Ok(())
        });
        assert!(bytes == whole, "build_into, reorder {reorder}");
        assert_eq!(stats.finish(), TreeStats::of(&tree, &config.sah));
        let bytes = streamed(&path, scene, reorder, |w| {
            tree.feed(w).unwrap();
            Ok(())
        });
        assert!(bytes == whole, "feed, reorder {reorder}");
        for params in [SlimParams::FAST, SlimParams::SMALL] {
            let (slim, _) = slim::slim(&tree, scene, &config, &params);
            let whole = format::write_to_vec(&slim, scene, &options(reorder)).unwrap();
            let bytes = streamed(&path, scene, reorder, |w| {
                slim.feed(w).unwrap();
                Ok(())
            });
            assert!(bytes == whole, "slim, reorder {reorder}");
        }
    }
    std::fs::remove_file(&path).unwrap();
    assert_eq!(
        slimkd::fsio::entry_names(dir).unwrap(),
        Vec::<String>::new()
    );
}

#[test]
fn streamed_files_equal_write_to_vec_on_random_scenes() {
    let dir = fresh_temp_dir("stream-random");
    let mut rng = Rng(0x5eed_57e4);
    for k in 0..12 {
        let n = 1 + rng.below(1500);
        let scene = if k % 2 == 0 {
            let g = 1 + rng.below(40);
            random_small_scene(&mut rng, n, g)
        } else {
            let g = 1 + rng.below(12);
            random_grid_scene(&mut rng, n, g)
        };
        assert_streams_equal(&scene, &dir, &LevelOptions::default());
    }
}

#[test]
fn streamed_files_equal_write_to_vec_on_bundled_scenes() {
    let dir = fresh_temp_dir("stream-bundled");
    assert_streams_equal(&load_scene("bunny_npm.obj"), &dir, &LevelOptions::default());
}

/// Under a budget so small that the level columns and the depth-first
/// subtrees go to scratch files, the small-node threshold low enough that
/// the subtrees are many, the file is the same.
#[test]
fn streamed_files_equal_write_to_vec_under_a_memory_budget() {
    let dir = fresh_temp_dir("stream-budget");
    let scratch = fresh_temp_dir("stream-budget-scratch");
    let options = LevelOptions {
        mem_budget: Some(1 << 16),
        scratch_dir: scratch.to_path_buf(),
        small_threshold: 64,
        ..LevelOptions::default()
    };
    assert_streams_equal(&load_scene("bunny_npm.obj"), &dir, &options);
    // The subtrees' chunk files were unlinked once mapped.
    assert_eq!(
        slimkd::fsio::entry_names(&scratch).unwrap(),
        Vec::<String>::new()
    );
}

/// A tree whose inner nodes have both children empty (the left one keeps
/// a word), only the left one empty (it has none) and only the right one
/// empty: the left child's word is decided when its sibling comes.
#[test]
fn empty_children_get_the_words_of_write_to_vec() {
    let scene = strip_scene(4);
    let b = scene_bounds(&scene);
    let mid = |k: usize| (b.min[k] + b.max[k]) / 2.0;
    let inner = |axis: u8, right: u32| Node::Inner {
        axis,
        pos: mid(axis as usize),
        right: NodeId(right),
        t_ref: None,
    };
    let leaf = |start: u32, count: u32| Node::Leaf { start, count };
    let tree = TreeIr {
        bounds: b,
        nodes: vec![
            inner(0, 4),
            // Both children empty.
            inner(1, 3),
            leaf(0, 0),
            leaf(0, 0),
            // Only the left child empty.
            inner(2, 6),
            leaf(0, 0),
            // Only the right child empty.
            inner(1, 8),
            leaf(0, 4),
            leaf(0, 0),
        ],
        leaf_tris: (0..4).map(TriId).collect(),
    };
    let dir = fresh_temp_dir("stream-empty");
    let path = dir.join("e.kd");
    for reorder in [false, true] {
        let whole = format::write_to_vec(&tree, &scene, &options(reorder)).unwrap();
        let bytes = streamed(&path, &scene, reorder, |w| {
            tree.feed(w).unwrap();
            Ok(())
        });
        assert!(bytes == whole, "reorder {reorder}");
        read(&bytes);
    }
}

fn scene_bounds(scene: &TriangleColumns) -> Aabb {
    scene
        .positions()
        .iter()
        .fold(Aabb::EMPTY, |b, &p| b.union(&Aabb::new(p, p)))
}

/// The error `write_file_streamed` gives for what `produce` feeds it;
/// no file at the path, none left in the directory.
fn stream_error(
    dir: &str,
    scene: &TriangleColumns,
    produce: impl FnOnce(&mut format::StreamWriter<'_>),
) -> FormatError {
    let dir = fresh_temp_dir(dir);
    let path = dir.join("bad.kd");
    let err = format::write_file_streamed(&path, scene, &options(false), |w| {
        produce(w);
        Ok::<(), FormatError>(())
    })
    .unwrap_err();
    assert!(!path.exists());
    assert_eq!(
        slimkd::fsio::entry_names(&dir).unwrap(),
        Vec::<String>::new()
    );
    err
}

#[test]
fn a_stream_that_is_not_one_tree_is_an_error() {
    let scene = strip_scene(4);
    let b = scene_bounds(&scene);
    let x = (b.min.x + b.max.x) / 2.0;
    // An inner node without its children.
    let err = stream_error("stream-not-a-tree", &scene, |w| {
        w.bounds(b).unwrap();
        w.inner(0, x, None).unwrap();
    });
    assert!(err.to_string().contains("ended before"), "{err}");
    // Nothing at all.
    let err = stream_error("stream-not-a-tree", &scene, |_| {});
    assert!(err.to_string().contains("ended before"), "{err}");
    // A node after the whole tree.
    let err = stream_error("stream-not-a-tree", &scene, |w| {
        w.bounds(b).unwrap();
        w.leaf(&[TriId(0)]).unwrap();
        assert!(w.leaf(&[TriId(1)]).is_err());
    });
    assert!(err.to_string().contains("after the whole tree"), "{err}");
    // A node before the bounds.
    let err = stream_error("stream-not-a-tree", &scene, |w| {
        assert!(w.leaf(&[]).is_err());
    });
    assert!(
        err.to_string().contains("before the tree's bounds"),
        "{err}"
    );
}

/// What a case of a bad stream feeds the writer.
type Produce = dyn Fn(&mut format::StreamWriter<'_>);

#[test]
fn bad_nodes_in_a_stream_are_errors_naming_the_node() {
    let scene = strip_scene(4);
    let b = scene_bounds(&scene);
    let x = (b.min.x + b.max.x) / 2.0;
    let cases: [(&str, Box<Produce>); 4] = [
        (
            "outside the node's cell",
            Box::new(move |w| {
                w.bounds(b).unwrap();
                w.inner(0, x, None).unwrap();
                // The left child's cell ends at x.
                assert!(w.inner(0, x + 1.0, None).is_err());
            }),
        ),
        (
            "axis 3",
            Box::new(move |w| {
                w.bounds(b).unwrap();
                assert!(w.inner(3, x, None).is_err());
            }),
        ),
        (
            "not finite",
            Box::new(move |w| {
                w.bounds(b).unwrap();
                assert!(w.inner(0, f32::NAN, None).is_err());
            }),
        ),
        (
            "triangle 9 of 4",
            Box::new(move |w| {
                w.bounds(b).unwrap();
                w.inner(0, x, None).unwrap();
                assert!(w.leaf(&[TriId(9)]).is_err());
                // Stopped: later nodes are refused too.
                assert!(w.leaf(&[]).is_err());
            }),
        ),
    ];
    for (message, produce) in cases {
        let err = stream_error("stream-bad-nodes", &scene, |w| produce(w));
        assert!(err.to_string().contains(message), "{message}: {err}");
    }
}

/// `build -o` of a std level tree (streamed) writes the bytes and prints
/// the figures of the path through a `TreeIr` (`--builder sweep`), with
/// and without `--reorder` and a budget.
#[test]
fn build_o_streamed_equals_the_tree_path() {
    let dir = fresh_temp_dir("stream-cli");
    let scene = manifest_dir().join("scenes/nexuiz_dieselpower.obj");
    let scratch = fresh_temp_dir("stream-cli-scratch");
    let run = |out: &Path, extra: &[&str]| -> serde_json::Value {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_slimkd"))
            .arg("build")
            .arg(&scene)
            .arg("-o")
            .arg(out)
            .args(["--json", "-q"])
            .args(extra)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let scratch_arg = scratch.to_str().unwrap();
    for reorder in [&[][..], &["--reorder"][..]] {
        let a = dir.join("streamed.kd");
        let b = dir.join("tree.kd");
        let c = dir.join("budget.kd");
        let ja = run(&a, reorder);
        let jb = run(&b, &[reorder, &["--builder", "sweep"]].concat());
        let jc = run(
            &c,
            &[reorder, &["--mem-budget", "64K", "--scratch", scratch_arg]].concat(),
        );
        let bytes = std::fs::read(&b).unwrap();
        assert!(std::fs::read(&a).unwrap() == bytes, "{reorder:?}");
        assert!(std::fs::read(&c).unwrap() == bytes, "{reorder:?}");
        for key in [
            "nodes_total",
            "nodes_leaf",
            "refs",
            "max_depth",
            "mean_leaf_depth",
            "sah_cost",
            "leaf_depth_histogram",
            "idx16",
            "idx32",
            "tree_bytes",
        ] {
            assert_eq!(ja[key], jb[key], "{key}");
            assert_eq!(jc[key], jb[key], "{key}");
        }
    }
    assert_eq!(
        slimkd::fsio::entry_names(&scratch).unwrap(),
        Vec::<String>::new()
    );
    let mut names = slimkd::fsio::entry_names(&dir).unwrap();
    names.sort();
    assert_eq!(names, ["budget.kd", "streamed.kd", "tree.kd"]);
}
