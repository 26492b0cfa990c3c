//! The import pipeline, in one place: a scan file (or, for callers that made one themselves, a
//! [`Source`]) becomes a committed scene in a [`Pool`].
//!
//! Every importer of the project goes through here — the `arbor-server import` CLI, the build
//! and memory benchmarks, the test support — so the order of the steps and what a failure leaves
//! behind are decided once:
//!
//! 1. the pool refuses a bad or taken name before any work ([`Pool::begin_import`]);
//! 2. the file (or every tile of a point set) is parsed into disk-backed columns in a scratch
//!    directory (errors name the file and the place, and the pool has not been touched yet;
//!    the scratch directories killed imports left beside it are removed first:
//!    [`crate::scratch`]);
//! 3. the octree is built straight into the import transaction;
//! 4. the memory figures are recorded in the description and the transaction commits — the
//!    scene becomes visible in one catalogue insert. A failure in 2–3 drops the transaction,
//!    which removes whatever it wrote.

use std::path::{Path, PathBuf};

use arbor_proto::SceneDescription;
use thiserror::Error;

use crate::import::tiles::import_tiles;
use crate::import::{ImportError, ImportOptions, import_file};
use crate::memory::{AnonPeakSampler, peak_rss_bytes};
use crate::octree::{BuildError, BuildOptions, BuildTarget, build_scene_observed};
use crate::pool::{Pool, PoolError};
use crate::progress::{ImportProgress, Phase};
use crate::scratch::ScratchDir;
use crate::source::Source;

/// What to import, and how.
#[derive(Clone, Debug, Default)]
pub struct SceneImport {
    /// The scene's name in the pool.
    pub name: String,
    /// The scan file (the first tile of a point set).
    pub input: PathBuf,
    /// Further tiles of a point set, read after `input` as one scene, in this order (LAS/LAZ and
    /// point PLY files; see [`crate::import::tiles`]).
    pub more_tiles: Vec<PathBuf>,
    /// How to read it (format override, raw volume layout).
    pub import: ImportOptions,
    /// How to build the octree.
    pub build: BuildOptions,
    /// Replace a scene of the same name atomically instead of refusing.
    pub replace: bool,
    /// Where the scratch directory goes (default: the system's temporary directory).
    pub scratch_parent: Option<PathBuf>,
}

/// A committed import: the stored description, and the parsed source with the scratch
/// directory that backs it (dropping it removes the scratch files).
#[derive(Debug)]
pub struct ImportedScene {
    /// The description as committed.
    pub description: SceneDescription,
    /// The parsed input (its columns are memory-mapped scratch files).
    pub source: Source,
    /// The scratch directory; removed on drop.
    pub scratch: ScratchDir,
}

