//! The cost of a traversal step and of a ray–triangle test, measured on
//! the traverser as it is (`slimkd calibrate`): the figures the SAH's
//! `K_T` and `K_I` stand for.
//!
//! [`measure_scene`] builds a scene's tree at several `K_T` values (with
//! one `K_I`), so that the ratio of steps to tests per ray varies, writes
//! each as `.kd` bytes (Morton-reordered, as `build --reorder` does) and
//! traces primary rays from the scene's views and ambient-occlusion rays
//! from their hits ([`slimkd::trace::rays::secondary_rays`]) through each,
//! as single rays and as 16-ray packets. Each combination is a
//! [`Sample`]: its time per ray (the median over the repetitions, the
//! trees interleaved within each repetition so that drift in the machine's
//! speed touches all alike) and its work per ray, counted by the counting
//! traversal in an untimed pass (deterministic). [`fit`] then finds
//! non-negative `a`, `b`, `c` of `time = a·steps + b·tests + c` per ray by
//! least squares. A step is a node visited, inner or leaf; for packets it
//! is one node step of the packet (shared by its active lanes) or of a ray
//! of a small packet or a one-lane cell walked ray by ray, and a test is
//! one lane's test. So `a/b`
//! is the ratio `K_T/K_I` of the traverser per step it executes; the SAH
//! prices a node visit of one ray, which for packets is `a` times the
//! packet steps per visit ([`packet_steps_per_visit`]: about 0.14 on
//! primary rays, 0.94 on AO rays over the six shared scenes).
//!
//! Times are processor time per ray (the process's processor clock, all
//! threads), so that neither the thread count nor other processes taking
//! the cores (which stretch wall time by their share) enter the figures;
//! wall time × threads per ray is kept beside them. (Processor time still
//! counts what contention does to the caches, and a pool thread's short
//! spin for work at the end of a batch.)

use crate::lab::figures::median;
use slimkd::build::{self, BuildConfig, BuildError};
use slimkd::format::{AlignedBytes, FormatError, KdFile};
use slimkd::geom::Ray;
use slimkd::pipeline::Pipeline;
use slimkd::render::{self, Camera, View};
use slimkd::scene::TriangleColumns;
use slimkd::trace::packet::PacketTracer;
use slimkd::trace::rays::{self, Query};
use slimkd::trace::{self as tr, ClosestHit, Hit, Scalar, TraceStats};

/// Why a scene could not be measured: one of its trees could not be
/// built or written as a `.kd` image.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// The build with `k_t` failed.
    #[error("{scene}: the build with K_T {k_t}: {source}")]
    Build {
        scene: String,
        k_t: f64,
        source: BuildError,
    },
    /// The tree of `k_t` could not be written or opened as a `.kd` image.
    #[error("{scene}: the tree of K_T {k_t} as a .kd file: {source}")]
    Format {
        scene: String,
        k_t: f64,
        source: FormatError,
    },
}

/// The `K_T` values trees are built with by default (with `K_I` 20: from
/// a third of today's ratio to four times it; the steps per ray vary by a
/// factor of about two over them).
pub const DEFAULT_KT_VALUES: [f64; 4] = [5.0, 15.0, 30.0, 60.0];

/// The traversal mode of a sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Mode {
    /// One ray at a time (the scalar traverser).
    Single,
    /// 16 consecutive rays at a time (the packet traverser).
    Packet,
}

impl Mode {
    pub const ALL: [Mode; 2] = [Mode::Packet, Mode::Single];

    pub fn name(self) -> &'static str {
        match self {
            Mode::Single => "single",
            Mode::Packet => "packet",
        }
    }
}

/// The ray set of a sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RaySet {
    /// Camera rays of the scene's views, closest hit.
    Primary,
    /// Ambient-occlusion rays from the primary hits, any hit.
    Ao,
}

impl RaySet {
    pub const ALL: [RaySet; 2] = [RaySet::Primary, RaySet::Ao];

    pub fn name(self) -> &'static str {
        match self {
            RaySet::Primary => "primary",
            RaySet::Ao => "ao",
        }
    }

    fn query(self) -> Query {
        match self {
            RaySet::Primary => Query::Closest,
            RaySet::Ao => Query::Occluded,
        }
    }
}

