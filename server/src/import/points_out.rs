//! Where point importers write: one set of point columns that any number of files append to, so
//! a tiled set becomes one [`PointSource`] exactly as one file holding the same points would.
//!
//! Colour is kept at 16 bits until the end: LAS writers often store 8-bit values in the 16-bit
//! fields, and whether they did is decided over *every* LAS point of the set (largest channel
//! ≤ 255 → used as they are, else shifted down by 8), so splitting a file into tiles cannot
//! change its colours. PLY colour is 8-bit and kept as it is. A channel (colour, normals) is kept
//! only when every file has it; otherwise it is dropped with a warning.

use std::path::Path;

use rayon::prelude::*;

use super::{ImportError, names, push, writer};
use crate::octree::MAX_PRIMITIVES;
use crate::source::{Column, ColumnMut, ColumnWriter, PointSource, Source, remove_column};

/// Scratch name of the 16-bit colour column, converted to 8 bits at the end.
const RGB16_COLUMN: &str = "src_rgb16";

/// How the colour of a run of points was stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ColourDepth {
    /// LAS 16-bit fields: 8 or 16 bits decided over all LAS points of the set.
    Las,
    /// Already 8-bit (PLY).
    Eight,
}

/// One file's run of points: where it ends and how its colour was stored.
#[derive(Debug)]
struct Run {
    end: u64,
    depth: ColourDepth,
}

/// Point columns being written, for one file or a whole tile set.
#[derive(Debug)]
pub struct PointSetWriter<'a> {
    /// Names the set in errors that concern no single file (the first file, or the set).
    label: String,
    scratch: &'a Path,
    positions: ColumnWriter<[f64; 3]>,
    rgb16: Option<ColumnWriter<[u16; 3]>>,
    normals: Option<ColumnWriter<[f32; 3]>>,
    /// First file without colour / without normals (for the warning).
    colourless: Option<String>,
    normal_less: Option<String>,
    las_max_channel: u16,
    runs: Vec<Run>,
    files: usize,
}

impl<'a> PointSetWriter<'a> {
    /// Columns under `scratch`; `label` names the set in errors about no single file.
    pub fn new(label: &str, scratch: &'a Path) -> Result<Self, ImportError> {
        Ok(Self {
            label: label.to_owned(),
            scratch,
            positions: writer(label, scratch, names::POSITIONS)?,
            rgb16: Some(writer(label, scratch, RGB16_COLUMN)?),
            normals: None,
            colourless: None,
            normal_less: None,
            las_max_channel: 0,
            runs: Vec::new(),
            files: 0,
        })
    }

    /// Points written so far.
    pub fn len(&self) -> u64 {
        self.positions.len() as u64
    }

    /// Whether no point was written.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Starts the points of a file: says which channels it has. Call once per file, before its
    /// points.
    pub fn begin_file(
        &mut self,
        file: &str,
        has_colour: bool,
        has_normals: bool,
    ) -> Result<(), ImportError> {
        let first = self.files == 0;
        self.files += 1;
        if !has_colour && self.rgb16.take().is_some() {
            self.colourless = Some(file.to_owned());
            remove_column(self.scratch, RGB16_COLUMN);
        }
        if first && has_normals {
            self.normals = Some(writer(file, self.scratch, names::NORMALS)?);
        } else if !has_normals && self.normals.take().is_some() {
            remove_column(self.scratch, names::NORMALS);
        }
        if !has_normals && !first && self.normal_less.is_none() {
            self.normal_less = Some(file.to_owned());
        }
        Ok(())
    }

    /// Appends a point of `file`; the coordinates must be finite (checked by the caller, which
    /// knows the record's place).
    pub fn push_position(&mut self, file: &str, p: [f64; 3]) -> Result<(), ImportError> {
        if self.len() >= MAX_PRIMITIVES {
            return Err(ImportError::TooManyPrimitives {
                file: file.to_owned(),
                what: "points",
                count: self.len() + 1,
                limit: MAX_PRIMITIVES,
            });
        }
        push(file, &mut self.positions, p)
    }

