//! Atomic file writes, shared by every writer of the crate (the `.kd`
//! writer, the image writers and the binary scene cache).
//!
//! A file is written to a temporary file in the same directory (a fresh
//! name per call, so concurrent writes to one path never share it), synced,
//! renamed onto its path, and the directory is synced (best effort). A
//! failed or killed write leaves no file at the path, and never a
//! half-written one that could pass for valid; a failed write removes its
//! temporary file and leaves whatever was at the path untouched.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Distinguishes the temporary files of concurrent writes in one process.
static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes `path` atomically: `body` writes the contents into a fresh
/// temporary file (opened for reading and writing), which is then synced
/// and renamed onto `path`. I/O errors become `E` through `io`.
pub fn write_atomically<E>(
    path: &Path,
    io: impl Fn(std::io::Error) -> E,
    body: impl FnOnce(&mut File) -> Result<(), E>,
) -> Result<(), E> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .ok_or_else(|| io(std::io::Error::other("not a file name")))?;
    // A name left behind by a killed writer is skipped, never reused.
    let mut attempt = 0;
    let (tmp, f) = loop {
        let tmp = dir.join(format!(
            ".{}.tmp.{}.{}",
            name.to_string_lossy(),
            std::process::id(),
            TMP_COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        match std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(f) => break (tmp, f),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && attempt < 100 => {
                attempt += 1;
            }
            Err(e) => return Err(io(e)),
        }
    };
    let result = (|| {
        let mut f = f;
        body(&mut f)?;
        f.sync_all().map_err(&io)?;
        drop(f);
        std::fs::rename(&tmp, path).map_err(&io)
    })();
    if let Err(e) = result {
        // The original error is more useful than a failure to clean up.
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    // Make the rename durable; not every platform can open a directory.
    if let Ok(d) = File::open(&dir) {
        let _ = d.sync_all();
    }
    Ok(())
}
