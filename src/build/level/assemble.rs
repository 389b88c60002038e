//! Turns the level builder's records into the canonical [`TreeIr`].
//!
//! Consumes one record per node, made in breadth-first order (an inner
//! node names its children's records; a leaf names its triangle list; a
//! small node names the level whose depth-first subtrees hold its own) and
//! the [`SubStore`] of those subtrees. Produces the nodes in depth-first
//! pre-order with the leaf lists concatenated in the same order, which is
//! the order every builder emits (see [`crate::tree`]), so the result
//! compares equal to the Wald-Havran builder's tree.
//!
//! **Memory.** The depth-first subtrees are most of the tree, so they are
//! never held twice. They are stored packed (12 bytes a node instead of a
//! [`Node`]'s 20), one stream per level in the level's node order, in
//! chunks that are mappings of their own (anonymous, or under a budget
//! unlinked scratch files). A level's nodes are in
//! left-to-right order of the tree, so pre-order reads each level's stream
//! front to back: the assembly copies every subtree once, and each chunk is
//! unmapped (its pages returned to the system, whatever the allocator
//! does) as soon as it has been read. The tree and the subtrees left to
//! copy together stay within about one chunk per level of the tree alone;
//! [`assemble_into`] hands the nodes to a sink instead, so with the
//! streamed writer only the subtrees left to read are held.

use crate::columns::ColumnsError;
use crate::tree::{Node, NodeId, PreOrderSink, SinkStop, TreeIr, TreeIrSink, TriId};
use memmap2::MmapMut;
use std::collections::VecDeque;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// What became of one node of a level.
#[derive(Clone, Copy, Debug)]
pub enum NodeRecord {
    /// Not decided yet (only while building).
    Open,
    Inner {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
    },
    /// `tris[start .. start + count]` of the breadth-first leaves.
    Leaf { start: usize, count: u32 },
    /// A subtree finished depth-first at this depth: the next one in that
    /// level's [`SubStream`].
    Sub(u32),
    /// Cell `k` of a cut (`super::build_top`): an empty leaf here.
    Cell(u32),
}

/// The smallest chunk, in `u32` words (1 MiB).
const MIN_CHUNK_WORDS: usize = 1 << 18;
/// Words of one packed node: `[axis or LEAF, pos bits or start, right or
/// count]`.
const NODE_WORDS: usize = 3;
const LEAF: u32 = 3;
/// Words before a subtree's nodes: its record, node count, triangle count.
const HEADER_WORDS: usize = 3;

/// A chunk of a stream: an anonymous mapping, so that dropping it returns
/// its pages to the system (a `Vec` of a few MiB may come from the
/// allocator's heap, which keeps freed pages), and pages never written are
/// never resident.
struct Chunk {
    map: MmapMut,
    /// Words written.
    len: usize,
    /// Words read back.
    read: usize,
}

/// Distinguishes the chunk files of one process.
static CHUNK_FILES: AtomicU64 = AtomicU64::new(0);

impl Chunk {
    /// An anonymous mapping, or with `dir` a mapping of an unlinked
    /// scratch file there (its pages are the page cache's, which the
    /// kernel writes back and reclaims under pressure, not the process's
    /// anonymous memory).
    fn new(words: usize, dir: Option<&Path>) -> Result<Chunk, ColumnsError> {
        let bytes = words * 4;
        let map = match dir {
            Some(dir) => {
                let path = dir.join(format!(
                    ".slimkd-subtrees.{}.{}",
                    std::process::id(),
                    CHUNK_FILES.fetch_add(1, Ordering::Relaxed)
                ));
                crate::columns::map_file(&path, bytes as u64)?.expect("a chunk is never empty")
            }
            None => MmapMut::map_anon(bytes).map_err(|source| ColumnsError::Memory {
                bytes: bytes as u64,
                source,
            })?,
        };
        Ok(Chunk {
            map,
            len: 0,
            read: 0,
        })
    }

    fn capacity(&self) -> usize {
        self.map.len() / 4
    }

    fn words(&self) -> &[u32] {
        // A page-aligned mapping of a multiple of 4 bytes: cannot fail.
        bytemuck::cast_slice(&self.map[..])
    }

    fn words_mut(&mut self) -> &mut [u32] {
        bytemuck::cast_slice_mut(&mut self.map[..])
    }
}

