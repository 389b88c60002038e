//! The cost of a traversal step and of a ray–triangle test, measured on
//! the traverser as it is (`slimkd calibrate`): the figures the SAH's
//! `K_T` and `K_I` stand for.
//!
//! [`measure_scene`] builds a scene's tree at several `K_T` values (with
//! one `K_I`), so that the ratio of steps to tests per ray varies, writes
//! each as `.kd` bytes (Morton-reordered, as `build --reorder` does) and
//! traces primary rays from the scene's views and ambient-occlusion rays
//! from their hits ([`crate::trace::rays::secondary_rays`]) through each,
//! as single rays and as 16-ray packets. Each combination is a
//! [`Sample`]: its time per ray (the median over the repetitions, the
//! trees interleaved within each repetition so that drift in the machine's
//! speed touches all alike) and its work per ray, counted by the counting
//! traversal in an untimed pass (deterministic). [`fit`] then finds
//! non-negative `a`, `b`, `c` of `time = a·steps + b·tests + c` per ray by
//! least squares. A step is a node visited, inner or leaf; for packets it
//! is one node step of the packet (shared by its active lanes) or of a ray
//! of an octant traced ray by ray, and a test is one lane's test. So `a/b`
//! is the ratio `K_T/K_I` of the traverser.
//!
//! Times are processor time per ray (the process's processor clock, all
//! threads), so that neither the thread count nor other processes taking
//! the cores (which stretch wall time by their share) enter the figures;
//! wall time × threads per ray is kept beside them. (Processor time still
//! counts what contention does to the caches, and a pool thread's short
//! spin for work at the end of a batch.)

