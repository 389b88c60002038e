//! A facade for the whole flow a renderer needs: build a tree from a scene
//! or from its own vertex and index buffers, write it as a `.kd` file, map
//! it back, and trace single rays, 16-ray packets or batches, over the
//! wide boxes once they are built for secondary rays
//! ([`Accel::prepare_secondary`]).
//!
//! [`Accel`] is one type whether its tree is an in-memory `.kd` image or a
//! mapped file: both trace through the same file walk
//! ([`crate::trace::FileWalk`]), so a tree answers exactly the same hits
//! before and after a round trip through the disk.
//!
//! ```
//! use slimkd::accel::{Accel, BuildOptions};
//! use slimkd::geom::Ray;
//! use glam::Vec3;
//!
//! let vertices = [[0.0, 0.0, 5.0], [2.0, 0.0, 5.0], [0.0, 2.0, 5.0]];
//! let accel = Accel::from_buffers(&vertices, &[[0, 1, 2]], &BuildOptions::default()).unwrap();
//! let dir = std::env::temp_dir().join(format!("slimkd-accel-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! let path = dir.join("tri.kd");
//! accel.write(&path).unwrap();
//! let mapped = Accel::open(&path).unwrap();
//! let hit = mapped.intersect(&Ray::new(Vec3::new(0.5, 0.5, 0.0), Vec3::Z)).unwrap();
//! assert_eq!((hit.t, hit.prim), (5.0, 0));
//! assert_eq!((hit.u, hit.v), (0.25, 0.25));
//! std::fs::remove_dir_all(&dir).unwrap();
//! ```

use crate::build::{BuildConfig, BuildError};
use crate::format::{self, AlignedBytes, FormatError, KdFile, Mapped};
use crate::geom::{Aabb, Ray, RayPrecomp};
use crate::pipeline::{Pipeline, PipelineError};
use crate::scene::{InvalidColumns, TriangleColumns};
use crate::slim::{HoistRule, SlimParams};
use crate::trace::packet::{PacketTracer, SimdLevel};
use crate::trace::rays::{closest_batch, occluded_batch};
use crate::trace::wide::{WideBoxes, WideError, WideTracer};
use crate::trace::{ClosestHit, FileWalk, Hit, HitContext, OccluderCache, Scalar, Walk};
use glam::Vec3;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Which tree to build.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Preset {
    /// The standard SAH kd-tree.
    #[default]
    Std,
    /// Slimmed with [`SlimParams::FAST`] (few hoists, fast traversal).
    Fast,
    /// Slimmed with [`SlimParams::SMALL`] (more hoists, smaller tree).
    Small,
}

/// How [`Accel::build`] builds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuildOptions {
    /// The tree to build.
    pub preset: Preset,
    /// Renumber triangles in Morton order in the file (smaller leaves; hit
    /// ids stay the input's). Default `true`.
    pub reorder: bool,
    /// Worker threads for the build; `None` (or `Some(0)`) uses rayon's
    /// current pool.
    pub threads: Option<usize>,
    /// Bytes of anonymous memory the build may hold; above it the
    /// builder's columns go to scratch files in the system's temporary
    /// directory. `None` (the default): no budget.
    pub mem_budget: Option<u64>,
}

impl Default for BuildOptions {
    fn default() -> Self {
        BuildOptions {
            preset: Preset::Std,
            reorder: true,
            threads: None,
            mem_budget: None,
        }
    }
}

/// A ray hit, in the input's numbering.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HitRecord {
    /// Hit distance along the ray (in units of its direction's length).
    pub t: f32,
    /// Barycentric weight of the triangle's vertex 1: the hit point is
    /// `(1 - u - v)·v0 + u·v1 + v·v2`, as in Embree.
    pub u: f32,
    /// Barycentric weight of the triangle's vertex 2.
    pub v: f32,
    /// Geometric normal `(v1 - v0) × (v2 - v0)`, not normalised.
    pub ng: Vec3,
    /// The triangle hit: its index in the input (the scene's triangle
    /// order, or the index buffer's triple).
    pub prim: u32,
}

/// 16 rays in structure-of-arrays form; lane `i` is the ray
/// `org_*[i] + t·dir_*[i]`, `t` in `(tmin[i], tmax[i]]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayPacket {
    /// Origin x per lane.
    pub org_x: [f32; 16],
    /// Origin y per lane.
    pub org_y: [f32; 16],
    /// Origin z per lane.
    pub org_z: [f32; 16],
    /// Direction x per lane.
    pub dir_x: [f32; 16],
    /// Direction y per lane.
    pub dir_y: [f32; 16],
    /// Direction z per lane.
    pub dir_z: [f32; 16],
    /// Start of the ray interval per lane (exclusive).
    pub tmin: [f32; 16],
    /// End of the ray interval per lane (inclusive for hits).
    pub tmax: [f32; 16],
}