/// Depth-first subtrees, packed, in the order they were pushed.
pub struct SubStream {
    chunks: VecDeque<Chunk>,
    /// The size of a new chunk (a subtree larger than it gets a chunk of
    /// its own size).
    chunk_words: usize,
    /// Where chunks are scratch files (under a memory budget).
    dir: Option<Arc<Path>>,
    subs: usize,
    nodes: usize,
    tris: usize,
}

impl SubStream {
    pub fn new(chunk_words: usize, dir: Option<Arc<Path>>) -> SubStream {
        SubStream {
            chunks: VecDeque::new(),
            chunk_words: chunk_words.max(MIN_CHUNK_WORDS),
            dir,
            subs: 0,
            nodes: 0,
            tris: 0,
        }
    }

    /// Appends the subtree of record `rec` (nodes numbered from 0, leaf
    /// lists starting at 0, no hoisted triangles).
    pub fn push(
        &mut self,
        rec: u32,
        nodes: &[Node],
        leaf_tris: &[TriId],
    ) -> Result<(), ColumnsError> {
        let need = HEADER_WORDS + NODE_WORDS * nodes.len() + leaf_tris.len();
        if self
            .chunks
            .back()
            .is_none_or(|c| c.capacity() - c.len < need)
        {
            self.chunks
                .push_back(Chunk::new(need.max(self.chunk_words), self.dir.as_deref())?);
        }
        let c = self.chunks.back_mut().expect("a chunk was just made");
        let at = c.len;
        let w = &mut c.words_mut()[at..at + need];
        let (head, rest) = w.split_at_mut(HEADER_WORDS);
        let (packed, tris) = rest.split_at_mut(NODE_WORDS * nodes.len());
        head.copy_from_slice(&[rec, nodes.len() as u32, leaf_tris.len() as u32]);
        for (p, n) in packed.chunks_exact_mut(NODE_WORDS).zip(nodes) {
            p.copy_from_slice(&match *n {
                Node::Inner { t_ref: Some(_), .. } => {
                    panic!("standard trees hoist no triangles")
                }
                Node::Inner {
                    axis, pos, right, ..
                } => [u32::from(axis), pos.to_bits(), right.0],
                Node::Leaf { start, count } => [LEAF, start, count],
            });
        }
        for (p, t) in tris.iter_mut().zip(leaf_tris) {
            *p = t.0;
        }
        c.len += need;
        self.subs += 1;
        self.nodes += nodes.len();
        self.tris += leaf_tris.len();
        Ok(())
    }

    /// Appends `other`'s subtrees after this one's.
    pub fn append(&mut self, mut other: SubStream) {
        self.chunks.append(&mut other.chunks);
        self.subs += other.subs;
        self.nodes += other.nodes;
        self.tris += other.tris;
    }

    pub fn len(&self) -> usize {
        self.subs
    }

    /// The next subtree: its record, packed nodes and leaf triangles.
    /// Chunks read to the end are dropped first.
    fn pop(&mut self) -> Option<(u32, &[u32], &[u32])> {
        while self.chunks.front().is_some_and(|c| c.read == c.len) {
            self.chunks.pop_front();
        }
        let c = self.chunks.front_mut()?;
        let at = c.read;
        let [rec, n, t] = [0, 1, 2].map(|k| c.words()[at + k] as usize);
        let need = HEADER_WORDS + NODE_WORDS * n + t;
        c.read += need;
        let w = &c.words()[at + HEADER_WORDS..at + need];
        let (packed, tris) = w.split_at(NODE_WORDS * n);
        Some((rec as u32, packed, tris))
    }
}

/// The depth-first subtrees of the whole build: one stream per depth.
pub struct SubStore {
    levels: Vec<SubStream>,
    /// Where the streams' chunks are scratch files, if anywhere.
    pub dir: Option<Arc<Path>>,
    words: usize,
    nodes: usize,
    tris: usize,
}

impl SubStore {
    /// An empty store whose chunks are anonymous mappings, or with `dir`
    /// scratch files there.
    pub fn new(dir: Option<Arc<Path>>) -> SubStore {
        SubStore {
            levels: Vec::new(),
            dir,
            words: 0,
            nodes: 0,
            tris: 0,
        }
    }

    /// The chunk size for new streams: at least 1 MiB, and large enough
    /// that the store never needs more than a few thousand mappings.
    pub fn chunk_words(&self) -> usize {
        (self.words / 512).max(MIN_CHUNK_WORDS)
    }

