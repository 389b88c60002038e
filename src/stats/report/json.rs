//! The report as JSON: the numbers of the Markdown, unrounded.

use super::*;
use crate::pipeline::{figures_json, merge_json};
use serde_json::{Value, json};

pub(super) fn jnum(x: f64) -> Value {
    if x.is_finite() { json!(x) } else { Value::Null }
}

impl Report {
    /// The report as one JSON object, with the numbers of the Markdown
    /// (unrounded; `null` for a value that is not finite).
    pub fn json(&self) -> Value {
        let scenes: Vec<Value> = self.scenes.iter().map(scene_json).collect();
        json!({
            "schema": crate::pipeline::JSON_SCHEMA,
            "machine": {
                "all_threads": self.all_threads,
                "width": self.size.0,
                "height": self.size.1,
                "reps": self.reps,
                "simd": self.simd,
                "arch": std::env::consts::ARCH,
                "available_parallelism": std::thread::available_parallelism().map_or(1, |n| n.get()),
            },
            "build": {
                "builder": "level",
                "k_t": self.build.sah.k_t,
                "k_i": self.build.sah.k_i,
                "lambda_empty": self.build.sah.lambda_empty,
                "reorder": true,
            },
            "presets": TreeKind::ALL.iter().filter_map(|k| k.params(self.rule).map(|p| json!({
                "tree": k.name(),
                "tau_occu": p.tau_occu,
                "tau_freq": p.tau_freq,
                "max_t2rn": p.max_t2rn,
                "hoist_rule": rule_name(p.rule),
            }))).collect::<Vec<_>>(),
            "sweep": self.sweep,
            "scenes": scenes,
        })
    }
}

fn scene_json(s: &SceneReport) -> Value {
    let g = s.paper_geometry_bytes();
    json!({
        "name": s.name,
        "triangles": s.triangles,
        "vertices": s.vertices,
        "table1": {
            "bins": s.table1.bins.iter().map(|b| json!({
                "lo": b.lo,
                "hi": b.hi,
                "triangles": b.triangles,
                "mean_longest_edge": jnum(b.mean_longest_edge),
            })).collect::<Vec<_>>(),
            "total_indices": s.table1.total_indices,
            "indices_per_triangle": jnum(s.table1.ratio()),
        },
        "table2": {
            "geometry_bytes": g,
            "std_tree_bytes": s.std_tree_bytes(),
            "std_classic_bytes": s.classic_std_bytes(),
            "tree_to_geometry": jnum(ratio(s.std_tree_bytes() as f64, g as f64)),
            "classic_to_geometry": jnum(ratio(s.classic_std_bytes() as f64, g as f64)),
        },
        "table3a": s.table3a.iter().map(|r| {
            let f = &r.figures;
            let mut row = figures_json(f);
            merge_json(&mut row, json!({
                "tree": r.tree.name(),
                "mib": f.tree_bytes() as f64 / MIB,
                "reduction_pct": jnum(s.reduction_pct(r.tree)),
                "reduction_vs_classic_pct": jnum(s.reduction_vs_classic_pct(r.tree)),
                "hoisted": r.hoisted,
                "file_bytes": r.file_bytes,
                "max_depth": r.max_depth,
            }));
            row
        }).collect::<Vec<_>>(),
        "table3b": s.table3b.iter().map(|v| json!({
            "view": v.view,
            "hits": v.hits,
            "checksum": v.checksum,
            "trees": TreeKind::ALL.iter().map(|&k| {
                let r = &v.rates[k as usize];
                let l = v.loss_pct(k);
                let spread = |i: usize| {
                    let s = &v.loss[k as usize][i];
                    json!({
                        "median": jnum(s.median),
                        "q1": jnum(s.q1),
                        "q3": jnum(s.q3),
                        "min": jnum(s.min),
                        "max": jnum(s.max),
                        "within_noise": s.includes_zero(),
                    })
                };
                json!({
                    "tree": k.name(),
                    "scalar_1t": jnum(r.scalar_1t),
                    "scalar_all": jnum(r.scalar_all),
                    "packet_1t": jnum(r.packet_1t),
                    "packet_all": jnum(r.packet_all),
                    "loss_pct": {
                        "scalar_1t": jnum(l[0]),
                        "scalar_all": jnum(l[1]),
                        "packet_1t": jnum(l[2]),
                        "packet_all": jnum(l[3]),
                    },
                    "loss_spread_pct": {
                        "scalar_1t": spread(0),
                        "scalar_all": spread(1),
                        "packet_1t": spread(2),
                        "packet_all": spread(3),
                    },
                })
            }).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
        "table4": {
            "load_s": s.table4.load_s,
            "std_build_s": s.table4.std_build_s,
            "fast_slim_s": s.table4.slim_s[0],
            "small_slim_s": s.table4.slim_s[1],
            "fast_ratio": jnum(s.table4.slim_ratio(0)),
            "small_ratio": jnum(s.table4.slim_ratio(1)),
            "write_s": {
                "std": s.table4.write_s[0],
                "fast": s.table4.write_s[1],
                "small": s.table4.write_s[2],
            },
        },
        "figure5": s.sweep.iter().map(|p| json!({
            "tau_occu": p.tau_occu,
            "tau_freq": p.tau_freq,
            "max_t2rn": p.max_t2rn,
            "tree_bytes": p.tree_bytes,
            "hoisted": p.hoisted,
            "reduction_pct": jnum(p.reduction_pct),
            "loss_pct": jnum(p.loss_pct),
            "loss_q1_pct": jnum(p.loss_spread.q1),
            "loss_q3_pct": jnum(p.loss_spread.q3),
            "within_noise": p.loss_spread.includes_zero(),
            "view_loss_pct": p.view_loss_pct.iter().map(|&x| jnum(x)).collect::<Vec<_>>(),
            "slim_s": p.slim_s,
        })).collect::<Vec<_>>(),
        "figure6": {
            "std": s.leaf_depths[0],
            "fast": s.leaf_depths[1],
            "small": s.leaf_depths[2],
        },
    })
}
