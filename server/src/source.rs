//! What an importer hands to the builder: geometry in flat, disk-backed columns.
//!
//! Importers stream primitives into [`ColumnWriter`]s, which append to files in a scratch
//! directory; [`ColumnWriter::finish`] memory-maps the file. The builder then reads the columns as
//! plain slices while the kernel pages them in and out, so the source geometry never has to fit in
//! RAM (see ARCHITECTURE.md, "Memory bound").

use std::fs::File;
use std::io::{BufWriter, Write};
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

use bytemuck::Pod;

/// One kind of input, as the builder sees it.
#[derive(Debug)]
pub enum Source {
    /// Indexed triangles (OBJ, PLY faces or triangle strips).
    Mesh(MeshSource),
    /// Unconnected points (point-only PLY, LAS/LAZ).
    Points(PointSource),
    /// A regular grid of scalar samples (NRRD, raw), surfaced by an iso threshold.
    Volume(VolumeSource),
}

/// Indexed triangle mesh. Positions are f64 so projected coordinates keep millimetres.
#[derive(Debug)]
pub struct MeshSource {
    pub positions: Column<[f64; 3]>,
    /// Per-vertex normals, when the file has them (same length as `positions`).
    pub normals: Option<Column<[f32; 3]>>,
    /// Per-vertex 8-bit RGB, when the file has it (same length as `positions`).
    pub colors: Option<Column<[u8; 3]>>,
    /// Vertex indices, every index `< positions.len()` (importers check this).
    pub triangles: Column<[u32; 3]>,
}

/// Point cloud.
#[derive(Debug)]
pub struct PointSource {
    pub positions: Column<[f64; 3]>,
    /// 8-bit RGB per point, when the file has colour.
    pub colors: Option<Column<[u8; 3]>>,
    /// Normals per point, when the file has them.
    pub normals: Option<Column<[f32; 3]>>,
}

/// Scalar volume on a regular grid; sample `(i, j, k)` sits at `origin + (i, j, k) * spacing`
/// and is stored at `values[i + dims[0] * (j + dims[1] * k)]`.
#[derive(Debug)]
pub struct VolumeSource {
    pub dims: [u32; 3],
    pub spacing: [f64; 3],
    pub origin: [f64; 3],
    pub values: Column<f32>,
    /// Value range of the source type, used to normalise density (e.g. 0..255 for uint8).
    pub value_range: [f32; 2],
}

/// Errors while writing or mapping a column.
#[derive(Debug, thiserror::Error)]
pub enum ColumnError {
    /// The scratch file could not be created, written or mapped.
    #[error("scratch column {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Appends fixed-size records to a scratch file.
#[derive(Debug)]
pub struct ColumnWriter<T: Pod> {
    path: PathBuf,
    out: BufWriter<File>,
    len: usize,
    _t: PhantomData<T>,
}

impl<T: Pod> ColumnWriter<T> {
    /// Creates `dir/name.col`.
    pub fn create(dir: &Path, name: &str) -> Result<Self, ColumnError> {
        let path = column_path(dir, name);
        // Read access too: the file is memory-mapped once written.
        let file = scratch_file(&path).map_err(|source| ColumnError::Io {
            path: path.clone(),
            source,
        })?;
        Ok(Self {
            path,
            out: BufWriter::with_capacity(1 << 20, file),
            len: 0,
            _t: PhantomData,
        })
    }

    pub fn push(&mut self, value: T) -> Result<(), ColumnError> {
        self.out
            .write_all(bytemuck::bytes_of(&value))
            .map_err(|source| ColumnError::Io {
                path: self.path.clone(),
                source,
            })?;
        self.len += 1;
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Flushes and maps the file read-only.
    #[allow(unsafe_code)]
    pub fn finish(self) -> Result<Column<T>, ColumnError> {
        let path = self.path;
        let io = |source| ColumnError::Io {
            path: path.clone(),
            source,
        };
        // No sync: a scratch column is read back through the page cache and deleted with the
        // import; forcing it to disk made every column's writer wait for the device.
        let file = self.out.into_inner().map_err(|e| io(e.into_error()))?;
        let map = if self.len == 0 {
            None
        } else {
            // SAFETY: the file is private to this import's scratch directory and is never
            // written again after this point.
            Some(unsafe { memmap2::Mmap::map(&file) }.map_err(io)?)
        };
        Ok(Column {
            map,
            len: self.len,
            _t: PhantomData,
        })
    }
}

/// A writable, memory-mapped array of `len` zeroed `T`s in a scratch file, for outputs written
/// in random order (e.g. one normal per point, computed region by region).
pub struct ColumnMut<T: Pod> {
    path: PathBuf,
    map: Option<memmap2::MmapMut>,
    len: usize,
    _t: PhantomData<T>,
}

impl<T: Pod> std::fmt::Debug for ColumnMut<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ColumnMut").field("len", &self.len).finish()
    }
}

/// Where the column `name` of a scratch directory lives.
pub fn column_path(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}.col"))
}

/// Deletes the column `name` of a scratch directory once nothing maps it any more: its pages
/// not yet written back are discarded and its memory is free for what comes next, instead of
/// lingering until the whole scratch directory goes.
pub fn remove_column(dir: &Path, name: &str) {
    let _ = std::fs::remove_file(column_path(dir, name));
}

/// Opens a scratch file for reading and writing, created or emptied.
pub fn scratch_file(path: &Path) -> std::io::Result<File> {
    File::options()
        .create(true)
        .truncate(true)
        .read(true)
        .write(true)
        .open(path)
}

