//! RGBA8 frames: what the renderers produce, what runs save as PNG, and the comparisons that
//! reports and tests make between a frame and a reference (RMSE, share of changed pixels,
//! coverage holes).
//!
//! Alpha 0 means "the ray hit nothing", so coverage questions are answered from alpha.

use std::path::{Path, PathBuf};

/// Why an image operation failed.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The PNG could not be encoded or written.
    #[error("writing PNG {path}: {source}")]
    Save {
        /// The file.
        path: PathBuf,
        /// What the encoder or the file system said.
        source: ::image::ImageError,
    },
    /// The PNG could not be read or decoded.
    #[error("reading PNG {path}: {source}")]
    Load {
        /// The file.
        path: PathBuf,
        /// What the decoder or the file system said.
        source: ::image::ImageError,
    },
    /// Two images compared have different sizes.
    #[error("image sizes differ: {a:?} vs {b:?}")]
    SizeMismatch {
        /// Width and height of the first.
        a: (u32, u32),
        /// Width and height of the second.
        b: (u32, u32),
    },
}

/// A `width × height` RGBA8 image, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// `width · height · 4` bytes.
    pub rgba: Vec<u8>,
}

impl Image {
    /// A fully transparent image.
    ///
    /// # Panics
    /// If `width · height · 4` bytes do not fit in memory addressing (a programming error; the
    /// cameras cap frames at 16384²).
    pub fn new(width: u32, height: u32) -> Image {
        let len = (width as usize)
            .checked_mul(height as usize)
            .and_then(|n| n.checked_mul(4))
            .expect("image size overflows usize");
        Image {
            width,
            height,
            rgba: vec![0; len],
        }
    }

    fn offset(&self, x: u32, y: u32) -> Option<usize> {
        (x < self.width && y < self.height)
            .then(|| (y as usize * self.width as usize + x as usize) * 4)
    }

    /// The pixel at `(x, y)`, `None` outside the image.
    pub fn get(&self, x: u32, y: u32) -> Option<[u8; 4]> {
        let o = self.offset(x, y)?;
        let p = self.rgba.get(o..o + 4)?;
        Some([p[0], p[1], p[2], p[3]])
    }

    /// Sets the pixel at `(x, y)`; returns `false` (and changes nothing) outside the image.
    pub fn put(&mut self, x: u32, y: u32, rgba: [u8; 4]) -> bool {
        match self.offset(x, y).and_then(|o| self.rgba.get_mut(o..o + 4)) {
            Some(p) => {
                p.copy_from_slice(&rgba);
                true
            }
            None => false,
        }
    }

    /// Writes the image as an RGBA PNG.
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<(), ImageError> {
        let path = path.as_ref();
        ::image::save_buffer_with_format(
            path,
            &self.rgba,
            self.width,
            self.height,
            ::image::ExtendedColorType::Rgba8,
            ::image::ImageFormat::Png,
        )
        .map_err(|source| ImageError::Save {
            path: path.to_owned(),
            source,
        })
    }

    /// Reads a PNG, converting any colour type to RGBA8.
    pub fn load_png(path: impl AsRef<Path>) -> Result<Image, ImageError> {
        let path = path.as_ref();
        let err = |source| ImageError::Load {
            path: path.to_owned(),
            source,
        };
        let img = ::image::ImageReader::open(path)
            .map_err(|e| err(::image::ImageError::IoError(e)))?
            .with_guessed_format()
            .map_err(|e| err(::image::ImageError::IoError(e)))?
            .decode()
            .map_err(err)?
            .into_rgba8();
        Ok(Image {
            width: img.width(),
            height: img.height(),
            rgba: img.into_raw(),
        })
    }

    fn same_size(&self, other: &Image) -> Result<(), ImageError> {
        if (self.width, self.height) == (other.width, other.height) {
            Ok(())
        } else {
            Err(ImageError::SizeMismatch {
                a: (self.width, self.height),
                b: (other.width, other.height),
            })
        }
    }