use crate::build::{self, BuildConfig, BuildError};
use crate::format::{self, AlignedBytes, KdFile, WriteOptions};
use crate::geom::Ray;
use crate::pipeline::median;
use crate::render::{self, Camera, View};
use crate::scene::TriangleColumns;
use crate::trace::packet::PacketTracer;
use crate::trace::rays::{self, Query};
use crate::trace::{self as tr, ClosestHit, Hit, Scalar, TraceStats};

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
) -> Result<SceneMeasurement, String> {
    let threads = rayon::current_num_threads();
    let mut files: Vec<KdFile<AlignedBytes>> = Vec::new();
    let mut trees = Vec::new();
    for &k_t in &options.kt_values {
        progress(&format!("{name}: building with K_T {k_t}, K_I {}", options.k_i));
        let mut config = BuildConfig::default();
        config.sah.k_t = k_t;
        config.sah.k_i = options.k_i;
        let tree = build::build(scene, &config, build::Builder::Level, None)
            .map_err(|e: BuildError| format!("{name}: the build with K_T {k_t}: {e}"))?;
        let bytes = format::write_to_vec(
            &tree,
            scene,
            &WriteOptions {
                reorder: true,
                ..Default::default()
            },
        )
        .and_then(|b| KdFile::from_bytes(format::aligned_copy(&b)))
        .map_err(|e| format!("{name}: the tree of K_T {k_t} as a .kd file: {e}"))?;
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
                let count = |r: &[Ray], out: &mut [Hit], s: &mut TraceStats| match mode {
                    Mode::Packet => packet.trace_counted(r, any, out, s),
                    Mode::Single => {
                        for (ray, h) in r.iter().zip(out.iter_mut()) {
                            *h = tr::traverse_counted(file, ray, any, s);
                        }
                    }
                };
                let (_, s) = rays::count_batch(rays, set.query(), mode == Mode::Packet, &count);
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
                for (m, mode) in Mode::ALL.into_iter().enumerate() {
                    let tracer: &dyn ClosestHit = match mode {
                        Mode::Packet => &packets[k],
                        Mode::Single => &scalars[k],
                    };
                    let i = k * per_tree + s * Mode::ALL.len() + m;
                    let mut seconds = 0.0;
                    let cpu_start = crate::sys::process_cpu_seconds();
                    for _ in 0..passes[i] {
                        seconds +=
                            rays::trace_batch(tracer, rays, set.query(), mode == Mode::Packet)
                                .seconds;
                    }
                    let cpu = cpu_start
                        .zip(crate::sys::process_cpu_seconds())
                        .map(|(a, b)| b - a);
                    if rep == 0 {
                        passes[i] = (MIN_SECONDS / seconds.max(1e-9)).ceil().max(1.0) as usize;
                    } else if !rays.is_empty() {
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

/// A least-squares fit of `ns = a·steps + b·tests + c` per ray with
/// `a, b, c ≥ 0`.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    /// Nanoseconds per traversal step.
    pub a: f64,
    /// Nanoseconds per ray–triangle test.
    pub b: f64,
    /// Nanoseconds per ray besides (setup, clipping to the scene's box).
    pub c: f64,
    /// `1 − SSR/SST` (SST about the mean; 1 when the times are all equal
    /// and fitted exactly).
    pub r2: f64,
    /// The root mean square of the residuals, ns.
    pub rms_residual: f64,
    /// Measured minus fitted, ns, per sample in the order given.
    pub residuals: Vec<f64>,
}

impl Fit {
    /// The `K_T` that goes with `k_i` in the traverser's ratio, `k_i·a/b`
    /// (infinite when `b` is 0, NaN when both are).
    pub fn implied_k_t(&self, k_i: f64) -> f64 {
        k_i * self.a / self.b
    }
}

/// One observation of the fit: work per ray and time per ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    pub steps: f64,
    pub tests: f64,
    pub ns: f64,
}

/// Solves the `n`×`n` system `m·x = v` by Gaussian elimination with partial
/// pivoting; `None` if it is singular (a pivot below 10⁻¹² of the largest
/// entry).
fn solve(mut m: [[f64; 3]; 3], mut v: [f64; 3], n: usize) -> Option<[f64; 3]> {
    let scale = m
        .iter()
        .take(n)
        .flat_map(|r| r.iter().take(n))
        .fold(0.0f64, |s, x| s.max(x.abs()));
    if scale == 0.0 {
        return None;
    }
    for col in 0..n {
        let pivot = (col..n).max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))?;
        if m[pivot][col].abs() <= 1e-12 * scale {
            return None;
        }
        m.swap(col, pivot);
        v.swap(col, pivot);
        for row in col + 1..n {
            let f = m[row][col] / m[col][col];
            for k in col..n {
                m[row][k] -= f * m[col][k];
            }
            v[row] -= f * v[col];
        }
    }
    let mut x = [0.0; 3];
    for row in (0..n).rev() {
        let mut s = v[row];
        for k in row + 1..n {
            s -= m[row][k] * x[k];
        }
        x[row] = s / m[row][row];
    }
    Some(x)
}

