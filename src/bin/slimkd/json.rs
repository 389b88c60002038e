//! The objects `--json` prints: one `serde` struct per part, shared by the
//! commands that print the same quantity, so that a key means one thing
//! everywhere (docs/json-schema.md lists every key, its meaning and unit).

use crate::CmdResult;
use crate::lab::figures::{FiguresJson, JSON_SCHEMA, NodeCounts, StorageJson};
use serde::Serialize;
use slimkd::stats::TreeStats;

/// One command's object: `schema` and `command` first, then its parts.
#[derive(Serialize)]
pub(crate) struct Doc<T: Serialize> {
    pub(crate) schema: u32,
    pub(crate) command: &'static str,
    #[serde(flatten)]
    pub(crate) body: T,
}

/// Prints `body` as the one JSON object of `command`.
pub(crate) fn print_json<T: Serialize>(command: &'static str, body: T) -> CmdResult<()> {
    let doc = Doc {
        schema: JSON_SCHEMA,
        command,
        body,
    };
    println!("{}", serde_json::to_string(&doc)?);
    Ok(())
}

/// A loaded scene.
#[derive(Serialize)]
pub(crate) struct SceneJson {
    /// The scene file as given (or the embedded scene's file name).
    pub(crate) scene: String,
    /// Its name: the file's stem.
    pub(crate) scene_name: String,
    pub(crate) triangles: usize,
    pub(crate) vertices: usize,
    pub(crate) dropped_degenerate: usize,
    pub(crate) load_s: f64,
}

/// A built tree's figures.
#[derive(Serialize)]
pub(crate) struct TreeJson {
    #[serde(flatten)]
    pub(crate) nodes: NodeCounts,
    pub(crate) nodes_empty_leaf: usize,
    pub(crate) refs: usize,
    pub(crate) max_depth: u32,
    pub(crate) mean_leaf_depth: f64,
    pub(crate) sah_cost: f64,
    pub(crate) leaf_depth_histogram: Vec<u64>,
}

impl TreeJson {
    pub(crate) fn of(s: &TreeStats) -> TreeJson {
        TreeJson {
            nodes: NodeCounts::of_stats(s),
            nodes_empty_leaf: s.empty_leaves,
            refs: s.refs,
            max_depth: s.max_depth,
            mean_leaf_depth: s.mean_leaf_depth,
            sah_cost: s.sah_cost,
            leaf_depth_histogram: s.leaf_depths.clone(),
        }
    }
}

#[derive(Serialize)]
pub(crate) struct LevelJson {
    pub(crate) sah_s: f64,
    pub(crate) classify_clip_s: f64,
    pub(crate) events_s: f64,
    pub(crate) leaves_s: f64,
    pub(crate) small_nodes_s: f64,
    pub(crate) setup_s: f64,
    pub(crate) assemble_s: f64,
    pub(crate) levels: u64,
    pub(crate) groups: u64,
    pub(crate) small_nodes: u64,
    pub(crate) small_threshold: u64,
    pub(crate) finisher_reserve_bytes: u64,
    pub(crate) start_rss_anon_bytes: u64,
    pub(crate) peak_rss_anon_bytes: u64,
    pub(crate) peak_rss_file_bytes: u64,
    pub(crate) scratch_bytes_written: u64,
    pub(crate) cpu_s: f64,
}

#[derive(Serialize)]
pub(crate) struct SlimJson {
    pub(crate) hoisted: usize,
    pub(crate) cancelled: usize,
    pub(crate) rejected: usize,
    pub(crate) priced: usize,
    pub(crate) rebuilds: usize,
    pub(crate) rebuilt_refs: u64,
    pub(crate) passes: u32,
    pub(crate) analysis_s: f64,
    pub(crate) rebuild_s: f64,
    pub(crate) apply_s: f64,
    pub(crate) assemble_s: f64,
}

