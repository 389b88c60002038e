//! Secondary rays over a wide box hierarchy of the tree's leaves, built
//! in memory when a tree is opened for it: per leaf the tight bounds of
//! its triangles clipped to its cell, per inner node the union of its
//! children's (and of its hoisted triangle's part of its cell), and the
//! tree collapsed into nodes of up to eight such boxes, empty cells left
//! out, a subtree of at most eight distinct triangles one leaf where that
//! costs less (`Plan`); a slim tree's hoisted triangle takes a slot of its node as a
//! leaf of one triangle, boxed by its part of the node's cell. A single
//! ray tests a node's eight boxes in the lanes of one AVX2 register and
//! visits the ones it enters, nearest first for a closest
//! hit, in slot order for an any-hit query, and tests a leaf's triangles
//! eight at a time in the lanes of another (their vertices read from
//! a copy in triangle order); a packet of 16 rays (any-hit queries, or
//! closest hits where asked) decides every box in every lane, each lane
//! up to its best hit so far, visits a child with the lanes that enter it
//! (in the order of its first lane's entry distances), tests a leaf's
//! triangles in those lanes with the packet kernel (a leaf that few
//! lanes enter with the single walk's test, lane by lane), and hands a
//! child that few lanes enter to the single walk, lane by lane. The
//! renderer's AO rays run as closest hits in these packets at 1.2–1.7×
//! Embree's speed with AVX-512 and 0.93–1.16× with AVX2, where the kd
//! packets' 16-lane loops, two halves in AVX2, ran them at 0.54–0.76×.
//!
//! **Why.** A short secondary ray descends the kd-tree's ~30 levels to
//! where it starts and then crosses ~10 cells, 7 of them empty
//! (ravenbridge's AO rays, perf-notes "Ropes"): ~60 binary steps. The
//! boxes drop the empty cells and take about three levels a step: 9.5
//! node visits an AO ray there, and a renderer's AO packet takes 2.8
//! node visits a ray against the kd packets' 15.4 steps. The renderer's
//! AO frame runs 1.05–1.4× faster on four of the shared scenes
//! (`render --secondary wide`; perf-notes "Secondary rays over wide
//! boxes"). It costs memory besides the tree (96 and 113 bytes a
//! triangle on dieselpower and ravenbridge, whose std trees take 21 and
//! 31; 36 of them the vertex copy), so it is built on request.
//!
//! **A single any-hit walk takes the children in slot order**, not
//! nearest first, as Embree's occlusion walk does. An AO ray starts on a
//! surface: the boxes it enters first are those at its origin, of the
//! surface it leaves, which seldom block it. In slot order ravenbridge's
//! AO rays take 9.5 node visits and 7.0 triangle tests a ray against
//! nearest first's 13.0 and 13.9, and run 1.4× as fast (1.01–1.04× on
//! dieselpower, candela_city and black_forest); the slots sorted by box
//! area, largest first, visit as many nodes (9.4) and run 4 % slower,
//! the children no longer in their memory order. Packets keep their
//! first lane's nearest-first order: in slot order they ran ravenbridge's
//! AO rays 1.3× as fast but candela_city's and black_forest's 0.85–0.9×.
//!
//! **Exact, as the other walks.** A triangle's part of a leaf's cell lies
//! in that leaf's box (the clip's bounds are rounded outward, and padded
//! by [`PAD`] of their magnitude), and every ancestor's box holds its
//! children's, so the ray enters every box that holds a hit point. A box
//! is visited when its entry distance lies within [`MARGIN`] of its exit
//! and of the best hit so far (ties included: the smaller input id wins,
//! as in brute force), so rounding of the slab distances never drops one.
//! A hoisted triangle's slot holds its part of its kd node's cell (a
//! part outside lies in the cells of other leaves that list it). A
//! triangle may be tested again in another leaf, which changes nothing.
//! Rays whose direction has a component so small that its inverse
//! overflows go to the walk from the root.

use super::packet::{
    Best, LANES, Lanes, MIN_LANES, OccluderCache, Occluders, Packet, PacketTracer, all_lanes, bits,
    test_cached, test_triangle, test_triangle_of, write_hits,
};
use super::{
    ClosestHit, Hit, KdSource, MARGIN, Scalar, SourceNode, TraceStats, Walk, test_one, walk_ray,
};
use crate::geom::{Aabb, Ray, RayPrecomp, clip_triangle};
use crate::tree::MAX_DEPTH;
use glam::Vec3;
use std::mem::MaybeUninit;
use thiserror::Error;

/// Boxes a node holds: one AVX2 register of `f32` per plane.
pub const WIDTH: usize = 8;

/// Relative padding of every box: the clip's bounds are already rounded
/// outward; this covers a hit point that the watertight test accepts a
/// rounding off its triangle.
pub const PAD: f32 = 1.0 / (1 << 18) as f32;

/// A child slot that holds a leaf: `LEAF | start` of its list in
/// [`WideBoxes`]'s `tris`.
const LEAF: u32 = 1 << 31;
/// An unused slot (its box is empty, so it is never entered).
const NONE: u32 = u32::MAX;

/// Pending nodes a walk can hold: each level of the hierarchy (at most
/// one a level of the kd-tree) pushes at most `WIDTH - 1` more than it
/// pops.
const STACK: usize = WIDTH * (MAX_DEPTH as usize + 2);

/// A packet with this few lanes left at a node walks them alone from
/// there ([`walk_alone`]): a packet's node visit decides all 8 boxes in
/// all 16 lanes, where the single walk decides one ray's 8 in one AVX2
/// register. On the renderer's AO rays of the six shared scenes, packets
/// run 1.05–1.22× as fast (ravenbridge, which keeps 5.0 lanes a node
/// visit, most); 1 and 3 lanes ran within 3 % of 2.
const ALONE_LANES: u32 = 2;

/// [`ALONE_LANES`] for the AVX2 and baseline copies, whose packet
/// operations take two 8-lane halves where the single walk's box and
/// leaf tests are the same AVX2 code as in the AVX-512 copy. At 7 rather
/// than 5, AO packets run 1.02–1.09× as fast on ravenbridge and 1.04–1.07×
/// on bunny_scan, where packets keep fewest lanes, and 0.96–1.01× on the
/// other four shared scenes (two rounds each); 5 rather than 2 gained
/// 1.00–1.08× before the leaves were tested in lanes. On an AVX2-only
/// AMD EPYC (Zen 3), 2 to 7 run within the noise of one another and more
/// lanes lose (10: dieselpower's AO packets 0.93×, 15: 0.80×).
const ALONE_LANES_HALVES: u32 = 7;

/// A leaf that this few lanes of a packet enter is tested by each lane
/// alone, eight triangles at a time ([`leaf_in_lanes`]), rather than a
/// triangle at a time in all 16 lanes: on ravenbridge's AO packets 35 %
/// of those triangle tests have one lane, 19 % two. The renderer's AO
/// rays run 1.00–1.09× as fast on the six shared scenes (bunny_scan
/// most; AVX-512, two rounds); at 1, 3 and 4 lanes within noise of 2.
const LEAF_ALONE_LANES: u32 = 2;

/// [`LEAF_ALONE_LANES`] for the AVX2 copy, whose triangle test in a
/// packet takes two 8-lane halves: AO rays 1.08–1.29× as fast on
/// dieselpower, ravenbridge and bunny_scan, against 1.07–1.25× at 2
/// lanes.
const LEAF_ALONE_LANES_HALVES: u32 = 4;

/// Why a tree has no wide boxes.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum WideError {
    /// More nodes than the source holds, or deeper than any tree (a file
    /// whose children share subtrees or loop).
    #[error("the tree's nodes do not form a tree of at most {0} nodes")]
    NotATree(usize),
}

/// One node: the boxes of up to eight children, plane by plane, and
/// their references.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct WideNode {
    /// Rows 0–2 the boxes' lower x, y and z planes, rows 3–5 their
    /// upper ones: a ray picks its entry and exit rows once
    /// ([`Slabs::new`]) and a node visit loads them without a choice.
    planes: [[f32; WIDTH]; 6],
    /// A child node's index, `LEAF | start` of a leaf's list in
    /// [`WideBoxes`]'s `tris`, or `NONE`.
    child: [u32; WIDTH],
    /// Bit `j` set where slot `j` holds a leaf.
    leaves: u32,
    /// Bit `j` set where slot `j` holds a child.
    used: u32,
}

impl WideNode {
    const EMPTY: WideNode = WideNode {
        planes: [
            [f32::INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
        ],
        child: [NONE; WIDTH],
        leaves: 0,
        used: 0,
    };
}

/// The wide box hierarchy of one tree ([`WideBoxes::new`]).
pub struct WideBoxes {
    nodes: Vec<WideNode>,
    /// Per leaf slot (`LEAF | start`): its triangle count at `start`
    /// and its first lane in `ids` at `start + 1`.
    tris: Vec<u32>,
    /// Every leaf's triangles (source numbering), leaf after leaf, and
    /// `WIDTH` zeros, so that eight lanes from any leaf's first can be
    /// loaded.
    ids: Vec<u32>,
    /// Per triangle (source numbering) its vertices, nine `f32` in a row
    /// for the leaf tests in lanes, and one triangle of zeros after the
    /// last; empty where no leaf lists a triangle.
    verts: Vec<[Vec3; 3]>,
    leaves: usize,
    /// The tree's identity ([`Walk::tag`]).
    tag: (usize, usize),
}

/// `b` grown by [`PAD`] of its magnitude on every side.
fn padded(b: &Aabb) -> Aabb {
    let grow = |x: Vec3| x.abs() * PAD + Vec3::splat(f32::MIN_POSITIVE);
    Aabb::new(b.min - grow(b.min), b.max + grow(b.max))
}

impl WideBoxes {
    /// The hierarchy of the tree `walk` views: one pass computes every
    /// node's tight box (each reference clipped to its leaf's cell, the
    /// leaves in parallel), a second plans where the kd subtrees are cut
    /// into wide nodes (`Plan`), a third lays the nodes out top-down as
    /// planned, and a fourth pulls child nodes into their parent's free
    /// slots. Errors when the nodes do not form a tree (a file not
    /// validated).
    pub fn new<'a, W: Walk<'a>>(walk: W) -> Result<WideBoxes, WideError> {
        let n_ids = walk.tag().1;
        let limit = walk.step_limit() as usize;
        let (tight, hoist_boxes, post) = tight_boxes(walk, n_ids, limit, leaf_box)?;
        let is_node = |c: u32| (c as usize) < n_ids;
        let plan = Plan::new(walk, &tight, &hoist_boxes, &post);
        let mut nodes = vec![WideNode::EMPTY];
        let mut leaves = 0usize;
        let mut tris: Vec<u32> = Vec::new();
        let mut all_ids: Vec<u32> = Vec::new();
        // (kd node, wide node it fills)
        let mut todo = vec![(0u32, 0u32)];
        if !is_node(0) {
            // An empty tree: a root without children.
            todo.clear();
        }
        while let Some((kd, w)) = todo.pop() {
            let mut front: Vec<(u32, bool)> = Vec::with_capacity(WIDTH + 1);
            let mut hoist = None;
            match walk.node(kd) {
                SourceNode::Leaf(tris) => {
                    // Only the root can be a leaf here.
                    if !tris.is_empty() {
                        front.push((kd, false));
                    }
                }
                SourceNode::Inner(i) => {
                    // Its hoisted triangle, where it has a part of the cell.
                    hoist = i
                        .t_ref
                        .map(|t| (t, hoist_boxes[&kd]))
                        .filter(|(_, part)| !part.is_empty());
                    // Its children as the plan spreads them over its
                    // slots, one kept free for the hoisted triangle.
                    plan.place_children(kd, plan.own_slots(kd), &mut front);
                }
            }
            let mut slots: Vec<(Aabb, u32)> = Vec::with_capacity(WIDTH);
            for &(c, merged) in &front {
                let child = match walk.node(c) {
                    _ if merged => {
                        leaves += 1;
                        let ids = plan.subtree_tris(c);
                        LEAF | push_run(&mut tris, &mut all_ids, ids.into_iter(), limit)?
                    }
                    SourceNode::Leaf(list) => {
                        leaves += 1;
                        let ids = (0..list.len()).map(|i| list.get(i));
                        LEAF | push_run(&mut tris, &mut all_ids, ids, limit)?
                    }
                    SourceNode::Inner(_) => {
                        let id = nodes.len() as u32;
                        nodes.push(WideNode::EMPTY);
                        todo.push((c, id));
                        id
                    }
                };
                slots.push((tight[c as usize], child));
            }
            // The hoisted triangle as a leaf of its own in the free slot,
            // boxed by its part of the kd node's cell: a ray tests it only
            // where it enters that part, not at every visit of the node
            // (none where the part is empty), and `pull_up` can take the
            // node into its parent like any other. `small`'s AO packets
            // test 13 % fewer triangles a ray on bunny_scan than with the
            // triangle tested at every visit, 12 % on black_forest, and
            // its AO frame runs 1.02–1.08× as fast there.
            if let Some((t, part)) = hoist {
                let start = push_run(&mut tris, &mut all_ids, [t].into_iter(), limit)?;
                slots.push((part, LEAF | start));
            }
            let node = &mut nodes[w as usize];
            for (slot, (b, child)) in slots.into_iter().enumerate() {
                let b = padded(&b);
                for k in 0..3 {
                    node.planes[k][slot] = b.min[k];
                    node.planes[3 + k][slot] = b.max[k];
                }
                node.child[slot] = child;
                if child & LEAF != 0 {
                    node.leaves |= 1 << slot;
                }
            }
        }
        let nodes = pull_up(&nodes);
        let n_tris = all_ids.iter().map(|&t| t as usize + 1).max().unwrap_or(0);
        let mut verts = Vec::new();
        if n_tris > 0 {
            use rayon::prelude::*;
            // Every triangle up to the last listed once, in order and in
            // parallel, rather than once a reference; and one of zeros, so
            // that `block_hits_avx2` reads four `f32` from any triangle's
            // last.
            verts = (0..n_tris as u32)
                .into_par_iter()
                .map(|t| walk.triangle(t))
                .collect();
            verts.push([Vec3::ZERO; 3]);
        }
        all_ids.extend([0; WIDTH]);
        Ok(WideBoxes {
            nodes,
            tris,
            ids: all_ids,
            verts,
            leaves,
            tag: walk.tag(),
        })
    }