/// One tree, ray set and mode: its time and work per ray.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    pub k_t: f64,
    pub rays: RaySet,
    pub mode: Mode,
    pub n_rays: usize,
    /// Processor nanoseconds per ray (every thread's, the process's
    /// processor clock): the median over the repetitions.
    pub ns_per_ray: f64,
    /// Each repetition's figure.
    pub ns_per_ray_reps: Vec<f64>,
    /// Wall-clock nanoseconds × threads per ray: the median over the
    /// repetitions.
    pub wall_ns_per_ray: f64,
    /// Each repetition's figure.
    pub wall_ns_per_ray_reps: Vec<f64>,
    /// Traversal steps per ray (nodes visited, inner and leaf; a packet
    /// step counts once for the packet).
    pub steps_per_ray: f64,
    /// Ray–triangle tests per ray (leaf and hoisted triangles).
    pub tests_per_ray: f64,
    /// Leaves visited per ray.
    pub leaves_per_ray: f64,
}

/// One tree a scene was measured with.
#[derive(Clone, Debug, PartialEq)]
pub struct TreeFiguresOf {
    pub k_t: f64,
    pub nodes: u64,
    /// The `.kd` file's tree bytes (Morton-reordered).
    pub tree_bytes: u64,
}

/// Everything measured on one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneMeasurement {
    pub name: String,
    pub triangles: usize,
    /// The views the primary rays came from (`default`: the default
    /// camera, for a scene without views).
    pub views: Vec<String>,
    pub trees: Vec<TreeFiguresOf>,
    pub samples: Vec<Sample>,
}

/// What to measure.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrateOptions {
    /// `K_T` of the trees (at least two distinct values make the fit
    /// meaningful).
    pub kt_values: Vec<f64>,
    /// `K_I` of every tree (the build's; the implied `K_T` is scaled to it).
    pub k_i: f64,
    /// Primary rays per scene, split over its views; about as many
    /// ambient-occlusion rays go with them (4 per hit of a frame of a
    /// quarter of the pixels).
    pub rays_per_scene: usize,
    /// Timed repetitions after one warm-up; the median is taken.
    pub reps: usize,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            kt_values: DEFAULT_KT_VALUES.to_vec(),
            k_i: build::sah::SahParams::default().k_i,
            rays_per_scene: 1 << 16,
            reps: 7,
        }
    }
}

/// The shortest timed repetition of a sample: its ray set is traced as
/// often as it takes. A batch of a few thousand rays lasts about a
/// millisecond, where waking the pool's threads and the last chunk's
/// imbalance weigh as much as the rays (4,096 rays on dieselpower: 600 to
/// 2,000 ns per ray from one repetition to the next).
pub const MIN_SECONDS: f64 = 0.05;

/// The view ids whose cameras a scene's primary rays come from.
pub const VIEW_IDS: [&str; 3] = ["1", "2", "3"];

/// The primary rays of `cameras`, each frame in row-major order, one
/// frame after the other.
fn frames(cameras: &[Camera]) -> Vec<Ray> {
    cameras
        .iter()
        .flat_map(|c| (0..c.height).flat_map(move |y| (0..c.width).map(move |x| c.ray(x, y))))
        .collect()
}

/// The cameras of the scene's views ([`VIEW_IDS`]) at `side`×`side`, or the
/// default camera (named `default`) when it has none.
fn cameras(
    name: &str,
    scene: &TriangleColumns,
    views: &[View],
    side: u32,
) -> (Vec<String>, Vec<Camera>) {
    let found: Vec<&View> = VIEW_IDS
        .iter()
        .filter_map(|id| render::find_view_named(views, name, id))
        .collect();
    if found.is_empty() {
        return (
            vec!["default".to_string()],
            vec![Camera::default_for(&scene.bounds(), side, side)],
        );
    }
    (
        found.iter().map(|v| v.id.clone()).collect(),
        found
            .iter()
            .map(|v| Camera::from_view(v, side, side))
            .collect(),
    )
}

