//! Camera, views files, tiled parallel rendering and image output.
//!
//! Consumes anything that answers closest-hit queries ([`ClosestHit`]) and
//! the scene (for shading normals); produces a [`Frame`] (colour + depth)
//! and the per-frame figures other ray tracers can be compared on: the
//! number of hits and the checksum of hit distances.
//!
//! **Camera convention (exact).** All camera arithmetic is `f64`, evaluated
//! in the order written, and rounded to `f32` only at the end:
//! `f = normalize(at − eye)`, `r = normalize(cross(f, up))`,
//! `u = cross(r, f)`, `t = tan(fov·π/180/2)`; for pixel `(x, y)`,
//! `sx = ((x+0.5)/W·2 − 1)·t·W/H`, `sy = (1 − (y+0.5)/H·2)·t`,
//! `d = normalize(f + sx·r + sy·u)`; origin `eye`, `tmin = 0`,
//! `tmax = +∞`; `normalize` divides each component by
//! `sqrt(x·x + y·y + z·z)`. `y = 0` is the top row.

pub mod ao;
mod image_out;

pub use ao::{
    AoFrame, AoOptions, AoTimes, FrameRays, Secondary, frame_rays, shade_ao, trace_ao_frame,
};
pub use image_out::{Frame, ImageError, write_depth_f32, write_exr, write_image, write_png};

use crate::format::KdFile;
use crate::geom::{Aabb, Ray};
use crate::progress::Progress;
use crate::scene::TriangleColumns;
use crate::trace::rays::job_len;
use crate::trace::{ClosestHit, Hit};
use glam::{DVec3, Vec3};
use rayon::prelude::*;
use std::path::Path;
use std::time::Instant;

/// A pinhole camera (see the module docs for the convention).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// The centre of projection.
    pub eye: DVec3,
    /// A point the camera looks at (the image centre).
    pub at: DVec3,
    /// The image's up direction (need not be orthogonal to the view).
    pub up: DVec3,
    /// The vertical field of view, in degrees.
    pub fov_deg: f64,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

fn normalize(v: DVec3) -> DVec3 {
    let len = (v.x * v.x + v.y * v.y + v.z * v.z).sqrt();
    DVec3::new(v.x / len, v.y / len, v.z / len)
}

fn cross(a: DVec3, b: DVec3) -> DVec3 {
    DVec3::new(
        a.y * b.z - a.z * b.y,
        a.z * b.x - a.x * b.z,
        a.x * b.y - a.y * b.x,
    )
}

impl Camera {
    /// The default view of a scene box: `at` = its centre `C`, `eye = C +
    /// normalize(0.6, 0.4, 1.0)·1.2·D` with `D` its diagonal, up = +y, 60°.
    pub fn default_for(bounds: &Aabb, width: u32, height: u32) -> Camera {
        let lo = bounds.min.as_dvec3();
        let hi = bounds.max.as_dvec3();
        let c = DVec3::new(
            (lo.x + hi.x) / 2.0,
            (lo.y + hi.y) / 2.0,
            (lo.z + hi.z) / 2.0,
        );
        let e = hi - lo;
        let d = (e.x * e.x + e.y * e.y + e.z * e.z).sqrt();
        let n = normalize(DVec3::new(0.6, 0.4, 1.0));
        Camera {
            eye: c + n * 1.2 * d,
            at: c,
            up: DVec3::new(0.0, 1.0, 0.0),
            fov_deg: 60.0,
            width,
            height,
        }
    }

    /// A view from a views file, at the given size.
    pub fn from_view(view: &View, width: u32, height: u32) -> Camera {
        Camera {
            eye: view.eye,
            at: view.at,
            up: view.up,
            fov_deg: view.fov_deg,
            width,
            height,
        }
    }