    /// Appends the 16-bit LAS colour of the next point of `file` (when colour is still kept).
    pub fn push_las_colour(&mut self, file: &str, rgb: [u16; 3]) -> Result<(), ImportError> {
        if let Some(w) = &mut self.rgb16 {
            self.las_max_channel = self.las_max_channel.max(rgb[0]).max(rgb[1]).max(rgb[2]);
            push(file, w, rgb)?;
        }
        Ok(())
    }

    /// Whether colour is still being kept (every file so far had it).
    pub fn keeps_colour(&self) -> bool {
        self.rgb16.is_some()
    }

    /// Ends the points of a LAS file.
    pub fn end_las_file(&mut self) {
        self.runs.push(Run {
            end: self.len(),
            depth: ColourDepth::Las,
        });
    }

    /// Appends every point of an already imported point source (a PLY tile) as one file.
    pub fn append_source(&mut self, file: &str, points: &PointSource) -> Result<(), ImportError> {
        self.begin_file(file, points.colors.is_some(), points.normals.is_some())?;
        for &p in points.positions.iter() {
            self.push_position(file, p)?;
        }
        if let (Some(w), Some(c)) = (&mut self.rgb16, &points.colors) {
            for &rgb in c.iter() {
                push(file, w, rgb.map(u16::from))?;
            }
        }
        if let (Some(w), Some(n)) = (&mut self.normals, &points.normals) {
            for &v in n.iter() {
                push(file, w, v)?;
            }
        }
        self.runs.push(Run {
            end: self.len(),
            depth: ColourDepth::Eight,
        });
        Ok(())
    }

    /// Maps the columns: colour converted to 8 bits, channels some file lacked dropped.
    pub fn finish(self) -> Result<Source, ImportError> {
        let label = self.label.as_str();
        let col = |e| ImportError::column(label, e);
        if let Some(f) = &self.colourless
            && self.files > 1
        {
            tracing::warn!(file = %f, "a tile has no colour: the scene is imported without colour");
        }
        if let Some(f) = &self.normal_less {
            tracing::warn!(file = %f, "a tile has no normals: normals are estimated for every point");
        }
        let positions = self.positions.finish().map_err(col)?;
        let normals = match self.normals {
            Some(w) => Some(w.finish().map_err(col)?),
            None => None,
        };
        let colors = match self.rgb16 {
            None => None,
            Some(w) => Some(to_8bit(
                label,
                self.scratch,
                w.finish().map_err(col)?,
                &self.runs,
                self.las_max_channel,
            )?),
        };
        Ok(Source::Points(PointSource {
            positions,
            colors,
            normals,
        }))
    }
}

/// Converts the 16-bit colour column to 8 bits run by run and removes it.
fn to_8bit(
    label: &str,
    scratch: &Path,
    rgb16: Column<[u16; 3]>,
    runs: &[Run],
    las_max_channel: u16,
) -> Result<Column<[u8; 3]>, ImportError> {
    let las_shift = if is_8bit(las_max_channel) { 0 } else { 8 };
    tracing::debug!(
        max_channel = las_max_channel,
        "LAS colour is {}",
        if las_shift == 0 {
            "8-bit values in 16-bit fields"
        } else {
            "true 16-bit"
        }
    );
    // Converted on every core into a mapped column (a serial pass over every point between
    // reading and sorting): each run's part is cut into chunks written independently.
    let mut out = ColumnMut::<[u8; 3]>::create(scratch, names::COLORS, rgb16.len())
        .map_err(|e| ImportError::column(label, e))?;
    let mut parts = Vec::new();
    let mut rest: &mut [[u8; 3]] = &mut out;
    let mut start = 0usize;
    for run in runs {
        let shift = match run.depth {
            ColourDepth::Las => las_shift,
            ColourDepth::Eight => 0,
        };
        let end = run.end as usize;
        let (part, tail) = std::mem::take(&mut rest).split_at_mut(end - start);
        parts.push((start, part, shift));
        rest = tail;
        start = end;
    }
    const CHUNK: usize = 1 << 16;
    parts.into_par_iter().for_each(|(start, part, shift)| {
        part.par_chunks_mut(CHUNK)
            .enumerate()
            .for_each(|(k, chunk)| {
                let from = start + k * CHUNK;
                let source = &rgb16[from..from + chunk.len()];
                for (o, c) in chunk.iter_mut().zip(source) {
                    *o = c.map(|v| (v >> shift) as u8);
                }
            });
    });
    drop(rgb16);
    remove_column(scratch, RGB16_COLUMN);
    out.finish().map_err(|e| ImportError::column(label, e))
}