    /// Whether these are the boxes of the tree `walk` views (the walks
    /// over boxes of another tree go from the root instead).
    pub fn is_of<'a, W: Walk<'a>>(&self, walk: W) -> bool {
        self.tag == walk.tag()
    }

    /// Bytes held in memory (not part of the tree's bytes).
    pub fn bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<WideNode>()
            + self.tris.len() * 4
            + self.ids.len() * 4
            + self.verts.len() * std::mem::size_of::<[Vec3; 3]>()
    }

    /// Nodes of the hierarchy.
    pub fn nodes(&self) -> usize {
        self.nodes.len()
    }

    /// Non-empty leaves it holds.
    pub fn leaves(&self) -> usize {
        self.leaves
    }
}

/// Appends a leaf's run of triangles `ids` (its count and first lane to
/// `tris`, the triangles to `all_ids`) and returns its `start` in `tris`.
/// Errors where the numbering would overflow.
fn push_run(
    tris: &mut Vec<u32>,
    all_ids: &mut Vec<u32>,
    ids: impl ExactSizeIterator<Item = u32>,
    limit: usize,
) -> Result<u32, WideError> {
    let start = tris.len();
    if start + 2 >= LEAF as usize || all_ids.len() + ids.len() >= u32::MAX as usize {
        return Err(WideError::NotATree(limit));
    }
    tris.push(ids.len() as u32);
    tris.push(all_ids.len() as u32);
    all_ids.extend(ids);
    Ok(start as u32)
}

/// The same hierarchy with every child node that fits into its
/// parent's free slots taken into it (its boxes replace its own), and the
/// nodes renumbered from the root: the [`Plan`] spreads every node that
/// fits, but keeps a node with a hoisted triangle whole, and such a node
/// (its triangle's slot with its children's) can still fit.
fn pull_up(old: &[WideNode]) -> Vec<WideNode> {
    let slots = |n: &WideNode| n.child.iter().filter(|&&c| c != NONE).count();
    let mut out: Vec<WideNode> = Vec::with_capacity(old.len());
    if old.is_empty() {
        return out;
    }
    out.push(old[0]);
    let mut at = 0usize;
    while at < out.len() {
        let mut n = out[at];
        // Take in the child that fits with the most slots, while one fits.
        loop {
            let used = slots(&n);
            let mut pick: Option<(usize, usize)> = None;
            for j in 0..WIDTH {
                let c = n.child[j];
                if c == NONE || c & LEAF != 0 {
                    continue;
                }
                let cn = &old[c as usize];
                let k = slots(cn);
                if used - 1 + k <= WIDTH && pick.is_none_or(|(_, b)| k > b) {
                    pick = Some((j, k));
                }
            }
            let Some((j, _)) = pick else { break };
            let cn = old[n.child[j] as usize];
            // Slot `j` takes the child's first slot, free slots the rest.
            let free_slots: Vec<usize> = (0..WIDTH).filter(|&s| n.child[s] == NONE).collect();
            let mut free = free_slots.into_iter();
            let mut first = true;
            for s in 0..WIDTH {
                if cn.child[s] == NONE {
                    continue;
                }
                let dst = if first {
                    first = false;
                    j
                } else {
                    free.next().expect("the child fits")
                };
                for row in 0..6 {
                    n.planes[row][dst] = cn.planes[row][s];
                }
                n.child[dst] = cn.child[s];
            }
            if first {
                // A child without slots: its own slot goes empty.
                n.child[j] = NONE;
                for (row, plane) in n.planes.iter_mut().enumerate() {
                    plane[j] = WideNode::EMPTY.planes[row][0];
                }
            }
        }
        // Renumber the inner children into `out`.
        n.leaves = 0;
        n.used = 0;
        for j in 0..WIDTH {
            let c = n.child[j];
            if c == NONE {
                continue;
            }
            n.used |= 1 << j;
            if c & LEAF != 0 {
                n.leaves |= 1 << j;
            } else {
                n.child[j] = out.len() as u32;
                out.push(old[c as usize]);
            }
        }
        out[at] = n;
        at += 1;
    }
    out
}

/// Every kd node's tight box: its references clipped to its cell, its
/// hoisted triangle's part, its children's boxes; empty for a subtree
/// without triangles. Errors when the nodes do not form a tree.
fn tight_boxes<'a, W: Walk<'a>>(
    walk: W,
    n_ids: usize,
    limit: usize,
    leaf: impl Fn(W, u32, &Aabb) -> Aabb + Sync,
) -> Result<(Vec<Aabb>, HoistBoxes, Vec<u32>), WideError> {
    use rayon::prelude::*;
    let mut tight = vec![Aabb::EMPTY; n_ids];
    let mut hoists = HoistBoxes::new();
    if n_ids == 0 {
        return Ok((tight, hoists, Vec::new()));
    }
    // Depth-first, every node with its cell: the leaves listed for the
    // clipping, which runs in parallel (ravenbridge's 1.3 M references),
    // and the inner nodes in post-order, each after its children.
    let mut leaves: Vec<(u32, Aabb)> = Vec::new();
    let mut inner: Vec<(u32, Aabb)> = Vec::new();
    let mut stack: Vec<(u32, Aabb, u32, bool)> = vec![(0, walk.bounds(), 0, false)];
    let mut steps = 0usize;
    while let Some((n, cell, depth, done)) = stack.pop() {
        match walk.node(n) {
            SourceNode::Leaf(_) => {
                steps += 1;
                if steps > limit {
                    return Err(WideError::NotATree(limit));
                }
                leaves.push((n, cell));
            }
            SourceNode::Inner(_) if done => inner.push((n, cell)),
            SourceNode::Inner(i) => {
                steps += 1;
                if steps > limit || depth > MAX_DEPTH {
                    return Err(WideError::NotATree(limit));
                }
                stack.push((n, cell, depth, true));
                let (l, r) = cell.split(usize::from(i.axis), i.pos);
                for (c, b) in [(i.left, l), (i.right, r)] {
                    if (c as usize) < n_ids {
                        stack.push((c, b, depth + 1, false));
                    }
                }
            }
        }
    }
    let clipped: Vec<Aabb> = leaves
        .par_iter()
        .map(|&(n, cell)| leaf(walk, n, &cell))
        .collect();
    for (&(n, _), b) in leaves.iter().zip(clipped) {
        tight[n as usize] = b;
    }
    let mut post = Vec::with_capacity(inner.len());
    for (n, cell) in inner {
        post.push(n);
        let SourceNode::Inner(i) = walk.node(n) else {
            unreachable!("listed as an inner node")
        };
        let mut b = Aabb::EMPTY;
        if let Some(t) = i.t_ref {
            if let Some(c) = clip_triangle(&walk.triangle(t), &cell) {
                b = c;
            }
            hoists.insert(n, b);
        }
        for c in [i.left, i.right] {
            if (c as usize) < n_ids {
                b = b.union(&tight[c as usize]);
            }
        }
        tight[n as usize] = b;
    }
    Ok((tight, hoists, post))
}

/// How the kd subtrees are cut into wide nodes: per kd node and number
/// of slots `j` (1 to [`WIDTH`]), the least expected cost of the wide
/// nodes and leaves that cover its subtree in at most `j` slots of a
/// parent, and whether the node takes one slot itself ([`Plan::TAKE`]),
/// takes one slot as a single leaf of its subtree's distinct triangles
/// ([`Plan::MERGE`]) or spreads its children over them (the dynamic
/// programme of Ylitie, Karras & Laine 2017 for wide BVHs). A box's cost
/// is its surface area (the chance that a ray which enters its parent
/// enters it) times [`LEAF_VISIT`] and [`TRIANGLE_TEST`] per triangle for
/// a leaf, one for a node. A node with a hoisted triangle is never
/// spread or merged, as its triangle's slot belongs to it.
///
/// Against a greedy top-down collapse (open the child with the largest
/// box until the node holds eight), which leaves the nodes at the bottom
/// with few slots, the hierarchy has a quarter fewer nodes (bunny_scan
/// 25,373 → 19,035; 146 → 125 bytes a triangle in all) and the
/// renderer's AO packets run 1.02–1.07× as fast. The plan holds 40
/// bytes a kd node while the boxes are built (black_forest's peak 360
/// MB against 321) and takes a seventh of their time (1.07 s against
/// 0.93).
///
/// A merged subtree holds at most [`WIDTH`] distinct triangles (a run of
/// the single walk's lanes), each once where its kd leaves repeat them
/// (3.8 references a triangle on bunny_scan): the hierarchy takes 15 %
/// fewer bytes there (125 → 106 a triangle; dieselpower 96 → 85,
/// ravenbridge 113 → 106) for the same instructions a ray.
struct Plan<'w, W> {
    walk: W,
    tight: &'w [Aabb],
    hoists: &'w HoistBoxes,
    /// Per kd node, `cost[j - 1]` for `j` slots.
    cost: Vec<[f32; WIDTH]>,
    /// Per kd node, `choice[j - 1]`: [`Plan::TAKE`], [`Plan::PASS`] (its
    /// one child with boxes takes the `j` slots) or the left child's
    /// share of them.
    choice: Vec<[u8; WIDTH]>,
}