    /// Whether the camera defines rays: finite vectors, `eye ≠ at`, an
    /// `up` that is not parallel to the view direction, `0 < fov < 180`
    /// and a non-empty image. The error says which fails. Without this a
    /// degenerate camera gives NaN directions, and every ray misses.
    ///
    /// `up` counts as parallel when the sine of its angle to the view
    /// direction is below `1e-9`: the right vector would then be mostly
    /// rounding error, so the image would depend on the last bits of the
    /// inputs (decided here; pbrt's `LookAt` likewise refuses a parallel
    /// `up`).
    pub fn check(&self) -> Result<(), CameraError> {
        let finite = |v: DVec3| v.x.is_finite() && v.y.is_finite() && v.z.is_finite();
        if !(finite(self.eye) && finite(self.at) && finite(self.up)) {
            return Err(CameraError::NotFinite);
        }
        if !(self.fov_deg > 0.0 && self.fov_deg < 180.0) {
            return Err(CameraError::BadFov { fov: self.fov_deg });
        }
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::EmptyImage {
                width: self.width,
                height: self.height,
            });
        }
        let d = self.at - self.eye;
        if d.length() == 0.0 {
            return Err(CameraError::SamePoint);
        }
        let up_len = self.up.length();
        if cross(normalize(d), self.up).length() <= 1e-9 * up_len {
            return Err(CameraError::UpParallel {
                up: self.up,
                dir: d,
            });
        }
        Ok(())
    }

    /// The primary ray through the centre of pixel `(x, y)`.
    pub fn ray(&self, x: u32, y: u32) -> Ray {
        self.lens().ray(x, y)
    }

    /// The camera's frame, for many rays: [`Lens::ray`] is [`Camera::ray`]
    /// without its normalisations and tangent (made for every pixel, they
    /// took 7 % of a 1024² AO render's time).
    pub fn lens(&self) -> Lens {
        let f = normalize(self.at - self.eye);
        let r = normalize(cross(f, self.up));
        Lens {
            eye: self.eye.as_vec3(),
            f,
            r,
            u: cross(r, f),
            t: (self.fov_deg * std::f64::consts::PI / 180.0 / 2.0).tan(),
            w: f64::from(self.width),
            h: f64::from(self.height),
        }
    }
}

/// A camera's eye, unit view, right and up vectors, the tangent of half
/// its field of view and its image size ([`Camera::lens`]).
#[derive(Clone, Copy, Debug)]
pub struct Lens {
    eye: Vec3,
    f: DVec3,
    r: DVec3,
    u: DVec3,
    t: f64,
    w: f64,
    h: f64,
}

impl Lens {
    /// The primary ray through the centre of pixel `(x, y)`, bit for bit
    /// [`Camera::ray`]'s.
    pub fn ray(&self, x: u32, y: u32) -> Ray {
        let (t, w, h) = (self.t, self.w, self.h);
        let sx = ((f64::from(x) + 0.5) / w * 2.0 - 1.0) * t * w / h;
        let sy = (1.0 - (f64::from(y) + 0.5) / h * 2.0) * t;
        let d = normalize(self.f + sx * self.r + sy * self.u);
        Ray::new(self.eye, d.as_vec3())
    }
}

/// Why [`Camera::check`] refused a camera.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// `eye`, `at` or `up` has a NaN or infinite coordinate.
    #[error("the camera's eye, at and up must be finite")]
    NotFinite,
    /// The field of view is not in `(0, 180)` degrees.
    #[error("fov {fov} is not in (0, 180)")]
    BadFov {
        /// The field of view given.
        fov: f64,
    },
    /// The image has no pixel.
    #[error("image size {width}x{height} is empty")]
    EmptyImage {
        /// The width given.
        width: u32,
        /// The height given.
        height: u32,
    },
    /// `eye == at`: there is no view direction.
    #[error("eye and at are the same point: no view direction")]
    SamePoint,
    /// `up` is zero or parallel to `dir = at - eye`.
    #[error(
        "up ({}, {}, {}) is zero or parallel to the view direction (at - eye = {}, {}, {})",
        .up.x, .up.y, .up.z, .dir.x, .dir.y, .dir.z
    )]
    UpParallel {
        /// The up vector given.
        up: DVec3,
        /// The view direction `at - eye`.
        dir: DVec3,
    },
}

/// A line of a views file that [`parse_views`] refused: its number
/// (1-based), what is wrong, and its text.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewsError {
    /// The line's number, from 1.
    pub line: usize,
    /// What is wrong with it.
    pub problem: ViewProblem,
    /// The line as it is in the file.
    pub text: String,
}

