//! The plan, cell and part files of a build in cells (layouts in
//! [`super`]): writers (atomic) and readers that check length, magic,
//! version and checksum before anything else, then what the build relies
//! on, so that no byte string makes them panic; every error names the
//! file.

use super::{CellMismatch, CellsError, Corruption, FileKind};
use crate::build::SahParams;
use crate::build::level::{Cut, CutCell};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::{MAX_DEPTH, Node, NodeId, TreeIr, TriId};
use glam::Vec3;
use std::io::Write;
use std::path::{Path, PathBuf};

const PLAN_MAGIC: [u8; 8] = *b"SLIMKPL\0";
const CELL_MAGIC: [u8; 8] = *b"SLIMKDC\0";
const PART_MAGIC: [u8; 8] = *b"SLIMKPT\0";
/// 2: the SAH parameters hold the split price and its scale.
pub(super) const VERSION: u32 = 2;
const PLAN_HEADER: usize = 8 + 4 + 4 + 8 + 8 + 5 * 8 + 4 + 4 + 8 + 8 + 24 + 3 * 8;
const CELL_HEADER: usize = 8 + 4 + 4 + 4 + 4 + 5 * 8 + 4 + 4 + 24 + 8;
const PART_HEADER: usize = 8 + 4 + 4 + 4 + 4 + 8 + 24 + 8 + 8;
/// Bytes of one reference of a cell file: id, box, triangle.
const CELL_REF: u64 = 4 + 24 + 36;
/// Bytes of one cell of a plan.
const PLAN_CELL: u64 = 4 + 8 + 4 + 8;
const LEAF: u32 = 3;

/// The plan's file name in a work directory.
pub const PLAN_NAME: &str = "plan.kdplan";

/// The plan of work directory `dir`.
pub fn plan_path(dir: &Path) -> PathBuf {
    dir.join(PLAN_NAME)
}

/// Cell `i`'s file in work directory `dir`.
pub fn cell_path(dir: &Path, i: usize) -> PathBuf {
    dir.join(format!("cell-{i:05}.kdcell"))
}

/// Cell `i`'s part in work directory `dir`.
pub fn part_path(dir: &Path, i: usize) -> PathBuf {
    dir.join(format!("cell-{i:05}.kdpart"))
}

/// A cell's identity: the CRC-32 and length of its cell file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CellId {
    /// The CRC-32 the file ends with.
    pub crc: u32,
    /// The file's length in bytes.
    pub len: u64,
}

/// One cell of a [`Plan`].
#[derive(Clone, Debug, PartialEq)]
pub struct PlanCell {
    /// The leaf of the top tree that stands for it.
    pub node: NodeId,
    /// Its references.
    pub refs: u64,
    /// Its cell file's identity.
    pub id: CellId,
}

/// A work directory's plan: the build's parameters, the top tree and the
/// cells.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// The scene's geometry hash (the `.kd` header's).
    pub scene_hash: u64,
    /// The scene's triangles.
    pub n_tris: u64,
    /// `K_T`, `K_I`, `λ`, `μ` and the whole scene's price scale (`max_depth`
    /// is `None`: `depth_limit` holds it).
    pub sah: SahParams,
    /// The depth limit of the whole scene.
    pub depth_limit: u32,
    /// The cut.
    pub cut: Cut,
    /// The tree above the cells; each cell an empty leaf.
    pub top: TreeIr,
    /// The cells in pre-order.
    pub cells: Vec<PlanCell>,
}

/// A cell file read back: what [`super::build_cell`] needs.
pub struct CellInput {
    /// Its number in the plan.
    pub index: u32,
    /// The plan's cells.
    pub n_cells: u32,
    /// `K_T`, `K_I`, `λ`, `μ` and the whole scene's price scale.
    pub sah: SahParams,
    /// The depth limit of the whole scene.
    pub depth_limit: u32,
    /// The node's depth.
    pub depth: u32,
    /// The node's cell.
    pub cell: Aabb,
    /// Its references' triangle ids in the scene, ascending.
    pub tris: Vec<u32>,
    /// Their boxes.
    pub boxes: Vec<Aabb>,
    /// The referenced triangles alone: triangle `i` is the scene's
    /// `tris[i]`.
    pub scene: TriangleColumns,
}

/// Bytes and their CRC, written through a buffer.
struct Out<W: Write> {
    w: W,
    crc: crc32fast::Hasher,
    len: u64,
}

