//! `slimkd calibrate`: the cost of a traversal step and of a ray–triangle
//! test on this machine's traverser, fitted per scene and pooled
//! ([`crate::lab::calibrate`]).

use crate::args::{CalibrateArgs, OutputFlags, Usage};
use crate::build::load;
use crate::json::print_json;
use crate::lab::calibrate::{self as cal, Fit, Mode, SceneMeasurement};
use crate::{CmdResult, DEFAULT_ARG, pool};
use serde::Serialize;
use std::path::PathBuf;

/// `slimkd calibrate --json`.
#[derive(Serialize)]
struct CalibrateJson {
    threads: usize,
    simd: &'static str,
    reps: usize,
    rays_per_scene: usize,
    k_i: f64,
    kt_values: Vec<f64>,
    scenes: Vec<SceneCalJson>,
    /// Every scene's samples, per mode.
    pooled: FitsJson,
    /// Every scene's samples of one ray set, per mode.
    pooled_primary: FitsJson,
    pooled_ao: FitsJson,
}

#[derive(Serialize)]
struct SceneCalJson {
    name: String,
    triangles: usize,
    views: Vec<String>,
    trees: Vec<TreeCalJson>,
    samples: Vec<SampleJson>,
    fits: FitsJson,
}

#[derive(Serialize)]
struct TreeCalJson {
    k_t: f64,
    nodes_total: u64,
    tree_bytes: u64,
}

#[derive(Serialize)]
struct SampleJson {
    k_t: f64,
    rays: &'static str,
    mode: &'static str,
    n_rays: usize,
    ns_per_ray: f64,
    ns_per_ray_reps: Vec<f64>,
    wall_ns_per_ray: f64,
    steps_per_ray: f64,
    tests_per_ray: f64,
    leaves_per_ray: f64,
}

#[derive(Serialize)]
struct FitsJson {
    packet: Option<FitJson>,
    single: Option<FitJson>,
}

#[derive(Serialize)]
struct FitJson {
    samples: usize,
    a_ns_per_step: f64,
    b_ns_per_test: f64,
    /// Per ray set (`primary`, `ao`; pooled: per scene and ray set).
    c_ns_per_ray: Vec<f64>,
    k_t_over_k_i: f64,
    implied_k_t: f64,
    steps_per_visit: f64,
    implied_k_t_per_visit: f64,
    r2: f64,
    rms_residual_ns: f64,
    residuals_ns: Vec<f64>,
}

impl FitJson {
    fn of(f: &Fit, samples: usize, k_i: f64, steps_per_visit: f64) -> FitJson {
        FitJson {
            samples,
            a_ns_per_step: f.a,
            b_ns_per_test: f.b,
            c_ns_per_ray: f.c.clone(),
            k_t_over_k_i: f.implied_k_t(1.0),
            implied_k_t: f.implied_k_t(k_i),
            steps_per_visit,
            implied_k_t_per_visit: f.implied_k_t(k_i) * steps_per_visit,
            r2: f.r2,
            rms_residual_ns: f.rms_residual,
            residuals_ns: f.residuals.clone(),
        }
    }
}

/// The fits of one set of samples, per mode, and the packets' mean node
/// steps per ray visit over those samples (1 for single rays).
struct Fits {
    fits: [(Mode, Option<Fit>, usize); 2],
    packet_steps_per_visit: f64,
}

impl Fits {
    /// The fits of `obs(mode)`, the observations of each mode.
    fn of(obs: impl Fn(Mode) -> Vec<cal::Observation>, ratios: &[f64]) -> Fits {
        Fits {
            fits: Mode::ALL.map(|m| {
                let o = obs(m);
                (m, cal::fit(&o), o.len())
            }),
            packet_steps_per_visit: ratios.iter().sum::<f64>() / ratios.len().max(1) as f64,
        }
    }

    /// One scene's fits: an intercept per ray set.
    fn scene(m: &SceneMeasurement) -> Fits {
        Fits::of(
            |mode| cal::observations(&m.samples, mode, |s| s.rays as usize),
            &cal::packet_steps_per_visit(&m.samples, None),
        )
    }

