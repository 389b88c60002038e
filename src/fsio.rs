//! Atomic file writes, shared by every writer of the crate (the `.kd`
//! writer, the image writers and the binary scene cache).
//!
//! A file is written to a temporary file in the same directory (a fresh
//! name per call, so concurrent writes to one path never share it), synced,
//! renamed onto its path, and the directory is synced (best effort). A
//! failed or killed write leaves no file at the path, and never a
//! half-written one that could pass for valid; a failed write removes its
//! temporary file and leaves whatever was at the path untouched.
//!
//! On Linux the temporary file has no name while it is written
//! (`O_TMPFILE`): it is given one (`linkat` through `/proc/self/fd`) only
//! once written and synced, just before the rename. So a write killed by
//! Ctrl-C, `kill -9` or the OOM killer leaves nothing behind, not even a
//! hidden temporary file of the size written so far. Where the directory's
//! filesystem or the kernel cannot do that, or `/proc` is not mounted, the
//! temporary file is named from the start (`.NAME.tmp.PID.N`).
//!
//! A write killed between naming and renaming (or, named from the start,
//! at any time) leaves `.NAME.tmp.PID.N` behind. The next write of the same
//! path removes every such file whose writer `PID` no longer runs (a live
//! writer's, including this process's own concurrent writes, is left
//! alone), so a leftover lasts only until the path is written again.
//!
//! [`open_regular`] is the one way the crate opens an input file: it
//! refuses what is not a regular file (a FIFO would block `open` forever).

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
    let mut staged = Staged::create(path).map_err(&io)?;
    body(staged.file())?;
    staged.commit().map_err(&io)
}

/// A file being written to replace `path` atomically: a temporary file in
/// the same directory (unnamed while written, where it can be), then
/// [`Staged::stage`]d (synced and named) and [`Staged::commit`]ted
/// (renamed onto `path`, the directory synced, best effort). Dropped
/// before its commit, it leaves nothing behind and `path` untouched.
///
/// Several files can be written all or nothing: stage every one, then
/// commit them (what the report does with its Markdown, JSON and figures).
pub struct Staged {
    file: Option<File>,
    /// The temporary file's name, once it has one.
    named: Option<PathBuf>,
    /// Synced and named: only the rename is left.
    staged: bool,
    path: PathBuf,
    dir: PathBuf,
}