/// What is wrong with a line of a views file.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ViewProblem {
    /// The line has no first word (the scene's name).
    #[error("no scene name")]
    NoSceneName,
    /// The line has no second word (the view's id).
    #[error("no view id")]
    NoViewId,
    /// A later word is not `key=value`.
    #[error("expected key=value")]
    NotKeyValue,
    /// The value of this key does not parse.
    #[error("bad {0}")]
    Bad(&'static str),
    /// A key other than `eye`, `at`, `up` and `fov`.
    #[error("unknown key `{}`", crate::text::escape_controls(.0))]
    UnknownKey(String),
    /// This key is missing.
    #[error("missing {0}")]
    Missing(&'static str),
    /// The view's camera does not define rays.
    #[error("{0}")]
    Camera(#[source] CameraError),
}

// Written by hand: the source is the camera error inside the problem
// (none for the other problems), which a derive cannot say.
impl std::fmt::Display for ViewsError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let text = crate::text::escape_controls(&self.text);
        write!(f, "line {}: {}: {text}", self.line, self.problem)
    }
}

impl std::error::Error for ViewsError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match &self.problem {
            ViewProblem::Camera(e) => Some(e),
            _ => None,
        }
    }
}

/// One line of a views file:
/// `SCENE VIEW_ID eye=x,y,z at=x,y,z up=x,y,z fov=DEG  # comment`.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// The scene's name (a file's stem or its header's scene tag).
    pub scene: String,
    /// The view's name among the scene's views.
    pub id: String,
    /// [`Camera::eye`].
    pub eye: DVec3,
    /// [`Camera::at`].
    pub at: DVec3,
    /// [`Camera::up`].
    pub up: DVec3,
    /// [`Camera::fov_deg`].
    pub fov_deg: f64,
}

/// Parses a views file; errors name the line.
pub fn parse_views(text: &str) -> Result<Vec<View>, ViewsError> {
    let mut views = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let bad = |problem: ViewProblem| ViewsError {
            line: i + 1,
            problem,
            text: raw.to_string(),
        };
        let mut words = line.split_whitespace();
        let scene = words
            .next()
            .ok_or_else(|| bad(ViewProblem::NoSceneName))?
            .to_string();
        let id = words
            .next()
            .ok_or_else(|| bad(ViewProblem::NoViewId))?
            .to_string();
        let (mut eye, mut at, mut up, mut fov) = (None, None, None, None);
        for w in words {
            let (key, value) = w
                .split_once('=')
                .ok_or_else(|| bad(ViewProblem::NotKeyValue))?;
            match key {
                "eye" => eye = Some(parse_vec3(value).ok_or_else(|| bad(ViewProblem::Bad("eye")))?),
                "at" => at = Some(parse_vec3(value).ok_or_else(|| bad(ViewProblem::Bad("at")))?),
                "up" => up = Some(parse_vec3(value).ok_or_else(|| bad(ViewProblem::Bad("up")))?),
                "fov" => {
                    fov = Some(
                        value
                            .parse::<f64>()
                            .map_err(|_| bad(ViewProblem::Bad("fov")))?,
                    )
                }
                _ => return Err(bad(ViewProblem::UnknownKey(key.to_string()))),
            }
        }
        let view = View {
            scene,
            id,
            eye: eye.ok_or_else(|| bad(ViewProblem::Missing("eye")))?,
            at: at.ok_or_else(|| bad(ViewProblem::Missing("at")))?,
            up: up.ok_or_else(|| bad(ViewProblem::Missing("up")))?,
            fov_deg: fov.ok_or_else(|| bad(ViewProblem::Missing("fov")))?,
        };
        Camera::from_view(&view, 1, 1)
            .check()
            .map_err(|e| bad(ViewProblem::Camera(e)))?;
        views.push(view);
    }
    Ok(views)
}

/// Parses `x,y,z`.
pub fn parse_vec3(s: &str) -> Option<DVec3> {
    let v: Vec<f64> = s
        .split(',')
        .map(|c| c.trim().parse().ok())
        .collect::<Option<_>>()?;
    (v.len() == 3 && v.iter().all(|c| c.is_finite())).then(|| DVec3::new(v[0], v[1], v[2]))
}

/// Finds the view of a scene and id. The scene is matched by the file's
/// stem, as [`find_view_named`] matches a name (so `stk_all.small.kd` and
/// `stk_all_fast.kd` find the views of `stk_all`).
pub fn find_view<'a>(views: &'a [View], scene_path: &Path, id: &str) -> Option<&'a View> {
    find_view_named(views, scene_path.file_stem()?.to_str()?, id)
}

