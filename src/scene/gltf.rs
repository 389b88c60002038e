//! glTF 2.0, as `.gltf` (JSON, its buffers embedded as base64 `data:` URIs
//! or in side files beside it) or `.glb` (binary, the buffer in the file),
//! through the `gltf` crate.
//!
//! Consumes the scene's node hierarchy: the default scene, else the first
//! scene, else every root node (one no node names as a child), in index
//! order. Produces every triangle primitive of every node's mesh, in
//! depth-first node order (children in their listed order), primitives in
//! mesh order, under the node's world transform (the product of the
//! transforms from the root down, in `f64`, each position rounded to `f32`
//! once; identity transforms leave positions bit for bit as stored). A
//! mesh used by two nodes is loaded twice. Primitives of mode `TRIANGLES`,
//! `TRIANGLE_STRIP` and `TRIANGLE_FAN` become triangles by the rules of
//! the glTF specification (3.7.2.1); points and lines are skipped.
//! Vertices are those of the `POSITION` accessor (`f32` x, y, z), indices
//! those of the `indices` accessor (`u8`, `u16` or `u32`) or `0, 1, 2, ...`
//! without one. Materials, textures, normals and animations are ignored
//! (so the crate's `import` feature, which decodes images, is left out,
//! and buffers are read here).
//!
//! Errors name the file and the part of it (`buffer 1`, `node 3 mesh 0
//! primitive 2`): JSON that does not parse or validate (the crate's
//! message, with its line and column), a buffer that is missing, shorter
//! than it says, or not readable, an accessor outside its buffer view or a
//! view outside its buffer, a `POSITION` or index accessor of the wrong
//! type, a sparse or view-less accessor (not supported), an index out of
//! range, a node hierarchy with a cycle, a NaN or infinite coordinate
//! (after the transform), and a file without triangles. Degenerate
//! triangles are dropped and counted, as for OBJ.

use super::{LoadSummary, SceneError, TriangleColumns};
use ::gltf::accessor::{DataType, Dimensions};
use ::gltf::buffer::Source;
use ::gltf::mesh::{Mode, Semantic};
use ::gltf::{Accessor, Document, Node};
use base64::Engine;
use glam::{DMat4, Vec3};
use std::path::Path;

/// Loads a `.gltf` or `.glb` file. See the module docs for the rules.
pub fn load_gltf(path: &Path) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    load_gltf_bytes(path, &bytes)
}

/// Loads glTF or GLB data held in memory; `name` is used in error
/// messages, and side buffers are looked for beside it.
pub fn load_gltf_bytes(
    name: &Path,
    bytes: &[u8],
) -> Result<(TriangleColumns, LoadSummary), SceneError> {
    let at = |what: String, message: String| SceneError::Element {
        path: name.to_path_buf(),
        what,
        message,
    };
    let invalid = |e: String| SceneError::Invalid {
        path: name.to_path_buf(),
        message: format!("not a valid glTF file: {e}"),
    };
    let parsed =
        ::gltf::Gltf::from_slice_without_validation(bytes).map_err(|e| invalid(e.to_string()))?;
    check_position_indices(parsed.document.as_json()).map_err(invalid)?;
    let document = ::gltf::Document::from_json(parsed.document.into_json())
        .map_err(|e| invalid(e.to_string()))?;
    let gltf = ::gltf::Gltf {
        document,
        blob: parsed.blob,
    };
    let buffers = read_buffers(name, &gltf.document, gltf.blob.as_deref())
        .map_err(|(i, message)| at(format!("buffer {i}"), message))?;
    let mut loader = Loader {
        buffers: &buffers,
        positions: Vec::new(),
        indices: Vec::new(),
    };
    for root in roots(&gltf.document) {
        // Each entry: a node, its parent's world transform, its depth.
        let mut stack = vec![(root, DMat4::IDENTITY, 0usize)];
        while let Some((node, parent, depth)) = stack.pop() {
            if depth > gltf.document.nodes().len() {
                return Err(at(
                    format!("node {}", node.index()),
                    "the node hierarchy has a cycle".into(),
                ));
            }
            let local =
                DMat4::from_cols_array_2d(&node.transform().matrix().map(|c| c.map(f64::from)));
            let world = parent * local;
            if let Some(mesh) = node.mesh() {
                for primitive in mesh.primitives() {
                    let what = format!(
                        "node {} mesh {} primitive {}",
                        node.index(),
                        mesh.index(),
                        primitive.index()
                    );
                    loader
                        .primitive(&primitive, &world)
                        .map_err(|message| at(what, message))?;
                }
            }
            let children: Vec<Node> = node.children().collect();
            stack.extend(children.into_iter().rev().map(|c| (c, world, depth + 1)));
        }
    }
    super::finish(
        name,
        loader.positions,
        loader.indices,
        0,
        "no mesh primitive with triangles in the scene",
    )
}

