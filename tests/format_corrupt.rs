//! Corrupt `.kd` files are rejected without panics, with specific errors:
//! every single-bit flip, truncation, overwrites, random byte strings and
//! targeted edits. A corrupt header or section table is refused on open
//! (`KdFile::from_bytes`, O(1)); a file corrupt in its sections opens, and
//! traces without panic or hang (its hits may be wrong), and is refused by
//! the full check (`KdFile::validate`) or by `verify` (the checksums).

mod common;

use common::kd::*;
use glam::Vec3;
use slimkd::format::node::{self, LEAF16_LIMIT, NodeWord};
use slimkd::format::{FormatError, HEADER_SIZE, KdFile, NodeFault, Section, aligned_copy};
use slimkd::geom::{Aabb, Ray};
use slimkd::trace::packet::{PacketTracer, SimdLevel};
use slimkd::trace::{self, ClosestHit, Hit};
use std::panic::{AssertUnwindSafe, catch_unwind};

// ---------------------------------------------------------------------
// Corrupt files.
// ---------------------------------------------------------------------

/// What reading a byte string gave.
#[derive(Debug)]
enum Outcome {
    /// `from_bytes` refused it.
    Rejected(FormatError),
    /// `from_bytes` accepted it and `validate` refused it.
    Invalid(FormatError),
    /// `from_bytes` and `validate` accepted it and `verify` refused it.
    BadChecksum(FormatError),
    /// All three accepted it.
    Accepted,
}

/// Whether `e` is an error of the sections' contents, which only the full
/// check finds (every other error is the header's or the section table's,
/// which the open must find).
fn is_contents_error(e: &FormatError) -> bool {
    match e {
        FormatError::Node { .. } | FormatError::Index { .. } => true,
        FormatError::Header(m) => m.to_string().contains("do not match the nodes"),
        _ => false,
    }
}

/// Rays and packets traced over every file `from_bytes` accepts.
struct Probes {
    rays: Vec<Ray>,
    packets: Vec<[Ray; 16]>,
    levels: Vec<SimdLevel>,
}

impl Probes {
    fn around(bounds: &Aabb, seed: u64) -> Probes {
        let mut rng = Rng(seed);
        Probes {
            rays: rays_at(bounds, &mut rng, 16),
            packets: packets_at(bounds, &mut rng, 1),
            levels: SimdLevel::available(),
        }
    }
}

/// Reads `bytes` as a file; when `from_bytes` accepts it, traces every
/// probe over it with every traverser (before the full check, as a reader
/// that opened it would), then runs `validate` and `verify`. `Err` says
/// what panicked.
fn probe(bytes: &[u8], probes: &Probes) -> Result<Outcome, String> {
    let data = aligned_copy(bytes);
    let file = match catch_unwind(AssertUnwindSafe(|| KdFile::from_bytes(data))) {
        Ok(Ok(file)) => file,
        Ok(Err(e)) => return Ok(Outcome::Rejected(e)),
        Err(_) => return Err("from_bytes panicked".into()),
    };
    catch_unwind(AssertUnwindSafe(|| {
        for ray in &probes.rays {
            std::hint::black_box(trace::traverse(&file, ray));
        }
        for rays in &probes.packets {
            for &level in &probes.levels {
                let mut out = [Hit::MISS; 16];
                PacketTracer::with_level(&file, level).closest_hit_4x4(rays, &mut out);
                std::hint::black_box(out);
            }
        }
        std::hint::black_box(file.leaf_depth_histogram());
        std::hint::black_box(file.figures().tree_bytes());
    }))
    .map_err(|_| "traversal panicked")?;
    let valid =
        catch_unwind(AssertUnwindSafe(|| file.validate())).map_err(|_| "validate panicked")?;
    if let Err(e) = valid {
        return Ok(Outcome::Invalid(e));
    }
    let verified =
        catch_unwind(AssertUnwindSafe(|| file.verify())).map_err(|_| "verify panicked")?;
    Ok(match verified {
        Ok(()) => Outcome::Accepted,
        Err(e) => Outcome::BadChecksum(e),
    })
}

/// Runs cases and collects failures, so that one run reports many.
struct Suite {
    probes: Probes,
    cases: usize,
    accepted: usize,
    failures: Vec<String>,
}

impl Suite {
    fn new(probes: Probes) -> Suite {
        Suite {
            probes,
            cases: 0,
            accepted: 0,
            failures: Vec::new(),
        }
    }

    /// Probes one case; `check` judges the outcome (`Err` = failure).
    fn case(
        &mut self,
        what: &dyn Fn() -> String,
        bytes: &[u8],
        check: impl FnOnce(&Outcome) -> Result<(), String>,
    ) {
        self.cases += 1;
        match probe(bytes, &self.probes) {
            Ok(outcome) => {
                if matches!(outcome, Outcome::Accepted) {
                    self.accepted += 1;
                }
                if let Err(msg) = check(&outcome) {
                    self.fail(format!("{}: {msg} (got {outcome:?})", what()));
                }
            }
            Err(msg) => self.fail(format!("{}: {msg}", what())),
        }
    }

    fn fail(&mut self, msg: String) {
        if self.failures.len() < 20 {
            self.failures.push(msg);
        } else if self.failures.len() == 20 {
            self.failures.push("...".into());
        }
    }

    fn finish(self, name: &str, min_cases: usize) -> usize {
        assert!(
            self.failures.is_empty(),
            "{name}: {} failures in {} cases:\n{}",
            self.failures.len(),
            self.cases,
            self.failures.join("\n")
        );
        assert!(self.cases >= min_cases, "{name}: only {} cases", self.cases);
        eprintln!(
            "{name}: {} cases, {} accepted by from_bytes and verify",
            self.cases, self.accepted
        );
        self.cases
    }
}

fn no_check(_: &Outcome) -> Result<(), String> {
    Ok(())
}

fn must_fail(o: &Outcome) -> Result<(), String> {
    match o {
        Outcome::Accepted => Err("accepted".into()),
        _ => Ok(()),
    }
}

