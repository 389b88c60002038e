//! Builds a tree from the caller's own vertex and index buffers (a box of
//! 12 triangles) and traces a few rays, single and as a masked packet.
//!
//! ```sh
//! cargo run --release --example embed_buffers
//! ```

use glam::Vec3;
use slimkd::accel::{Accel, BuildOptions, RayPacket};
use slimkd::geom::Ray;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // The corners of the box [0, 2] × [0, 1] × [0, 1]; corner i has
    // x = bit 0, y = bit 1, z = bit 2.
    let vertices: Vec<[f32; 3]> = (0..8)
        .map(|i| {
            [
                2.0 * (i & 1) as f32,
                ((i >> 1) & 1) as f32,
                ((i >> 2) & 1) as f32,
            ]
        })
        .collect();
    // Two triangles per face, wound outwards.
    let indices: [[u32; 3]; 12] = [
        [0, 2, 1],
        [1, 2, 3], // z = 0
        [4, 5, 6],
        [5, 7, 6], // z = 1
        [0, 1, 4],
        [1, 5, 4], // y = 0
        [2, 6, 3],
        [3, 6, 7], // y = 1
        [0, 4, 2],
        [2, 4, 6], // x = 0
        [1, 3, 5],
        [3, 7, 5], // x = 2
    ];
    let accel = Accel::from_buffers(&vertices, &indices, &BuildOptions::default())?;

    let rays = [
        Ray::new(Vec3::new(0.5, 0.5, -3.0), Vec3::Z), // hits the z = 0 face
        Ray::new(Vec3::new(1.0, 0.5, 0.5), Vec3::X),  // from inside: x = 2
        Ray::new(Vec3::new(-1.0, 0.25, 0.75), Vec3::X), // the x = 0 face
        Ray::new(Vec3::new(5.0, 5.0, 5.0), Vec3::Y),  // misses
    ];
    for ray in &rays {
        match accel.intersect(ray) {
            Some(h) => println!(
                "ray from {} along {}: triangle {} at t = {}, u = {}, v = {}, ng = {}",
                ray.origin, ray.dir, h.prim, h.t, h.u, h.v, h.ng
            ),
            None => println!("ray from {} along {}: miss", ray.origin, ray.dir),
        }
    }
    // A shadow ray that stops short of the box, and one that reaches it.
    let mut short = rays[0];
    short.tmax = 2.5;
    println!("occluded within t < 2.5: {}", accel.occluded(&short));
    short.tmax = 3.5;
    println!("occluded within t < 3.5: {}", accel.occluded(&short));

    // The same rays as one packet, lanes 0–3 in the mask.
    let packet = RayPacket::from_rays(&rays);
    let hits = accel.intersect_packet(&packet, 0b1111);
    for (i, ray) in rays.iter().enumerate() {
        assert_eq!(hits[i], accel.intersect(ray));
    }
    let occluded = accel.occluded_packet(&packet, 0b1111);
    println!("packet: lanes occluded {occluded:#06b}");
    if occluded != 0b0111 {
        return Err("expected lanes 0, 1 and 2 to hit the box".into());
    }
    Ok(())
}