impl Staged {
    /// A fresh temporary file for `path`, opened for reading and writing.
    pub fn create(path: &Path) -> std::io::Result<Staged> {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        if path.file_name().is_none() {
            return Err(std::io::Error::other("not a file name"));
        }
        let mut staged = Staged {
            file: None,
            named: None,
            staged: false,
            path: path.to_path_buf(),
            dir,
        };
        remove_stale_temporaries(&staged.dir, path.file_name().expect("checked"));
        if let Some(f) = unnamed::create(&staged.dir) {
            staged.file = Some(f);
            return Ok(staged);
        }
        // A name left behind by a killed writer is skipped, never reused.
        for _ in 0..100 {
            let tmp = staged.fresh_name();
            match std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create_new(true)
                .open(&tmp)
            {
                Ok(f) => {
                    staged.file = Some(f);
                    staged.named = Some(tmp);
                    return Ok(staged);
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(e),
            }
        }
        Err(std::io::Error::other("no free temporary name"))
    }

    /// The file to write.
    pub fn file(&mut self) -> &mut File {
        self.file
            .as_mut()
            .expect("a staged file is open until committed")
    }

    /// Syncs the contents and gives the file its temporary name, so that
    /// only the rename is left (once: staging again does nothing).
    pub fn stage(&mut self) -> std::io::Result<()> {
        if self.staged {
            return Ok(());
        }
        let f = self
            .file
            .as_ref()
            .expect("a staged file is open until committed");
        f.sync_all()?;
        if self.named.is_none() {
            self.named = Some(unnamed::give_name(f, || self.fresh_name())?);
        }
        self.staged = true;
        Ok(())
    }

    /// Renames the staged file onto its path (staging it first if need
    /// be) and syncs the directory.
    pub fn commit(mut self) -> std::io::Result<()> {
        self.stage()?;
        self.file = None;
        let tmp = self.named.take().expect("staged");
        #[cfg(test)]
        tests::fault_before_rename();
        if let Err(e) = std::fs::rename(&tmp, &self.path) {
            // The original error is more useful than a failure to clean up.
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
        // Make the rename durable; not every platform can open a directory.
        if let Ok(d) = File::open(&self.dir) {
            let _ = d.sync_all();
        }
        Ok(())
    }

    fn fresh_name(&self) -> PathBuf {
        let name = self.path.file_name().expect("checked in create");
        self.dir.join(format!(
            ".{}.tmp.{}.{}",
            name.to_string_lossy(),
            std::process::id(),
            TMP_COUNTER.fetch_add(1, Ordering::Relaxed)
        ))
    }
}

/// The writer's process id in `entry` if it is a temporary file of `name`
/// (`.NAME.tmp.PID.N`, as [`Staged::fresh_name`] makes them).
fn temporary_writer(entry: &str, name: &str) -> Option<u32> {
    let rest = entry.strip_prefix('.')?.strip_prefix(name)?;
    let (pid, n) = rest.strip_prefix(".tmp.")?.split_once('.')?;
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    (digits(pid) && digits(n)).then(|| pid.parse().ok())?
}

/// Whether process `pid` runs (where that cannot be told: yes, so that
/// nothing a live writer may still rename is removed).
fn process_runs(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    #[cfg(target_os = "linux")]
    {
        let Ok(pid) = libc::pid_t::try_from(pid) else {
            return true;
        };
        if pid <= 0 {
            return true;
        }
        // SAFETY: signal 0 sends nothing; `kill` only checks that the
        // process exists and takes no pointers.
        let rc = unsafe { libc::kill(pid, 0) };
        rc == 0 || std::io::Error::last_os_error().raw_os_error() != Some(libc::ESRCH)
    }
    #[cfg(not(target_os = "linux"))]
    {
        true
    }
}

/// Removes the temporary files of `name` in `dir` that writers killed
/// before their rename left (best effort: a failure to list or remove is
/// not the new write's failure).
fn remove_stale_temporaries(dir: &Path, name: &std::ffi::OsStr) {
    let Some(name) = name.to_str() else {
        return;
    };
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let Some(entry_name) = file_name.to_str() else {
            continue;
        };
        if let Some(pid) = temporary_writer(entry_name, name)
            && !process_runs(pid)
        {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// Opens `path` for reading if it is a regular file (after symbolic
/// links); anything else is an error that says what it is. The check is
/// made on the path before opening and again on the open file, which is
/// opened non-blocking so that a FIFO swapped in between cannot block the
/// `open` (on a regular file `O_NONBLOCK` changes nothing).
pub fn open_regular(path: &Path) -> std::io::Result<File> {
    let not_regular = |m: &std::fs::Metadata| -> std::io::Error {
        if m.is_dir() {
            return std::io::ErrorKind::IsADirectory.into();
        }
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("not a regular file ({})", file_kind(m)),
        )
    };
    let before = std::fs::metadata(path)?;
    if !before.is_file() {
        return Err(not_regular(&before));
    }
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path)?;
    let after = file.metadata()?;
    if !after.is_file() {
        return Err(not_regular(&after));
    }
    Ok(file)
}

/// What kind of file `m` describes, in words.
fn file_kind(m: &std::fs::Metadata) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        let t = m.file_type();
        if t.is_fifo() {
            return "a FIFO";
        }
        if t.is_socket() {
            return "a socket";
        }
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
    }
    if m.is_dir() {
        "a directory"
    } else {
        "a special file"
    }
}

impl Drop for Staged {
    /// Not committed: the temporary file goes (an unnamed one with its
    /// descriptor).
    fn drop(&mut self) {
        self.file = None;
        if let Some(tmp) = self.named.take() {
            let _ = std::fs::remove_file(tmp);
        }
    }
}

/// Unnamed temporary files (`O_TMPFILE`), named once written.
#[cfg(target_os = "linux")]
mod unnamed {
    use std::ffi::CString;
    use std::fs::File;
    use std::os::fd::AsRawFd;
    use std::os::unix::ffi::OsStrExt;
    use std::os::unix::fs::OpenOptionsExt;
    use std::path::{Path, PathBuf};

    /// An unnamed file in `dir`, opened for reading and writing, or `None`
    /// where that cannot be done (the filesystem or kernel lacks
    /// `O_TMPFILE`, or `/proc` is not mounted, so it could not be named
    /// later; the caller then names its file from the start).
    pub fn create(dir: &Path) -> Option<File> {
        if !Path::new("/proc/self/fd").is_dir() {
            return None;
        }
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .mode(0o666)
            .custom_flags(libc::O_TMPFILE)
            .open(dir)
            .ok()
    }

