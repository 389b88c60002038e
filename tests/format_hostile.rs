//! Valid-looking files that would make work unbounded: leaf index ranges
//! must cover each index array exactly once, so that a file of a few bytes
//! cannot list the same long range in every leaf.

mod common;

use common::kd::*;
use slimkd::format::node::{self, NodeWord};
use slimkd::format::{FormatError, KdFile, aligned_copy};

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

fn with_leaf(bytes: &[u8], slot: usize, w: NodeWord) -> Result<(), FormatError> {
    let mut b = bytes.to_vec();
    set_word(&mut b, slot, encode(w));
    fix_all_crcs(&mut b);
    KdFile::from_bytes(aligned_copy(&b)).map(|_| ())
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
            .filter(|(_, w)| matches!(w, NodeWord::Leaf16 { count, .. } | NodeWord::Leaf32 { count, .. } if *count >= 2))
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