/// Refuses a primitive whose `POSITION` names no accessor: `gltf-json`
/// 1.4's validation reads that accessor without checking the index (and
/// panics), so this runs before it.
fn check_position_indices(root: &::gltf::json::Root) -> Result<(), String> {
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            for index in primitive.attributes.values() {
                if index.value() >= root.accessors.len() {
                    return Err(format!(
                        "meshes[{m}].primitives[{p}].attributes: accessor {} does not exist \
                         ({} accessors)",
                        index.value(),
                        root.accessors.len()
                    ));
                }
            }
        }
    }
    Ok(())
}

/// The scene's root nodes (see the module docs).
fn roots(document: &Document) -> Vec<Node<'_>> {
    if let Some(scene) = document
        .default_scene()
        .or_else(|| document.scenes().next())
    {
        return scene.nodes().collect();
    }
    let mut is_child = vec![false; document.nodes().len()];
    for node in document.nodes() {
        for child in node.children() {
            is_child[child.index()] = true;
        }
    }
    document.nodes().filter(|n| !is_child[n.index()]).collect()
}

/// Every buffer's bytes, or the index of the first that cannot be had and
/// why.
fn read_buffers(
    name: &Path,
    document: &Document,
    blob: Option<&[u8]>,
) -> Result<Vec<Vec<u8>>, (usize, String)> {
    let mut out = Vec::new();
    for buffer in document.buffers() {
        let i = buffer.index();
        let data = match buffer.source() {
            Source::Bin => blob
                .ok_or((i, "refers to the GLB binary chunk, which is missing".into()))?
                .to_vec(),
            Source::Uri(uri) if uri.starts_with("data:") => {
                let (_, payload) = uri
                    .split_once(";base64,")
                    .ok_or((i, "a data URI that is not base64".to_string()))?;
                base64::engine::general_purpose::STANDARD
                    .decode(payload)
                    .map_err(|e| (i, format!("bad base64 data: {e}")))?
            }
            Source::Uri(uri) => {
                if uri.contains("://") {
                    return Err((i, format!("`{uri}`: only relative file names are read")));
                }
                let side = name.parent().unwrap_or(Path::new("")).join(uri);
                std::fs::read(&side).map_err(|e| (i, format!("{}: {e}", side.display())))?
            }
        };
        if data.len() < buffer.length() {
            return Err((
                i,
                format!(
                    "{} bytes, but the file says {}",
                    data.len(),
                    buffer.length()
                ),
            ));
        }
        out.push(data);
    }
    Ok(out)
}

/// The triangles gathered so far.
struct Loader<'b> {
    buffers: &'b [Vec<u8>],
    positions: Vec<Vec3>,
    indices: Vec<[u32; 3]>,
}