    /// The fits of every scene's samples (of the ray set `only`, or of
    /// all): an intercept per scene and ray set, so that `a` and `b` come
    /// from how time changes with the tree.
    fn pooled(all: &[SceneMeasurement], only: Option<cal::RaySet>) -> Fits {
        let ratios: Vec<f64> = all
            .iter()
            .flat_map(|m| cal::packet_steps_per_visit(&m.samples, only))
            .collect();
        Fits::of(
            |mode| {
                all.iter()
                    .enumerate()
                    .flat_map(|(i, m)| {
                        let samples = m
                            .samples
                            .iter()
                            .filter(|s| only.is_none_or(|r| s.rays == r));
                        let sets = if only.is_some() {
                            1
                        } else {
                            cal::RaySet::ALL.len()
                        };
                        cal::observations(samples, mode, move |s| {
                            i * sets + if only.is_some() { 0 } else { s.rays as usize }
                        })
                    })
                    .collect()
            },
            &ratios,
        )
    }

    /// Node steps per ray visit in `mode`.
    fn steps_per_visit(&self, mode: Mode) -> f64 {
        match mode {
            Mode::Packet => self.packet_steps_per_visit,
            Mode::Single => 1.0,
        }
    }

    fn json(&self, k_i: f64) -> FitsJson {
        let get = |mode: Mode| {
            self.fits
                .iter()
                .find(|(m, _, _)| *m == mode)
                .and_then(|(_, f, n)| {
                    f.as_ref()
                        .map(|f| FitJson::of(f, *n, k_i, self.steps_per_visit(mode)))
                })
        };
        FitsJson {
            packet: get(Mode::Packet),
            single: get(Mode::Single),
        }
    }
}

