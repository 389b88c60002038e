//! Writing a `.kd` file from a tree handed over in pre-order
//! ([`PreOrderSink`]), so that the whole tree is never in memory: the node
//! words go out to the file in windows as they are made (as
//! [`super::write_file`]'s do), the leaf index arrays go through bounded
//! buffers into unlinked temporary files beside the output and are copied
//! into place after the node section, and the header goes last. What is
//! held is the layout's stack (one entry per pending right child, at most
//! [`MAX_DEPTH`]), the words set late, two 1 MiB buffers and, with
//! `reorder`, the Morton order and its inverse (8 bytes a triangle). The
//! bytes are those of [`super::write_to_vec`] for the same tree.

use super::node::{self, MAX_LEAF32, MAX_NODES};
use super::write::{
    Entries, SectionSink, WINDOW, Words, WriteOptions, check_scene, finish_kd, flush_to, leaf_word,
    new_id, renumbering,
};
use super::{FormatError, HEADER_SIZE, HeaderError, Limit, NodeFault, Section, TreeFigures};
use crate::geom::Aabb;
use crate::scene::TriangleColumns;
use crate::tree::{MAX_DEPTH, PreOrderSink, SinkStop, TriId};
use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Bytes an index array holds in memory before they go to its file.
const SPILL_BUF: usize = 1 << 20;

/// Distinguishes the index files of concurrent writes in one process.
static SPILL_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A leaf index array of `width`-byte entries: a bounded buffer, emptied
/// into an unlinked temporary file (made on the first overflow) whenever
/// it fills.
struct Spill {
    width: usize,
    /// Bytes held before they go to the file ([`SPILL_BUF`] but in tests).
    cap: usize,
    buf: Vec<u8>,
    file: Option<File>,
    /// The directory of the temporary file, and the name it had.
    dir: PathBuf,
    name: PathBuf,
    entries: u64,
}

impl Spill {
    fn new(width: usize, dir: &Path, cap: usize) -> Spill {
        Spill {
            width,
            cap,
            buf: Vec::with_capacity(cap + 64),
            file: None,
            dir: dir.to_path_buf(),
            name: PathBuf::new(),
            entries: 0,
        }
    }

    fn io(&self, source: std::io::Error) -> FormatError {
        FormatError::Io {
            path: self.name.clone(),
            source,
        }
    }

    fn spill(&mut self) -> Result<(), FormatError> {
        if self.file.is_none() {
            self.name = self.dir.join(format!(
                ".slimkd-idx{}.{}.{}.tmp",
                8 * self.width,
                std::process::id(),
                SPILL_COUNTER.fetch_add(1, Ordering::Relaxed)
            ));
            let f = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create_new(true)
                .open(&self.name)
                .map_err(|e| self.io(e))?;
            // Unlinked at once: nothing is left behind, whatever happens.
            std::fs::remove_file(&self.name).map_err(|e| self.io(e))?;
            self.file = Some(f);
        }
        let f = self.file.as_mut().expect("made above");
        let r = f.write_all(&self.buf);
        r.map_err(|e| self.io(e))?;
        self.buf.clear();
        Ok(())
    }

    /// Hands the whole array, in order, to `put`.
    fn copy_out(
        &mut self,
        put: &mut dyn FnMut(&[u8]) -> std::io::Result<()>,
    ) -> std::io::Result<()> {
        if let Some(f) = &mut self.file {
            let len = f.stream_position()?;
            f.seek(SeekFrom::Start(0))?;
            let mut block = vec![0u8; SPILL_BUF];
            let mut left = len;
            while left > 0 {
                let n = left.min(block.len() as u64) as usize;
                f.read_exact(&mut block[..n])?;
                put(&block[..n])?;
                left -= n as u64;
            }
        }
        put(&self.buf)
    }
}

impl Entries for Spill {
    fn count(&self) -> u64 {
        self.entries
    }

    fn put(&mut self, ids: &[u32]) -> Result<(), FormatError> {
        for &t in ids {
            self.buf.extend_from_slice(&t.to_le_bytes()[..self.width]);
        }
        self.entries += ids.len() as u64;
        if self.buf.len() >= self.cap {
            self.spill()?;
        }
        Ok(())
    }
}

