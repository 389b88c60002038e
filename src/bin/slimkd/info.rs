//! `slimkd info`, `verify` and `convert`.

use crate::CmdResult;
use crate::args::{OutputFlags, Usage, check_output_dir};
use crate::build::load;
use crate::json::{FileJson, SceneJson, print_json};
use crate::kd_file::{expect_kd, open_kd};
use serde::Serialize;
use slimkd::format::{self, Section};
use slimkd::scene::{self};
use slimkd::stats::bytes::{ByteSplit, paper_layout_bytes_of};
use std::path::Path;
use std::time::Instant;

/// `slimkd convert --json`.
#[derive(Serialize)]
struct ConvertJson {
    #[serde(flatten)]
    scene: SceneJson,
    output: String,
    output_bytes: u64,
    write_s: f64,
}

/// Where a `.kd` file's tree bytes go ([`ByteSplit`]).
#[derive(Serialize)]
struct BytesJson {
    inner: u64,
    t_inner: u64,
    leaves: u64,
    empty_leaves: u64,
    idx32: u64,
    idx16: u64,
    duplicates: u64,
    hoist_bound: u64,
}

/// `slimkd info --json`.
#[derive(Serialize)]
struct InfoJson {
    #[serde(flatten)]
    file: FileJson,
    file_bytes: usize,
    version: u32,
    preset: &'static str,
    k_t: f64,
    k_i: f64,
    lambda_empty: f64,
    depth_limit: u32,
    split_price: f64,
    tau_occu: f32,
    tau_freq: f32,
    max_t2rn: u32,
    reordered: bool,
    tree_bytes_per_triangle: f64,
    paper_layout_bytes: u64,
    paper_layout_bytes_per_triangle: f64,
    empty_leaves_without_word: u64,
    one_triangle_leaves: u64,
    max_depth: u32,
    leaf_depth_histogram: Vec<u64>,
    bytes: BytesJson,
}

/// One section of a verified file.
#[derive(Serialize)]
struct SectionJson {
    name: &'static str,
    offset: usize,
    bytes: usize,
    crc32: String,
}

/// `slimkd verify --json` (of a valid file; an invalid one is an error).
#[derive(Serialize)]
struct VerifyJson {
    #[serde(flatten)]
    file: FileJson,
    valid: bool,
    sections: Vec<SectionJson>,
}

pub(crate) fn cmd_convert(scene: &Path, output: &Path, ui: OutputFlags) -> CmdResult<()> {
    if !scene::is_scene_cache(output) {
        return Err(Usage(format!(
            "{}: a scene cache's name must end in .kds (that is how commands recognise it)",
            output.display()
        ))
        .into());
    }
    check_output_dir(output)?;
    let loaded = load(scene, ui.bars_off())?;
    let start = Instant::now();
    scene::write_scene_cache(output, &loaded.scene, &loaded.summary)?;
    let write_s = start.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(output).map(|m| m.len()).unwrap_or(0);
    if ui.json {
        return print_json(
            "convert",
            ConvertJson {
                scene: SceneJson::of(&loaded),
                output: output.display().to_string(),
                output_bytes: bytes,
                write_s,
            },
        );
    }
    if ui.quiet {
        return Ok(());
    }
    println!("scene:   {} ({})", loaded.path.display(), loaded.summary);
    println!("load:    {:.3} s", loaded.seconds);
    println!(
        "written: {} ({:.1} MiB) in {write_s:.3} s",
        output.display(),
        bytes as f64 / (1 << 20) as f64
    );
    if ui.verbose {
        println!(
            "columns: {} positions ({} bytes), {} index triples ({} bytes), {} lines read",
            loaded.scene.positions().len(),
            12 * loaded.scene.positions().len(),
            loaded.scene.len(),
            12 * loaded.scene.len(),
            loaded.summary.lines
        );
    }
    Ok(())
}