impl RayPacket {
    /// Lane `i` of the packet as a [`Ray`].
    pub fn ray(&self, i: usize) -> Ray {
        Ray {
            origin: Vec3::new(self.org_x[i], self.org_y[i], self.org_z[i]),
            dir: Vec3::new(self.dir_x[i], self.dir_y[i], self.dir_z[i]),
            tmin: self.tmin[i],
            tmax: self.tmax[i],
        }
    }

    /// A packet of up to 16 rays (lanes past `rays.len()` are rays along
    /// `+z` from the origin with the empty interval `(0, 0]`: in a mask,
    /// they find nothing).
    ///
    /// # Panics
    ///
    /// If `rays` holds more than 16 rays.
    pub fn from_rays(rays: &[Ray]) -> RayPacket {
        assert!(rays.len() <= 16, "a packet holds at most 16 rays");
        let mut p = RayPacket {
            org_x: [0.0; 16],
            org_y: [0.0; 16],
            org_z: [0.0; 16],
            dir_x: [0.0; 16],
            dir_y: [0.0; 16],
            dir_z: [0.0; 16],
            tmin: [0.0; 16],
            tmax: [0.0; 16],
        };
        p.dir_z = [1.0; 16];
        for (i, r) in rays.iter().enumerate() {
            p.org_x[i] = r.origin.x;
            p.org_y[i] = r.origin.y;
            p.org_z[i] = r.origin.z;
            p.dir_x[i] = r.dir.x;
            p.dir_y[i] = r.dir.y;
            p.dir_z[i] = r.dir.z;
            p.tmin[i] = r.tmin;
            p.tmax[i] = r.tmax;
        }
        p
    }
}

/// Why an [`Accel`] could not be built, written or opened.
#[derive(Debug, thiserror::Error)]
pub enum AccelError {
    /// The caller's buffers break the scene invariant (a non-finite
    /// vertex, an index out of range).
    #[error("invalid scene buffers: {0}")]
    Scene(#[source] InvalidColumns),
    /// The builder failed (its columns).
    #[error("kd-tree build failed: {0}")]
    Build(#[source] BuildError),
    /// The build's thread pool could not be made.
    #[error("cannot start the build threads: {0}")]
    Threads(#[source] rayon::ThreadPoolBuildError),
    /// The tree could not be stored, or a `.kd` file is not valid;
    /// `path` is the file, where there is one.
    #[error("{}", format_message(path.as_deref(), source))]
    Format {
        /// The file read or written (`None` for an in-memory image).
        path: Option<PathBuf>,
        /// What is wrong.
        source: FormatError,
    },
    /// The wide boxes ([`Accel::prepare_secondary`]) could not be built
    /// over the tree's nodes (a file not verified, whose nodes do not form
    /// a tree).
    #[error("{}: {source}", path.as_deref().map_or("kd image".into(), |p| p.display().to_string()))]
    Boxes {
        /// The mapped file (`None` for an in-memory image).
        path: Option<PathBuf>,
        /// What is wrong.
        source: WideError,
    },
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
}

/// [`AccelError::Format`]'s message: the file and what is wrong with it
/// (an I/O error's own message, without the path the format error
/// repeats), or the in-memory image's.
fn format_message(path: Option<&Path>, source: &FormatError) -> String {
    match (path, source) {
        (Some(p), FormatError::Io { source, .. }) => format!("{}: {source}", p.display()),
        (Some(p), source) => format!("{}: {source}", p.display()),
        (None, source) => format!("kd image: {source}"),
    }
}

impl AccelError {
    /// The file the error is about, if any.
    pub fn path(&self) -> Option<&Path> {
        match self {
            AccelError::Format { path, .. } | AccelError::Boxes { path, .. } => path.as_deref(),
            AccelError::Io { path, .. } => Some(path),
            _ => None,
        }
    }
}

/// The tree's `.kd` image: built in memory or mapped from a file.
enum Image {
    Memory(KdFile<AlignedBytes>),
    Mapped(KdFile<Mapped>),
}

/// Calls `$body` with `$f` bound to the image's `KdFile`, whichever kind.
macro_rules! with_file {
    ($img:expr, |$f:ident| $body:expr) => {
        match $img {
            Image::Memory($f) => $body,
            Image::Mapped($f) => $body,
        }
    };
}

/// A kd-tree with its geometry, ready to trace.
///
/// Tracing takes `&self` and `Accel` is `Sync`, so one `Accel` serves any
/// number of threads.
pub struct Accel {
    image: Image,
    /// Input triangle id → file triangle id (the inverse of the file's
    /// `tri_map`; empty when the file is not reordered), made on the first
    /// hit record or triangle that needs it rather than on open: a pass
    /// over the whole map, where opening is O(1).
    file_id: OnceLock<Vec<u32>>,
    /// The wide boxes over the tree's leaves, once
    /// [`Accel::prepare_secondary`] has built them.
    boxes: OnceLock<WideBoxes>,
    /// The mapped file (for errors).
    path: Option<PathBuf>,
}

// Checked here: the docs promise that threads share an `Accel` and its
// tracers, the wide boxes included.
const _: fn() = || {
    fn shared<T: Send + Sync>() {}
    shared::<Accel>();
    shared::<AccelTracer<'static>>();
};

impl fmt::Debug for Accel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Accel")
            .field("mapped", &self.is_mapped())
            .field("triangles", &self.len())
            .finish()
    }
}

impl Accel {
    /// Builds the tree of `scene` with the level builder, slims it for
    /// [`Preset::Fast`] and [`Preset::Small`] (byte hoist rule for the file
    /// as `options.reorder` writes it), and keeps its `.kd` image in
    /// memory. The header records the configuration built with.
    pub fn build(scene: &TriangleColumns, options: &BuildOptions) -> Result<Accel, AccelError> {
        match options.threads {
            Some(n) if n > 0 => rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(AccelError::Threads)?
                .install(|| Self::build_here(scene, options)),
            _ => Self::build_here(scene, options),
        }
    }

