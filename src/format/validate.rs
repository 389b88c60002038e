//! [`KdFile::validate`]: the checks of a file's sections, in named steps
//! (the nodes in one pre-order pass, the index arrays' coverage, the
//! header's counts, the indices, the geometry).

use super::node::{self, LEAF16_LIMIT, NodeWord};
use super::{FormatError, HeaderError, KdFile, NodeFault, TreeFigures};
use crate::geom::Aabb;
use crate::tree::MAX_DEPTH;
use glam::Vec3;

/// Which positions of an index array leaves have claimed: one bit each,
/// claimed a 64-bit word at a time.
struct Coverage {
    bits: Vec<u64>,
    len: u64,
    claimed: u64,
}

impl Coverage {
    fn new(len: u64) -> Coverage {
        Coverage {
            bits: vec![0; len.div_ceil(64) as usize],
            len,
            claimed: 0,
        }
    }

    /// Claims `start..start + count` (inside the array); `false` if a
    /// position in it was claimed before.
    fn claim(&mut self, start: u64, count: u64) -> bool {
        let end = start + count;
        let mut at = start;
        while at < end {
            let word = (at / 64) as usize;
            let lo = at % 64;
            let hi = (end - word as u64 * 64).min(64);
            let mask = (u64::MAX >> (64 - (hi - lo))) << lo;
            if self.bits[word] & mask != 0 {
                return false;
            }
            self.bits[word] |= mask;
            at = word as u64 * 64 + hi;
        }
        self.claimed += count;
        true
    }

    fn is_full(&self) -> bool {
        self.claimed == self.len
    }
}

/// The node expected next in the pre-order pass: its slot, cell, depth,
/// and whether it may be an empty leaf word.
struct Expect {
    slot: u64,
    cell: Aabb,
    depth: u32,
    may_be_empty: bool,
}

fn node_err(index: u64, fault: NodeFault) -> FormatError {
    FormatError::Node { index, fault }
}

/// The state of the pass over the nodes: what it counted so far, and the
/// index positions the leaves claimed.
struct NodePass<'a> {
    words: &'a [u64],
    idx16: &'a [u16],
    n_tris: u64,
    /// The header's maximum depth.
    max_depth: u32,
    /// Counted as the header counts (`words`, `triangles` and the other
    /// fields of the sections stay 0).
    seen: TreeFigures,
    /// The leaves' index ranges cover each index array exactly once, as
    /// the writer lays them out: so the work of any traversal (and of
    /// `info`) is bounded by the file's size, whatever its splits.
    cover32: Coverage,
    cover16: Coverage,
}