/// Finds the view of the scene called `name` and id: the view of that
/// scene, or else of the longest scene name that `name` starts with,
/// followed by `.`, `_` or `-`.
pub fn find_view_named<'a>(views: &'a [View], name: &str, id: &str) -> Option<&'a View> {
    if let Some(v) = views.iter().find(|v| v.scene == name && v.id == id) {
        return Some(v);
    }
    views
        .iter()
        .filter(|v| {
            v.id == id
                && name.len() > v.scene.len()
                && name.starts_with(v.scene.as_str())
                && matches!(name.as_bytes()[v.scene.len()], b'.' | b'_' | b'-')
        })
        .max_by_key(|v| v.scene.len())
}

/// How hits are coloured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shading {
    /// Grey `|cos|` between the ray and the geometric normal.
    EyeLight,
    /// The geometric normal, facing the eye, mapped to `[0, 1]`.
    Normals,
}

/// The side of a square image tile.
pub const TILE: u32 = 16;

/// Per-pixel hits of one frame, row-major, `y = 0` first.
pub struct HitBuffer {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// `width · height` closest hits ([`Hit::MISS`] where a ray misses).
    pub hits: Vec<Hit>,
    /// Seconds spent generating and tracing the rays.
    pub seconds: f64,
    /// Of `seconds`, the share spent generating the rays (the pass's wall
    /// time split in proportion to its threads' time on each, as
    /// [`ao::AoTimes`] splits the secondary pass).
    pub making_s: f64,
}

impl HitBuffer {
    /// Pixels whose hit distance is finite.
    pub fn n_hits(&self) -> u64 {
        self.hits.iter().filter(|h| h.t.is_finite()).count() as u64
    }

    /// Sum of `f64(t)` over the hit pixels, in row-major order.
    pub fn checksum(&self) -> f64 {
        self.hits
            .iter()
            .filter(|h| h.t.is_finite())
            .fold(0.0, |s, h| s + f64::from(h.t))
    }

    /// Rays traced per second, in millions.
    pub fn mrays_per_s(&self) -> f64 {
        self.hits.len() as f64 / self.seconds / 1e6
    }

    /// The hit distances, `+∞` for a miss (a [`Frame`]'s depth).
    pub fn depth(&self) -> Vec<f32> {
        self.hits.iter().map(|h| h.t).collect()
    }
}

/// The camera's primary rays in the order [`trace_frame`] traces them:
/// tile by tile ([`TILE`]² pixels, row after row of tiles), in each
/// tile its 4×4 blocks row after row, each block's 16 rays row-major (a
/// block cut by the image's edge, which it traces ray by ray, row-major):
/// where the sides are multiples of 4, 16 consecutive rays are one of its
/// packets.
pub fn primary_rays(camera: &Camera) -> Vec<Ray> {
    let (w, h) = (camera.width, camera.height);
    let mut rays = Vec::with_capacity(w as usize * h as usize);
    for ty in (0..h).step_by(TILE as usize) {
        for tx in (0..w).step_by(TILE as usize) {
            let (tw, th) = ((tx + TILE).min(w) - tx, (ty + TILE).min(h) - ty);
            tile_rays(camera, (tx, ty), (tw, th), &mut rays);
        }
    }
    rays
}

/// Appends to `rays` the rays of the `tw × th` tile at `(x0, y0)`, in 4×4
/// blocks (row by row within a block, blocks row by row), the order of
/// [`primary_rays`] and of the frame's packets.
fn tile_rays(camera: &Camera, (x0, y0): (u32, u32), (tw, th): (u32, u32), rays: &mut Vec<Ray>) {
    let lens = camera.lens();
    for by in (0..th).step_by(4) {
        for bx in (0..tw).step_by(4) {
            for y in by..(by + 4).min(th) {
                for x in bx..(bx + 4).min(tw) {
                    rays.push(lens.ray(x0 + x, y0 + y));
                }
            }
        }
    }
}

/// Traces every pixel, tiles in parallel on the current rayon pool. Each
/// tile is traced in 4×4 blocks through [`ClosestHit::closest_hit_4x4`]
/// (packets, for a packet tracer); blocks cut by the image border go ray
/// by ray.
pub fn trace_frame(tracer: &dyn ClosestHit, camera: &Camera) -> HitBuffer {
    trace_frame_with_progress(tracer, camera, None)
}