/// A node still to come: its cell and depth, and for a right child its
/// parent's slot and word without the slot field (which the right child
/// fills in: its own slot, or 0 when it has no word).
#[derive(Clone, Copy)]
struct Pending {
    cell: Aabb,
    depth: u32,
    parent: Option<(usize, u64)>,
}

/// The [`PreOrderSink`] of [`write_file_streamed`]: lays out each node as
/// it comes (format version 2, see [`node`]) and refuses what
/// [`super::write_file`] refuses (a tree too large for the format, an axis
/// over 2, a split that is not finite or outside its cell, a triangle id
/// out of range), and a stream that is not one whole tree. The first error
/// is kept and stops the producer.
pub struct StreamWriter<'f> {
    scene: &'f TriangleColumns,
    /// Old triangle id to new, with `reorder`.
    inverse: Option<Vec<u32>>,
    words: Words<'f>,
    idx32: Spill,
    idx16: Spill,
    bounds: Option<Aabb>,
    stack: Vec<Pending>,
    /// Nodes seen.
    count: usize,
    /// A left child that is an empty leaf came and awaits its sibling: it
    /// has a word only if the sibling is an empty leaf too (then the
    /// sibling has none).
    deferred: bool,
    /// The node counts (as the header counts them) so far.
    figures: TreeFigures,
    max_depth: u32,
    ids: Vec<u32>,
    error: Option<FormatError>,
}

impl StreamWriter<'_> {
    fn stop(&mut self, r: Result<(), FormatError>) -> Result<(), SinkStop> {
        r.map_err(|e| {
            self.error.get_or_insert(e);
            SinkStop
        })
    }

    fn bad_node(i: usize, fault: NodeFault) -> FormatError {
        FormatError::Node {
            index: i as u64,
            fault,
        }
    }

    fn bad_tri(&self, i: usize, t: TriId) -> FormatError {
        FormatError::Index {
            section: "tree",
            position: i as u64,
            message: format!("node {i} lists triangle {} of {}", t.0, self.scene.len()),
        }
    }

    fn new_id(&self, t: TriId) -> u32 {
        new_id(self.inverse.as_deref(), t)
    }

    fn push_word(&mut self, word: u64) -> Result<(), FormatError> {
        if self.words.len() as u64 >= MAX_NODES {
            return Err(FormatError::TooLarge(Limit::NodeWords));
        }
        self.words.push(word)
    }

    /// Places the next node; `None` when it has no word (an empty leaf
    /// whose word, if any, is decided by its sibling or by the parent's
    /// slot field), else its pending entry.
    fn place(&mut self, i: usize, empty: bool) -> Result<Option<Pending>, FormatError> {
        let p = if i == 0 {
            let cell = self
                .bounds
                .ok_or_else(|| FormatError::from(HeaderError::NodeBeforeBounds))?;
            Pending {
                cell,
                depth: 0,
                parent: None,
            }
        } else {
            self.stack
                .pop()
                .ok_or_else(|| Self::bad_node(i, NodeFault::AfterTree))?
        };
        if p.depth > MAX_DEPTH {
            return Err(FormatError::TooLarge(Limit::Depth));
        }
        self.max_depth = self.max_depth.max(p.depth);
        match p.parent {
            // A left child: if empty, its word waits for its sibling.
            None if i > 0 && empty => {
                self.figures.leaves += 1;
                self.deferred = true;
                return Ok(None);
            }
            None => {}
            Some((parent, word)) => {
                if std::mem::take(&mut self.deferred) {
                    if empty {
                        // Both children empty: the left one keeps a word.
                        self.push_word(node::encode_leaf32(0, 0))?;
                    } else {
                        self.figures.implicit_empty += 1;
                    }
                }
                let field = if empty { 0 } else { self.words.len() as u64 };
                self.words.set(parent, word | field << 3);
                if empty {
                    self.figures.leaves += 1;
                    self.figures.implicit_empty += 1;
                    return Ok(None);
                }
            }
        }
        Ok(Some(p))
    }

    fn try_inner(&mut self, axis: u8, pos: f32, t_ref: Option<TriId>) -> Result<(), FormatError> {
        let i = self.count;
        self.count += 1;
        let p = self.place(i, false)?.expect("an inner node has a word");
        if axis > 2 {
            return Err(Self::bad_node(i, NodeFault::Axis(axis)));
        }
        if !pos.is_finite() {
            return Err(Self::bad_node(i, NodeFault::SplitNotFinite));
        }
        let k = usize::from(axis);
        if !(pos >= p.cell.min[k] && pos <= p.cell.max[k]) {
            return Err(Self::bad_node(
                i,
                NodeFault::SplitOutsideCell {
                    pos,
                    axis: k,
                    min: p.cell.min[k],
                    max: p.cell.max[k],
                },
            ));
        }
        let slot = self.words.len();
        // The slot field is filled in by the right child.
        let word = node::encode_inner(axis, t_ref.is_some(), 0, pos);
        self.push_word(word)?;
        match t_ref {
            Some(t) => {
                if t.0 as usize >= self.scene.len() {
                    return Err(self.bad_tri(i, t));
                }
                self.figures.t_inner += 1;
                self.push_word(node::encode_tref(self.new_id(t)))?;
            }
            None => self.figures.inner += 1,
        }
        let (left, right) = p.cell.split(k, pos);
        self.stack.push(Pending {
            cell: right,
            depth: p.depth + 1,
            parent: Some((slot, word)),
        });
        self.stack.push(Pending {
            cell: left,
            depth: p.depth + 1,
            parent: None,
        });
        Ok(())
    }

    fn try_leaf(&mut self, tris: &[TriId]) -> Result<(), FormatError> {
        let i = self.count;
        self.count += 1;
        // Checked before the list is read: a leaf this large is always in
        // 4-byte mode, whose count field has 27 bits.
        if tris.len() > MAX_LEAF32 as usize {
            return Err(FormatError::TooLarge(Limit::Leaf(tris.len() as u64)));
        }
        if let Some(&t) = tris.iter().find(|t| t.0 as usize >= self.scene.len()) {
            return Err(self.bad_tri(i, t));
        }
        if self.place(i, tris.is_empty())?.is_none() {
            return Ok(());
        }
        let inverse = self.inverse.as_deref();
        let word = leaf_word(
            &mut self.ids,
            tris.iter().map(|&t| new_id(inverse, t)),
            &mut self.idx32,
            &mut self.idx16,
            &mut self.figures,
        );
        self.push_word(word?)
    }
}