impl NodePass<'_> {
    /// Checks the inner node word at `i` (its axis, its split inside the
    /// cell, its depth, its T-reference) and pushes its children's
    /// expectations; returns the slot of the left child.
    fn inner(
        &mut self,
        i: usize,
        e: &Expect,
        (axis, t_ref, right, pos): (u8, bool, u32, f32),
        pending: &mut Vec<Expect>,
    ) -> Result<usize, FormatError> {
        if axis > 2 {
            return Err(node_err(i as u64, NodeFault::Axis(3)));
        }
        let k = usize::from(axis);
        let cell = e.cell;
        if !(pos >= cell.min[k] && pos <= cell.max[k]) {
            return Err(node_err(
                i as u64,
                NodeFault::SplitOutsideCell {
                    pos,
                    axis: k,
                    min: cell.min[k],
                    max: cell.max[k],
                },
            ));
        }
        let depth = e.depth + 1;
        if depth > MAX_DEPTH || depth > self.max_depth {
            return Err(node_err(i as u64, NodeFault::TooDeep));
        }
        if t_ref {
            self.t_reference(i)?;
            self.seen.t_inner += 1;
        } else {
            self.seen.inner += 1;
        }
        let first = i as u64 + 1 + u64::from(t_ref);
        let (left_cell, right_cell) = cell.split(k, pos);
        let child = |slot: u64, cell: Aabb, may_be_empty: bool| Expect {
            slot,
            cell,
            depth,
            may_be_empty,
        };
        let right = u64::from(right);
        if right == 0 {
            // The right child is empty; the left one has a word, which may
            // be an empty leaf (both children empty).
            self.seen.leaves += 1;
            self.seen.implicit_empty += 1;
            pending.push(child(first, left_cell, true));
        } else if right == first {
            self.seen.leaves += 1;
            self.seen.implicit_empty += 1;
            pending.push(child(first, right_cell, false));
        } else if right > first {
            pending.push(child(right, right_cell, false));
            pending.push(child(first, left_cell, false));
        } else {
            return Err(node_err(i as u64, NodeFault::RightChildNotAfter(right)));
        }
        Ok(first as usize)
    }

    /// Checks the T-reference word after the type II node at `i`.
    fn t_reference(&self, i: usize) -> Result<(), FormatError> {
        let n_tris = self.n_tris;
        match self.words.get(i + 1).map(|&t| node::decode(t)) {
            Some(Ok(NodeWord::TRef { tri })) if u64::from(tri) < n_tris => Ok(()),
            Some(Ok(NodeWord::TRef { tri })) => Err(node_err(
                i as u64 + 1,
                NodeFault::TRefOutOfRange {
                    tri: u64::from(tri),
                    n_tris,
                },
            )),
            _ => Err(node_err(i as u64, NodeFault::MissingTRef)),
        }
    }

    /// Checks the leaf (or misplaced T-reference) word at `i`: its
    /// triangle or index range, and that the range claims no index
    /// another leaf claimed.
    fn leaf(&mut self, i: usize, e: &Expect, word: NodeWord) -> Result<(), FormatError> {
        let n_tris = self.n_tris;
        let overlap = |array: &'static str| node_err(i as u64, NodeFault::LeafRangeOverlap(array));
        match word {
            NodeWord::Inner { .. } => unreachable!("inner nodes go to `NodePass::inner`"),
            NodeWord::TRef { .. } => {
                return Err(node_err(i as u64, NodeFault::TRefAsChild));
            }
            NodeWord::Leaf1 { tri } => {
                if u64::from(tri) >= n_tris {
                    return Err(node_err(
                        i as u64,
                        NodeFault::TriangleOutOfRange {
                            tri: u64::from(tri),
                            n_tris,
                        },
                    ));
                }
                self.seen.one_leaves += 1;
            }
            NodeWord::Leaf32 { count, start } => {
                let end = u64::from(start) + u64::from(count);
                if end > self.cover32.len {
                    return Err(node_err(
                        i as u64,
                        NodeFault::LeafRangeOutside {
                            start: u64::from(start),
                            count: u64::from(count),
                            array: "idx32",
                        },
                    ));
                }
                if count == 0 && (start != 0 || !e.may_be_empty) {
                    return Err(node_err(i as u64, NodeFault::EmptyLeafWithWord));
                }
                if count == 1 {
                    return Err(node_err(i as u64, NodeFault::OneTriangleLeafWithIndex));
                }
                if !self.cover32.claim(u64::from(start), u64::from(count)) {
                    return Err(overlap("idx32"));
                }
            }
            NodeWord::Leaf16 {
                count,
                upper,
                start,
            } => {
                let end = u64::from(start) + u64::from(count);
                if count >= LEAF16_LIMIT || end > self.cover16.len {
                    return Err(node_err(
                        i as u64,
                        NodeFault::LeafRangeOutside {
                            start: u64::from(start),
                            count: u64::from(count),
                            array: "idx16",
                        },
                    ));
                }
                if count < 2 {
                    return Err(node_err(i as u64, NodeFault::Leaf16Count(u64::from(count))));
                }
                if !self.cover16.claim(u64::from(start), u64::from(count)) {
                    return Err(overlap("idx16"));
                }
                // Every index of the leaf is `upper << 16 | low`.
                let base = u64::from(upper) << 16;
                if let Some(&low) = self.idx16[start as usize..end as usize]
                    .iter()
                    .find(|&&low| base + u64::from(low) >= n_tris)
                {
                    return Err(node_err(
                        i as u64,
                        NodeFault::TriangleOutOfRange {
                            tri: base + u64::from(low),
                            n_tris,
                        },
                    ));
                }
            }
        }
        self.seen.leaves += 1;
        Ok(())
    }

    /// One pass in pre-order: the node expected next must be the word at
    /// `i`, so every word is one node of one tree, reached once, each
    /// child after its parent; the cells carry every split's bounds.
    fn run(&mut self, root: Aabb) -> Result<(), FormatError> {
        let n = self.words.len() as u64;
        let mut pending = vec![Expect {
            slot: 0,
            cell: root,
            depth: 0,
            may_be_empty: true,
        }];
        let mut i = 0usize;
        while let Some(e) = pending.pop() {
            if e.slot != i as u64 {
                return Err(node_err(
                    i as u64,
                    NodeFault::NotPreOrder {
                        expected: i as u64,
                        slot: e.slot,
                    },
                ));
            }
            let Some(&w) = self.words.get(i) else {
                return Err(node_err(i as u64, NodeFault::ChildSlotOutside(n)));
            };
            let decoded = node::decode(w).map_err(|m| node_err(i as u64, NodeFault::Word(m)))?;
            if let NodeWord::Inner {
                axis,
                t_ref,
                right,
                pos,
            } = decoded
            {
                i = self.inner(i, &e, (axis, t_ref, right, pos), &mut pending)?;
            } else {
                self.leaf(i, &e, decoded)?;
                i += 1;
            }
        }
        if i as u64 != n {
            return Err(node_err(i as u64, NodeFault::Unreferenced));
        }
        Ok(())
    }

    /// Checks that the leaves' ranges cover each index array.
    fn check_coverage(&self) -> Result<(), FormatError> {
        for (cover, array) in [(&self.cover32, "idx32"), (&self.cover16, "idx16")] {
            if !cover.is_full() {
                return Err(FormatError::Index {
                    section: array,
                    position: cover.claimed,
                    message: "indices that no leaf lists".into(),
                });
            }
        }
        Ok(())
    }
}

