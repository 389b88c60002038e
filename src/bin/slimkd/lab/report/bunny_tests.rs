//! The report on the shipped bunny: every table
//! against an independent computation, the frames against brute force, and
//! the files it writes (Markdown, JSON, SVG figures; atomic, nothing left
//! behind on failure).

use crate::lab::report::front::{self, FrontGrid, FrontOptions, FrontSetting};
use crate::lab::report::{self, Report, ReportError, ReportOptions, TreeKind};
use crate::lab::test_dirs::{dir_entries, fresh_temp_dir};
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, KdFile, TreeFigures, WriteOptions};
use slimkd::render::{self, Camera, View};
use slimkd::scene::{self, TriangleColumns};
use slimkd::slim::{self, SlimParams};
use slimkd::trace::BruteForce;
use slimkd::tree::{Node, TreeIr};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

const SIZE: (u32, u32) = (32, 32);
const GRID_OCCU: [f64; 2] = [0.5, 0.9];
const GRID_FREQ: [f64; 2] = [0.4, 0.7];

fn manifest(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

fn bunny() -> &'static TriangleColumns {
    static SCENE: OnceLock<TriangleColumns> = OnceLock::new();
    SCENE.get_or_init(|| {
        scene::load_obj(&manifest("scenes/bunny_npm.obj"))
            .unwrap()
            .0
    })
}

fn views() -> Vec<View> {
    render::parse_views(&std::fs::read_to_string(manifest("scenes/views.txt")).unwrap()).unwrap()
}

fn std_tree() -> &'static TreeIr {
    static TREE: OnceLock<TreeIr> = OnceLock::new();
    TREE.get_or_init(|| {
        build::build(
            bunny(),
            &BuildConfig::default(),
            Algorithm::WaldHavran,
            None,
        )
        .unwrap()
    })
}

/// The report on the bunny with its three views and a 2×2 sweep, and the
/// progress lines it printed (made once, shared by the tests).
fn bunny_report() -> &'static (Report, Vec<String>) {
    static REPORT: OnceLock<(Report, Vec<String>)> = OnceLock::new();
    REPORT.get_or_init(|| {
        let options = ReportOptions {
            scenes: vec![("bunny_npm".into(), bunny().clone(), 0.25)],
            views: views(),
            size: SIZE,
            reps: 1,
            sweep: true,
            all_threads: 2,
            sweep_grid: Some((GRID_OCCU.to_vec(), GRID_FREQ.to_vec())),
            rule: SlimParams::FAST.rule,
        };
        let mut lines = Vec::new();
        let r = report::run(&options, &mut |l| lines.push(l.to_string())).unwrap();
        (r, lines)
    })
}

/// Writes a tree as the report does (reordered) and returns its figures and
/// leaf-depth histogram.
fn written(tree: &TreeIr) -> (TreeFigures, Vec<u64>) {
    let bytes = format::write_to_vec(
        tree,
        bunny(),
        &WriteOptions {
            reorder: true,
            ..WriteOptions::default()
        },
    )
    .unwrap();
    let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
    (file.figures(), file.leaf_depth_histogram())
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
}

#[test]
fn table1_counts_every_triangle_and_every_index() {
    let (r, _) = bunny_report();
    let s = &r.scenes[0];
    let scene = bunny();
    let tree = std_tree();
    // Leaves per triangle, counted by walking the tree.
    let mut per_tri = vec![0u64; scene.len()];
    tree.walk(|_, node, _, _| {
        if let Node::Leaf { start, count } = *node {
            for t in tree.leaf(start, count) {
                per_tri[t.0 as usize] += 1;
            }
        }
    });
    let t1 = &s.table1;
    assert_eq!(t1.triangles, scene.len() as u64);
    assert_eq!(
        t1.bins.iter().map(|b| b.triangles).sum::<u64>(),
        scene.len() as u64
    );
    assert_eq!(t1.total_indices, tree.leaf_tris.len() as u64);
    assert_eq!(t1.total_indices, per_tri.iter().sum::<u64>());
    assert!(close(
        t1.ratio(),
        tree.leaf_tris.len() as f64 / scene.len() as f64
    ));
    // The 12 intervals, plus the 0 row only if a triangle is in no leaf.
    let has_zero = per_tri.contains(&0);
    assert_eq!(t1.bins.len(), 12 + usize::from(has_zero));
    assert_eq!(t1.bins.last().unwrap().hi, None);
    assert_eq!(t1.bins.last().unwrap().lo, 15001);
    for b in &t1.bins {
        let hi = b.hi.unwrap_or(u64::MAX);
        let members: Vec<usize> = (0..scene.len())
            .filter(|&t| per_tri[t] >= b.lo && per_tri[t] <= hi)
            .collect();
        assert_eq!(b.triangles, members.len() as u64, "interval {}", b.label());
        if members.is_empty() {
            assert!(b.mean_longest_edge.is_nan());
        } else {
            let mean = members
                .iter()
                .map(|&t| {
                    let [a, b, c] = scene.tri(t as u32).map(|v| v.as_dvec3());
                    [a.distance(b), b.distance(c), c.distance(a)]
                        .into_iter()
                        .fold(0.0, f64::max)
                })
                .sum::<f64>()
                / members.len() as f64;
            assert!(close(b.mean_longest_edge, mean), "interval {}", b.label());
        }
    }
    // Consecutive intervals, as in the paper.
    let uppers: Vec<Option<u64>> = t1.bins.iter().map(|b| b.hi).collect();
    assert!(uppers.contains(&Some(10)) && uppers.contains(&Some(15000)));
    for w in t1.bins.windows(2) {
        assert_eq!(w[0].hi.unwrap() + 1, w[1].lo);
    }
}

