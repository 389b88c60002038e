//! Typed structure-of-arrays columns that live in RAM below a byte budget
//! and in memory-mapped scratch files above it.
//!
//! Consumes a [`ScratchConfig`] (budget, scratch directory, optional limit
//! on scratch bytes). Produces [`Column<T>`]s of `bytemuck::Pod` elements,
//! zero-initialised, that dereference to `[T]` wherever they live, so the
//! code that fills and reads them does not know which. The level builder
//! ([`crate::build::level`]) keeps each level's references and event
//! columns in them (DESIGN.md, "Memory and scale"; Wu, Zhao & Liu 2011 keep
//! the same columns in GPU memory).
//!
//! **Guarantees.**
//! - A column is in RAM when the RAM columns alive, itself included, fit
//!   the budget; otherwise it is a file of its own in the scratch
//!   directory, mapped read-write.
//! - Scratch files never outlive the build, whatever way it ends. On Unix a
//!   file is unlinked as soon as it is mapped, so the kernel frees it when
//!   the mapping goes: on drop, on error, on panic, on Ctrl-C and on
//!   `kill -9` alike, with no signal handler. Elsewhere it is removed when
//!   the column is dropped.
//! - The space of a file is reserved when it is created
//!   (`posix_fallocate` on Linux; written with zeros elsewhere), so a full
//!   disk is a [`ColumnsError::NoSpace`] naming the path, never a `SIGBUS`
//!   on a later write into the mapping.
//! - Every error names the path it is about.
//! - Large RAM columns are reused: a dropped one's memory goes to the
//!   scratch's pool and the next column it fits is made in it (zeroed
//!   again for [`Scratch::column`]; left as it was for
//!   [`Scratch::column_for_overwrite`]), so each level of the level
//!   builder writes into the memory of the level before last instead of
//!   fresh pages (see `Pool`).

use bytemuck::Pod;
use memmap2::MmapMut;
use std::fmt;
use std::fs::{File, OpenOptions};
use std::io;
use std::marker::PhantomData;
use std::ops::{Deref, DerefMut};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

/// Where columns go.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct ScratchConfig {
    /// Bytes of columns kept in RAM at once; columns beyond it are mapped
    /// files. `None` keeps everything in RAM, `Some(0)` maps everything.
    pub mem_budget: Option<u64>,
    /// The directory the scratch files are created in. It must exist; it
    /// is never created.
    pub dir: PathBuf,
    /// At most this many bytes of scratch files alive at once (a disk
    /// quota); `None` for no limit beyond the disk's.
    pub scratch_limit: Option<u64>,
}

impl Default for ScratchConfig {
    fn default() -> Self {
        ScratchConfig {
            mem_budget: None,
            dir: std::env::temp_dir(),
            scratch_limit: None,
        }
    }
}