impl<D: AsRef<[u8]>> KdFile<D> {
    /// Checks the contents of the sections, in one pass over the nodes
    /// and one over the geometry (reads all but the padding): every node
    /// word (known type and mode bits, the nodes one tree in pre-order with
    /// every child where its parent's slot field says, splits inside their
    /// cells, depth at most the header's maximum and [`MAX_DEPTH`]), every
    /// leaf range and index (the ranges covering each index array once),
    /// the header's counts against the nodes, and the geometry
    /// ([`KdFile::validate_geometry`]). Never panics.
    pub fn validate(&self) -> Result<(), FormatError> {
        let counts = self.figures();
        let mut pass = NodePass {
            words: self.nodes(),
            idx16: self.idx16(),
            n_tris: counts.triangles,
            max_depth: self.max_depth(),
            seen: TreeFigures::default(),
            cover32: Coverage::new(counts.idx32),
            cover16: Coverage::new(counts.idx16),
        };
        pass.run(self.bounds())?;
        pass.check_coverage()?;
        Self::check_node_counts(&pass.seen, &counts)?;
        self.check_idx32()?;
        self.validate_geometry()
    }

    /// Checks the header's node counts against those the pass over the
    /// nodes made.
    fn check_node_counts(seen: &TreeFigures, c: &TreeFigures) -> Result<(), FormatError> {
        let s = seen;
        if (s.inner, s.t_inner, s.leaves, s.implicit_empty, s.one_leaves)
            != (c.inner, c.t_inner, c.leaves, c.implicit_empty, c.one_leaves)
        {
            return Err(HeaderError::NodeCounts.into());
        }
        Ok(())
    }

    /// Checks every idx32 entry against the triangle count (the idx16
    /// entries are checked with their leaves, which hold their upper bits).
    fn check_idx32(&self) -> Result<(), FormatError> {
        let n_tris = self.figures().triangles;
        if let Some(p) = self.idx32().iter().position(|&t| u64::from(t) >= n_tris) {
            return Err(FormatError::Index {
                section: "idx32",
                position: p as u64,
                message: format!("triangle {} of {n_tris}", self.idx32()[p]),
            });
        }
        Ok(())
    }

    /// Checks the geometry sections: every vertex index in range, every
    /// coordinate finite, not `-0.0` and inside the header's scene bounds,
    /// and the triangle map a permutation. What [`KdFile::to_columns`]
    /// needs; part of [`KdFile::validate`].
    pub fn validate_geometry(&self) -> Result<(), FormatError> {
        super::check_vertex_indices(self.triangles(), self.figures().vertices)?;
        if let Some(p) = self
            .vertices()
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(FormatError::Index {
                section: "vertices",
                position: p as u64,
                message: "non-finite coordinate".into(),
            });
        }
        self.check_vertices_in_bounds()?;
        if let Some(p) = self
            .vertices()
            .iter()
            .position(|v| v.iter().any(|c| c.to_bits() == (-0.0f32).to_bits()))
        {
            return Err(FormatError::Index {
                section: "vertices",
                position: p as u64,
                message: "coordinate -0.0 (the scene's columns hold +0.0)".into(),
            });
        }
        self.check_tri_map()
    }

    /// The scene bounds are the root cell: a vertex outside it would make
    /// a triangle that brute force hits and no traversal can reach (and a
    /// default camera aimed from the bounds miss the scene). `-0.0` never
    /// leaves the scene's columns (`TriangleColumns` holds none), so a
    /// file holding one was not written from them.
    fn check_vertices_in_bounds(&self) -> Result<(), FormatError> {
        let v = self.vertices();
        let bounds = self.bounds();
        for (t, tri) in self.triangles().iter().enumerate() {
            for &i in tri {
                let p = Vec3::from_array(v[i as usize]);
                if !(p.cmpge(bounds.min).all() && p.cmple(bounds.max).all()) {
                    return Err(FormatError::Index {
                        section: "vertices",
                        position: u64::from(i),
                        message: format!(
                            "vertex {p} of triangle {t} lies outside the header's scene bounds"
                        ),
                    });
                }
            }
        }
        Ok(())
    }

    /// Checks that the triangle map, if any, is a permutation.
    fn check_tri_map(&self) -> Result<(), FormatError> {
        let n_tris = self.figures().triangles;
        if let Some(map) = self.tri_map() {
            let mut seen = vec![false; map.len()];
            for (p, &t) in map.iter().enumerate() {
                if u64::from(t) >= n_tris || std::mem::replace(&mut seen[t as usize], true) {
                    return Err(FormatError::Index {
                        section: "tri_map",
                        position: p as u64,
                        message: "not a permutation of the triangles".into(),
                    });
                }
            }
        }
        Ok(())
    }
}