/// Builds, traces and counts one scene (see the module's documentation),
/// on the current rayon pool; `progress` gets a line per step.
///
/// # Errors
///
/// If a build fails ([`BuildError`]) or a tree cannot be written as a
/// `.kd` file; the message names the scene and `K_T`.
pub fn measure_scene(
    name: &str,
    scene: &TriangleColumns,
    views: &[View],
    options: &CalibrateOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<SceneMeasurement, CalibrateError> {
    let threads = rayon::current_num_threads();
    let mut files: Vec<KdFile<AlignedBytes>> = Vec::new();
    let mut trees = Vec::new();
    for &k_t in &options.kt_values {
        progress(&format!(
            "{name}: building with K_T {k_t}, K_I {}",
            options.k_i
        ));
        let mut config = BuildConfig::default();
        config.sah.k_t = k_t;
        config.sah.k_i = options.k_i;
        let pipeline = Pipeline::new(config);
        let (tree, _) = pipeline
            .build(scene, None)
            .map_err(|source| CalibrateError::Build {
                scene: name.to_string(),
                k_t,
                source,
            })?;
        let bytes =
            pipeline
                .write_image(&tree, scene)
                .map_err(|source| CalibrateError::Format {
                    scene: name.to_string(),
                    k_t,
                    source,
                })?;
        trees.push(TreeFiguresOf {
            k_t,
            nodes: bytes.figures().nodes(),
            tree_bytes: bytes.figures().tree_bytes(),
        });
        files.push(bytes);
    }
    let n_cams = {
        let (ids, _) = cameras(name, scene, views, 1);
        ids.len()
    };
    let side = ((options.rays_per_scene / n_cams) as f64).sqrt().max(4.0) as u32;
    let (view_ids, cams) = cameras(name, scene, views, side);
    let primary = frames(&cams);
    // The ambient-occlusion rays: 4 per hit of a frame of half the side,
    // so about as many as primary rays, in packets of 4 neighbouring
    // pixels' rays.
    let (_, half) = cameras(name, scene, views, (side / 2).max(2));
    let ao = match files.first() {
        Some(f) => rays::secondary_rays(scene, &Scalar::new(f), &frames(&half), 4).ao,
        None => Vec::new(),
    };
    let sets = [(RaySet::Primary, primary), (RaySet::Ao, ao)];
    let scalars: Vec<_> = files.iter().map(Scalar::new).collect();
    let packets: Vec<_> = files.iter().map(PacketTracer::new).collect();
    // The work per ray, counted once (it is deterministic).
    let mut samples = Vec::new();
    for (k, file) in files.iter().enumerate() {
        progress(&format!(
            "{name}: counting the work per ray, K_T {}",
            options.kt_values[k]
        ));
        for (set, rays) in &sets {
            for mode in Mode::ALL {
                let any = set.query() == Query::Occluded;
                let packet = &packets[k];
                let count =
                    |r: &[Ray],
                     out: &mut [Hit],
                     s: &mut TraceStats,
                     cache: &mut slimkd::trace::OccluderCache| match mode {
                        Mode::Packet => packet.trace_counted_cached(r, any, out, s, cache),
                        Mode::Single => {
                            for (ray, h) in r.iter().zip(out.iter_mut()) {
                                *h = tr::traverse_counted(file, ray, any, s);
                            }
                        }
                    };
                let (_, s) = rays::count_batch(
                    rays,
                    set.query(),
                    if mode == Mode::Packet {
                        rays::Pieces::Packets
                    } else {
                        rays::Pieces::Single
                    },
                    &count,
                );
                let per_ray = |v: u64| v as f64 / rays.len().max(1) as f64;
                samples.push(Sample {
                    k_t: options.kt_values[k],
                    rays: *set,
                    mode,
                    n_rays: rays.len(),
                    ns_per_ray: f64::NAN,
                    ns_per_ray_reps: Vec::new(),
                    wall_ns_per_ray: f64::NAN,
                    wall_ns_per_ray_reps: Vec::new(),
                    steps_per_ray: per_ray(s.nodes),
                    tests_per_ray: per_ray(s.tris + s.hoisted),
                    leaves_per_ray: per_ray(s.leaves),
                });
            }
        }
    }
    // The timing: one warm-up round, then `reps` rounds; each round starts
    // with the next tree, so that no tree always follows the same one.
    let per_tree = sets.len() * Mode::ALL.len();
    // How often each sample's set is traced per repetition, set by the
    // warm-up round so that a repetition lasts at least MIN_SECONDS.
    let mut passes = vec![1usize; samples.len()];
    for rep in 0..=options.reps {
        progress(&format!(
            "{name}: timing, repetition {rep} of {}{}",
            options.reps,
            if rep == 0 { " (warm-up)" } else { "" }
        ));
        for j in 0..files.len() {
            let k = (rep + j) % files.len();
            for (s, (set, rays)) in sets.iter().enumerate() {
                // No AO rays where no primary ray hits: nothing to time
                // (the warm-up would ask for tens of thousands of passes
                // over no rays to fill MIN_SECONDS).
                if rays.is_empty() {
                    continue;
                }
                for (m, mode) in Mode::ALL.into_iter().enumerate() {
                    let tracer: &dyn ClosestHit = match mode {
                        Mode::Packet => &packets[k],
                        Mode::Single => &scalars[k],
                    };
                    let i = k * per_tree + s * Mode::ALL.len() + m;
                    let mut seconds = 0.0;
                    let cpu_start = slimkd::sys::process_cpu_seconds();
                    for _ in 0..passes[i] {
                        seconds +=
                            rays::trace_batch(tracer, rays, set.query(), mode == Mode::Packet)
                                .seconds;
                    }
                    let cpu = cpu_start
                        .zip(slimkd::sys::process_cpu_seconds())
                        .map(|(a, b)| b - a);
                    if rep == 0 {
                        passes[i] = (MIN_SECONDS / seconds.max(1e-9)).ceil().max(1.0) as usize;
                    } else {
                        let traced = (passes[i] * rays.len()) as f64;
                        let wall_ns = seconds * 1e9 * threads as f64 / traced;
                        samples[i].wall_ns_per_ray_reps.push(wall_ns);
                        samples[i]
                            .ns_per_ray_reps
                            .push(cpu.map_or(wall_ns, |c| c * 1e9 / traced));
                    }
                }
            }
        }
    }
    for s in &mut samples {
        s.ns_per_ray = median(&s.ns_per_ray_reps);
        s.wall_ns_per_ray = median(&s.wall_ns_per_ray_reps);
    }
    Ok(SceneMeasurement {
        name: name.to_string(),
        triangles: scene.len(),
        views: view_ids,
        trees,
        samples,
    })
}

/// A least-squares fit of `ns = a·steps + b·tests + c_g` per ray with
/// `a, b ≥ 0` and one intercept `c_g` per group of observations.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    /// Nanoseconds per traversal step.
    pub a: f64,
    /// Nanoseconds per ray–triangle test.
    pub b: f64,
    /// Nanoseconds per ray besides, per group (setup, clipping to the
    /// scene's box, and what a group's rays cost more per step and test
    /// than another's: ambient-occlusion rays miss the caches that
    /// coherent primary rays share). Not constrained in sign.
    pub c: Vec<f64>,
    /// `1 − SSR/SST` with SST about each group's mean: the share of the
    /// variation within the groups (from tree to tree) that steps and
    /// tests explain; 1 when there is none and the fit is exact.
    pub r2: f64,
    /// The root mean square of the residuals, ns.
    pub rms_residual: f64,
    /// Measured minus fitted, ns, per observation in the order given.
    pub residuals: Vec<f64>,
}