/// Why a column could not be made.
#[derive(Debug, thiserror::Error)]
pub enum ColumnsError {
    /// A large allocation of the builder (the tree it assembles) did not
    /// fit in memory.
    #[error("{0}")]
    OutOfMemory(crate::sys::OutOfMemory),
    /// The scratch directory does not exist or is not a directory.
    #[error(
        "scratch directory {}: {source} (it must be an existing, writable directory)",
        path.display()
    )]
    NoDir {
        /// The directory asked for.
        path: PathBuf,
        /// What `stat` said.
        source: io::Error,
    },
    /// A scratch file could not be created, sized or mapped (an
    /// unwritable directory, for example).
    #[error("scratch file {}: cannot {op}: {source}", path.display())]
    File {
        /// The scratch file.
        path: PathBuf,
        /// The step that failed, as the message words it (`map`, ...).
        op: &'static str,
        /// The system's error.
        source: io::Error,
    },
    /// The disk holding the scratch directory is full.
    #[error(
        "scratch file {}: no space left for {bytes} bytes (free some disk or choose another scratch directory)",
        path.display()
    )]
    NoSpace {
        /// The scratch file that did not fit.
        path: PathBuf,
        /// Its size.
        bytes: u64,
    },
    /// The scratch files would exceed the scratch limit
    /// ([`LevelOptions::scratch_limit`](crate::build::level::LevelOptions::scratch_limit)).
    #[error(
        "scratch directory {}: the scratch limit of {limit} bytes would be exceeded ({requested} bytes requested)",
        path.display()
    )]
    Limit {
        /// The scratch directory.
        path: PathBuf,
        /// The limit, in bytes.
        limit: u64,
        /// The scratch bytes alive with this file.
        requested: u64,
    },
    /// A count does not fit the builder's index width.
    #[error("too many {what}: at most {limit} are supported")]
    Capacity {
        /// What was counted (references, events, nodes).
        what: &'static str,
        /// The most the index width holds.
        limit: u64,
    },
    /// Memory could not be mapped (out of memory, or of mappings).
    #[error(
        "out of memory: cannot map {bytes} bytes for a column: {source} (a smaller \
         --mem-budget, e.g. --mem-budget 64M, keeps the builder's columns in scratch files)"
    )]
    Memory {
        /// The size of the mapping.
        bytes: u64,
        /// What `mmap` said.
        source: io::Error,
    },
}

/// Byte counts of the level builder's columns (RAM and scratch files),
/// for reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ScratchStats {
    /// The most bytes of RAM columns alive at once.
    pub peak_ram_bytes: u64,
    /// The most bytes of scratch files alive at once.
    pub peak_file_bytes: u64,
    /// Bytes of all scratch files created (each is written once).
    pub file_bytes_total: u64,
    /// Scratch files created.
    pub files: u64,
}

/// The allocator of columns: the budget, the directory and the counters.
/// Columns borrow it, so it outlives them.
#[derive(Debug)]
pub(crate) struct Scratch {
    config: ScratchConfig,
    /// Bytes of RAM columns alive; guards the budget.
    ram: AtomicU64,
    /// Bytes of scratch files alive; guards `scratch_limit`.
    file: AtomicU64,
    peak_ram: AtomicU64,
    peak_file: AtomicU64,
    file_total: AtomicU64,
    /// Scratch files created so far.
    files: AtomicU64,
    /// File names handed out; makes them unique.
    names: AtomicU64,
    pool: Mutex<Pool>,
}

/// The memory of dropped RAM columns of at least [`Pool::MIN_BYTES`], kept
/// for the next columns it fits.
///
/// Fresh memory costs a page fault and a zeroed page on its first touch:
/// 1.8–4.3 µs a page on this project's virtual machines, against 0.16 µs
/// to zero a page that is already mapped. The level builder drops each
/// level's columns once the next level is written, so the level after
/// next can be made in their memory. Levels grow (clipped references), so
/// a fresh buffer is made with [`Pool::HEADROOM`] to spare: the same
/// column two levels on still fits it.
///
/// Bounds: a buffer is kept only while the pool and the RAM columns alive
/// together stay within the budget, at most [`Pool::MAX_BUFFERS`] are
/// kept, and a request that fits none drops the smaller ones (older
/// levels' columns, which no later request of their kind fits either).
/// The headroom is address space: only the pages a column uses are
/// touched. Under a budget ([`ScratchConfig::mem_budget`] below
/// `u64::MAX`) buffers are made to measure instead, since a pooled column
/// counts against the budget with its whole capacity.
///
/// The level builder asks for its columns with
/// [`Scratch::column_for_overwrite`], so reused memory is not zeroed
/// first (a fresh buffer is zeroed lazily by the system, page by page, as
/// the parallel passes first write it).
///
/// On stk_all (6.2 M triangles, 2 threads, no budget) the pool cuts the
/// build's page faults from 2.83 M to 0.74 M; the figures, and the
/// variants not taken, are in `docs/perf-notes.md`.
#[derive(Debug, Default)]
struct Pool {
    /// Buffers of `u64`s, so that any `Pod` type of alignment up to 8 can
    /// be laid over them.
    free: Vec<Vec<u64>>,
    /// Bytes of capacity in `free`.
    bytes: u64,
}