impl<W: Write> Out<W> {
    fn new(w: W) -> Out<W> {
        Out {
            w,
            crc: crc32fast::Hasher::new(),
            len: 0,
        }
    }
    fn put(&mut self, b: &[u8]) -> std::io::Result<()> {
        self.crc.update(b);
        self.len += b.len() as u64;
        self.w.write_all(b)
    }
    fn u32(&mut self, v: u32) -> std::io::Result<()> {
        self.put(&v.to_le_bytes())
    }
    fn u64(&mut self, v: u64) -> std::io::Result<()> {
        self.put(&v.to_le_bytes())
    }
    fn f32(&mut self, v: f32) -> std::io::Result<()> {
        self.put(&v.to_le_bytes())
    }
    fn f64(&mut self, v: f64) -> std::io::Result<()> {
        self.put(&v.to_le_bytes())
    }
    fn aabb(&mut self, b: &Aabb) -> std::io::Result<()> {
        for v in b.min.to_array().into_iter().chain(b.max.to_array()) {
            self.f32(v)?;
        }
        Ok(())
    }
    /// `K_T`, `K_I`, `λ`, `μ` and the price scale (0 for none).
    fn sah(&mut self, p: &SahParams) -> std::io::Result<()> {
        self.f64(p.k_t)?;
        self.f64(p.k_i)?;
        self.f64(p.lambda_empty)?;
        self.f64(p.split_price)?;
        self.f64(p.price_scale.unwrap_or(0.0))
    }
    fn tree_columns(&mut self, t: &TreeIr) -> std::io::Result<()> {
        for n in &t.nodes {
            let w = match *n {
                Node::Inner {
                    axis, pos, right, ..
                } => [u32::from(axis), pos.to_bits(), right.0],
                Node::Leaf { start, count } => [LEAF, start, count],
            };
            for x in w {
                self.u32(x)?;
            }
        }
        for t in &t.leaf_tris {
            self.u32(t.0)?;
        }
        Ok(())
    }
    /// Writes the CRC; returns the file's identity.
    fn finish(mut self) -> std::io::Result<CellId> {
        let crc = self.crc.clone().finalize();
        self.w.write_all(&crc.to_le_bytes())?;
        self.w.flush()?;
        Ok(CellId {
            crc,
            len: self.len + 4,
        })
    }
}

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> CellsError + '_ {
    move |source| CellsError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn write_with(
    path: &Path,
    body: impl FnOnce(&mut Out<std::io::BufWriter<&mut std::fs::File>>) -> std::io::Result<()>,
) -> Result<CellId, CellsError> {
    let io = io_err(path);
    let mut id = None;
    crate::fsio::write_atomically(path, &io, |file| {
        let mut out = Out::new(std::io::BufWriter::with_capacity(1 << 20, file));
        body(&mut out).map_err(&io)?;
        id = Some(out.finish().map_err(&io)?);
        Ok(())
    })?;
    Ok(id.expect("the body ran"))
}

/// Writes cell `index` of `n_cells`: the node `cell` of `scene`'s build
/// with parameters `sah` and the scene's depth limit. Returns its identity.
pub fn write_cell(
    path: &Path,
    scene: &TriangleColumns,
    sah: &SahParams,
    depth_limit: u32,
    index: u32,
    n_cells: u32,
    cell: &CutCell,
) -> Result<CellId, CellsError> {
    write_with(path, |o| {
        o.put(&CELL_MAGIC)?;
        o.u32(VERSION)?;
        o.u32(0)?;
        o.u32(index)?;
        o.u32(n_cells)?;
        o.sah(sah)?;
        o.u32(depth_limit)?;
        o.u32(cell.depth)?;
        o.aabb(&cell.cell)?;
        o.u64(cell.tris.len() as u64)?;
        for &t in &cell.tris {
            o.u32(t)?;
        }
        for b in &cell.boxes {
            o.aabb(b)?;
        }
        for &t in &cell.tris {
            for v in scene.tri(t) {
                for c in v.to_array() {
                    o.f32(c)?;
                }
            }
        }
        Ok(())
    })
}

/// Writes the part of the cell with identity `cell` (its subtree `tree`,
/// the scene's triangle ids).
pub fn write_part(path: &Path, cell: CellId, tree: &TreeIr) -> Result<(), CellsError> {
    if tree
        .nodes
        .iter()
        .any(|n| matches!(n, Node::Inner { t_ref: Some(_), .. }))
    {
        return Err(CellsError::Corrupt {
            path: path.to_path_buf(),
            what: Corruption::StandardTree,
        });
    }
    write_with(path, |o| {
        o.put(&PART_MAGIC)?;
        o.u32(VERSION)?;
        o.u32(0)?;
        o.u32(cell.crc)?;
        o.u32(0)?;
        o.u64(cell.len)?;
        o.aabb(&tree.bounds)?;
        o.u64(tree.nodes.len() as u64)?;
        o.u64(tree.leaf_tris.len() as u64)?;
        o.tree_columns(tree)
    })
    .map(|_| ())
}

