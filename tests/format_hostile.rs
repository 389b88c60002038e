//! Valid-looking files that would make work unbounded: leaf index ranges
//! must cover each index array exactly once, so that a file of a few bytes
//! cannot list the same long range in every leaf.

mod common;

use common::kd::*;
use slimkd::format::node::{self, NodeWord};
use slimkd::format::{FormatError, KdFile, NodeFault, aligned_copy};

/// The node slots of the leaves of `file` with their words, in slot order.
fn leaves(bytes: &[u8]) -> Vec<(usize, NodeWord)> {
    let file = read(bytes);
    file.nodes()
        .iter()
        .enumerate()
        .filter_map(|(i, &w)| match node::decode(w) {
            Ok(l @ (NodeWord::Leaf16 { .. } | NodeWord::Leaf32 { .. })) => Some((i, l)),
            _ => None,
        })
        .collect()
}

fn encode(w: NodeWord) -> u64 {
    match w {
        NodeWord::Leaf16 {
            count,
            upper,
            start,
        } => node::encode_leaf16(count, upper, start),
        NodeWord::Leaf32 { count, start } => node::encode_leaf32(count, start),
        _ => unreachable!("a leaf"),
    }
}

/// The file with leaf `w` at `slot`: it opens (the open reads no node) and
/// traces; the result is what the full check says.
fn with_leaf(bytes: &[u8], slot: usize, w: NodeWord) -> Result<(), FormatError> {
    let mut b = bytes.to_vec();
    set_word(&mut b, slot, encode(w));
    fix_all_crcs(&mut b);
    let file = KdFile::from_bytes(aligned_copy(&b)).expect("the header is intact");
    let mut rng = Rng(5);
    for ray in rays_at(&file.bounds(), &mut rng, 64) {
        std::hint::black_box(slimkd::trace::traverse(&file, &ray));
    }
    file.validate()
}

#[test]
fn leaf_ranges_must_not_overlap_or_leave_gaps() {
    for reorder in [false, true] {
        let scene = load_scene("bunny_npm.obj");
        let bytes = write(&std_tree(&scene), &scene, reorder);
        let leaves = leaves(&bytes);
        // Two non-empty leaves of the same mode.
        let full: Vec<_> = leaves
            .iter()
            // At least 3 indices: one fewer is still a leaf with an index
            // list (a one-triangle leaf has none).
            .filter(|(_, w)| matches!(w, NodeWord::Leaf16 { count, .. } | NodeWord::Leaf32 { count, .. } if *count >= 3))
            .collect();
        let (a, b) = full
            .iter()
            .flat_map(|a| full.iter().map(move |b| (*a, *b)))
            .find(|((_, x), (_, y))| {
                std::mem::discriminant(x) == std::mem::discriminant(y) && x != y
            })
            .expect("two leaves of one mode");
        // Leaf b lists leaf a's range: an overlap (and b's own range is left
        // unlisted).
        let b_as_a = match (a.1, b.1) {
            (
                NodeWord::Leaf16 {
                    count,
                    upper,
                    start,
                },
                NodeWord::Leaf16 { .. },
            ) => NodeWord::Leaf16 {
                count,
                upper,
                start,
            },
            (NodeWord::Leaf32 { count, start }, NodeWord::Leaf32 { .. }) => {
                NodeWord::Leaf32 { count, start }
            }
            _ => unreachable!(),
        };
        let e = with_leaf(&bytes, b.0, b_as_a).unwrap_err().to_string();
        assert!(e.contains("overlaps"), "{e}");
        // A leaf that lists one index fewer leaves a gap.
        let shorter = match b.1 {
            NodeWord::Leaf16 {
                count,
                upper,
                start,
            } => NodeWord::Leaf16 {
                count: count - 1,
                upper,
                start,
            },
            NodeWord::Leaf32 { count, start } => NodeWord::Leaf32 {
                count: count - 1,
                start,
            },
            _ => unreachable!(),
        };
        let e = with_leaf(&bytes, b.0, shorter).unwrap_err().to_string();
        assert!(e.contains("no leaf lists"), "{e}");
        // The unchanged file is still valid (the checks accept the writer's
        // layout).
        assert!(with_leaf(&bytes, b.0, b.1).is_ok());
    }
}

