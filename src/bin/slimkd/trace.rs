//! `slimkd trace`: traces a ray file through a mapped `.kd` file, timed like
//! the Embree peer program's `--rays` mode, and optionally counts the
//! traversal's work with a separate, untimed counting pass.

use serde::Serialize;
use slimkd::fsio;
use slimkd::trace::packet::PacketTracer;
use slimkd::trace::rays::{self, Query};
use slimkd::trace::ropes::{RopeTracer, Ropes};
use slimkd::trace::wide::{WideBoxes, WideTracer};
use slimkd::trace::{self as tr, ClosestHit, Hit, KdSource, Scalar, TraceStats};
use std::io::Write;
use std::time::Instant;

use crate::CmdResult;
use crate::args::{OutputFlags, TraceArgs, TraceMode};
use crate::json::print_json;

/// `slimkd trace --json`.
#[derive(Serialize)]
struct TraceJson {
    file: String,
    rays_file: String,
    mode: &'static str,
    query: &'static str,
    simd: &'static str,
    threads: usize,
    rays: usize,
    mrays_per_s: f64,
    mrays_per_s_reps: Vec<f64>,
    hits: u64,
    checksum: f64,
    open_ms: f64,
    /// `--mode ropes`: the ropes' build and size, apart from the tree's.
    ropes: Option<RopesJson>,
    /// `--mode wide`: the boxes' build and size, apart from the tree's.
    wide: Option<WideJson>,
    stats: Option<TraceStatsJson>,
}

#[derive(Serialize)]
struct RopesJson {
    build_ms: f64,
    bytes: usize,
    bytes_per_tri: f64,
    cells: usize,
}

#[derive(Serialize)]
struct WideJson {
    build_ms: f64,
    bytes: usize,
    bytes_per_tri: f64,
    nodes: usize,
    leaves: usize,
}

#[derive(Serialize)]
struct TraceStatsJson {
    rays: u64,
    nodes_per_ray: f64,
    leaves_per_ray: f64,
    tris_per_ray: f64,
    hoisted_per_ray: f64,
    cached_per_ray: f64,
    packets: u64,
    lanes_per_step: f64,
}