pub(crate) fn cmd_info(path: &Path, ui: OutputFlags) -> CmdResult<()> {
    expect_kd(path, "info")?;
    let start = Instant::now();
    let file = open_kd(path, format::Check::Header)?;
    let open_ms = start.elapsed().as_secs_f64() * 1e3;
    // The depth histogram and the byte split read every node.
    file.read_ahead();
    let f = file.figures();
    let c = file.config();
    let hist = file.leaf_depth_histogram();
    let split = ByteSplit::of(&file);
    let paper = paper_layout_bytes_of(&f);
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    let per_tri = |b: u64| b as f64 / f.triangles.max(1) as f64;
    if ui.json {
        return print_json(
            "info",
            InfoJson {
                file: FileJson::of(path, &file, open_ms),
                file_bytes: file.as_bytes().len(),
                version: format::VERSION,
                preset: c.preset.name(),
                k_t: c.k_t,
                k_i: c.k_i,
                lambda_empty: c.lambda_empty,
                depth_limit: c.depth_limit,
                split_price: c.split_price,
                tau_occu: c.tau_occu,
                tau_freq: c.tau_freq,
                max_t2rn: c.max_t2rn,
                reordered: file.is_reordered(),
                tree_bytes_per_triangle: per_tri(f.tree_bytes()),
                paper_layout_bytes: paper,
                paper_layout_bytes_per_triangle: per_tri(paper),
                empty_leaves_without_word: f.implicit_empty,
                one_triangle_leaves: f.one_leaves,
                max_depth: file.max_depth(),
                leaf_depth_histogram: hist,
                bytes: BytesJson {
                    inner: split.inner_bytes,
                    t_inner: split.t_inner_bytes,
                    leaves: split.leaf_bytes,
                    empty_leaves: split.empty_leaf_bytes,
                    idx32: split.idx32_bytes,
                    idx16: split.idx16_bytes,
                    duplicates: split.duplicate_bytes,
                    hoist_bound: split.hoist_bound_bytes,
                },
            },
        );
    }
    if ui.quiet {
        return Ok(());
    }
    let b = file.bounds();
    println!(
        "file        {} ({} bytes, format version {})",
        path.display(),
        file.as_bytes().len(),
        format::VERSION
    );
    println!(
        "build       preset {}, K_T {}, K_I {}, λ {}, depth limit {}, split price {}, τ_occu {}, τ_freq {}, max_t2rn {}",
        c.preset.name(),
        c.k_t,
        c.k_i,
        c.lambda_empty,
        c.depth_limit,
        c.split_price,
        c.tau_occu,
        c.tau_freq,
        c.max_t2rn
    );
    println!(
        "scene       {} (geometry hash {:016x}): {} triangles{}, {} vertices, bounds ({}, {}, {}) – ({}, {}, {})",
        c.scene
            .name()
            .map_or_else(|| "name not recorded".to_string(), |n| format!("`{n}`")),
        c.scene.geometry_hash,
        f.triangles,
        if file.is_reordered() {
            " (Morton-reordered)"
        } else {
            ""
        },
        f.vertices,
        b.min.x,
        b.min.y,
        b.min.z,
        b.max.x,
        b.max.y,
        b.max.z
    );
    println!(
        "table 3(a)  inner      t-inner     leaf       total      4-byte idx  2-byte idx  memory (MiB)"
    );
    println!(
        "            {:<10} {:<11} {:<10} {:<10} {:<11} {:<11} {:.2}",
        f.inner,
        f.t_inner,
        f.leaves,
        f.nodes(),
        f.idx32,
        f.idx16,
        mib(f.tree_bytes())
    );
    println!(
        "bytes       tree {} ({:.1} per triangle) in this file's format, geometry {} ({:.1} per triangle)",
        f.tree_bytes(),
        per_tri(f.tree_bytes()),
        f.geometry_bytes(),
        per_tri(f.geometry_bytes())
    );
    println!(
        "paper       this tree in the paper's std layout (Wald 2004: 8-byte nodes, empty leaves and T-references included, 4-byte indices, no reordering): {} ({:.1} per triangle); this file {:.1}% smaller",
        paper,
        per_tri(paper),
        100.0 * (1.0 - f.tree_bytes() as f64 / paper.max(1) as f64)
    );
    let pct = |b: u64| 100.0 * b as f64 / split.total().max(1) as f64;
    println!(
        "split       inner {:.1}%, t-inner + T-ref {:.1}%, leaves {:.1}%, empty leaves {:.1}%, idx32 {:.1}%, idx16 {:.1}%",
        pct(split.inner_bytes),
        pct(split.t_inner_bytes),
        pct(split.leaf_bytes),
        pct(split.empty_leaf_bytes),
        pct(split.idx32_bytes),
        pct(split.idx16_bytes)
    );
    println!(
        "bound       with the nodes unchanged: duplicate references {} bytes ({:.1}%), hoisting saves at most {} bytes ({:.1}%)",
        split.duplicate_bytes,
        pct(split.duplicate_bytes),
        split.hoist_bound_bytes,
        pct(split.hoist_bound_bytes)
    );
    println!("depth       max {}; leaves per depth:", file.max_depth());
    let peak = hist.iter().copied().max().unwrap_or(1).max(1);
    for (d, &n) in hist.iter().enumerate() {
        if n > 0 {
            let bar = "#".repeat(((n as f64 / peak as f64) * 50.0).ceil() as usize);
            println!("            {d:>3} {n:>10} {bar}");
        }
    }
    if ui.verbose {
        print_sections(&file);
    }
    println!("open        {open_ms:.3} ms (mmap + header check)");
    Ok(())
}

/// The section table: each section's offset, length and stored CRC-32.
fn print_sections<D: AsRef<[u8]>>(file: &format::KdFile<D>) {
    for s in Section::ALL {
        let (range, crc) = file.section_range(s);
        println!(
            "section     {:<9} at {:>10}, {:>10} bytes, CRC-32 {crc:08x}",
            s.name(),
            range.start,
            range.len()
        );
    }
}

pub(crate) fn cmd_verify(path: &Path, ui: OutputFlags) -> CmdResult<()> {
    expect_kd(path, "verify")?;
    let start = Instant::now();
    let file = open_kd(path, format::Check::Verify)?;
    let open_ms = start.elapsed().as_secs_f64() * 1e3;
    let f = file.figures();
    if ui.json {
        return print_json(
            "verify",
            VerifyJson {
                file: FileJson::of(path, &file, open_ms),
                valid: true,
                sections: Section::ALL
                    .iter()
                    .map(|&s| {
                        let (range, crc) = file.section_range(s);
                        SectionJson {
                            name: s.name(),
                            offset: range.start,
                            bytes: range.len(),
                            crc32: format!("{crc:08x}"),
                        }
                    })
                    .collect(),
            },
        );
    }
    if ui.quiet {
        return Ok(());
    }
    println!(
        "{}: ok ({} nodes, {} triangles, all checksums match)",
        path.display(),
        f.nodes(),
        f.triangles
    );
    if ui.verbose {
        print_sections(&file);
    }
    Ok(())
}