impl<'w, 'a, W: Walk<'a>> Plan<'w, W> {
    const TAKE: u8 = 0;
    const PASS: u8 = u8::MAX;
    const MERGE: u8 = u8::MAX - 1;

    /// The plan of a tree whose tight boxes are `tight`, hoisted parts
    /// `hoists`, and inner nodes `post` (each after its children).
    fn new(walk: W, tight: &'w [Aabb], hoists: &'w HoistBoxes, post: &[u32]) -> Self {
        let mut plan = Plan {
            walk,
            tight,
            hoists,
            cost: vec![[0.0; WIDTH]; tight.len()],
            choice: vec![[Self::TAKE; WIDTH]; tight.len()],
        };
        let leaf_cost = |k: usize| LEAF_VISIT + TRIANGLE_TEST * k as f32;
        for (n, b) in tight.iter().enumerate() {
            if b.is_empty() {
                continue;
            }
            if let SourceNode::Leaf(list) = walk.node(n as u32) {
                plan.cost[n] = [b.surface_area() as f32 * leaf_cost(list.len()); WIDTH];
            }
        }
        let mut sets: std::collections::HashMap<u32, Vec<u32>> = Default::default();
        for &n in post {
            if tight[n as usize].is_empty() {
                continue;
            }
            let SourceNode::Inner(i) = walk.node(n) else {
                unreachable!("listed as an inner node")
            };
            let hoisted = i.t_ref.is_some();
            let kids = plan.kids(n);
            let area = tight[n as usize].surface_area() as f32;
            let mut own = area + plan.spread(kids, plan.own_slots(n)).0;
            let mut take = Self::TAKE;
            // The children's sets are taken out even where this node
            // cannot merge, so that the map holds only those of nodes
            // whose parent is still to come.
            if let Some(set) = plan.merged(kids, &mut sets, WIDTH).filter(|_| !hoisted) {
                let m = area * leaf_cost(set.len());
                if m < own {
                    own = m;
                    take = Self::MERGE;
                }
                sets.insert(n, set);
            }
            let mut cost = [own; WIDTH];
            let mut choice = [take; WIDTH];
            if !hoisted {
                for j in 2..=WIDTH {
                    let (c, how) = plan.spread(kids, j);
                    if c < own {
                        cost[j - 1] = c;
                        choice[j - 1] = how;
                    }
                }
            }
            plan.cost[n as usize] = cost;
            plan.choice[n as usize] = choice;
        }
        plan
    }

    /// The distinct triangles of the subtree of the children `kids`, where
    /// they are at most `max` and no node holds a hoisted triangle
    /// (`sets` holds those of the inner children; theirs are taken out).
    fn merged(
        &self,
        kids: ([u32; 2], usize),
        sets: &mut std::collections::HashMap<u32, Vec<u32>>,
        max: usize,
    ) -> Option<Vec<u32>> {
        let mut all = Vec::new();
        let mut whole = true;
        for &c in &kids.0[..kids.1] {
            match self.walk.node(c) {
                SourceNode::Leaf(list) if list.len() <= max => {
                    all.extend((0..list.len()).map(|i| list.get(i)));
                }
                SourceNode::Leaf(_) => whole = false,
                SourceNode::Inner(_) => match sets.remove(&c) {
                    Some(s) => all.extend(s),
                    None => whole = false,
                },
            }
        }
        all.sort_unstable();
        all.dedup();
        (whole && all.len() <= max).then_some(all)
    }

    /// The distinct triangles of the leaves with boxes under `n`, found
    /// again for a merged node as the layout reaches it: the plan keeps a
    /// subtree's set only until its parent is planned, so that it never
    /// holds the sets of the whole tree at once.
    fn subtree_tris(&self, n: u32) -> Vec<u32> {
        let mut all = Vec::new();
        let mut todo = vec![n];
        while let Some(c) = todo.pop() {
            match self.walk.node(c) {
                SourceNode::Leaf(list) => all.extend((0..list.len()).map(|i| list.get(i))),
                SourceNode::Inner(_) => {
                    let (k, m) = self.kids(c);
                    todo.extend_from_slice(&k[..m]);
                }
            }
        }
        all.sort_unstable();
        all.dedup();
        all
    }

    /// The slots inner node `n` has for its children as a wide node: all
    /// but the one its hoisted triangle takes where that has a part of
    /// its cell.
    fn own_slots(&self, n: u32) -> usize {
        WIDTH - usize::from(self.hoists.get(&n).is_some_and(|b| !b.is_empty()))
    }

    /// The children of inner node `n` that hold triangles.
    fn kids(&self, n: u32) -> ([u32; 2], usize) {
        let mut kids = [0; 2];
        let mut k = 0;
        if let SourceNode::Inner(i) = self.walk.node(n) {
            for c in [i.left, i.right] {
                if (c as usize) < self.tight.len() && !self.tight[c as usize].is_empty() {
                    kids[k] = c;
                    k += 1;
                }
            }
        }
        (kids, k)
    }

    /// The least cost of a node's children `kids` (as [`Plan::kids`]) in
    /// at most `s` slots, and how.
    fn spread(&self, kids: ([u32; 2], usize), s: usize) -> (f32, u8) {
        match kids {
            (_, 0) => (0.0, Self::PASS),
            ([c, _], 1) => (self.cost[c as usize][s - 1], Self::PASS),
            ([l, r], _) => {
                let mut best = (f32::INFINITY, 1);
                for k in 1..s {
                    let c = self.cost[l as usize][k - 1] + self.cost[r as usize][s - k - 1];
                    if c < best.0 {
                        best = (c, k as u8);
                    }
                }
                best
            }
        }
    }

    /// Appends the slots of `n`'s children spread over `s` slots.
    fn place_children(&self, n: u32, s: usize, front: &mut Vec<(u32, bool)>) {
        let kids = self.kids(n);
        match (kids, self.spread(kids, s).1) {
            ((_, 0), _) => {}
            (([c, _], 1), _) => self.place(c, s, front),
            (([l, r], _), k) => {
                self.place(l, usize::from(k), front);
                self.place(r, s - usize::from(k), front);
            }
        }
    }

    /// Appends the slots of `n` given `j` slots.
    fn place(&self, n: u32, j: usize, front: &mut Vec<(u32, bool)>) {
        match self.choice[n as usize][j - 1] {
            Self::TAKE => front.push((n, false)),
            Self::MERGE => front.push((n, true)),
            _ => self.place_children(n, j, front),
        }
    }
}

/// A leaf visit's cost in the [`Plan`], in node visits: the leaf's
/// count and first lane read, and a packet's lanes sorted out.
const LEAF_VISIT: f32 = 1.0;

/// A triangle test's cost in the [`Plan`], in node visits. Packets test
/// a leaf triangle by triangle; at 0.125 the plan merged twice as much on
/// bunny_scan (80 bytes a triangle), but its AO packets took 3 % more
/// instructions a ray, at 0.35 and 0.5 as many as without merges.
const TRIANGLE_TEST: f32 = 0.35;

/// Per kd node with a hoisted triangle, the triangle's part of its cell
/// (empty where it has none).
type HoistBoxes = std::collections::HashMap<u32, Aabb>;

/// The tight box of leaf `n` of cell `cell`: the union of its references
/// clipped to the cell. The references inside the cell come first (their
/// own bounds), and a straddler is clipped only where its bounds in the
/// cell could grow the box (its clip lies in them): the union is the
/// same, and black_forest's boxes take 683 ms on one thread instead of
/// 805 (ravenbridge 240 instead of 263; the clipper is still 39 % of
/// black_forest's).
fn leaf_box<'a, W: Walk<'a>>(walk: W, n: u32, cell: &Aabb) -> Aabb {
    let mut b = Aabb::EMPTY;
    let SourceNode::Leaf(tris) = walk.node(n) else {
        return b;
    };
    for i in 0..tris.len() {
        let tb = Aabb::of_triangle(&walk.triangle(tris.get(i)));
        if cell.contains(&tb) {
            b = b.union(&tb);
        }
    }
    for i in 0..tris.len() {
        let tri = walk.triangle(tris.get(i));
        let tb = Aabb::of_triangle(&tri);
        if cell.contains(&tb) || b.contains(&tb.intersection(cell)) {
            continue;
        }
        if let Some(c) = clip_triangle(&tri, cell) {
            b = b.union(&c);
        }
    }
    b
}

/// The runs of eight lanes a leaf of `n` triangles from lane `first`
/// takes: each run's first lane and the mask of the leaf's lanes in it.
#[inline(always)]
fn leaf_runs(first: usize, n: usize) -> impl Iterator<Item = (usize, u32)> {
    (first..first + n).step_by(WIDTH).map(move |l| {
        let k = (first + n - l).min(WIDTH);
        (l, (1u32 << k) - 1)
    })
}

