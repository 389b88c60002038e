//! Finishing small nodes depth-first with the finisher of [`super::dfs`]:
//! a level's small nodes in parallel ([`Finish`]), and single subtrees for
//! the slim pass ([`SubtreeBuilder`]).

use super::assemble::SubStream;
use super::dfs::Finisher;
use super::events::{MAX_REFS, PackedBox, push_events, to_box};
use super::{DEFAULT_TINY_THRESHOLD, Level, NewEvents, tiny};
use crate::build::sah::{self, LeafRule};
use crate::build::{BuildConfig, Progress, root_cell};
use crate::columns::ColumnsError;
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::{Node, TriId};
use rayon::prelude::*;
use std::sync::Arc;

/// What finishing small nodes needs of the builder (copied out, so that it
/// runs alongside the passes that change the builder).
pub(super) struct Finish<'a> {
    pub(super) scene: &'a TriangleColumns,
    pub(super) params: sah::SahParams,
    pub(super) rule: LeafRule,
    pub(super) progress: Option<&'a Progress>,
    pub(super) chunk_words: usize,
    pub(super) chunk_dir: Option<Arc<std::path::Path>>,
    pub(super) mode: NewEvents,
    pub(super) tiny: usize,
}

impl Finish<'_> {
    /// Finishes the small nodes depth-first, in parallel across nodes.
    /// Their subtrees are packed into runs, in the level's node order:
    /// each fold of rayon's covers a run of consecutive nodes, returned
    /// with the index in `small` of its first node.
    pub(super) fn runs(
        &self,
        l: &Level<'_>,
        small: &[usize],
        depth: u32,
    ) -> Vec<(usize, Result<SubStream, ColumnsError>)> {
        small
            .par_iter()
            .enumerate()
            .fold(
                || {
                    (
                        usize::MAX,
                        Finisher::new(self.scene, &self.params, self.rule, self.progress)
                            .with_new_events(self.mode)
                            .with_tiny(self.tiny),
                        Ok(SubStream::new(self.chunk_words, self.chunk_dir.clone())),
                    )
                },
                |(first, mut fin, out), (k, &j)| {
                    let out = out.and_then(|mut out| {
                        let nd = &l.nodes[j];
                        let ev = [0, 1, 2].map(|k| &l.ev[k][nd.ev[k]..nd.ev[k] + nd.nev[k]]);
                        let (nodes, leaf_tris) = fin.build(
                            &l.tri[nd.refs..nd.refs + nd.n],
                            &l.bounds[nd.refs..nd.refs + nd.n],
                            ev,
                            nd.refs as u32,
                            nd.cell,
                            depth,
                            nd.weight,
                        );
                        out.push(nd.rec, nodes, leaf_tris)?;
                        Ok(out)
                    });
                    (first.min(k), fin, out)
                },
            )
            .map(|(first, _, out)| (first, out))
            .filter(|(first, _)| *first != usize::MAX)
            .collect()
    }
}

/// Builds subtrees of single nodes depth-first, with the finisher the
/// level builder uses for its small nodes (`dfs`, no heap allocation per
/// node): the subtree is the one [`super::wald_havran::build_subtree`] builds for
/// the same references, cell and depth. The slim post-pass rebuilds its
/// subtrees with it. One per worker; its scratch is reused across builds.
pub(crate) struct SubtreeBuilder<'a> {
    finisher: Finisher<'a>,
    tri: Vec<u32>,
    boxes: Vec<PackedBox>,
    ev: [Vec<u64>; 3],
}

impl<'a> SubtreeBuilder<'a> {
    pub fn new(scene: &'a TriangleColumns, config: &'a BuildConfig) -> SubtreeBuilder<'a> {
        // The scene's bounds are its root cell ([`root_cell`]); the slim pass
        // gives the price scale in `config`, so that workers skip this pass.
        let rule = config
            .sah
            .leaf_rule(scene.len(), || root_cell(scene.bounds()));
        SubtreeBuilder {
            finisher: Finisher::new(scene, &config.sah, rule, None)
                .with_tiny(DEFAULT_TINY_THRESHOLD),
            tri: Vec::new(),
            boxes: Vec::new(),
            ev: Default::default(),
        }
    }

    /// The subtree of a node at `depth` with cell `cell` and the triangle
    /// references `refs` (ascending ids, boxes inside `cell`, fewer than
    /// 2³⁰), under the depth limit of the whole scene: its nodes and leaf
    /// lists in pre-order (the [`TreeIr`] of bounds `cell`), borrowed until
    /// the next build, so that the slim pass copies out only the subtrees
    /// it keeps. `None` if the build stopped because the subtree takes at
    /// least `byte_limit` bytes in the file ([`Finisher::with_byte_limit`];
    /// `u64::MAX`: never).
    pub fn build(
        &mut self,
        refs: impl IntoIterator<Item = (TriId, Aabb)>,
        cell: Aabb,
        depth: u32,
        byte_limit: u64,
    ) -> Option<(&[Node], &[TriId])> {
        self.tri.clear();
        self.boxes.clear();
        for (t, b) in refs {
            debug_assert!(self.tri.last().is_none_or(|&last| last < t.0));
            self.tri.push(t.0);
            self.boxes.push(to_box(&b));
        }
        assert!(self.tri.len() < MAX_REFS, "too many references");
        // The finisher sweeps a node of at most the tiny threshold without
        // events, so they are made only for a larger one (98 % of the slim
        // pass's rebuilds on dieselpower are tiny).
        let tiny = self.tri.len() <= DEFAULT_TINY_THRESHOLD.min(tiny::MAX_TINY);
        for (axis, ev) in self.ev.iter_mut().enumerate() {
            ev.clear();
            if tiny {
                continue;
            }
            for (r, b) in self.boxes.iter().enumerate() {
                push_events(b, axis, r as u32, ev);
            }
            ev.sort_unstable();
        }
        let ev = [0, 1, 2].map(|k| self.ev[k].as_slice());
        let finisher = self.finisher.with_byte_limit(byte_limit);
        finisher.build(&self.tri, &self.boxes, ev, 0, cell, depth, Progress::TOTAL);
        if finisher.stopped() {
            return None;
        }
        Some(finisher.output())
    }
}