    /// Root-mean-square difference over the R, G and B values of all pixels, in 0..255 units
    /// (alpha is ignored: a miss is black). 0 for empty images.
    pub fn rmse(&self, other: &Image) -> Result<f64, ImageError> {
        self.same_size(other)?;
        let mut sum = 0u64;
        for (a, b) in self.rgba.chunks_exact(4).zip(other.rgba.chunks_exact(4)) {
            for c in 0..3 {
                let d = u64::from(a[c].abs_diff(b[c]));
                sum += d * d;
            }
        }
        let n = self.rgba.len() / 4 * 3;
        Ok(if n == 0 {
            0.0
        } else {
            (sum as f64 / n as f64).sqrt()
        })
    }

    /// Share (0..=1) of pixels whose RGBA differ at all; 1 when the sizes differ, 0 for two
    /// empty images.
    pub fn differing_share(&self, other: &Image) -> f64 {
        if self.same_size(other).is_err() {
            return 1.0;
        }
        let n = self.rgba.len() / 4;
        if n == 0 {
            return 0.0;
        }
        let differ = self
            .rgba
            .chunks_exact(4)
            .zip(other.rgba.chunks_exact(4))
            .filter(|(a, b)| a != b)
            .count();
        differ as f64 / n as f64
    }

    /// Pixels with alpha > 0 (a ray hit something).
    pub fn coverage(&self) -> u64 {
        self.rgba.chunks_exact(4).filter(|p| p[3] > 0).count() as u64
    }

    /// Pixels empty here (alpha 0) but covered in `reference`: holes. Sizes must match.
    pub fn uncovered_where_covered(&self, reference: &Image) -> Result<u64, ImageError> {
        self.same_size(reference)?;
        Ok(self
            .rgba
            .chunks_exact(4)
            .zip(reference.rgba.chunks_exact(4))
            .filter(|(a, r)| a[3] == 0 && r[3] > 0)
            .count() as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn get_put_and_metrics() {
        let mut a = Image::new(4, 3);
        assert_eq!(a.coverage(), 0);
        assert!(a.put(3, 2, [10, 20, 30, 255]));
        assert!(!a.put(4, 0, [1, 1, 1, 1]));
        assert_eq!(a.get(3, 2), Some([10, 20, 30, 255]));
        assert_eq!(a.get(0, 3), None);
        assert_eq!(a.coverage(), 1);
        let b = Image::new(4, 3);
        assert_eq!(b.uncovered_where_covered(&a).unwrap(), 1);
        assert_eq!(a.uncovered_where_covered(&b).unwrap(), 0);
        assert!((a.differing_share(&b) - 1.0 / 12.0).abs() < 1e-15);
        let expect = ((100.0 + 400.0 + 900.0) / 36.0f64).sqrt();
        assert!((a.rmse(&b).unwrap() - expect).abs() < 1e-12);
        assert_eq!(a.rmse(&a).unwrap(), 0.0);
        assert!(a.rmse(&Image::new(3, 4)).is_err());
        assert_eq!(a.differing_share(&Image::new(3, 4)), 1.0);
    }

    #[test]
    fn png_round_trip_and_named_errors() {
        let dir = std::env::temp_dir().join(format!("arbor-image-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut a = Image::new(5, 2);
        a.put(0, 0, [1, 2, 3, 4]);
        a.put(4, 1, [255, 0, 128, 255]);
        let p = dir.join("a.png");
        a.save_png(&p).unwrap();
        assert_eq!(Image::load_png(&p).unwrap(), a);
        let missing = dir.join("missing.png");
        let e = Image::load_png(&missing).unwrap_err();
        assert!(e.to_string().contains("missing.png"), "{e}");
        let junk = dir.join("junk.png");
        std::fs::write(&junk, b"not a png").unwrap();
        let e = Image::load_png(&junk).unwrap_err();
        assert!(e.to_string().contains("junk.png"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