/// [`trace_frame`], advancing `progress` by an equal share per tile traced
/// (to exactly 1 at the end).
pub fn trace_frame_with_progress(
    tracer: &dyn ClosestHit,
    camera: &Camera,
    progress: Option<&Progress>,
) -> HitBuffer {
    let (w, h) = (camera.width, camera.height);
    let tiles_x = w.div_ceil(TILE);
    let tiles_y = h.div_ceil(TILE);
    let n_tiles = u64::from(tiles_x * tiles_y);
    let start = Instant::now();
    // Per tile: its hits, the seconds spent making its rays and tracing
    // them (two clock reads a tile).
    let tiles: Vec<(Vec<Hit>, f64, f64)> = (0..tiles_x * tiles_y)
        .into_par_iter()
        .with_max_len(job_len((TILE * TILE) as usize))
        .map_init(Vec::new, |rays, tile| {
            let (x0, y0) = ((tile % tiles_x) * TILE, (tile / tiles_x) * TILE);
            let (tw, th) = ((x0 + TILE).min(w) - x0, (y0 + TILE).min(h) - y0);
            let t0 = Instant::now();
            rays.clear();
            tile_rays(camera, (x0, y0), (tw, th), rays);
            let t1 = Instant::now();
            let mut out = vec![Hit::MISS; (tw * th) as usize];
            let mut k = 0;
            for by in (0..th).step_by(4) {
                for bx in (0..tw).step_by(4) {
                    if bx + 4 <= tw && by + 4 <= th {
                        let block: &[Ray; 16] = rays[k..k + 16].try_into().expect("a 4×4 block");
                        k += 16;
                        let mut hits = [Hit::MISS; 16];
                        tracer.closest_hit_4x4(block, &mut hits);
                        for (i, hit) in hits.into_iter().enumerate() {
                            let (x, y) = (bx + i as u32 % 4, by + i as u32 / 4);
                            out[(y * tw + x) as usize] = hit;
                        }
                    } else {
                        for y in by..(by + 4).min(th) {
                            for x in bx..(bx + 4).min(tw) {
                                out[(y * tw + x) as usize] = tracer.closest_hit(&rays[k]);
                                k += 1;
                            }
                        }
                    }
                }
            }
            let t2 = Instant::now();
            Progress::advance(progress, u64::from(tile), u64::from(tile) + 1, n_tiles);
            (out, (t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64())
        })
        .collect();
    let seconds = start.elapsed().as_secs_f64();
    let (making, tracing) = tiles
        .iter()
        .fold((0.0, 0.0), |(m, t), &(_, a, b)| (m + a, t + b));
    let making_s = if making + tracing > 0.0 {
        seconds * making / (making + tracing)
    } else {
        0.0
    };
    let mut hits = vec![Hit::MISS; (w as usize) * (h as usize)];
    for (tile, (pixels, _, _)) in tiles.into_iter().enumerate() {
        let tile = tile as u32;
        let (x0, y0) = ((tile % tiles_x) * TILE, (tile / tiles_x) * TILE);
        let tw = (x0 + TILE).min(w) - x0;
        for (i, hit) in pixels.into_iter().enumerate() {
            let (x, y) = (x0 + i as u32 % tw, y0 + i as u32 / tw);
            hits[(y * w + x) as usize] = hit;
        }
    }
    HitBuffer {
        width: w,
        height: h,
        hits,
        seconds,
        making_s,
    }
}

/// Where shading finds the geometric normal (not normalised) of a hit's
/// triangle, by its input id.
pub trait TriangleNormals: Sync {
    /// The normal of input triangle `tri`.
    fn normal(&self, tri: u32) -> Vec3;
}

impl<T: TriangleNormals + ?Sized> TriangleNormals for &T {
    fn normal(&self, tri: u32) -> Vec3 {
        (**self).normal(tri)
    }
}

impl TriangleNormals for TriangleColumns {
    fn normal(&self, tri: u32) -> Vec3 {
        TriangleColumns::normal(self, tri)
    }
}

/// The normals of a frame's hit triangles, read from a `.kd` file's
/// mapped sections where they lie: nothing of the geometry is copied, and
/// only the pages of the triangles hit (and, in a reordered file, the
/// `tri_map`, read once) are touched. What it holds is one entry per
/// distinct triangle hit, and a bit per triangle while it is made.
pub struct FileNormals<'a, D: AsRef<[u8]>> {
    file: &'a KdFile<D>,
    /// The distinct input ids hit, ascending, and beside each its file id.
    hit_ids: Vec<(u32, u32)>,
}

