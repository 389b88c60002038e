//! `slimkd render` and the main job's render: the camera, the source of
//! the tree (built or a mapped file), frames and their figures.

use crate::args::{
    ModeArg, OutputFlags, RenderArgs, SecondaryArg, ShadingArg, Usage, check_image_output,
    check_output_dir,
};
use crate::build::{Built, Loaded, build_tree, load, pipeline_of, print_summary};
use crate::json::{
    AoJson, BuildJson, BuiltJson, FileJson, FrameJson, RenderCmdJson, RenderSourceJson, SceneJson,
    TreeJson, print_json,
};
use crate::kd_file::{is_kd_file, open_kd};
use crate::lab::figures;
use crate::progress_bar::with_bar;
use crate::{CmdResult, DEFAULT_ARG, pool};
use slimkd::format::{Check, KdFile, Mapped};
use slimkd::progress::Progress;
use slimkd::render::{
    self, AoFrame, AoOptions, AoTimes, Camera, HitBuffer, Secondary, Shading, View,
};
use slimkd::scene::TriangleColumns;
use slimkd::stats::TreeStats;
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::ropes::{RopeTracer, Ropes};
use slimkd::trace::wide::{WideBoxes, WideTracer};
use slimkd::trace::{BruteForce, ClosestHit, KdSource, Scalar, TreeTracer};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The camera: explicit flags override a view, a view overrides the
/// default camera of the scene box. `recorded`: the scene name a `.kd`
/// file's header records, which views are matched by before the file's
/// stem (so a renamed file keeps its views).
pub(crate) fn camera_for(
    args: &RenderArgs,
    scene_path: &Path,
    recorded: Option<&str>,
    bounds: &slimkd::geom::Aabb,
) -> CmdResult<Camera> {
    let (w, h) = args.size;
    let mut cam = Camera::default_for(bounds, w, h);
    if let Some(id) = &args.view {
        let views: Vec<View> = crate::read_views(args.views.as_deref())?;
        let from = match &args.views {
            Some(file) => format!("the views file {}", file.display()),
            None => "the embedded views".into(),
        };
        let stem = scene_path.file_stem().unwrap_or_default().to_string_lossy();
        let view = recorded
            .and_then(|name| render::find_view_named(&views, name, id))
            .or_else(|| render::find_view_named(&views, &stem, id))
            .ok_or_else(|| {
                let names = match recorded {
                    Some(name) if name != stem => format!(
                        "scene `{name}` (the name {} records) or `{stem}` (its file stem)",
                        scene_path.display()
                    ),
                    _ => format!("scene `{stem}`"),
                };
                format!(
                    "no view `{id}` for {names} in {from}: a view is matched by the scene name \
                     a .kd file records, else by the file's stem, or by the longest scene name \
                     either starts with, followed by `.`, `_` or `-`"
                )
            })?;
        cam = Camera::from_view(view, w, h);
    } else if args.views.is_some() {
        return Err(Usage("--views needs --view ID".into()).into());
    }
    if let Some(v) = args.eye {
        cam.eye = v;
    }
    if let Some(v) = args.at {
        cam.at = v;
    }
    if let Some(v) = args.up {
        cam.up = v;
    }
    if let Some(v) = args.fov {
        if !(v > 0.0 && v < 180.0) {
            return Err(Usage(format!("--fov {v} is not in (0, 180)")).into());
        }
        cam.fov_deg = v;
    }
    cam.check()?;
    Ok(cam)
}

/// What a render traces: a tree built from a scene, or a mapped file.
pub(crate) enum Source {
    Built {
        loaded: Loaded,
        built: Box<Built>,
        stats: TreeStats,
    },
    File {
        file: KdFile<Mapped>,
        /// Only for `--mode brute`, which needs the scene as columns.
        columns: Option<TriangleColumns>,
        open_ms: f64,
    },
}