impl Pool {
    const MIN_BYTES: u64 = 1 << 20;
    const MAX_BUFFERS: usize = 16;
    /// A fresh buffer's capacity over the request, in eighths. (Five
    /// quarters make no fewer page faults, and 3.5% more peak RssAnon on
    /// stk_all.)
    const HEADROOM: usize = 9;

    /// The smallest buffer of at least `words`, if one is kept.
    fn take(&mut self, words: usize) -> Option<Vec<u64>> {
        let i = self
            .free
            .iter()
            .enumerate()
            .filter(|(_, b)| b.capacity() >= words)
            .min_by_key(|(_, b)| b.capacity())?
            .0;
        let b = self.free.swap_remove(i);
        self.bytes -= Self::bytes_of(&b);
        Some(b)
    }

    /// Makes room for a fresh buffer of `words` that no kept one fits:
    /// drops the kept buffers smaller than it, then more until the pool
    /// holds at most `room` bytes.
    fn make_room(&mut self, words: usize, room: u64) {
        self.free.retain(|b| b.capacity() >= words);
        self.bytes = self.free.iter().map(Self::bytes_of).sum();
        while self.bytes > room {
            let b = self.free.pop().expect("bytes are held");
            self.bytes -= Self::bytes_of(&b);
        }
    }

    fn bytes_of(b: &Vec<u64>) -> u64 {
        b.capacity() as u64 * 8
    }
}

impl Scratch {
    /// Checks that the scratch directory exists when a budget can send
    /// columns there, so a bad directory fails before any work is done.
    pub fn new(config: ScratchConfig) -> Result<Scratch, ColumnsError> {
        if config.mem_budget.is_some() {
            match std::fs::metadata(&config.dir) {
                Ok(m) if m.is_dir() => {}
                Ok(_) => {
                    return Err(ColumnsError::NoDir {
                        path: config.dir.clone(),
                        source: io::Error::new(io::ErrorKind::NotADirectory, "not a directory"),
                    });
                }
                Err(source) => {
                    return Err(ColumnsError::NoDir {
                        path: config.dir.clone(),
                        source,
                    });
                }
            }
        }
        Ok(Scratch {
            config,
            ram: AtomicU64::new(0),
            file: AtomicU64::new(0),
            peak_ram: AtomicU64::new(0),
            peak_file: AtomicU64::new(0),
            file_total: AtomicU64::new(0),
            files: AtomicU64::new(0),
            names: AtomicU64::new(0),
            pool: Mutex::new(Pool::default()),
        })
    }

    /// The bytes of columns kept in RAM at once (`None`: no budget).
    pub fn mem_budget(&self) -> Option<u64> {
        self.config.mem_budget
    }

    /// The budget as a bound to compare byte counts with: no budget is
    /// no bound.
    fn ram_limit(&self) -> u64 {
        self.config.mem_budget.unwrap_or(u64::MAX)
    }

    /// What the columns made so far used, peaks included.
    pub fn stats(&self) -> ScratchStats {
        ScratchStats {
            peak_ram_bytes: self.peak_ram.load(Ordering::Relaxed),
            peak_file_bytes: self.peak_file.load(Ordering::Relaxed),
            file_bytes_total: self.file_total.load(Ordering::Relaxed),
            files: self.files.load(Ordering::Relaxed),
        }
    }

