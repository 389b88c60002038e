//! The report as JSON: the numbers of the Markdown, unrounded, as `serde`
//! structs (docs/json-schema.md). A value that is not finite is written
//! as `null` (serde_json's rule for `f64`).

use super::*;
use crate::lab::figures::{FiguresJson, JSON_SCHEMA};
use serde::Serialize;
use serde_json::Value;

#[derive(Serialize)]
struct ReportJson<'a> {
    schema: u32,
    machine: MachineJson,
    build: BuildJson,
    presets: Vec<PresetJson>,
    sweep: bool,
    scenes: Vec<SceneJson<'a>>,
}

#[derive(Serialize)]
struct MachineJson {
    all_threads: usize,
    width: u32,
    height: u32,
    reps: usize,
    simd: &'static str,
    arch: &'static str,
    available_parallelism: usize,
}

#[derive(Serialize)]
struct BuildJson {
    builder: &'static str,
    k_t: f64,
    k_i: f64,
    lambda_empty: f64,
    reorder: bool,
}

#[derive(Serialize)]
struct PresetJson {
    tree: &'static str,
    tau_occu: f64,
    tau_freq: f64,
    max_t2rn: u32,
    hoist_rule: &'static str,
}

#[derive(Serialize)]
struct SceneJson<'a> {
    name: &'a str,
    triangles: u64,
    vertices: u64,
    table1: Table1Json,
    table2: Table2Json,
    table3a: Vec<SizeRowJson>,
    table3b: Vec<ViewJson<'a>>,
    table4: Table4Json,
    figure5: Vec<SweepPointJson<'a>>,
    figure6: Figure6Json<'a>,
}

#[derive(Serialize)]
struct BinJson {
    lo: u64,
    hi: Option<u64>,
    triangles: u64,
    mean_longest_edge: f64,
}

#[derive(Serialize)]
struct Table1Json {
    bins: Vec<BinJson>,
    total_indices: u64,
    indices_per_triangle: f64,
}

#[derive(Serialize)]
struct Table2Json {
    geometry_bytes: u64,
    std_tree_bytes: u64,
    std_classic_bytes: u64,
    tree_to_geometry: f64,
    classic_to_geometry: f64,
}

#[derive(Serialize)]
struct SizeRowJson {
    #[serde(flatten)]
    figures: FiguresJson,
    tree: &'static str,
    mib: f64,
    paper_layout_bytes: u64,
    reduction_pct: f64,
    reduction_vs_classic_pct: f64,
    hoisted: usize,
    file_bytes: u64,
    max_depth: u32,
}

/// One value per column of Table 3(b).
#[derive(Serialize)]
struct ColumnsJson<T> {
    scalar_1t: T,
    scalar_all: T,
    packet_1t: T,
    packet_all: T,
}

impl<T> ColumnsJson<T> {
    fn of(values: [T; 4]) -> ColumnsJson<T> {
        let [scalar_1t, scalar_all, packet_1t, packet_all] = values;
        ColumnsJson {
            scalar_1t,
            scalar_all,
            packet_1t,
            packet_all,
        }
    }
}

#[derive(Serialize)]
struct SpreadJson {
    median: f64,
    q1: f64,
    q3: f64,
    min: f64,
    max: f64,
    within_noise: bool,
}

impl SpreadJson {
    fn of(s: &Spread) -> SpreadJson {
        SpreadJson {
            median: s.median,
            q1: s.q1,
            q3: s.q3,
            min: s.min,
            max: s.max,
            within_noise: s.includes_zero(),
        }
    }
}

#[derive(Serialize)]
struct TreeRatesJson {
    tree: &'static str,
    #[serde(flatten)]
    rates: ColumnsJson<f64>,
    loss_pct: ColumnsJson<f64>,
    loss_spread_pct: ColumnsJson<SpreadJson>,
}

#[derive(Serialize)]
struct ViewJson<'a> {
    view: &'a str,
    hits: u64,
    checksum: f64,
    trees: Vec<TreeRatesJson>,
}

#[derive(Serialize)]
struct WriteTimesJson {
    std: f64,
    fast: f64,
    small: f64,
}

#[derive(Serialize)]
struct Table4Json {
    load_s: f64,
    std_build_s: f64,
    fast_slim_s: f64,
    small_slim_s: f64,
    fast_base_s: f64,
    small_base_s: f64,
    fast_ratio: f64,
    small_ratio: f64,
    write_s: WriteTimesJson,
}

#[derive(Serialize)]
struct SweepPointJson<'a> {
    tau_occu: f64,
    tau_freq: f64,
    max_t2rn: u32,
    tree_bytes: u64,
    hoisted: usize,
    reduction_pct: f64,
    loss_pct: f64,
    loss_q1_pct: f64,
    loss_q3_pct: f64,
    within_noise: bool,
    view_loss_pct: &'a [f64],
    slim_s: f64,
}

#[derive(Serialize)]
struct Figure6Json<'a> {
    std: &'a [u64],
    fast: &'a [u64],
    small: &'a [u64],
}