/// Why an import failed. The pool is unchanged in every case.
#[derive(Debug, Error)]
pub enum PipelineError {
    /// The scratch directory could not be created.
    #[error("creating a scratch directory{}: {source}", parent.as_ref().map(|p| format!(" in {}", p.display())).unwrap_or_default())]
    Scratch {
        /// The parent asked for, if any.
        parent: Option<PathBuf>,
        /// What the file system said.
        #[source]
        source: std::io::Error,
    },
    /// The file could not be parsed (the error names the file and the place).
    #[error(transparent)]
    Import(#[from] ImportError),
    /// The octree could not be built.
    #[error("building scene {name:?}: {source}")]
    Build {
        /// The scene.
        name: String,
        /// What the builder said.
        #[source]
        source: BuildError,
    },
    /// The pool refused the name, or reading or writing it failed.
    #[error(transparent)]
    Pool(#[from] PoolError),
}

/// Parses `request.input`, builds it and commits it to `pool` as `request.name`.
pub fn import_scene(pool: &Pool, request: &SceneImport) -> Result<ImportedScene, PipelineError> {
    import_scene_observed(pool, request, &ImportProgress::default(), Superseded::Drop)
        .map(|(scene, _)| scene)
}

/// What a replacing import does with the generation it supersedes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Superseded {
    /// Drop it at once (nobody else reads the pool).
    Drop,
    /// Keep it and return it, for readers that opened it to finish on it (the serving daemon
    /// drops it with [`Pool::drop_retired`] when its last session ended).
    Keep,
}

/// [`import_scene`], reporting progress as it goes; with [`Superseded::Keep`] also returns the
/// generation a replacement superseded.
pub fn import_scene_observed(
    pool: &Pool,
    request: &SceneImport,
    progress: &ImportProgress,
    superseded: Superseded,
) -> Result<(ImportedScene, Option<u64>), PipelineError> {
    let scratch = scratch_dir(request.scratch_parent.as_deref())?;
    // Checked again by `begin_import`; refusing here avoids parsing a file for nothing.
    if !request.replace && pool.contains(&request.name)? {
        return Err(PoolError::SceneExists(request.name.clone()).into());
    }
    let sampler = AnonPeakSampler::start();
    progress.enter(Phase::Reading, 0);
    let source = if request.more_tiles.is_empty() {
        import_file(&request.input, &request.import, scratch.path())?
    } else {
        let mut files = vec![request.input.clone()];
        files.extend(request.more_tiles.iter().cloned());
        import_tiles(&files, &request.import.tiles, scratch.path())?
    };
    tracing::info!("read {}: {}", request.input.display(), source.describe());
    let mut label = request
        .input
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    if !request.more_tiles.is_empty() {
        label = format!("{label} + {} more tiles", request.more_tiles.len());
    }
    let job = SourceImport {
        source: &source,
        name: &request.name,
        label: &label,
        build: &request.build,
        scratch: scratch.path(),
        replace: request.replace,
    };
    let (description, retired) =
        build_into_pool_observed(pool, &job, Some(sampler), progress, superseded)?;
    Ok((
        ImportedScene {
            description,
            source,
            scratch,
        },
        retired,
    ))
}

/// An already parsed source to build into a pool (callers that make or reuse a [`Source`]
/// themselves: synthetic test scenes, benchmarks building one file several ways).
#[derive(Clone, Copy, Debug)]
pub struct SourceImport<'a> {
    /// The parsed input.
    pub source: &'a Source,
    /// The scene's name in the pool.
    pub name: &'a str,
    /// What the input was, for the description (e.g. the file name).
    pub label: &'a str,
    /// How to build the octree.
    pub build: &'a BuildOptions,
    /// Scratch directory for the build's spill and record files.
    pub scratch: &'a Path,
    /// Replace a scene of the same name atomically instead of refusing.
    pub replace: bool,
}

/// Builds `job.source` into `pool` and commits it; `sampler`, if given, was started before
/// parsing and supplies the peak anonymous memory recorded in the description.
pub fn build_into_pool(
    pool: &Pool,
    job: &SourceImport<'_>,
    sampler: Option<AnonPeakSampler>,
) -> Result<SceneDescription, PipelineError> {
    let progress = ImportProgress::default();
    build_into_pool_observed(pool, job, sampler, &progress, Superseded::Drop).map(|(d, _)| d)
}

/// [`build_into_pool`], reporting progress; returns the superseded generation when kept.
///
/// The progress stays at [`Phase::Committing`]: the caller enters [`Phase::Done`] once its own
/// bookkeeping (retiring the old generation, recording the outcome) is finished, so whoever
/// watches the phase never sees "done" before the import's effects are all visible.
pub fn build_into_pool_observed(
    pool: &Pool,
    job: &SourceImport<'_>,
    sampler: Option<AnonPeakSampler>,
    progress: &ImportProgress,
    superseded: Superseded,
) -> Result<(SceneDescription, Option<u64>), PipelineError> {
    let mut txn = pool.begin_import(job.name, job.replace)?;
    let target = BuildTarget {
        name: job.name,
        source_label: job.label,
        scratch: job.scratch,
    };
    let mut description = build_scene_observed(job.source, &target, job.build, &mut txn, progress)
        .map_err(|source| PipelineError::Build {
            name: job.name.to_owned(),
            source,
        })?;
    description.stats.peak_rss_bytes = peak_rss_bytes();
    if let Some(sampler) = sampler {
        description.stats.peak_anon_bytes = sampler.finish();
    }
    progress.enter(Phase::Committing, 0);
    let retired = match superseded {
        Superseded::Drop => {
            txn.commit(&description)?;
            None
        }
        Superseded::Keep => txn.commit_retaining(&description)?,
    };
    Ok((description, retired))
}

fn scratch_dir(parent: Option<&Path>) -> Result<ScratchDir, PipelineError> {
    ScratchDir::new(parent).map_err(|source| PipelineError::Scratch {
        parent: parent.map(Path::to_path_buf),
        source,
    })
}
