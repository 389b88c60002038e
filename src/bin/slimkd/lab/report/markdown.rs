//! The report as Markdown: one function per table and figure.

use super::*;
use slimkd::stats::bytes::paper_layout_bytes_of;

/// A number with `prec` decimals, or `–` when it is not finite.
fn num(x: f64, prec: usize) -> String {
    if x.is_finite() {
        format!("{x:.prec$}")
    } else {
        "–".to_string()
    }
}

/// A Markdown table with padded columns; `right[i]` right-aligns column
/// `i`.
fn md_table(header: &[&str], right: &[bool], rows: &[Vec<String>]) -> String {
    let width = |s: &str| s.chars().count();
    let mut w: Vec<usize> = header.iter().map(|h| width(h).max(3)).collect();
    for row in rows {
        for (i, cell) in row.iter().enumerate() {
            w[i] = w[i].max(width(cell));
        }
    }
    let line = |cells: Vec<String>| {
        let mut s = String::from("|");
        for (i, c) in cells.iter().enumerate() {
            let pad = " ".repeat(w[i] - width(c));
            if right[i] {
                s += &format!(" {pad}{c} |");
            } else {
                s += &format!(" {c}{pad} |");
            }
        }
        s + "\n"
    };
    let mut out = line(header.iter().map(|h| h.to_string()).collect());
    out += &line(
        (0..header.len())
            .map(|i| {
                if right[i] {
                    format!("{}:", "-".repeat(w[i] - 1))
                } else {
                    "-".repeat(w[i])
                }
            })
            .collect(),
    );
    for row in rows {
        out += &line(row.clone());
    }
    out
}

impl Report {
    /// The report as Markdown, as written to `report.md` (its figures
    /// linked as `report.figure5.svg`, `report.figure6.svg`): see
    /// [`Report::markdown_for`] (what the tests read).
    #[cfg(test)]
    pub fn markdown(&self) -> String {
        self.markdown_for(Path::new("report.md"))
    }

    /// The report as Markdown to be written to `md_path`: the title, then
    /// one section per table and figure, the figures linked by the names
    /// of [`ReportPaths::for_markdown`] (`report.*` if `md_path` has no
    /// file name).
    pub fn markdown_for(&self, md_path: &Path) -> String {
        let (figure5, figure6) = ReportPaths::for_markdown(md_path)
            .or_else(|_| ReportPaths::for_markdown(Path::new("report.md")))
            .map(|p| p.figure_names())
            .unwrap_or_default();
        let mut md = String::new();
        md += &self.md_intro();
        md += &self.md_table1();
        md += &self.md_table2();
        md += &self.md_table3a();
        md += &self.md_table3b();
        md += &self.md_table4();
        if self.sweep {
            md += &self.md_figure5(&figure5);
        }
        md += &self.md_figure6(&figure6);
        md
    }

    /// The title and the machine figures.
    fn md_intro(&self) -> String {
        let mut md = String::new();
        let names: Vec<&str> = self.scenes.iter().map(|s| s.name.as_str()).collect();
        md += "# slimkd report\n\n";
        md += &format!(
            "The tables and figures of Choi, Chang & Ihm (2013) for {} scene{}: {}.\n\n",
            self.scenes.len(),
            if self.scenes.len() == 1 { "" } else { "s" },
            names.join(", ")
        );
        let preset = |k: TreeKind| k.params(self.rule).expect("a slim tree kind");
        let (fast, small) = (preset(TreeKind::Fast), preset(TreeKind::Small));
        md += &format!(
            "**Machine figures.** Frame rates are the median of {} frame{} (after one warm-up frame) of \
             {}×{} primary rays, one per pixel, on 1 thread and on {} threads; the packet mode traces \
             4×4 rays with the `{}` kernel. Host: {} with {} hardware threads. Trees are built by the \
             level builder (K_T {}, K_I {}, λ {}), written with Morton reordering (2-byte leaves where \
             they fit) and traced from the `.kd` bytes in memory. Presets: fast τ_occu {} τ_freq {}, \
             small τ_occu {} τ_freq {}, max_t2rn {}, rebuilds' K_T ×{} (fast) and ×{} (small), hoist rule `{}`. Percentages are 100·(1 − x/std): a positive \
             reduction is a smaller tree, a positive loss a slower frame.\n\n",
            self.reps,
            if self.reps == 1 { "" } else { "s" },
            self.size.0,
            self.size.1,
            self.all_threads,
            self.simd,
            std::env::consts::ARCH,
            std::thread::available_parallelism().map_or(1, |n| n.get()),
            self.build.sah.k_t,
            self.build.sah.k_i,
            self.build.sah.lambda_empty,
            fast.tau_occu,
            fast.tau_freq,
            small.tau_occu,
            small.tau_freq,
            fast.max_t2rn,
            fast.coarsen,
            small.coarsen,
            rule_name(self.rule),
        );
        md
    }