#[test]
fn tables_2_and_3a_equal_the_written_files() {
    let (r, _) = bunny_report();
    let s = &r.scenes[0];
    let scene = bunny();
    let tree = std_tree();
    let (std_fig, std_hist) = written(tree);
    assert_eq!(s.table3a[0].tree, TreeKind::Std);
    assert_eq!(s.table3a[0].figures, std_fig);
    assert_eq!(s.table3a[0].figures.t_inner, 0);
    assert_eq!(s.leaf_depths[0], std_hist);
    // Table 2.
    assert_eq!(s.triangles, 3674);
    assert_eq!(s.vertices, scene.positions().len() as u64);
    assert_eq!(
        s.paper_geometry_bytes(),
        12 * scene.len() as u64 + 32 * scene.positions().len() as u64
    );
    assert_eq!(s.std_tree_bytes(), std_fig.tree_bytes());
    assert_eq!(
        s.classic_std_bytes(),
        8 * tree.nodes.len() as u64 + 4 * tree.leaf_tris.len() as u64
    );
    // 2-byte leaves make the stored tree smaller than the classic one.
    assert!(std_fig.idx16 > 0 && s.std_tree_bytes() < s.classic_std_bytes());
    // Fast and small: their std tree at their split price and the slim
    // pass, run here, written the same way.
    for (k, params) in [(1, SlimParams::FAST), (2, SlimParams::SMALL)] {
        let mut config = BuildConfig::default();
        config.sah.split_price = params.split_price.expect("the presets have a split price");
        let base = build::build(scene, &config, Algorithm::WaldHavran, None).unwrap();
        let (slim_tree, slim_report) = slim::slim(&base, scene, &config, &params);
        let (fig, hist) = written(&slim_tree);
        let row = &s.table3a[k];
        assert_eq!(row.tree, TreeKind::ALL[k]);
        assert_eq!(row.figures, fig, "{}", row.tree.name());
        assert_eq!(row.hoisted, slim_report.hoisted);
        assert_eq!(row.figures.t_inner as usize, slim_report.hoisted);
        assert_eq!(s.leaf_depths[k], hist);
        let bytes = fig.tree_bytes() as f64;
        assert!(close(
            s.reduction_pct(row.tree),
            100.0 * (1.0 - bytes / std_fig.tree_bytes() as f64)
        ));
        assert!(close(
            s.reduction_vs_classic_pct(row.tree),
            100.0 * (1.0 - bytes / s.classic_std_bytes() as f64)
        ));
    }
    assert_eq!(s.reduction_pct(TreeKind::Std), 0.0);
    // Figure 6: every histogram counts every leaf.
    for (row, hist) in s.table3a.iter().zip(&s.leaf_depths) {
        assert_eq!(hist.iter().sum::<u64>(), row.figures.leaves);
        assert_eq!(hist.len() as u32, row.max_depth + 1);
    }
}

