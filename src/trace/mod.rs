//! Closest-hit queries: the scalar front-to-back kd-tree traverser, the 4×4
//! packet traverser ([`packet`]) and the brute-force reference.
//!
//! Consumes any [`KdSource`]: an in-memory [`TreeIr`] with its
//! [`TriangleColumns`] ([`TreeTracer`]), or a mapped `.kd` file
//! ([`KdFile`]); produces a [`Hit`] per ray, with the *input* triangle id. Every traverser uses the same watertight test
//! ([`intersect_triangle`]) and the same rule for the closest hit: the
//! smallest `t` in `(tmin, tmax]`, ties going to the smaller triangle id. So
//! the traverser and brute force return exactly the same hit, bit for bit.
//!
//! **Robust early exit.** Split-plane distances `ts` and hit distances `t`
//! are rounded independently, so a hit that lies on a split plane may be
//! computed just inside one cell while a triangle of the neighbouring cell
//! is computed just before it. The traverser therefore widens every
//! decision by a relative margin [`MARGIN`]: it visits both children unless
//! the plane is clearly outside `[tmin, tmax]`, and it skips a pending cell
//! only when its entry distance lies clearly beyond the best hit. (Pending
//! cells are checked one by one rather than assumed sorted: a ray lying in
//! a split plane visits both children over the same interval.) This costs a
//! rare extra cell visit and keeps the result equal to brute force unless a
//! hit distance carries a relative error above ~2⁻¹² (a triangle many
//! thousand times larger than its distance to the eye, seen at a grazing
//! angle).

pub mod packet;

use crate::format::node::{self as word, NodeWord};
use crate::format::{KdFile, LeafIndices};
use crate::geom::{Aabb, Ray, RayPrecomp, intersect_triangle};
use crate::scene::TriangleColumns;
use crate::tree::{Node, TreeIr, TriId};
use glam::Vec3;

/// Relative margin on cell boundaries (see the module docs).
pub const MARGIN: f32 = 1.0 / 4096.0;

/// Stack entries: one per inner node on a root path, so more than the
/// deepest tree ([`crate::tree::MAX_DEPTH`]) can have.
pub const MAX_STACK: usize = crate::tree::MAX_DEPTH as usize + 1;

/// The closest hit of a ray, or a miss.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Hit distance; `f32::INFINITY` for a miss.
    pub t: f32,
    /// The triangle hit; [`Hit::NO_TRI`] for a miss.
    pub tri: TriId,
}

impl Hit {
    pub const NO_TRI: TriId = TriId(u32::MAX);
    pub const MISS: Hit = Hit {
        t: f32::INFINITY,
        tri: Hit::NO_TRI,
    };

    pub fn is_hit(&self) -> bool {
        self.tri != Hit::NO_TRI
    }

    /// Keeps `(t, tri)` if it is closer, or equally close with a smaller id.
    #[inline]
    pub fn offer(&mut self, t: f32, tri: TriId) {
        if t < self.t || (t == self.t && tri < self.tri) {
            *self = Hit { t, tri };
        }
    }
}

/// Anything that answers closest-hit queries (used by the renderer).
pub trait ClosestHit: Sync {
    fn closest_hit(&self, ray: &Ray) -> Hit;

    /// Traces a 4×4 block of rays; the default traces them one by one.
    fn closest_hit_4x4(&self, rays: &[Ray; 16], out: &mut [Hit; 16]) {
        for (r, h) in rays.iter().zip(out.iter_mut()) {
            *h = self.closest_hit(r);
        }
    }
}

/// A node as a traverser sees it.
#[derive(Clone, Copy, Debug)]
pub enum SourceNode<'a> {
    /// `t_ref` is a hoisted triangle (type II node), in source numbering.
    Inner {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
        t_ref: Option<u32>,
    },
    Leaf(LeafTris<'a>),
}

/// The triangles of a leaf, in source numbering.
#[derive(Clone, Copy, Debug)]
pub enum LeafTris<'a> {
    Ids(&'a [TriId]),
    File(LeafIndices<'a>),
}

impl LeafTris<'_> {
    #[inline]
    pub fn for_each(&self, mut f: impl FnMut(u32)) {
        match self {
            LeafTris::Ids(ids) => ids.iter().for_each(|t| f(t.0)),
            LeafTris::File(l) => l.for_each(f),
        }
    }
}

/// A kd-tree that traversers can walk: in memory or in a file.
pub trait KdSource: Sync {
    /// The root cell.
    fn bounds(&self) -> Aabb;
    fn root(&self) -> u32;
    fn node(&self, n: u32) -> SourceNode<'_>;
    /// The vertices of a triangle (source numbering).
    fn triangle(&self, t: u32) -> [Vec3; 3];
    /// The input id reported for a triangle (ties are broken on it).
    fn input_id(&self, t: u32) -> TriId;
}