    fn build_here(scene: &TriangleColumns, options: &BuildOptions) -> Result<Accel, AccelError> {
        let rule = HoistRule::Bytes {
            reordered: options.reorder,
        };
        let (params, preset) = match options.preset {
            Preset::Std => (None, format::Preset::Std),
            Preset::Fast => (Some(SlimParams::FAST.with_rule(rule)), format::Preset::Fast),
            Preset::Small => (
                Some(SlimParams::SMALL.with_rule(rule)),
                format::Preset::Small,
            ),
        };
        let pipeline = Pipeline {
            mem_budget: options.mem_budget,
            reorder: options.reorder,
            ..Pipeline::new(BuildConfig::default()).slimmed(params, preset)
        };
        let file = pipeline.image(scene).map_err(|e| match e {
            PipelineError::Build(e) => AccelError::Build(e),
            PipelineError::Format(source) => AccelError::Format { path: None, source },
        })?;
        Ok(Accel::new(Image::Memory(file), None))
    }

    /// Builds from the caller's buffers: triangle `i` is
    /// `indices[i]` into `vertices`, and hits report `prim == i`.
    pub fn from_buffers(
        vertices: &[[f32; 3]],
        indices: &[[u32; 3]],
        options: &BuildOptions,
    ) -> Result<Accel, AccelError> {
        let positions = vertices.iter().map(|&v| Vec3::from_array(v)).collect();
        let scene = TriangleColumns::new(positions, indices.to_vec()).map_err(AccelError::Scene)?;
        Accel::build(&scene, options)
    }

    /// Maps a `.kd` file and checks its header and section table, in O(1)
    /// ([`format::Check::Header`]: a corrupt section gives wrong hits, never
    /// a panic; [`Accel::verify`] checks the rest). The file must not be
    /// modified in place
    /// while mapped (slimkd replaces files by rename, which is safe; see
    /// [`KdFile::open`]).
    pub fn open(path: impl AsRef<Path>) -> Result<Accel, AccelError> {
        let path = path.as_ref();
        let file =
            KdFile::open(path, format::Check::Header).map_err(|source| AccelError::Format {
                path: Some(path.to_path_buf()),
                source,
            })?;
        Ok(Accel::new(Image::Mapped(file), Some(path.to_path_buf())))
    }

    /// Writes the tree as a `.kd` file, atomically (a temporary file in the
    /// same directory, renamed into place).
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), AccelError> {
        let path = path.as_ref();
        let bytes = with_file!(&self.image, |f| f.as_bytes());
        crate::fsio::write_atomically(
            path,
            |source| AccelError::Io {
                path: path.to_path_buf(),
                source,
            },
            |file| {
                use std::io::Write;
                file.write_all(bytes).map_err(|source| AccelError::Io {
                    path: path.to_path_buf(),
                    source,
                })
            },
        )
    }

    /// Checks every node, index and vertex and every section's checksum
    /// ([`format::Check::Verify`]; reads the whole image).
    pub fn verify(&self) -> Result<(), AccelError> {
        let path = self.path.clone();
        with_file!(&self.image, |f| f.check(format::Check::Verify))
            .map_err(|source| AccelError::Format { path, source })
    }

