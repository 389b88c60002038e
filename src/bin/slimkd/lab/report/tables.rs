//! The tables' measurements: Table 1 from a tree, Table 3(b) over the
//! views, and one point of the Figure 5 sweep.

use super::*;
use slimkd::pipeline::Pipeline;

/// The two thread pools: one thread and all threads.
pub(super) struct Pools {
    pub(super) one: rayon::ThreadPool,
    pub(super) all: rayon::ThreadPool,
}

impl Pools {
    pub(super) fn get(&self, all: bool) -> &rayon::ThreadPool {
        if all { &self.all } else { &self.one }
    }
}

/// A tree written and opened again.
pub(super) struct Written {
    pub(super) file: KdFile<AlignedBytes>,
    pub(super) seconds: f64,
}

/// Serialises a tree (reordered) and opens the bytes.
pub(super) fn write_tree(
    name: &str,
    label: &str,
    tree: &TreeIr,
    scene: &TriangleColumns,
    pipeline: &Pipeline,
) -> Result<Written, ReportError> {
    let err = |source| ReportError::Format {
        scene: name.to_string(),
        tree: label.to_string(),
        source,
    };
    let start = Instant::now();
    let bytes = format::write_to_vec(tree, scene, &pipeline.write_options(scene)).map_err(err)?;
    let seconds = start.elapsed().as_secs_f64();
    let file = KdFile::from_bytes(format::aligned_copy(&bytes)).map_err(err)?;
    Ok(Written { file, seconds })
}

/// Table 1 for a tree: how many leaves hold each triangle, in intervals.
pub fn duplication(tree: &TreeIr, scene: &TriangleColumns) -> Duplication {
    let mut leaves_of = vec![0u64; scene.len()];
    let mut total = 0u64;
    for node in &tree.nodes {
        if let Node::Leaf { start, count } = *node {
            for t in tree.leaf(start, count) {
                leaves_of[t.0 as usize] += 1;
            }
            total += u64::from(count);
        }
    }
    // Interval 0 is "in no leaf"; then the paper's intervals and the rest.
    let mut uppers = vec![0u64];
    uppers.extend_from_slice(&DUPLICATION_BOUNDS);
    let n_bins = uppers.len() + 1;
    let mut counts = vec![0u64; n_bins];
    let mut edge_sums = vec![0f64; n_bins];
    for (t, &n) in leaves_of.iter().enumerate() {
        let bin = uppers.partition_point(|&u| u < n);
        let [a, b, c] = scene.tri(t as u32);
        let (a, b, c) = (a.as_dvec3(), b.as_dvec3(), c.as_dvec3());
        let longest = (b - a).length().max((c - b).length()).max((a - c).length());
        counts[bin] += 1;
        edge_sums[bin] += longest;
    }
    let bins = (0..n_bins)
        .filter(|&i| i > 0 || counts[0] > 0)
        .map(|i| DuplicationBin {
            lo: if i == 0 { 0 } else { uppers[i - 1] + 1 },
            hi: uppers.get(i).copied(),
            triangles: counts[i],
            mean_longest_edge: if counts[i] > 0 {
                edge_sums[i] / counts[i] as f64
            } else {
                f64::NAN
            },
        })
        .collect();
    Duplication {
        bins,
        total_indices: total,
        triangles: scene.len() as u64,
    }
}

/// Checks one frame's hits against the reference frame of its view.
pub(super) fn check_hits(
    reference: &[Hit],
    got: &render::HitBuffer,
    what: impl FnOnce() -> String,
) -> Result<(), ReportError> {
    if got.hits.as_slice() == reference {
        return Ok(());
    }
    let first = reference
        .iter()
        .zip(&got.hits)
        .position(|(a, b)| a != b)
        .unwrap_or(0);
    Err(ReportError::Mismatch(format!(
        "{}: {} hits (checksum {}) against std's {} (checksum {}); first differing pixel {first}",
        what(),
        got.n_hits(),
        got.checksum(),
        reference.iter().filter(|h| h.t.is_finite()).count(),
        reference
            .iter()
            .filter(|h| h.t.is_finite())
            .fold(0.0, |s, h| s + f64::from(h.t)),
    )))
}

/// The loss in % of each repetition's rate against the reference's rate of
/// the same repetition.
fn paired_loss(rates: &[f64], reference: &[f64]) -> Vec<f64> {
    rates
        .iter()
        .zip(reference)
        .map(|(&r, &s)| percent_below(r, s))
        .collect()
}