/// A valid file to corrupt, with what it was made from.
struct Base {
    name: &'static str,
    bytes: Vec<u8>,
    bounds: Aabb,
}

/// Small valid files: plain, reordered, with type II nodes (reordered), and
/// one with a 4-byte leaf (2048 ids, repeating triangles).
fn small_bases() -> Vec<Base> {
    let mut rng = Rng(11);
    let scene = random_small_scene(&mut rng, 24, 6);
    let tree = std_tree(&scene);
    // Dense enough for leaves of several triangles (2-byte leaves; a leaf
    // of one triangle has no index entry).
    let scene2 = random_small_scene(&mut rng, 80, 4);
    let (tree2, hoisted) = hoist(&std_tree(&scene2), &scene2, 12, true);
    assert!(hoisted >= 3, "{hoisted} type II nodes");
    let scene3 = strip_scene(6);
    let mut big_leaf: Vec<u32> = (0..LEAF16_LIMIT).map(|i| i % 3).collect();
    big_leaf.sort_unstable();
    let tree3 = strip_tree(&scene3, &[big_leaf, vec![3, 4], vec![5]], false);
    let bases = vec![
        Base {
            name: "grid",
            bytes: write(&tree, &scene, false),
            bounds: tree.bounds,
        },
        Base {
            name: "grid-reordered",
            bytes: write(&tree, &scene, true),
            bounds: tree.bounds,
        },
        Base {
            name: "type2-reordered",
            bytes: write(&tree2, &scene2, true),
            bounds: tree2.bounds,
        },
        Base {
            name: "idx32",
            bytes: write(&tree3, &scene3, false),
            bounds: tree3.bounds,
        },
    ];
    for b in &bases {
        read(&b.bytes);
    }
    let f = read(&bases[2].bytes).figures();
    assert!(f.t_inner >= 3 && f.idx16 > 0, "{f:?}");
    assert!(read(&bases[3].bytes).figures().idx32 >= u64::from(LEAF16_LIMIT));
    bases
}

/// The bunny, reordered, with type II nodes: a bigger file, sampled.
fn bunny_base() -> Base {
    let scene = load_scene("bunny_npm.obj");
    let (tree, _) = hoist(&std_tree(&scene), &scene, 21, true);
    Base {
        name: "bunny-type2-reordered",
        bytes: write(&tree, &scene, true),
        bounds: tree.bounds,
    }
}

/// Which part of a valid file a byte lies in.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Region {
    Magic,
    Version,
    Endianness,
    /// Covered by the header checksum (the checksum itself included).
    Header,
    /// Header bytes 340..384: the counts of empty leaves without a word and
    /// of one-triangle leaves (outside the checksum, checked against the
    /// nodes), then reserved zero bytes.
    Reserved,
    Section(Section),
    /// Zero padding after a section.
    Padding(Section),
}

fn region(b: &[u8], pos: usize) -> Region {
    match pos {
        0..8 => Region::Magic,
        8..12 => Region::Version,
        12..16 => Region::Endianness,
        16..340 => Region::Header,
        340..HEADER_SIZE => Region::Reserved,
        _ => {
            let s = Section::ALL
                .into_iter()
                .rev()
                .find(|&s| section(b, s).start <= pos)
                .unwrap();
            if section(b, s).contains(&pos) {
                Region::Section(s)
            } else {
                Region::Padding(s)
            }
        }
    }
}

/// The error a single corrupted byte at `pos` of a valid file must give.
fn check_single_flip(b: &[u8], pos: usize, o: &Outcome) -> Result<(), String> {
    let ok = match (region(b, pos), o) {
        (Region::Magic, Outcome::Rejected(FormatError::BadMagic)) => true,
        (Region::Version, Outcome::Rejected(FormatError::Version { expected: 2, .. })) => true,
        (Region::Endianness, Outcome::Rejected(FormatError::Endianness)) => true,
        (Region::Header, Outcome::Rejected(FormatError::HeaderChecksum { .. })) => true,
        (Region::Reserved, Outcome::Rejected(FormatError::Header(_))) => true,
        // The count of one-triangle leaves: only the nodes can show it
        // wrong.
        (Region::Reserved, Outcome::Invalid(e @ FormatError::Header(_))) => is_contents_error(e),
        (Region::Padding(s), Outcome::Rejected(FormatError::Section { section, .. })) => {
            *section == s.name()
        }
        (Region::Section(_), Outcome::Invalid(e)) => is_contents_error(e),
        (
            Region::Section(s),
            Outcome::BadChecksum(FormatError::ChecksumMismatch { section, .. }),
        ) => *section == s.name(),
        _ => false,
    };
    if ok {
        Ok(())
    } else {
        Err(format!("wrong outcome for {:?}", region(b, pos)))
    }
}

/// Runs `cases` on every small base and the bunny, each with a suite of
/// its own (probes seeded with `probe_seed`, at least `min_cases` cases),
/// all drawing from one generator seeded with `seed`; asserts at least
/// `min_total` cases in all.
fn on_every_base(
    seed: u64,
    probe_seed: u64,
    min_cases: usize,
    min_total: usize,
    mut cases: impl FnMut(&Base, &mut Suite, &mut Rng),
) {
    let mut bases = small_bases();
    bases.push(bunny_base());
    let mut rng = Rng(seed);
    let mut total = 0;
    for base in &bases {
        let mut suite = Suite::new(Probes::around(&base.bounds, probe_seed));
        cases(base, &mut suite, &mut rng);
        total += suite.finish(base.name, min_cases);
    }
    assert!(total >= min_total, "{total} cases");
}

