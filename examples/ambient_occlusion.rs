//! A small renderer on the `Accel` facade: primary rays from view 1 of the
//! embedded scene, 8 cosine-distributed ambient-occlusion rays per hit
//! pixel traced a row at a time with `occluded_batch` through one
//! `AccelTracer` (`Accel::tracer`, the file view taken once) over the
//! wide boxes (`Accel::prepare_secondary`), rows in parallel with rayon;
//! writes a
//! grey `ao.png` to the current directory.
//!
//! ```sh
//! cargo run --release --example ambient_occlusion
//! ```

use glam::Vec3;
use rayon::prelude::*;
use slimkd::accel::{Accel, BuildOptions};
use slimkd::geom::Ray;
use slimkd::render::{self, Camera, Frame};
use std::path::Path;
use std::time::Instant;

const SIZE: u32 = 256;
const AO_RAYS: u32 = 8;

/// A hash of the pixel and sample number to `[0, 1)` (deterministic images).
fn random(x: u32, y: u32, i: u32) -> f32 {
    let mut h = (u64::from(x) << 40) ^ (u64::from(y) << 20) ^ u64::from(i);
    h = h.wrapping_add(0x9E37_79B9_7F4A_7C15);
    h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((h ^ (h >> 31)) >> 40) as f32 / (1u64 << 24) as f32
}

/// A direction about `n` (unit) with density proportional to the cosine.
fn cosine_sample(n: Vec3, r1: f32, r2: f32) -> Vec3 {
    let (t, b) = n.any_orthonormal_pair();
    let phi = 2.0 * std::f32::consts::PI * r1;
    let r = r2.sqrt();
    t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - r2).max(0.0).sqrt()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let obj = root.join("scenes/nexuiz_dieselpower.obj");
    let (scene, _) = slimkd::scene::load(&obj)?;
    let accel = Accel::build(&scene, &BuildOptions::default())?;
    let views = render::parse_views(&std::fs::read_to_string(root.join("scenes/views.txt"))?)?;
    let view = render::find_view(&views, &obj, "1").ok_or("no view 1 for the scene")?;
    let camera = Camera::from_view(view, SIZE, SIZE);
    camera.check()?;
    let bounds = accel.bounds();
    let diagonal = (bounds.max - bounds.min).length();
    let radius = 0.05 * diagonal;
    let eps = 1e-5 * diagonal;

    // The wide boxes for secondary rays (memory beside the tree): single
    // rays and any-hit batches go over them from here on.
    accel.prepare_secondary()?;
    // One tracer for the frame: the file view is taken once, not per ray.
    // A row's AO rays go to the tracer as one batch, which traces them in
    // packets of one octant; each worker keeps one occluder cache.
    let tracer = accel.tracer();
    let start = Instant::now();
    let rows: Vec<Vec<(f32, f32)>> = (0..SIZE)
        .into_par_iter()
        .map_init(slimkd::OccluderCache::new, |cache, y| {
            let mut pixels = Vec::with_capacity(SIZE as usize);
            let mut ao_rays = Vec::new();
            for x in 0..SIZE {
                let ray = camera.ray(x, y);
                let Some(hit) = tracer.intersect(&ray) else {
                    pixels.push((0.0, f32::INFINITY));
                    continue;
                };
                let p = ray.origin + ray.dir * hit.t;
                let mut n = hit.ng.normalize();
                if n.dot(ray.dir) > 0.0 {
                    n = -n;
                }
                for i in 0..AO_RAYS {
                    let d = cosine_sample(n, random(x, y, 2 * i), random(x, y, 2 * i + 1));
                    ao_rays.push(Ray {
                        origin: p + n * eps,
                        dir: d,
                        tmin: eps,
                        tmax: radius,
                    });
                }
                pixels.push((0.0, hit.t));
            }
            let mut blocked = vec![false; ao_rays.len()];
            tracer.occluded_batch(&ao_rays, &mut blocked, cache);
            let mut per_hit = blocked.chunks(AO_RAYS as usize);
            for (grey, t) in &mut pixels {
                if t.is_finite() {
                    let open = per_hit
                        .next()
                        .map_or(0, |b| b.iter().filter(|&&b| !b).count());
                    *grey = open as f32 / AO_RAYS as f32;
                }
            }
            pixels
        })
        .collect();
    let seconds = start.elapsed().as_secs_f64();
    let pixels: Vec<(f32, f32)> = rows.into_iter().flatten().collect();
    let hits = pixels.iter().filter(|p| p.1.is_finite()).count();
    let frame = Frame {
        width: SIZE,
        height: SIZE,
        rgb: pixels.iter().map(|&(g, _)| [g; 3]).collect(),
        depth: pixels.iter().map(|&(_, t)| t).collect(),
    };
    render::write_png(Path::new("ao.png"), &frame)?;
    let rays = pixels.len() + hits * AO_RAYS as usize;
    println!(
        "ao.png: {SIZE}×{SIZE}, {hits} hit pixels, {rays} rays in {seconds:.3} s ({:.2} Mrays/s)",
        rays as f64 / seconds / 1e6
    );
    Ok(())
}
