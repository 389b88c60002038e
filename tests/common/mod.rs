//! Shared test helpers: grid-snapped scenes and rays (vertices on integers,
//! rays through half-integers, as svenstaro/bvh's test base does), the
//! checks every test ends with, and temporary directories.

#![allow(dead_code)]

pub mod kd;

use glam::Vec3;
use proptest::prelude::*;
use slimkd::build::level::LevelOptions;
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::format::{self, WriteOptions};
use slimkd::geom::Ray;
use slimkd::scene::TriangleColumns;
use slimkd::slim::{self, SlimParams};
use slimkd::trace;
use slimkd::tree::TreeIr;

/// A triangle with integer vertices in `[0, g]³`.
pub fn grid_triangle(g: i32) -> impl Strategy<Value = [Vec3; 3]> {
    let v = (0..=g, 0..=g, 0..=g).prop_map(|(x, y, z)| Vec3::new(x as f32, y as f32, z as f32));
    [v.clone(), v.clone(), v]
}

/// 0–`max` grid triangles in `[0, g]³` for a random `g` in 1..=6.
pub fn grid_scene(max: usize) -> impl Strategy<Value = Vec<[Vec3; 3]>> {
    (1i32..=6).prop_flat_map(move |g| prop::collection::vec(grid_triangle(g), 0..=max))
}

/// A ray from a half-integer (or integer) point towards another, so that it
/// passes through half-integers; sometimes axis-aligned, sometimes starting
/// on a grid plane.
pub fn grid_ray(g: i32) -> impl Strategy<Value = Ray> {
    let coord = move || (-2..=2 * g + 2).prop_map(|k| k as f32 * 0.5);
    let point = move || (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    (point(), point(), 0..4u8).prop_filter_map("zero direction", |(o, target, kind)| {
        let mut d = target - o;
        if kind == 0 {
            // Axis-aligned: keep the largest component only.
            let a = d.abs();
            d = if a.x >= a.y && a.x >= a.z {
                Vec3::new(d.x, 0.0, 0.0)
            } else if a.y >= a.z {
                Vec3::new(0.0, d.y, 0.0)
            } else {
                Vec3::new(0.0, 0.0, d.z)
            };
        }
        (d != Vec3::ZERO).then(|| Ray::new(o, d))
    })
}

pub fn columns(tris: &[[Vec3; 3]]) -> TriangleColumns {
    TriangleColumns::from_triangles(tris).expect("finite test triangles")
}

/// Builds with every builder (naive, Wald-Havran and level), asserts they
/// produce the same tree and that it is valid; slims it with the `fast`
/// preset (a valid tree too) and writes both trees to `.kd` bytes that
/// read back, verify and hold the tree's nodes. Returns the standard tree.
pub fn build_checked(scene: &TriangleColumns, config: &BuildConfig) -> TreeIr {
    let wald_havran = build::build(scene, config, Algorithm::WaldHavran, None).unwrap();
    let naive = build::build(scene, config, Algorithm::Naive, None).unwrap();
    assert_eq!(wald_havran, naive, "Wald-Havran and naive trees differ");
    if let Err(e) = wald_havran.validate(scene) {
        panic!("invalid tree: {e}\n{wald_havran:?}");
    }
    let (level, _) = build::level::build(scene, config, None, &LevelOptions::default())
        .expect("the level build succeeds");
    assert_eq!(level, wald_havran, "level and Wald-Havran trees differ");
    let (slim, _) = slim::slim(&wald_havran, scene, config, &SlimParams::FAST);
    if let Err(e) = slim.validate(scene) {
        panic!("invalid slim tree: {e}\n{slim:?}");
    }
    for tree in [&wald_havran, &slim] {
        assert_round_trip(tree, scene);
    }
    wald_havran
}

/// Writes `tree` to `.kd` bytes and reads them back: the file is valid,
/// its checksums hold, and it holds the tree (the same nodes, split planes
/// bit for bit, leaves as sets of input ids) and its figures.
pub fn assert_round_trip(tree: &TreeIr, scene: &TriangleColumns) {
    let bytes = format::write_to_vec(tree, scene, &WriteOptions::default()).unwrap();
    let file = kd::read(&bytes);
    assert_eq!(kd::file_shape(&file), kd::ir_shape(tree), "the file's tree");
    kd::assert_figures(&file, tree, scene);
}

/// Asserts that traversal returns exactly brute force's hit for each ray.
pub fn assert_traversal_matches(tree: &TreeIr, scene: &TriangleColumns, rays: &[Ray]) {
    for ray in rays {
        let want = trace::brute_force(scene, ray);
        let got = trace::closest_hit(tree, scene, ray);
        assert_eq!(got, want, "ray {ray:?}");
    }
}

/// Rays from many half-integer points of `[-1, g+1]³` towards the centre
/// and along the axes.
pub fn ray_fan(g: f32) -> Vec<Ray> {
    let mut rays = Vec::new();
    let c = Vec3::splat(g * 0.5 + 0.25);
    let steps = [-1.0, -0.5, 0.0, 0.5, 0.25 * g, 0.5 * g, g, g + 0.5, g + 1.0];
    for &x in &steps {
        for &y in &steps {
            for &z in &steps {
                let o = Vec3::new(x, y, z);
                if o != c {
                    rays.push(Ray::new(o, c - o));
                }
                for d in [Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X, -Vec3::Y, -Vec3::Z] {
                    rays.push(Ray::new(o, d));
                }
            }
        }
    }
    rays
}

/// `n` cases, or `PROPTEST_CASES` when set (for long stress runs: the
/// explicit count would otherwise override the variable).
pub fn cases(n: u32) -> ProptestConfig {
    let env = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok());
    ProptestConfig::with_cases(env.unwrap_or(n))
}

