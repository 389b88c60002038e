//! slimkd builds, stores and traces SAH kd-trees for ray tracing large
//! static triangle scenes.
//!
//! The pipeline:
//!
//! 1. [`scene::load`] reads a mesh (OBJ, PLY, glTF/GLB, gzip, or a scene
//!    cache) into [`scene::TriangleColumns`].
//! 2. [`build::build`] builds the standard SAH kd-tree (exact SAH, perfect
//!    splits) as a [`tree::TreeIr`]; [`build::naive`] is the O(N²)
//!    reference, [`build::wald_havran`] the O(N log N) builder of Wald & Havran
//!    (2006), and [`build::level`] the breadth-first parallel builder of
//!    Wu, Zhao & Liu (2011) over columns that may live in scratch
//!    files; all three produce the same tree.
//! 3. [`slim::slim`] hoists duplicated triangles into inner nodes (Choi,
//!    Chang & Ihm 2013); [`format`](mod@format) writes the tree and its geometry as a
//!    `.kd` file that [`format::KdFile`] maps and validates.
//! 4. [`trace`] finds closest hits: scalar front-to-back traversal, 4×4
//!    SIMD packets, or brute force for reference.
//! 5. [`render`] shoots camera rays over image tiles in parallel and writes
//!    PNG or OpenEXR; [`stats`] takes a tree's figures.
//!
//! [`pipeline::Pipeline`] runs steps 2–3 as one: build, slim and write,
//! under a memory budget, with the build recorded in the file's header.
//!
//! [`accel`] wraps steps 2–4 for a renderer: [`Accel`] builds from a
//! scene or the caller's buffers, writes and maps `.kd` files, and traces
//! single rays and masked 16-ray packets ([`RayPacket`]), with hit records
//! ([`HitRecord`]: barycentrics, geometric normal, input triangle id);
//! [`Accel::tracer`] gives an [`AccelTracer`] that takes the file's view
//! once for many rays. These, [`BuildOptions`], [`Preset`], [`AccelError`],
//! [`Ray`] and the scene types are re-exported here.
//!
//! ```
//! use slimkd::{build, scene::TriangleColumns, trace, geom::Ray};
//! use glam::Vec3;
//!
//! let scene = TriangleColumns::from_triangles(&[[
//!     Vec3::new(0.0, 0.0, 5.0), Vec3::new(2.0, 0.0, 5.0), Vec3::new(0.0, 2.0, 5.0),
//! ]]).unwrap();
//! let tree = build::build(&scene, &build::BuildConfig::default(), build::Algorithm::WaldHavran, None).unwrap();
//! tree.validate(&scene).unwrap();
//! let hit = trace::closest_hit(&tree, &scene, &Ray::new(Vec3::new(0.5, 0.5, 0.0), Vec3::Z));
//! assert_eq!(hit.t, 5.0);
//! assert_eq!(hit.tri.0, 0);
//! ```
//!
//! The same through the facade, round trip through a file included:
//!
//! ```
//! use slimkd::{Accel, BuildOptions, Ray};
//! use glam::Vec3;
//!
//! let vertices = [[0.0, 0.0, 5.0], [2.0, 0.0, 5.0], [0.0, 2.0, 5.0]];
//! let built = Accel::from_buffers(&vertices, &[[0, 1, 2]], &BuildOptions::default()).unwrap();
//! let path = std::env::temp_dir().join(format!("slimkd-lib-doc-{}.kd", std::process::id()));
//! built.write(&path).unwrap();
//! let accel = Accel::open(&path).unwrap();
//! let hit = accel.intersect(&Ray::new(Vec3::new(0.5, 0.5, 0.0), Vec3::Z)).unwrap();
//! assert_eq!((hit.t, hit.prim, hit.u, hit.v), (5.0, 0, 0.25, 0.25));
//! assert_eq!(hit.ng, Vec3::new(0.0, 0.0, 4.0));
//! let tracer = accel.tracer();
//! assert_eq!(tracer.intersect(&Ray::new(Vec3::new(0.5, 0.5, 0.0), Vec3::Z)), Some(hit));
//! std::fs::remove_file(&path).unwrap();
//! ```

#![deny(unsafe_op_in_unsafe_fn)]
#![warn(missing_docs)]
#![warn(clippy::undocumented_unsafe_blocks)]

pub mod accel;
pub mod build;
pub mod cells;
pub(crate) mod columns;
pub mod format;
#[doc(hidden)] // the CLI's atomic writes and input checks
pub mod fsio;
pub mod geom;
pub mod pipeline;
pub mod progress;
pub mod render;
pub mod scene;
pub(crate) mod simd;
pub mod slim;
pub mod stats;
#[doc(hidden)] // the CLI's allocator hooks and /proc figures
pub mod sys;
pub(crate) mod text;
pub mod trace;
pub mod tree;

pub use accel::{Accel, AccelError, AccelTracer, BuildOptions, HitRecord, Preset, RayPacket};
pub use geom::Ray;
pub use scene::{SceneError, SceneFormat, TriangleColumns};
pub use trace::OccluderCache;
