//! Image loading: 8- or 16-bit, grey or colour PNG, JPEG, TIFF (and PNM) files into a
//! [`FloatImage`].
//!
//! Grey values keep the file's scale (0–255 for 8-bit, 0–65535 for 16-bit, as stored for
//! float files); colour becomes Rec. 709 luma (0.2126 R + 0.7152 G + 0.0722 B) on that same
//! scale; alpha is ignored.

use super::FloatImage;
use image::{DynamicImage, ImageDecoder, ImageReader};
use std::io::{BufRead, Seek};
use std::path::{Path, PathBuf};

/// An image that could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    /// Opening or decoding failed, or the image is beyond the limits.
    #[error("cannot read image {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        source: ImageDecodeError,
    },
}

/// Why image bytes could not be decoded.
#[derive(Debug, thiserror::Error)]
pub enum ImageDecodeError {
    /// The decoder's error (format, corrupt data, its allocation limit).
    #[error("{0}")]
    Image(#[from] image::ImageError),
    /// The header gives a size beyond [`crate::limits::image_size`].
    #[error("{0}")]
    Size(crate::invalid::Invalid),
}

/// Bytes a decoder may allocate: a 2²⁸-pixel image of 16-bit RGBA samples.
const MAX_DECODE_BYTES: u64 = 8 * crate::limits::MAX_IMAGE_PIXELS;

/// Decodes an image (format from its first bytes) whose header gives a size within
/// [`crate::limits::image_size`]; a larger one is refused before its pixels are allocated.
pub fn decode<R: BufRead + Seek>(reader: ImageReader<R>) -> Result<DynamicImage, ImageDecodeError> {
    let mut reader = reader
        .with_guessed_format()
        .map_err(image::ImageError::IoError)?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(crate::limits::MAX_IMAGE_SIDE);
    limits.max_image_height = Some(crate::limits::MAX_IMAGE_SIDE);
    limits.max_alloc = Some(MAX_DECODE_BYTES);
    reader.limits(limits);
    let decoder = reader.into_decoder()?;
    let (w, h) = decoder.dimensions();
    crate::limits::image_size(w, h).map_err(ImageDecodeError::Size)?;
    Ok(DynamicImage::from_decoder(decoder)?)
}

/// Reads an image file as grey levels on the file's own scale (see the module doc).
pub fn load_gray(path: &Path) -> Result<FloatImage, ImageIoError> {
    let read = |source| ImageIoError::Read {
        path: path.to_owned(),
        source,
    };
    let reader = ImageReader::open(path).map_err(|e| read(image::ImageError::IoError(e).into()))?;
    Ok(to_gray(&decode(reader).map_err(read)?))
}

/// Converts a decoded image to grey levels on its own scale (see the module doc).
pub fn to_gray(img: &DynamicImage) -> FloatImage {
    let (w, h) = (img.width(), img.height());
    let luma = |r: f32, g: f32, b: f32| 0.2126 * r + 0.7152 * g + 0.0722 * b;
    let data: Vec<f32> = match img {
        DynamicImage::ImageLuma8(i) => i.as_raw().iter().map(|&v| v as f32).collect(),
        DynamicImage::ImageLuma16(i) => i.as_raw().iter().map(|&v| v as f32).collect(),
        DynamicImage::ImageLumaA8(i) => i.pixels().map(|p| p.0[0] as f32).collect(),
        DynamicImage::ImageLumaA16(i) => i.pixels().map(|p| p.0[0] as f32).collect(),
        DynamicImage::ImageRgb8(i) => i
            .pixels()
            .map(|p| luma(p.0[0] as f32, p.0[1] as f32, p.0[2] as f32))
            .collect(),
        DynamicImage::ImageRgba8(i) => i
            .pixels()
            .map(|p| luma(p.0[0] as f32, p.0[1] as f32, p.0[2] as f32))
            .collect(),
        DynamicImage::ImageRgb16(i) => i
            .pixels()
            .map(|p| luma(p.0[0] as f32, p.0[1] as f32, p.0[2] as f32))
            .collect(),
        DynamicImage::ImageRgba16(i) => i
            .pixels()
            .map(|p| luma(p.0[0] as f32, p.0[1] as f32, p.0[2] as f32))
            .collect(),
        DynamicImage::ImageRgb32F(i) => i.pixels().map(|p| luma(p.0[0], p.0[1], p.0[2])).collect(),
        DynamicImage::ImageRgba32F(i) => i.pixels().map(|p| luma(p.0[0], p.0[1], p.0[2])).collect(),
        other => other
            .to_rgb32f()
            .pixels()
            .map(|p| luma(p.0[0], p.0[1], p.0[2]))
            .collect(),
    };
    FloatImage::from_raw(w, h, data).expect("one value per pixel")
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{ImageBuffer, Luma, Rgb};

    fn temp_path(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("hexcal-imageio-{}-{name}", std::process::id()))
    }

    #[test]
    fn reads_grey_and_colour_files_on_their_own_scale() {
        let g8 = ImageBuffer::from_fn(5, 3, |x, y| Luma([(x * 40 + y) as u8]));
        let g16 = ImageBuffer::from_fn(5, 3, |x, y| Luma([(x * 10_000 + y) as u16]));
        let rgb = ImageBuffer::from_fn(5, 3, |x, _| Rgb([(x * 50) as u8, 100u8, 0u8]));
        type Expected = Box<dyn Fn(u32, u32) -> f32>;
        let cases: Vec<(&str, DynamicImage, Expected)> = vec![
            (
                "g8.png",
                DynamicImage::ImageLuma8(g8),
                Box::new(|x, y| (x * 40 + y) as f32),
            ),
            (
                "g16.png",
                DynamicImage::ImageLuma16(g16.clone()),
                Box::new(|x, y| (x * 10_000 + y) as f32),
            ),
            (
                "g16.tiff",
                DynamicImage::ImageLuma16(g16),
                Box::new(|x, y| (x * 10_000 + y) as f32),
            ),
            (
                "rgb.png",
                DynamicImage::ImageRgb8(rgb),
                Box::new(|x, _| 0.2126 * (x * 50) as f32 + 0.7152 * 100.0),
            ),
        ];
        for (name, img, want) in cases {
            let path = temp_path(name);
            img.save(&path).expect("write test image");
            let got = load_gray(&path).expect("read back");
            std::fs::remove_file(&path).ok();
            assert_eq!(got.dimensions(), (5, 3));
            for (x, y, p) in got.enumerate_pixels() {
                assert!(
                    (p.0[0] - want(x, y)).abs() < 1e-3,
                    "{name} ({x},{y}): {} vs {}",
                    p.0[0],
                    want(x, y)
                );
            }
        }
    }

    #[test]
    fn errors_name_the_file() {
        let path = temp_path("missing.png");
        let err = load_gray(&path).unwrap_err().to_string();
        assert!(err.contains("missing.png"), "{err}");
        let bad = temp_path("bad.png");
        std::fs::write(&bad, b"not an image").unwrap();
        let err = load_gray(&bad).unwrap_err().to_string();
        std::fs::remove_file(&bad).ok();
        assert!(err.contains("bad.png"), "{err}");
    }
}