    fn new(image: Image, path: Option<PathBuf>) -> Accel {
        Accel {
            image,
            file_id: OnceLock::new(),
            boxes: OnceLock::new(),
            path,
        }
    }

    /// [`Accel::file_id`]'s map, made on first use.
    fn file_id(&self) -> &[u32] {
        self.file_id.get_or_init(|| {
            with_file!(&self.image, |f| match f.tri_map() {
                Some(map) => {
                    let mut inv = vec![0u32; map.len()];
                    // A map that is not a permutation (a file not validated)
                    // leaves some entries 0: never an index out of range.
                    for (file, &input) in map.iter().enumerate() {
                        if let Some(slot) = inv.get_mut(input as usize) {
                            *slot = file as u32;
                        }
                    }
                    inv
                }
                None => Vec::new(),
            })
        })
    }

    /// Builds, once, the wide boxes that trace secondary rays fast: the
    /// tree's non-empty leaves under a hierarchy of eight tight boxes a
    /// node ([`WideBoxes`]), in memory beside the tree (66–146 bytes a
    /// triangle on the six shared scenes, where their std trees take
    /// 10–39; built in 42–811 ms for 35 K–1.1 M triangles on two threads,
    /// in the caller's rayon pool). From then on single rays
    /// ([`Accel::intersect`], [`Accel::occluded`] and the walks from a
    /// context), any-hit packets and batches, closest-hit packets whose
    /// rays start apart and closest-hit batches of incoherent rays go over
    /// the boxes; with AVX-512 a camera's packets and coherent batches stay
    /// the kd packets, where a camera's rays run up to 1.33× as fast
    /// (candela_city's primary rays), and with AVX2 they go over the boxes
    /// too ([`WideTracer::closest_packets`]). The answers are the same, bit
    /// for bit.
    ///
    /// Through an [`AccelTracer`], on the renderer's view-1 rays of four
    /// shared scenes in batches of 4,096 on two threads (the AVX-512 and
    /// AVX2 copies): any-hit batches run 1.05–2.5× as fast over the boxes
    /// (shadow rays 1.05–1.5×, AO rays 1.25–2.5×), AO closest-hit batches
    /// 1.13–2.0×, the camera's and shadow closest-hit batches with AVX-512
    /// as before (0.97–1.05×, on the kd packets). Single rays (`slimkd trace --mode
    /// single|wide`): 1.1–2.3× on every ray kind and query.
    ///
    /// Returns the boxes; later calls return them at once. Threads that
    /// race here each build, and one's boxes are kept.
    pub fn prepare_secondary(&self) -> Result<&WideBoxes, AccelError> {
        if let Some(b) = self.boxes.get() {
            return Ok(b);
        }
        let boxes =
            with_file!(&self.image, |f| WideBoxes::new(FileWalk::new(f))).map_err(|source| {
                AccelError::Boxes {
                    path: self.path.clone(),
                    source,
                }
            })?;
        Ok(self.boxes.get_or_init(|| boxes))
    }

    /// The wide boxes, if [`Accel::prepare_secondary`] has built them.
    pub fn secondary_boxes(&self) -> Option<&WideBoxes> {
        self.boxes.get()
    }

    /// Whether the tree is a mapped file (from [`Accel::open`]).
    pub fn is_mapped(&self) -> bool {
        matches!(self.image, Image::Mapped(_))
    }

    /// The number of triangles.
    pub fn len(&self) -> usize {
        with_file!(&self.image, |f| f.triangles().len())
    }

    /// Whether there are no triangles.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The box around every triangle (the root cell).
    pub fn bounds(&self) -> Aabb {
        with_file!(&self.image, |f| f.bounds())
    }

    /// The `.kd` bytes.
    pub fn as_bytes(&self) -> &[u8] {
        with_file!(&self.image, |f| f.as_bytes())
    }

    /// The vertices of input triangle `prim`.
    ///
    /// # Panics
    ///
    /// If `prim` is not below [`Accel::len`].
    pub fn triangle(&self, prim: u32) -> [Vec3; 3] {
        let file_id = self.file_id();
        let id = if file_id.is_empty() {
            prim
        } else {
            file_id[prim as usize]
        };
        with_file!(&self.image, |f| f.triangle(id))
    }

    /// The closest hit with `t` in `(ray.tmin, ray.tmax]`, if any (ties go
    /// to the smaller `prim`).
    ///
    /// # Panics
    ///
    /// If `ray` breaks the contract of [`Ray::check`] (every query of the
    /// facade does, for each ray it is given): a ray that starts behind
    /// its origin, say, would get a wrong answer, not an error.
    #[track_caller]
    pub fn intersect(&self, ray: &Ray) -> Option<HitRecord> {
        self.tracer().intersect(ray)
    }