    /// Table 1: leaves per triangle, one table per scene.
    fn md_table1(&self) -> String {
        let mut md = String::new();
        md += "## Table 1. Leaves per triangle (std tree)\n\n";
        md += "For each triangle, the number of leaves whose list holds it; per interval the number \
               of triangles and their mean longest-edge length (scene units).\n\n";
        for s in &self.scenes {
            md += &format!("### {}\n\n", s.name);
            let rows: Vec<Vec<String>> = s
                .table1
                .bins
                .iter()
                .map(|b| {
                    vec![
                        b.label(),
                        b.triangles.to_string(),
                        num(100.0 * ratio(b.triangles as f64, s.triangles as f64), 2),
                        num(b.mean_longest_edge, 4),
                    ]
                })
                .collect();
            md += &md_table(
                &["leaves", "triangles", "% of triangles", "mean longest edge"],
                &[false, true, true, true],
                &rows,
            );
            md += &format!(
                "\nTotal indices {} for {} triangles: {} per triangle.\n\n",
                s.table1.total_indices,
                s.table1.triangles,
                num(s.table1.ratio(), 3)
            );
        }
        md
    }

    /// Table 2: geometry against the std tree.
    fn md_table2(&self) -> String {
        let mut md = String::new();
        md += "## Table 2. Geometry against the std tree\n\n";
        md += "Geometry as the paper counts it: 12 bytes per triangle and 32 per vertex. *slimkd \
               std*: the std tree as stored, 8 bytes per node, 4 or 2 per leaf index (2-byte leaves \
               applied). *Paper's std*: the same tree in the paper's layout (Wald 2004): 8 bytes per \
               node, empty leaves included, and 4 per leaf reference, no reordering.\n\n";
        let rows: Vec<Vec<String>> = self
            .scenes
            .iter()
            .map(|s| {
                let g = s.paper_geometry_bytes() as f64;
                vec![
                    s.name.clone(),
                    s.triangles.to_string(),
                    s.vertices.to_string(),
                    num(g / MIB, 3),
                    num(s.std_tree_bytes() as f64 / MIB, 3),
                    num(ratio(s.std_tree_bytes() as f64, g), 3),
                    num(s.classic_std_bytes() as f64 / MIB, 3),
                    num(ratio(s.classic_std_bytes() as f64, g), 3),
                ]
            })
            .collect();
        md += &md_table(
            &[
                "scene",
                "triangles",
                "vertices",
                "geometry (MiB)",
                "slimkd std, as stored (MiB)",
                "slimkd std / geometry",
                "paper's std, Wald 2004 layout (MiB)",
                "paper's std / geometry",
            ],
            &[false, true, true, true, true, true, true, true],
            &rows,
        );
        md += "\n";
        md
    }

