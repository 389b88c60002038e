//! The traversers' view of a `.kd` file: its sections as plain slices,
//! taken once per query, so that a node step is one load and a few bit
//! operations on the raw 8-byte word (no decoded enum, no section lookup).

use super::{LeafTris, SourceNode, Walk};
use crate::format::node::{A_TYPE2, MAX_LEAF32};
use crate::format::{KdFile, LeafIndices};
use crate::geom::Aabb;
use crate::tree::TriId;
use glam::Vec3;

/// The sections of a validated [`KdFile`]. Only [`FileWalk::new`] makes
/// one, so every word, child block, leaf range and vertex index in it
/// passed [`KdFile::from_bytes`]; indexing stays checked all the same (a
/// failed check is a panic, never a wrong read).
#[derive(Clone, Copy)]
pub struct FileWalk<'a> {
    nodes: &'a [u64],
    idx32: &'a [u32],
    idx16: &'a [u16],
    vertices: &'a [[f32; 3]],
    triangles: &'a [[u32; 3]],
    tri_map: Option<&'a [u32]>,
    bounds: Aabb,
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
    pub fn new<D: AsRef<[u8]>>(file: &'a KdFile<D>) -> FileWalk<'a> {
        FileWalk {
            nodes: file.nodes(),
            idx32: file.idx32(),
            idx16: file.idx16(),
            vertices: file.vertices(),
            triangles: file.triangles(),
            tri_map: file.tri_map(),
            bounds: file.bounds(),
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
        let w = self.nodes[n as usize];
        let hi = (w >> 32) as u32;
        if w & 0b11 != 0b11 {
            // Type I or II inner node: children at `block` (type I) or
            // after the T-reference at `block` (type II).
            let block = (w as u32) >> 3;
            let type2 = w & A_TYPE2 != 0;
            let left = block + u32::from(type2);
            let t_ref = type2.then(|| (self.nodes[block as usize] >> 32) as u32);
            return SourceNode::Inner {
                axis: (w & 0b11) as u8,
                pos: f32::from_bits(hi),
                left,
                right: left + 1,
                t_ref,
            };
        }
        if w & A_TYPE2 != 0 {
            // A T-reference is never a child (validated); read as empty.
            return SourceNode::Leaf(LeafTris::Ids(&[]));
        }
        let start = hi as usize;
        let leaf = if (w >> 3) & 1 == 0 {
            let count = (((w as u32) >> 5) & MAX_LEAF32) as usize;
            LeafIndices::Idx32(&self.idx32[start..start + count])
        } else {
            let count = (((w as u32) >> 5) & 0x7ff) as usize;
            LeafIndices::Idx16 {
                upper: (w as u32) & 0xffff_0000,
                low: &self.idx16[start..start + count],
            }
        };
        SourceNode::Leaf(LeafTris::File(leaf))
    }

    #[inline(always)]
    fn triangle(&self, t: u32) -> [Vec3; 3] {
        let v = self.vertices;
        self.triangles[t as usize].map(|i| Vec3::from_array(v[i as usize]))
    }

    #[inline(always)]
    fn input_id(&self, t: u32) -> TriId {
        TriId(match self.tri_map {
            Some(map) => map[t as usize],
            None => t,
        })
    }
}