pub fn v(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3::new(x, y, z)
}

/// The 12 triangles of an axis-aligned box.
pub fn box_mesh(lo: Vec3, hi: Vec3) -> Vec<[Vec3; 3]> {
    let c = |i: u32| {
        v(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        )
    };
    let quads = [
        [0, 1, 3, 2],
        [4, 6, 7, 5],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 5, 7, 3],
    ];
    quads
        .iter()
        .flat_map(|q| [[c(q[0]), c(q[1]), c(q[2])], [c(q[0]), c(q[2]), c(q[3])]])
        .collect()
}

/// 16 rays from one half-integer origin towards a 4×4 grid of targets (a
/// coherent packet), or 16 independent grid rays.
pub fn packet(g: i32) -> impl Strategy<Value = [Ray; 16]> {
    let coord = move || (-2..=2 * g + 2).prop_map(|k| k as f32 * 0.5);
    let point = move || (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    let coherent = (point(), point(), 1..4i32, 0..3usize).prop_map(|(o, t, step, axis)| {
        std::array::from_fn(|i| {
            let mut target = t;
            let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
            target[a] += (i % 4) as f32 * 0.5 * step as f32;
            target[b] += (i / 4) as f32 * 0.5 * step as f32;
            let d = target - o;
            Ray::new(o, if d == Vec3::ZERO { Vec3::X } else { d })
        })
    });
    let loose = prop::collection::vec(grid_ray(g), 16).prop_map(|v| std::array::from_fn(|i| v[i]));
    prop_oneof![3 => coherent, 1 => loose]
}

/// The named degenerate shapes: the scenes of `tests/degenerate.rs`, which
/// `tests/level.rs` also builds with every threshold.
pub fn degenerate_scenes() -> Vec<(&'static str, Vec<[Vec3; 3]>)> {
    let mut out = vec![("empty", vec![])];
    out.push((
        "one triangle",
        vec![[v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0)]],
    ));
    let mut sheet = Vec::new();
    for i in 0..8 {
        for j in 0..8 {
            let (x, y) = (i as f32, j as f32);
            sheet.push([v(x, y, 2.0), v(x + 1.0, y, 2.0), v(x, y + 1.0, 2.0)]);
            sheet.push([
                v(x + 1.0, y, 2.0),
                v(x + 1.0, y + 1.0, 2.0),
                v(x, y + 1.0, 2.0),
            ]);
        }
    }
    out.push(("all coplanar", sheet));
    let mut lattice = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                let lo = v(i as f32 * 2.0, j as f32 * 2.0, k as f32 * 2.0);
                lattice.extend(box_mesh(lo, lo + Vec3::ONE));
            }
        }
    }
    out.push(("axis-aligned in split planes", lattice));
    out.push((
        "zero-area and point",
        vec![
            [v(0.0, 0.0, 0.0), v(1.0, 1.0, 1.0), v(2.0, 2.0, 2.0)],
            [v(1.0, 1.0, 1.0); 3],
            [v(3.0, 0.0, 0.0), v(3.0, 0.0, 0.0), v(3.0, 2.0, 0.0)],
            [v(0.0, 0.0, 1.0), v(3.0, 0.0, 1.0), v(0.0, 3.0, 1.0)],
        ],
    ));
    let t = [v(0.0, 0.0, 1.0), v(2.0, 0.0, 1.0), v(0.0, 2.0, 1.0)];
    let mut dups = vec![[v(5.0, 5.0, 5.0), v(6.0, 5.0, 5.0), v(5.0, 6.0, 5.0)]];
    dups.extend(std::iter::repeat_n(t, 10));
    out.push(("coincident duplicates", dups));
    let mut needle = vec![[v(0.0, 0.0, 0.0), v(100.0, 0.001, 0.0), v(100.0, 0.0, 0.002)]];
    for i in 0..20 {
        let x = i as f32 * 5.0;
        needle.push([v(x, -1.0, -1.0), v(x, 1.0, -1.0), v(x, 0.0, 1.0)]);
    }
    out.push(("needle", needle));
    let mut huge = vec![[
        v(-100.0, -100.0, 0.5),
        v(300.0, -100.0, 0.5),
        v(-100.0, 300.0, 0.5),
    ]];
    for i in 0..6 {
        for j in 0..6 {
            let (x, y) = (i as f32 * 10.0, j as f32 * 10.0);
            huge.push([v(x, y, 0.0), v(x + 1.0, y, 1.0), v(x, y + 1.0, 1.0)]);
        }
    }
    out.push(("huge triangle spanning the scene", huge));
    let mut boxes = box_mesh(v(0.0, 0.0, 0.0), v(10.0, 10.0, 10.0));
    boxes.extend(box_mesh(v(4.0, 4.0, 4.0), v(6.0, 6.0, 6.0)));
    out.push(("box inside a box", boxes));
    let mut deep = Vec::new();
    let mut s = 1.0f32;
    for _ in 0..60 {
        deep.push([v(0.0, 0.0, 0.0), v(s, 0.0, 0.0), v(0.0, s, s)]);
        s *= 0.5;
    }
    out.push(("deep corner cluster", deep));
    out
}