    /// Table 3(a): tree sizes.
    fn md_table3a(&self) -> String {
        let mut md = String::new();
        md += "## Table 3(a). Tree size\n\n";
        md += "Nodes as the paper counts them (inner, t-inner, leaf); memory is 8·(nodes + \
               T-references) + 4·idx32 + 2·idx16 bytes as stored; *paper layout* is the same tree \
               with 4-byte indices only (Wald 2004: 8·(nodes + T-references) + 4·references). The two \
               baselines: *vs slimkd std* compares with the std tree as stored, in the same format \
               (2-byte leaves applied); *vs paper's std* with the std tree in the paper's layout \
               (Table 2).\n\n";
        let mut rows = Vec::new();
        for s in &self.scenes {
            for row in &s.table3a {
                let f = &row.figures;
                rows.push(vec![
                    s.name.clone(),
                    row.tree.name().to_string(),
                    f.inner.to_string(),
                    f.t_inner.to_string(),
                    f.leaves.to_string(),
                    f.nodes().to_string(),
                    f.idx32.to_string(),
                    f.idx16.to_string(),
                    num(f.tree_bytes() as f64 / MIB, 3),
                    num(paper_layout_bytes_of(f) as f64 / MIB, 3),
                    num(s.reduction_pct(row.tree), 1),
                    num(s.reduction_vs_classic_pct(row.tree), 1),
                ]);
            }
        }
        md += &md_table(
            &[
                "scene",
                "tree",
                "inner",
                "t-inner",
                "leaf",
                "total",
                "4-byte idx",
                "2-byte idx",
                "memory (MiB)",
                "paper layout (MiB)",
                "reduction vs slimkd std, same format (%)",
                "reduction vs paper's std (%)",
            ],
            &[
                false, false, true, true, true, true, true, true, true, true, true, true,
            ],
            &rows,
        );
        md += "\n";
        md
    }

    /// Table 3(b): frame rates and their loss against std.
    fn md_table3b(&self) -> String {
        let mut md = String::new();
        md += "## Table 3(b). Frame rate\n\n";
        md += &format!(
            "Mrays/s (median of {} frames after a warm-up, the trees' frames interleaved, each \
             repetition starting with the next tree); *loss* is the drop against std in the same \
             column, %: the median over the repetitions of each frame's loss against std's frame of \
             the same repetition, with the interquartile range in parentheses; ≈ marks a loss whose \
             range includes 0, which the repetitions do not tell from noise. Every tree and mode \
             gave the same hits as std (checked per pixel).\n\n",
            self.reps
        );
        let all = format!("{}T", self.all_threads);
        let heads = [
            "scalar 1T".to_string(),
            "loss".to_string(),
            format!("scalar {all}"),
            "loss".to_string(),
            "packet 1T".to_string(),
            "loss".to_string(),
            format!("packet {all}"),
            "loss".to_string(),
        ];
        let mut header: Vec<&str> = vec!["scene", "view", "hits", "tree"];
        header.extend(heads.iter().map(String::as_str));
        let mut rows = Vec::new();
        for s in &self.scenes {
            for v in &s.table3b {
                for kind in TreeKind::ALL {
                    let r = v.rates[kind as usize].as_array();
                    let l = v.loss[kind as usize];
                    let mut row = vec![
                        s.name.clone(),
                        v.view.clone(),
                        v.hits.to_string(),
                        kind.name().to_string(),
                    ];
                    for i in 0..4 {
                        row.push(num(r[i], 2));
                        row.push(if kind == TreeKind::Std {
                            String::new()
                        } else {
                            loss_cell(&l[i])
                        });
                    }
                    rows.push(row);
                }
            }
        }
        let mut right = vec![false, false, true, false];
        right.extend([true; 8]);
        md += &md_table(&header, &right, &rows);
        md += "\n";
        md
    }

    /// Table 4: build times.
    fn md_table4(&self) -> String {
        let mut md = String::new();
        md += "## Table 4. Build times\n\n";
        md += "Seconds. A preset's slim pass runs on its own std tree (built at its split price); \
               *ratio* is the preset's build (that tree, then the pass) over the std build. *Write* \
               serialises the tree and geometry to `.kd` bytes in memory.\n\n";
        let rows: Vec<Vec<String>> = self
            .scenes
            .iter()
            .map(|s| {
                let t = &s.table4;
                vec![
                    s.name.clone(),
                    s.triangles.to_string(),
                    num(t.load_s, 3),
                    num(t.std_build_s, 3),
                    num(t.slim_s[0], 3),
                    num(t.slim_ratio(0), 2),
                    num(t.slim_s[1], 3),
                    num(t.slim_ratio(1), 2),
                    num(t.write_s[0], 3),
                    num(t.write_s[1], 3),
                    num(t.write_s[2], 3),
                ]
            })
            .collect();
        md += &md_table(
            &[
                "scene",
                "triangles",
                "load",
                "std build",
                "fast pass",
                "fast ratio",
                "small pass",
                "small ratio",
                "write std",
                "write fast",
                "write small",
            ],
            &[
                false, true, true, true, true, true, true, true, true, true, true,
            ],
            &rows,
        );
        md += "\n";
        md
    }