/// An in-memory tree and its scene.
pub struct TreeTracer<'a> {
    pub tree: &'a TreeIr,
    pub scene: &'a TriangleColumns,
}

impl KdSource for TreeTracer<'_> {
    fn bounds(&self) -> Aabb {
        self.tree.bounds
    }

    fn root(&self) -> u32 {
        0
    }

    #[inline]
    fn node(&self, n: u32) -> SourceNode<'_> {
        match self.tree.nodes[n as usize] {
            Node::Inner {
                axis,
                pos,
                right,
                t_ref,
            } => SourceNode::Inner {
                axis,
                pos,
                left: n + 1,
                right: right.0,
                t_ref: t_ref.map(|t| t.0),
            },
            Node::Leaf { start, count } => {
                SourceNode::Leaf(LeafTris::Ids(self.tree.leaf(start, count)))
            }
        }
    }

    #[inline]
    fn triangle(&self, t: u32) -> [Vec3; 3] {
        self.scene.tri(t)
    }

    #[inline]
    fn input_id(&self, t: u32) -> TriId {
        TriId(t)
    }
}

impl<D: AsRef<[u8]> + Sync> KdSource for KdFile<D> {
    fn bounds(&self) -> Aabb {
        KdFile::bounds(self)
    }

    fn root(&self) -> u32 {
        0
    }

    #[inline]
    fn node(&self, n: u32) -> SourceNode<'_> {
        let words = self.nodes();
        // from_bytes validated every word, child block and leaf range; a
        // word that still fails to decode reads as an empty leaf.
        match word::decode(words[n as usize]) {
            Ok(NodeWord::Inner {
                axis,
                t_ref,
                block,
                pos,
            }) => {
                let first = block + u32::from(t_ref);
                let t_ref = match t_ref.then(|| word::decode(words[block as usize])) {
                    Some(Ok(NodeWord::TRef { tri })) => Some(tri),
                    _ => None,
                };
                SourceNode::Inner {
                    axis,
                    pos,
                    left: first,
                    right: first + 1,
                    t_ref,
                }
            }
            Ok(w @ (NodeWord::Leaf32 { .. } | NodeWord::Leaf16 { .. })) => {
                SourceNode::Leaf(LeafTris::File(self.leaf(w)))
            }
            _ => SourceNode::Leaf(LeafTris::Ids(&[])),
        }
    }

    #[inline]
    fn triangle(&self, t: u32) -> [Vec3; 3] {
        KdFile::triangle(self, t)
    }

    #[inline]
    fn input_id(&self, t: u32) -> TriId {
        TriId(KdFile::input_id(self, t))
    }
}

/// Scalar traversal of any source.
pub struct Scalar<'a, S>(pub &'a S);

impl<S: KdSource> ClosestHit for Scalar<'_, S> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        traverse(self.0, ray)
    }
}

impl ClosestHit for TreeTracer<'_> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        traverse(self, ray)
    }
}

/// Tests every triangle: the reference.
pub struct BruteForce<'a>(pub &'a TriangleColumns);

impl ClosestHit for BruteForce<'_> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        brute_force(self.0, ray)
    }
}

/// The closest hit by testing every triangle.
pub fn brute_force(scene: &TriangleColumns, ray: &Ray) -> Hit {
    let rp = RayPrecomp::new(ray);
    let mut best = Hit::MISS;
    for i in 0..scene.len() as u32 {
        if let Some(t) = intersect_triangle(&rp, &scene.tri(i), ray.tmin, best.t.min(ray.tmax)) {
            best.offer(t, TriId(i));
        }
    }
    best
}

/// The `[t0, t1]` interval of the ray inside the closed box `bounds`, or
/// `None` when it clearly misses.
pub fn clip_ray(bounds: &Aabb, ray: &Ray, inv_dir: Vec3) -> Option<(f32, f32)> {
    let mut t0 = ray.tmin;
    let mut t1 = ray.tmax;
    for k in 0..3 {
        let o = ray.origin[k];
        if ray.dir[k] == 0.0 {
            // Parallel to the slab: inside it for every t, or never. (The
            // general formula would give 0 · ∞ = NaN on a face plane.)
            if o < bounds.min[k] || o > bounds.max[k] {
                return None;
            }
            continue;
        }
        let a = (bounds.min[k] - o) * inv_dir[k];
        let b = (bounds.max[k] - o) * inv_dir[k];
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    if t1 < ray.tmin || t0 > t1 + t1 * MARGIN {
        None
    } else {
        Some((t0, t1))
    }
}

/// Which children a ray visits at a split, and over which intervals: the
/// one decision rule of every traverser (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SplitVisit {
    /// The interval in the left child, if it is visited.
    pub left: Option<(f32, f32)>,
    pub right: Option<(f32, f32)>,
    /// Whether the left child comes first along the ray.
    pub left_first: bool,
}