/// Writes a plan.
pub fn write_plan(path: &Path, plan: &Plan) -> Result<(), CellsError> {
    write_with(path, |o| {
        o.put(&PLAN_MAGIC)?;
        o.u32(VERSION)?;
        o.u32(0)?;
        o.u64(plan.scene_hash)?;
        o.u64(plan.n_tris)?;
        o.sah(&plan.sah)?;
        o.u32(plan.depth_limit)?;
        o.u32(plan.cut.max_cells as u32)?;
        o.u64(plan.cut.max_refs as u64)?;
        o.u64(plan.cut.min_refs as u64)?;
        o.aabb(&plan.top.bounds)?;
        o.u64(plan.top.nodes.len() as u64)?;
        o.u64(plan.top.leaf_tris.len() as u64)?;
        o.u64(plan.cells.len() as u64)?;
        o.tree_columns(&plan.top)?;
        for c in &plan.cells {
            o.u32(c.node.0)?;
            o.u64(c.refs)?;
            o.u32(c.id.crc)?;
            o.u64(c.id.len)?;
        }
        Ok(())
    })
    .map(|_| ())
}

/// A file read whole, its magic, version and checksum checked.
struct In<'a> {
    path: &'a Path,
    data: Vec<u8>,
    at: usize,
}

impl<'a> In<'a> {
    fn open(
        path: &'a Path,
        magic: [u8; 8],
        kind: FileKind,
        header: usize,
    ) -> Result<In<'a>, CellsError> {
        let mut data = Vec::new();
        crate::fsio::open_regular(path)
            .and_then(|mut f| std::io::Read::read_to_end(&mut f, &mut data))
            .map_err(io_err(path))?;
        let r = In { path, data, at: 0 };
        if r.data.len() < 8 || r.data[..8] != magic {
            return Err(r.corrupt(Corruption::Magic { kind }));
        }
        if r.data.len() < header + 4 {
            return Err(r.corrupt(Corruption::Header {
                kind,
                len: r.data.len(),
                needed: header + 4,
            }));
        }
        let version = u32::from_le_bytes(r.data[8..12].try_into().expect("4 bytes"));
        if version != VERSION {
            return Err(r.corrupt(Corruption::Version { kind, version }));
        }
        Ok(In { at: 16, ..r })
    }

    fn corrupt(&self, what: Corruption) -> CellsError {
        CellsError::Corrupt {
            path: self.path.to_path_buf(),
            what,
        }
    }

    /// Checks that the file is `expect` bytes long (from the header's
    /// counts) and that its checksum holds; returns its identity.
    fn check(&self, kind: FileKind, expect: Option<u64>) -> Result<CellId, CellsError> {
        let len = self.data.len() as u64;
        if expect != Some(len) {
            return Err(self.corrupt(match expect {
                Some(expected) => Corruption::Length {
                    kind,
                    len,
                    expected,
                },
                None => Corruption::Counts { kind },
            }));
        }
        let (body, tail) = self.data.split_at(self.data.len() - 4);
        let stored = u32::from_le_bytes(tail.try_into().expect("4 bytes"));
        let crc = crc32fast::hash(body);
        if crc != stored {
            return Err(self.corrupt(Corruption::Checksum { kind }));
        }
        Ok(CellId { crc, len })
    }

    fn take<const N: usize>(&mut self) -> [u8; N] {
        let b = self.data[self.at..self.at + N].try_into().expect("N bytes");
        self.at += N;
        b
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.take())
    }
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take())
    }
    fn aabb(&mut self) -> Aabb {
        let v: [f32; 6] = std::array::from_fn(|_| self.f32());
        Aabb::new(Vec3::new(v[0], v[1], v[2]), Vec3::new(v[3], v[4], v[5]))
    }
    fn sah(&mut self) -> Result<SahParams, CellsError> {
        let p = SahParams {
            k_t: self.f64(),
            k_i: self.f64(),
            lambda_empty: self.f64(),
            max_depth: None,
            split_price: self.f64(),
            price_scale: Some(self.f64()).filter(|&s| s != 0.0),
        };
        let positive = |x: f64| x.is_finite() && x > 0.0;
        let costs_ok = positive(p.k_t) && positive(p.k_i);
        let lambda_ok = p.lambda_empty > 0.0 && p.lambda_empty <= 1.0;
        let price_ok =
            p.split_price.is_finite() && p.split_price >= 0.0 && p.price_scale.is_none_or(positive);
        if !(costs_ok && lambda_ok && price_ok) {
            return Err(self.corrupt(Corruption::SahParams));
        }
        Ok(p)
    }

    /// A tree of `n` nodes and `t` leaf entries in canonical pre-order
    /// whose deepest node lies at most `max_depth` below its root; leaf
    /// lists ascending.
    fn tree(
        &mut self,
        bounds: Aabb,
        n: usize,
        t: usize,
        max_depth: u32,
    ) -> Result<TreeIr, CellsError> {
        let mut nodes = Vec::with_capacity(n);
        for _ in 0..n {
            let w = [self.u32(), self.u32(), self.u32()];
            nodes.push(if w[0] == LEAF {
                Node::Leaf {
                    start: w[1],
                    count: w[2],
                }
            } else {
                let pos = f32::from_bits(w[1]);
                if w[0] > 2 || !pos.is_finite() {
                    return Err(self.corrupt(Corruption::Node(nodes.len())));
                }
                Node::Inner {
                    axis: w[0] as u8,
                    pos,
                    right: NodeId(w[2]),
                    t_ref: None,
                }
            });
        }
        let leaf_tris: Vec<TriId> = (0..t).map(|_| TriId(self.u32())).collect();
        // Pre-order: the nodes are visited in index order, each leaf's
        // list follows the one before.
        let (mut visited, mut listed) = (0usize, 0u64);
        let mut stack = vec![(0usize, 0u32)];
        while let Some((i, depth)) = stack.pop() {
            if i != visited || i >= n {
                return Err(self.corrupt(Corruption::PreOrder(visited)));
            }
            if depth > max_depth {
                return Err(self.corrupt(Corruption::TooDeep(i)));
            }
            visited += 1;
            match nodes[i] {
                Node::Inner { right, .. } => {
                    let r = right.0 as usize;
                    if r <= i + 1 || r >= n {
                        return Err(self.corrupt(Corruption::RightChild(i)));
                    }
                    stack.push((r, depth + 1));
                    stack.push((i + 1, depth + 1));
                }
                Node::Leaf { start, count } => {
                    let end = u64::from(start) + u64::from(count);
                    if u64::from(start) != listed || end > t as u64 {
                        return Err(self.corrupt(Corruption::LeafList(i)));
                    }
                    let list = &leaf_tris[start as usize..end as usize];
                    if list.windows(2).any(|w| w[0] >= w[1]) {
                        return Err(self.corrupt(Corruption::LeafOrder(i)));
                    }
                    listed = end;
                }
            }
        }
        if visited != n || listed != t as u64 {
            return Err(self.corrupt(Corruption::OutsideTree));
        }
        Ok(TreeIr {
            bounds,
            nodes,
            leaf_tris,
        })
    }
}