/// The watertight test of one ray against the eight triangles of
/// `boxes`'s lanes from `l0`, lane by lane, in the operations and order
/// of [`intersect_triangle`]: the lanes hit in `(tmin, tmax]` with their
/// `t` (bit for bit the scalar test's), and the lanes whose `f32`
/// arithmetic cannot decide (the scalar test redoes those in `f64`;
/// [`test_one`] does it for them). The vertices come from `verts`, 36
/// bytes a triangle, where vertices copied into each lane took 40 bytes
/// a reference (272 bytes a triangle in all on ravenbridge, whose leaves
/// hold 5 references a triangle, against 129) for AO packets at most 8 %
/// faster (AVX2 copy) and within 4 % either way (AVX-512). They are read
/// as rows of four `f32`, two lanes a register, and turned into columns
/// by shuffles, not gathered a component at a time: the single walk's AO
/// rays run 1.06× as fast on dieselpower (nine gathers took 84 cycles a
/// leaf).
///
/// # Safety
/// The CPU has AVX2, and `boxes.verts` is not empty.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn block_hits_avx2(
    rp: &RayPrecomp,
    boxes: &WideBoxes,
    l0: usize,
    tmin: f32,
    tmax: f32,
) -> (u32, u32, [f32; WIDTH]) {
    use std::arch::x86_64::*;
    let ids = &boxes.ids[l0..l0 + WIDTH];
    let o = rp.origin.to_array();
    const _: () = assert!(std::mem::size_of::<[Vec3; 3]>() == 9 * 4);
    let verts = boxes.verts.as_ptr().cast::<f32>();
    // Four `f32` from component `c` of lane `l`'s triangle in the low
    // half, of lane `l + 4`'s in the high half.
    // SAFETY: `Vec3` is three `f32` (`repr(C)`, no padding: asserted
    // above), so triangle `id` is the nine `f32` from `9 * id`; every id
    // in `ids` is a triangle that `verts` (not empty) holds, and `verts`
    // holds one triangle more after the last, so the four `f32` from
    // `9 * id + c` (`c ≤ 8`) lie in it.
    let quad = |l: usize, c: usize| unsafe {
        _mm256_loadu2_m128(
            verts.add(9 * ids[l + 4] as usize + c),
            verts.add(9 * ids[l] as usize + c),
        )
    };
    // Four such rows, lanes `l` and `l + 4` each, turned into four
    // columns of eight lanes.
    let columns = |c: usize| {
        let a = [quad(0, c), quad(1, c), quad(2, c), quad(3, c)];
        let t0 = _mm256_unpacklo_ps(a[0], a[1]);
        let t1 = _mm256_unpackhi_ps(a[0], a[1]);
        let t2 = _mm256_unpacklo_ps(a[2], a[3]);
        let t3 = _mm256_unpackhi_ps(a[2], a[3]);
        [
            _mm256_shuffle_ps::<0x44>(t0, t2),
            _mm256_shuffle_ps::<0xEE>(t0, t2),
            _mm256_shuffle_ps::<0x44>(t1, t3),
            _mm256_shuffle_ps::<0xEE>(t1, t3),
        ]
    };
    let ([c0, c1, c2, c3], [c4, c5, c6, c7]) = (columns(0), columns(4));
    let c8 = {
        let (a0, a1, a2, a3) = (quad(0, 8), quad(1, 8), quad(2, 8), quad(3, 8));
        _mm256_shuffle_ps::<0x44>(_mm256_unpacklo_ps(a0, a1), _mm256_unpacklo_ps(a2, a3))
    };
    let comps = [c0, c1, c2, c3, c4, c5, c6, c7, c8];
    let org = [
        _mm256_set1_ps(o[0]),
        _mm256_set1_ps(o[1]),
        _mm256_set1_ps(o[2]),
    ];
    // The three vertices relative to the origin, permuted: `[x, y, z]` of
    // the test are components `kx, ky, kz`. One arm per permutation
    // `RayPrecomp::new` makes, so that each picks registers by constant
    // indices: picked by the ray's indices, the nine columns went through
    // the stack (a block of eight took 220 instructions, now 180).
    // (Written out: `array::map` is not inlined here, its closure
    // compiled without AVX2.)
    let rel = |i: usize, k: usize| _mm256_sub_ps(comps[3 * i + k], org[k]);
    let verts = |kx: usize, ky: usize, kz: usize| {
        let vert = |i: usize| [rel(i, kx), rel(i, ky), rel(i, kz)];
        [vert(0), vert(1), vert(2)]
    };
    let [a, bb, c] = match (rp.kx, rp.ky, rp.kz) {
        (1, 2, 0) => verts(1, 2, 0),
        (2, 1, 0) => verts(2, 1, 0),
        (2, 0, 1) => verts(2, 0, 1),
        (0, 2, 1) => verts(0, 2, 1),
        (0, 1, 2) => verts(0, 1, 2),
        (1, 0, 2) => verts(1, 0, 2),
        // No other `RayPrecomp::new` makes; every lane to the scalar test.
        _ => return (0, (1 << WIDTH) - 1, [0.0; WIDTH]),
    };
    let (sx, sy, sz) = (
        _mm256_set1_ps(rp.sx),
        _mm256_set1_ps(rp.sy),
        _mm256_set1_ps(rp.sz),
    );
    let (sub, mul, add) = (_mm256_sub_ps, _mm256_mul_ps, _mm256_add_ps);
    let ax = sub(a[0], mul(sx, a[2]));
    let ay = sub(a[1], mul(sy, a[2]));
    let bx = sub(bb[0], mul(sx, bb[2]));
    let by = sub(bb[1], mul(sy, bb[2]));
    let cx = sub(c[0], mul(sx, c[2]));
    let cy = sub(c[1], mul(sy, c[2]));
    let u = sub(mul(cx, by), mul(cy, bx));
    let v = sub(mul(ax, cy), mul(ay, cx));
    let w = sub(mul(bx, ay), mul(by, ax));
    let sign = _mm256_set1_ps(-0.0);
    let abs = |x: __m256| _mm256_andnot_ps(sign, x);
    let tiny = _mm256_set1_ps(f32::MIN_POSITIVE);
    // `edges_need_f64`: `maxps`/`minps` return their second operand where
    // either is NaN, as `min_of` does.
    let m = _mm256_min_ps(_mm256_min_ps(abs(u), abs(v)), abs(w));
    let edges = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_NGE_UQ>(m, tiny)) as u32;
    let zero = _mm256_setzero_ps();
    let lt = |x: __m256| _mm256_cmp_ps::<_CMP_LT_OQ>(x, zero);
    let gt = |x: __m256| _mm256_cmp_ps::<_CMP_GT_OQ>(x, zero);
    let neg = _mm256_or_ps(_mm256_or_ps(lt(u), lt(v)), lt(w));
    let pos = _mm256_or_ps(_mm256_or_ps(gt(u), gt(v)), gt(w));
    let mixed = _mm256_movemask_ps(_mm256_and_ps(neg, pos)) as u32;
    let det = add(add(u, v), w);
    let az = mul(sz, a[2]);
    let bz = mul(sz, bb[2]);
    let cz = mul(sz, c[2]);
    let t_scaled = add(add(mul(u, az), mul(v, bz)), mul(w, cz));
    let t = _mm256_div_ps(t_scaled, det);
    // `t_needs_f64`.
    let under = _mm256_cmp_ps::<_CMP_NGE_UQ>(abs(t_scaled), tiny);
    let over = _mm256_cmp_ps::<_CMP_NLE_UQ>(abs(add(det, t)), _mm256_set1_ps(f32::MAX));
    let t_bad = _mm256_movemask_ps(_mm256_or_ps(under, over)) as u32;
    let within = _mm256_and_ps(
        _mm256_cmp_ps::<_CMP_GT_OQ>(t, _mm256_set1_ps(tmin)),
        _mm256_cmp_ps::<_CMP_LE_OQ>(t, _mm256_set1_ps(tmax)),
    );
    let within = _mm256_movemask_ps(within) as u32;
    let redo = edges | (!mixed & t_bad);
    let hit = !edges & !mixed & !t_bad & within;
    let mut ts = [0f32; WIDTH];
    // SAFETY: `ts` is 8 `f32`, one unaligned vector store.
    unsafe { _mm256_storeu_ps(ts.as_mut_ptr(), t) };
    (hit, redo, ts)
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn block_hits_avx2(
    _: &RayPrecomp,
    _: &WideBoxes,
    _: usize,
    _: f32,
    _: f32,
) -> (u32, u32, [f32; WIDTH]) {
    unreachable!("AVX2 is set only on x86-64")
}

/// Packs eight flags into a byte, flag `i` into bit `i`.
#[inline(always)]
fn mask8(b: [bool; WIDTH]) -> u32 {
    const GATHER: u64 = 0x0102_0408_1020_4080;
    let x = u64::from_le_bytes(b.map(u8::from));
    (x.wrapping_mul(GATHER) >> 56) as u32
}

/// A ray as the box tests read it.
struct Slabs {
    o: [f32; 3],
    inv: [f32; 3],
    /// `inv` times [`REACH`], for the exit distances ([`enter`]).
    far_inv: [f32; 3],
    /// Per axis, the row of [`WideNode`]'s planes where the ray enters
    /// (`k`, or `3 + k` where the direction is negative) and where it
    /// leaves; each below 6.
    rows: [(usize, usize); 3],
    tmin: f32,
}

impl Slabs {
    /// A ray of origin `o`, direction inverse `inv`, from `tmin`, whose
    /// direction is negative on the axes of `neg`.
    #[inline(always)]
    fn new(o: [f32; 3], inv: [f32; 3], neg: [bool; 3], tmin: f32) -> Slabs {
        // By arithmetic, not a select per axis (42 instructions a ray).
        let row = |k: usize| {
            let s = 3 * usize::from(neg[k]);
            (k + s, k + 3 - s)
        };
        let rows = [row(0), row(1), row(2)];
        let far_inv = inv.map(|x| x * REACH);
        Slabs {
            o,
            inv,
            far_inv,
            rows,
            tmin,
        }
    }

    /// The entry and exit planes of axis `k` of `wn`.
    #[inline(always)]
    fn planes<'n>(&self, wn: &'n WideNode, k: usize) -> (&'n [f32; WIDTH], &'n [f32; WIDTH]) {
        let (n, f) = self.rows[k];
        // SAFETY: `Slabs::new`, the only maker of `rows`, keeps them below
        // 6, the rows of `planes`. (Chosen by the signs at each visit, the
        // planes took 17 of a node visit's 60 instructions.)
        unsafe { (wn.planes.get_unchecked(n), wn.planes.get_unchecked(f)) }
    }
}

/// `1 + MARGIN`: the exit distances of the box tests are taken this much
/// further ([`enter`]).
const REACH: f32 = 1.0 + MARGIN;

/// The boxes of `wn` the ray enters in `(tmin, limit]` (bit `j` for slot
/// `j`), and their entry distances. Each axis's entry and exit planes are
/// chosen once by the direction's sign. A NaN (a zero component with the
/// origin in the face plane) compares false and leaves the bound as it
/// was: the ray runs in the closed slab. An empty slot's `∞` planes give
/// an entry at `+∞`.
///
/// A box is entered when its entry distance is at most its exit distance
/// [`MARGIN`] further (and `limit` so much further): the exit distances
/// are found with the inverses times [`REACH`] (`Slabs::far_inv`), so the
/// margin costs no operation after them (as `tf + |tf| · MARGIN` it was
/// three on the chain from a node's load to its mask). For an exit at
/// `tf ≥ 0` that is `tf` plus its margin within a few units in the last
/// place (the margin is 2¹¹ of them); at `tf < 0` it is further back, and
/// such a box is missed either way, as every entry distance is at least
/// `tmin`, which is at least 0 ([`Ray::tmin`], as for every walk).
#[inline(always)]
fn enter(wn: &WideNode, r: &Slabs, limit: f32) -> (u32, [f32; WIDTH]) {
    let p = [r.planes(wn, 0), r.planes(wn, 1), r.planes(wn, 2)];
    let mut near = [0f32; WIDTH];
    let mut hit = [false; WIDTH];
    for j in 0..WIDTH {
        let mut tn = r.tmin;
        let mut tf = limit * REACH;
        for (k, (np, fp)) in p.iter().enumerate() {
            let n = (np[j] - r.o[k]) * r.inv[k];
            let f = (fp[j] - r.o[k]) * r.far_inv[k];
            tn = if n > tn { n } else { tn };
            tf = if f < tf { f } else { tf };
        }
        near[j] = tn;
        hit[j] = tn <= tf;
    }
    (mask8(hit), near)
}