impl PreOrderSink for StreamWriter<'_> {
    fn bounds(&mut self, bounds: Aabb) -> Result<(), SinkStop> {
        let r = if self.bounds.is_some() {
            Err(HeaderError::BoundsTwice.into())
        } else {
            self.bounds = Some(bounds);
            check_scene(bounds, self.scene)
        };
        self.stop(r)
    }

    fn inner(&mut self, axis: u8, pos: f32, t_ref: Option<TriId>) -> Result<(), SinkStop> {
        if self.error.is_some() {
            return Err(SinkStop);
        }
        let r = self.try_inner(axis, pos, t_ref);
        self.stop(r)
    }

    fn leaf(&mut self, tris: &[TriId]) -> Result<(), SinkStop> {
        if self.error.is_some() {
            return Err(SinkStop);
        }
        let r = self.try_leaf(tris);
        self.stop(r)
    }
}

/// Writes the `.kd` file of the tree that `produce` hands to its
/// [`StreamWriter`] in pre-order, atomically (as
/// [`super::write_file`]: a temporary file beside `path`, synced, renamed;
/// an error or a kill leaves no file at `path` and no temporary file).
/// The bytes are [`super::write_to_vec`]'s for the same tree. An error of
/// `produce` is returned as it is; otherwise the writer's first error, or
/// an error if the nodes given were not one whole tree.
pub fn write_file_streamed<T, E: From<FormatError>>(
    path: &Path,
    scene: &TriangleColumns,
    options: &WriteOptions,
    produce: impl FnOnce(&mut StreamWriter<'_>) -> Result<T, E>,
) -> Result<T, E> {
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut result = None;
    crate::fsio::write_atomically(
        path,
        |e| E::from(io(e)),
        |f| {
            result = Some(write_streamed(
                f, &dir, scene, options, &io, WINDOW, SPILL_BUF, produce,
            )?);
            Ok(())
        },
    )?;
    Ok(result.expect("set when the write succeeds"))
}

/// [`write_file_streamed`]'s writing into `f` (at its start), with index
/// files in `dir`, node windows of `window` words and index buffers of
/// `spill_cap` bytes.
#[allow(clippy::too_many_arguments)]
fn write_streamed<T, E: From<FormatError>>(
    f: &mut File,
    dir: &Path,
    scene: &TriangleColumns,
    options: &WriteOptions,
    io: &dyn Fn(std::io::Error) -> FormatError,
    window: usize,
    spill_cap: usize,
    produce: impl FnOnce(&mut StreamWriter<'_>) -> Result<T, E>,
) -> Result<T, E> {
    let (perm, inverse) = renumbering(scene, options);
    f.write_all(&[0u8; HEADER_SIZE]).map_err(io)?;
    let mut flush = flush_to(f, io, window);
    let mut w = StreamWriter {
        scene,
        inverse,
        words: Words::new(window, &mut flush),
        idx32: Spill::new(4, dir, spill_cap),
        idx16: Spill::new(2, dir, spill_cap),
        bounds: None,
        stack: Vec::new(),
        count: 0,
        deferred: false,
        figures: TreeFigures::default(),
        max_depth: 0,
        ids: Vec::new(),
        error: None,
    };
    let t = produce(&mut w)?;
    if let Some(e) = w.error.take() {
        return Err(e.into());
    }
    if w.count == 0 || !w.stack.is_empty() {
        return Err(FormatError::Node {
            index: w.count as u64,
            fault: NodeFault::Incomplete,
        }
        .into());
    }
    let StreamWriter {
        words,
        mut idx32,
        mut idx16,
        mut figures,
        max_depth,
        bounds,
        inverse,
        ..
    } = w;
    drop(inverse);
    figures.words = words.len() as u64;
    figures.idx32 = idx32.entries;
    figures.idx16 = idx16.entries;
    let late = words.finish()?;
    // The windows are out: `f` is free for the rest of the file.
    drop(flush);
    let bounds = bounds.expect("a whole tree came after its bounds");
    let mut put_idx = |section: Section, sink: &mut SectionSink<'_, File>| {
        let spill = if section == Section::Idx32 {
            &mut idx32
        } else {
            &mut idx16
        };
        spill.copy_out(&mut |b| sink.put(b))
    };
    finish_kd(
        f,
        late,
        figures,
        max_depth,
        &mut put_idx,
        scene,
        perm.as_deref(),
        options,
        bounds,
        io,
    )?;
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::testing::{grid_tree, whole_files};

    /// Node windows of a few words and index buffers of a few bytes (so
    /// both index arrays go through their files) give the bytes of
    /// `write_to_vec`, and no index file is left in the directory.
    #[test]
    fn small_windows_and_spilled_index_arrays_give_the_same_bytes() {
        let (scene, tree) = grid_tree(600, 30, (1.5, 2.5));
        let dir = std::env::temp_dir().join(format!("slimkd-stream-unit-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        for (options, whole) in whole_files(&scene, &tree) {
            let reorder = options.reorder;
            for (window, cap) in [(1, 1), (3, 6), (64, 64), (WINDOW, SPILL_BUF)] {
                let path = dir.join("out.kd");
                let mut f = std::fs::OpenOptions::new()
                    .read(true)
                    .write(true)
                    .create(true)
                    .truncate(true)
                    .open(&path)
                    .unwrap();
                let io = |e| panic!("{e}");
                write_streamed::<_, FormatError>(
                    &mut f,
                    &dir,
                    &scene,
                    &options,
                    &io,
                    window,
                    cap,
                    |w| Ok(tree.feed(w)),
                )
                .unwrap()
                .unwrap();
                drop(f);
                let bytes = std::fs::read(&path).unwrap();
                assert!(
                    bytes == whole,
                    "window {window}, buffer {cap}, reorder {reorder}"
                );
                std::fs::remove_file(&path).unwrap();
                assert_eq!(
                    crate::fsio::entry_names(&dir).unwrap(),
                    Vec::<String>::new()
                );
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