/// A mapped file rewritten in place after it was opened can hold anything:
/// here every inner node's right slot points at itself or backwards (a
/// loop) and every leaf lists a range past its index array or a triangle
/// past the last. The traversers read such a right child as empty and
/// such leaves as empty, so a ray ends (it would spin forever on the loop)
/// and never hits or panics.
#[test]
fn a_mapped_file_changed_in_place_never_loops() {
    use slimkd::format::Section;
    use slimkd::geom::Ray;
    use slimkd::trace::packet::PacketTracer;
    use slimkd::trace::{ClosestHit, Hit, Scalar};
    use std::os::unix::fs::FileExt;

    let mut rng = Rng(7);
    let scene = random_small_scene(&mut rng, 300, 4);
    let bytes = write(&std_tree(&scene), &scene, false);
    let dir = common::fresh_temp_dir("changed_in_place");
    let path = dir.join("t.kd");
    std::fs::write(&path, &bytes).unwrap();
    let file = KdFile::open(&path, slimkd::format::Check::Verify).unwrap();
    let nodes = section(&bytes, Section::Nodes);
    let mut changed = bytes.clone();
    let (mut loops, mut leaves) = (0, 0);
    for (i, at) in nodes.clone().step_by(8).enumerate() {
        let w = get_u64(&changed, at);
        let new = match w & node::A_MASK {
            node::A_LEAF => {
                leaves += 1;
                w | (0xffff_ff00u64 << 32)
            }
            node::A_TREF => w,
            _ => {
                loops += 1;
                // Itself, or the slot before (the root: itself).
                let to = if i % 2 == 0 { i } else { i - 1 };
                (w & !(0x1fff_ffffu64 << 3)) | ((to as u64) << 3)
            }
        };
        set_u64(&mut changed, at, new);
    }
    assert!(
        loops > 10 && leaves > 10,
        "{loops} inner nodes, {leaves} leaves"
    );
    std::fs::OpenOptions::new()
        .write(true)
        .open(&path)
        .unwrap()
        .write_all_at(&changed[nodes.clone()], nodes.start as u64)
        .unwrap();
    assert_eq!(
        file.nodes()[0],
        get_u64(&changed, nodes.start),
        "the map shows the change"
    );
    let (done, finished) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let b = file.bounds();
        let rays: Vec<Ray> = (0..16)
            .map(|i| {
                let o = b.min - (b.max - b.min) * 0.5;
                let t = b.min + (b.max - b.min) * (0.2 + 0.04 * i as f32);
                Ray::new(o, (t - o).normalize())
            })
            .collect();
        let single: Vec<Hit> = rays
            .iter()
            .map(|r| Scalar::new(&file).closest_hit(r))
            .collect();
        let mut packet = vec![Hit::MISS; 16];
        PacketTracer::new(&file).closest_hit_n(&rays, &mut packet);
        let mut any = vec![false; 16];
        PacketTracer::new(&file).occluded_n(&rays, &mut any);
        done.send((single, packet, any)).unwrap();
    });
    let (single, packet, any) = finished
        .recv_timeout(std::time::Duration::from_secs(10))
        .expect("traversal of the changed file ended within 10 s");
    // Every walk goes down left children to a leaf that holds nothing.
    assert!(single.iter().chain(&packet).all(|h| !h.is_hit()));
    assert!(any.iter().all(|&a| !a));
    std::fs::remove_dir_all(&dir).ok();
}

