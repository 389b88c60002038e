//! The one way from a scene to a tree file: [`Pipeline`] builds the
//! standard tree (with the memory-budget policy of the level builder),
//! slims it, and writes it as a `.kd` file or image whose header records
//! the build ([`file_config`]). The facade ([`crate::accel`]) and the
//! command line (its builds, the report, the sweep) all run it.

use crate::build::level::{self, LevelOptions, LevelReport};
use crate::build::{self, Algorithm, BuildConfig, BuildError};
use crate::format::{
    self, AlignedBytes, FileConfig, FormatError, KdFile, Preset, SceneTag, WriteOptions,
};
use crate::progress::Progress;
use crate::scene::TriangleColumns;
use crate::slim::{self, SlimParams, SlimPhases, SlimReport};
use crate::tree::{PreOrderSink, TreeIr};
use std::borrow::Cow;
use std::path::Path;

/// Why a [`Pipeline`] stopped: its build or its writing failed (the
/// message is that of the step).
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// The build failed (its scratch files, or the scene).
    #[error(transparent)]
    Build(#[from] BuildError),
    /// The tree could not be written or its image opened.
    #[error(transparent)]
    Format(#[from] FormatError),
}

/// What to make of a scene: the build, the slim pass, and how the file
/// is written. Each step is a method, so that a caller can time it or
/// show its progress; [`Pipeline::image`] runs them all.
#[derive(Clone, Debug)]
pub struct Pipeline {
    /// The cost model and depth limit of the build (and the slim pass).
    pub config: BuildConfig,
    /// Which builder makes the standard tree (all make the same tree).
    pub algorithm: Algorithm,
    /// The level builder's options but its budget and finisher size,
    /// which [`Pipeline::level_options`] sets.
    pub level: LevelOptions,
    /// Bytes of anonymous memory the level build may hold; `None`: no
    /// budget.
    pub mem_budget: Option<u64>,
    /// Nodes of fewer references than this are finished depth-first;
    /// `None`: the default, or the budget's
    /// ([`LevelOptions::small_threshold_for_budget`]).
    pub small: Option<usize>,
    /// The slim pass; `None`: the standard tree.
    pub slim: Option<SlimParams>,
    /// The preset the file records.
    pub preset: Preset,
    /// Renumber triangles in Morton order in the file.
    pub reorder: bool,
    /// The scene's name the file records; `None`: no scene tag.
    pub scene_name: Option<String>,
}

impl Pipeline {
    /// The standard tree of `config` with the level builder, no budget,
    /// written reordered and without a scene tag.
    pub fn new(config: BuildConfig) -> Pipeline {
        Pipeline {
            config,
            algorithm: Algorithm::Level,
            level: LevelOptions::default(),
            mem_budget: None,
            small: None,
            slim: None,
            preset: Preset::Std,
            reorder: true,
            scene_name: None,
        }
    }

    /// The same pipeline with the slim pass `slim` recorded as `preset`,
    /// and the pass's split price ([`SlimParams::split_price`]), if it has
    /// one, in the build configuration: the std tree the pass starts from
    /// must be built by this pipeline, not taken from another.
    pub fn slimmed(&self, slim: Option<SlimParams>, preset: Preset) -> Pipeline {
        let mut config = self.config;
        if let Some(mu) = slim.and_then(|p| p.split_price) {
            config.sah.split_price = mu;
        }
        Pipeline {
            config,
            slim,
            preset,
            ..self.clone()
        }
    }

    /// The level builder's options under the memory budget: the budget
    /// itself, and finishers that take larger nodes under a budget (which
    /// saves levels of scratch traffic) unless [`Pipeline::small`] says
    /// otherwise.
    pub fn level_options(&self) -> LevelOptions {
        let small_threshold = self.small.unwrap_or_else(|| {
            LevelOptions::small_threshold_for_budget(self.mem_budget, rayon::current_num_threads())
        });
        LevelOptions {
            mem_budget: self.mem_budget,
            small_threshold,
            ..self.level.clone()
        }
    }

    /// Builds the standard tree (on the current rayon pool), with the
    /// level builder's report when it ran.
    pub fn build(
        &self,
        scene: &TriangleColumns,
        progress: Option<&Progress>,
    ) -> Result<(TreeIr, Option<LevelReport>), BuildError> {
        match self.algorithm {
            Algorithm::Level => {
                let (tree, report) =
                    level::build(scene, &self.config, progress, &self.level_options())?;
                Ok((tree, Some(report)))
            }
            other => Ok((build::build(scene, &self.config, other, progress)?, None)),
        }
    }

    /// Builds the standard tree straight into the file `path` (the level
    /// builder, no slim pass), feeding `sink` too; `built` is called once
    /// the tree is complete, before the file is finished. `None`: the
    /// tree did not reach the file. The file's bytes are those of
    /// [`Pipeline::build`] then [`Pipeline::write_file`].
    pub fn build_into_file(
        &self,
        path: &Path,
        scene: &TriangleColumns,
        progress: Option<&Progress>,
        sink: &mut impl PreOrderSink,
        built: impl FnOnce(),
    ) -> Result<Option<LevelReport>, PipelineError> {
        let options = self.level_options();
        format::write_file_streamed(path, scene, &self.write_options(scene), |w| {
            let report =
                level::build_into(scene, &self.config, progress, &options, &mut (w, sink))?;
            built();
            Ok(report)
        })
    }

    /// The std tree this pipeline's slim pass starts from: `std`, built by
    /// `built_by`, where that pipeline has this one's build configuration,
    /// else this pipeline's own build (a preset's split price,
    /// [`SlimParams::split_price`]), on the current rayon pool.
    pub fn base_tree<'t>(
        &self,
        std: &'t TreeIr,
        built_by: &Pipeline,
        scene: &TriangleColumns,
    ) -> Result<Cow<'t, TreeIr>, BuildError> {
        if self.config == built_by.config {
            Ok(Cow::Borrowed(std))
        } else {
            Ok(Cow::Owned(self.build(scene, None)?.0))
        }
    }

    /// The pipeline's slim pass over `tree` (on the current rayon pool);
    /// `None` for the standard tree.
    pub fn slim(
        &self,
        tree: &TreeIr,
        scene: &TriangleColumns,
        progress: Option<&Progress>,
    ) -> Option<(TreeIr, SlimReport, SlimPhases)> {
        let params = self.slim.as_ref()?;
        Some(slim::slim_with_progress(
            tree,
            scene,
            &self.config,
            params,
            progress,
        ))
    }

    /// How the tree of `scene` is written: reordered or not, with the
    /// build recorded in the header.
    pub fn write_options(&self, scene: &TriangleColumns) -> WriteOptions {
        let config = file_config(&self.config, scene.len(), self.preset, self.slim.as_ref());
        WriteOptions {
            reorder: self.reorder,
            config: match &self.scene_name {
                Some(name) => FileConfig {
                    scene: SceneTag::new(name, scene),
                    ..config
                },
                None => config,
            },
        }
    }

    /// Writes `tree` as the `.kd` file `path` (atomically).
    pub fn write_file(
        &self,
        path: &Path,
        tree: &TreeIr,
        scene: &TriangleColumns,
    ) -> Result<(), FormatError> {
        format::write_file(path, tree, scene, &self.write_options(scene))
    }

    /// Writes `tree` as `.kd` bytes in memory and opens them.
    pub fn write_image(
        &self,
        tree: &TreeIr,
        scene: &TriangleColumns,
    ) -> Result<KdFile<AlignedBytes>, FormatError> {
        let bytes = format::write_to_vec(tree, scene, &self.write_options(scene))?;
        KdFile::from_bytes(format::aligned_copy(&bytes))
    }

    /// The whole pipeline in memory: build, slim, write, open.
    pub fn image(&self, scene: &TriangleColumns) -> Result<KdFile<AlignedBytes>, PipelineError> {
        let (tree, _) = self.build(scene, None)?;
        let tree = match self.slim(&tree, scene, None) {
            Some((slimmed, _, _)) => slimmed,
            None => tree,
        };
        Ok(self.write_image(&tree, scene)?)
    }
}

/// The build parameters a `.kd` file records: the SAH constants and depth
/// limit of `config` for `n_tris` triangles, the preset, and the slim
/// thresholds (zero without a slim pass).
pub fn file_config(
    config: &BuildConfig,
    n_tris: usize,
    preset: Preset,
    slim: Option<&SlimParams>,
) -> FileConfig {
    let (tau_occu, tau_freq, max_t2rn) = slim.map_or((0.0, 0.0, 0), |p| {
        (p.tau_occu as f32, p.tau_freq as f32, p.max_t2rn)
    });
    FileConfig {
        k_t: config.sah.k_t,
        k_i: config.sah.k_i,
        lambda_empty: config.sah.lambda_empty,
        depth_limit: config.sah.depth_limit(n_tris),
        split_price: config.sah.split_price,
        preset,
        tau_occu,
        tau_freq,
        max_t2rn,
        scene: Default::default(),
    }
}