pub(crate) fn cmd_calibrate(args: &CalibrateArgs, ui: OutputFlags) -> CmdResult<()> {
    let mut distinct = args.kt.clone();
    distinct.sort_by(f64::total_cmp);
    distinct.dedup();
    if distinct.len() < 2 {
        return Err(Usage(
            "--kt needs at least two distinct values (the fit needs trees whose ratio of \
             steps to tests differs)"
                .into(),
        )
        .into());
    }
    let views = crate::read_views(args.views.as_deref())?;
    let scenes = if args.scenes.is_empty() {
        vec![PathBuf::from(DEFAULT_ARG)]
    } else {
        args.scenes.clone()
    };
    let pool = pool(args.threads)?;
    let threads = pool.current_num_threads();
    let options = cal::CalibrateOptions {
        kt_values: args.kt.clone(),
        k_i: args.ki,
        rays_per_scene: args.rays_per_scene,
        reps: args.reps,
    };
    let mut measured: Vec<SceneMeasurement> = Vec::new();
    for path in &scenes {
        let loaded = load(path, ui.bars_off())?;
        let name = loaded.name();
        let m = pool.install(|| {
            cal::measure_scene(&name, &loaded.scene, &views, &options, &mut |line| {
                if !ui.quiet && !ui.json {
                    eprintln!("{line}");
                }
            })
        })?;
        measured.push(m);
    }
    let simd = slimkd::trace::packet::SimdLevel::detect().name();
    let pooled = Fits::pooled(&measured, None);
    let pooled_primary = Fits::pooled(&measured, Some(cal::RaySet::Primary));
    let pooled_ao = Fits::pooled(&measured, Some(cal::RaySet::Ao));
    if ui.json {
        return print_json(
            "calibrate",
            CalibrateJson {
                threads,
                simd,
                reps: args.reps,
                rays_per_scene: args.rays_per_scene,
                k_i: args.ki,
                kt_values: args.kt.clone(),
                scenes: measured
                    .iter()
                    .map(|m| SceneCalJson {
                        name: m.name.clone(),
                        triangles: m.triangles,
                        views: m.views.clone(),
                        trees: m
                            .trees
                            .iter()
                            .map(|t| TreeCalJson {
                                k_t: t.k_t,
                                nodes_total: t.nodes,
                                tree_bytes: t.tree_bytes,
                            })
                            .collect(),
                        samples: m
                            .samples
                            .iter()
                            .map(|s| SampleJson {
                                k_t: s.k_t,
                                rays: s.rays.name(),
                                mode: s.mode.name(),
                                n_rays: s.n_rays,
                                ns_per_ray: s.ns_per_ray,
                                ns_per_ray_reps: s.ns_per_ray_reps.clone(),
                                wall_ns_per_ray: s.wall_ns_per_ray,
                                steps_per_ray: s.steps_per_ray,
                                tests_per_ray: s.tests_per_ray,
                                leaves_per_ray: s.leaves_per_ray,
                            })
                            .collect(),
                        fits: Fits::scene(m).json(args.ki),
                    })
                    .collect(),
                pooled: pooled.json(args.ki),
                pooled_primary: pooled_primary.json(args.ki),
                pooled_ao: pooled_ao.json(args.ki),
            },
        );
    }
    if ui.quiet {
        return Ok(());
    }
    println!(
        "calibrate: {threads} threads ({simd} packets), trees with K_T {} and K_I {}, {} primary rays \
         per scene and about as many AO rays, median of {} repetitions; processor ns per ray",
        args.kt
            .iter()
            .map(|k| k.to_string())
            .collect::<Vec<_>>()
            .join(", "),
        args.ki,
        args.rays_per_scene,
        args.reps
    );
    if ui.verbose {
        println!(
            "{:<24} {:>6} {:<8} {:<7} {:>8} {:>10} {:>10} {:>10} {:>10}",
            "scene", "K_T", "rays", "mode", "n", "ns/ray", "steps/ray", "tests/ray", "tree bytes"
        );
        for m in &measured {
            for s in &m.samples {
                let bytes = m
                    .trees
                    .iter()
                    .find(|t| t.k_t == s.k_t)
                    .map_or(0, |t| t.tree_bytes);
                println!(
                    "{:<24} {:>6} {:<8} {:<7} {:>8} {:>10.1} {:>10.2} {:>10.2} {:>10}",
                    m.name,
                    s.k_t,
                    s.rays.name(),
                    s.mode.name(),
                    s.n_rays,
                    s.ns_per_ray,
                    s.steps_per_ray,
                    s.tests_per_ray,
                    bytes
                );
            }
        }
        println!();
    }
    println!(
        "{:<24} {:<7} {:>7} {:>12} {:>12} {:>15} {:>9} {:>14} {:>10} {:>7} {:>13}",
        "scene",
        "mode",
        "samples",
        "a (ns/step)",
        "b (ns/test)",
        "c pri/ao (ns)",
        "a/b",
        format!("K_T at K_I {}", args.ki),
        "per visit",
        "R²",
        "rms resid (ns)"
    );
    let rows = measured
        .iter()
        .map(|m| (m.name.clone(), Fits::scene(m)))
        .chain([
            ("pooled".to_string(), pooled),
            ("pooled, primary rays".to_string(), pooled_primary),
            ("pooled, AO rays".to_string(), pooled_ao),
        ]);
    for (name, fits) in rows {
        for (mode, fit, n) in &fits.fits {
            match fit {
                Some(f) => println!(
                    "{:<24} {:<7} {:>7} {:>12.3} {:>12.3} {:>15} {:>9.3} {:>14.1} {:>10.1} {:>7.3} {:>13.2}",
                    name,
                    mode.name(),
                    n,
                    f.a,
                    f.b,
                    if f.c.len() == cal::RaySet::ALL.len() {
                        format!("{:.1}/{:.1}", f.c[0], f.c[1])
                    } else {
                        "per scene".to_string()
                    },
                    f.implied_k_t(1.0),
                    f.implied_k_t(args.ki),
                    f.implied_k_t(args.ki) * fits.steps_per_visit(*mode),
                    f.r2,
                    f.rms_residual
                ),
                None => println!("{name:<24} {:<7} {n:>7} (no samples)", mode.name()),
            }
        }
    }
    println!(
        "c: per ray set (primary/ao), per scene and ray set when pooled; per visit: the K_T per \
         node visit of one ray, what the SAH prices (a packet step is shared by its lanes: \
         K_T × packet steps per visit)"
    );
    Ok(())
}