#[test]
fn table3b_frames_agree_with_brute_force_and_losses_are_right() {
    let (r, _) = bunny_report();
    let s = &r.scenes[0];
    let views = views();
    let ids: Vec<&str> = s.table3b.iter().map(|v| v.view.as_str()).collect();
    assert_eq!(ids, ["1", "2", "3"]);
    for v in &s.table3b {
        let view = render::find_view(&views, Path::new("scenes/bunny_npm.obj"), &v.view).unwrap();
        let cam = Camera::from_view(view, SIZE.0, SIZE.1);
        let brute = render::trace_frame(&BruteForce(bunny()), &cam);
        assert_eq!(v.hits, brute.n_hits(), "view {}", v.view);
        assert_eq!(v.checksum, brute.checksum(), "view {}", v.view);
        assert!(v.hits > 0);
        for k in TreeKind::ALL {
            let rates = v.rates[k as usize].as_array();
            assert!(rates.iter().all(|x| x.is_finite() && *x > 0.0), "{rates:?}");
            let std = v.rates[0].as_array();
            let loss = v.loss_pct(k);
            for i in 0..4 {
                assert!(close(loss[i], 100.0 * (1.0 - rates[i] / std[i])));
            }
        }
        assert_eq!(v.loss_pct(TreeKind::Std), [0.0; 4]);
    }
    assert_eq!(r.all_threads, 2);
    assert_eq!((r.size, r.reps), (SIZE, 1));
}

#[test]
fn table4_and_figure5_are_consistent() {
    let (r, lines) = bunny_report();
    let s = &r.scenes[0];
    let t = &s.table4;
    assert_eq!(t.load_s, 0.25);
    for x in [t.std_build_s, t.slim_s[0], t.slim_s[1]]
        .into_iter()
        .chain(t.write_s)
    {
        assert!(x.is_finite() && x >= 0.0);
    }
    for i in 0..2 {
        // The presets have their own split price, hence their own std tree.
        assert!(t.base_s[i] > 0.0);
        assert!(close(
            t.slim_ratio(i),
            (t.base_s[i] + t.slim_s[i]) / t.std_build_s
        ));
    }
    // The sweep: the grid in order, each point checked against its tree.
    let grid: Vec<(f64, f64)> = s.sweep.iter().map(|p| (p.tau_occu, p.tau_freq)).collect();
    let expected: Vec<(f64, f64)> = GRID_OCCU
        .iter()
        .flat_map(|&o| GRID_FREQ.iter().map(move |&f| (o, f)))
        .collect();
    assert_eq!(grid, expected);
    let std_bytes = s.std_tree_bytes() as f64;
    for p in &s.sweep {
        assert_eq!(p.max_t2rn, report::SWEEP_MAX_T2RN);
        let params = SlimParams {
            tau_occu: p.tau_occu,
            tau_freq: p.tau_freq,
            max_t2rn: p.max_t2rn,
            rule: SlimParams::FAST.rule,
            rebuild: slimkd::slim::Rebuild::Sah,
            coarsen: 1.0,
            cost_ratio: f64::INFINITY,
            split_price: None,
        };
        let (tree, sr) = slim::slim(std_tree(), bunny(), &BuildConfig::default(), &params);
        assert_eq!(p.tree_bytes, written(&tree).0.tree_bytes());
        assert_eq!(p.hoisted, sr.hoisted);
        assert!(close(
            p.reduction_pct,
            100.0 * (1.0 - p.tree_bytes as f64 / std_bytes)
        ));
        assert_eq!(p.view_loss_pct.len(), 3);
        assert!(close(p.loss_pct, report::median(&p.view_loss_pct)));
    }
    // (0.5, 0.4) is the paper's s setting, with the report's byte rule.
    let small = s
        .sweep
        .iter()
        .find(|p| (p.tau_occu, p.tau_freq) == (0.5, 0.4))
        .unwrap();
    let paper_s = SlimParams::PAPER_SMALL.with_rule(SlimParams::FAST.rule);
    let (tree, _) = slim::slim(std_tree(), bunny(), &BuildConfig::default(), &paper_s);
    assert_eq!(small.tree_bytes, written(&tree).0.tree_bytes());
    // Progress: one line per step, prefixed with the scene.
    assert_eq!(lines[0], "bunny_npm: building std tree");
    assert!(lines.iter().all(|l| l.starts_with("bunny_npm: ")));
    assert!(lines.iter().any(|l| l.contains("slim pass (small)")));
    assert_eq!(lines.iter().filter(|l| l.contains("sweep")).count(), 4);
}