impl<'a, D: AsRef<[u8]> + Sync> FileNormals<'a, D> {
    /// The normals of the triangles `buffer` hit, in `file`.
    pub fn new(file: &'a KdFile<D>, buffer: &HitBuffer) -> FileNormals<'a, D> {
        let n_tris = file.triangles().len();
        let mut hit_ids: Vec<(u32, u32)> = buffer
            .hits
            .iter()
            .filter(|h| h.is_hit() && (h.tri.0 as usize) < n_tris)
            .map(|h| (h.tri.0, h.tri.0))
            .collect();
        hit_ids.sort_unstable();
        hit_ids.dedup();
        if let Some(map) = file.tri_map() {
            // File id of every input id hit: one pass over the map (a
            // permutation in a valid file; an entry out of range matches
            // nothing), testing each entry against a bit set of the ids hit.
            let mut wanted = vec![0u64; n_tris.div_ceil(64)];
            for &(input, _) in &hit_ids {
                wanted[input as usize / 64] |= 1 << (input % 64);
            }
            let found: Vec<(u32, u32)> = map
                .par_iter()
                .enumerate()
                .filter(|&(_, &input)| {
                    wanted
                        .get(input as usize / 64)
                        .is_some_and(|w| w & (1 << (input % 64)) != 0)
                })
                .map(|(file_id, &input)| (input, file_id as u32))
                .collect();
            for (input, file_id) in found {
                if let Ok(k) = hit_ids.binary_search_by_key(&input, |&(i, _)| i) {
                    hit_ids[k].1 = file_id;
                }
            }
        }
        FileNormals { file, hit_ids }
    }
}

impl<D: AsRef<[u8]> + Sync> TriangleNormals for FileNormals<'_, D> {
    /// The normal of input triangle `tri`, one of those hit (zero for any
    /// other, which shading does not ask for).
    fn normal(&self, tri: u32) -> Vec3 {
        let Ok(k) = self.hit_ids.binary_search_by_key(&tri, |&(i, _)| i) else {
            return Vec3::ZERO;
        };
        // Every read is checked, so that a file whose sections are not all
        // validated on open still cannot make shading panic.
        let vertices = self.file.vertices();
        let corner = |v: u32| vertices.get(v as usize).copied().map(Vec3::from_array);
        let Some(&[a, b, c]) = self.file.triangles().get(self.hit_ids[k].1 as usize) else {
            return Vec3::ZERO;
        };
        match (corner(a), corner(b), corner(c)) {
            (Some(a), Some(b), Some(c)) => (b - a).cross(c - a),
            _ => Vec3::ZERO,
        }
    }
}