/// [`enter`] in AVX2 intrinsics, the same operations in the same order
/// (`maxps`/`minps` return their second operand where either is NaN, as
/// `enter`'s selects do): LLVM's form of the lane loop assembled its
/// vectors lane by lane.
///
/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn enter_avx2(wn: &WideNode, r: &Slabs, limit: f32) -> (u32, [f32; WIDTH]) {
    use std::arch::x86_64::*;
    // SAFETY: a plane array is 8 `f32`, one unaligned vector load.
    let ld = |a: &[f32; WIDTH]| unsafe { _mm256_loadu_ps(a.as_ptr()) };
    let mut tn = _mm256_set1_ps(r.tmin);
    let mut tf = _mm256_set1_ps(limit * REACH);
    for k in 0..3 {
        let (np, fp) = r.planes(wn, k);
        let o = _mm256_set1_ps(r.o[k]);
        let (inv, far_inv) = (_mm256_set1_ps(r.inv[k]), _mm256_set1_ps(r.far_inv[k]));
        let n = _mm256_mul_ps(_mm256_sub_ps(ld(np), o), inv);
        let f = _mm256_mul_ps(_mm256_sub_ps(ld(fp), o), far_inv);
        tn = _mm256_max_ps(n, tn);
        tf = _mm256_min_ps(f, tf);
    }
    let hit = _mm256_cmp_ps::<_CMP_LE_OQ>(tn, tf);
    let mut near = [0f32; WIDTH];
    // SAFETY: `near` is 8 `f32`, one unaligned vector store.
    unsafe { _mm256_storeu_ps(near.as_mut_ptr(), tn) };
    (_mm256_movemask_ps(hit) as u32, near)
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn enter_avx2(wn: &WideNode, r: &Slabs, limit: f32) -> (u32, [f32; WIDTH]) {
    enter(wn, r, limit)
}

/// The slot of the smallest entry distance among the bits of `m` (not
/// zero).
#[inline(always)]
fn nearest(m: u32, near: &[f32; WIDTH]) -> usize {
    let mut jn = m.trailing_zeros() as usize;
    let mut rest = m & (m - 1);
    while rest != 0 {
        let j = rest.trailing_zeros() as usize;
        rest &= rest - 1;
        if near[j] < near[jn] {
            jn = j;
        }
    }
    jn
}

/// Of the slots of `m` (not zero), the one of the least entry distance
/// `near`; the others are pushed onto `stack` as `entry(slot)`. Shared by
/// the single closest-hit walk (entries carry the distance) and the
/// packets (entries carry the lanes).
#[inline(always)]
fn take_nearest<E: Copy>(
    mut m: u32,
    near: &[f32; WIDTH],
    entry: impl Fn(usize) -> E,
    stack: &mut [MaybeUninit<E>],
    sp: &mut usize,
) -> usize {
    let mut next = m.trailing_zeros() as usize;
    m &= m - 1;
    while m != 0 {
        let j = m.trailing_zeros() as usize;
        m &= m - 1;
        let (keep, push) = if near[j] < near[next] {
            (j, next)
        } else {
            (next, j)
        };
        stack[*sp] = MaybeUninit::new(entry(push));
        *sp += 1;
        next = keep;
    }
    next
}

/// One ray through the hierarchy, nearest box first. `ANY`: stop at the
/// first hit in `(tmin, tmax)`, the boxes taken in slot order; `COUNT`:
/// add the work to `stats` (a node visit is a node step).
#[inline(always)]
pub(crate) fn walk_wide<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool, const AVX2: bool>(
    src: W,
    boxes: &WideBoxes,
    ray: &Ray,
    stats: &mut TraceStats,
) -> Hit {
    let inv = Vec3::ONE / ray.dir;
    let d = ray.dir.to_array();
    let o = ray.origin.to_array();
    let inv_a = inv.to_array();
    if boxes.tag != src.tag() || !boxes_take(o, d, inv_a, ray.tmin, ray.tmax) {
        return walk_ray::<_, ANY, COUNT>(src, ray, stats);
    }
    if COUNT {
        stats.rays += 1;
    }
    let neg = [inv_a[0] < 0.0, inv_a[1] < 0.0, inv_a[2] < 0.0];
    let slabs = Slabs::new(o, inv_a, neg, ray.tmin);
    let rp = RayPrecomp::new(ray);
    descend::<_, ANY, COUNT, AVX2>(src, boxes, ray, &rp, &slabs, 0, Hit::MISS, stats).0
}

/// Whether the boxes take a ray of origin `o`, direction `d` (whose
/// inverse is `inv`) and range `tmin..=tmax`; else it walks from the
/// root. A direction component whose inverse overflows (or a NaN) is
/// left to that walk; an exact zero gives ±∞, which the slab arithmetic
/// handles.
#[inline(always)]
fn boxes_take(o: [f32; 3], d: [f32; 3], inv: [f32; 3], tmin: f32, tmax: f32) -> bool {
    // `&` and `|`, not `&&` and `||`: one branch, not seven.
    let mut take = tmin <= tmax;
    for k in 0..3 {
        take &= (d[k] == 0.0) | inv[k].is_finite();
        take &= o[k].is_finite();
    }
    take
}

/// [`walk_wide`]'s walk of a ray the boxes can take (its direction's
/// inverse finite where the direction is not zero, its origin finite),
/// as `rp` and `slabs`, through the subtree of `root`, from the best hit
/// found so far `best` (`Hit::MISS` from the root; a closest-hit
/// packet's lane passes its own, which culls the boxes beyond it). Also
/// returns the triangle (source numbering) that ended an any-hit walk,
/// or `NONE`.
#[allow(
    clippy::too_many_arguments,
    reason = "the ray's state, passed apart into the inlined walk"
)]
#[inline(always)]
fn descend<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool, const AVX2: bool>(
    src: W,
    boxes: &WideBoxes,
    ray: &Ray,
    rp: &RayPrecomp,
    slabs: &Slabs,
    root: u32,
    mut best: Hit,
    stats: &mut TraceStats,
) -> (Hit, u32) {
    let (nodes, tris, ids) = (&boxes.nodes[..], &boxes.tris[..], &boxes.ids[..]);
    let mut stack = [const { MaybeUninit::<(u32, f32)>::uninit() }; STACK];
    let mut sp = 0usize;
    let mut node = root;
    'walk: loop {
        let wn = &nodes[node as usize];
        if COUNT {
            stats.nodes += 1;
        }
        // An any-hit walk's best hit stays a miss until it stops.
        let limit = if ANY { ray.tmax } else { best.t.min(ray.tmax) };
        let (entered, near) = if AVX2 {
            // SAFETY: `AVX2` is set only where this CPU has AVX2
            // (`WideTracer::walk`).
            unsafe { enter_avx2(wn, slabs, limit) }
        } else {
            enter(wn, slabs, limit)
        };
        // The entered leaves (nearest first for closest hits: a hit
        // shortens the rest).
        let mut lm = entered & wn.leaves;
        while lm != 0 {
            let j = if ANY {
                lm.trailing_zeros() as usize
            } else {
                nearest(lm, &near)
            };
            lm &= !(1 << j);
            if !ANY {
                let cut = best.t.min(ray.tmax);
                if near[j] > cut + cut.abs() * MARGIN {
                    continue;
                }
            }
            let start = (wn.child[j] & !LEAF) as usize;
            let n = tris[start] as usize;
            if COUNT {
                stats.leaves += 1;
                stats.tris += n as u64;
            }
            let first = tris[start + 1] as usize;
            if AVX2 && !boxes.verts.is_empty() {
                // SAFETY: `AVX2` is set only where this CPU has AVX2
                // (`WideTracer::walk`); `verts` is not empty.
                let hit =
                    unsafe { leaf_in_lanes::<_, ANY>(src, boxes, ray, rp, first, n, &mut best) };
                if let Some(t) = hit {
                    return (best, t);
                }
            } else {
                for &t in &ids[first..first + n] {
                    if test_one::<_, ANY>(src, rp, ray, t, &mut best) {
                        return (best, t);
                    }
                }
            }
        }
        let im = entered & !wn.leaves;
        if ANY {
            // An any-hit walk takes its children in slot order (see the
            // module docs; its limit is `tmax` until it stops, so every
            // entered and every pending child is in reach): the first
            // entered next, the others pushed to come off in slot order.
            if im != 0 {
                let next = im.trailing_zeros() as usize;
                let mut rest = im & !(1 << next);
                while rest != 0 {
                    let j = 31 - rest.leading_zeros() as usize;
                    rest &= !(1 << j);
                    stack[sp] = MaybeUninit::new((wn.child[j], 0.0));
                    sp += 1;
                }
                node = wn.child[next];
                continue 'walk;
            }
            if sp == 0 {
                break;
            }
            sp -= 1;
            // SAFETY: every entry below the old `sp` was written.
            node = unsafe { stack[sp].assume_init() }.0;
            continue 'walk;
        }
        // The entered inner children: the nearest next, the others
        // pushed.
        if im != 0 {
            let next = take_nearest(im, &near, |j| (wn.child[j], near[j]), &mut stack, &mut sp);
            let cut = best.t.min(ray.tmax);
            if near[next] <= cut + cut.abs() * MARGIN {
                node = wn.child[next];
                continue 'walk;
            }
        }
        // The next pending node still in reach.
        while sp > 0 {
            sp -= 1;
            // SAFETY: every entry below the old `sp` was written.
            let (c, t) = unsafe { stack[sp].assume_init() };
            let cut = best.t.min(ray.tmax);
            if t <= cut + cut.abs() * MARGIN {
                node = c;
                continue 'walk;
            }
        }
        break;
    }
    (if ANY { Hit::MISS } else { best }, NONE)
}

/// One ray against a leaf's triangles `ids[first..first + n]` of
/// `boxes`, eight at a time in the lanes of [`block_hits_avx2`] (the
/// lanes it cannot decide by [`test_one`]): every hit offered to `best`,
/// or under `ANY` the first in `(tmin, tmax)` kept there and its
/// triangle (source numbering) returned.
///
/// # Safety
/// The CPU has AVX2, and `boxes.verts` is not empty.
#[inline(always)]
unsafe fn leaf_in_lanes<'a, W: Walk<'a>, const ANY: bool>(
    src: W,
    boxes: &WideBoxes,
    ray: &Ray,
    rp: &RayPrecomp,
    first: usize,
    n: usize,
    best: &mut Hit,
) -> Option<u32> {
    for (l0, lanes) in leaf_runs(first, n) {
        let run = &boxes.ids[l0..l0 + WIDTH];
        let limit = best.t.min(ray.tmax);
        // SAFETY: the caller's.
        let (hit, redo, t) = unsafe { block_hits_avx2(rp, boxes, l0, ray.tmin, limit) };
        let (hit, redo) = (hit & lanes, redo & lanes);
        let mut m = hit;
        while m != 0 {
            let l = m.trailing_zeros() as usize;
            m &= m - 1;
            if ANY {
                if t[l] < ray.tmax {
                    *best = Hit {
                        t: t[l],
                        tri: src.input_id(run[l]),
                    };
                    return Some(run[l]);
                }
            } else {
                best.offer(t[l], src.input_id(run[l]));
            }
        }
        let mut m = redo;
        while m != 0 {
            let l = m.trailing_zeros() as usize;
            m &= m - 1;
            if test_one::<_, ANY>(src, rp, ray, run[l], best) {
                return Some(run[l]);
            }
        }
    }
    None
}

/// Up to 16 rays as one packet over the boxes, any-hit queries (`ANY`,
/// `cache`'s triangles first: [`OccluderCache`]) or closest hits: lanes
/// the boxes cannot take (a direction component whose inverse overflows,
/// a non-finite origin) and packets of fewer than [`MIN_LANES`] rays
/// walk alone.
#[inline(always)]
fn wide_packet<
    'a,
    W: Walk<'a>,
    const ANY: bool,
    const COUNT: bool,
    const M: bool,
    const AVX2: bool,