    /// Links the unnamed file `f` into its directory under the first name
    /// `fresh` gives that is free; returns that name.
    pub fn give_name(f: &File, fresh: impl Fn() -> PathBuf) -> std::io::Result<PathBuf> {
        let src =
            CString::new(format!("/proc/self/fd/{}", f.as_raw_fd())).expect("no NUL in a number");
        for _ in 0..100 {
            let name = fresh();
            let dst = CString::new(name.as_os_str().as_bytes())
                .map_err(|_| std::io::Error::other("a NUL byte in the path"))?;
            // SAFETY: both paths are NUL-terminated strings that outlive the
            // call; `linkat` reads them and keeps no pointer.
            let rc = unsafe {
                libc::linkat(
                    libc::AT_FDCWD,
                    src.as_ptr(),
                    libc::AT_FDCWD,
                    dst.as_ptr(),
                    libc::AT_SYMLINK_FOLLOW,
                )
            };
            if rc == 0 {
                return Ok(name);
            }
            let e = std::io::Error::last_os_error();
            if e.kind() != std::io::ErrorKind::AlreadyExists {
                return Err(e);
            }
        }
        Err(std::io::Error::other("no free temporary name"))
    }
}

/// Elsewhere the temporary file is named from the start.
#[cfg(not(target_os = "linux"))]
mod unnamed {
    use std::fs::File;
    use std::path::{Path, PathBuf};

    pub fn create(_dir: &Path) -> Option<File> {
        None
    }

    pub fn give_name(_f: &File, _fresh: impl Fn() -> PathBuf) -> std::io::Result<PathBuf> {
        unreachable!("no unnamed files here")
    }
}

