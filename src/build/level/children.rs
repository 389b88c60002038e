//! Steps 4 and 5 of a level: the split nodes' children opened, their
//! references classified and written ([`super::classify`]), and their
//! event lists partitioned and merged ([`super::events`]).

use super::assemble::NodeRecord;
use super::classify::{Classified, SideCounts, classify_pass, piece_carries, write_children};
use super::events::{PackedBox, merge_new_events, partition_events};
use super::pieces::{PIECE, Piece, pieces};
use super::{Level, LevelBuilder, LevelNode};
use crate::build::Progress;
use crate::build::sah::Split;
use crate::columns::{Column, ColumnsError};

/// The children of a level's split nodes after step 4, for step 5.
pub(super) struct Children<'s> {
    /// The next level's nodes: per split node, left then right.
    nodes: Vec<LevelNode>,
    /// The next level's events per axis.
    ev_len: [usize; 3],
    tri: Column<'s, u32>,
    bounds: Column<'s, PackedBox>,
    /// Per reference of the level: its placement code.
    place: Column<'s, u8>,
    /// Per reference of the level: its index in the next level and side,
    /// or [`placement::DROPPED`] (see [`write_children`]).
    new_idx: Column<'s, u32>,
    /// The clipped copies, `(child node << 32) | new reference`.
    copies: Vec<u64>,
}

impl<'a> LevelBuilder<'a> {
    /// Step 4: classifies the split nodes' references and clips the
    /// straddlers, opens the children (per split node, left then right)
    /// and writes their references into the next level's columns.
    pub(super) fn children(
        &mut self,
        l: &Level<'a>,
        splits: &[(usize, Split)],
    ) -> Result<Children<'a>, ColumnsError> {
        let rsegs: Vec<(usize, usize)> = splits
            .iter()
            .map(|&(j, _)| (l.nodes[j].refs, l.nodes[j].n))
            .collect();
        let rpieces = pieces(&rsegs, PIECE, |_| true);
        let mut place = self
            .scratch
            .column_for_overwrite::<u8>("place", l.tri.len())?;
        let classified = classify_pass(self.scene, l, splits, &rsegs, &rpieces, &mut place);
        self.report.clipped += classified
            .iter()
            .map(|c| c.clipped.len() as u64)
            .sum::<u64>();

        let rcarry = piece_carries(&rpieces, &classified);
        let (next_nodes, refs_at, ev_at) = self.open_children(l, splits, &rpieces, &classified);
        Self::capacity(refs_at)?;
        let mut tri = self.scratch.column_for_overwrite::<u32>("tri", refs_at)?;
        let mut boxes = self
            .scratch
            .column_for_overwrite::<PackedBox>("bounds", refs_at)?;
        let mut new_idx = self
            .scratch
            .column_for_overwrite::<u32>("new-idx", l.tri.len())?;
        let copies = write_children(
            l,
            &place,
            &rsegs,
            &rpieces,
            &classified,
            &rcarry,
            &next_nodes,
            &mut tri,
            &mut boxes,
            &mut new_idx,
        );
        Ok(Children {
            nodes: next_nodes,
            ev_len: ev_at,
            tri,
            bounds: boxes,
            place,
            new_idx,
            copies,
        })
    }

    /// The children of the split nodes as the next level's nodes (per
    /// split node, left then right), their records opened and their
    /// reference and event ranges laid out in order; returns them with the
    /// next level's reference and per-axis event counts.
    fn open_children(
        &mut self,
        l: &Level<'a>,
        splits: &[(usize, Split)],
        rpieces: &[Piece],
        classified: &[Classified],
    ) -> (Vec<LevelNode>, usize, [usize; 3]) {
        let mut totals = vec![SideCounts::default(); splits.len()];
        for (p, c) in rpieces.iter().zip(classified) {
            for (k, si) in p.nodes.clone().enumerate() {
                totals[si] = totals[si] + c.counts[k];
            }
        }
        let mut next_nodes = Vec::with_capacity(2 * splits.len());
        let (mut refs_at, mut ev_at) = (0usize, [0usize; 3]);
        for (si, &(j, split)) in splits.iter().enumerate() {
            let nd = &l.nodes[j];
            let t = &totals[si];
            let (lc, rc) = nd.cell.split(split.axis as usize, split.pos);
            let (wl, wr) = Progress::share(nd.weight, t.n[0], t.n[1]);
            let left = self.recs.len() as u32;
            self.recs[nd.rec as usize] = NodeRecord::Inner {
                axis: split.axis,
                pos: split.pos,
                left,
                right: left + 1,
            };
            for (side, (cell, weight)) in [(lc, wl), (rc, wr)].into_iter().enumerate() {
                let nev = [0, 1, 2].map(|k| t.inherited[side][k] + t.new[side][k]);
                next_nodes.push(LevelNode {
                    cell,
                    refs: refs_at,
                    n: t.n[side],
                    ev: ev_at,
                    nev,
                    weight,
                    rec: self.recs.len() as u32,
                });
                self.recs.push(NodeRecord::Open);
                refs_at += t.n[side];
                for k in 0..3 {
                    ev_at[k] += nev[k];
                }
            }
        }
        (next_nodes, refs_at, ev_at)
    }

    /// Step 5: the children's event lists (the inherited events
    /// partitioned, the clipped copies' events sorted and merged in);
    /// returns the next level.
    pub(super) fn child_events(
        &self,
        l: &Level<'a>,
        splits: &[(usize, Split)],
        children: Children<'a>,
        depth: u32,
    ) -> Result<Level<'a>, ColumnsError> {
        let Children {
            nodes,
            ev_len,
            tri,
            bounds,
            place,
            new_idx,
            copies,
        } = children;
        let mut ev = Vec::with_capacity(3);
        for &len in &ev_len {
            ev.push(self.scratch.column_for_overwrite::<u64>("ev", len)?);
        }
        let mut ev: [Column<'a, u64>; 3] = ev.try_into().expect("three axes");
        partition_events(l, splits, &place, &new_idx, &nodes, &mut ev);
        drop(place);
        drop(new_idx);
        merge_new_events(copies, &bounds, &nodes, &mut ev, self.options.new_events);
        Ok(Level {
            depth: depth + 1,
            nodes,
            tri,
            bounds,
            ev,
        })
    }
}