/// Whether a LAS colour column with this largest channel value holds 8-bit values.
pub(crate) fn is_8bit(max_channel: u16) -> bool {
    max_channel <= 255
}

#[cfg(test)]
mod tests {
    use super::*;

    fn colours(s: &Source) -> Vec<[u8; 3]> {
        match s {
            Source::Points(p) => p.colors.as_ref().expect("colour kept").to_vec(),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn colour_runs_are_converted_by_their_own_depth_across_chunks() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = PointSetWriter::new("set", dir.path()).unwrap();
        // A true 16-bit LAS run, longer than a conversion chunk, then an 8-bit (PLY) run, then
        // LAS again.
        let las = |i: u64| [(i * 37 % 65536) as u16, 65535, (i % 300) as u16 * 200];
        let n1 = (1 << 16) + 123;
        w.begin_file("a.las", true, false).unwrap();
        for i in 0..n1 {
            w.push_position("a.las", [i as f64, 0.0, 0.0]).unwrap();
            w.push_las_colour("a.las", las(i)).unwrap();
        }
        w.end_las_file();
        let ply_dir = tempfile::tempdir().unwrap();
        let ply: Vec<[u8; 3]> = (0..1000u32).map(|i| [i as u8, 7, 255]).collect();
        let positions: Vec<[f64; 3]> = (0..1000).map(|i| [f64::from(i), 1.0, 0.0]).collect();
        let source = PointSource {
            positions: Column::from_slice(ply_dir.path(), "p", &positions).unwrap(),
            colors: Some(Column::from_slice(ply_dir.path(), "c", &ply).unwrap()),
            normals: None,
        };
        w.append_source("b.ply", &source).unwrap();
        w.begin_file("c.las", true, false).unwrap();
        for i in 0..10 {
            w.push_position("c.las", [0.0, 0.0, i as f64]).unwrap();
            w.push_las_colour("c.las", las(i)).unwrap();
        }
        w.end_las_file();
        let got = colours(&w.finish().unwrap());
        let mut want: Vec<[u8; 3]> = (0..n1).map(|i| las(i).map(|v| (v >> 8) as u8)).collect();
        want.extend(&ply);
        want.extend((0..10).map(|i| las(i).map(|v| (v >> 8) as u8)));
        assert_eq!(got, want);
    }

    #[test]
    fn eight_bit_values_in_las_fields_are_kept_as_they_are() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = PointSetWriter::new("set", dir.path()).unwrap();
        w.begin_file("a.las", true, false).unwrap();
        for i in 0..300u16 {
            w.push_position("a.las", [f64::from(i), 0.0, 0.0]).unwrap();
            w.push_las_colour("a.las", [i % 256, 255, 0]).unwrap();
        }
        w.end_las_file();
        let got = colours(&w.finish().unwrap());
        let want: Vec<[u8; 3]> = (0..300u16).map(|i| [(i % 256) as u8, 255, 0]).collect();
        assert_eq!(got, want);
    }
}