/// How a tree was built.
#[derive(Serialize)]
pub(crate) struct BuildJson {
    pub(crate) builder: &'static str,
    /// The whole build: std tree and slim pass.
    pub(crate) build_s: f64,
    pub(crate) std_build_s: f64,
    pub(crate) k_t: f64,
    pub(crate) k_i: f64,
    pub(crate) lambda_empty: f64,
    pub(crate) split_price: f64,
    pub(crate) preset: &'static str,
    pub(crate) hoisted: usize,
    pub(crate) tau_occu: Option<f64>,
    pub(crate) tau_freq: Option<f64>,
    pub(crate) max_t2rn: Option<u32>,
    pub(crate) coarsen: Option<f64>,
    /// `None` (JSON `null`) without a slim pass or without a price.
    pub(crate) cost_ratio: Option<f64>,
    pub(crate) hoist_rule: Option<&'static str>,
    /// `sah` or `prune` (`slim::Rebuild`); `None` without a slim pass.
    pub(crate) rebuild: Option<&'static str>,
    pub(crate) level: Option<LevelJson>,
    pub(crate) slim: Option<SlimJson>,
}

/// A `.kd` file written.
#[derive(Serialize)]
pub(crate) struct WrittenJson {
    pub(crate) output: String,
    pub(crate) write_s: f64,
    pub(crate) reorder: bool,
    #[serde(flatten)]
    pub(crate) storage: StorageJson,
}

/// The peak memory of a command.
#[derive(Serialize)]
pub(crate) struct MemoryJson {
    pub(crate) peak_rss_anon_bytes: u64,
    pub(crate) peak_rss_file_bytes: u64,
}

/// `slimkd build --json`.
#[derive(Serialize)]
pub(crate) struct BuildCmdJson {
    #[serde(flatten)]
    pub(crate) scene: SceneJson,
    #[serde(flatten)]
    pub(crate) tree: TreeJson,
    #[serde(flatten)]
    pub(crate) build: BuildJson,
    pub(crate) threads: usize,
    #[serde(flatten)]
    pub(crate) written: Option<WrittenJson>,
    #[serde(flatten)]
    pub(crate) memory: MemoryJson,
    /// A build in cells (`build --cells`, `stitch`).
    #[serde(flatten)]
    pub(crate) cells: Option<CellsJson>,
}

/// A build in cells: its work directory and cells.
#[derive(Serialize)]
pub(crate) struct CellsJson {
    pub(crate) cells_dir: String,
    /// Whether the plan was made by this command (false: resumed or read).
    pub(crate) planned: bool,
    pub(crate) plan_s: f64,
    /// Per cell, in pre-order.
    pub(crate) cell_list: Vec<CellJson>,
}

/// `slimkd build-cell --json`.
#[derive(Serialize)]
pub(crate) struct BuildCellJson {
    pub(crate) cell: String,
    pub(crate) part: String,
    pub(crate) refs: u64,
    pub(crate) nodes: u64,
    pub(crate) read_s: f64,
    pub(crate) build_s: f64,
    /// Reading, building and writing.
    pub(crate) total_s: f64,
    pub(crate) threads: usize,
}

/// One cell of a build in cells.
#[derive(Serialize)]
pub(crate) struct CellJson {
    pub(crate) cell: String,
    pub(crate) part: String,
    pub(crate) refs: u64,
    /// Its part was there and valid before this command.
    pub(crate) kept: bool,
    /// Seconds this command took to build it (null: not built here).
    pub(crate) build_s: Option<f64>,
}

/// A `.kd` file opened.
#[derive(Serialize)]
pub(crate) struct FileJson {
    pub(crate) file: String,
    /// The scene name the header records (null: not recorded).
    pub(crate) scene_name: Option<String>,
    /// The header's geometry hash, 16 hex digits (all zero: not recorded).
    pub(crate) geometry_hash: String,
    pub(crate) triangles: u64,
    pub(crate) vertices: u64,
    pub(crate) open_ms: f64,
    #[serde(flatten)]
    pub(crate) figures: FiguresJson,
}

