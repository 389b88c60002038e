//! The module boundaries of `../shared/DESIGN.md` that hold today, checked
//! on the source: the `use` and path lines of `src/**/*.rs` (comments and
//! `#[cfg(test)]` modules, which may build trees to test with, left out).
//!
//! - `trace`, `render`, `scene`, `geom`, `format` and `tree.rs` never name
//!   `crate::build` (a renderer that reads files does not need the
//!   builder; [`slimkd::progress::Progress`] lives outside it for that).
//! - `build` never names `crate::format`, `crate::trace`,
//!   `crate::render`, `crate::slim`, `crate::stats`, `crate::cells`,
//!   `crate::pipeline` or `crate::accel` (it is below all of them).
//! - `scene` never names `crate::format` (it knows a `.kd` file by its own
//!   copy of the magic, held equal to the format's at compile time).
//! - The library never names `plotters`: charts are the lab's, in the
//!   binary.
//! - No import circle: not between the library's top-level modules (a
//!   folder counts as one), nor between the files of one folder (a
//!   folder's `mod.rs` and its files may name each other: that is how a
//!   module shares its parent's types), nor in the binary.

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
fn the_builder_names_no_module_above_it() {
    let v = violations(
        &["build"],
        &[
            "crate::format",
            "crate::trace",
            "crate::render",
            "crate::slim",
            "crate::stats",
            "crate::cells",
            "crate::pipeline",
            "crate::accel",
        ],
    );
    assert!(
        v.is_empty(),
        "the builder names a module above it:\n{}",
        v.join("\n")
    );
}

#[test]
fn scene_never_names_the_file_format() {
    let v = violations(&["scene"], &["crate::format"]);
    assert!(v.is_empty(), "scene names format:\n{}", v.join("\n"));
}

#[test]
fn the_library_draws_no_charts() {
    let dirs: Vec<String> = std::fs::read_dir(src())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != "bin")
        .collect();
    let dirs: Vec<&str> = dirs.iter().map(String::as_str).collect();
    let v = violations(&dirs, &["plotters"]);
    assert!(v.is_empty(), "the library draws charts:\n{}", v.join("\n"));
}

/// The check itself finds what it looks for.
#[test]
fn the_check_sees_a_use_line() {
    let v = violations(&["render"], &["crate::progress"]);
    assert!(!v.is_empty());
}

/// One crate's module files: `src/lib.rs` and the modules below it, or a
/// binary's `main.rs` and its modules; each with its module path.
fn crate_modules(root_dir: &Path, root_file: &str, skip: &[&str]) -> Vec<(Vec<String>, PathBuf)> {
    let mut out = Vec::new();
    for f in rust_files(root_dir) {
        let rel = f.strip_prefix(root_dir).unwrap();
        let parts: Vec<String> = rel
            .iter()
            .map(|s| s.to_string_lossy().into_owned())
            .collect();
        if skip.iter().any(|s| parts[0] == *s) {
            continue;
        }
        let mut path: Vec<String> = parts.clone();
        let last = path.pop().unwrap();
        if last != "mod.rs" && last != root_file {
            path.push(last.trim_end_matches(".rs").to_string());
        } else if last == root_file && !path.is_empty() {
            continue; // another crate's root
        }
        out.push((path, f));
    }
    out
}

/// The paths a file's code names through `crate::` and `super::`, made
/// absolute (module path segments, then an item or `*`), groups
/// (`crate::a::{b, c::d}`) expanded.
fn named_paths(code: &str, module: &[String]) -> Vec<Vec<String>> {
    fn ident(s: &[u8], mut i: usize) -> (usize, String) {
        let start = i;
        while i < s.len() && (s[i].is_ascii_alphanumeric() || s[i] == b'_' || s[i] == b'*') {
            i += 1;
        }
        (i, String::from_utf8_lossy(&s[start..i]).into_owned())
    }
    fn skip_ws(s: &[u8], mut i: usize) -> usize {
        while i < s.len() && s[i].is_ascii_whitespace() {
            i += 1;
        }
        i
    }
    /// A use tree at `i` below `prefix`: its leaf paths, and where it ends.
    fn tree(s: &[u8], mut i: usize, prefix: Vec<String>, out: &mut Vec<Vec<String>>) -> usize {
        let mut path = prefix;
        loop {
            i = skip_ws(s, i);
            if i < s.len() && s[i] == b'{' {
                i += 1;
                loop {
                    i = skip_ws(s, i);
                    if i >= s.len() {
                        return i;
                    }
                    if s[i] == b'}' {
                        return i + 1;
                    }
                    if s[i] == b',' {
                        i += 1;
                        continue;
                    }
                    let before = i;
                    i = tree(s, i, path.clone(), out);
                    if i == before {
                        i += 1;
                    }
                }
            }
            let (j, name) = ident(s, i);
            if name.is_empty() {
                if !path.is_empty() {
                    out.push(path);
                }
                return j;
            }
            i = j;
            if name != "self" {
                path.push(name);
            }
            if s[i..].starts_with(b"::") {
                i += 2;
            } else {
                out.push(path);
                return i;
            }
        }
    }
    let s = code.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < s.len() {
        let boundary =
            i == 0 || !(s[i - 1].is_ascii_alphanumeric() || s[i - 1] == b'_' || s[i - 1] == b':');
        if boundary && s[i..].starts_with(b"crate::") {
            i = tree(s, i + 7, Vec::new(), &mut out);
        } else if boundary && s[i..].starts_with(b"super::") {
            let mut base: Vec<String> = module.to_vec();
            while s[i..].starts_with(b"super::") {
                base.pop();
                i += 7;
            }
            i = tree(s, i, base, &mut out);
        } else {
            i += 1;
        }
    }
    out
}