    /// Whether anything is hit with `t` in `(ray.tmin, ray.tmax)`.
    #[track_caller]
    pub fn occluded(&self, ray: &Ray) -> bool {
        self.tracer().occluded(ray)
    }

    /// [`Accel::intersect`] for the lanes of `packet` whose bit is set in
    /// `mask` (traced as one packet); the other lanes are `None`.
    #[track_caller]
    pub fn intersect_packet(&self, packet: &RayPacket, mask: u16) -> [Option<HitRecord>; 16] {
        self.tracer().intersect_packet(packet, mask)
    }

    /// [`Accel::occluded`] for the lanes of `packet` whose bit is set in
    /// `mask`: bit `i` of the result is set iff lane `i` is in the mask and
    /// occluded.
    #[track_caller]
    pub fn occluded_packet(&self, packet: &RayPacket, mask: u16) -> u16 {
        self.tracer().occluded_packet(packet, mask)
    }

    /// A handle that traces many rays: the file's sections are taken once
    /// here rather than per call, as [`Accel::intersect`] and the other
    /// per-call methods do (about 5 % of a ray's time). It answers exactly
    /// what they answer; it is `Copy` and `Sync`, so threads can share one
    /// or make their own. A tracer made after [`Accel::prepare_secondary`]
    /// traces over the wide boxes.
    pub fn tracer(&self) -> AccelTracer<'_> {
        AccelTracer {
            walk: with_file!(&self.image, |f| FileWalk::new(f)),
            owner: self,
            level: SimdLevel::detect(),
            boxes: self.boxes.get(),
        }
    }
}

/// Tracing through an [`Accel`] with its file view taken once
/// ([`Accel::tracer`]).
#[derive(Clone, Copy)]
pub struct AccelTracer<'a> {
    /// The file's sections.
    walk: FileWalk<'a>,
    /// The accel, for its `file_id` map (made on the first hit record).
    owner: &'a Accel,
    /// The packets' instruction set, detected once.
    level: SimdLevel,
    /// The wide boxes, where [`Accel::prepare_secondary`] had built them
    /// when the tracer was made.
    boxes: Option<&'a WideBoxes>,
}

impl fmt::Debug for AccelTracer<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("AccelTracer")
            .field("level", &self.level)
            .finish_non_exhaustive()
    }
}