impl Fit {
    /// The `K_T` that goes with `k_i` in the traverser's ratio, `k_i·a/b`
    /// (infinite when `b` is 0, NaN when both are).
    pub fn implied_k_t(&self, k_i: f64) -> f64 {
        k_i * self.a / self.b
    }
}

/// One observation of the fit: work per ray and time per ray, and its
/// group (which intercept it takes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    pub steps: f64,
    pub tests: f64,
    pub ns: f64,
    pub group: usize,
}

/// The fit of `ns = a·steps + b·tests + c_g` with `a, b ≥ 0`, by least
/// squares.
///
/// The intercepts go first (Frisch–Waugh): within each group, steps, tests
/// and times are taken about the group's means, which leaves `a` and `b`
/// to fit without intercept. With two unknowns the non-negative solution
/// is the best of the unconstrained solutions over `{a, b}`, `{a}`, `{b}`
/// and none whose coefficients are all non-negative (the optimum of a
/// convex problem is its face's unconstrained optimum); each is solved by
/// its normal equations. Then `c_g` is the group's mean time less
/// `a·steps + b·tests` at its means. `None` for no observations.
pub fn fit(obs: &[Observation]) -> Option<Fit> {
    if obs.is_empty() {
        return None;
    }
    let groups = obs.iter().map(|o| o.group).max().unwrap_or(0) + 1;
    let mut sums = vec![[0.0f64; 4]; groups];
    for o in obs {
        let g = &mut sums[o.group];
        g[0] += o.steps;
        g[1] += o.tests;
        g[2] += o.ns;
        g[3] += 1.0;
    }
    let means: Vec<[f64; 3]> = sums
        .iter()
        .map(|g| {
            let n = g[3].max(1.0);
            [g[0] / n, g[1] / n, g[2] / n]
        })
        .collect();
    // Centred columns: x = (steps, tests), y = ns.
    let centred: Vec<([f64; 2], f64)> = obs
        .iter()
        .map(|o| {
            let m = means[o.group];
            ([o.steps - m[0], o.tests - m[1]], o.ns - m[2])
        })
        .collect();
    let (mut sxx, mut sxy, mut syy) = ([[0.0f64; 2]; 2], [0.0f64; 2], 0.0f64);
    for (x, y) in &centred {
        for i in 0..2 {
            for j in 0..2 {
                sxx[i][j] += x[i] * x[j];
            }
            sxy[i] += x[i] * y;
        }
        syy += y * y;
    }
    // SSR of (a, b) from the sums: Σ(y − a·x0 − b·x1)².
    let ssr_of = |a: f64, b: f64| {
        (syy - 2.0 * (a * sxy[0] + b * sxy[1])
            + a * a * sxx[0][0]
            + 2.0 * a * b * sxx[0][1]
            + b * b * sxx[1][1])
            .max(0.0)
    };
    let scale = sxx[0][0].max(sxx[1][1]);
    let mut candidates = vec![(0.0, 0.0)];
    for i in 0..2 {
        if sxx[i][i] > 1e-12 * scale {
            let v = sxy[i] / sxx[i][i];
            candidates.push(if i == 0 { (v, 0.0) } else { (0.0, v) });
        }
    }
    let det = sxx[0][0] * sxx[1][1] - sxx[0][1] * sxx[0][1];
    if det > 1e-12 * scale * scale {
        candidates.push((
            (sxy[0] * sxx[1][1] - sxy[1] * sxx[0][1]) / det,
            (sxy[1] * sxx[0][0] - sxy[0] * sxx[0][1]) / det,
        ));
    }
    let (a, b) = candidates
        .into_iter()
        .filter(|&(a, b)| a >= 0.0 && b >= 0.0 && a.is_finite() && b.is_finite())
        .min_by(|x, y| ssr_of(x.0, x.1).total_cmp(&ssr_of(y.0, y.1)))
        .unwrap_or((0.0, 0.0));
    let c: Vec<f64> = means.iter().map(|m| m[2] - a * m[0] - b * m[1]).collect();
    let residuals: Vec<f64> = obs
        .iter()
        .map(|o| o.ns - (a * o.steps + b * o.tests + c[o.group]))
        .collect();
    let ssr: f64 = residuals.iter().map(|r| r * r).sum();
    let r2 = if syy > 0.0 {
        1.0 - ssr / syy
    } else if ssr <= 1e-18 {
        1.0
    } else {
        f64::NAN
    };
    Some(Fit {
        a,
        b,
        c,
        r2,
        rms_residual: (ssr / obs.len() as f64).sqrt(),
        residuals,
    })
}