/// The degenerate scene called `name` in [`degenerate_scenes`].
pub fn degenerate_scene(name: &str) -> Vec<[Vec3; 3]> {
    degenerate_scenes()
        .into_iter()
        .find(|(n, _)| *n == name)
        .unwrap_or_else(|| panic!("no degenerate scene {name:?}"))
        .1
}

/// A directory of one test under the system temporary directory, removed
/// with everything in it when the test ends, unless it fails: a failing
/// test's files stay for a look.
pub struct TestDir(std::path::PathBuf);

impl std::ops::Deref for TestDir {
    type Target = std::path::Path;
    fn deref(&self) -> &std::path::Path {
        &self.0
    }
}

impl AsRef<std::path::Path> for TestDir {
    fn as_ref(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TestDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A directory of this test process (named after the test file, the
/// process and `name`) under the system temporary directory, made if
/// missing; removed when the returned guard drops (see [`TestDir`]).
pub fn temp_dir(name: &str) -> TestDir {
    let dir = std::env::temp_dir().join(format!(
        "slimkd-{}-{}-{name}",
        env!("CARGO_CRATE_NAME"),
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("cannot make {}: {e}", dir.display()));
    TestDir(dir)
}

/// [`temp_dir`], emptied first: a fresh, empty directory for one test.
pub fn fresh_temp_dir(name: &str) -> TestDir {
    let dir = temp_dir(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("cannot make {}: {e}", dir.display()));
    dir
}

/// The names of the entries of `dir`, sorted.
pub fn dir_entries(dir: &std::path::Path) -> Vec<String> {
    slimkd::fsio::entry_names(dir).unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
}

/// Runs the `slimkd` binary of this build with `args`.
pub fn slimkd(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_slimkd"))
        .args(args)
        .output()
        .expect("the binary runs")
}

/// The one JSON object a successful command printed.
pub fn json(out: &std::process::Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("one JSON object")
}

/// Says that the calling test cannot run on this machine, and why, where
/// `cargo test` shows it: on the process's standard error, which the test
/// harness does not capture (it captures `println!` and `eprintln!`).
/// Where `SLIMKD_REQUIRE_TOOLS` is set the test fails instead: `.ci/run`
/// installs every tool the tests need and sets it, so nothing skips there.
/// The caller returns after it.
pub fn skip(reason: &str) {
    use std::io::Write;
    let test = std::thread::current()
        .name()
        .unwrap_or("a test")
        .to_string();
    assert!(
        std::env::var_os("SLIMKD_REQUIRE_TOOLS").is_none(),
        "{test} cannot run here: {reason} (SLIMKD_REQUIRE_TOOLS is set)"
    );
    let _ = writeln!(std::io::stderr(), "skipped {test}: {reason}");
}

/// Rays from grid points of `[0, g]³` at half-integer steps (on split
/// planes, box faces, edges and corners of cells) in scattered directions
/// (many along an axis, so with zero components, or a diagonal), short
/// and long, as shadow and ambient-occlusion rays are.
pub fn secondary_ray(g: i32) -> impl Strategy<Value = Ray> {
    let coord = move || (-1..=2 * g + 1).prop_map(|k| k as f32 * 0.5);
    let point = (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    let dir = (-4i32..=4, -4i32..=4, -4i32..=4)
        .prop_filter("zero direction", |&(x, y, z)| (x, y, z) != (0, 0, 0))
        .prop_map(|(x, y, z)| Vec3::new(x as f32, y as f32, z as f32));
    (
        point,
        dir,
        prop_oneof![Just(0.0f32), 0.0f32..0.5],
        prop_oneof![Just(f32::INFINITY), 0.1f32..4.0],
    )
        .prop_map(|(o, d, tmin, span)| Ray {
            tmin,
            tmax: tmin + span,
            ..Ray::new(o, d)
        })
}