/// The names of the entries of `dir`, sorted (lossily made UTF-8): what a
/// directory holds after writes, which the tests check for temporary files
/// left behind.
pub fn entry_names(dir: &Path) -> std::io::Result<Vec<String>> {
    let mut names = std::fs::read_dir(dir)?
        .map(|e| Ok(e?.file_name().to_string_lossy().into_owned()))
        .collect::<std::io::Result<Vec<String>>>()?;
    names.sort();
    Ok(names)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// Set in a child process of `a_kill_before_the_rename_is_cleaned_up`
    /// (from its environment): the write dies between naming its
    /// temporary file and the rename, as a `kill -9` there would.
    pub(super) fn fault_before_rename() {
        if std::env::var_os(KILL_BEFORE_RENAME).is_some() {
            std::process::abort();
        }
    }

    const KILL_BEFORE_RENAME: &str = "SLIMKD_TEST_FSIO_KILL_BEFORE_RENAME";

    /// The child's half of the test below: writes `out.bin` in the
    /// directory its environment names and dies before the rename.
    #[test]
    fn child_killed_before_rename() {
        let Some(dir) = std::env::var_os(KILL_BEFORE_RENAME) else {
            return;
        };
        let path = Path::new(&dir).join("out.bin");
        let _ = write_atomically(&path, |e| e, |f| f.write_all(b"complete"));
        unreachable!("the write dies before its rename");
    }

    /// A writer killed between naming its temporary file and the rename
    /// leaves `.out.bin.tmp.PID.N`; the next write of `out.bin` removes it
    /// (its writer is dead) and leaves a live writer's alone.
    #[test]
    fn a_kill_before_the_rename_is_cleaned_up() {
        let dir = scratch("killed");
        let status = std::process::Command::new(std::env::current_exe().unwrap())
            .args([
                "fsio::tests::child_killed_before_rename",
                "--exact",
                "--quiet",
            ])
            .env(KILL_BEFORE_RENAME, &dir)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .unwrap();
        assert!(!status.success());
        let left = entries(&dir);
        assert_eq!(left.len(), 1, "{left:?}");
        assert!(left[0].starts_with(".out.bin.tmp."), "{left:?}");
        assert_eq!(std::fs::read(dir.join(&left[0])).unwrap(), b"complete");
        // A live writer's temporary file (this process's) stays.
        let live = format!(".out.bin.tmp.{}.999999", std::process::id());
        std::fs::write(dir.join(&live), b"live").unwrap();
        write_atomically(&dir.join("out.bin"), |e| e, |f| f.write_all(b"again")).unwrap();
        assert_eq!(entries(&dir), [live.as_str(), "out.bin"]);
        assert_eq!(std::fs::read(dir.join("out.bin")).unwrap(), b"again");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn temporary_names_are_recognised_exactly() {
        assert_eq!(temporary_writer(".a.kd.tmp.123.4", "a.kd"), Some(123));
        for other in [
            "a.kd",
            ".a.kd.tmp.123",
            ".a.kd.tmp.x.4",
            ".a.kd.tmp.123.4.5",
            ".b.kd.tmp.123.4",
            ".a.kd.tmp..4",
            ".xa.kd.tmp.1.2",
        ] {
            assert_eq!(temporary_writer(other, "a.kd"), None, "{other}");
        }
    }

    /// A FIFO is refused at once (no `open` that waits for a writer), a
    /// directory is named as one, a regular file opens.
    #[cfg(target_os = "linux")]
    #[test]
    fn open_regular_refuses_a_fifo() {
        let dir = scratch("fifo");
        let fifo = dir.join("pipe");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a NUL-terminated path that outlives the call.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let e = open_regular(&fifo).unwrap_err();
        assert_eq!(e.to_string(), "not a regular file (a FIFO)");
        let e = open_regular(&dir).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::IsADirectory);
        std::fs::write(dir.join("f"), b"x").unwrap();
        assert!(open_regular(&dir.join("f")).is_ok());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    fn entries(dir: &Path) -> Vec<String> {
        entry_names(dir).unwrap()
    }

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("slimkd-fsio-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// A write replaces the file whole; a failed one leaves the old file
    /// and no temporary file; where unnamed files work, nothing is in the
    /// directory while the body writes (so a kill then leaves nothing).
    #[test]
    fn writes_are_atomic_and_leave_nothing_behind() {
        let dir = scratch("atomic");
        let path = dir.join("out.bin");
        let unnamed_here = unnamed::create(&dir).is_some();
        write_atomically(
            &path,
            |e| e,
            |f| {
                f.write_all(b"first")?;
                if unnamed_here {
                    assert!(entries(&dir).is_empty(), "{:?}", entries(&dir));
                }
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"first");
        assert_eq!(entries(&dir), ["out.bin"]);

        let failed = write_atomically(
            &path,
            |e| e,
            |f| {
                f.write_all(b"second, half")?;
                if unnamed_here {
                    assert_eq!(entries(&dir), ["out.bin"]);
                }
                Err(std::io::Error::other("the body failed"))
            },
        );
        assert_eq!(failed.unwrap_err().to_string(), "the body failed");
        assert_eq!(std::fs::read(&path).unwrap(), b"first");
        assert_eq!(entries(&dir), ["out.bin"]);

        write_atomically(&path, |e| e, |f| f.write_all(b"third")).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"third");
        assert_eq!(entries(&dir), ["out.bin"]);
        // The file reads back while written (the `.kd` writer reads its
        // node section back for the checksum).
        write_atomically(
            &path,
            |e| e,
            |f| {
                use std::io::{Read, Seek, SeekFrom};
                f.write_all(b"fourth")?;
                f.seek(SeekFrom::Start(0))?;
                let mut back = String::new();
                f.read_to_string(&mut back)?;
                assert_eq!(back, "fourth");
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"fourth");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Staged files are all or nothing: one dropped before its commit
    /// leaves no trace (staged and named or not), and the others land only
    /// when committed.
    #[test]
    fn staged_files_land_only_when_committed() {
        let dir = scratch("staged");
        let (a, b) = (dir.join("a.md"), dir.join("b.json"));
        let mut sa = Staged::create(&a).unwrap();
        sa.file().write_all(b"A").unwrap();
        sa.stage().unwrap();
        let mut sb = Staged::create(&b).unwrap();
        sb.file().write_all(b"B").unwrap();
        drop(sb);
        assert_eq!(
            entries(&dir).iter().filter(|e| !e.starts_with('.')).count(),
            0
        );
        drop(sa);
        assert!(entries(&dir).is_empty(), "{:?}", entries(&dir));
        let mut sa = Staged::create(&a).unwrap();
        let mut sb = Staged::create(&b).unwrap();
        sa.file().write_all(b"A").unwrap();
        sb.file().write_all(b"B").unwrap();
        sa.stage().unwrap();
        sb.stage().unwrap();
        sa.commit().unwrap();
        sb.commit().unwrap();
        assert_eq!(entries(&dir), ["a.md", "b.json"]);
        assert_eq!(std::fs::read(&b).unwrap(), b"B");
        assert!(Staged::create(&dir.join("..")).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// This machine's temporary directory (ext4 or tmpfs on Linux) takes
    /// unnamed files, so the test above checks the directory mid-write.
    #[cfg(target_os = "linux")]
    #[test]
    fn unnamed_files_work_on_linux_temp_dirs() {
        let dir = scratch("unnamed");
        assert!(unnamed::create(&dir).is_some());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