    /// A zeroed column of `len` elements; `name` goes into the file name.
    /// Only the tests make one: the level builder writes its columns whole
    /// ([`Scratch::column_for_overwrite`]).
    #[cfg(test)]
    pub fn column<T: Pod>(&self, name: &str, len: usize) -> Result<Column<'_, T>, ColumnsError> {
        self.make(name, len, true)
    }

    /// A column of `len` elements whose contents are unspecified: zeros,
    /// or a dropped column's bytes where it reuses that memory (any bytes
    /// are a valid `T`, which is `Pod`). For a caller that writes every
    /// element before it reads it, so that reused memory is not zeroed
    /// first: each level of the level builder rewrites hundreds of MB on
    /// large scenes. Debug builds fill reused memory with `0xA5` bytes
    /// instead, so that an element read before it is written shows.
    pub fn column_for_overwrite<T: Pod>(
        &self,
        name: &str,
        len: usize,
    ) -> Result<Column<'_, T>, ColumnsError> {
        self.make(name, len, false)
    }

    fn make<T: Pod>(
        &self,
        name: &str,
        len: usize,
        zeroed: bool,
    ) -> Result<Column<'_, T>, ColumnsError> {
        let bytes = (len as u64).saturating_mul(size_of::<T>() as u64);
        // Reserve the bytes against the budget first; give them back when
        // they do not fit, so concurrent allocations never overshoot it.
        let before = self.ram.fetch_add(bytes, Ordering::Relaxed);
        // An empty column needs no file, whatever the budget.
        if bytes == 0
            || before
                .checked_add(bytes)
                .is_some_and(|b| b <= self.ram_limit())
        {
            if bytes >= Pool::MIN_BYTES && align_of::<T>() <= 8 {
                let v = self.words(bytes.div_ceil(8) as usize, before, zeroed);
                // A pooled buffer counts with its whole capacity: the
                // pages an earlier column touched past this one's end
                // stay resident.
                let held = Pool::bytes_of(&v);
                self.ram.fetch_add(held - bytes, Ordering::Relaxed);
                self.peak_ram.fetch_max(before + held, Ordering::Relaxed);
                return Ok(Column {
                    storage: Storage::Pooled(v),
                    len,
                    bytes: held,
                    scratch: self,
                });
            }
            self.peak_ram.fetch_max(before + bytes, Ordering::Relaxed);
            return Ok(Column {
                storage: Storage::Ram(vec![T::zeroed(); len]),
                len,
                bytes,
                scratch: self,
            });
        }
        self.ram.fetch_sub(bytes, Ordering::Relaxed);
        let seq = self.names.fetch_add(1, Ordering::Relaxed);
        let path = self
            .config
            .dir
            .join(format!("slimkd-{}-{seq}-{name}.col", std::process::id()));
        let before = self.file.fetch_add(bytes, Ordering::Relaxed);
        if let Some(limit) = self.config.scratch_limit
            && before + bytes > limit
        {
            self.file.fetch_sub(bytes, Ordering::Relaxed);
            return Err(ColumnsError::Limit {
                path: self.config.dir.clone(),
                limit,
                requested: before + bytes,
            });
        }
        // From here on, the column (or its drop on error) gives the bytes
        // back.
        let map = match map_file(&path, bytes) {
            Ok(m) => m,
            Err(e) => {
                self.file.fetch_sub(bytes, Ordering::Relaxed);
                return Err(e);
            }
        };
        self.peak_file.fetch_max(before + bytes, Ordering::Relaxed);
        self.file_total.fetch_add(bytes, Ordering::Relaxed);
        self.files.fetch_add(1, Ordering::Relaxed);
        Ok(Column {
            storage: Storage::File {
                map,
                path: (!cfg!(unix)).then_some(path),
            },
            len,
            bytes,
            scratch: self,
        })
    }

    /// `words` `u64`s, in a pooled buffer where one fits (zeroed if
    /// `zeroed`, else as it was); else fresh zeroed ones, after dropping
    /// kept buffers until the RAM columns alive (`alive` bytes besides
    /// this one), the pool and it fit the budget.
    fn words(&self, words: usize, alive: u64, zeroed: bool) -> Vec<u64> {
        // Under a budget a buffer is made to measure: the headroom would
        // count against the budget and send other columns to files.
        let capacity = if self.config.mem_budget.is_none() {
            words / 8 * Pool::HEADROOM + 1
        } else {
            words
        };
        let reused = self.pool.lock().map_or(None, |mut p| {
            let got = p.take(words);
            if got.is_none() {
                let need = alive.saturating_add(capacity as u64 * 8);
                p.make_room(words, self.ram_limit().saturating_sub(need));
            }
            got
        });
        match reused {
            Some(mut v) => {
                if zeroed {
                    v.clear();
                } else {
                    v.truncate(words);
                }
                // A buffer of a larger column (levels shrink once the
                // finisher takes their nodes) gives its pages past the
                // headroom back to the system, so that a shrinking level
                // keeps no more memory than a fresh buffer would.
                if v.capacity() > capacity {
                    v.shrink_to(capacity);
                }
                v.resize(words, 0);
                if !zeroed && cfg!(debug_assertions) {
                    v.fill(0xA5A5_A5A5_A5A5_A5A5);
                }
                v
            }
            None => {
                // Zeroed by the system as its pages are first touched
                // (by the parallel passes that fill the column), not here.
                let mut v = vec![0u64; capacity];
                v.truncate(words);
                v
            }
        }
    }

    /// Drops the pool's buffers (when no more large columns will be made:
    /// the level builder calls it after its last level).
    pub fn release_pool(&self) {
        if let Ok(mut p) = self.pool.lock() {
            *p = Pool::default();
        }
    }

    /// Keeps a dropped column's buffer for later columns, within the
    /// bounds of [`Pool`].
    fn give_back(&self, v: Vec<u64>) {
        let Ok(mut pool) = self.pool.lock() else {
            return;
        };
        let bytes = Pool::bytes_of(&v);
        let alive = self.ram.load(Ordering::Relaxed);
        let within = alive.saturating_add(pool.bytes).saturating_add(bytes) <= self.ram_limit();
        if within && pool.free.len() < Pool::MAX_BUFFERS {
            pool.bytes += bytes;
            pool.free.push(v);
        }
    }
}