impl Loader<'_> {
    /// Appends one primitive's triangles under `world`.
    fn primitive(
        &mut self,
        primitive: &::gltf::Primitive<'_>,
        world: &DMat4,
    ) -> Result<(), String> {
        let mode = primitive.mode();
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            return Ok(());
        }
        let accessor = primitive
            .get(&Semantic::Positions)
            .ok_or("no POSITION attribute")?;
        if accessor.data_type() != DataType::F32 || accessor.dimensions() != Dimensions::Vec3 {
            return Err("the POSITION accessor is not f32 x, y, z".into());
        }
        let (data, stride, count) = elements(self.buffers, &accessor, "POSITION")?;
        let base = self.positions.len();
        if base + count > u32::MAX as usize {
            return Err("more than 2^32 vertices in the scene".into());
        }
        let identity = *world == DMat4::IDENTITY;
        for v in 0..count {
            let at = v * stride;
            let f = |k: usize| {
                f32::from_le_bytes(
                    data[at + 4 * k..at + 4 * k + 4]
                        .try_into()
                        .expect("4 bytes"),
                )
            };
            let stored = Vec3::new(f(0), f(1), f(2));
            let p = if identity {
                stored
            } else {
                world.transform_point3(stored.as_dvec3()).as_vec3()
            };
            if !p.is_finite() {
                return Err(format!(
                    "vertex {v}: coordinate {stored} is not finite{}",
                    if identity {
                        ""
                    } else {
                        " under the node's transform"
                    }
                ));
            }
            self.positions.push(p);
        }
        let corners: Vec<u32> = match primitive.indices() {
            None => (0..count as u32).collect(),
            Some(accessor) => {
                let size = match (accessor.data_type(), accessor.dimensions()) {
                    (DataType::U8, Dimensions::Scalar) => 1,
                    (DataType::U16, Dimensions::Scalar) => 2,
                    (DataType::U32, Dimensions::Scalar) => 4,
                    _ => return Err("the index accessor is not u8, u16 or u32 scalars".into()),
                };
                let (data, stride, n) = elements(self.buffers, &accessor, "index")?;
                let mut corners = Vec::with_capacity(n);
                for i in 0..n {
                    let b = &data[i * stride..i * stride + size];
                    let index = match size {
                        1 => u32::from(b[0]),
                        2 => u32::from(u16::from_le_bytes([b[0], b[1]])),
                        _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                    };
                    if index as usize >= count {
                        return Err(format!(
                            "index {i}: vertex {index} out of range ({count} vertices)"
                        ));
                    }
                    corners.push(index);
                }
                corners
            }
        };
        let base = base as u32;
        let c = |i: usize| base + corners[i];
        let n = corners.len();
        match mode {
            Mode::Triangles => {
                for t in 0..n / 3 {
                    self.indices.push([c(3 * t), c(3 * t + 1), c(3 * t + 2)]);
                }
            }
            Mode::TriangleStrip => {
                for i in 0..n.saturating_sub(2) {
                    let odd = i % 2;
                    self.indices.push([c(i), c(i + 1 + odd), c(i + 2 - odd)]);
                }
            }
            _ => {
                for i in 0..n.saturating_sub(2) {
                    self.indices.push([c(i + 1), c(i + 2), c(0)]);
                }
            }
        }
        Ok(())
    }
}

/// An accessor's elements: the bytes from its first element on, the
/// stride, and the count, every element checked to lie inside its
/// view and the view inside its buffer.
fn elements<'b>(
    buffers: &'b [Vec<u8>],
    accessor: &Accessor<'_>,
    what: &str,
) -> Result<(&'b [u8], usize, usize), String> {
    if accessor.sparse().is_some() {
        return Err(format!("the {what} accessor is sparse (not supported)"));
    }
    let view = accessor.view().ok_or(format!(
        "the {what} accessor has no buffer view (not supported)"
    ))?;
    let buffer = &buffers[view.buffer().index()];
    let view_data = view
        .offset()
        .checked_add(view.length())
        .and_then(|end| buffer.get(view.offset()..end))
        .ok_or(format!(
            "buffer view {} lies outside its buffer",
            view.index()
        ))?;
    let size = accessor.size();
    let stride = view.stride().unwrap_or(size);
    if stride < size {
        return Err(format!(
            "buffer view {} has a stride of {stride} bytes, below the {size} of an element",
            view.index()
        ));
    }
    let count = accessor.count();
    if count == 0 {
        return Ok((&[], stride, 0));
    }
    let fits = stride
        .checked_mul(count - 1)
        .and_then(|n| n.checked_add(size))
        .and_then(|n| n.checked_add(accessor.offset()))
        .is_some_and(|end| end <= view_data.len());
    if !fits {
        return Err(format!(
            "the {what} accessor ({count} elements) lies outside buffer view {}",
            view.index()
        ));
    }
    Ok((&view_data[accessor.offset()..], stride, count))
}
