//! `slimkd` without arguments: the std tree and the `small` and `fast` slim
//! trees of the embedded scene, each written as a reordered `.kd` file into
//! a temporary directory, mapped back and traced with packets from the same
//! view; one table compares them. The std tree then renders the frame a
//! renderer would (primary rays, a shadow ray and AO rays per hit, the
//! time by ray kind), and that picture goes to `slimkd.png`.

use crate::args::OutputFlags;
use crate::build::{Loaded, build_tree, load, print_scene_line, print_summary};
use crate::json::{AoJson, SceneJson, print_json};
use crate::kd_file::open_kd;
use crate::lab::figures::{self, FiguresJson};
use crate::render::wide_by_default;
use crate::{CmdResult, DEFAULT_ARG, DEFAULT_SCENE_NAME, DEFAULT_VIEWS};
use slimkd::build::BuildConfig;
use slimkd::format::{self, Preset};
use slimkd::pipeline::Pipeline;
use slimkd::render::{self, AoFrame, AoOptions, Camera, HitBuffer, Secondary};
use slimkd::slim::SlimParams;
use slimkd::stats::TreeStats;
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::wide::{WideBoxes, WideTracer};
use slimkd::trace::{ClosestHit, KdSource};
use slimkd::tree::TreeIr;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The image the main job writes into the current directory.
const IMAGE: &str = "slimkd.png";
/// Frames traced per tree (the median is reported).
const REPS: usize = 3;
const SIZE: (u32, u32) = (1024, 1024);
/// The AO frame of the picture: 8 AO rays a hit (4 leave the picture
/// grainy), shadow and AO rays in packets (the fastest way to trace them:
/// `docs/perf-notes.md`, "Rays from a hit context"), over wide boxes
/// where they fit ([`wide_by_default`]).
const AO: AoOptions = AoOptions {
    spp: 8,
    secondary: Secondary::Packet,
};

/// A directory of its own under the system temporary directory, removed
/// when dropped (on success and on error).
struct TempDir(PathBuf);