>(
    src: W,
    boxes: &WideBoxes,
    rays: &[Ray],
    out: &mut [Hit],
    stats: &mut TraceStats,
    cache: &mut OccluderCache,
) {
    if rays.len() < MIN_LANES as usize {
        for (r, o) in rays.iter().zip(out.iter_mut()) {
            *o = walk_wide::<_, ANY, COUNT, AVX2>(src, boxes, r, stats);
        }
        return;
    }
    let p = Packet::new(rays);
    let mut best = Best::NONE;
    let mut mask = all_lanes(rays);
    // The lanes the boxes cannot take, from the packet's inverses (the
    // same `1 / d` as the single walk's; divided here per ray they took
    // 2 % of an AO packet's time).
    let mut solo = if boxes.tag != src.tag() {
        mask
    } else {
        // Every lane decided at once (lanes past the last ray repeat the
        // first), without the branches of a lane at a time: they took 45
        // of a bunny_scan AO packet's 830 instructions a ray.
        let mut bad = [false; LANES];
        for (i, b) in bad.iter_mut().enumerate() {
            let mut take = p.tmin[i] <= p.tmax[i];
            for k in 0..3 {
                take &= (p.dir[k][i] == 0.0) | p.inv[k][i].is_finite();
                take &= p.o[k][i].is_finite();
            }
            *b = !take;
        }
        bits::<M>(bad) & mask
    };
    mask &= !solo;
    // The cache's protocol as the kd packets' `trace_rays_cached` has it,
    // written out: a helper taking the walk as a closure ran these
    // packets at 0.6–0.85× and the kd ones at 0.4× (the closure's body
    // did not get the instruction set's copy of the walk).
    if ANY {
        let cached = cache.tris(&src);
        let mut occ = [u32::MAX; LANES];
        let done = test_cached::<_, COUNT, M>(src, &p, &cached, mask, &mut best, stats, &mut occ);
        if mask & !done != 0 {
            walk_packet_wide::<_, true, COUNT, M, AVX2>(
                src,
                boxes,
                rays,
                &p,
                mask & !done,
                &mut best,
                stats,
                &mut occ,
            );
        }
        cache.update(&occ);
    } else if mask != 0 {
        walk_packet_wide::<_, false, COUNT, M, AVX2>(
            src,
            boxes,
            rays,
            &p,
            mask,
            &mut best,
            stats,
            &mut (),
        );
    }
    write_hits(&best, out);
    while solo != 0 {
        let i = solo.trailing_zeros() as usize;
        solo &= solo - 1;
        out[i] = walk_ray::<_, ANY, COUNT>(src, &rays[i], stats);
    }
}

/// The lanes of `act` through the boxes as one packet, any-hit queries
/// (`ANY`) or closest hits: at a node every lane decides every box with
/// the single walk's rule (up to its best hit so far, for closest hits),
/// a child is visited by the lanes that enter it, a leaf's triangles are
/// tested in those lanes, and a blocked lane leaves an any-hit packet. A
/// node that [`ALONE_LANES`] lanes or fewer ([`ALONE_LANES_HALVES`] in
/// 8-lane halves) reach is walked by each alone (a node visit each in
/// `stats`), a closest-hit lane from its best hit so far.
#[allow(
    clippy::too_many_arguments,
    reason = "the packet's state, passed apart into the inlined walk"
)]
#[inline(always)]
fn walk_packet_wide<
    'a,
    W: Walk<'a>,
    const ANY: bool,
    const COUNT: bool,
    const M: bool,
    const AVX2: bool,
>(
    src: W,
    boxes: &WideBoxes,
    rays: &[Ray],
    p: &Packet,
    mut act: u16,
    best: &mut Best,
    stats: &mut TraceStats,
    occ: &mut impl Occluders,
) {
    if COUNT {
        stats.rays += u64::from(act.count_ones());
        stats.packets += 1;
    }
    let perm = p.shared_permutation(act);
    let mut neg = [[false; LANES]; 3];
    let mut signs = [None; 3];
    for (k, n) in neg.iter_mut().enumerate() {
        *n = p.inv[k].map(|x| x < 0.0);
        let m = bits::<M>(*n) & act;
        if m == 0 || m == act {
            signs[k] = Some(m != 0);
        }
    }
    let frustum = if AVX2 && !M && signs.iter().all(Option::is_some) {
        // SAFETY: `AVX2` is set only where this CPU has AVX2
        // (`WideTracer::packet`).
        Some(unsafe { Frustum::new_avx2(p, act, &signs) })
    } else {
        None
    };
    let (nodes, tris, ids) = (&boxes.nodes[..], &boxes.tris[..], &boxes.ids[..]);
    let leaf_alone = if M {
        LEAF_ALONE_LANES
    } else {
        LEAF_ALONE_LANES_HALVES
    };
    let mut stack = [const { MaybeUninit::<(u32, u16)>::uninit() }; STACK];
    let mut sp = 0usize;
    let (mut node, mut mask) = (0u32, act);
    'walk: loop {
        if mask.count_ones() <= if M { ALONE_LANES } else { ALONE_LANES_HALVES } {
            act &= !walk_alone::<_, ANY, COUNT, AVX2>(
                src, boxes, rays, p, &neg, node, mask, best, stats, occ,
            );
            match pop(&stack, &mut sp, act) {
                Some(next) => {
                    (node, mask) = next;
                    continue 'walk;
                }
                None => return,
            }
        }
        let wn = &nodes[node as usize];
        if COUNT {
            stats.nodes += 1;
            stats.lane_steps += u64::from(mask.count_ones());
        }
        // Per slot, the lanes that enter its box. Where the packet's
        // lanes share their directions' signs (a renderer's AO packet of
        // one direction cell), each axis's entry and exit planes are one
        // broadcast from arrays chosen once a node; otherwise they are
        // chosen per lane. The AVX2 copy (two 8-lane halves) skips a
        // half without lanes.
        let mut lanes_in = [0u16; WIDTH];
        let mut entered = 0u32;
        // Each lane's reach: its `tmax`, and for closest hits its best
        // hit so far (the single walk's `best.t.min(ray.tmax)`).
        let mut reach = p.tmax;
        if !ANY {
            for (r, (&t, &tmax)) in reach.iter_mut().zip(best.t.iter().zip(&p.tmax)) {
                *r = if t < tmax { t } else { tmax };
            }
        }
        if mask != 0 {
            let mut planes: SharedPlanes = [None; 3];
            for k in 0..3 {
                planes[k] = match signs[k] {
                    Some(true) => Some((&wn.planes[3 + k], &wn.planes[k])),
                    Some(false) => Some((&wn.planes[k], &wn.planes[3 + k])),
                    None => None,
                };
            }
            let mut used = wn.used;
            if let Some(f) = &frustum {
                // SAFETY: `AVX2` is set only where this CPU has AVX2
                // (`WideTracer::packet`).
                used &= unsafe { f.slots_avx2(wn) };
            }
            while used != 0 {
                let j = used.trailing_zeros() as usize;
                used &= used - 1;
                lanes_in[j] = if AVX2 && !M {
                    let mut m = 0;
                    for i0 in [0, WIDTH] {
                        if (mask >> i0) & 0xff != 0 {
                            // SAFETY: `AVX2` is set only where this CPU
                            // has AVX2 (`WideTracer::packet`).
                            m |= unsafe { half_lanes_avx2(p, &reach, i0, wn, j, &planes) };
                        }
                    }
                    m & mask
                } else {
                    bits::<M>(slot_lanes(p, &reach, wn, j, &planes, &neg)) & mask
                };
                // Collected here: read back from `lanes_in` just stored,
                // 16 bits a slot, the loads waited on the stores (7 % of
                // dieselpower's AO packet samples).
                entered |= u32::from(lanes_in[j] != 0) << j;
            }
        }
        // The packet's order: the entry distances of its first lane, by
        // the single walk's test (read from lanes just stored, they would
        // wait on Zen 4's store forwarding).
        let near = if entered & !wn.leaves & (entered & !wn.leaves).wrapping_sub(1) != 0 {
            let lane = lane_slabs(p, &neg, mask.trailing_zeros() as usize);
            if AVX2 {
                // SAFETY: `AVX2` is set only where this CPU has AVX2
                // (`WideTracer::packet`).
                unsafe { enter_avx2(wn, &lane, f32::INFINITY).1 }
            } else {
                enter(wn, &lane, f32::INFINITY).1
            }
        } else {
            [0.0; WIDTH]
        };
        // The entered leaves, in their lanes.
        let mut lm = entered & wn.leaves;
        while lm != 0 {
            let j = lm.trailing_zeros() as usize;
            lm &= lm - 1;
            let mut lanes = lanes_in[j] & act;
            let start = (wn.child[j] & !LEAF) as usize;
            let n = tris[start] as usize;
            if COUNT && lanes != 0 {
                stats.leaves += 1;
            }
            let first = tris[start + 1] as usize;
            if AVX2 && lanes.count_ones() <= leaf_alone && !boxes.verts.is_empty() {
                // So few lanes test the leaf each alone, eight triangles
                // at a time.
                let mut m = lanes;
                while m != 0 {
                    let i = m.trailing_zeros() as usize;
                    m &= m - 1;
                    if COUNT {
                        stats.tris += n as u64;
                    }
                    let mut h = if ANY { Hit::MISS } else { best.lane(i) };
                    // SAFETY: `AVX2` is set only where this CPU has AVX2
                    // (`WideTracer::packet`); `verts` is not empty.
                    let r = unsafe {
                        leaf_in_lanes::<_, ANY>(
                            src,
                            boxes,
                            &rays[i],
                            &p.precomp(i),
                            first,
                            n,
                            &mut h,
                        )
                    };
                    if !ANY {
                        best.set_lane(i, h);
                    } else if let Some(t) = r {
                        best.set_lane(i, h);
                        occ.note(1 << i, t);
                        act &= !(1 << i);
                    }
                }
                continue;
            }
            for &t in &ids[first..first + n] {
                if lanes == 0 {
                    break;
                }
                if COUNT {
                    stats.tris += u64::from(lanes.count_ones());
                }
                // The vertex copy's nine values in one or two cache
                // lines, where `src.triangle` reads an index triple and
                // then three vertices: black_forest's AO packets run
                // 1.02–1.03× as fast (ravenbridge 0.96–1.07×, others
                // within noise; AVX-512, four rounds).
                let h = match boxes.verts.get(t as usize) {
                    Some(tri) => test_triangle_of::<_, ANY, M>(src, p, perm, t, tri, lanes, best),
                    None => test_triangle::<_, ANY, M>(src, p, perm, t, lanes, best),
                };
                if ANY {
                    occ.note(h, t);
                    act &= !h;
                    lanes &= !h;
                }
            }
        }
        if ANY && act == 0 {
            return;
        }
        // The entered inner children: the nearest next, the others
        // pushed with their lanes.
        let im = entered & !wn.leaves;
        if im != 0 {
            let next = take_nearest(
                im,
                &near,
                |j| (wn.child[j], lanes_in[j]),
                &mut stack,
                &mut sp,
            );
            if lanes_in[next] & act != 0 {
                (node, mask) = (wn.child[next], lanes_in[next] & act);
                continue 'walk;
            }
        }
        match pop(&stack, &mut sp, act) {
            Some(next) => (node, mask) = next,
            None => return,
        }
    }
}

/// The bounds of a packet's lanes whose directions share their signs on
/// every axis, for a test of a node's eight boxes on behalf of all of them
/// at once before each box is decided lane by lane (the frustum test of
/// Embree's packets): a box that no lane can enter is not tested in the
/// lanes. Bounds, not a tighter frustum, so that the test is conservative
/// by the monotony of rounding alone: a lane's `(plane - o) · inv` lies
/// between the products of the corners of `[plane - o_hi, plane - o_lo] ×
/// [inv_lo, inv_hi]`, each rounded, and its `tmin` and reach between the
/// packet's least and greatest. Without it, the renderer's AO packets run
/// at 0.84–0.94× on an AVX2-only AMD EPYC (Zen 3).
struct Frustum {
    o_lo: [f32; 3],
    o_hi: [f32; 3],
    inv_lo: [f32; 3],
    inv_hi: [f32; 3],
    tmin: f32,
    reach: f32,
    /// Per axis, the rows of the entry and exit planes, as [`Slabs`].
    rows: [(usize, usize); 3],
}