/// Creates `path` (it must not exist), reserves `bytes` for it, maps it
/// and, on Unix, unlinks it. Nothing is left at `path` on error.
pub(crate) fn map_file(path: &Path, bytes: u64) -> Result<Option<MmapMut>, ColumnsError> {
    let err = |op, source| ColumnsError::File {
        path: path.to_path_buf(),
        op,
        source,
    };
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .create_new(true)
        .open(path)
        .map_err(|e| err("create", e))?;
    // The file exists from here: remove it on every early return.
    let result = reserve_and_map(&file, path, bytes);
    if result.is_err() || cfg!(unix) {
        // On Unix the mapping keeps the unlinked file's pages alive, and
        // the kernel frees them when the mapping goes, however the process
        // ends. A failed removal leaves a file behind, which is worth an
        // error of its own only when nothing else went wrong.
        if let Err(e) = std::fs::remove_file(path)
            && result.is_ok()
        {
            return Err(err("remove", e));
        }
    }
    result
}

fn reserve_and_map(file: &File, path: &Path, bytes: u64) -> Result<Option<MmapMut>, ColumnsError> {
    if bytes == 0 {
        // A zero-length mapping is an error on Linux; an empty column needs
        // no bytes.
        return Ok(None);
    }
    reserve(file, bytes).map_err(|e| {
        if e.kind() == io::ErrorKind::StorageFull || e.raw_os_error() == Some(28) {
            ColumnsError::NoSpace {
                path: path.to_path_buf(),
                bytes,
            }
        } else {
            ColumnsError::File {
                path: path.to_path_buf(),
                op: "reserve space for",
                source: e,
            }
        }
    })?;
    // SAFETY: the file was created by this call with `create_new`, under a
    // name no other column uses, and (on Unix) is unlinked right after, so
    // nothing else in this process writes or truncates it while it is
    // mapped. Another process could open it in the instant between
    // creation and unlinking and truncate it, but the scratch directory is
    // the user's own; no data of ours outside the mapping depends on it.
    let map = unsafe { MmapMut::map_mut(file) }.map_err(|e| ColumnsError::File {
        path: path.to_path_buf(),
        op: "map",
        source: e,
    })?;
    Ok(Some(map))
}