/// Colours a traced frame.
pub fn shade(
    buffer: &HitBuffer,
    camera: &Camera,
    scene: &(impl TriangleNormals + ?Sized),
    shading: Shading,
) -> Frame {
    let background = [0.05f32, 0.05, 0.08];
    let lens = camera.lens();
    let rgb = (0..buffer.hits.len())
        .into_par_iter()
        .map(|i| {
            let hit = buffer.hits[i];
            if !hit.is_hit() {
                return background;
            }
            let (x, y) = (i as u32 % buffer.width, i as u32 / buffer.width);
            let dir = lens.ray(x, y).dir;
            let n = scene.normal(hit.tri.0).normalize_or_zero();
            let n = if n.dot(dir) > 0.0 { -n } else { n };
            match shading {
                Shading::EyeLight => {
                    let c = 0.1 + 0.9 * n.dot(-dir).abs();
                    [c, c, c]
                }
                Shading::Normals => {
                    let c = n * 0.5 + Vec3::splat(0.5);
                    [c.x, c.y, c.z]
                }
            }
        })
        .collect();
    Frame {
        width: buffer.width,
        height: buffer.height,
        rgb,
        depth: buffer.depth(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_centre_ray_looks_at_target() {
        let cam = Camera {
            eye: DVec3::new(0.0, 0.0, 10.0),
            at: DVec3::ZERO,
            up: DVec3::Y,
            fov_deg: 90.0,
            width: 2,
            height: 2,
        };
        // Pixel (0, 0) is the top-left one: it looks left (−x) and up (+y).
        let r = cam.ray(0, 0);
        assert!(r.dir.x < 0.0 && r.dir.y > 0.0 && r.dir.z < 0.0);
        let r = cam.ray(1, 1);
        assert!(r.dir.x > 0.0 && r.dir.y < 0.0);
        assert_eq!(r.origin, Vec3::new(0.0, 0.0, 10.0));
        // With fov 90 and 2x2 pixels, sx = ±0.5 and sy = ±0.5 exactly.
        let expect = normalize(DVec3::new(0.5, -0.5, -1.0)).as_vec3();
        assert_eq!(r.dir, expect);
    }

    #[test]
    fn degenerate_cameras_are_refused() {
        let good = Camera {
            eye: DVec3::new(0.0, 5.0, 0.0),
            at: DVec3::ZERO,
            up: DVec3::Z,
            fov_deg: 60.0,
            width: 4,
            height: 3,
        };
        assert_eq!(good.check(), Ok(()));
        assert!(good.ray(0, 0).dir.is_finite());
        let with = |f: &dyn Fn(&mut Camera)| {
            let mut c = good;
            f(&mut c);
            c.check().unwrap_err().to_string()
        };
        // Looking straight down (−y) with up = +y: no right vector, and
        // the rays would be NaN.
        let parallel = with(&|c| c.up = DVec3::Y);
        assert!(parallel.contains("parallel"), "{parallel}");
        let mut down = good;
        down.up = DVec3::Y;
        assert!(!down.ray(0, 0).dir.is_finite());
        assert!(with(&|c| c.up = DVec3::new(0.0, -3.0, 0.0)).contains("parallel"));
        assert!(with(&|c| c.up = DVec3::ZERO).contains("zero"));
        assert!(with(&|c| c.at = c.eye).contains("same point"));
        assert!(with(&|c| c.fov_deg = 180.0).contains("fov"));
        assert!(with(&|c| c.fov_deg = 0.0).contains("fov"));
        assert!(with(&|c| c.fov_deg = f64::NAN).contains("fov"));
        assert!(with(&|c| c.width = 0).contains("empty"));
        assert!(with(&|c| c.eye.x = f64::INFINITY).contains("finite"));
        // Nearly parallel but well defined: accepted.
        let mut tilted = good;
        tilted.up = DVec3::new(1e-6, 1.0, 0.0);
        assert_eq!(tilted.check(), Ok(()));
        assert!(tilted.ray(1, 2).dir.is_finite());
        // A views file line with such a camera is refused, naming the line.
        let err = parse_views("a 1 eye=0,0,0 at=0,0,0 up=0,1,0 fov=60\n")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("line 1") && err.contains("same point"),
            "{err}"
        );
        let err = parse_views("\na 2 eye=0,5,0 at=0,0,0 up=0,1,0 fov=60")
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 2") && err.contains("parallel"), "{err}");
        assert!(parse_views("a 1 eye=1,2,3 at=0,0,0 up=0,1,0 fov=200").is_err());
    }

    #[test]
    fn views_parse_and_match_by_stem() {
        let text = "# comment\nbunny 1 eye=1,2,3 at=0,0,0 up=0,1,0 fov=60  # hits 0.9\n\nbunny 2 eye=1,2,3 at=0,0,1 up=0,1,0 fov=45\n";
        let views = parse_views(text).unwrap();
        assert_eq!(views.len(), 2);
        let v = find_view(&views, Path::new("/x/bunny.obj"), "2").unwrap();
        assert_eq!(v.fov_deg, 45.0);
        assert_eq!(v.at, DVec3::new(0.0, 0.0, 1.0));
        assert!(find_view(&views, Path::new("cat.obj"), "1").is_none());
        assert_eq!(
            find_view(&views, Path::new("bunny.small.kd"), "2")
                .unwrap()
                .fov_deg,
            45.0
        );
        assert!(find_view(&views, Path::new("bunnyx.kd"), "2").is_none());
        assert!(
            parse_views("a 1 eye=1,2 at=0,0,0 up=0,1,0 fov=60")
                .unwrap_err()
                .to_string()
                .contains("line 1")
        );
        assert!(
            parse_views("a 1 at=0,0,0 up=0,1,0 fov=60")
                .unwrap_err()
                .to_string()
                .contains("missing eye")
        );
    }
}