impl AccelTracer<'_> {
    /// Calls `f` with the tracer of every query: over the wide boxes where
    /// they are built (its closest-hit packets are the kd packets, but in
    /// the AVX2 copy: [`WideTracer::closest_packets`]), else the kd walks
    /// and packets.
    fn with<R>(&self, f: impl FnOnce(&dyn ClosestHit) -> R) -> R {
        match self.boxes {
            Some(b) => f(&WideTracer::with_level(&self.walk, b, self.level)),
            None => f(&PacketTracer::with_level(&self.walk, self.level)),
        }
    }

    /// [`AccelTracer::with`] for closest-hit packets: over the boxes'
    /// packets where they are built and `boxes_pay` (asked only then) says
    /// the rays run faster there.
    fn with_closest<R>(
        &self,
        boxes_pay: impl FnOnce() -> bool,
        f: impl FnOnce(&dyn ClosestHit) -> R,
    ) -> R {
        match self.boxes {
            Some(b) if boxes_pay() => {
                f(&WideTracer::with_level(&self.walk, b, self.level).closest_packets())
            }
            _ => self.with(f),
        }
    }

    /// [`Accel::intersect`].
    #[track_caller]
    pub fn intersect(&self, ray: &Ray) -> Option<HitRecord> {
        expect_valid(ray);
        let hit = self.with(|t| t.closest_hit(ray));
        self.record(ray, hit)
    }

    /// [`Accel::occluded`].
    #[track_caller]
    pub fn occluded(&self, ray: &Ray) -> bool {
        expect_valid(ray);
        self.with(|t| t.occluded(ray))
    }

    /// [`Accel::intersect`], and the [`HitContext`] of the hit point
    /// (`origin + t · dir`), from which the rays that leave it (shadow, AO,
    /// reflection) can start: [`AccelTracer::occluded_from`],
    /// [`AccelTracer::intersect_from`].
    #[track_caller]
    pub fn intersect_with_context(&self, ray: &Ray) -> Option<(HitRecord, HitContext)> {
        expect_valid(ray);
        let hit = self.with(|t| t.closest_hit(ray));
        let record = self.record(ray, hit)?;
        let mut ctx = HitContext::default();
        Scalar::new(&self.walk).locate_into(ray.origin + ray.dir * hit.t, &mut ctx);
        Some((record, ctx))
    }

    /// The [`HitContext`] of the cell holding `point`.
    pub fn locate(&self, point: Vec3) -> HitContext {
        let mut ctx = HitContext::default();
        Scalar::new(&self.walk).locate_into(point, &mut ctx);
        ctx
    }

    /// [`AccelTracer::intersect`] walked from `ctx`: the same record for
    /// any ray, less work for one that starts near the context's point (a
    /// context of another accel walks from the root). Over the wide boxes
    /// where they are built, which need no context: there AO rays run
    /// 1.5–2.6× as fast as from their hit's context (`slimkd trace --mode
    /// from-hit|wide`, three shared scenes, closest and any hit).
    #[track_caller]
    pub fn intersect_from(&self, ctx: &HitContext, ray: &Ray) -> Option<HitRecord> {
        if self.boxes.is_some() {
            return self.intersect(ray);
        }
        expect_valid(ray);
        let hit = Scalar::new(&self.walk).closest_hit_from(ctx, ray);
        self.record(ray, hit)
    }

    /// [`AccelTracer::occluded`] walked from `ctx`: the same answer for any
    /// ray (over the wide boxes where they are built, as
    /// [`AccelTracer::intersect_from`]).
    #[track_caller]
    pub fn occluded_from(&self, ctx: &HitContext, ray: &Ray) -> bool {
        if self.boxes.is_some() {
            return self.occluded(ray);
        }
        expect_valid(ray);
        Scalar::new(&self.walk).occluded_from(ctx, ray)
    }

    /// [`Accel::intersect_packet`]. Where the wide boxes are built, a
    /// packet whose rays start at different points (AO, bounce or shadow
    /// rays from a tile's hits) goes over them; a packet from one point (a
    /// camera's) stays the kd packets with AVX-512, which the boxes do not
    /// beat there, and goes over the boxes with AVX2.
    #[track_caller]
    pub fn intersect_packet(&self, packet: &RayPacket, mask: u16) -> [Option<HitRecord>; 16] {
        let (rays, lanes, n) = gather(packet, mask);
        let mut hits = [Hit::MISS; 16];
        self.with_closest(
            || !one_origin(&rays[..n]),
            |t| t.closest_hit_n(&rays[..n], &mut hits[..n]),
        );
        let mut out = [None; 16];
        for i in 0..n {
            out[lanes[i]] = self.record(&rays[i], hits[i]);
        }
        out
    }

    /// [`Accel::occluded_packet`].
    #[track_caller]
    pub fn occluded_packet(&self, packet: &RayPacket, mask: u16) -> u16 {
        self.occluded_lanes(packet, mask, |t, rays, occ| t.occluded_n(rays, occ))
    }

    /// [`Accel::occluded_packet`] that tests the triangles of `cache`
    /// first and leaves this packet's occluders in it for the next call:
    /// the same answers, less work for consecutive packets blocked by the
    /// same triangles, as a renderer's shadow rays toward one light are
    /// ([`OccluderCache`]; keep one cache per thread and kind of ray).
    #[track_caller]
    pub fn occluded_packet_cached(
        &self,
        packet: &RayPacket,
        mask: u16,
        cache: &mut OccluderCache,
    ) -> u16 {
        self.occluded_lanes(packet, mask, |t, rays, occ| {
            t.occluded_n_cached(rays, occ, cache)
        })
    }

    /// [`AccelTracer::intersect`] for each of a batch of rays (hundreds
    /// to thousands, any directions), into `out`: traced in packets of 16
    /// rays of one octant and longest axis (one vertex permutation of the
    /// triangle test), in the batch's order within such a group (so a
    /// batch whose neighbouring rays start close together, as neighbouring
    /// pixels' do, makes coherent packets), or of one direction cell where
    /// the batch's origins lie close together against its rays' length (a
    /// tile's AO rays; [`crate::trace::rays::order_for_packets`]); a batch
    /// whose packets mostly keep one octant already (shadow rays toward
    /// one light) is traced in its own order
    /// ([`crate::trace::rays::mixed_octants`]). Where the wide boxes are
    /// built ([`Accel::prepare_secondary`]), a batch of incoherent rays
    /// (directions spread over a hemisphere, as a tile's AO or bounce rays
    /// are) goes over them in packets; the others (a camera's rays, shadow
    /// rays toward one light) stay the kd packets. The same records as
    /// ray by ray.
    ///
    /// # Panics
    /// If `out` and `rays` differ in length, or a ray breaks
    /// [`Ray::check`].
    #[track_caller]
    pub fn intersect_batch(&self, rays: &[Ray], out: &mut [Option<HitRecord>]) {
        assert_eq!(rays.len(), out.len(), "one record per ray");
        rays.iter().for_each(expect_valid);
        let mut hits = vec![Hit::MISS; rays.len()];
        self.with_closest(
            || incoherent(rays),
            |t| closest_batch(t, rays, &mut hits, &mut Vec::new()),
        );
        for ((o, r), h) in out.iter_mut().zip(rays).zip(hits) {
            *o = self.record(r, h);
        }
    }

    /// [`AccelTracer::occluded`] for each of a batch of rays into `out`,
    /// traced as [`AccelTracer::intersect_batch`] traces, through `cache`
    /// ([`AccelTracer::occluded_packet_cached`]). A renderer's AO rays, 4 a
    /// pixel in pixel order, trace 1.06–1.13× as fast as in packets of
    /// consecutive rays, and faster still when the pixels come in tiles.
    ///
    /// # Panics
    /// If `out` and `rays` differ in length, or a ray breaks
    /// [`Ray::check`].
    #[track_caller]
    pub fn occluded_batch(&self, rays: &[Ray], out: &mut [bool], cache: &mut OccluderCache) {
        assert_eq!(rays.len(), out.len(), "one answer per ray");
        rays.iter().for_each(expect_valid);
        self.with(|t| occluded_batch(t, rays, out, cache, &mut Vec::new()));
    }

    /// The lanes of `mask` that `trace` finds occluded, traced as one
    /// packet of the active lanes.
    #[track_caller]
    fn occluded_lanes(
        &self,
        packet: &RayPacket,
        mask: u16,
        trace: impl FnOnce(&dyn ClosestHit, &[Ray], &mut [bool]),
    ) -> u16 {
        let (rays, lanes, n) = gather(packet, mask);
        let mut occ = [false; 16];
        self.with(|t| trace(t, &rays[..n], &mut occ[..n]));
        (0..n).filter(|&i| occ[i]).fold(0, |m, i| m | 1 << lanes[i])
    }

    fn record(&self, ray: &Ray, hit: Hit) -> Option<HitRecord> {
        hit.is_hit().then(|| {
            let prim = hit.tri.0;
            let file_id = self.owner.file_id();
            let id = if file_id.is_empty() {
                prim
            } else {
                file_id[prim as usize]
            };
            record(ray, hit, self.walk.triangle(id))
        })
    }
}