/// Sizes the file to `bytes`, allocating its blocks now.
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
fn reserve(file: &File, bytes: u64) -> io::Result<()> {
    use std::os::fd::AsRawFd;
    unsafe extern "C" {
        // glibc and musl: `int posix_fallocate(int fd, off_t offset, off_t
        // len)`, with a 64-bit `off_t` on 64-bit Linux. It returns an error
        // number instead of setting errno.
        fn posix_fallocate(fd: i32, offset: i64, len: i64) -> i32;
    }
    let len = i64::try_from(bytes).map_err(|_| io::Error::from(io::ErrorKind::FileTooLarge))?;
    // SAFETY: the descriptor belongs to `file`, which is open for writing
    // and outlives the call; the function reads no memory of ours.
    let rc = unsafe { posix_fallocate(file.as_raw_fd(), 0, len) };
    match rc {
        0 => Ok(()),
        // Filesystems without fallocate (and glibc's emulation failing)
        // fall back to writing zeros.
        95 => write_zeros(file, bytes),
        e => Err(io::Error::from_raw_os_error(e)),
    }
}

#[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
fn reserve(file: &File, bytes: u64) -> io::Result<()> {
    write_zeros(file, bytes)
}

/// Writes `bytes` zeros, so the filesystem allocates (or refuses) them now.
#[allow(dead_code)]
fn write_zeros(mut file: &File, bytes: u64) -> io::Result<()> {
    use std::io::Write;
    let zeros = vec![0u8; 1 << 20];
    let mut left = bytes;
    while left > 0 {
        let n = left.min(zeros.len() as u64) as usize;
        file.write_all(&zeros[..n])?;
        left -= n as u64;
    }
    file.flush()
}

enum Storage<T> {
    Ram(Vec<T>),
    /// A large column in a buffer that goes back to the pool: at least
    /// `len * size_of::<T>()` bytes of `u64`s (`T`'s alignment is at most
    /// 8).
    Pooled(Vec<u64>),
    /// `None` for an empty column. `path` is kept only where the file must
    /// be removed on drop (not on Unix, where it is already unlinked).
    File {
        map: Option<MmapMut>,
        path: Option<PathBuf>,
    },
}

/// A column of `len` elements of `T`, in RAM or in a mapped scratch file.
/// Dereferences to `[T]`.
pub(crate) struct Column<'s, T: Pod> {
    storage: Storage<T>,
    len: usize,
    /// What this column counts against the budget or the scratch limit.
    bytes: u64,
    scratch: &'s Scratch,
}

impl<T: Pod> Column<'_, T> {
    /// Whether the column is a mapped file.
    pub fn is_mapped(&self) -> bool {
        matches!(self.storage, Storage::File { .. })
    }
}

impl<T: Pod> Deref for Column<'_, T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        match &self.storage {
            Storage::Ram(v) => v,
            // 8-aligned, and cut to a whole number of `T`s: the cast checks
            // both and cannot fail.
            Storage::Pooled(v) => bytemuck::cast_slice(
                &bytemuck::cast_slice::<u64, u8>(v)[..self.len * size_of::<T>()],
            ),
            Storage::File { map: Some(m), .. } => {
                // A page-aligned mapping of exactly `len * size_of::<T>()`
                // bytes: the cast checks both and cannot fail.
                bytemuck::cast_slice(&m[..self.len * size_of::<T>()])
            }
            Storage::File { map: None, .. } => &[],
        }
    }
}