/// The import circles of one crate: between its top-level modules (a
/// folder counts as one), and between the files of one folder (a folder's
/// `mod.rs` and its children may name each other: that is how Rust
/// modules share their parent's types).
fn circles(root_dir: &Path, root_file: &str, skip: &[&str]) -> Vec<String> {
    let modules = crate_modules(root_dir, root_file, skip);
    let code: Vec<String> = modules
        .iter()
        .map(|(_, f)| {
            code_lines(f)
                .into_iter()
                .map(|(_, l)| l)
                .collect::<Vec<_>>()
                .join("\n")
        })
        .collect();
    // File index -> indices of the files it names.
    let mut edges = vec![std::collections::BTreeSet::new(); modules.len()];
    for (a, (module, _)) in modules.iter().enumerate() {
        for p in named_paths(&code[a], module) {
            // The longest module-path prefix of p.
            let target = modules
                .iter()
                .enumerate()
                .filter(|(_, (m, _))| p.starts_with(m))
                .max_by_key(|(_, (m, _))| m.len())
                .map(|(b, _)| b);
            if let Some(b) = target
                && b != a
            {
                edges[a].insert(b);
            }
        }
    }
    let mut found = Vec::new();
    // Two graphs: top-level modules, and siblings within a folder.
    let top = |i: usize| modules[i].0.first().cloned();
    let is_dir_mod = |i: usize| modules[i].1.ends_with("mod.rs");
    let folder = |i: usize| modules[i].1.parent().unwrap().to_path_buf();
    let mut graphs: Vec<(
        String,
        std::collections::BTreeMap<String, std::collections::BTreeSet<String>>,
    )> = vec![("modules".into(), Default::default())];
    for (a, targets) in edges.iter().enumerate() {
        for &b in targets {
            let (Some(ta), Some(tb)) = (top(a), top(b)) else {
                continue; // the crate root re-exports; it is no module's dependency
            };
            if ta != tb {
                graphs[0].1.entry(ta).or_default().insert(tb);
            } else if folder(a) == folder(b) && !is_dir_mod(a) && !is_dir_mod(b) {
                let name = folder(a)
                    .strip_prefix(root_dir)
                    .unwrap()
                    .display()
                    .to_string();
                let g = match graphs.iter_mut().find(|(n, _)| *n == name) {
                    Some((_, g)) => g,
                    None => {
                        graphs.push((name, Default::default()));
                        &mut graphs.last_mut().unwrap().1
                    }
                };
                let file = |i: usize| {
                    modules[i]
                        .1
                        .file_name()
                        .unwrap()
                        .to_string_lossy()
                        .into_owned()
                };
                g.entry(file(a)).or_default().insert(file(b));
            }
        }
    }
    for (name, g) in graphs {
        // Depth-first search for a back edge; report the cycle it closes.
        fn visit(
            n: &str,
            g: &std::collections::BTreeMap<String, std::collections::BTreeSet<String>>,
            stack: &mut Vec<String>,
            done: &mut std::collections::BTreeSet<String>,
            found: &mut Vec<String>,
        ) {
            if let Some(at) = stack.iter().position(|s| s == n) {
                found.push(format!("{} -> {n}", stack[at..].join(" -> ")));
                return;
            }
            if !done.insert(n.to_string()) {
                return;
            }
            stack.push(n.to_string());
            for m in g.get(n).into_iter().flatten() {
                visit(m, g, stack, done, found);
            }
            stack.pop();
        }
        let mut done = Default::default();
        let mut cycles = Vec::new();
        for n in g.keys() {
            visit(n, &g, &mut Vec::new(), &mut done, &mut cycles);
        }
        found.extend(cycles.into_iter().map(|c| format!("{name}: {c}")));
    }
    found
}

#[test]
fn no_import_circle_in_the_library() {
    let c = circles(&src(), "lib.rs", &["bin"]);
    assert!(c.is_empty(), "import circles:\n{}", c.join("\n"));
}

#[test]
fn no_import_circle_in_the_cli() {
    let c = circles(&src().join("bin/slimkd"), "main.rs", &[]);
    assert!(c.is_empty(), "import circles:\n{}", c.join("\n"));
}

/// The circle check sees a circle: two siblings naming each other, and
/// two modules naming each other.
#[test]
fn the_circle_check_sees_a_circle() {
    let dir = std::env::temp_dir().join(format!("slimkd-circles-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("a")).unwrap();
    std::fs::write(dir.join("lib.rs"), "pub mod a;\npub mod b;\n").unwrap();
    std::fs::write(dir.join("a/mod.rs"), "mod x;\nmod y;\nuse crate::b::B;\n").unwrap();
    std::fs::write(dir.join("a/x.rs"), "use super::y::{Y, self};\n").unwrap();
    std::fs::write(
        dir.join("a/y.rs"),
        "pub struct Y;\nfn f() { super::x::g(); }\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("b.rs"),
        "use crate::{a::{self, x}, c};\npub struct B;\n",
    )
    .unwrap();
    let c = circles(&dir, "lib.rs", &[]);
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(
        c.iter().any(|c| c.contains("x.rs -> y.rs -> x.rs")),
        "{c:?}"
    );
    assert!(c.iter().any(|c| c.contains("a -> b -> a")), "{c:?}");
}