/// `KdFile::read` (the CLI's `--no-mmap`) holds the file in memory: the
/// file truncated on disk afterwards (which a map answers with SIGBUS)
/// changes nothing, and it traces as the mapped file did.
#[test]
fn a_file_read_into_memory_survives_truncation() {
    use slimkd::geom::Ray;
    use slimkd::trace::{ClosestHit, Hit, Scalar};

    let mut rng = Rng(11);
    let scene = random_small_scene(&mut rng, 300, 4);
    let bytes = write(&std_tree(&scene), &scene, false);
    let dir = common::fresh_temp_dir("read_into_memory");
    let path = dir.join("t.kd");
    std::fs::write(&path, &bytes).unwrap();
    let trace = |file: &KdFile<slimkd::format::Mapped>| -> Vec<Hit> {
        let b = file.bounds();
        (0..64)
            .map(|i| {
                let o = b.min - (b.max - b.min) * 0.5;
                let t = b.min + (b.max - b.min) * (0.1 + 0.0125 * i as f32);
                Scalar::new(file).closest_hit(&Ray::new(o, (t - o).normalize()))
            })
            .collect()
    };
    let mapped = trace(&KdFile::open(&path, slimkd::format::Check::Verify).unwrap());
    assert!(mapped.iter().any(|h| h.is_hit()));
    let read = KdFile::read(&path, slimkd::format::Check::Verify).unwrap();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&path)
        .unwrap()
        .set_len(0)
        .unwrap();
    assert_eq!(trace(&read), mapped);
    assert!(
        KdFile::read(&path, slimkd::format::Check::Header).is_err(),
        "the truncated file is refused"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A file of a few words whose slot fields make a DAG (node `j`'s children
/// are nodes `j + 1` and `j + 2`, so 60 nodes have Fib(60) ≈ 2^40 paths),
/// with counts that add up: it opens (the open reads no node), every
/// traverser and the depth histogram stop after `2 · words + 1` steps
/// (without that bound a ray in every split plane walks all 2^40 paths),
/// wide boxes are refused, and the full check refuses it: every node must lie where its parent's
/// pre-order says.
#[test]
fn shared_subtrees_end_at_the_step_limit_and_are_refused_by_validate() {
    use slimkd::geom::Ray;
    use slimkd::trace::packet::{PacketTracer, SimdLevel};
    use slimkd::trace::{self, Hit, TraceStats};

    let scene = strip_scene(2);
    let template = write(
        &strip_tree(&scene, &[vec![0], vec![1]], false),
        &scene,
        false,
    );
    let k = 60u64;
    let pos = 0.75f32;
    let mut nodes: Vec<u64> = (0..k)
        .map(|j| node::encode_inner(0, false, j as u32 + 2, pos))
        .collect();
    nodes.extend([node::encode_leaf1(0), node::encode_leaf1(1)]);
    let mut sections =
        slimkd::format::Section::ALL.map(|s| template[section(&template, s)].to_vec());
    sections[0] = nodes.iter().flat_map(|w| w.to_le_bytes()).collect();
    let mut b = template.clone();
    // k inner nodes, k + 1 leaves, k + 2 words: k - 1 empty leaves
    // without a word, two one-triangle leaves.
    set_u64(&mut b, H_WORDS, k + 2);
    set_u64(&mut b, H_INNER, k);
    set_u64(&mut b, H_LEAVES, k + 1);
    set_u64(&mut b, H_IMPLICIT_EMPTY, k - 1);
    set_u64(&mut b, H_ONE_LEAVES, 2);
    set_u32(&mut b, H_MAX_DEPTH, k as u32 + 1);
    let b = with_sections(&b, &sections);
    let file = KdFile::from_bytes(aligned_copy(&b)).expect("the header is intact");
    let limit = 2 * (k + 2) + 1;
    // Rays that start in every split plane (x = 0.75) go down both
    // children of every node, and miss both triangles, so nothing cuts
    // the walk short.
    let rays: Vec<Ray> = (0..16)
        .map(|i| {
            let o = glam::Vec3::new(pos, -1.0, 0.03 * i as f32);
            Ray::new(o, glam::Vec3::Y)
        })
        .collect();
    for any in [false, true] {
        let mut stats = TraceStats::default();
        let hit = trace::traverse_counted(&file, &rays[0], any, &mut stats);
        assert!(!hit.is_hit());
        assert_eq!(stats.nodes, limit, "any {any}: the walk ends at the limit");
        for level in SimdLevel::available() {
            let mut out = [Hit::MISS; 16];
            let mut stats = TraceStats::default();
            PacketTracer::with_level(&file, level).trace_counted(&rays, any, &mut out, &mut stats);
            assert!(out.iter().all(|h| !h.is_hit()), "{level:?}");
            // One octant of 16 lanes: 16 limits at most, one per lane.
            assert!(
                (limit..=16 * limit).contains(&stats.nodes),
                "{level:?}, any {any}: {} steps",
                stats.nodes
            );
        }
    }
    for level in SimdLevel::available() {
        let mut occ = [true; 16];
        trace::lanes::occluded_lanes(trace::FileWalk::new(&file), level, &rays, &mut occ);
        assert_eq!(occ, [false; 16], "lanes, {level:?}");
    }
    let leaves: u64 = file.leaf_depth_histogram().iter().sum();
    assert!(leaves <= limit, "{leaves} leaves counted");
    // Wide boxes are refused rather than built over 2^40 paths.
    use slimkd::trace::KdSource;
    assert!(slimkd::trace::wide::WideBoxes::new(file.walk()).is_err());
    match file.validate() {
        Err(FormatError::Node { fault, .. }) => {
            assert!(matches!(fault, NodeFault::NotPreOrder { .. }), "{fault}")
        }
        Err(e) => panic!("wrong error: {e}"),
        Ok(()) => panic!("a DAG passed the full check"),
    }
    // The same words as a tree (each right child an empty leaf without a
    // word, the last node's two leaves): valid, so the refusal above is
    // the DAG's.
    let mut tree_nodes: Vec<u64> = (0..k - 1)
        .map(|_| node::encode_inner(0, false, 0, pos))
        .collect();
    tree_nodes.push(node::encode_inner(0, false, k as u32 + 1, pos));
    tree_nodes.extend([node::encode_leaf1(0), node::encode_leaf1(1)]);
    sections[0] = tree_nodes.iter().flat_map(|w| w.to_le_bytes()).collect();
    let t = with_sections(&b, &sections);
    let file = KdFile::from_bytes_checked(aligned_copy(&t)).unwrap();
    file.verify().unwrap();
}

/// A reordered file whose triangle map points past the triangles (its
/// checksums repaired) opens, and every hit it gives names a triangle of
/// the file (the entry's own file id), so a caller that looks the hit's
/// triangle up (shading, `Accel::triangle`) cannot index out of range; the
/// full check refuses it.
#[test]
fn a_triangle_map_out_of_range_still_gives_ids_of_the_file() {
    use slimkd::format::Section;
    use slimkd::trace::packet::PacketTracer;
    use slimkd::trace::{ClosestHit, Hit};

    let mut rng = Rng(9);
    let scene = random_small_scene(&mut rng, 300, 4);
    let mut b = write(&std_tree(&scene), &scene, true);
    let map = section(&b, Section::TriMap);
    for at in map.step_by(4) {
        set_u32(&mut b, at, u32::MAX - 1);
    }
    fix_all_crcs(&mut b);
    let file = KdFile::from_bytes(aligned_copy(&b)).expect("the header is intact");
    let n = file.figures().triangles as u32;
    let rays = rays_at(&file.bounds(), &mut rng, 256);
    let single: Vec<Hit> = rays
        .iter()
        .map(|r| slimkd::trace::traverse(&file, r))
        .collect();
    let mut packet = vec![Hit::MISS; rays.len()];
    for (rays, out) in rays.chunks(16).zip(packet.chunks_mut(16)) {
        PacketTracer::new(&file).closest_hit_n(rays, out);
    }
    assert!(single.iter().any(|h| h.is_hit()));
    for h in single.iter().chain(&packet).filter(|h| h.is_hit()) {
        assert!(h.tri.0 < n, "hit id {} of {n} triangles", h.tri.0);
    }
    assert!(matches!(
        file.validate(),
        Err(FormatError::Index {
            section: "tri_map",
            ..
        })
    ));
}
