//! The traversers' view of a `.kd` file: its sections as plain slices,
//! taken once per query, so that a node step is one load and a few bit
//! operations on the raw 8-byte word (no decoded enum, no section lookup).

use super::{InnerNode, LeafTris, SourceNode, Walk};
use crate::format::node::{A_TYPE2, E_IDX16, E_IDX32, E_ONE, MAX_LEAF32};
use crate::format::{KdFile, LeafIndices};
use crate::geom::Aabb;
use crate::tree::TriId;
use glam::Vec3;

/// The slot an empty child reads as: past any node section (at most
/// 2^29 words), so [`Walk::node`] gives an empty leaf without a load.
pub(crate) const NO_WORD: u32 = u32::MAX;

/// The sections of a [`KdFile`] whose header and section table passed
/// [`KdFile::from_bytes`]; their contents are checked where they are read,
/// not on open (a file need not pass [`KdFile::validate`], and a mapped
/// file rewritten in place by another process can hold anything).
///
/// A check that fails reads as nothing rather than panicking: a child
/// slot that does not lie after its node (a loop) or outside the node
/// section, or a leaf range outside its index array, is an empty leaf; a
/// triangle index out of range (a one-triangle leaf's too) or a vertex
/// index out of range is a triangle that is never hit. Each is a
/// comparison the slice indexing made anyway, and the first keeps every
/// walk moving forward through the nodes. Forward slots can still share
/// subtrees, whose paths can be exponentially many, so a walk stops after
/// [`Walk::step_limit`] steps: [`KdFile::node_limit`], the most nodes (words and
/// empty children without one) a tree of that many words has. A split
/// outside its cell is not checked: it only sends a ray to a child it
/// would not have visited, and the walk stays bounded. So a corrupt file
/// gives wrong hits at worst. (A file truncated under the mapping is
/// another matter: the kernel answers a read of the lost pages with
/// SIGBUS; see [`KdFile::open`].)
#[derive(Clone, Copy)]
pub struct FileWalk<'a> {
    pub(super) nodes: &'a [u64],
    pub(super) idx32: &'a [u32],
    pub(super) idx16: &'a [u16],
    pub(super) vertices: &'a [[f32; 3]],
    pub(super) triangles: &'a [[u32; 3]],
    tri_map: Option<&'a [u32]>,
    bounds: Aabb,
    /// `2 · nodes.len() + 1` (at most 2^30 + 1: [`KdFile::from_bytes`]
    /// refuses more than 2^29 words).
    step_limit: u32,
}

/// A walk is its own source, so a caller that took one once (the facade's
/// `AccelTracer`) hands it to a traverser without taking it again.
impl super::KdSource for FileWalk<'_> {
    type Walk<'a>
        = FileWalk<'a>
    where
        Self: 'a;

    fn walk(&self) -> FileWalk<'_> {
        *self
    }
}

impl<'a> FileWalk<'a> {
    /// The sections of `file` as slices.
    pub fn new<D: AsRef<[u8]>>(file: &'a KdFile<D>) -> FileWalk<'a> {
        FileWalk {
            nodes: file.nodes(),
            idx32: file.idx32(),
            idx16: file.idx16(),
            vertices: file.vertices(),
            triangles: file.triangles(),
            tri_map: file.tri_map(),
            bounds: file.bounds(),
            step_limit: u32::try_from(file.node_limit()).unwrap_or(u32::MAX),
        }
    }
}

impl<'a> Walk<'a> for FileWalk<'a> {
    #[inline(always)]
    fn bounds(&self) -> Aabb {
        self.bounds
    }

    #[inline(always)]
    fn node(&self, n: u32) -> SourceNode<'a> {
        const EMPTY: SourceNode<'static> = SourceNode::Leaf(LeafTris::Ids(&[]));
        let Some(&w) = self.nodes.get(n as usize) else {
            return EMPTY;
        };
        let hi = (w >> 32) as u32;
        if w & 0b11 != 0b11 {
            // Type I or II inner node (format version 2, see
            // `format::node`): the left child follows the node (and its
            // T-reference), the right child is at the slot field; an empty
            // child has no word and reads as `NO_WORD`, which lies past the
            // node section and so reads as an empty leaf.
            let type2 = w & A_TYPE2 != 0;
            let first = n + 1 + u32::from(type2);
            let field = (w as u32) >> 3;
            let left = if field == first { NO_WORD } else { first };
            // Validated files have every child after its node; a field that
            // is not (0 for an empty right child, or a slot rewritten under
            // the map) is no child, so every walk moves forward and ends.
            let right = if field > n { field } else { NO_WORD };
            let t_ref = if type2 {
                match self.nodes.get(n as usize + 1) {
                    Some(&t) => Some((t >> 32) as u32),
                    None => return EMPTY,
                }
            } else {
                None
            };
            return SourceNode::Inner(InnerNode {
                axis: (w & 0b11) as u8,
                pos: f32::from_bits(hi),
                left,
                right,
                t_ref,
            });
        }
        if w & A_TYPE2 != 0 {
            // A T-reference is never a child (validated); read as empty.
            return EMPTY;
        }
        let start = hi as usize;
        let leaf = match (w >> 3) & 0b11 {
            E_IDX32 => {
                let count = (((w as u32) >> 5) & MAX_LEAF32) as usize;
                match self.idx32.get(start..start + count) {
                    Some(ids) => LeafIndices::Idx32(ids),
                    None => return EMPTY,
                }
            }
            E_IDX16 => {
                let count = (((w as u32) >> 5) & 0x7ff) as usize;
                match self.idx16.get(start..start + count) {
                    Some(low) => LeafIndices::Idx16 {
                        upper: (w as u32) & 0xffff_0000,
                        low,
                    },
                    None => return EMPTY,
                }
            }
            E_ONE => LeafIndices::One(hi),
            _ => return EMPTY,
        };
        SourceNode::Leaf(LeafTris::File(leaf))
    }

    #[inline(always)]
    fn triangle(&self, t: u32) -> [Vec3; 3] {
        let v = self.vertices;
        let vertex = |i: u32| v.get(i as usize).map(|&p| Vec3::from_array(p));
        match self
            .triangles
            .get(t as usize)
            .map(|&[a, b, c]| (vertex(a), vertex(b), vertex(c)))
        {
            Some((Some(a), Some(b), Some(c))) => [a, b, c],
            // Degenerate (zero area): never hit.
            _ => [Vec3::ZERO; 3],
        }
    }

    #[inline(always)]
    fn step_limit(&self) -> u32 {
        self.step_limit
    }

    fn tag(&self) -> (usize, usize) {
        (self.nodes.as_ptr() as usize, self.nodes.len())
    }

    #[inline(always)]
    fn input_id(&self, t: u32) -> TriId {
        // A map entry out of range (a file not validated) reads as `t`, so
        // that a hit's id always names a triangle of the file (a triangle
        // `t` out of range is never hit).
        TriId(match self.tri_map {
            Some(map) => map
                .get(t as usize)
                .copied()
                .filter(|&i| (i as usize) < map.len())
                .unwrap_or(t),
            None => t,
        })
    }
}