    /// Appends subtrees finished at `depth`, in the level's node order.
    pub fn add(&mut self, depth: u32, s: SubStream) {
        let d = depth as usize;
        if self.levels.len() <= d {
            let dir = &self.dir;
            self.levels
                .resize_with(d + 1, || SubStream::new(0, dir.clone()));
        }
        self.words += HEADER_WORDS * s.subs + NODE_WORDS * s.nodes + s.tris;
        self.nodes += s.nodes;
        self.tris += s.tris;
        self.levels[d].append(s);
    }
}

/// The tree, in pre-order from record 0, and the leaves that stand for
/// cells (`NodeRecord::Cell`) with their cell numbers, in pre-order; consumes the
/// subtrees. Its two columns are reserved whole up front, so a tree that
/// does not fit in memory is an error naming them.
#[allow(clippy::type_complexity)]
pub fn assemble(
    bounds: crate::geom::Aabb,
    recs: &[NodeRecord],
    tris: &[TriId],
    subs: SubStore,
) -> Result<(TreeIr, Vec<(NodeId, u32)>), ColumnsError> {
    let n_nodes = recs
        .iter()
        .filter(|r| !matches!(r, NodeRecord::Sub(_)))
        .count()
        + subs.nodes;
    let n_tris = tris.len() + subs.tris;
    let mut nodes = Vec::new();
    let mut leaf_tris = Vec::new();
    crate::sys::try_reserve(&mut nodes, n_nodes, "the tree's nodes")
        .map_err(ColumnsError::OutOfMemory)?;
    crate::sys::try_reserve(&mut leaf_tris, n_tris, "the tree's leaf triangle lists")
        .map_err(ColumnsError::OutOfMemory)?;
    let mut sink = TreeIrSink::with_capacity(nodes, leaf_tris);
    let cells = assemble_into(bounds, recs, tris, subs, &mut sink)
        .expect("a TreeIrSink takes any one tree");
    let tree = sink.finish().expect("the records form one tree");
    debug_assert_eq!(tree.nodes.len(), n_nodes);
    debug_assert_eq!(tree.leaf_tris.len(), n_tris);
    Ok((tree, cells))
}

/// Hands the tree to `sink` in pre-order from record 0, consuming the
/// subtrees as it goes (each chunk unmapped once read, so the build's
/// memory shrinks while the sink takes the tree); returns the pre-order
/// positions of the leaves that stand for cells (`NodeRecord::Cell`, given to the
/// sink as empty leaves) with their cell numbers.
pub fn assemble_into(
    bounds: crate::geom::Aabb,
    recs: &[NodeRecord],
    tris: &[TriId],
    mut subs: SubStore,
    sink: &mut impl PreOrderSink,
) -> Result<Vec<(NodeId, u32)>, SinkStop> {
    sink.bounds(bounds)?;
    let mut cells = Vec::new();
    // Nodes handed out so far: the next node's pre-order position.
    let mut count = 0usize;
    let mut list = Vec::new();
    let mut stack = vec![0u32];
    while let Some(r) = stack.pop() {
        match recs[r as usize] {
            NodeRecord::Open => unreachable!("every record is decided before assembly"),
            NodeRecord::Inner {
                axis,
                pos,
                left,
                right,
            } => {
                sink.inner(axis, pos, None)?;
                count += 1;
                stack.push(right);
                stack.push(left);
            }
            NodeRecord::Leaf { start, count: n } => {
                sink.leaf(&tris[start..start + n as usize])?;
                count += 1;
            }
            NodeRecord::Cell(k) => {
                cells.push((NodeId(count as u32), k));
                sink.leaf(&[])?;
                count += 1;
            }
            NodeRecord::Sub(depth) => {
                let (rec, packed, sub_tris) = subs.levels[depth as usize]
                    .pop()
                    .expect("each small node has its subtree");
                assert_eq!(rec, r, "a level's subtrees are read in its node order");
                // The packed nodes are in pre-order already.
                for w in packed.chunks_exact(NODE_WORDS) {
                    if w[0] == LEAF {
                        list.clear();
                        list.extend(
                            sub_tris[w[1] as usize..(w[1] + w[2]) as usize]
                                .iter()
                                .map(|&t| TriId(t)),
                        );
                        sink.leaf(&list)?;
                    } else {
                        sink.inner(w[0] as u8, f32::from_bits(w[1]), None)?;
                    }
                    count += 1;
                }
            }
        }
    }
    Ok(cells)
}
