//! Builds the embedded scene, writes it as a `.kd` file in a temporary
//! directory, maps it back and traces one ray.
//!
//! ```sh
//! cargo run --release --example trace_one_ray
//! ```

use glam::Vec3;
use slimkd::accel::{Accel, BuildOptions, Preset};
use slimkd::geom::Ray;
use std::path::Path;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let obj = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/nexuiz_dieselpower.obj");
    let (scene, _) = slimkd::scene::load_obj(&obj)?;
    let options = BuildOptions {
        preset: Preset::Small,
        ..Default::default()
    };
    let built = Accel::build(&scene, &options)?;

    let dir = std::env::temp_dir().join(format!("slimkd-trace-one-ray-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("nexuiz_dieselpower.small.kd");
    built.write(&path)?;
    drop(built);
    let accel = Accel::open(&path)?;
    println!(
        "{}: {} triangles, {} bytes",
        path.display(),
        accel.len(),
        accel.as_bytes().len()
    );

    // From view 1's eye (scenes/views.txt) towards its target.
    let eye = Vec3::new(576.35, 144.33, 38.0);
    let at = Vec3::new(-3165.47, -2531.26, 38.0);
    let ray = Ray::new(eye, (at - eye).normalize());
    let hit = accel.intersect(&ray);
    match hit {
        Some(h) => println!(
            "hit triangle {} at t = {} (u = {}, v = {}), point {}, normal {}",
            h.prim,
            h.t,
            h.u,
            h.v,
            ray.origin + ray.dir * h.t,
            h.ng.normalize()
        ),
        None => println!("miss"),
    }
    std::fs::remove_dir_all(&dir)?;
    if hit.is_none() {
        return Err("the ray should hit the wall".into());
    }
    Ok(())
}