/// The rows of every Markdown table: a table's lines all have one width.
fn check_tables_aligned(md: &str) -> usize {
    let mut tables = 0;
    let mut width = None;
    for line in md.lines() {
        if line.starts_with('|') {
            let w = line.chars().count();
            match width {
                None => {
                    tables += 1;
                    width = Some(w);
                }
                Some(x) => assert_eq!(x, w, "misaligned row: {line}"),
            }
        } else {
            width = None;
        }
    }
    tables
}

#[test]
fn markdown_and_json_hold_the_numbers() {
    let (r, _) = bunny_report();
    let s = &r.scenes[0];
    let md = r.markdown();
    for heading in [
        "## Table 1",
        "## Table 2",
        "## Table 3(a)",
        "## Table 3(b)",
        "## Table 4",
        "## Figure 5",
        "## Figure 6",
        "](report.figure5.svg)",
        "](report.figure6.svg)",
        "level builder",
        "32×32",
        "2 threads",
        "median of 1 frame",
    ] {
        assert!(md.contains(heading), "no `{heading}` in\n{md}");
    }
    // Table 1 (1), Table 2, 3(a), 3(b), 4, the sweep, Figure 6 (1).
    assert_eq!(check_tables_aligned(&md), 7);
    let total = format!("Total indices {}", s.table1.total_indices);
    assert!(md.contains(&total));
    let j = r.json();
    let js = &j["scenes"][0];
    assert_eq!(js["name"], "bunny_npm");
    assert_eq!(js["table1"]["total_indices"], s.table1.total_indices);
    let bins = js["table1"]["bins"].as_array().unwrap();
    assert_eq!(
        bins.iter()
            .map(|b| b["triangles"].as_u64().unwrap())
            .sum::<u64>(),
        3674
    );
    assert_eq!(js["table2"]["std_tree_bytes"], s.std_tree_bytes());
    assert_eq!(js["table2"]["std_classic_bytes"], s.classic_std_bytes());
    for (k, row) in s.table3a.iter().enumerate() {
        let jr = &js["table3a"][k];
        assert_eq!(jr["tree"], row.tree.name());
        assert_eq!(jr["tree_bytes"], row.figures.tree_bytes());
        assert_eq!(jr["idx16"], row.figures.idx16);
        assert_eq!(jr["nodes_t_inner"], row.figures.t_inner);
    }
    assert_eq!(js["table3b"].as_array().unwrap().len(), 3);
    assert_eq!(js["table3b"][0]["hits"], s.table3b[0].hits);
    assert_eq!(
        js["table3b"][1]["trees"][2]["packet_all"].as_f64().unwrap(),
        s.table3b[1].rates[2].packet_all
    );
    assert_eq!(js["figure5"].as_array().unwrap().len(), 4);
    assert_eq!(js["figure6"]["small"], serde_json::json!(s.leaf_depths[2]));
    assert_eq!(j["machine"]["all_threads"], 2);
    assert_eq!(j["machine"]["reps"], 1);
    assert_eq!(j["build"]["builder"], "level");
}

/// JSON equality up to the last bits of floats (serde_json's default float
/// parser is not correctly rounded).
fn same_json(a: &serde_json::Value, b: &serde_json::Value) -> bool {
    use serde_json::Value;
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => match (x.as_u64(), y.as_u64()) {
            (Some(x), Some(y)) => x == y,
            _ => close(x.as_f64().unwrap(), y.as_f64().unwrap()),
        },
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(x, y)| same_json(x, y))
        }
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len()
                && x.iter()
                    .all(|(k, v)| y.get(k).is_some_and(|w| same_json(v, w)))
        }
        _ => a == b,
    }
}