impl<T: Pod> ColumnMut<T> {
    /// A sparse scratch file of `len` zeroed elements, mapped. Not allocated up front: at 4 GiB a
    /// `fallocate`d mapping took 9.4 s to fill on these machines against 2.1 s for a sparse
    /// one (unwritten extents converted page by page at writeback), though at 1 GiB they were
    /// even.
    pub fn create(dir: &Path, name: &str, len: usize) -> Result<Self, ColumnError> {
        let path = column_path(dir, name);
        let io = |source| ColumnError::Io {
            path: path.clone(),
            source,
        };
        let file = scratch_file(&path).map_err(io)?;
        file.set_len((len * std::mem::size_of::<T>()) as u64)
            .map_err(io)?;
        Self::map_written(file, &path, len)
    }

    /// Maps, writable, `len` elements of a scratch file at least that long. One written whole
    /// already (e.g. with `pwrite`) has its pages in the page cache, so writes through the
    /// mapping fault no holes in.
    #[allow(unsafe_code)]
    pub fn map_written(file: File, path: &Path, len: usize) -> Result<Self, ColumnError> {
        let io = |source| ColumnError::Io {
            path: path.to_owned(),
            source,
        };
        let bytes = (len * std::mem::size_of::<T>()) as u64;
        if file.metadata().map_err(io)?.len() < bytes {
            return Err(io(std::io::Error::other(
                "scratch file shorter than its records",
            )));
        }
        let map = if len == 0 {
            None
        } else {
            // SAFETY: the file is private to this import's scratch directory.
            Some(unsafe { memmap2::MmapMut::map_mut(&file) }.map_err(io)?)
        };
        Ok(Self {
            path: path.to_owned(),
            map,
            len,
            _t: PhantomData,
        })
    }

    /// Flushes and turns the mapping read-only.
    pub fn finish(self) -> Result<Column<T>, ColumnError> {
        let path = self.path;
        let map = match self.map {
            Some(m) => Some(m.make_read_only().map_err(|source| ColumnError::Io {
                path: path.clone(),
                source,
            })?),
            None => None,
        };
        Ok(Column {
            map,
            len: self.len,
            _t: PhantomData,
        })
    }
}

impl<T: Pod> std::ops::Deref for ColumnMut<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        match &self.map {
            Some(m) => &bytemuck::cast_slice(&m[..])[..self.len],
            None => &[],
        }
    }
}

impl<T: Pod> std::ops::DerefMut for ColumnMut<T> {
    fn deref_mut(&mut self) -> &mut [T] {
        match &mut self.map {
            Some(m) => &mut bytemuck::cast_slice_mut(&mut m[..])[..self.len],
            None => &mut [],
        }
    }
}

/// A read-only, memory-mapped array of `T`.
pub struct Column<T: Pod> {
    map: Option<memmap2::Mmap>,
    len: usize,
    _t: PhantomData<T>,
}

impl<T: Pod> std::fmt::Debug for Column<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Column").field("len", &self.len).finish()
    }
}

impl<T: Pod> Column<T> {
    /// Maps `len` records of a scratch file that was written in place (e.g. sorted bucket by
    /// bucket) and is never written again.
    #[allow(unsafe_code)]
    pub fn map_file(file: File, path: &Path, len: usize) -> Result<Self, ColumnError> {
        let map = if len == 0 {
            None
        } else {
            // SAFETY: the file is private to this import's scratch directory and is never
            // written again after this point.
            Some(
                unsafe { memmap2::Mmap::map(&file) }.map_err(|source| ColumnError::Io {
                    path: path.to_owned(),
                    source,
                })?,
            )
        };
        if let Some(m) = &map
            && m.len() < len * std::mem::size_of::<T>()
        {
            return Err(ColumnError::Io {
                path: path.to_owned(),
                source: std::io::Error::other("scratch file shorter than its records"),
            });
        }
        Ok(Column {
            map,
            len,
            _t: PhantomData,
        })
    }

    /// Writes `values` into a fresh column (tests and small inputs).
    pub fn from_slice(dir: &Path, name: &str, values: &[T]) -> Result<Self, ColumnError> {
        let mut w = ColumnWriter::create(dir, name)?;
        for v in values {
            w.push(*v)?;
        }
        w.finish()
    }
}

impl<T: Pod> std::ops::Deref for Column<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        match &self.map {
            // Mappings are page aligned, so any Pod element type is aligned.
            Some(m) => &bytemuck::cast_slice(&m[..])[..self.len],
            None => &[],
        }
    }
}

impl Source {
    /// Number of input primitives (triangles, points or grid samples).
    pub fn primitive_count(&self) -> u64 {
        match self {
            Source::Mesh(m) => m.triangles.len() as u64,
            Source::Points(p) => p.positions.len() as u64,
            Source::Volume(v) => v.values.len() as u64,
        }
    }

    /// Short human description, e.g. "mesh: 69451 triangles, 35947 vertices".
    pub fn describe(&self) -> String {
        match self {
            Source::Mesh(m) => format!(
                "mesh: {} triangles, {} vertices{}{}",
                m.triangles.len(),
                m.positions.len(),
                if m.normals.is_some() { ", normals" } else { "" },
                if m.colors.is_some() { ", colour" } else { "" }
            ),
            Source::Points(p) => format!(
                "points: {}{}{}",
                p.positions.len(),
                if p.normals.is_some() { ", normals" } else { "" },
                if p.colors.is_some() { ", colour" } else { "" }
            ),
            Source::Volume(v) => format!(
                "volume: {}x{}x{} samples, spacing {:?}",
                v.dims[0], v.dims[1], v.dims[2], v.spacing
            ),
        }
    }
}
