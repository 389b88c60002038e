//! Opening the `.kd` files the commands read: mapped (or read, with
//! `--no-mmap`) and checked, with errors that name the file; below every
//! command, which all open files the same way.

use crate::CmdResult;
use slimkd::format::{self, Check, KdFile, Mapped};
use std::path::Path;

pub(crate) fn is_kd_file(path: &Path) -> bool {
    slimkd::scene::is_kd_file(path)
}

/// Refuses a scene given to `command`, which reads a `.kd` tree file,
/// saying what it is (by its magic bytes or name) rather than what its
/// first bytes are not.
pub(crate) fn expect_kd(path: &Path, command: &str) -> CmdResult<()> {
    if is_kd_file(path) {
        return Ok(());
    }
    match slimkd::scene::SceneFormat::detect(path) {
        Some(scene) => Err(format!(
            "{}: this is {}, {command} expects a .kd tree file (`slimkd build SCENE -o FILE.kd` makes one)",
            path.display(),
            scene.describe()
        )
        .into()),
        None => Ok(()),
    }
}

/// `--no-mmap`: `.kd` files are read into memory rather than mapped (set
/// once by `main` before any command runs).
pub(crate) static NO_MMAP: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

/// Maps (or with `--no-mmap` reads) a `.kd` file and checks it as `check`
/// says; every error names the file once.
pub(crate) fn open_kd(path: &Path, check: Check) -> CmdResult<KdFile<Mapped>> {
    let opened = if NO_MMAP.load(std::sync::atomic::Ordering::Relaxed) {
        KdFile::read(path, check)
    } else {
        KdFile::open(path, check)
    };
    opened.map_err(|e| match e {
        // It names the file already.
        format::FormatError::Io { .. } => e.to_string().into(),
        _ => format!("{}: {e}", path.display()).into(),
    })
}