/// Per tree and ray set of `samples` (of the ray set `only`, or all): the
/// packets' steps per ray over single rays' steps per ray on the same
/// tree and rays, that is packet node steps per node visit of a ray. The
/// SAH prices a node visit of one ray, so a packet step's cost `a` is
/// `a·ratio` per visit.
pub fn packet_steps_per_visit(samples: &[Sample], only: Option<RaySet>) -> Vec<f64> {
    samples
        .iter()
        .filter(|p| p.mode == Mode::Packet && only.is_none_or(|r| p.rays == r))
        .filter_map(|p| {
            samples
                .iter()
                .find(|s| s.mode == Mode::Single && s.rays == p.rays && s.k_t == p.k_t)
                .filter(|s| s.steps_per_ray > 0.0)
                .map(|s| p.steps_per_ray / s.steps_per_ray)
        })
        .collect()
}

/// The observations of the samples of `mode` with a finite time, grouped
/// by `group` (e.g. the ray set, or the scene and the ray set).
pub fn observations<'a>(
    samples: impl IntoIterator<Item = &'a Sample>,
    mode: Mode,
    group: impl Fn(&Sample) -> usize,
) -> Vec<Observation> {
    samples
        .into_iter()
        .filter(|s| s.mode == mode && s.ns_per_ray.is_finite())
        .map(|s| Observation {
            steps: s.steps_per_ray,
            tests: s.tests_per_ray,
            ns: s.ns_per_ray,
            group: group(s),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Steps and tests that vary independently, as trees of different K_T
    /// and ray sets make them, in `groups` groups with intercepts `c`.
    fn synthetic(a: f64, b: f64, c: &[f64]) -> Vec<Observation> {
        (0..12)
            .map(|i| {
                let steps = 20.0 + 7.0 * i as f64;
                let tests = 5.0 + 3.0 * ((i * 5) % 7) as f64;
                let group = i % c.len();
                Observation {
                    steps,
                    tests,
                    ns: a * steps + b * tests + c[group],
                    group,
                }
            })
            .collect()
    }

    #[test]
    fn fit_recovers_known_coefficients() {
        for (a, b, c) in [
            (2.5, 9.0, vec![30.0]),
            (1.0, 0.25, vec![0.0]),
            (0.0, 4.0, vec![12.0]),
            (3.0, 11.0, vec![40.0, -15.0, 100.0]),
        ] {
            let f = fit(&synthetic(a, b, &c)).unwrap();
            assert!((f.a - a).abs() < 1e-9, "{f:?}");
            assert!((f.b - b).abs() < 1e-9, "{f:?}");
            for (got, want) in f.c.iter().zip(&c) {
                assert!((got - want).abs() < 1e-7, "{f:?}");
            }
            assert_eq!(f.c.len(), c.len());
            assert!((f.r2 - 1.0).abs() < 1e-12, "{f:?}");
            assert!(f.rms_residual < 1e-7, "{f:?}");
            assert!((f.implied_k_t(20.0) - 20.0 * a / b).abs() < 1e-9);
        }
    }

    #[test]
    fn fit_with_noise_is_close_and_reports_it() {
        let mut obs = synthetic(3.0, 10.0, &[20.0]);
        for (i, o) in obs.iter_mut().enumerate() {
            o.ns += if i % 2 == 0 { 1.0 } else { -1.0 };
        }
        let f = fit(&obs).unwrap();
        assert!((f.a - 3.0).abs() < 0.1 && (f.b - 10.0).abs() < 0.3, "{f:?}");
        assert!(f.r2 < 1.0 && f.r2 > 0.99, "{f:?}");
        assert!(f.rms_residual > 0.5 && f.rms_residual < 1.0, "{f:?}");
        let sum: f64 = f.residuals.iter().sum();
        assert!(sum.abs() < 1e-6, "residuals sum to zero with an intercept");
    }

    #[test]
    fn fit_keeps_coefficients_non_negative() {
        // Time falls with the tests: unconstrained, b would be negative.
        let obs = synthetic(2.0, -1.5, &[40.0]);
        let f = fit(&obs).unwrap();
        assert_eq!(f.b, 0.0, "{f:?}");
        assert!(f.a > 0.0);
        // The best fit with b = 0 is the unconstrained fit in steps alone.
        let g = fit(&obs
            .iter()
            .map(|o| Observation { tests: 0.0, ..*o })
            .collect::<Vec<_>>())
        .unwrap();
        assert!((f.a - g.a).abs() < 1e-9 && (f.c[0] - g.c[0]).abs() < 1e-7);
        assert!(fit(&[]).is_none());
    }
}