/// The record of a traversal's hit on `tri` (its vertices): barycentrics
/// and normal.
fn record(ray: &Ray, hit: Hit, tri: [Vec3; 3]) -> HitRecord {
    let (u, v) = barycentrics(ray, &tri);
    HitRecord {
        t: hit.t,
        u,
        v,
        ng: (tri[1] - tri[0]).cross(tri[2] - tri[0]),
        prim: hit.tri.0,
    }
}

/// Whether a batch's directions spread too far for the kd packets to
/// keep their lanes together: the mean of its unit directions is shorter
/// than [`COHERENT`] (a camera's rays or shadow rays toward one light
/// come close to 1; cosine-distributed AO rays over a flat patch to 2/3).
/// Read from at most 256 rays spread over the batch: every ray's square
/// root and division cost a camera's rays 10–20 % of their time.
fn incoherent(rays: &[Ray]) -> bool {
    let step = (rays.len() / 256).max(1);
    let (sum, n) = rays
        .iter()
        .step_by(step)
        .map(|r| r.dir.normalize_or_zero())
        .fold((Vec3::ZERO, 0usize), |(a, n), d| (a + d, n + 1));
    sum.length() < COHERENT * n as f32
}

/// [`incoherent`]'s bound.
const COHERENT: f32 = 0.9;

/// Whether the rays start at one point (a pinhole camera's packet), the
/// closest-hit packets the wide boxes do not beat the kd-tree on with
/// AVX-512 (0.91–1.04× in `trace`'s packets). A renderer's packets from a tile's hits,
/// which a spread of directions cannot tell from a camera's where they
/// share a direction cell, run over the boxes through
/// [`AccelTracer::intersect_packet`] 1.13–1.56× as fast as the kd
/// packets with AVX-512 and 1.45–2.04× with AVX2 (AO rays; shadow rays
/// toward one light 0.97–1.17× and 1.11–1.39×).
fn one_origin(rays: &[Ray]) -> bool {
    rays.iter().all(|r| r.origin == rays[0].origin)
}

/// Panics where `ray` breaks [`Ray::check`]'s contract, naming the ray.
#[track_caller]
fn expect_valid(ray: &Ray) {
    if let Err(why) = ray.check() {
        panic!("invalid ray {ray:?}: {why}");
    }
}