/// (a) Every single-bit flip of the small files (exhaustively) and a sample
/// of the bunny's is caught by `from_bytes` or `verify`, with the error of
/// the region it lies in; random multi-bit flips are caught too.
#[test]
fn corrupt_bit_flips() {
    on_every_base(100, 1, 1000, 20_000, |base, suite, rng| {
        let orig = &base.bytes;
        let bits = orig.len() * 8;
        // The idx32 base and the bunny are sampled; the others exhaustive.
        let exhaustive = bits <= 40_000;
        let singles: Vec<usize> = if exhaustive {
            (0..bits).collect()
        } else {
            (0..3000).map(|_| rng.below(bits)).collect()
        };
        let mut b = orig.clone();
        for bit in singles {
            b[bit / 8] ^= 1 << (bit % 8);
            suite.case(
                &|| format!("{}: flip bit {bit} (byte {})", base.name, bit / 8),
                &b,
                |o| check_single_flip(orig, bit / 8, o),
            );
            b[bit / 8] ^= 1 << (bit % 8);
        }
        for _ in 0..1500 {
            let k = 2 + rng.below(15);
            let mut flipped = Vec::new();
            while flipped.len() < k {
                let bit = rng.below(bits);
                if !flipped.contains(&bit) {
                    flipped.push(bit);
                }
            }
            for &bit in &flipped {
                b[bit / 8] ^= 1 << (bit % 8);
            }
            suite.case(
                &|| format!("{}: flip bits {flipped:?}", base.name),
                &b,
                must_fail,
            );
            for &bit in &flipped {
                b[bit / 8] ^= 1 << (bit % 8);
            }
        }
    });
}

/// (b) Truncation to every length of the small files and to a sample of
/// the bunny's is reported as `Truncated`.
#[test]
fn corrupt_truncations() {
    on_every_base(200, 2, 300, 5_000, |base, suite, rng| {
        let len = base.bytes.len();
        let lengths: Vec<usize> = if len <= 16_384 {
            (0..len).collect()
        } else {
            let mut v: Vec<usize> = (0..400).map(|_| rng.below(len)).collect();
            v.extend([0, 1, HEADER_SIZE - 1, HEADER_SIZE, HEADER_SIZE + 1, len - 1]);
            v
        };
        for cut in lengths {
            suite.case(
                &|| format!("{}: truncated to {cut} of {len}", base.name),
                &base.bytes[..cut],
                |o| match o {
                    Outcome::Rejected(FormatError::Truncated { needed, got })
                        if *got == cut as u64 && *needed > *got =>
                    {
                        Ok(())
                    }
                    _ => Err("not reported as truncated".into()),
                },
            );
        }
        // Longer than the layout: trailing bytes are refused too.
        for extra in [1, 7, 64, 200] {
            let mut b = base.bytes.clone();
            b.resize(len + extra, 0);
            suite.case(
                &|| format!("{}: {extra} trailing zero bytes", base.name),
                &b,
                |o| match o {
                    Outcome::Rejected(FormatError::Header(_)) => Ok(()),
                    _ => Err("trailing bytes not refused".into()),
                },
            );
        }
    });
}

/// (c) Random byte overwrites anywhere are caught; overwrites of node words
/// and vertices with plausible values and all checksums repaired open,
/// never make reading or traversal panic, and are judged by the full check (these reach traversal of
/// odd but valid trees: moved splits, other leaf ranges, extreme
/// coordinates).
#[test]
fn corrupt_overwrites() {
    on_every_base(300, 3, 1500, 5_000, |base, suite, rng| {
        let orig = &base.bytes;
        let len = orig.len();
        for _ in 0..600 {
            let mut b = orig.clone();
            for _ in 0..1 + rng.below(8) {
                let at = rng.below(len);
                b[at] = rng.next() as u8;
            }
            let changed = b != *orig;
            suite.case(&|| format!("{}: random overwrite", base.name), &b, |o| {
                if changed { must_fail(o) } else { Ok(()) }
            });
        }
        let n_words = section(orig, Section::Nodes).len() / 8;
        let n_idx32 = section(orig, Section::Idx32).len() / 4;
        let n_idx16 = section(orig, Section::Idx16).len() / 2;
        let n_tris = section(orig, Section::Triangles).len() / 12;
        let verts = section(orig, Section::Vertices);
        for _ in 0..600 {
            let mut b = orig.clone();
            for _ in 0..1 + rng.below(3) {
                if rng.chance(3) {
                    // A vertex coordinate: anything finite, extremes
                    // included.
                    let at = verts.start + 4 * rng.below(verts.len() / 4);
                    let v = match rng.below(4) {
                        0 => f32::MAX * (rng.unit() - 0.5),
                        1 => f32::MIN_POSITIVE * rng.unit(),
                        2 => (rng.unit() - 0.5) * 1e6,
                        _ => f32::from_bits(rng.next() as u32),
                    };
                    set_u32(&mut b, at, v.to_bits());
                } else {
                    let i = rng.below(n_words);
                    let w = plausible_word(rng, i, n_words, n_idx32, n_idx16, n_tris);
                    set_word(&mut b, i, w);
                }
            }
            fix_all_crcs(&mut b);
            suite.case(
                &|| format!("{}: plausible edit, checksums repaired", base.name),
                &b,
                |o| match o {
                    Outcome::BadChecksum(_) => Err("checksums were repaired".into()),
                    // Only the sections changed: the open reads none of
                    // them, so it opens (and traced), and the full check
                    // judges it.
                    Outcome::Rejected(_) => Err("refused on open".into()),
                    Outcome::Invalid(e) if !is_contents_error(e) => {
                        Err("not an error of the contents".into())
                    }
                    _ => Ok(()),
                },
            );
        }
        // Header fields set to small or nearby values, header checksum
        // repaired.
        // (offset, 8 bytes wide): the counts, the section table, and the
        // 4-byte fields that the reader checks.
        let fields: Vec<(usize, bool)> = [
            H_WORDS,
            H_INNER,
            H_T_INNER,
            H_LEAVES,
            H_IDX32,
            H_IDX16,
            H_TRIANGLES,
            H_VERTICES,
        ]
        .into_iter()
        .chain((0..6).flat_map(|s| [H_TABLE + s * H_ENTRY, H_TABLE + s * H_ENTRY + 8]))
        .map(|f| (f, true))
        .chain(
            [H_MAX_DEPTH, H_FLAGS, H_PRESET]
                .into_iter()
                .chain((0..6).map(|k| H_BOUNDS + 4 * k))
                .map(|f| (f, false)),
        )
        .collect();
        for _ in 0..600 {
            let mut b = orig.clone();
            for _ in 0..1 + rng.below(3) {
                let (at, wide) = fields[rng.below(fields.len())];
                if wide {
                    let old = get_u64(&b, at);
                    let v = match rng.below(4) {
                        0 => old.wrapping_add(rng.below(130) as u64).wrapping_sub(65),
                        1 => rng.below(64) as u64,
                        2 => rng.next(),
                        _ => old ^ (1 << rng.below(64)),
                    };
                    set_u64(&mut b, at, v);
                } else {
                    let old = get_u32(&b, at);
                    let v = match rng.below(3) {
                        0 => old.wrapping_add(rng.below(5) as u32).wrapping_sub(2),
                        1 => (rng.unit() * 20.0 - 10.0).to_bits(),
                        _ => rng.next() as u32,
                    };
                    set_u32(&mut b, at, v);
                }
            }
            fix_header_crc(&mut b);
            suite.case(
                &|| format!("{}: header fields, checksum repaired", base.name),
                &b,
                no_check,
            );
        }
    });
}