impl Report {
    /// The report as one JSON object, with the numbers of the Markdown
    /// (unrounded; `null` for a value that is not finite).
    pub fn json(&self) -> Value {
        let doc = ReportJson {
            schema: JSON_SCHEMA,
            machine: MachineJson {
                all_threads: self.all_threads,
                width: self.size.0,
                height: self.size.1,
                reps: self.reps,
                simd: self.simd,
                arch: std::env::consts::ARCH,
                available_parallelism: std::thread::available_parallelism().map_or(1, |n| n.get()),
            },
            build: BuildJson {
                builder: "level",
                k_t: self.build.sah.k_t,
                k_i: self.build.sah.k_i,
                lambda_empty: self.build.sah.lambda_empty,
                reorder: true,
            },
            presets: TreeKind::ALL
                .iter()
                .filter_map(|k| {
                    k.params(self.rule).map(|p| PresetJson {
                        tree: k.name(),
                        tau_occu: p.tau_occu,
                        tau_freq: p.tau_freq,
                        max_t2rn: p.max_t2rn,
                        hoist_rule: rule_name(p.rule),
                    })
                })
                .collect(),
            sweep: self.sweep,
            scenes: self.scenes.iter().map(scene_json).collect(),
        };
        serde_json::to_value(doc).expect("plain numbers and strings serialise")
    }
}

fn scene_json(s: &SceneReport) -> SceneJson<'_> {
    let g = s.paper_geometry_bytes();
    SceneJson {
        name: &s.name,
        triangles: s.triangles,
        vertices: s.vertices,
        table1: Table1Json {
            bins: s
                .table1
                .bins
                .iter()
                .map(|b| BinJson {
                    lo: b.lo,
                    hi: b.hi,
                    triangles: b.triangles,
                    mean_longest_edge: b.mean_longest_edge,
                })
                .collect(),
            total_indices: s.table1.total_indices,
            indices_per_triangle: s.table1.ratio(),
        },
        table2: Table2Json {
            geometry_bytes: g,
            std_tree_bytes: s.std_tree_bytes(),
            std_classic_bytes: s.classic_std_bytes(),
            tree_to_geometry: ratio(s.std_tree_bytes() as f64, g as f64),
            classic_to_geometry: ratio(s.classic_std_bytes() as f64, g as f64),
        },
        table3a: s
            .table3a
            .iter()
            .map(|r| SizeRowJson {
                figures: FiguresJson::of(&r.figures),
                tree: r.tree.name(),
                mib: r.figures.tree_bytes() as f64 / MIB,
                paper_layout_bytes: slimkd::stats::bytes::paper_layout_bytes_of(&r.figures),
                reduction_pct: s.reduction_pct(r.tree),
                reduction_vs_classic_pct: s.reduction_vs_classic_pct(r.tree),
                hoisted: r.hoisted,
                file_bytes: r.file_bytes,
                max_depth: r.max_depth,
            })
            .collect(),
        table3b: s
            .table3b
            .iter()
            .map(|v| ViewJson {
                view: &v.view,
                hits: v.hits,
                checksum: v.checksum,
                trees: TreeKind::ALL
                    .iter()
                    .map(|&k| TreeRatesJson {
                        tree: k.name(),
                        rates: ColumnsJson::of(v.rates[k as usize].as_array()),
                        loss_pct: ColumnsJson::of(v.loss_pct(k)),
                        loss_spread_pct: ColumnsJson::of(
                            v.loss[k as usize].each_ref().map(SpreadJson::of),
                        ),
                    })
                    .collect(),
            })
            .collect(),
        table4: Table4Json {
            load_s: s.table4.load_s,
            std_build_s: s.table4.std_build_s,
            fast_slim_s: s.table4.slim_s[0],
            small_slim_s: s.table4.slim_s[1],
            fast_base_s: s.table4.base_s[0],
            small_base_s: s.table4.base_s[1],
            fast_ratio: s.table4.slim_ratio(0),
            small_ratio: s.table4.slim_ratio(1),
            write_s: WriteTimesJson {
                std: s.table4.write_s[0],
                fast: s.table4.write_s[1],
                small: s.table4.write_s[2],
            },
        },
        figure5: s
            .sweep
            .iter()
            .map(|p| SweepPointJson {
                tau_occu: p.tau_occu,
                tau_freq: p.tau_freq,
                max_t2rn: p.max_t2rn,
                tree_bytes: p.tree_bytes,
                hoisted: p.hoisted,
                reduction_pct: p.reduction_pct,
                loss_pct: p.loss_pct,
                loss_q1_pct: p.loss_spread.q1,
                loss_q3_pct: p.loss_spread.q3,
                within_noise: p.loss_spread.includes_zero(),
                view_loss_pct: &p.view_loss_pct,
                slim_s: p.slim_s,
            })
            .collect(),
        figure6: Figure6Json {
            std: &s.leaf_depths[0],
            fast: &s.leaf_depths[1],
            small: &s.leaf_depths[2],
        },
    }
}
