//! Work pieces: how a level's flat columns are cut for the threads, so that
//! every pass is parallel over elements (events, references), not over
//! nodes (Wu, Zhao & Liu 2011, §4: the top levels have few huge nodes).
//!
//! Consumes the segments (start, length) of the nodes taking part in a
//! pass, in column order. Produces pieces of about `target` elements: a
//! piece holds either several whole nodes or a part of one large node. A
//! large node's parts are consecutive pieces, and where a pass needs
//! counts from the start of the node (the SAH sweep, the stable
//! partitions), it sums the counts of the node's earlier parts: the CPU
//! form of a segmented scan, with one carry per piece instead of one per
//! element. The cut points depend on the data alone, never on the thread
//! count.

use rayon::prelude::*;
use std::ops::{Add, Range};

/// Elements per work piece: large enough that a piece's fixed costs vanish,
/// small enough that the top levels split into many pieces per thread.
pub const PIECE: usize = 1 << 14;

/// A pair of counts with `+`, for carries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Pair(pub [usize; 2]);

impl Add for Pair {
    type Output = Pair;
    fn add(self, o: Pair) -> Pair {
        Pair([self.0[0] + o.0[0], self.0[1] + o.0[1]])
    }
}

/// Part of a pass: the nodes `nodes` (indices into the segment list), and,
/// when it is a part of one node, the element range of that part.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Piece {
    pub nodes: Range<usize>,
    pub part: Option<Range<usize>>,
}

impl Piece {
    /// The element range of node `i` (one of `self.nodes`) in this piece.
    #[inline]
    pub fn range(&self, seg: (usize, usize)) -> Range<usize> {
        match &self.part {
            Some(r) => r.clone(),
            None => seg.0..seg.0 + seg.1,
        }
    }

    /// Whether this piece is a part of a node that does not start the node,
    /// so it needs a carry.
    #[inline]
    pub fn continues(&self, seg: (usize, usize)) -> bool {
        self.part.as_ref().is_some_and(|r| r.start != seg.0)
    }
}

/// Cuts the segments into pieces of about `target` elements. A large
/// segment is cut only before elements `i` with `can_cut(i)` (the SAH sweep
/// must not cut a run of equal positions).
pub fn pieces(
    segs: &[(usize, usize)],
    target: usize,
    can_cut: impl Fn(usize) -> bool,
) -> Vec<Piece> {
    let target = target.max(1);
    let mut out = Vec::new();
    let mut group_start = 0;
    let mut acc = 0;
    for (i, &(start, len)) in segs.iter().enumerate() {
        if len > target {
            if group_start < i {
                out.push(Piece {
                    nodes: group_start..i,
                    part: None,
                });
            }
            let m = len.div_ceil(target);
            let end = start + len;
            let mut from = start;
            for t in 1..m {
                let mut cut = start + t * (len / m) + (t * (len % m)) / m;
                while cut < end && !can_cut(cut) {
                    cut += 1;
                }
                if cut > from && cut < end {
                    out.push(Piece {
                        nodes: i..i + 1,
                        part: Some(from..cut),
                    });
                    from = cut;
                }
            }
            out.push(Piece {
                nodes: i..i + 1,
                part: Some(from..end),
            });
            group_start = i + 1;
            acc = 0;
        } else {
            acc += len.max(1);
            if acc >= target {
                out.push(Piece {
                    nodes: group_start..i + 1,
                    part: None,
                });
                group_start = i + 1;
                acc = 0;
            }
        }
    }
    if group_start < segs.len() {
        out.push(Piece {
            nodes: group_start..segs.len(),
            part: None,
        });
    }
    out
}

/// For each piece, the carry of its node: the sum of `counts` of the
/// earlier parts of the same node (`C::default()` for a piece that starts
/// its nodes).
pub fn carries<C: Copy + Default + std::ops::Add<Output = C>>(
    pieces: &[Piece],
    counts: &[C],
) -> Vec<C> {
    let mut out = Vec::with_capacity(pieces.len());
    let mut prev: Option<(usize, C)> = None;
    for (p, &c) in pieces.iter().zip(counts) {
        let carry = match (&p.part, prev) {
            (Some(_), Some((node, acc))) if node == p.nodes.start => acc,
            _ => C::default(),
        };
        out.push(carry);
        prev = p.part.as_ref().map(|_| (p.nodes.start, carry + c));
    }
    out
}

/// The carries of an element pass ([`carries`]) whose counts come from
/// the elements themselves: each element `e` of a part counts in bin
/// `bin(e)` of three and `pair` makes the pass's pair of the three bins.
/// A node's last part is not counted, since no carry needs it.
pub fn element_carries(
    ps: &[Piece],
    segs: &[(usize, usize)],
    src: &[u64],
    bin: impl Fn(u64) -> usize + Sync,
    pair: impl Fn([usize; 3]) -> Pair + Sync,
) -> Vec<Pair> {
    let counts: Vec<Pair> = ps
        .par_iter()
        .map(|p| match &p.part {
            Some(r) if r.end != segs[p.nodes.start].0 + segs[p.nodes.start].1 => {
                let mut c = [0usize; 3];
                for &e in &src[r.clone()] {
                    c[bin(e)] += 1;
                }
                pair(c)
            }
            _ => Pair::default(),
        })
        .collect();
    carries(ps, &counts)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_small_and_cuts_large() {
        let segs = [(0, 3), (3, 3), (10, 25), (35, 1), (36, 0)];
        let ps = pieces(&segs, 5, |_| true);
        assert_eq!(
            ps[0],
            Piece {
                nodes: 0..2,
                part: None
            }
        );
        let parts: Vec<_> = ps.iter().filter_map(|p| p.part.clone()).collect();
        assert_eq!(parts.first().unwrap().start, 10);
        assert_eq!(parts.last().unwrap().end, 35);
        for w in parts.windows(2) {
            assert_eq!(w[0].end, w[1].start);
        }
        assert_eq!(
            ps.last().unwrap(),
            &Piece {
                nodes: 3..5,
                part: None
            }
        );
        let counts: Vec<usize> = ps
            .iter()
            .map(|p| p.part.as_ref().map_or(0, |r| r.len()))
            .collect();
        let c = carries(&ps, &counts);
        for (p, c) in ps.iter().zip(&c) {
            if let Some(r) = &p.part {
                assert_eq!(*c, r.start - 10);
            }
        }
    }

    #[test]
    fn respects_cut_points() {
        let segs = [(0, 100)];
        let ps = pieces(&segs, 10, |i| i % 30 == 0);
        let parts: Vec<_> = ps.iter().map(|p| p.part.clone().unwrap()).collect();
        assert_eq!(parts, vec![0..30, 30..60, 60..90, 90..100]);
    }
}