/// A node word likely to pass some of the reader's checks: a leaf with a
/// range inside the index arrays, an inner node with its right child at a
/// later slot or empty, a one-triangle leaf, a T-reference, or random bits.
fn plausible_word(
    rng: &mut Rng,
    i: usize,
    n_words: usize,
    n_idx32: usize,
    n_idx16: usize,
    n_tris: usize,
) -> u64 {
    let tri = rng.below(n_tris.max(1) + 2) as u32;
    match rng.below(6) {
        0 => {
            let start = rng.below(n_idx16 + 2);
            let count = rng.below((n_idx16 + 2).saturating_sub(start) + 1);
            node::encode_leaf16(count as u32, rng.below(2) as u16, start as u32)
        }
        1 => {
            let start = rng.below(n_idx32 + 2);
            let count = rng.below((n_idx32 + 2).saturating_sub(start) + 1);
            node::encode_leaf32(count as u32, start as u32)
        }
        2 => {
            // The right child at a later slot, or empty (0).
            let right = if rng.chance(4) {
                0
            } else {
                i + 1 + rng.below(n_words.saturating_sub(i) + 2)
            };
            let pos = (rng.unit() - 0.25) * 12.0;
            node::encode_inner(rng.below(3) as u8, rng.chance(3), right as u32, pos)
        }
        3 if rng.chance(2) => node::encode_leaf1(tri),
        3 => node::encode_tref(tri),
        4 => {
            // Keep the word's type and move its split or range a little.
            (rng.next() & 0xFFFF_FFFF_0000_0000) | (rng.below(256) as u64 & !0b111) | 0b011
        }
        _ => rng.next(),
    }
}

/// (d) Random byte strings: raw, and with a valid magic, version, byte
/// order and header checksum (so that they reach the later checks).
#[test]
fn corrupt_random_strings() {
    let mut rng = Rng(400);
    let mut suite = Suite::new(Probes::around(&Aabb::new(Vec3::ZERO, Vec3::splat(4.0)), 4));
    for _ in 0..1500 {
        let len = rng.below(3000);
        let b: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        suite.case(&|| format!("random {len} bytes"), &b, must_fail);
    }
    let template = &small_bases()[0].bytes;
    for _ in 0..1500 {
        let len = HEADER_SIZE + 64 * rng.below(40);
        let mut b: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        b[..16].copy_from_slice(&template[..16]);
        set_u32(&mut b, H_HEADER_SIZE, HEADER_SIZE as u32);
        if rng.chance(2) {
            // Plausible small counts.
            for f in [
                H_INNER,
                H_T_INNER,
                H_IDX32,
                H_IDX16,
                H_TRIANGLES,
                H_VERTICES,
            ] {
                set_u64(&mut b, f, rng.below(8) as u64);
            }
            let leaves = get_u64(&b, H_INNER) + get_u64(&b, H_T_INNER) + 1;
            set_u64(&mut b, H_LEAVES, leaves);
            let words = get_u64(&b, H_LEAVES) * 2 - 1 + get_u64(&b, H_T_INNER);
            set_u64(&mut b, H_WORDS, words);
        }
        fix_header_crc(&mut b);
        suite.case(&|| format!("forged header, {len} bytes"), &b, no_check);
    }
    suite.finish("random strings", 3000);
}

