//! The committed golden `.kd` files (`tests/golden/`): the current
//! version's must keep loading; version 1's must be refused with a message
//! that says to rebuild it.

mod common;

use common::kd::*;
use glam::Vec3;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, FileConfig, KdFile, Preset, WriteOptions, aligned_copy};
use slimkd::geom::Ray;
use slimkd::scene::TriangleColumns;
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{self, ClosestHit, Hit};
use slimkd::tree::TreeIr;
use std::path::PathBuf;

// ---------------------------------------------------------------------
// The golden file.
// ---------------------------------------------------------------------

/// How the golden file was made: the bunny, the SAH tree of the sweep
/// builder with the default costs and a depth limit of 16 (to keep the file
/// small), type II nodes made by `hoist` (seed 2024, hoisted triangles
/// sometimes removed from the leaves below), reordered; the header records
/// the costs, the depth limit and the `custom` preset.
fn golden_inputs() -> (TriangleColumns, TreeIr, WriteOptions) {
    let scene = load_scene("bunny_npm.obj");
    let mut config = BuildConfig::default();
    config.sah.max_depth = Some(GOLDEN_DEPTH_LIMIT);
    // The file was made before splits had a price.
    config.sah.split_price = 0.0;
    let std = build::build(&scene, &config, Algorithm::WaldHavran, None).unwrap();
    let (tree, _) = hoist(&std, &scene, 2024, true);
    let options = WriteOptions {
        reorder: true,
        config: FileConfig {
            k_t: config.sah.k_t,
            k_i: config.sah.k_i,
            lambda_empty: config.sah.lambda_empty,
            depth_limit: GOLDEN_DEPTH_LIMIT,
            preset: Preset::Custom,
            ..FileConfig::default()
        },
    };
    (scene, tree, options)
}

const GOLDEN_DEPTH_LIMIT: u32 = 16;

fn golden_path() -> PathBuf {
    manifest_dir().join("tests/golden/bunny_npm.v2.kd")
}

/// The same inputs written by format version 1 (children in blocks of two,
/// every empty leaf a word).
fn golden_v1_path() -> PathBuf {
    manifest_dir().join("tests/golden/bunny_npm.v1.kd")
}

/// A version-1 file is refused, and the error says what to do.
#[test]
fn version_1_file_says_to_rebuild() {
    let bytes = std::fs::read(golden_v1_path()).unwrap();
    assert_eq!(bytes.len(), 170_368);
    let err = KdFile::from_bytes(aligned_copy(&bytes))
        .err()
        .expect("version 1 is refused");
    assert!(
        matches!(
            err,
            format::FormatError::Version {
                expected: 2,
                got: 1
            }
        ),
        "{err:?}"
    );
    let message = err.to_string();
    assert!(
        message.contains("version 1") && message.contains("rebuild"),
        "{message}"
    );
}

/// Rewrites `tests/golden/bunny_npm.kd`. Run only on purpose, when the
/// format changes (with a new version number):
/// `cargo test --release --test format_golden -- --ignored regenerate_golden`.
#[test]
#[ignore]
fn regenerate_golden() {
    let (scene, tree, options) = golden_inputs();
    format::write_file(&golden_path(), &tree, &scene, &options).unwrap();
    let file = KdFile::open(&golden_path(), slimkd::format::Check::Verify).unwrap();
    eprintln!(
        "wrote {} ({} bytes): {:?}, max depth {}",
        golden_path().display(),
        file.as_bytes().len(),
        file.figures(),
        file.max_depth()
    );
}

/// The committed golden file (see `tests/golden/README.md`) still loads,
/// verifies, has the figures it was written with, and traces exactly like
/// brute force on the scene re-loaded from the OBJ: files written by
/// earlier builds stay readable.
#[test]
fn golden_file_still_loads() {
    let bytes = std::fs::read(golden_path()).unwrap();
    assert_eq!(bytes.len(), GOLDEN_SIZE);
    let file = KdFile::from_bytes(aligned_copy(&bytes)).unwrap();
    file.verify().unwrap();
    assert_eq!(file.figures(), GOLDEN_FIGURES);
    assert_eq!(file.max_depth(), GOLDEN_MAX_DEPTH);
    assert!(file.is_reordered());
    let scene = load_scene("bunny_npm.obj");
    let c = file.config();
    assert_eq!((c.k_t, c.k_i, c.lambda_empty), (15.0, 20.0, 0.8));
    assert_eq!(c.depth_limit, GOLDEN_DEPTH_LIMIT);
    assert_eq!(c.preset, Preset::Custom);
    assert_eq!(file.bounds(), scene.bounds());
    // A fan of rays from a grid of points around the bunny towards its
    // centre, and along the axes.
    let b = scene.bounds();
    let (lo, ext) = (b.min - b.extent() * 0.25, b.extent() * 1.5);
    let centre = b.center();
    let mut rays = Vec::new();
    for i in 0..6 {
        for j in 0..6 {
            for k in 0..6 {
                let o = lo + ext * Vec3::new(i as f32, j as f32, k as f32) / 5.0;
                rays.push(Ray::new(o, centre - o));
                rays.push(Ray::new(o, Vec3::X));
                rays.push(Ray::new(o, -Vec3::Y));
                rays.push(Ray::new(o, Vec3::Z));
            }
        }
    }
    let mut hits = 0;
    for ray in &rays {
        let want = trace::brute_force(&scene, ray);
        hits += usize::from(want.is_hit());
        assert_eq!(trace::traverse(&file, ray), want, "ray {ray:?}");
    }
    assert!(hits > rays.len() / 10, "{hits} hits");
    let mut rng = Rng(600);
    for rays in packets_at(&b, &mut rng, 8) {
        let want: Vec<Hit> = rays.iter().map(|r| trace::brute_force(&scene, r)).collect();
        for level in SimdLevel::available() {
            let mut got = [Hit::MISS; 16];
            PacketTracer::with_level(&file, level).closest_hit_4x4(&rays, &mut got);
            assert_eq!(got.to_vec(), want, "{level:?}");
        }
    }
}

// The golden file's size and figures, as written by `regenerate_golden`.
const GOLDEN_SIZE: usize = 154_880;
const GOLDEN_MAX_DEPTH: u32 = 16;
const GOLDEN_FIGURES: format::TreeFigures = format::TreeFigures {
    inner: 1721,
    t_inner: 1852,
    leaves: 3574,
    implicit_empty: 1922,
    one_leaves: 60,
    idx32: 0,
    idx16: 8465,
    triangles: 3674,
    vertices: 1839,
    words: 7077,
};