/// The non-negative least-squares fit of `ns = a·steps + b·tests + c`.
///
/// With three unknowns the exact non-negative solution is the best of the
/// unconstrained least-squares solutions over every subset of them (the
/// others held at 0) whose coefficients are all non-negative: the optimum
/// of a convex problem lies on the face of the orthant spanned by its
/// positive coefficients, where it is that face's unconstrained optimum.
/// Each subset is solved by its normal equations. `None` for no
/// observations.
pub fn fit(obs: &[Observation]) -> Option<Fit> {
    if obs.is_empty() {
        return None;
    }
    let features = |o: &Observation| [o.steps, o.tests, 1.0];
    let ssr_of = |x: &[f64; 3]| {
        obs.iter()
            .map(|o| {
                let f = features(o);
                let r = o.ns - (x[0] * f[0] + x[1] * f[1] + x[2] * f[2]);
                r * r
            })
            .sum::<f64>()
    };
    let mut best = ([0.0; 3], ssr_of(&[0.0; 3]));
    for subset in 1u32..8 {
        let vars: Vec<usize> = (0..3).filter(|i| subset & (1 << i) != 0).collect();
        let n = vars.len();
        let mut m = [[0.0; 3]; 3];
        let mut v = [0.0; 3];
        for o in obs {
            let f = features(o);
            for (i, &p) in vars.iter().enumerate() {
                for (j, &q) in vars.iter().enumerate() {
                    m[i][j] += f[p] * f[q];
                }
                v[i] += f[p] * o.ns;
            }
        }
        let Some(sol) = solve(m, v, n) else { continue };
        if sol.iter().take(n).any(|&c| c < 0.0 || !c.is_finite()) {
            continue;
        }
        let mut x = [0.0; 3];
        for (i, &p) in vars.iter().enumerate() {
            x[p] = sol[i];
        }
        let ssr = ssr_of(&x);
        if ssr < best.1 {
            best = (x, ssr);
        }
    }
    let (x, ssr) = best;
    let mean = obs.iter().map(|o| o.ns).sum::<f64>() / obs.len() as f64;
    let sst: f64 = obs.iter().map(|o| (o.ns - mean) * (o.ns - mean)).sum();
    let r2 = if sst > 0.0 {
        1.0 - ssr / sst
    } else if ssr == 0.0 {
        1.0
    } else {
        f64::NAN
    };
    let residuals = obs
        .iter()
        .map(|o| {
            let f = features(o);
            o.ns - (x[0] * f[0] + x[1] * f[1] + x[2] * f[2])
        })
        .collect();
    Some(Fit {
        a: x[0],
        b: x[1],
        c: x[2],
        r2,
        rms_residual: (ssr / obs.len() as f64).sqrt(),
        residuals,
    })
}

/// The observations of the samples of `mode` (those with a finite time).
pub fn observations<'a>(
    samples: impl IntoIterator<Item = &'a Sample>,
    mode: Mode,
) -> Vec<Observation> {
    samples
        .into_iter()
        .filter(|s| s.mode == mode && s.ns_per_ray.is_finite())
        .map(|s| Observation {
            steps: s.steps_per_ray,
            tests: s.tests_per_ray,
            ns: s.ns_per_ray,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn synthetic(a: f64, b: f64, c: f64) -> Vec<Observation> {
        // Steps and tests that vary independently, as trees of different
        // K_T and ray sets make them.
        (0..12)
            .map(|i| {
                let steps = 20.0 + 7.0 * i as f64;
                let tests = 5.0 + 3.0 * ((i * 5) % 7) as f64;
                Observation {
                    steps,
                    tests,
                    ns: a * steps + b * tests + c,
                }
            })
            .collect()
    }

    #[test]
    fn fit_recovers_known_coefficients() {
        for (a, b, c) in [(2.5, 9.0, 30.0), (1.0, 0.25, 0.0), (0.0, 4.0, 12.0)] {
            let f = fit(&synthetic(a, b, c)).unwrap();
            assert!((f.a - a).abs() < 1e-9, "{f:?}");
            assert!((f.b - b).abs() < 1e-9, "{f:?}");
            assert!((f.c - c).abs() < 1e-7, "{f:?}");
            assert!((f.r2 - 1.0).abs() < 1e-12, "{f:?}");
            assert!(f.rms_residual < 1e-7, "{f:?}");
            assert!((f.implied_k_t(20.0) - 20.0 * a / b).abs() < 1e-9);
        }
    }

    #[test]
    fn fit_with_noise_is_close_and_reports_it() {
        let mut obs = synthetic(3.0, 10.0, 20.0);
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
        let obs = synthetic(2.0, -1.5, 40.0);
        let f = fit(&obs).unwrap();
        assert_eq!(f.b, 0.0, "{f:?}");
        assert!(f.a >= 0.0 && f.c >= 0.0);
        // The best fit with b = 0 is the unconstrained fit in steps alone.
        let g = fit(
            &obs.iter()
                .map(|o| Observation { tests: 0.0, ..*o })
                .collect::<Vec<_>>(),
        )
        .unwrap();
        assert!((f.a - g.a).abs() < 1e-9 && (f.c - g.c).abs() < 1e-7);
        assert!(fit(&[]).is_none());
    }
}