fn finite_box(b: &Aabb) -> bool {
    b.min.is_finite() && b.max.is_finite() && b.min.cmple(b.max).all()
}

/// The identity of a cell file that reads back whole (length and
/// checksum), without parsing it.
pub fn cell_id(path: &Path) -> Result<CellId, CellsError> {
    let mut r = In::open(path, CELL_MAGIC, FileKind::Cell, CELL_HEADER)?;
    r.at = CELL_HEADER - 8;
    let n = r.u64();
    let expect = n
        .checked_mul(CELL_REF)
        .and_then(|b| b.checked_add(CELL_HEADER as u64 + 4));
    r.check(FileKind::Cell, expect)
}

/// Reads a cell file; returns it with its identity.
pub fn read_cell(path: &Path) -> Result<(CellInput, CellId), CellsError> {
    let mut r = In::open(path, CELL_MAGIC, FileKind::Cell, CELL_HEADER)?;
    let index = r.u32();
    let n_cells = r.u32();
    let sah = r.sah();
    let depth_limit = r.u32();
    let depth = r.u32();
    let cell = r.aabb();
    let n = r.u64();
    let expect = n
        .checked_mul(CELL_REF)
        .and_then(|b| b.checked_add(CELL_HEADER as u64 + 4));
    let id = r.check(FileKind::Cell, expect)?;
    let sah = sah?;
    if index >= n_cells {
        return Err(r.corrupt(Corruption::CellIndex { index, n_cells }));
    }
    if depth > depth_limit || depth_limit > MAX_DEPTH {
        return Err(r.corrupt(Corruption::Depth {
            depth,
            limit: depth_limit,
        }));
    }
    if !finite_box(&cell) {
        return Err(r.corrupt(Corruption::CellBox));
    }
    let n = n as usize;
    let tris: Vec<u32> = (0..n).map(|_| r.u32()).collect();
    if tris.windows(2).any(|w| w[0] >= w[1]) {
        return Err(r.corrupt(Corruption::TriangleOrder));
    }
    let boxes: Vec<Aabb> = (0..n).map(|_| r.aabb()).collect();
    if let Some(k) = boxes.iter().position(|b| !finite_box(b)) {
        return Err(r.corrupt(Corruption::RefBox(k)));
    }
    let corners: Vec<[Vec3; 3]> = (0..n)
        .map(|_| {
            std::array::from_fn(|_| {
                let c: [f32; 3] = std::array::from_fn(|_| r.f32());
                Vec3::from_array(c)
            })
        })
        .collect();
    let scene = TriangleColumns::from_triangles(&corners)
        .map_err(|e| r.corrupt(Corruption::Triangles(e)))?;
    Ok((
        CellInput {
            index,
            n_cells,
            sah,
            depth_limit,
            depth,
            cell,
            tris,
            boxes,
            scene,
        },
        id,
    ))
}