#[inline]
pub fn split_visit(o: f32, d: f32, inv_d: f32, pos: f32, tmin: f32, tmax: f32) -> SplitVisit {
    let ts = (pos - o) * inv_d;
    let below_first = o < pos || (o == pos && d <= 0.0);
    let (near, far) = if o == pos {
        // The ray starts in the plane (or lies in it: ts is NaN). The far
        // cell touches it only at t = 0, but a triangle there may be
        // computed a rounding error beyond 0, so both cells are visited.
        (Some((tmin, tmax)), Some((tmin, tmax)))
    } else if ts <= 0.0 || ts - ts * MARGIN > tmax {
        (Some((tmin, tmax)), None)
    } else if ts + ts * MARGIN < tmin {
        (None, Some((tmin, tmax)))
    } else {
        (Some((tmin, ts.min(tmax))), Some((ts.max(tmin), tmax)))
    };
    if below_first {
        SplitVisit {
            left: near,
            right: far,
            left_first: true,
        }
    } else {
        SplitVisit {
            left: far,
            right: near,
            left_first: false,
        }
    }
}

/// The scalar traversal of an in-memory tree.
pub fn closest_hit(tree: &TreeIr, scene: &TriangleColumns, ray: &Ray) -> Hit {
    traverse(&TreeTracer { tree, scene }, ray)
}

/// Front-to-back traversal with a stack of `(node, tmin, tmax)` entries.
pub fn traverse<S: KdSource + ?Sized>(src: &S, ray: &Ray) -> Hit {
    let inv_dir = Vec3::ONE / ray.dir;
    let Some((t0, t1)) = clip_ray(&src.bounds(), ray, inv_dir) else {
        return Hit::MISS;
    };
    let rp = RayPrecomp::new(ray);
    let mut best = Hit::MISS;
    let mut stack = [(0u32, 0f32, 0f32); MAX_STACK];
    let mut sp = 0usize;
    let (mut node, mut tmin, mut tmax) = (src.root(), t0, t1);
    let test = |t_src: u32, best: &mut Hit| {
        if let Some(t) =
            intersect_triangle(&rp, &src.triangle(t_src), ray.tmin, best.t.min(ray.tmax))
        {
            best.offer(t, src.input_id(t_src));
        }
    };
    loop {
        match src.node(node) {
            SourceNode::Inner {
                axis,
                pos,
                left,
                right,
                t_ref,
            } => {
                if let Some(tri) = t_ref {
                    // Early intersection (Choi et al. 2013, §4.2): a hoisted
                    // triangle is tested when its node is visited.
                    test(tri, &mut best);
                }
                let k = axis as usize;
                let v = split_visit(ray.origin[k], ray.dir[k], inv_dir[k], pos, tmin, tmax);
                let (first, second) = if v.left_first {
                    ((left, v.left), (right, v.right))
                } else {
                    ((right, v.right), (left, v.left))
                };
                match (first.1, second.1) {
                    (Some(a), Some(b)) => {
                        // The traversal depth is at most MAX_DEPTH (checked
                        // by TreeIr::validate and KdFile::from_bytes).
                        stack[sp] = (second.0, b.0, b.1);
                        sp += 1;
                        (node, tmin, tmax) = (first.0, a.0, a.1);
                        continue;
                    }
                    (Some(a), None) => {
                        (node, tmin, tmax) = (first.0, a.0, a.1);
                        continue;
                    }
                    (None, Some(b)) => {
                        (node, tmin, tmax) = (second.0, b.0, b.1);
                        continue;
                    }
                    (None, None) => {}
                }
            }
            SourceNode::Leaf(tris) => tris.for_each(|t| test(t, &mut best)),
        }
        // Resume with the nearest pending cell that may still hold a hit
        // at or before the best one. Once a hit lies inside the current
        // cell this skips every pending cell, which is the early exit. A
        // cell is never skipped on a tie: a triangle there could hit at the
        // same t with a smaller id.
        loop {
            if sp == 0 {
                return best;
            }
            sp -= 1;
            (node, tmin, tmax) = stack[sp];
            if tmin - tmin * MARGIN <= best.t {
                break;
            }
        }
    }
}
