//! What hoisting saves, per hoisted triangle: deterministic counts, no
//! timings (the slim bench times the pass).
//!
//! For each scene it builds the standard tree (level builder, default
//! constants), runs the slim pass under each setting (the `fast` and
//! `small` presets; the paper's `f` and `s` settings with its rule, and
//! with the byte rule: `paper f/b`, `paper s/b`), and
//! prints the triangles hoisted, and per hoisted triangle the nodes,
//! references and tree bytes saved against the std tree, the bytes counted
//! both ways ([`ByteLayout::V1`], every leaf a word and every reference an
//! index, and [`ByteLayout::V2`], the file of today, which the byte rule
//! counts in: empty leaves free and one-triangle leaves without an
//! index), with the
//! file's Morton numbering (`--reorder`). The std tree's line gives its
//! depth limit and how many of its leaves (non-empty ones) sit there.
//!
//! Scenes: the OBJ files given after `--`, else the default scene
//! `scenes/nexuiz_dieselpower.obj`. For example
//! `cargo bench --bench hoist -- ~/.cache/slimkd-scenes/{nexuiz_dieselpower,nexuiz_aneurysm,bunny_scan}.obj`.

use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::scene::TriangleColumns;
use slimkd::slim::{self, ByteLayout, HoistRule, SlimParams, tree_bytes};
use slimkd::tree::{Node, TreeIr};
use std::path::{Path, PathBuf};

/// Figures of one tree.
struct Figures {
    nodes: usize,
    refs: usize,
    v1: u64,
    v2: u64,
}

fn figures(tree: &TreeIr, scene: &TriangleColumns) -> Figures {
    Figures {
        nodes: tree.nodes.len(),
        refs: tree.leaf_tris.len(),
        v1: tree_bytes(tree, scene, true, ByteLayout::V1),
        v2: tree_bytes(tree, scene, true, ByteLayout::V2),
    }
}

/// Non-empty leaves at depth `limit` or deeper.
fn leaves_at_limit(tree: &TreeIr, limit: u32) -> usize {
    let mut n = 0;
    let mut stack = vec![(0usize, 0u32)];
    while let Some((i, d)) = stack.pop() {
        match tree.nodes[i] {
            Node::Inner { right, .. } => {
                stack.push((i + 1, d + 1));
                stack.push((right.0 as usize, d + 1));
            }
            Node::Leaf { count, .. } => n += usize::from(count > 0 && d >= limit),
        }
    }
    n
}

fn bench_scene(name: &str, scene: &TriangleColumns, config: &BuildConfig) {
    let std_tree = build::build(scene, config, Algorithm::Level, None).expect("the std build");
    let s = figures(&std_tree, scene);
    let limit = config.sah.depth_limit(scene.len());
    println!(
        "{name}: {} triangles; std: {} nodes, {} refs, {} B (v1), {} B (v2), depth limit {limit}, {} of its leaves there",
        scene.len(),
        s.nodes,
        s.refs,
        s.v1,
        s.v2,
        leaves_at_limit(&std_tree, limit)
    );
    println!(
        "  {:<12} {:>8} {:>10} {:>10} {:>10} {:>10} {:>9} {:>9}",
        "setting", "hoisted", "nodes/h", "refs/h", "B v1/h", "B v2/h", "v1", "v2"
    );
    let bytes = HoistRule::Bytes { reordered: true };
    let runs = [
        ("fast", SlimParams::FAST),
        ("small", SlimParams::SMALL),
        ("paper f", SlimParams::PAPER_FAST),
        ("paper s", SlimParams::PAPER_SMALL),
        ("paper f/b", SlimParams::PAPER_FAST.with_rule(bytes)),
        ("paper s/b", SlimParams::PAPER_SMALL.with_rule(bytes)),
    ];
    for (label, params) in runs {
        let (tree, report) = slim::slim(&std_tree, scene, config, &params);
        let f = figures(&tree, scene);
        let per = |a: f64, b: f64| (a - b) / report.hoisted.max(1) as f64;
        let pct = |a: u64, b: u64| 100.0 * (b as f64 / a as f64 - 1.0);
        println!(
            "  {:<12} {:>8} {:>10.2} {:>10.2} {:>10.1} {:>10.1} {:>8.1}% {:>8.1}%",
            label,
            report.hoisted,
            per(s.nodes as f64, f.nodes as f64),
            per(s.refs as f64, f.refs as f64),
            per(s.v1 as f64, f.v1 as f64),
            per(s.v2 as f64, f.v2 as f64),
            pct(s.v1, f.v1),
            pct(s.v2, f.v2),
        );
    }
}

fn main() {
    let mut paths: Vec<PathBuf> = std::env::args()
        .skip(1)
        .filter(|a| a.ends_with(".obj"))
        .map(PathBuf::from)
        .collect();
    if paths.is_empty() {
        paths.push(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/nexuiz_dieselpower.obj"));
    }
    let config = BuildConfig::default();
    for path in paths {
        let scene = slimkd::scene::load_obj(&path)
            .unwrap_or_else(|e| panic!("cannot load the scene: {e}"))
            .0;
        let name = path.file_stem().unwrap_or_default().to_string_lossy();
        bench_scene(&name, &scene, &config);
    }
}