/// Reads a part and checks that it was built from the cell with identity
/// `cell`.
pub fn read_part(path: &Path, cell: CellId) -> Result<TreeIr, CellsError> {
    let mut r = In::open(path, PART_MAGIC, FileKind::Part, PART_HEADER)?;
    let id = CellId {
        crc: r.u32(),
        len: {
            r.u32();
            r.u64()
        },
    };
    let bounds = r.aabb();
    let (n, t) = (r.u64(), r.u64());
    let expect = n
        .checked_mul(12)
        .and_then(|b| b.checked_add(t.checked_mul(4)?))
        .and_then(|b| b.checked_add(PART_HEADER as u64 + 4));
    r.check(FileKind::Part, expect)?;
    if id != cell {
        return Err(CellsError::Mismatch {
            path: path.to_path_buf(),
            what: CellMismatch::PartOfAnotherCell,
        });
    }
    if n == 0 || n > u64::from(u32::MAX) || t > u64::from(u32::MAX) || !finite_box(&bounds) {
        return Err(r.corrupt(Corruption::PartHeader));
    }
    r.tree(bounds, n as usize, t as usize, MAX_DEPTH)
}

/// Reads a plan.
pub fn read_plan(path: &Path) -> Result<Plan, CellsError> {
    let mut r = In::open(path, PLAN_MAGIC, FileKind::Plan, PLAN_HEADER)?;
    let scene_hash = r.u64();
    let n_tris = r.u64();
    let sah = r.sah();
    let depth_limit = r.u32();
    let max_cells = r.u32();
    let max_refs = r.u64();
    let min_refs = r.u64();
    let bounds = r.aabb();
    let (n, t, c) = (r.u64(), r.u64(), r.u64());
    let expect = n
        .checked_mul(12)
        .and_then(|b| b.checked_add(t.checked_mul(4)?))
        .and_then(|b| b.checked_add(c.checked_mul(PLAN_CELL)?))
        .and_then(|b| b.checked_add(PLAN_HEADER as u64 + 4));
    r.check(FileKind::Plan, expect)?;
    let sah = sah?;
    if n == 0 || n > u64::from(u32::MAX) || t > u64::from(u32::MAX) || c > u64::from(max_cells) {
        return Err(r.corrupt(Corruption::PlanHeader));
    }
    if depth_limit > MAX_DEPTH || !finite_box(&bounds) {
        return Err(r.corrupt(Corruption::PlanHeader));
    }
    let top = r.tree(bounds, n as usize, t as usize, depth_limit)?;
    let mut cells = Vec::with_capacity(c as usize);
    for k in 0..c as usize {
        let node = NodeId(r.u32());
        let refs = r.u64();
        let id = CellId {
            crc: r.u32(),
            len: r.u64(),
        };
        let after_last = cells.last().is_none_or(|p: &PlanCell| p.node < node);
        let empty_leaf = matches!(
            top.nodes.get(node.0 as usize),
            Some(Node::Leaf { count: 0, .. })
        );
        if !after_last || !empty_leaf {
            return Err(r.corrupt(Corruption::CellNode(k)));
        }
        cells.push(PlanCell { node, refs, id });
    }
    if top.leaf_tris.iter().any(|t| u64::from(t.0) >= n_tris) {
        return Err(r.corrupt(Corruption::PlanTriangle));
    }
    Ok(Plan {
        scene_hash,
        n_tris,
        sah,
        depth_limit,
        cut: Cut {
            max_cells: max_cells as usize,
            max_refs: max_refs as usize,
            min_refs: min_refs as usize,
        },
        top,
        cells,
    })
}
