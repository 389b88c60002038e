use super::*;

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("slimkd-col-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn entries(d: &Path) -> usize {
    std::fs::read_dir(d).unwrap().count()
}

/// A scratch in `dir` that keeps `mem_budget` bytes of columns in RAM.
fn scratch(
    mem_budget: u64,
    dir: &Path,
    scratch_limit: Option<u64>,
) -> Result<Scratch, ColumnsError> {
    Scratch::new(ScratchConfig {
        mem_budget: Some(mem_budget),
        dir: dir.to_path_buf(),
        scratch_limit,
    })
}

#[test]
fn ram_then_file_above_the_budget() {
    let d = dir("budget");
    let s = scratch(64, &d, None).unwrap();
    let mut a = s.column::<u32>("a", 16).unwrap();
    let mut b = s.column::<u64>("b", 1000).unwrap();
    assert!(!a.is_mapped());
    assert!(b.is_mapped());
    a[3] = 7;
    b[999] = 9;
    assert_eq!(b.iter().sum::<u64>(), 9);
    assert_eq!(a.iter().sum::<u32>(), 7);
    assert_eq!(entries(&d), 0, "scratch files are unlinked once mapped");
    drop(b);
    drop(a);
    assert_eq!(s.stats().file_bytes_total, 8000);
    assert_eq!(s.stats().files, 1);
    let empty = s.column::<u64>("e", 0).unwrap();
    assert!(empty.is_empty());
    std::fs::remove_dir_all(d).unwrap();
}

/// A dropped large column's memory makes the next column it fits, which
/// reads as zeros all the same, whatever its type; a column the pool
/// cannot fit gets fresh memory.
#[test]
fn large_columns_reuse_dropped_memory_zeroed() {
    let s = Scratch::new(ScratchConfig::default()).unwrap();
    let n = (Pool::MIN_BYTES / 8) as usize;
    let mut a = s.column::<u64>("a", n).unwrap();
    a.fill(u64::MAX);
    let at = a.as_ptr() as usize;
    drop(a);
    // Smaller, of another type (alignment 4), still at least the pool's
    // minimum: the same memory, zeroed.
    let b = s.column::<[f32; 6]>("b", n / 3 + 1).unwrap();
    assert_eq!(b.as_ptr() as usize, at, "the dropped buffer is reused");
    assert!(b.iter().flatten().all(|&x| x.to_bits() == 0));
    // The pool is empty now: a second column is fresh memory.
    let c = s.column::<u32>("c", 2 * n).unwrap();
    assert_ne!(c.as_ptr() as usize, at);
    assert!(c.iter().all(|&x| x == 0));
    drop((b, c));
    // Released, the pool hands out nothing kept.
    s.release_pool();
    assert!(s.pool.lock().unwrap().free.is_empty());
}

/// A column for overwriting reuses a dropped buffer without zeroing it
/// (in a release build; a debug build fills it with `0xA5`).
#[test]
fn overwrite_columns_reuse_without_zeroing() {
    let s = Scratch::new(ScratchConfig::default()).unwrap();
    let n = (Pool::MIN_BYTES / 4) as usize;
    let mut a = s.column::<u32>("a", n).unwrap();
    a.fill(7);
    let at = a.as_ptr() as usize;
    drop(a);
    let b = s.column_for_overwrite::<u32>("b", n).unwrap();
    assert_eq!(b.as_ptr() as usize, at);
    assert_eq!(b.len(), n);
    let want = if cfg!(debug_assertions) {
        0xA5A5_A5A5
    } else {
        7
    };
    assert!(b.iter().all(|&x| x == want));
}

/// Under a budget the pool keeps a buffer only while it and the RAM
/// columns alive fit the budget, and a buffer is made to measure.
#[test]
fn the_pool_stays_within_the_budget() {
    let mib = 1usize << 20;
    let s = scratch(3 * mib as u64, &std::env::temp_dir(), None).unwrap();
    let a = s.column::<u8>("a", 2 * mib).unwrap();
    let b = s.column::<u8>("b", mib).unwrap();
    assert!(!a.is_mapped() && !b.is_mapped());
    assert_eq!(
        s.stats().peak_ram_bytes,
        3 * mib as u64,
        "no headroom under a budget"
    );
    drop(a);
    // 1 MiB alive + 2 MiB kept = the budget: kept.
    assert_eq!(s.pool.lock().unwrap().bytes, 2 * mib as u64);
    drop(b);
    // 0 alive + 2 + 1 kept: still within.
    assert_eq!(s.pool.lock().unwrap().bytes, 3 * mib as u64);
    // A column of 2.5 MiB fits no buffer: the kept ones are dropped to
    // make room for it, within the budget.
    let c = s.column::<u8>("c", 5 * mib / 2).unwrap();
    assert!(!c.is_mapped());
    let pool = s.pool.lock().unwrap();
    assert!(
        pool.bytes + (5 * mib / 2) as u64 <= 3 * mib as u64,
        "{}",
        pool.bytes
    );
}

#[test]
fn missing_dir_is_an_error_naming_it() {
    let d = std::env::temp_dir().join("slimkd-no-such-dir/deeper");
    let e = scratch(0, &d, None).unwrap_err();
    assert!(e.to_string().contains(&*d.to_string_lossy()), "{e}");
}

#[test]
fn scratch_limit_is_enforced() {
    let d = dir("limit");
    let s = scratch(0, &d, Some(100)).unwrap();
    let _a = s.column::<u8>("a", 60).unwrap();
    let e = s.column::<u8>("b", 60).unwrap_err();
    assert!(matches!(e, ColumnsError::Limit { .. }), "{e}");
    assert_eq!(entries(&d), 0);
    std::fs::remove_dir_all(d).unwrap();
}

#[test]
fn error_messages() {
    let path = PathBuf::from("/s/x");
    let io = || io::Error::from(io::ErrorKind::NotFound);
    let cases: [(ColumnsError, &str); 4] = [
        (
            ColumnsError::File {
                path: path.clone(),
                op: "map",
                source: io(),
            },
            "scratch file /s/x: cannot map: entity not found",
        ),
        (
            ColumnsError::Limit {
                path: path.clone(),
                limit: 100,
                requested: 120,
            },
            "scratch directory /s/x: the scratch limit of 100 bytes would be exceeded (120 bytes requested)",
        ),
        (
            ColumnsError::Memory {
                bytes: 64,
                source: io(),
            },
            "out of memory: cannot map 64 bytes for a column: entity not found (a smaller \
             --mem-budget, e.g. --mem-budget 64M, keeps the builder's columns in scratch files)",
        ),
        (
            ColumnsError::OutOfMemory(crate::sys::OutOfMemory {
                what: "the tree",
                bytes: 3 << 19,
            }),
            "out of memory: the tree (1.5 MiB) does not fit (a smaller --mem-budget, \
             e.g. --mem-budget 64M, keeps the builder's columns in scratch files)",
        ),
    ];
    for (e, want) in cases {
        assert_eq!(e.to_string(), want);
    }
}