impl<T: Pod> DerefMut for Column<'_, T> {
    fn deref_mut(&mut self) -> &mut [T] {
        let len = self.len;
        match &mut self.storage {
            Storage::Ram(v) => v,
            Storage::Pooled(v) => bytemuck::cast_slice_mut(
                &mut bytemuck::cast_slice_mut::<u64, u8>(v)[..len * size_of::<T>()],
            ),
            Storage::File { map: Some(m), .. } => {
                bytemuck::cast_slice_mut(&mut m[..len * size_of::<T>()])
            }
            Storage::File { map: None, .. } => &mut [],
        }
    }
}

impl<T: Pod> Drop for Column<'_, T> {
    fn drop(&mut self) {
        match &mut self.storage {
            Storage::Ram(_) => {
                self.scratch.ram.fetch_sub(self.bytes, Ordering::Relaxed);
            }
            Storage::Pooled(v) => {
                self.scratch.ram.fetch_sub(self.bytes, Ordering::Relaxed);
                self.scratch.give_back(std::mem::take(v));
            }
            Storage::File { map, path } => {
                // Unmap before removing, which some systems require.
                drop(map.take());
                if let Some(p) = path.take() {
                    let _ = std::fs::remove_file(p);
                }
                self.scratch.file.fetch_sub(self.bytes, Ordering::Relaxed);
            }
        }
    }
}

impl<T: Pod> fmt::Debug for Column<'_, T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Column")
            .field("len", &self.len)
            .field("mapped", &self.is_mapped())
            .finish()
    }
}

/// A view for writing disjoint elements of one slice from several threads.
///
/// The parallel passes of the level builder scatter elements to positions
/// computed by prefix sums; no two writers share a position, but the
/// positions of one writer are not one contiguous range, so the slice
/// cannot be split safely beforehand.
pub(crate) struct ScatterSlice<'a, T> {
    ptr: *mut T,
    len: usize,
    _slice: PhantomData<&'a mut [T]>,
}

// SAFETY: a ScatterSlice only hands out writes to distinct positions (the
// caller's obligation on `write`), so sharing it between threads is no
// more than sharing disjoint `&mut T`s, which `T: Send` allows.
unsafe impl<T: Send> Sync for ScatterSlice<'_, T> {}
// SAFETY: as above; it owns nothing.
unsafe impl<T: Send> Send for ScatterSlice<'_, T> {}

impl<'a, T> ScatterSlice<'a, T> {
    /// Shares `slice` for writes at disjoint positions.
    pub fn new(slice: &'a mut [T]) -> ScatterSlice<'a, T> {
        ScatterSlice {
            ptr: slice.as_mut_ptr(),
            len: slice.len(),
            _slice: PhantomData,
        }
    }

    /// Writes `value` at `i` (checked against the length).
    ///
    /// # Safety
    ///
    /// No other thread reads or writes position `i` while the
    /// `ScatterSlice` is alive.
    #[inline]
    pub unsafe fn write(&self, i: usize, value: T) {
        assert!(i < self.len, "scatter index {i} out of {}", self.len);
        // SAFETY: `i` is in bounds (checked above) and the caller promises
        // that no other thread touches position `i`; the borrow in
        // `_slice` keeps the slice alive and otherwise unused.
        unsafe { self.ptr.add(i).write(value) }
    }

    /// A mutable sub-slice `[start, end)`.
    ///
    /// # Safety
    ///
    /// No other thread reads or writes any position of `[start, end)`
    /// while the returned slice is alive.
    #[inline]
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn range_mut(&self, start: usize, end: usize) -> &mut [T] {
        assert!(
            start <= end && end <= self.len,
            "scatter range out of bounds"
        );
        // SAFETY: the range is in bounds (checked above) and exclusive to
        // the caller by its promise.
        unsafe { std::slice::from_raw_parts_mut(self.ptr.add(start), end - start) }
    }
}

#[cfg(test)]
mod tests;