impl Frustum {
    /// The bounds of the lanes of `act`, whose signs `signs` are shared
    /// (`Some(true)`: negative) on every axis. Their `tmax` bounds every
    /// reach, a closest-hit lane's best hit only shortening it.
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2"))]
    #[inline]
    unsafe fn new_avx2(p: &Packet, act: u16, signs: &[Option<bool>; 3]) -> Frustum {
        let mut rows = [(0, 3), (1, 4), (2, 5)];
        for (k, row) in rows.iter_mut().enumerate() {
            if signs[k] == Some(true) {
                *row = (3 + k, k);
            }
        }
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::*;
            // The lanes of `act` as two 8-lane masks.
            let bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
            let half = |m: u16| {
                let m = _mm256_and_si256(_mm256_set1_epi32(i32::from(m)), bits);
                _mm256_castsi256_ps(_mm256_cmpeq_epi32(m, bits))
            };
            let (lo, hi) = (half(act & 0xff), half(act >> 8));
            // SAFETY: `a` is 16 `f32`, two unaligned vector loads.
            let ld = |a: &Lanes| unsafe {
                (
                    _mm256_loadu_ps(a.as_ptr()),
                    _mm256_loadu_ps(a.as_ptr().add(8)),
                )
            };
            let least = |a: &Lanes| {
                let (x, y) = ld(a);
                let inf = _mm256_set1_ps(f32::INFINITY);
                let m = _mm256_min_ps(_mm256_blendv_ps(inf, x, lo), _mm256_blendv_ps(inf, y, hi));
                let m = _mm256_min_ps(m, _mm256_permute2f128_ps::<1>(m, m));
                let m = _mm256_min_ps(m, _mm256_shuffle_ps::<0b0100_1110>(m, m));
                _mm256_cvtss_f32(_mm256_min_ps(m, _mm256_shuffle_ps::<0b1011_0001>(m, m)))
            };
            let greatest = |a: &Lanes| {
                let (x, y) = ld(a);
                let inf = _mm256_set1_ps(f32::NEG_INFINITY);
                let m = _mm256_max_ps(_mm256_blendv_ps(inf, x, lo), _mm256_blendv_ps(inf, y, hi));
                let m = _mm256_max_ps(m, _mm256_permute2f128_ps::<1>(m, m));
                let m = _mm256_max_ps(m, _mm256_shuffle_ps::<0b0100_1110>(m, m));
                _mm256_cvtss_f32(_mm256_max_ps(m, _mm256_shuffle_ps::<0b1011_0001>(m, m)))
            };
            Frustum {
                o_lo: [least(&p.o[0]), least(&p.o[1]), least(&p.o[2])],
                o_hi: [greatest(&p.o[0]), greatest(&p.o[1]), greatest(&p.o[2])],
                inv_lo: [least(&p.inv[0]), least(&p.inv[1]), least(&p.inv[2])],
                inv_hi: [
                    greatest(&p.inv[0]),
                    greatest(&p.inv[1]),
                    greatest(&p.inv[2]),
                ],
                tmin: least(&p.tmin),
                reach: greatest(&p.tmax),
                rows,
            }
        }
        // Elsewhere no copy sets `AVX2`, and `slots_avx2` keeps every
        // slot: bounds that hold every ray.
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (p, act);
            Frustum {
                o_lo: [f32::NEG_INFINITY; 3],
                o_hi: [f32::INFINITY; 3],
                inv_lo: [f32::NEG_INFINITY; 3],
                inv_hi: [f32::INFINITY; 3],
                tmin: f32::NEG_INFINITY,
                reach: f32::INFINITY,
                rows,
            }
        }
    }

    /// The slots of `wn` that some lane may enter (bit `j` for slot `j`;
    /// a bound that is NaN keeps its slot).
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2"))]
    #[inline]
    unsafe fn slots_avx2(&self, wn: &WideNode) -> u32 {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::*;
            // SAFETY: a plane array is 8 `f32`, one unaligned vector load.
            let ld = |a: &[f32; WIDTH]| unsafe { _mm256_loadu_ps(a.as_ptr()) };
            let mut tn = _mm256_set1_ps(self.tmin);
            let mut tf = _mm256_set1_ps(self.reach);
            for k in 0..3 {
                let (nr, fr) = self.rows[k];
                let (np, fp) = (ld(&wn.planes[nr]), ld(&wn.planes[fr]));
                let (olo, ohi) = (_mm256_set1_ps(self.o_lo[k]), _mm256_set1_ps(self.o_hi[k]));
                let (ilo, ihi) = (
                    _mm256_set1_ps(self.inv_lo[k]),
                    _mm256_set1_ps(self.inv_hi[k]),
                );
                let (a, b) = (_mm256_sub_ps(np, ohi), _mm256_sub_ps(np, olo));
                let n = _mm256_min_ps(
                    _mm256_min_ps(_mm256_mul_ps(a, ilo), _mm256_mul_ps(a, ihi)),
                    _mm256_min_ps(_mm256_mul_ps(b, ilo), _mm256_mul_ps(b, ihi)),
                );
                let (c, d) = (_mm256_sub_ps(fp, ohi), _mm256_sub_ps(fp, olo));
                let f = _mm256_max_ps(
                    _mm256_max_ps(_mm256_mul_ps(c, ilo), _mm256_mul_ps(c, ihi)),
                    _mm256_max_ps(_mm256_mul_ps(d, ilo), _mm256_mul_ps(d, ihi)),
                );
                tn = _mm256_max_ps(n, tn);
                tf = _mm256_min_ps(f, tf);
            }
            let abs = _mm256_andnot_ps(_mm256_set1_ps(-0.0), tf);
            let reach = _mm256_add_ps(tf, _mm256_mul_ps(abs, _mm256_set1_ps(MARGIN)));
            _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_NGT_UQ>(tn, reach)) as u32
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = wn;
            u32::MAX
        }
    }
}

/// Per axis, where a packet's lanes share their direction's sign, a
/// node's entry and exit planes.
type SharedPlanes<'n> = [Option<(&'n [f32; WIDTH], &'n [f32; WIDTH])>; 3];

/// Whether each lane of `p` enters slot `j` of `wn` before its `reach`:
/// the single walk's slab test, lane by lane, with the planes of
/// `planes` where the lanes share their signs and those of `neg`
/// elsewhere.
#[inline(always)]
fn slot_lanes(
    p: &Packet,
    reach: &Lanes,
    wn: &WideNode,
    j: usize,
    planes: &SharedPlanes,
    neg: &[[bool; LANES]; 3],
) -> [bool; LANES] {
    let (mut tn, mut tf) = (p.tmin, *reach);
    for k in 0..3 {
        let (o, inv) = (&p.o[k], &p.inv[k]);
        match planes[k] {
            Some((np, fp)) => {
                let (np, fp) = (np[j], fp[j]);
                for i in 0..LANES {
                    let n = (np - o[i]) * inv[i];
                    let f = (fp - o[i]) * inv[i];
                    tn[i] = if n > tn[i] { n } else { tn[i] };
                    tf[i] = if f < tf[i] { f } else { tf[i] };
                }
            }
            None => {
                let (lo, hi) = (wn.planes[k][j], wn.planes[3 + k][j]);
                for i in 0..LANES {
                    let (np, fp) = if neg[k][i] { (hi, lo) } else { (lo, hi) };
                    let n = (np - o[i]) * inv[i];
                    let f = (fp - o[i]) * inv[i];
                    tn[i] = if n > tn[i] { n } else { tn[i] };
                    tf[i] = if f < tf[i] { f } else { tf[i] };
                }
            }
        }
    }
    let mut hit = [false; LANES];
    for i in 0..LANES {
        hit[i] = tn[i] <= tf[i] + tf[i].abs() * MARGIN;
    }
    hit
}

/// [`slot_lanes`] for the 8 lanes from `i0` (0 or 8) in AVX2
/// intrinsics, the same operations in the same order (`maxps`/`minps`
/// return their second operand where either is NaN or both are zero, as
/// the selects do): bit `i0 + i` for lane `i0 + i`. A packet's half
/// without lanes is skipped (ravenbridge's AO packets 1.05–1.09× as
/// fast). Written as a lane loop over 8 lanes, LLVM assembled the
/// vectors lane by lane: dieselpower's AO packets ran at 0.56× the loop
/// over all 16.
///
/// # Safety
/// The CPU has AVX2.
#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2"))]
#[inline]
unsafe fn half_lanes_avx2(
    p: &Packet,
    reach: &Lanes,
    i0: usize,
    wn: &WideNode,
    j: usize,
    planes: &SharedPlanes,
) -> u16 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        let half = |a: &Lanes| {
            let a = &a[i0..i0 + WIDTH];
            // SAFETY: `a` is 8 `f32`, one unaligned vector load.
            unsafe { _mm256_loadu_ps(a.as_ptr()) }
        };
        let (mut tn, mut tf) = (half(&p.tmin), half(reach));
        for (k, shared) in planes.iter().enumerate() {
            let (o, inv) = (half(&p.o[k]), half(&p.inv[k]));
            let (np, fp) = match shared {
                Some((np, fp)) => (_mm256_set1_ps(np[j]), _mm256_set1_ps(fp[j])),
                None => {
                    let (lo, hi) = (
                        _mm256_set1_ps(wn.planes[k][j]),
                        _mm256_set1_ps(wn.planes[3 + k][j]),
                    );
                    let neg = _mm256_cmp_ps::<_CMP_LT_OQ>(inv, _mm256_setzero_ps());
                    (_mm256_blendv_ps(lo, hi, neg), _mm256_blendv_ps(hi, lo, neg))
                }
            };
            let n = _mm256_mul_ps(_mm256_sub_ps(np, o), inv);
            let f = _mm256_mul_ps(_mm256_sub_ps(fp, o), inv);
            tn = _mm256_max_ps(n, tn);
            tf = _mm256_min_ps(f, tf);
        }
        let abs = _mm256_andnot_ps(_mm256_set1_ps(-0.0), tf);
        let reach = _mm256_add_ps(tf, _mm256_mul_ps(abs, _mm256_set1_ps(MARGIN)));
        let hit = _mm256_cmp_ps::<_CMP_LE_OQ>(tn, reach);
        (_mm256_movemask_ps(hit) as u16) << i0
    }
    // Elsewhere no copy sets `AVX2`; the 16-lane test, cut to the half.
    #[cfg(not(target_arch = "x86_64"))]
    {
        let neg = [0, 1, 2].map(|k| p.inv[k].map(|x| x < 0.0));
        bits::<false>(slot_lanes(p, reach, wn, j, planes, &neg)) & (0xff << i0)
    }
}

/// The next pending node of a packet that some of the lanes of `act`
/// enter, with those lanes; the nodes on the way are dropped.
#[inline(always)]
fn pop(stack: &[MaybeUninit<(u32, u16)>], sp: &mut usize, act: u16) -> Option<(u32, u16)> {
    while *sp > 0 {
        *sp -= 1;
        // SAFETY: every entry below the old `sp` was written.
        let (c, m) = unsafe { stack[*sp].assume_init() };
        if m & act != 0 {
            return Some((c, m & act));
        }
    }
    None
}

/// Lane `i` of a packet as the single walk's box test reads it.
#[inline(always)]
fn lane_slabs(p: &Packet, neg: &[[bool; LANES]; 3], i: usize) -> Slabs {
    Slabs::new(
        [p.o[0][i], p.o[1][i], p.o[2][i]],
        [p.inv[0][i], p.inv[1][i], p.inv[2][i]],
        [neg[0][i], neg[1][i], neg[2][i]],
        p.tmin[i],
    )
}