impl TempDir {
    fn new() -> CmdResult<TempDir> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let dir =
            std::env::temp_dir().join(format!("slimkd-main-job-{}-{nanos}", std::process::id()));
        std::fs::create_dir(&dir).map_err(|e| format!("cannot make {}: {e}", dir.display()))?;
        Ok(TempDir(dir))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// One row of the table.
/// `slimkd --json`: the main job's table.
#[derive(serde::Serialize)]
struct MainJson {
    #[serde(flatten)]
    scene: SceneJson,
    std_build_s: f64,
    threads: usize,
    width: u32,
    height: u32,
    reps: usize,
    simd: &'static str,
    trees: Vec<MainTreeJson>,
    /// The std tree's AO frame (the picture).
    ao: AoJson,
    image: &'static str,
}

/// One row of the main job's table.
#[derive(serde::Serialize)]
struct MainTreeJson {
    tree: &'static str,
    #[serde(flatten)]
    figures: FiguresJson,
    bytes_per_triangle: f64,
    refs_per_triangle: f64,
    mrays_per_s: f64,
    hits: u64,
    checksum: f64,
    same_hits_as_std: bool,
    write_s: f64,
}

struct Row {
    name: &'static str,
    figures: format::TreeFigures,
    mrays: f64,
    frame: HitBuffer,
    write_s: f64,
    /// The AO frame, of the tree that renders the picture, and how its
    /// secondary rays were traced (`packet` or `wide`).
    ao: Option<(AoFrame, &'static str)>,
}

/// Whether two frames hit the same triangles at the same distances, bit
/// for bit.
fn same_hits(a: &HitBuffer, b: &HitBuffer) -> bool {
    a.hits.len() == b.hits.len()
        && a.hits
            .iter()
            .zip(&b.hits)
            .all(|(x, y)| x.t.to_bits() == y.t.to_bits() && x.tri == y.tri)
}

/// The embedded scene's view 1 (the default camera if it had none).
fn camera(bounds: &slimkd::geom::Aabb) -> CmdResult<Camera> {
    let views = render::parse_views(DEFAULT_VIEWS)?;
    let cam = match render::find_view(&views, Path::new(DEFAULT_SCENE_NAME), "1") {
        Some(v) => Camera::from_view(v, SIZE.0, SIZE.1),
        None => Camera::default_for(bounds, SIZE.0, SIZE.1),
    };
    cam.check()?;
    Ok(cam)
}

/// Writes `tree` as a reordered `.kd` file, maps it back and traces
/// [`REPS`] frames with packets, after one untimed frame.
#[allow(clippy::too_many_arguments)]
fn write_and_trace(
    dir: &Path,
    name: &'static str,
    tree: &TreeIr,
    loaded: &Loaded,
    pipeline: &Pipeline,
    camera: &Camera,
    ao: Option<&AoOptions>,
) -> CmdResult<Row> {
    let path = dir.join(format!("{name}.kd"));
    let start = Instant::now();
    pipeline.write_file(&path, tree, &loaded.scene)?;
    let write_s = start.elapsed().as_secs_f64();
    let file = open_kd(&path, slimkd::format::Check::Header)?;
    let tracer = PacketTracer::new(&file);
    // One untimed frame first: it faults the file's pages in.
    let mut last = Some(render::trace_frame(&tracer, camera));
    let mut rates = Vec::with_capacity(REPS);
    for _ in 0..REPS {
        let buf = render::trace_frame(&tracer, camera);
        rates.push(buf.mrays_per_s());
        last = Some(buf);
    }
    let ao = match ao {
        Some(options) => {
            // Shadow and AO rays over wide boxes where they fit (as
            // `render --shading ao` by default).
            let boxes = if wide_by_default(file.triangles().len()) {
                Some(WideBoxes::new(file.walk()).map_err(|e| format!("{}: {e}", path.display()))?)
            } else {
                None
            };
            let wide = boxes.as_ref().map(|b| WideTracer::new(&file, b));
            let tracer: &dyn ClosestHit = match &wide {
                Some(w) => w,
                None => &tracer,
            };
            let frame = render::trace_ao_frame(
                tracer,
                camera,
                &file.bounds(),
                |buf| render::FileNormals::new(&file, buf),
                options,
            );
            Some((frame, if wide.is_some() { "wide" } else { "packet" }))
        }
        None => None,
    };
    Ok(Row {
        name,
        ao,
        figures: file.figures(),
        mrays: figures::median(&rates),
        frame: last.expect("REPS >= 1"),
        write_s,
    })
}

/// The main job; `-v` adds the build's phase times and memory.
pub(crate) fn main_job(ui: OutputFlags) -> CmdResult<()> {
    let verbose = ui.verbose;
    let text = !(ui.quiet || ui.json);
    // The text lines, which -q and --json leave out.
    macro_rules! say {
        ($($t:tt)*) => {
            if text {
                println!($($t)*);
            }
        };
    }
    let dir = TempDir::new()?;
    let loaded = load(Path::new(DEFAULT_ARG), ui.bars_off())?;
    let pipeline = Pipeline {
        scene_name: Some(loaded.name()),
        ..Pipeline::new(BuildConfig::default())
    };
    let built = build_tree(&loaded.scene, pipeline, ui.bars_off())?;
    let stats = TreeStats::of(&built.tree, &built.pipeline.config.sah);
    if !text {
    } else if verbose {
        print_summary(&loaded, &built, &stats, true);
    } else {
        print_scene_line(&loaded);
        say!(
            "build      std tree in {:.3} s with the {} builder on {} threads",
            built.std_seconds,
            built.builder,
            rayon::current_num_threads()
        );
    }
    let camera = camera(&built.tree.bounds)?;
    let mut rows = vec![write_and_trace(
        &dir.0,
        "std",
        &built.tree,
        &loaded,
        &built.pipeline,
        &camera,
        Some(&AO),
    )?];
    for (name, preset, params) in [
        ("small", Preset::Small, SlimParams::SMALL),
        ("fast", Preset::Fast, SlimParams::FAST),
    ] {
        let start = Instant::now();
        let pipeline = built.pipeline.slimmed(Some(params), preset);
        let base = pipeline.base_tree(&built.tree, &built.pipeline, &loaded.scene)?;
        let (tree, report, phases) = pipeline
            .slim(&base, &loaded.scene, None)
            .expect("the pipeline has a slim pass");
        let slim_s = start.elapsed().as_secs_f64();
        say!(
            "slim       {name} (μ {}, τ_occu {}, τ_freq {}, max_t2rn {}): {} triangles hoisted in {slim_s:.3} s",
            pipeline.config.sah.split_price,
            params.tau_occu,
            params.tau_freq,
            params.max_t2rn,
            report.hoisted
        );
        if verbose {
            say!(
                "           phases: {} passes; analysis {:.3} s, rebuilds {:.3} s, apply {:.3} s, assembly {:.3} s",
                phases.passes,
                phases.analysis_s,
                phases.rebuild_s,
                phases.apply_s,
                phases.assemble_s
            );
        }
        rows.push(write_and_trace(
            &dir.0, name, &tree, &loaded, &pipeline, &camera, None,
        )?);
    }
    let n = loaded.scene.len().max(1) as f64;
    say!(
        "render     {}x{} packets ({}), {} threads, median of {REPS} frames after a warm-up, from each tree's .kd file (reordered):",
        camera.width,
        camera.height,
        SimdLevel::detect().name(),
        rayon::current_num_threads()
    );
    say!(
        "           {:<6} {:>11} {:>9} {:>8} {:>9} {:>8}  same hits as std",
        "tree",
        "tree bytes",
        "bytes/tri",
        "nodes",
        "refs/tri",
        "Mrays/s"
    );
    for row in &rows {
        let f = &row.figures;
        // Leaf indices plus the T-references of hoisted triangles.
        let refs = f.idx32 + f.idx16 + f.t_inner;
        say!(
            "           {:<6} {:>11} {:>9.2} {:>8} {:>9.2} {:>8.2}  {}",
            row.name,
            f.tree_bytes(),
            f.tree_bytes() as f64 / n,
            f.nodes(),
            refs as f64 / n,
            row.mrays,
            if same_hits(&row.frame, &rows[0].frame) {
                "yes"
            } else {
                "no"
            }
        );
    }
    if verbose {
        for row in &rows {
            say!(
                "           wrote {}.kd in {:.3} s ({} hits, checksum {:.6})",
                row.name,
                row.write_s,
                row.frame.n_hits(),
                row.frame.checksum()
            );
        }
    }
    let (ao, secondary) = rows[0]
        .ao
        .as_ref()
        .expect("the std row renders the AO frame");
    let t = &ao.times;
    say!(
        "ao frame   std, {} AO rays a hit, secondary rays {secondary}: {:.0} ms = primary {:.0} ({} rays) + shadow {:.0} ({} rays) + AO {:.0} ({} rays, {:.1} Mrays/s); rays made in {:.0} ms (not in the frame)",
        AO.spp,
        t.frame_s() * 1e3,
        t.primary_s * 1e3,
        t.primary_rays,
        t.shadow_s * 1e3,
        t.shadow_rays,
        t.ao_s * 1e3,
        t.ao_rays,
        t.ao_rays as f64 / t.ao_s / 1e6,
        t.making_s * 1e3
    );
    render::write_image(Path::new(IMAGE), &render::shade_ao(ao))?;
    say!("wrote      {IMAGE}");
    if ui.json {
        print_json(
            "main",
            MainJson {
                scene: SceneJson::of(&loaded),
                std_build_s: built.std_seconds,
                threads: rayon::current_num_threads(),
                width: camera.width,
                height: camera.height,
                reps: REPS,
                simd: SimdLevel::detect().name(),
                trees: rows
                    .iter()
                    .map(|row| {
                        let f = &row.figures;
                        let refs = f.idx32 + f.idx16 + f.t_inner;
                        MainTreeJson {
                            tree: row.name,
                            figures: FiguresJson::of(f),
                            bytes_per_triangle: f.tree_bytes() as f64 / n,
                            refs_per_triangle: refs as f64 / n,
                            mrays_per_s: row.mrays,
                            hits: row.frame.n_hits(),
                            checksum: row.frame.checksum(),
                            same_hits_as_std: same_hits(&row.frame, &rows[0].frame),
                            write_s: row.write_s,
                        }
                    })
                    .collect(),
                ao: AoJson {
                    secondary,
                    ..AoJson::of(&AO, &[ao.times])
                },
                image: IMAGE,
            },
        )?;
    }
    if rows.iter().any(|r| !same_hits(&r.frame, &rows[0].frame)) {
        return Err("a slim tree's hits differ from the std tree's (a bug)".into());
    }
    Ok(())
}