/// Table 3(b) for one scene: every view, mode and thread count; the trees'
/// frames interleaved within each repetition so that drift in the machine's
/// speed touches all trees alike.
pub(super) fn measure_views(
    name: &str,
    cams: &[(String, Camera)],
    files: &[&KdFile<AlignedBytes>; 3],
    pools: &Pools,
    reps: usize,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<ViewRates>, ReportError> {
    let scalars: Vec<Scalar<'_, KdFile<AlignedBytes>>> =
        files.iter().map(|f| Scalar::new(*f)).collect();
    let packets: Vec<PacketTracer<'_, KdFile<AlignedBytes>>> =
        files.iter().map(|f| PacketTracer::new(*f)).collect();
    let mut out = Vec::new();
    for (id, cam) in cams {
        let reference = pools.one.install(|| render::trace_frame(&scalars[0], cam));
        let mut rates = [Rates::default(); 3];
        let mut loss = [[Spread::default(); 4]; 3];
        for packet in [false, true] {
            for all in [false, true] {
                let pool = pools.get(all);
                let threads = pool.current_num_threads();
                let mode = if packet { "packet" } else { "scalar" };
                progress(&format!(
                    "{name}: tracing view {id} ({mode}, {threads} thread{})",
                    if threads == 1 { "" } else { "s" }
                ));
                let tracers: Vec<&dyn ClosestHit> = if packet {
                    packets.iter().map(|t| t as &dyn ClosestHit).collect()
                } else {
                    scalars.iter().map(|t| t as &dyn ClosestHit).collect()
                };
                let mut samples: [Vec<f64>; 3] = Default::default();
                // One warm-up frame per tree, then the timed ones; each
                // repetition starts with the next tree, so that no tree
                // always follows the same one.
                for rep in 0..=reps {
                    for j in 0..TreeKind::ALL.len() {
                        let k = (rep + j) % TreeKind::ALL.len();
                        let buf = pool.install(|| render::trace_frame(tracers[k], cam));
                        check_hits(&reference.hits, &buf, || {
                            format!(
                                "{name} view {id}: the {} tree, {mode}, {threads} threads",
                                TreeKind::ALL[k].name()
                            )
                        })?;
                        if rep > 0 {
                            samples[k].push(buf.mrays_per_s());
                        }
                    }
                }
                let column = 2 * usize::from(packet) + usize::from(all);
                for k in 0..3 {
                    *rates[k].slot(packet, all) = median(&samples[k]);
                    loss[k][column] = Spread::of(&paired_loss(&samples[k], &samples[0]));
                }
            }
        }
        out.push(ViewRates {
            view: id.clone(),
            hits: reference.n_hits(),
            checksum: reference.checksum(),
            rates,
            loss,
        });
    }
    Ok(out)
}

/// One point of the sweep: a slim tree with the given thresholds against
/// std, packets on all threads.
#[allow(clippy::too_many_arguments)]
pub(super) fn sweep_point(
    name: &str,
    scene: &TriangleColumns,
    std_tree: &TreeIr,
    std_file: &KdFile<AlignedBytes>,
    pipeline: &Pipeline,
    params: SlimParams,
    cams: &[(String, Camera)],
    pools: &Pools,
    reps: usize,
) -> Result<SweepPoint, ReportError> {
    let start = Instant::now();
    let pipeline = pipeline.slimmed(Some(params), Preset::Custom);
    let slimmed = pools.all.install(|| pipeline.slim(std_tree, scene, None));
    let (tree, slim_report, _) = slimmed.expect("the pipeline has a slim pass");
    let slim_s = start.elapsed().as_secs_f64();
    let label = format!("τ_occu {} τ_freq {}", params.tau_occu, params.tau_freq);
    let written = write_tree(name, &label, &tree, scene, &pipeline)?;
    drop(tree);
    let std_tracer = PacketTracer::new(std_file);
    let tracer = PacketTracer::new(&written.file);
    let mut view_loss_pct = Vec::new();
    let mut all_losses = Vec::new();
    for (id, cam) in cams {
        let (mut std_rates, mut rates) = (Vec::new(), Vec::new());
        for rep in 0..=reps {
            // The two trees alternate which goes first.
            let (first, second) = if rep % 2 == 0 {
                (&std_tracer, &tracer)
            } else {
                (&tracer, &std_tracer)
            };
            let x = pools.all.install(|| render::trace_frame(first, cam));
            let y = pools.all.install(|| render::trace_frame(second, cam));
            let (a, b) = if rep % 2 == 0 { (x, y) } else { (y, x) };
            check_hits(&a.hits, &b, || {
                format!("{name} view {id}: the {label} tree")
            })?;
            if rep > 0 {
                std_rates.push(a.mrays_per_s());
                rates.push(b.mrays_per_s());
            }
        }
        let losses = paired_loss(&rates, &std_rates);
        view_loss_pct.push(median(&losses));
        all_losses.extend(losses);
    }
    let tree_bytes = written.file.figures().tree_bytes();
    Ok(SweepPoint {
        tau_occu: params.tau_occu,
        tau_freq: params.tau_freq,
        max_t2rn: params.max_t2rn,
        tree_bytes,
        hoisted: slim_report.hoisted,
        reduction_pct: percent_below(tree_bytes as f64, std_file.figures().tree_bytes() as f64),
        loss_pct: median(&view_loss_pct),
        loss_spread: Spread::of(&all_losses),
        view_loss_pct,
        slim_s,
    })
}