/// The lanes of `mask` each walked alone through the subtree of `node`
/// by the single walk (a closest-hit lane from its best hit so far);
/// returns the lanes an any-hit walk found blocked, their hits in `best`
/// (every lane's best hit, for closest hits). Cheaper than the packet
/// where so few lanes are left: a packet's node visit decides all 8
/// boxes in all 16 lanes.
#[allow(
    clippy::too_many_arguments,
    reason = "the packet's state, passed apart into the inlined walk"
)]
#[inline(always)]
fn walk_alone<'a, W: Walk<'a>, const ANY: bool, const COUNT: bool, const AVX2: bool>(
    src: W,
    boxes: &WideBoxes,
    rays: &[Ray],
    p: &Packet,
    neg: &[[bool; LANES]; 3],
    node: u32,
    mut mask: u16,
    best: &mut Best,
    stats: &mut TraceStats,
    occ: &mut impl Occluders,
) -> u16 {
    let mut hit = 0;
    while mask != 0 {
        let i = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        let slabs = lane_slabs(p, neg, i);
        let visits = stats.nodes;
        let from = if ANY { Hit::MISS } else { best.lane(i) };
        let (h, t) = descend::<_, ANY, COUNT, AVX2>(
            src,
            boxes,
            &rays[i],
            &p.precomp(i),
            &slabs,
            node,
            from,
            stats,
        );
        if COUNT {
            stats.lane_steps += stats.nodes - visits;
        }
        if !ANY {
            best.set_lane(i, h);
        } else if h.is_hit() {
            best.set_lane(i, h);
            occ.note(1 << i, t);
            hit |= 1 << i;
        }
    }
    hit
}

/// A tracer whose single rays walk the wide boxes, and whose any-hit
/// batches go over them in packets; its closest-hit batches are a
/// [`PacketTracer`]'s packets (a renderer's primary rays), or packets
/// over the boxes where asked and in the AVX2 copy
/// ([`WideTracer::closest_packets`]).
pub struct WideTracer<'a, S: KdSource + 'a> {
    packet: PacketTracer<'a, S>,
    boxes: &'a WideBoxes,
    /// Closest-hit batches go over the boxes in packets.
    closest_packets: bool,
}

impl<'a, S: KdSource> WideTracer<'a, S> {
    /// A tracer over `src` and its `boxes` (made by [`WideBoxes::new`]
    /// from `src`'s walk: the boxes of another tree are never used, every
    /// query then walks from the root).
    pub fn new(src: &'a S, boxes: &'a WideBoxes) -> Self {
        Self::with_level(src, boxes, crate::simd::SimdLevel::detect())
    }

    /// [`WideTracer::new`] compiled for `level` where this CPU has it;
    /// for the tests of every level's copy.
    pub fn with_level(src: &'a S, boxes: &'a WideBoxes, level: crate::simd::SimdLevel) -> Self {
        let packet = PacketTracer::with_level(src, level);
        WideTracer {
            closest_packets: packet.level() == crate::simd::SimdLevel::Avx2,
            packet,
            boxes,
        }
    }

    /// The same tracer, its closest-hit batches
    /// ([`ClosestHit::closest_hit_n`], [`ClosestHit::closest_hit_4x4`])
    /// traced as packets over the boxes rather than the kd-tree's packets:
    /// for incoherent rays (a renderer's AO rays), where a packet's lanes
    /// part after a few levels and the boxes drop the empty cells. With
    /// AVX-512 coherent primary rays keep the kd-tree's packets (the boxes
    /// run them at 0.91–1.06×); the AVX2 copy takes the boxes' packets
    /// for every closest hit without being asked, since with the test of
    /// a node's boxes for all lanes at once they run a
    /// camera's packets 1.24–1.58× as fast as its kd packets.
    pub fn closest_packets(self) -> Self {
        WideTracer {
            closest_packets: true,
            ..self
        }
    }

    fn scalar(&self) -> &Scalar<'a, S> {
        self.packet.scalar()
    }

    /// One ray over the boxes with its work added to `stats`.
    pub fn trace_counted(&self, ray: &Ray, any: bool, stats: &mut TraceStats) -> Hit {
        let w = self.scalar().walk;
        if any {
            walk_wide::<_, true, true, false>(w, self.boxes, ray, stats)
        } else {
            walk_wide::<_, false, true, false>(w, self.boxes, ray, stats)
        }
    }

    /// Up to 16 rays as one packet over the boxes, any-hit queries
    /// ([`ClosestHit::occluded_n_cached`], `cache`'s triangles first) or
    /// closest hits, with their work added to `stats` (a packet's node
    /// visit is one node step).
    ///
    /// # Panics
    ///
    /// If `rays` holds more than 16 rays or `out` is not as long.
    pub fn packet_counted(
        &self,
        rays: &[Ray],
        any: bool,
        out: &mut [Hit],
        stats: &mut TraceStats,
        cache: &mut OccluderCache,
    ) {
        if any {
            self.packet::<true, true>(rays, out, stats, cache)
        } else {
            self.packet::<false, true>(rays, out, stats, cache)
        }
    }

    fn packet<const ANY: bool, const COUNT: bool>(
        &self,
        rays: &[Ray],
        out: &mut [Hit],
        stats: &mut TraceStats,
        cache: &mut OccluderCache,
    ) {
        assert!(rays.len() <= LANES && out.len() == rays.len());
        if rays.is_empty() {
            return;
        }
        let (w, boxes, level) = (self.scalar().walk, self.boxes, self.scalar().level);
        if level == crate::simd::SimdLevel::Baseline {
            return wide_packet::<_, ANY, COUNT, false, false>(w, boxes, rays, out, stats, cache);
        }
        crate::simd_dispatch!(level, |WIDE| {
            wide_packet::<_, ANY, COUNT, WIDE, true>(w, boxes, rays, out, stats, cache)
        })
    }

    #[inline(always)]
    fn walk<const ANY: bool>(&self, ray: &Ray) -> Hit {
        let (w, boxes, level) = (self.scalar().walk, self.boxes, self.scalar().level);
        if level == crate::simd::SimdLevel::Baseline {
            return walk_wide::<_, ANY, false, false>(w, boxes, ray, &mut TraceStats::default());
        }
        crate::simd_dispatch!(level, |_WIDE| {
            walk_wide::<_, ANY, false, true>(w, boxes, ray, &mut TraceStats::default())
        })
    }
}

impl<'a, S: KdSource> ClosestHit for WideTracer<'a, S> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        self.walk::<false>(ray)
    }

    fn occluded(&self, ray: &Ray) -> bool {
        self.walk::<true>(ray).is_hit()
    }

    fn closest_hit_n(&self, rays: &[Ray], out: &mut [Hit]) {
        if self.closest_packets {
            let mut cache = OccluderCache::new();
            self.packet::<false, false>(rays, out, &mut TraceStats::default(), &mut cache)
        } else {
            self.packet.closest_hit_n(rays, out)
        }
    }

    fn occluded_n(&self, rays: &[Ray], out: &mut [bool]) {
        self.occluded_n_cached(rays, out, &mut OccluderCache::new())
    }

    fn occluded_n_cached(&self, rays: &[Ray], out: &mut [bool], cache: &mut OccluderCache) {
        let mut hits = [Hit::MISS; LANES];
        let hits = &mut hits[..rays.len()];
        self.packet::<true, false>(rays, hits, &mut TraceStats::default(), cache);
        for (o, h) in out.iter_mut().zip(hits.iter()) {
            *o = h.is_hit();
        }
    }

    fn closest_hit_4x4(&self, rays: &[Ray; 16], out: &mut [Hit; 16]) {
        if self.closest_packets {
            self.closest_hit_n(rays, out)
        } else {
            self.packet.closest_hit_4x4(rays, out)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::{Algorithm, BuildConfig, build};
    use crate::trace::{KdSource, TreeTracer};

    /// Every reference clipped: the union `leaf_box` skips clips of.
    fn every_clip<'a, W: Walk<'a>>(walk: W, n: u32, cell: &Aabb) -> Aabb {
        let mut b = Aabb::EMPTY;
        if let SourceNode::Leaf(tris) = walk.node(n) {
            for i in 0..tris.len() {
                if let Some(c) = clip_triangle(&walk.triangle(tris.get(i)), cell) {
                    b = b.union(&c);
                }
            }
        }
        b
    }

    /// The embedded scene's std tree, built once for the tests.
    fn dieselpower() -> TreeTracer<'static> {
        static TREE: std::sync::OnceLock<(crate::scene::TriangleColumns, crate::tree::TreeIr)> =
            std::sync::OnceLock::new();
        let (scene, tree) = TREE.get_or_init(|| {
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("scenes/nexuiz_dieselpower.obj");
            let scene = crate::scene::load_obj(&path).unwrap().0;
            let tree = build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
            (scene, tree)
        });
        TreeTracer { tree, scene }
    }

    /// The kd leaves with boxes and their references, and the wide
    /// hierarchy's leaves and references, of dieselpower's std tree.
    #[test]
    fn small_subtrees_become_one_leaf_each_triangle_once() {
        let source = dieselpower();
        let walk = source.walk();
        let (n_ids, limit) = (walk.tag().1, walk.step_limit() as usize);
        let tight = tight_boxes(walk, n_ids, limit, leaf_box).unwrap().0;
        let (mut kd_leaves, mut kd_refs) = (0, 0);
        for (n, b) in tight.iter().enumerate() {
            if let SourceNode::Leaf(list) = walk.node(n as u32)
                && !b.is_empty()
            {
                kd_leaves += 1;
                kd_refs += list.len();
            }
        }
        let boxes = WideBoxes::new(walk).unwrap();
        let mut refs = 0;
        for n in &boxes.nodes {
            for j in 0..WIDTH {
                if n.leaves & (1 << j) == 0 {
                    continue;
                }
                let start = (n.child[j] & !LEAF) as usize;
                let (count, first) = (boxes.tris[start] as usize, boxes.tris[start + 1] as usize);
                let mut ids = boxes.ids[first..first + count].to_vec();
                ids.sort_unstable();
                ids.dedup();
                assert_eq!(ids.len(), count, "a leaf lists a triangle twice");
                refs += count;
            }
        }
        // Merges happen, and each drops references (no kd leaf's list
        // repeats a triangle, so only merges can).
        assert!(
            boxes.leaves() < kd_leaves,
            "{} of {kd_leaves}",
            boxes.leaves()
        );
        assert!(refs < kd_refs, "{refs} of {kd_refs} references");
    }

    #[test]
    fn leaf_boxes_skip_only_clips_that_cannot_grow_them() {
        let source = dieselpower();
        let walk = source.walk();
        let (n_ids, limit) = (walk.tag().1, walk.step_limit() as usize);
        let fast = tight_boxes(walk, n_ids, limit, leaf_box).unwrap().0;
        let slow = tight_boxes(walk, n_ids, limit, every_clip).unwrap().0;
        assert_eq!(fast.len(), slow.len());
        let mut clipped = 0;
        for (n, (a, b)) in fast.iter().zip(&slow).enumerate() {
            assert_eq!(
                (a.min.to_array(), a.max.to_array()),
                (b.min.to_array(), b.max.to_array()),
                "node {n}"
            );
            clipped += usize::from(!a.is_empty());
        }
        assert!(clipped > 1000, "{clipped} nodes with boxes");
    }
}