/// The masked lanes of a packet, packed: the rays, their lane numbers and
/// how many.
///
/// # Panics
///
/// If a lane of `mask` breaks [`Ray::check`].
#[track_caller]
fn gather(packet: &RayPacket, mask: u16) -> ([Ray; 16], [usize; 16], usize) {
    let mut rays = [Ray::new(Vec3::ZERO, Vec3::Z); 16];
    let mut lanes = [0usize; 16];
    let mut n = 0;
    for lane in 0..16 {
        if mask & (1 << lane) != 0 {
            rays[n] = packet.ray(lane);
            expect_valid(&rays[n]);
            lanes[n] = lane;
            n += 1;
        }
    }
    (rays, lanes, n)
}

/// The barycentric weights `(u, v)` of vertices 1 and 2 at the ray's hit
/// point, computed with the watertight test's own operations
/// ([`crate::geom::intersect_triangle`]): the sheared, permuted vertices
/// relative to the origin, the edge functions `e0` (opposite vertex 0),
/// `e1`, `e2` (redone in `f64` when one is zero, as the test does), and
/// `u = e1 / det`, `v = e2 / det` with `det = e0 + e1 + e2`. So `u`, `v`
/// are exactly the weights the test's `t` was computed with.
pub fn barycentrics(ray: &Ray, tri: &[Vec3; 3]) -> (f32, f32) {
    let [e0, e1, e2] = crate::geom::edge_functions(&RayPrecomp::new(ray), tri);
    let det = e0 + e1 + e2;
    (e1 / det, e2 / det)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera's rays are coherent, rays over a hemisphere are not, so
    /// only the second batch goes over the boxes as closest hits.
    #[test]
    fn incoherent_batches_are_those_spread_over_a_hemisphere() {
        let camera: Vec<Ray> = (0..4096)
            .map(|i| {
                let (x, y) = ((i % 64) as f32 / 64.0 - 0.5, (i / 64) as f32 / 64.0 - 0.5);
                Ray::new(Vec3::ZERO, Vec3::new(x, y, -1.0))
            })
            .collect();
        assert!(!incoherent(&camera));
        let hemisphere: Vec<Ray> = (0..4096)
            .map(|i| {
                let (a, z) = (i as f32 * 2.399_963, (i % 97) as f32 / 97.0);
                let r = (1.0 - z * z).sqrt();
                Ray::new(Vec3::ZERO, Vec3::new(r * a.cos(), r * a.sin(), z))
            })
            .collect();
        assert!(incoherent(&hemisphere));
        assert!(!incoherent(&[]));
    }

    /// A camera's packet starts at one point; a packet of rays from a
    /// tile's hits does not, whatever its directions.
    #[test]
    fn camera_packets_start_at_one_point() {
        let eye = Vec3::new(1.0, 2.0, 3.0);
        let camera: Vec<Ray> = (0..16)
            .map(|i| Ray::new(eye, Vec3::new(i as f32 * 0.01, 0.0, -1.0)))
            .collect();
        assert!(one_origin(&camera) && one_origin(&camera[..1]) && one_origin(&[]));
        let mut hits = camera.clone();
        hits[15].origin.x += f32::EPSILON;
        assert!(!one_origin(&hits));
        hits[15].origin = Vec3::NAN;
        assert!(!one_origin(&hits));
    }

    /// The boxes a tracer takes are those of its own walk, so its walks
    /// over them do not fall back to the root walk; they are built once.
    #[test]
    fn a_tracer_walks_the_accels_own_boxes() {
        let vertices = [
            [0.0, 0.0, 5.0],
            [2.0, 0.0, 5.0],
            [0.0, 2.0, 5.0],
            [0.0, 0.0, 7.0],
            [3.0, 0.0, 7.0],
            [0.0, 3.0, 7.0],
        ];
        let accel =
            Accel::from_buffers(&vertices, &[[0, 1, 2], [3, 4, 5]], &BuildOptions::default())
                .unwrap();
        assert!(accel.tracer().boxes.is_none() && accel.secondary_boxes().is_none());
        let boxes = accel.prepare_secondary().unwrap() as *const WideBoxes;
        assert_eq!(accel.prepare_secondary().unwrap() as *const _, boxes);
        let tracer = accel.tracer();
        let b = tracer.boxes.expect("the tracer takes the boxes");
        assert!(b.is_of(tracer.walk));
        let hit = accel.intersect(&Ray::new(Vec3::new(0.5, 0.5, 0.0), Vec3::Z));
        assert_eq!(hit.map(|h| (h.t, h.prim)), Some((5.0, 0)));
    }
}
