//! The module boundaries of `../shared/DESIGN.md` that hold today, checked
//! on the source: the `use` and path lines of `src/**/*.rs` (comments and
//! `#[cfg(test)]` modules, which may build trees to test with, left out).
//!
//! - `trace`, `render`, `scene`, `geom`, `format` and `tree.rs` never name
//!   `crate::build` (a renderer that reads files does not need the
//!   builder; [`slimkd::progress::Progress`] lives outside it for that).
//! - `build` never names `crate::format`, `crate::trace` or
//!   `crate::render`.

use std::path::{Path, PathBuf};

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Every `.rs` file under `dir` (or `dir` itself if it is a file).
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    if dir.is_file() {
        return vec![dir.to_path_buf()];
    }
    let mut out = Vec::new();
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            out.extend(rust_files(&p));
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
    out
}

/// The non-comment lines of a file's non-test code, with their numbers:
/// everything before its first `#[cfg(test)]`.
fn code_lines(path: &Path) -> Vec<(usize, String)> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.lines()
        .enumerate()
        .take_while(|(_, l)| l.trim() != "#[cfg(test)]")
        .filter(|(_, l)| !l.trim_start().starts_with("//"))
        .map(|(i, l)| (i + 1, l.to_string()))
        .collect()
}

/// The lines of the files under `dirs` (relative to `src/`) that name any
/// of `forbidden`, as `path:line: text`.
fn violations(dirs: &[&str], forbidden: &[&str]) -> Vec<String> {
    let root = src();
    let mut out = Vec::new();
    for d in dirs {
        let files = rust_files(&root.join(d));
        assert!(!files.is_empty(), "no Rust file under src/{d}");
        for f in files {
            for (n, line) in code_lines(&f) {
                if forbidden.iter().any(|p| line.contains(p)) {
                    out.push(format!("{}:{n}: {}", f.display(), line.trim()));
                }
            }
        }
    }
    out
}

#[test]
fn only_the_builder_and_its_users_name_the_builder() {
    let v = violations(
        &["trace", "render", "scene", "geom", "format", "tree.rs"],
        &["crate::build"],
    );
    assert!(v.is_empty(), "these name the builder:\n{}", v.join("\n"));
}

#[test]
fn the_builder_never_names_format_trace_or_render() {
    let v = violations(
        &["build"],
        &["crate::format", "crate::trace", "crate::render"],
    );
    assert!(
        v.is_empty(),
        "the builder names format, trace or render:\n{}",
        v.join("\n")
    );
}

/// The check itself finds what it looks for.
#[test]
fn the_check_sees_a_use_line() {
    let v = violations(&["render"], &["crate::progress"]);
    assert!(!v.is_empty());
}