impl FileJson {
    pub(crate) fn of<D: AsRef<[u8]>>(
        path: &std::path::Path,
        file: &slimkd::format::KdFile<D>,
        open_ms: f64,
    ) -> FileJson {
        let f = file.figures();
        let tag = file.config().scene;
        FileJson {
            file: path.display().to_string(),
            scene_name: tag.name().map(str::to_string),
            geometry_hash: format!("{:016x}", tag.geometry_hash),
            triangles: f.triangles,
            vertices: f.vertices,
            open_ms,
            figures: FiguresJson::of(&f),
        }
    }
}

/// A frame traced.
#[derive(Serialize)]
pub(crate) struct FrameJson {
    pub(crate) mode: &'static str,
    pub(crate) simd: &'static str,
    pub(crate) threads: usize,
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) reps: usize,
    pub(crate) mrays_per_s: f64,
    pub(crate) hits: u64,
    pub(crate) checksum: f64,
    pub(crate) eye: [f64; 3],
    pub(crate) at: [f64; 3],
    pub(crate) up: [f64; 3],
    pub(crate) fov: f64,
    /// `--shading ao`: the frame by ray kind.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(crate) ao: Option<AoJson>,
}

/// `render --shading ao`: the frame's figures by ray kind, each the
/// median over the reps.
#[derive(Serialize)]
pub(crate) struct AoJson {
    pub(crate) spp: u32,
    pub(crate) secondary: &'static str,
    pub(crate) frame_ms: f64,
    pub(crate) primary_ms: f64,
    pub(crate) context_ms: f64,
    pub(crate) shadow_ms: f64,
    pub(crate) ao_ms: f64,
    pub(crate) primary_rays: u64,
    pub(crate) shadow_rays: u64,
    pub(crate) ao_rays: u64,
    pub(crate) shadowed: u64,
    pub(crate) ao_occluded: u64,
    /// Making the rays, not in `frame_ms`.
    pub(crate) making_ms: f64,
}

impl AoJson {
    /// The figures of the frames `reps` (at least one) traced with
    /// `options`: times the median over them, counts the first's.
    pub(crate) fn of(
        options: &slimkd::render::AoOptions,
        reps: &[slimkd::render::AoTimes],
    ) -> AoJson {
        use slimkd::render::AoTimes;
        let med = |f: fn(&AoTimes) -> f64| {
            1e3 * crate::lab::figures::median(&reps.iter().map(f).collect::<Vec<_>>())
        };
        let t = reps[0];
        AoJson {
            spp: options.spp,
            secondary: options.secondary.name(),
            frame_ms: med(AoTimes::frame_s),
            primary_ms: med(|t| t.primary_s),
            context_ms: med(|t| t.context_s),
            shadow_ms: med(|t| t.shadow_s),
            ao_ms: med(|t| t.ao_s),
            primary_rays: t.primary_rays,
            shadow_rays: t.shadow_rays,
            ao_rays: t.ao_rays,
            shadowed: t.shadowed,
            ao_occluded: t.ao_occluded,
            making_ms: med(|t| t.making_s),
        }
    }
}

/// What `render` traced: a tree it built, or a file.
#[derive(Serialize)]
#[serde(untagged)]
pub(crate) enum RenderSourceJson {
    Built(Box<BuiltJson>),
    File(FileJson),
}

/// A tree `render` built: the scene, the tree and the build.
#[derive(Serialize)]
pub(crate) struct BuiltJson {
    #[serde(flatten)]
    pub(crate) scene: SceneJson,
    #[serde(flatten)]
    pub(crate) tree: TreeJson,
    #[serde(flatten)]
    pub(crate) build: BuildJson,
}

/// `slimkd render --json`.
#[derive(Serialize)]
pub(crate) struct RenderCmdJson {
    #[serde(flatten)]
    pub(crate) source: RenderSourceJson,
    #[serde(flatten)]
    pub(crate) frame: FrameJson,
}