#[test]
fn write_puts_every_file_in_place_atomically() {
    let (r, _) = bunny_report();
    let dir = fresh_temp_dir("write");
    let md_path = dir.join("report.md");
    let paths = r.write(&md_path).unwrap();
    let expected: Vec<PathBuf> = [
        "report.md",
        "report.json",
        "report.figure5.svg",
        "report.figure6.svg",
    ]
    .iter()
    .map(|n| dir.join(n))
    .collect();
    assert_eq!(paths, expected);
    // Nothing else: no temporary file left.
    let names = dir_entries(&dir);
    assert_eq!(
        names,
        [
            "report.figure5.svg",
            "report.figure6.svg",
            "report.json",
            "report.md"
        ]
    );
    assert_eq!(std::fs::read_to_string(&md_path).unwrap(), r.markdown());
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    assert!(
        same_json(&j, &r.json()),
        "the file's JSON differs from Report::json"
    );
    for fig in ["report.figure5.svg", "report.figure6.svg"] {
        let svg = std::fs::read_to_string(dir.join(fig)).unwrap();
        assert!(svg.starts_with("<svg"), "{fig}");
        assert!(svg.trim_end().ends_with("</svg>"), "{fig}");
        assert!(svg.contains("bunny_npm"), "{fig}");
    }
    let fig5 = std::fs::read_to_string(dir.join("report.figure5.svg")).unwrap();
    assert!(fig5.contains("0.5/0.4") && fig5.contains("size reduction"));
    let fig6 = std::fs::read_to_string(dir.join("report.figure6.svg")).unwrap();
    assert!(fig6.contains("small") && fig6.contains("depth"));
    // Writing again replaces the files.
    r.write(&md_path).unwrap();
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 4);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn write_into_a_missing_directory_fails_and_leaves_nothing() {
    let (r, _) = bunny_report();
    let dir = fresh_temp_dir("missing");
    let missing = dir.join("no").join("such");
    let err = r.write(&missing.join("report.md")).unwrap_err();
    assert_eq!(err.kind(), std::io::ErrorKind::NotFound);
    assert!(err.to_string().contains("report.md"), "{err}");
    assert!(!dir.join("no").exists());
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
    // A Markdown path ending in .json would be overwritten by the JSON.
    let err = r.write(&dir.join("r.json")).unwrap_err();
    assert_eq!(err.kind(), std::io::ErrorKind::InvalidInput);
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn scene_without_views_uses_the_default_camera_and_no_sweep_writes_no_figure5() {
    let options = ReportOptions {
        scenes: vec![("my_bunny_copy.obj".into(), bunny().clone(), 0.0)],
        views: Vec::new(),
        size: (16, 8),
        reps: 2,
        sweep: false,
        all_threads: 1,
        sweep_grid: None,
        rule: SlimParams::FAST.rule,
    };
    let r = report::run(&options, &mut |_| {}).unwrap();
    let s = &r.scenes[0];
    assert_eq!(s.table3b.len(), 1);
    assert_eq!(s.table3b[0].view, "default");
    let cam = Camera::default_for(&bunny().bounds(), 16, 8);
    let brute = render::trace_frame(&BruteForce(bunny()), &cam);
    assert_eq!(s.table3b[0].hits, brute.n_hits());
    assert!(s.sweep.is_empty());
    let md = r.markdown();
    assert!(!md.contains("## Figure 5") && md.contains("## Figure 6"));
    let dir = fresh_temp_dir("nosweep");
    let paths = r.write(&dir.join("out.md")).unwrap();
    assert_eq!(
        paths,
        [
            dir.join("out.md"),
            dir.join("out.json"),
            dir.join("out.figure6.svg")
        ]
    );
    // The Markdown links the figure by that name.
    let written = std::fs::read_to_string(dir.join("out.md")).unwrap();
    assert!(written.contains("](out.figure6.svg)"), "{written}");
    assert_eq!(written, r.markdown_for(&dir.join("out.md")));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_options_are_errors() {
    let base = ReportOptions {
        scenes: Vec::new(),
        size: (8, 8),
        reps: 1,
        all_threads: 1,
        ..ReportOptions::default()
    };
    for bad in [
        ReportOptions {
            reps: 0,
            ..base.clone()
        },
        ReportOptions {
            all_threads: 0,
            ..base.clone()
        },
        ReportOptions {
            size: (0, 8),
            ..base.clone()
        },
    ] {
        let e = report::run(&bad, &mut |_| {}).unwrap_err();
        assert!(matches!(e, ReportError::Options(_)), "{e}");
    }
    // No scenes: an empty report that still renders.
    let r = report::run(&base, &mut |_| {}).unwrap();
    assert!(r.scenes.is_empty());
    assert!(r.markdown().contains("# slimkd report"));
    assert!(r.figure6_svg().unwrap().starts_with("<svg"));
}

/// Table 3(b) shows the spread of the per-repetition losses: each loss is
/// the median of the pairs' losses within its interquartile range, std's
/// is zero, and the Markdown gives the ranges and marks with ≈ those that
/// include 0. A scene without views is timed from the default camera with
/// a warning line (which starts no step), and the report's progress ends at
/// exactly 1 over all its steps.
#[test]
fn losses_have_their_spread_and_viewless_scenes_warn() {
    let options = ReportOptions {
        scenes: vec![("rabbit".into(), bunny().clone(), 0.0)],
        views: views(),
        size: SIZE,
        reps: 5,
        sweep: false,
        all_threads: 2,
        sweep_grid: None,
        rule: SlimParams::FAST.rule,
    };
    let progress = slimkd::progress::Progress::default();
    let mut lines = Vec::new();
    let r = report::run_with_progress(&options, Some(&progress), &mut |l| {
        lines.push(l.to_string())
    })
    .unwrap();
    assert_eq!(progress.fraction(), 1.0);
    let warnings: Vec<&String> = lines.iter().filter(|l| l.starts_with("warning:")).collect();
    assert_eq!(warnings.len(), 1, "{lines:?}");
    assert!(warnings[0].contains("rabbit") && warnings[0].contains("default camera"));
    let s = &r.scenes[0];
    assert_eq!(s.table3b.len(), 1);
    let v = &s.table3b[0];
    assert_eq!(v.view, "default");
    for k in TreeKind::ALL {
        for (i, sp) in v.loss[k as usize].iter().enumerate() {
            assert!(sp.min <= sp.q1 && sp.q1 <= sp.median, "{sp:?}");
            assert!(sp.median <= sp.q3 && sp.q3 <= sp.max, "{sp:?}");
            assert_eq!(v.loss_pct(k)[i], sp.median);
        }
    }
    assert!(
        v.loss[0]
            .iter()
            .all(|sp| (sp.min, sp.max) == (0.0, 0.0) && sp.includes_zero())
    );
    let md = r.markdown();
    assert!(md.contains("interquartile range"), "{md}");
    for k in [TreeKind::Fast, TreeKind::Small] {
        let sp = &v.loss[k as usize][3];
        let cell = format!("{:.1} ({:.1}…{:.1})", sp.median, sp.q1, sp.q3);
        assert!(md.contains(&cell), "{cell} in {md}");
    }
    let marked = v.loss[1..].iter().flatten().any(|sp| sp.includes_zero());
    assert_eq!(md.contains(") ≈"), marked, "{md}");
    let j = r.json();
    let spread = &j["scenes"][0]["table3b"][0]["trees"][1]["loss_spread_pct"]["packet_all"];
    assert_eq!(spread["q1"].as_f64().unwrap(), v.loss[1][3].q1);
    assert_eq!(j["schema"], 1);
}

#[test]
fn sweep_options_out_of_range_are_errors() {
    let scene = slimkd::scene::load_obj(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_npm.obj"),
    )
    .unwrap()
    .0;
    let std = FrontSetting {
        label: "std".into(),
        k_t: 15.0,
        k_i: 20.0,
        split_price: 0.0,
        slim: None,
        preset: None,
    };
    let options = |reps, threads, grid| FrontOptions {
        scenes: vec![("bunny_npm".into(), scene.clone())],
        views: Vec::new(),
        size: (8, 8),
        reps,
        threads,
        grid: Some(grid),
    };
    let grid = |points: Vec<usize>| FrontGrid {
        settings: vec![std.clone()],
        families: vec![front::FrontFamily {
            name: "one".into(),
            points,
        }],
    };
    let run = |o: &FrontOptions| front::run_front(o, None, &mut |_| {});
    for o in [
        options(0, 1, grid(vec![0])),
        options(1, 0, grid(vec![0])),
        options(1, 1, grid(vec![0, 1])),
        options(
            1,
            1,
            FrontGrid {
                settings: Vec::new(),
                families: Vec::new(),
            },
        ),
    ] {
        assert!(matches!(run(&o), Err(ReportError::Options(_))));
    }
    // One setting: a front of one point, traced from the default camera.
    let r = run(&options(1, 1, grid(vec![0]))).unwrap();
    let s = &r.scenes[0];
    assert_eq!(s.views, ["default"]);
    assert_eq!(s.points.len(), 1);
    assert!(s.points[0].on_front);
}

/// The figures of the default grid that `tests/sweep.rs` holds the
/// sweep's JSON to.
#[test]
fn the_default_grid_is_the_one_the_cli_test_expects() {
    assert_eq!(front::default_grid().settings.len(), 20);
    assert_eq!(front::FRONT_KT, [10.0, 15.0, 20.0, 30.0, 45.0]);
    assert_eq!(front::FRONT_SPLIT_PRICE, [0.0, 0.25, 0.5, 1.0, 8.0]);
}