/// The error a targeted edit must give.
#[derive(Clone, Copy)]
enum Want {
    /// One this function accepts.
    Is(fn(&FormatError) -> bool),
    /// `Truncated` with these lengths.
    Truncated { needed: u64, got: u64 },
    /// `Version`, expecting 2, with this version.
    Version(u32),
    /// `Section` naming this section.
    InSection(&'static str),
    /// `Index` naming this section.
    InIndex(&'static str),
}

use Want::*;

impl Want {
    fn accepts(self, e: &FormatError) -> bool {
        match (self, e) {
            (Is(check), e) => check(e),
            (Truncated { needed, got }, FormatError::Truncated { needed: n, got: g }) => {
                (needed, got) == (*n, *g)
            }
            (Version(v), FormatError::Version { expected: 2, got }) => *got == v,
            (InSection(name), FormatError::Section { section, .. })
            | (InIndex(name), FormatError::Index { section, .. }) => *section == name,
            _ => false,
        }
    }
}

/// (e) Targeted edits, each with the specific error it must give. Header
/// edits repair the header checksum so that they reach the later checks;
/// node and section edits repair nothing, so the open (header and table)
/// or the full check (contents) must refuse them structurally (or, for
/// pure data edits, `verify` by checksum).
#[test]
fn corrupt_targeted_edits() {
    let bases = small_bases();
    let mut suite = Suite::new(Probes::around(&bases[0].bounds, 5));
    for base in &bases {
        let orig = &base.bytes;
        let file = read(orig);
        let f = file.figures();
        let words: Vec<u64> = file.nodes().to_vec();
        let n = words.len();
        let decoded: Vec<NodeWord> = words.iter().map(|&w| node::decode(w).unwrap()).collect();
        // Inner nodes with their first child slot and slot field, leaves
        // with an index list, one-triangle leaves, T-references.
        let inners: Vec<(usize, usize, usize)> = decoded
            .iter()
            .enumerate()
            .filter_map(|(i, w)| match *w {
                NodeWord::Inner { t_ref, right, .. } => {
                    Some((i, i + 1 + usize::from(t_ref), right as usize))
                }
                _ => None,
            })
            .collect();
        let ones: Vec<usize> = (0..n)
            .filter(|&i| matches!(decoded[i], NodeWord::Leaf1 { .. }))
            .collect();
        let leaves: Vec<usize> = (0..n)
            .filter(|&i| {
                matches!(
                    decoded[i],
                    NodeWord::Leaf16 { .. } | NodeWord::Leaf32 { .. }
                )
            })
            .collect();
        let trefs: Vec<usize> = (0..n)
            .filter(|&i| matches!(decoded[i], NodeWord::TRef { .. }))
            .collect();
        assert!(!inners.is_empty() && !leaves.is_empty());

        let mut cases: Vec<(String, Vec<u8>, Want)> = Vec::new();
        let mut add = |what: &str, edit: &dyn Fn(&mut Vec<u8>), want: Want| {
            let mut b = orig.clone();
            edit(&mut b);
            cases.push((what.to_string(), b, want));
        };
        let header = |at: usize, v: u64, wide: bool| {
            move |b: &mut Vec<u8>| {
                if wide {
                    set_u64(b, at, v);
                } else {
                    set_u32(b, at, v as u32);
                }
                fix_header_crc(b);
            }
        };
        let header_err = Is(|e| matches!(e, FormatError::Header(_)));
        let node_err = Is(|e| matches!(e, FormatError::Node { .. }));
        let any_section = Is(|e| matches!(e, FormatError::Section { .. }));

        // The first checks.
        add(
            "bad magic",
            &|b| b[3] = b'X',
            Is(|e| matches!(e, FormatError::BadMagic)),
        );
        add(
            "empty",
            &|b| b.clear(),
            Truncated {
                needed: 384,
                got: 0,
            },
        );
        add(
            "100 bytes",
            &|b| b.truncate(100),
            Truncated {
                needed: 384,
                got: 100,
            },
        );
        add(
            "one byte short",
            &|b| {
                b.pop();
            },
            Is(|e| matches!(e, FormatError::Truncated { .. })),
        );
        add(
            "header checksum off by one",
            &|b| {
                let c = get_u32(b, H_CRC);
                set_u32(b, H_CRC, c.wrapping_add(1));
            },
            Is(|e| matches!(e, FormatError::HeaderChecksum { .. })),
        );
        add(
            "count edited, checksum not repaired",
            &|b| {
                set_u64(b, H_LEAVES, f.leaves + 1);
            },
            Is(|e| matches!(e, FormatError::HeaderChecksum { .. })),
        );
        // One header field set (`wide`: 8 bytes), the checksum repaired.
        let flags = get_u32(orig, H_FLAGS);
        let fields: [(&str, usize, u64, bool, Want); 26] = [
            ("version 1", H_VERSION, 1, false, Version(1)),
            ("version 3", H_VERSION, 3, false, Version(3)),
            ("version 0", H_VERSION, 0, false, Version(0)),
            (
                "other byte order",
                H_ENDIAN,
                0x0D0C_0B0A,
                false,
                Is(|e| matches!(e, FormatError::Endianness)),
            ),
            // Header fields out of range.
            ("header size 512", H_HEADER_SIZE, 512, false, header_err),
            ("unknown flag", H_FLAGS, 2, false, header_err),
            ("unknown preset", H_PRESET, 9, false, header_err),
            (
                "NaN bound",
                H_BOUNDS,
                f32::NAN.to_bits().into(),
                false,
                header_err,
            ),
            (
                "infinite bound",
                H_BOUNDS + 20,
                f32::INFINITY.to_bits().into(),
                false,
                header_err,
            ),
            (
                "inverted bounds",
                H_BOUNDS,
                1e30f32.to_bits().into(),
                false,
                header_err,
            ),
            ("depth over MAX_DEPTH", H_MAX_DEPTH, 101, false, header_err),
            ("zero node words", H_WORDS, 0, true, header_err),
            ("node words + 1", H_WORDS, f.words + 1, true, header_err),
            ("leaves + 1", H_LEAVES, f.leaves + 1, true, header_err),
            ("inner + 1", H_INNER, f.inner + 1, true, header_err),
            // The counts after the header checksum.
            (
                "implicit empty leaves + 1",
                H_IMPLICIT_EMPTY,
                f.implicit_empty + 1,
                true,
                header_err,
            ),
            (
                "implicit empty leaves - 1",
                H_IMPLICIT_EMPTY,
                f.implicit_empty.wrapping_sub(1),
                true,
                header_err,
            ),
            (
                "one-triangle leaves + 1",
                H_ONE_LEAVES,
                f.one_leaves + 1,
                true,
                header_err,
            ),
            (
                "one-triangle leaves - 1",
                H_ONE_LEAVES,
                f.one_leaves.wrapping_sub(1),
                true,
                header_err,
            ),
            (
                "every empty leaf counted as wordless",
                H_IMPLICIT_EMPTY,
                f.leaves - 1,
                true,
                header_err,
            ),
            (
                "triangles + 1",
                H_TRIANGLES,
                f.triangles + 1,
                true,
                InSection("triangles"),
            ),
            ("idx16 + 1", H_IDX16, f.idx16 + 1, true, InSection("idx16")),
            (
                "vertices count - 1",
                H_VERTICES,
                f.vertices - 1,
                true,
                InSection("vertices"),
            ),
            ("2^40 triangles", H_TRIANGLES, 1 << 40, true, header_err),
            (
                "reordered flag toggled",
                H_FLAGS,
                u64::from(flags ^ 1),
                false,
                InSection("tri_map"),
            ),
            (
                "header depth below the tree's",
                H_MAX_DEPTH,
                0,
                false,
                node_err,
            ),
        ];
        for (what, at, v, wide, want) in fields {
            add(what, &header(at, v, wide), want);
        }
        add(
            "counts add up but not to the section",
            &|b| {
                set_u64(b, H_INNER, f.inner + 1);
                set_u64(b, H_LEAVES, f.leaves + 1);
                set_u64(b, H_WORDS, f.words + 2);
                fix_header_crc(b);
            },
            InSection("nodes"),
        );
        add(
            "counts add up with one more wordless empty leaf than the nodes have",
            &|b| {
                // One more inner node and leaf, two more wordless empty
                // leaves: the same number of words.
                set_u64(b, H_INNER, f.inner + 1);
                set_u64(b, H_LEAVES, f.leaves + 1);
                set_u64(b, H_IMPLICIT_EMPTY, f.implicit_empty + 2);
                fix_header_crc(b);
            },
            Is(
                |e| matches!(e, FormatError::Header(m) if m.to_string().contains("do not match the nodes")),
            ),
        );
        add(
            "a type I node counted as type II",
            &|b| {
                // Inner − 1 and t-inner + 1 keep leaves = inner + t-inner + 1
                // but add a T-reference word, which the node section lacks.
                set_u64(b, H_INNER, f.inner.wrapping_sub(1));
                set_u64(b, H_T_INNER, f.t_inner + 1);
                set_u64(b, H_WORDS, f.words + 1);
                fix_header_crc(b);
            },
            InSection("nodes"),
        );
        // The section table: an entry's offset, or its length, set.
        for s in Section::ALL {
            let e = H_TABLE + s as usize * H_ENTRY;
            let ofs = get_u64(orig, e);
            let name = s.name();
            let mut entries = vec![
                ("offset + 64", e, ofs + 64),
                ("offset misaligned", e, ofs + 4),
                ("offset into the header", e, 320),
            ];
            // The start of the last non-empty section before this one.
            if let Some(prev) = Section::ALL[..s as usize]
                .iter()
                .map(|&p| section(orig, p))
                .rfind(|r| !r.is_empty())
            {
                entries.push(("overlaps the previous section", e, prev.start as u64));
            }
            entries.push(("offset near 2^64", e, u64::MAX - 63));
            entries.push(("length + 8", e + 8, get_u64(orig, e + 8) + 8));
            for (what, at, v) in entries {
                add(&format!("{name} {what}"), &header(at, v, true), any_section);
            }
        }
        add("non-zero reserved header byte", &|b| b[380] = 1, header_err);
        add("trailing byte", &|b| b.push(0), header_err);
        if let Some(s) = Section::ALL
            .into_iter()
            .find(|&s| !section(orig, s).len().is_multiple_of(64))
        {
            let at = section(orig, s).end;
            add("non-zero padding", &|b| b[at] = 0x80, InSection(s.name()));
        }

        // Node words (nothing repaired).
        let with_right = |i: usize, right: usize| {
            let (axis, t_ref, pos) = match decoded[i] {
                NodeWord::Inner {
                    axis, t_ref, pos, ..
                } => (axis, t_ref, pos),
                _ => unreachable!(),
            };
            node::encode_inner(axis, t_ref, right as u32, pos)
        };
        // Inner nodes with both children in words (the slot field after
        // the first child slot).
        let both: Vec<(usize, usize, usize)> = inners
            .iter()
            .copied()
            .filter(|&(_, first, r)| r > first)
            .collect();
        assert!(!both.is_empty());
        let (p, p_first, p_right) = both[0];
        let last = both[both.len() - 1];
        // (what, inner node, its new slot field)
        let mut slots = vec![
            ("right slot past the end", p, n),
            ("right slot at the last word", p, n - 1),
            ("right slot at 2^29 - 1", p, (1 << 29) - 1),
            ("right slot skips a word", p, p_right + 1),
            (
                "right slot one early (into the left subtree)",
                p,
                p_right - 1,
            ),
            (
                "right slot at the first child slot (the left child said empty)",
                p,
                p_first,
            ),
            // The right subtree's words are then referenced by nothing.
            ("right child said empty", p, 0),
        ];
        if last.0 > 0 {
            slots.push(("right slot backwards", last.0, last.0 - 1));
            slots.push(("right slot at itself", last.0, last.0));
        }
        // A second parent for a subtree: a right slot at a node inside
        // the left subtree (a DAG).
        if let Some(&(q, q_first, _)) = both
            .iter()
            .find(|&&(_, first, _)| matches!(decoded[first], NodeWord::Inner { .. }))
        {
            slots.push((
                "right slot at the left child's left child (a shared subtree)",
                q,
                match decoded[q_first] {
                    NodeWord::Inner { t_ref, .. } => q_first + 1 + usize::from(t_ref),
                    _ => unreachable!(),
                },
            ));
        }
        if inners.len() >= 2 {
            let (i, ..) = inners[1];
            slots.push(("two parents for one right subtree", i, p_right));
        }
        if let Some(&(q, ..)) = both.iter().find(|&&(i, first, _)| first == i + 2) {
            slots.push(("right slot at the node's own T-reference", q, q + 1));
        }
        for (what, i, right) in slots {
            add(what, &|b| set_word(b, i, with_right(i, right)), node_err);
        }
        // Words after the tree, with the counts adding up (one more inner
        // node and leaf) or not.
        add(
            "two words after the tree, counts adding up",
            &|b| {
                *b = with_words_appended(b, &[words[0], node::encode_leaf1(0)]);
                set_u64(b, H_INNER, f.inner + 1);
                set_u64(b, H_LEAVES, f.leaves + 1);
                fix_header_crc(b);
            },
            Is(|e| {
                matches!(
                    e,
                    FormatError::Node {
                        fault: NodeFault::Unreferenced,
                        ..
                    }
                )
            }),
        );
        add(
            "a word after the tree",
            &|b| *b = with_words_appended(b, &[node::encode_leaf1(0)]),
            header_err,
        );
        // Empty leaves with a word: only the left child of a node whose
        // right child is empty (R = 0) may be one, at start 0.
        for &(i, first, right) in &inners {
            let left_leaf = !matches!(decoded[first], NodeWord::Inner { .. });
            let right_leaf = right > first && !matches!(decoded[right], NodeWord::Inner { .. });
            if right > first && left_leaf {
                add(
                    "an empty left leaf word where the parent says both children have words",
                    &|b| set_word(b, first, node::encode_leaf32(0, 0)),
                    node_err,
                );
            }
            if right_leaf {
                add(
                    "an empty right leaf word",
                    &|b| set_word(b, right, node::encode_leaf32(0, 0)),
                    node_err,
                );
            }
            if right == first && left_leaf {
                add(
                    "an empty leaf word at the first child slot of a node whose left child is empty",
                    &|b| set_word(b, first, node::encode_leaf32(0, 0)),
                    node_err,
                );
            }
            if right == 0 && left_leaf {
                // (Start 1 lies past an empty idx32: refused as such;
                // `an_empty_leaf_word_must_start_at_0` has one inside.)
                add(
                    "the left child of a node with an empty right child: empty leaf word at start 1",
                    &|b| set_word(b, first, node::encode_leaf32(0, 1)),
                    node_err,
                );
                add(
                    "the left child of a node with an empty right child: empty 2-byte leaf word",
                    &|b| set_word(b, first, node::encode_leaf16(0, 0, 0)),
                    node_err,
                );
            }
            if i == 0 && right == 0 && !left_leaf {
                add(
                    "the root's right child said empty, its left child an empty leaf word",
                    &|b| set_word(b, first, node::encode_leaf32(0, 0)),
                    node_err,
                );
            }
        }
        // One-triangle leaves.
        for &l in &ones {
            let NodeWord::Leaf1 { tri } = decoded[l] else {
                unreachable!()
            };
            add(
                "one-triangle leaf of a triangle out of range",
                &|b| set_word(b, l, node::encode_leaf1(f.triangles as u32)),
                node_err,
            );
            add(
                "one-triangle leaf of triangle 2^32 - 1",
                &|b| set_word(b, l, node::encode_leaf1(u32::MAX)),
                node_err,
            );
            for bit in [5, 16, 31] {
                add(
                    &format!("one-triangle leaf with unused bit {bit} set"),
                    &|b| set_word(b, l, node::encode_leaf1(tri) | (1 << bit)),
                    node_err,
                );
            }
            // Inside the index arrays where they have an entry, so that
            // the count is what is refused.
            add(
                "one triangle in a 4-byte leaf",
                &|b| set_word(b, l, node::encode_leaf32(1, 0)),
                if f.idx32 > 0 {
                    Is(|e| {
                        matches!(
                            e,
                            FormatError::Node {
                                fault: NodeFault::OneTriangleLeafWithIndex,
                                ..
                            }
                        )
                    })
                } else {
                    node_err
                },
            );
            add(
                "one triangle in a 2-byte leaf",
                &|b| set_word(b, l, node::encode_leaf16(1, 0, 0)),
                if f.idx16 > 0 {
                    Is(|e| {
                        matches!(
                            e,
                            FormatError::Node {
                                fault: NodeFault::Leaf16Count(1),
                                ..
                            }
                        )
                    })
                } else {
                    node_err
                },
            );
        }
        let leaf = leaves[0];
        let (i, ..) = inners[0];
        let split = |pos: f32| (u64::from(pos.to_bits()) << 32) | (words[0] & 0xFFFF_FFFF);
        // (what, node, its new word)
        let mut node_words = vec![
            (
                "a T-reference where a child belongs",
                leaf,
                node::encode_tref(0),
            ),
            ("the root is a T-reference", 0, node::encode_tref(0)),
        ];
        assert_eq!(trefs.len() as u64, f.t_inner);
        for &t in &trefs {
            node_words.push((
                "T-reference replaced by a leaf",
                t,
                node::encode_leaf16(0, 0, 0),
            ));
            node_words.push((
                "T-reference to a triangle out of range",
                t,
                node::encode_tref(f.triangles as u32),
            ));
            node_words.push(("T-reference with unused bits", t, words[t] | 0x100));
        }
        node_words.push(("NaN split", 0, split(f32::NAN)));
        node_words.push(("infinite split", 0, split(f32::NEG_INFINITY)));
        for (what, at, word) in node_words {
            add(what, &|b| set_word(b, at, word), node_err);
        }
        add(
            "type I and II swapped",
            &|b| set_word(b, i, words[i] ^ node::A_TYPE2),
            Is(|e| matches!(e, FormatError::Node { .. } | FormatError::Header(_))),
        );
        for mode in [0b10u64, 0b11] {
            add(
                &format!("leaf mode E = {mode:02b}"),
                &|b| set_word(b, leaf, (words[leaf] & !0b11000) | (mode << 3)),
                node_err,
            );
        }
        for &l in &leaves {
            match decoded[l] {
                NodeWord::Leaf32 { count, start } if count > 0 => {
                    let past = f.idx32 as u32 - start + 1;
                    add(
                        "4-byte leaf range past idx32",
                        &|b| set_word(b, l, node::encode_leaf32(past.max(count + 1), start)),
                        node_err,
                    );
                    add(
                        "4-byte leaf starting past idx32",
                        &|b| set_word(b, l, node::encode_leaf32(2, f.idx32 as u32)),
                        node_err,
                    );
                    add(
                        "4-byte leaf start near 2^32",
                        &|b| set_word(b, l, node::encode_leaf32(count.max(2), u32::MAX)),
                        node_err,
                    );
                    add(
                        "index of idx32 out of range",
                        &|b| {
                            let at = section(b, Section::Idx32).start + 4 * start as usize;
                            set_u32(b, at, f.triangles as u32);
                        },
                        InIndex("idx32"),
                    );
                }
                NodeWord::Leaf16 {
                    count,
                    upper,
                    start,
                } if count > 0 => {
                    add(
                        "2-byte leaf range past idx16",
                        &|b| {
                            set_word(
                                b,
                                l,
                                node::encode_leaf16(count, upper, f.idx16 as u32 - count + 1),
                            )
                        },
                        node_err,
                    );
                    add(
                        "2-byte leaf with upper bits out of range",
                        &|b| set_word(b, l, node::encode_leaf16(count, upper + 1, start)),
                        node_err,
                    );
                    add(
                        "index of idx16 out of range",
                        &|b| {
                            let at = section(b, Section::Idx16).start + 2 * start as usize;
                            b[at..at + 2].copy_from_slice(&[0xFF, 0xFF]);
                        },
                        node_err,
                    );
                }
                _ => {}
            }
        }
        // Geometry: one 4-byte word of a section set.
        let mut geometry = vec![
            (
                "vertex index out of range",
                Section::Triangles,
                4,
                f.vertices as u32,
            ),
            ("NaN vertex", Section::Vertices, 8, f32::NAN.to_bits()),
            (
                "infinite vertex",
                Section::Vertices,
                0,
                f32::INFINITY.to_bits(),
            ),
        ];
        if file.is_reordered() {
            let first = get_u32(orig, section(orig, Section::TriMap).start);
            geometry.push(("tri_map repeats an id", Section::TriMap, 4, first));
            geometry.push((
                "tri_map id out of range",
                Section::TriMap,
                0,
                f.triangles as u32,
            ));
        }
        for (what, s, offset, v) in geometry {
            add(
                what,
                &|b| {
                    let at = section(b, s).start + offset;
                    set_u32(b, at, v);
                },
                InIndex(s.name()),
            );
        }

        // Pure data edits: structurally valid, caught by the checksums.
        let mut data_edits: Vec<(String, Vec<u8>, &'static str)> = Vec::new();
        let mut b = orig.clone();
        let at = section(&b, Section::Vertices).start;
        let v = f32::from_bits(get_u32(&b, at));
        set_u32(&mut b, at, (v + 1.0).to_bits());
        data_edits.push(("vertex moved".into(), b, "vertices"));
        let mut b = orig.clone();
        let (i, ..) = inners[0];
        let pos = match decoded[i] {
            NodeWord::Inner { pos, .. } => pos,
            _ => unreachable!(),
        };
        set_word(
            &mut b,
            i,
            (u64::from((pos + 0.5).to_bits()) << 32) | (words[i] & 0xFFFF_FFFF),
        );
        data_edits.push(("split moved".into(), b, "nodes"));
        let mut b = orig.clone();
        let at = section(&b, Section::Triangles).start;
        let (v0, v1) = (get_u32(&b, at), get_u32(&b, at + 4));
        set_u32(&mut b, at, v1);
        set_u32(&mut b, at + 4, v0);
        if v0 != v1 {
            data_edits.push(("triangle's vertices swapped".into(), b, "triangles"));
        }

        for (what, bytes, check) in cases {
            suite.case(&|| format!("{}: {what}", base.name), &bytes, |o| match o {
                Outcome::Rejected(e) if check.accepts(e) => Ok(()),
                Outcome::Invalid(e) if check.accepts(e) && is_contents_error(e) => Ok(()),
                _ => Err("not the expected error".into()),
            });
        }
        for (what, bytes, name) in data_edits {
            suite.case(&|| format!("{}: {what}", base.name), &bytes, |o| match o {
                Outcome::BadChecksum(FormatError::ChecksumMismatch { section, .. })
                    if *section == name =>
                {
                    Ok(())
                }
                _ => Err("not caught by the section checksum".into()),
            });
        }
    }
    // An unaligned buffer.
    let mut words = vec![0u64; bases[0].bytes.len() / 8 + 1];
    let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut words);
    bytes[1..=bases[0].bytes.len()].copy_from_slice(&bases[0].bytes);
    let unaligned = &bytes[1..=bases[0].bytes.len()];
    assert!(matches!(
        KdFile::from_bytes(unaligned),
        Err(FormatError::Misaligned)
    ));
    suite.finish("targeted edits", 200);
}

/// The one empty leaf with a word (the left child of a node whose two
/// children are empty) must read `Leaf32 { count: 0, start: 0 }`: a start
/// inside idx32 other than 0 is refused as such, so the encoding stays
/// canonical.
#[test]
fn an_empty_leaf_word_must_start_at_0() {
    use slimkd::tree::{Node, NodeId, TreeIr, TriId};
    let scene = strip_scene(6);
    // A 4-byte leaf, as in `small_bases` (its ids repeat).
    let mut big: Vec<TriId> = (0..LEAF16_LIMIT).map(|i| TriId(3 + i % 3)).collect();
    big.sort_unstable();
    let empty = Node::Leaf { start: 0, count: 0 };
    let tree = TreeIr {
        bounds: scene.bounds(),
        nodes: vec![
            Node::Inner {
                axis: 0,
                pos: 2.75,
                right: NodeId(4),
                t_ref: None,
            },
            // Triangle 1 spans x 1..1.5, across the split.
            Node::Inner {
                axis: 0,
                pos: 1.25,
                right: NodeId(3),
                t_ref: Some(TriId(1)),
            },
            empty,
            empty,
            Node::Leaf {
                start: 0,
                count: LEAF16_LIMIT,
            },
        ],
        leaf_tris: big,
    };
    let bytes = write(&tree, &scene, false);
    let file = read(&bytes);
    assert!(file.figures().idx32 >= 2);
    // The root, the type II node and its T-reference, its left child.
    assert_eq!(
        node::decode(file.nodes()[3]),
        Ok(NodeWord::Leaf32 { count: 0, start: 0 })
    );
    for start in [1, 2] {
        let mut b = bytes.clone();
        set_word(&mut b, 3, node::encode_leaf32(0, start));
        fix_all_crcs(&mut b);
        match KdFile::from_bytes_checked(aligned_copy(&b)) {
            Err(FormatError::Node { index: 3, fault }) => {
                assert_eq!(fault, NodeFault::EmptyLeafWithWord, "{fault}")
            }
            Err(e) => panic!("start {start}: wrong error {e}"),
            Ok(_) => panic!("start {start}: accepted"),
        }
    }
}