pub fn cmd_trace(args: &TraceArgs, ui: OutputFlags, pool: rayon::ThreadPool) -> CmdResult<()> {
    if args.reps == 0 {
        return Err("--reps must be at least 1".into());
    }
    let start = Instant::now();
    let file = crate::kd_file::open_kd(&args.file, slimkd::format::Check::Header)?;
    let open_ms = start.elapsed().as_secs_f64() * 1e3;
    let rays = rays::read_rays(&args.rays)?;
    let query = if args.occluded {
        Query::Occluded
    } else {
        Query::Closest
    };
    let packets = matches!(
        args.mode,
        TraceMode::Packet | TraceMode::Sorted | TraceMode::WidePacket
    );
    if matches!(args.mode, TraceMode::Stream | TraceMode::Lanes) && !args.occluded {
        return Err(
            crate::Usage("--mode stream and lanes answer --occluded queries only".into()).into(),
        );
    }
    let scalar = Scalar::new(&file);
    let packet = PacketTracer::new(&file);
    let ropes_start = Instant::now();
    let ropes = match args.mode {
        TraceMode::Ropes => {
            Some(Ropes::new(file.walk()).map_err(|e| format!("{}: {e}", args.file.display()))?)
        }
        _ => None,
    };
    let ropes_json = ropes.as_ref().map(|r| RopesJson {
        build_ms: ropes_start.elapsed().as_secs_f64() * 1e3,
        bytes: r.bytes(),
        bytes_per_tri: r.bytes() as f64 / file.triangles().len().max(1) as f64,
        cells: r.cells(),
    });
    let rope_tracer = ropes.as_ref().map(|r| RopeTracer::new(&file, r));
    let wide_start = Instant::now();
    let wide = match args.mode {
        // In the command's pool (its `-j`; rayon's global pool panics
        // where it cannot start its threads).
        TraceMode::Wide | TraceMode::WidePacket => Some(
            pool.install(|| WideBoxes::new(file.walk()))
                .map_err(|e| format!("{}: {e}", args.file.display()))?,
        ),
        _ => None,
    };
    let wide_json = wide.as_ref().map(|b| WideJson {
        build_ms: wide_start.elapsed().as_secs_f64() * 1e3,
        bytes: b.bytes(),
        bytes_per_tri: b.bytes() as f64 / file.triangles().len().max(1) as f64,
        nodes: b.nodes(),
        leaves: b.leaves(),
    });
    let wide_tracer = wide.as_ref().map(|b| match args.mode {
        TraceMode::WidePacket => WideTracer::new(&file, b).closest_packets(),
        _ => WideTracer::new(&file, b),
    });
    let tracer: &dyn ClosestHit = match (&rope_tracer, &wide_tracer, packets) {
        (Some(r), _, _) => r,
        (None, Some(w), _) => w,
        (None, None, true) => &packet,
        (None, None, false) => &scalar,
    };
    let (rates, last) = pool.install(|| {
        let batch = || match args.mode {
            TraceMode::FromHit | TraceMode::Ropes => {
                rays::trace_batch_from_hit(tracer, &rays, query)
            }
            TraceMode::Stream => rays::trace_batch_stream(&file, &rays, rays::STREAM),
            TraceMode::Lanes => rays::trace_batch_lanes(&file, &rays),
            TraceMode::Sorted => rays::trace_batch_sorted(tracer, &rays, query),
            _ => rays::trace_batch(tracer, &rays, query, packets),
        };
        let mut last = batch();
        let mut rates = Vec::new();
        for _ in 0..args.reps {
            last = batch();
            rates.push(last.mrays_per_s());
        }
        (rates, last)
    });
    let stats = args.stats.then(|| {
        let any = query == Query::Occluded;
        let count = |r: &[slimkd::geom::Ray],
                     out: &mut [Hit],
                     s: &mut TraceStats,
                     cache: &mut slimkd::trace::OccluderCache| {
            if let (Some(wt), true) = (&wide_tracer, packets) {
                wt.packet_counted(r, any, out, s, cache);
            } else if packets {
                packet.trace_counted_cached(r, any, out, s, cache);
            } else if let Some(wt) = &wide_tracer {
                for (ray, h) in r.iter().zip(out.iter_mut()) {
                    *h = wt.trace_counted(ray, any, s);
                }
            } else if let Some(rt) = &rope_tracer {
                let mut ctx = slimkd::trace::context::HitContext::default();
                for (ray, h) in r.iter().zip(out.iter_mut()) {
                    rt.locate_into(ray.origin, &mut ctx);
                    *h = rt.trace_from_counted(&ctx, ray, any, s);
                }
            } else if args.mode == TraceMode::FromHit {
                for (ray, h) in r.iter().zip(out.iter_mut()) {
                    let ctx = tr::locate(file.walk(), ray.origin);
                    *h = tr::traverse_from_counted(&file, &ctx, ray, any, s);
                }
            } else {
                for (ray, h) in r.iter().zip(out.iter_mut()) {
                    *h = tr::traverse_counted(&file, ray, any, s);
                }
            }
        };
        let pieces = match args.mode {
            TraceMode::Sorted => rays::Pieces::Sorted,
            _ if packets => rays::Pieces::Packets,
            _ => rays::Pieces::Single,
        };
        let (results, stats) = pool.install(|| rays::count_batch(&rays, query, pieces, &count));
        // The counting traversal must answer as the timed one did.
        let same = results
            .iter()
            .zip(&last.results)
            .all(|(a, b)| a.to_bits() == b.to_bits());
        (stats, same)
    });
    if let Some((_, false)) = stats {
        return Err("the counting traversal disagrees with the timed one (a bug)".into());
    }
    if let Some(path) = &args.dump {
        fsio::write_atomically(
            path,
            |e| format!("cannot write {}: {e}", path.display()),
            |f| {
                let bytes: Vec<u8> = last.results.iter().flat_map(|r| r.to_le_bytes()).collect();
                f.write_all(&bytes)
                    .map_err(|e| format!("cannot write {}: {e}", path.display()))
            },
        )?;
    }
    let mrays = crate::lab::figures::median(&rates);
    let simd = if packets || args.mode == TraceMode::Lanes {
        packet.level().name()
    } else {
        "scalar"
    };
    let mode = match args.mode {
        TraceMode::Single => "single",
        TraceMode::Packet => "packet",
        TraceMode::Sorted => "sorted",
        TraceMode::FromHit => "from-hit",
        TraceMode::Ropes => "ropes",
        TraceMode::Stream => "stream",
        TraceMode::Lanes => "lanes",
        TraceMode::Wide => "wide",
        TraceMode::WidePacket => "wide-packet",
    };
    let query_name = if args.occluded { "occluded" } else { "closest" };
    let threads = pool.current_num_threads();
    let per_ray = |s: &TraceStats, v: u64| v as f64 / (s.rays.max(1)) as f64;
    let lanes_per_step = |s: &TraceStats| {
        if s.nodes > 0 {
            s.lane_steps as f64 / s.nodes as f64
        } else {
            0.0
        }
    };
    if ui.json {
        print_json(
            "trace",
            TraceJson {
                file: args.file.display().to_string(),
                rays_file: args.rays.display().to_string(),
                mode,
                query: query_name,
                simd,
                threads,
                rays: rays.len(),
                mrays_per_s: mrays,
                mrays_per_s_reps: rates,
                hits: last.hits(query),
                checksum: last.checksum(query),
                open_ms,
                ropes: ropes_json,
                wide: wide_json,
                stats: stats.as_ref().map(|(s, _)| TraceStatsJson {
                    rays: s.rays,
                    nodes_per_ray: per_ray(s, s.nodes),
                    leaves_per_ray: per_ray(s, s.leaves),
                    tris_per_ray: per_ray(s, s.tris),
                    hoisted_per_ray: per_ray(s, s.hoisted),
                    cached_per_ray: per_ray(s, s.cached),
                    packets: s.packets,
                    lanes_per_step: lanes_per_step(s),
                }),
            },
        )?;
    } else if !ui.quiet {
        println!(
            "{mode} {query_name} ({simd}, {threads} threads): {:.3} Mrays/s (median of {}), {} rays, hits {}, checksum {:.6}",
            mrays,
            args.reps,
            rays.len(),
            last.hits(query),
            last.checksum(query)
        );
        if let Some(r) = &ropes_json {
            println!(
                "ropes: {} cells, {:.1} bytes/triangle (not in the tree's bytes), built in {:.0} ms",
                r.cells, r.bytes_per_tri, r.build_ms
            );
        }
        if let Some(w) = &wide_json {
            println!(
                "wide boxes: {} nodes over {} leaves, {:.1} bytes/triangle (not in the tree's bytes), built in {:.0} ms",
                w.nodes, w.leaves, w.bytes_per_tri, w.build_ms
            );
        }
        if let Some((s, _)) = &stats {
            if packets {
                println!(
                    "per ray: {:.2} packet node steps shared, {:.2} leaf triangle tests, {:.2} hoisted tests, {:.2} cached-occluder tests; {:.2} active lanes per step",
                    per_ray(s, s.nodes),
                    per_ray(s, s.tris),
                    per_ray(s, s.hoisted),
                    per_ray(s, s.cached),
                    lanes_per_step(s)
                );
            } else {
                println!(
                    "per ray: {:.2} nodes, {:.2} leaves, {:.2} triangle tests, {:.2} hoisted tests",
                    per_ray(s, s.nodes),
                    per_ray(s, s.leaves),
                    per_ray(s, s.tris),
                    per_ray(s, s.hoisted)
                );
            }
        }
    }
    Ok(())
}