pub(crate) fn cmd_render(args: &RenderArgs, ui: OutputFlags) -> CmdResult<()> {
    if args.reps == 0 {
        return Err(Usage("--reps must be at least 1".into()).into());
    }
    if args.shading != ShadingArg::Ao
        && (args.spp.is_some() || args.secondary.is_some() || args.dump_rays.is_some())
    {
        return Err(Usage("--spp, --secondary and --dump-rays need --shading ao".into()).into());
    }
    if let Some(spp) = args.spp {
        // The rays are made before the clock starts: 32 bytes a ray, so
        // 64 a pixel is 2 GiB at 1024x1024.
        if !(1..=64).contains(&spp) {
            return Err(Usage(format!("--spp {spp} is not in 1..=64")).into());
        }
    }
    if let Some(out) = &args.output {
        check_image_output(out)?;
    }
    if let Some(out) = &args.dump_t {
        check_output_dir(out)?;
    }
    if let Some(prefix) = &args.dump_rays {
        check_output_dir(&ray_file(prefix, "primary"))?;
    }
    let kd_input = args.scene.as_os_str() != DEFAULT_ARG && is_kd_file(&args.scene);
    if kd_input && !args.build.given.is_empty() {
        return Err(Usage(format!(
            "{} {} build flags, but {} is a .kd file, built already",
            args.build.given.join(", "),
            if args.build.given.len() == 1 {
                "is a"
            } else {
                "are"
            },
            args.scene.display()
        ))
        .into());
    }
    if !kd_input {
        args.build.check()?;
    }
    let pool = pool(args.build.threads)?;
    pool.install(|| {
        let source = if kd_input {
            let start = Instant::now();
            let file = open_kd(&args.scene, Check::Header)?;
            let open_ms = start.elapsed().as_secs_f64() * 1e3;
            // Brute force reads every triangle from columns: the one mode
            // that copies the geometry, after checking it.
            let columns = match args.mode {
                ModeArg::Brute => Some(
                    file.to_columns()
                        .map_err(|e| format!("{}: {e}", args.scene.display()))?,
                ),
                _ => None,
            };
            Source::File { file, columns, open_ms }
        } else {
            let loaded = load(&args.scene, ui.bars_off())?;
            // Not written: bytes are counted as in a reordered file.
            let pipeline = pipeline_of(&args.build, &loaded, true);
            let built = build_tree(&loaded.scene, pipeline, ui.bars_off())?;
            let stats = TreeStats::of(&built.tree, &built.pipeline.config.sah);
            Source::Built {
                loaded,
                built: Box::new(built),
                stats,
            }
        };
        let (scene_path, recorded, columns, bounds) = match &source {
            Source::Built { loaded, built, .. } => (loaded.path.clone(), None, Some(&loaded.scene), built.tree.bounds),
            Source::File { file, columns, .. } => {
                (args.scene.clone(), file.config().scene.name(), columns.as_ref(), file.bounds())
            }
        };
        let camera = camera_for(args, &scene_path, recorded, &bounds)?;
        let tree_tracer = match &source {
            Source::Built { loaded, built, .. } => Some(TreeTracer {
                tree: &built.tree,
                scene: &loaded.scene,
            }),
            Source::File { .. } => None,
        };
        let use_ropes = args.secondary == Some(SecondaryArg::Ropes);
        if use_ropes && args.mode != ModeArg::Packet {
            return Err(Usage("--secondary ropes traces its primary rays in packets (--mode packet)".into()).into());
        }
        let ropes_start = Instant::now();
        let ropes = match (&source, use_ropes) {
            (_, false) => None,
            (Source::Built { .. }, true) => Some(Ropes::new(tree_tracer.as_ref().expect("built").walk())),
            (Source::File { file, .. }, true) => Some(Ropes::new(file.walk())),
        }
        .transpose()
        .map_err(|e| format!("{}: {e}", args.scene.display()))?;
        let ropes_ms = ropes_start.elapsed().as_secs_f64() * 1e3;
        let tris = match &source {
            Source::File { file, .. } => file.triangles().len(),
            Source::Built { loaded, .. } => loaded.scene.len(),
        };
        let use_wide = match args.secondary {
            Some(secondary) => secondary == SecondaryArg::Wide,
            None => {
                args.shading == ShadingArg::Ao
                    && args.mode == ModeArg::Packet
                    && wide_by_default(tris)
            }
        };
        if args.secondary == Some(SecondaryArg::Wide) && args.mode != ModeArg::Packet {
            return Err(Usage("--secondary wide traces its primary rays in packets (--mode packet)".into()).into());
        }
        let wide_start = Instant::now();
        let wide = match (&source, use_wide) {
            (_, false) => None,
            (Source::Built { .. }, true) => Some(WideBoxes::new(tree_tracer.as_ref().expect("built").walk())),
            (Source::File { file, .. }, true) => Some(WideBoxes::new(file.walk())),
        }
        .transpose()
        .map_err(|e| format!("{}: {e}", args.scene.display()))?;
        let wide_ms = wide_start.elapsed().as_secs_f64() * 1e3;
        let tracer: Box<dyn ClosestHit + '_> = match (&source, args.mode, &ropes) {
            (Source::Built { .. }, _, _) if let Some(w) = &wide => {
                Box::new(WideTracer::new(tree_tracer.as_ref().expect("built"), w))
            }
            (Source::File { file, .. }, _, _) if let Some(w) = &wide => Box::new(WideTracer::new(file, w)),
            (Source::Built { .. }, _, Some(r)) => Box::new(RopeTracer::new(tree_tracer.as_ref().expect("built"), r)),
            (Source::File { file, .. }, _, Some(r)) => Box::new(RopeTracer::new(file, r)),
            (_, ModeArg::Brute, None) => Box::new(BruteForce(columns.expect("columns for brute force"))),
            (Source::Built { .. }, ModeArg::Single, None) => Box::new(Scalar::new(tree_tracer.as_ref().expect("built"))),
            (Source::Built { .. }, ModeArg::Packet, None) => Box::new(PacketTracer::new(tree_tracer.as_ref().expect("built"))),
            (Source::File { file, .. }, ModeArg::Single, None) => Box::new(Scalar::new(file)),
            (Source::File { file, .. }, ModeArg::Packet, None) => Box::new(PacketTracer::new(file)),
        };
        if let Some(r) = &ropes
            && !ui.quiet
            && !ui.json
        {
            eprintln!(
                "ropes      {} cells, {:.1} bytes/triangle (not in the tree's bytes), built in {ropes_ms:.0} ms",
                r.cells(),
                r.bytes() as f64 / tris.max(1) as f64
            );
        }
        if let Some(w) = &wide
            && !ui.quiet
            && !ui.json
        {
            eprintln!(
                "wide boxes {} nodes over {} leaves, {:.1} bytes/triangle (not in the tree's bytes), built in {wide_ms:.0} ms",
                w.nodes(),
                w.leaves(),
                w.bytes() as f64 / tris.max(1) as f64
            );
        }
        let mut rates = Vec::new();
        let mut last: Option<HitBuffer> = None;
        let mut ao_reps: Vec<AoTimes> = Vec::new();
        let mut ao_light: Option<AoFrame> = None;
        let ao_options = AoOptions {
            spp: args.spp.unwrap_or(4),
            secondary: match args.secondary.unwrap_or(SecondaryArg::Packet) {
                SecondaryArg::Single => Secondary::Single,
                SecondaryArg::Packet => Secondary::Packet,
                // A rope tracer's contexts are its cells.
                SecondaryArg::FromHit | SecondaryArg::Ropes => Secondary::FromHit,
                // A wide tracer's packets walk its boxes.
                SecondaryArg::Wide => Secondary::Packet,
            },
        };
        for rep in 0..args.reps {
            let progress = Progress::default();
            let rep_message = || format!("frame {} of {}", rep + 1, args.reps);
            if args.shading == ShadingArg::Ao {
                let frame = with_bar(ui.bars_off(), "rendering", &progress, &rep_message, || {
                    Ok(match &source {
                        Source::Built { loaded, .. } => render::trace_ao_frame(
                            tracer.as_ref(),
                            &camera,
                            &bounds,
                            |_| &loaded.scene,
                            &ao_options,
                        ),
                        Source::File { file, .. } => render::trace_ao_frame(
                            tracer.as_ref(),
                            &camera,
                            &bounds,
                            |buf| render::FileNormals::new(file, buf),
                            &ao_options,
                        ),
                    })
                })?;
                rates.push(frame.primary.mrays_per_s());
                ao_reps.push(frame.times);
                ao_light = Some(frame);
                continue;
            }
            let buf = with_bar(ui.bars_off(), "rendering", &progress, &rep_message, || {
                Ok(render::trace_frame_with_progress(
                    tracer.as_ref(),
                    &camera,
                    Some(&progress),
                ))
            })?;
            rates.push(buf.mrays_per_s());
            last = Some(buf);
        }
        if let (Some(prefix), Some(ao)) = (&args.dump_rays, &ao_light) {
            let spp = ao_options.spp;
            let rays = match &source {
                Source::Built { loaded, .. } => render::frame_rays(&ao.primary, &camera, &bounds, &&loaded.scene, spp),
                Source::File { file, .. } => {
                    let normals = render::FileNormals::new(file, &ao.primary);
                    render::frame_rays(&ao.primary, &camera, &bounds, &normals, spp)
                }
            };
            write_frame_rays(prefix, &rays)?;
        }
        let (buf, frame) = match ao_light {
            Some(ao) => {
                let frame = render::shade_ao(&ao);
                (ao.primary, frame)
            }
            None => {
                let buf = last.expect("reps >= 1");
                let shading = match args.shading {
                    ShadingArg::EyeLight | ShadingArg::Ao => Shading::EyeLight,
                    ShadingArg::Normals => Shading::Normals,
                };
                let frame = match &source {
                    Source::Built { loaded, .. } => render::shade(&buf, &camera, &loaded.scene, shading),
                    Source::File { file, .. } => {
                        render::shade(&buf, &camera, &render::FileNormals::new(file, &buf), shading)
                    }
                };
                (buf, frame)
            }
        };
        let ao = (!ao_reps.is_empty()).then(|| {
            let mut ao = AoJson::of(&ao_options, &ao_reps);
            if use_ropes {
                ao.secondary = "ropes";
            }
            if use_wide {
                ao.secondary = "wide";
            }
            ao
        });
        if let Some(out) = &args.output {
            render::write_image(out, &frame)?;
        }
        if let Some(out) = &args.dump_t {
            render::write_depth_f32(out, &frame)?;
        }
        let mrays = figures::median(&rates);
        let mode = args.mode.name();
        let simd = if args.mode == ModeArg::Packet {
            SimdLevel::detect().name()
        } else {
            "scalar"
        };
        let threads = pool.current_num_threads();
        if ui.json {
            let source = match &source {
                Source::Built { loaded, built, stats } => {
                    RenderSourceJson::Built(Box::new(BuiltJson {
                        scene: SceneJson::of(loaded),
                        tree: TreeJson::of(stats),
                        build: BuildJson::of(built),
                    }))
                }
                Source::File { file, open_ms, .. } => {
                    RenderSourceJson::File(FileJson::of(&args.scene, file, *open_ms))
                }
            };
            print_json(
                "render",
                RenderCmdJson {
                    source,
                    frame: FrameJson {
                        mode,
                        simd,
                        threads,
                        width: camera.width,
                        height: camera.height,
                        reps: args.reps,
                        mrays_per_s: mrays,
                        hits: buf.n_hits(),
                        checksum: buf.checksum(),
                        eye: camera.eye.to_array(),
                        at: camera.at.to_array(),
                        up: camera.up.to_array(),
                        fov: camera.fov_deg,
                        ao,
                    },
                },
            )?;
        } else if !ui.quiet {
            match &source {
                Source::Built { loaded, built, stats } => {
                    print_summary(loaded, built, stats, ui.verbose)
                }
                Source::File { file, open_ms, .. } => println!(
                    "file       {} ({} triangles), opened in {open_ms:.3} ms",
                    args.scene.display(),
                    file.figures().triangles
                ),
            }
            println!(
                "render     {}x{} {mode} ({simd}), {threads} threads: {:.2} Mrays/s (median of {}), {} hits, checksum {:.6}",
                camera.width,
                camera.height,
                mrays,
                args.reps,
                buf.n_hits(),
                buf.checksum()
            );
            if let Some(a) = &ao {
                let rate = |n: u64, ms: f64| n as f64 / ms / 1e3;
                println!(
                    "ao frame   {:.1} ms (median of {}): primary {:.1} ms ({} rays, {:.2} Mrays/s), contexts {:.1} ms, shadow {:.1} ms ({} rays, {:.2} Mrays/s, {} shadowed), AO {:.1} ms ({} rays, {:.2} Mrays/s, {} occluded); secondary rays {}; rays made in {:.1} ms (not in the frame)",
                    a.frame_ms,
                    args.reps,
                    a.primary_ms,
                    a.primary_rays,
                    rate(a.primary_rays, a.primary_ms),
                    a.context_ms,
                    a.shadow_ms,
                    a.shadow_rays,
                    rate(a.shadow_rays, a.shadow_ms),
                    a.shadowed,
                    a.ao_ms,
                    a.ao_rays,
                    rate(a.ao_rays, a.ao_ms),
                    a.ao_occluded,
                    a.secondary,
                    a.making_ms
                );
            }
            if ui.verbose {
                println!(
                    "camera     eye {},{},{} at {},{},{} up {},{},{} fov {}",
                    camera.eye.x,
                    camera.eye.y,
                    camera.eye.z,
                    camera.at.x,
                    camera.at.y,
                    camera.at.z,
                    camera.up.x,
                    camera.up.y,
                    camera.up.z,
                    camera.fov_deg
                );
            }
            if let Some(out) = &args.output {
                println!("wrote      {}", out.display());
            }
        }
        Ok(())
    })
}