    /// Figure 5 (with the sweep): the threshold sweep.
    fn md_figure5(&self, file: &str) -> String {
        let mut md = String::new();
        md += "## Figure 5. Threshold sweep\n\n";
        md += &format!(
            "Size reduction against std (same format) and frame-rate loss (packets, {} threads, \
             median over the views of the median per-repetition loss against std, the two trees \
             alternating which goes first) for a τ_occu × τ_freq grid, max_t2rn {SWEEP_MAX_T2RN}. \
             The range is the interquartile range of every view's per-repetition losses (the \
             figure's error bars); ≈ marks a loss whose range includes 0.\n\n\
             ![Figure 5]({file})\n\n",
            self.all_threads
        );
        let mut rows = Vec::new();
        for s in &self.scenes {
            for p in &s.sweep {
                rows.push(vec![
                    s.name.clone(),
                    format!("{}", p.tau_occu),
                    format!("{}", p.tau_freq),
                    p.hoisted.to_string(),
                    num(p.tree_bytes as f64 / MIB, 3),
                    num(p.reduction_pct, 1),
                    num(p.loss_pct, 1),
                    loss_range(&p.loss_spread),
                    num(p.slim_s, 3),
                ]);
            }
        }
        md += &md_table(
            &[
                "scene",
                "τ_occu",
                "τ_freq",
                "hoisted",
                "memory (MiB)",
                "reduction (%)",
                "loss (%)",
                "range (%)",
                "slim pass (s)",
            ],
            &[false, true, true, true, true, true, true, true, true],
            &rows,
        );
        md += "\n";
        md
    }

    /// Figure 6: leaf-depth histograms, one table per scene.
    fn md_figure6(&self, file: &str) -> String {
        let mut md = String::new();
        md += "## Figure 6. Leaf-depth histograms\n\n";
        md += &format!("Leaves per depth (root = 0).\n\n![Figure 6]({file})\n\n");
        for s in &self.scenes {
            md += &format!("### {}\n\n", s.name);
            let depth = s.leaf_depths.iter().map(Vec::len).max().unwrap_or(0);
            let rows: Vec<Vec<String>> = (0..depth)
                .map(|d| {
                    let mut row = vec![d.to_string()];
                    row.extend(
                        s.leaf_depths
                            .iter()
                            .map(|h| h.get(d).copied().unwrap_or(0).to_string()),
                    );
                    row
                })
                .collect();
            md += &md_table(
                &["depth", "std", "fast", "small"],
                &[true, true, true, true],
                &rows,
            );
            md += "\n";
        }
        md
    }
}

/// A loss with its interquartile range, `≈` when the range includes 0.
fn loss_cell(s: &Spread) -> String {
    if !s.median.is_finite() {
        return num(s.median, 1);
    }
    format!("{} {}", num(s.median, 1), loss_range(s))
}

/// An interquartile range, `(q1…q3)`, followed by `≈` when it includes 0.
fn loss_range(s: &Spread) -> String {
    if !(s.q1.is_finite() && s.q3.is_finite()) {
        return String::new();
    }
    format!(
        "({}…{}){}",
        num(s.q1, 1),
        num(s.q3, 1),
        if s.includes_zero() { " ≈" } else { "" }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn md_table_pads_columns() {
        let t = md_table(
            &["a", "bb"],
            &[false, true],
            &[
                vec!["τ_occu".into(), "1".into()],
                vec!["x".into(), "12345".into()],
            ],
        );
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 4);
        let widths: Vec<usize> = lines.iter().map(|l| l.chars().count()).collect();
        assert!(widths.iter().all(|&w| w == widths[0]), "{t}");
        assert!(
            lines[1].ends_with("---: |") || lines[1].ends_with("----: |"),
            "{t}"
        );
    }
}
