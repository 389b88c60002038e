//! Temporary directories of the lab's tests.

use std::path::{Path, PathBuf};

/// A directory removed when dropped, unless a panic is unwinding (its
/// files then stay for a look).
pub(crate) struct TestDir(PathBuf);

impl std::ops::Deref for TestDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for TestDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TestDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A fresh, empty directory of this test process (named after the
/// process and `name`) under the system temporary directory.
pub(crate) fn fresh_temp_dir(name: &str) -> TestDir {
    let dir = std::env::temp_dir().join(format!("slimkd-lab-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("cannot make {}: {e}", dir.display()));
    TestDir(dir)
}

/// The names of the entries of `dir`, sorted.
pub(crate) fn dir_entries(dir: &Path) -> Vec<String> {
    slimkd::fsio::entry_names(dir).unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
}