/// Triangles up to which `render --shading ao` and the main job trace
/// their shadow and AO rays over wide boxes unless told otherwise
/// (`--secondary`): on the six shared scenes the AO frame ran 1.00–1.40×
/// as fast as with the kd-tree's packets (views 1 and 2), for boxes of
/// 66–146 bytes a triangle with their vertex copy (8 Mi triangles: under
/// 1.2 GiB besides the tree), built once per opened tree in 0.03–0.9 s
/// and reported apart.
/// Larger scenes keep to the tree's bytes.
pub(crate) const WIDE_MAX_TRIANGLES: usize = 8 << 20;

/// Whether a scene of `tris` triangles traces its secondary rays over
/// wide boxes by default ([`WIDE_MAX_TRIANGLES`]).
pub(crate) fn wide_by_default(tris: usize) -> bool {
    tris <= WIDE_MAX_TRIANGLES
}

/// Writes `rays` to `PREFIX-primary.rays`, `PREFIX-shadow.rays` and
/// `PREFIX-ao.rays`: each staged first, then all renamed into place, so
/// that a failure leaves none of them changed.
fn write_frame_rays(prefix: &Path, rays: &render::FrameRays) -> CmdResult<()> {
    let mut staged = Vec::new();
    for (kind, list) in [
        ("primary", &rays.primary),
        ("shadow", &rays.shadow),
        ("ao", &rays.ao),
    ] {
        let path = ray_file(prefix, kind);
        let io = |e: std::io::Error| format!("{}: {e}", path.display());
        let mut file = slimkd::fsio::Staged::create(&path).map_err(io)?;
        file.file()
            .write_all(&slimkd::trace::rays::ray_bytes(list))
            .map_err(io)?;
        file.stage().map_err(io)?;
        staged.push((path, file));
    }
    for (path, file) in staged {
        file.commit()
            .map_err(|e| format!("{}: {e}", path.display()))?;
    }
    Ok(())
}

/// `PREFIX-KIND.rays`.
fn ray_file(prefix: &Path, kind: &str) -> PathBuf {
    let mut name = prefix.as_os_str().to_owned();
    name.push(format!("-{kind}.rays"));
    PathBuf::from(name)
}
