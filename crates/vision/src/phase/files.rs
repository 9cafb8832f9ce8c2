//! One camera's stack folder (a dataset's `pose-KKK/CAMERA`, docs/dataset.md) decoded to
//! files: `hexcal decode`.
//!
//! Takes a stack folder; gives, per projector p, its (u, v) maps as 32-bit float TIFF, the
//! validity mask, the lit image and the "what the projector sees" warp (Zhang–Huang) as PNG,
//! the ambient image as PNG, and `summary.json` with the valid fraction, the measured
//! modulation B_p and noise σ_I, and the predicted σ_φ and σ_u, σ_v.

use super::{DecodedStack, Decoder, FrameRef, NoiseModel, PhaseNoise, ProjectorMaps};
use hexcal_core::dataset::{DatasetError, StackReader};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Why a stack folder could not be decoded or written.
#[derive(Debug, thiserror::Error)]
pub enum DecodeFilesError {
    /// The stack folder is wrong (names the file, camera and frame).
    #[error(transparent)]
    Stack(#[from] DatasetError),
    /// The frames do not fit the sequence.
    #[error("{0}")]
    Decode(#[from] super::DecodeError),
    /// An output could not be written.
    #[error("{path}: {reason}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// Decode the stack in `dir` (frame by frame: one group of frames is held at a time).
pub fn decode_dir(dir: &Path) -> Result<DecodedStack, DecodeFilesError> {
    decode_stack(&StackReader::open(dir)?)
}

/// Decode an opened stack (e.g. one [`hexcal_core::dataset::Dataset::stack`] checked
/// against its dataset), frame by frame.
pub fn decode_stack(stack: &StackReader) -> Result<DecodedStack, DecodeFilesError> {
    let info = &stack.info;
    let mut decoder = Decoder::<u16>::new(
        &info.sequence,
        info.camera.clone(),
        info.width,
        info.height,
        stack.full_scale(),
    )?;
    for k in 0..info.sequence.frame_count() {
        let pixels = stack.frame(k)?;
        decoder.push_frame(
            k,
            FrameRef {
                width: info.width,
                height: info.height,
                pixels: &pixels,
            },
        )?;
    }
    Ok(decoder.finish()?)
}

/// One projector's figures in `summary.json`.
#[derive(Clone, Debug, Serialize)]
pub struct ProjectorSummary {
    /// Projector index in the sequence.
    pub projector: usize,
    /// Valid pixels / all pixels.
    pub valid_fraction: f64,
    /// Measured modulation, noise and the predicted phase and position noise.
    pub noise: PhaseNoise,
}

/// `summary.json` of a decoded stack.
#[derive(Clone, Debug, Serialize)]
pub struct DecodeSummary {
    /// Camera name.
    pub camera: String,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// The measured per-frame noise model σ_I²(A).
    pub noise: NoiseModel,
    /// Saturated pixels / all pixels.
    pub saturated_fraction: f64,
    /// Per projector.
    pub projectors: Vec<ProjectorSummary>,
    /// The stack check's verdict (docs/design.md §6b).
    pub verdict: super::check::StackVerdict,
}

impl DecodeSummary {
    /// The summary of `decoded`.
    pub fn new(decoded: &DecodedStack) -> DecodeSummary {
        let (w, h) = decoded.ambient.dimensions();
        let n = f64::from(w) * f64::from(h);
        DecodeSummary {
            camera: decoded.camera.clone(),
            width: w,
            height: h,
            noise: decoded.noise,
            saturated_fraction: decoded.saturated.count() as f64 / n,
            projectors: decoded
                .projectors
                .iter()
                .enumerate()
                .map(|(p, m)| ProjectorSummary {
                    projector: p,
                    valid_fraction: m.valid.count() as f64 / n,
                    noise: m.noise,
                })
                .collect(),
            verdict: decoded.verdict.clone(),
        }
    }
}

fn write_err(path: &Path) -> impl Fn(String) -> DecodeFilesError + '_ {
    move |reason| DecodeFilesError::Write {
        path: path.to_owned(),
        reason,
    }
}

fn write_tiff_f32(path: &Path, w: u32, h: u32, data: &[f32]) -> Result<(), DecodeFilesError> {
    let err = write_err(path);
    hexcal_core::atomic::write_encoded(
        path,
        |bytes| {
            tiff::encoder::TiffEncoder::new(bytes)
                .and_then(|mut enc| {
                    enc.write_image::<tiff::encoder::colortype::Gray32Float>(w, h, data)
                })
                .map_err(|e| err(e.to_string()))
        },
        |e| err(e.to_string()),
    )
}

fn write_png_gray(path: &Path, img: &image::GrayImage) -> Result<(), DecodeFilesError> {
    let err = write_err(path);
    hexcal_core::atomic::write_encoded(
        path,
        |bytes| {
            img.write_to(bytes, image::ImageFormat::Png)
                .map_err(|e| err(e.to_string()))
        },
        |e| err(e.to_string()),
    )
}

/// A DN image on an 8-bit scale (values scaled so `full_scale` is 255).
fn to_8bit(img: &hexcal_core::images::FloatImage, full_scale: f32) -> image::GrayImage {
    let s = 255.0 / full_scale;
    image::GrayImage::from_fn(img.width(), img.height(), |x, y| {
        image::Luma([(img.get_pixel(x, y).0[0] * s).round().clamp(0.0, 255.0) as u8])
    })
}

/// "What the projector sees" (Zhang–Huang): the camera's ambient + lit image moved to each
/// valid pixel's decoded (u, v) in the projector's raster (nearest projector pixel; holes
/// stay black).
pub fn projector_view(
    maps: &ProjectorMaps,
    image: &hexcal_core::images::FloatImage,
    width: u32,
    height: u32,
    full_scale: f32,
) -> image::GrayImage {
    let mut out = image::GrayImage::new(width, height);
    let s = 255.0 / full_scale;
    for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
        if !ok {
            continue;
        }
        let (u, v) = (maps.u.as_raw()[i].round(), maps.v.as_raw()[i].round());
        if u >= 0.0 && v >= 0.0 && (u as u32) < width && (v as u32) < height {
            let val = (image.as_raw()[i] * s).round().clamp(0.0, 255.0) as u8;
            out.put_pixel(u as u32, v as u32, image::Luma([val]));
        }
    }
    out
}

/// Decode the stack in `dir` and write everything to `out`; gives the files written and
/// the summary.
pub fn decode_to_files(
    dir: &Path,
    out: &Path,
) -> Result<(Vec<PathBuf>, DecodeSummary), DecodeFilesError> {
    let decoded = decode_dir(dir)?;
    write_decoded(dir, &decoded, out)
}

/// The files of [`decode_to_files`] for the stack in `dir` already decoded.
pub fn write_decoded(
    dir: &Path,
    decoded: &DecodedStack,
    out: &Path,
) -> Result<(Vec<PathBuf>, DecodeSummary), DecodeFilesError> {
    let stack = StackReader::open(dir)?;
    let full_scale = stack.full_scale();
    std::fs::create_dir_all(out).map_err(|e| write_err(out)(e.to_string()))?;
    let mut files = Vec::new();
    let (w, h) = decoded.ambient.dimensions();
    let path = out.join("ambient.png");
    write_png_gray(&path, &to_8bit(&decoded.ambient, full_scale))?;
    files.push(path);
    for (p, maps) in decoded.projectors.iter().enumerate() {
        let code = stack.info.sequence.projectors()[p];
        let name = |what: &str| out.join(format!("projector{p}-{what}"));
        for (what, img) in [("u.tiff", &maps.u), ("v.tiff", &maps.v)] {
            let path = name(what);
            write_tiff_f32(&path, w, h, img.as_raw())?;
            files.push(path);
        }
        let lit = maps.lit_image();
        for (what, img) in [
            ("valid.png", maps.valid.to_image()),
            ("lit.png", to_8bit(&lit, full_scale)),
            (
                "view.png",
                projector_view(maps, &lit, code.width, code.height, full_scale),
            ),
        ] {
            let path = name(what);
            write_png_gray(&path, &img)?;
            files.push(path);
        }
    }
    let summary = DecodeSummary::new(decoded);
    let path = out.join("summary.json");
    let text =
        serde_json::to_string_pretty(&summary).map_err(|e| write_err(&path)(e.to_string()))?;
    hexcal_core::atomic::write(&path, format!("{text}\n").as_bytes())
        .map_err(|e| write_err(&path)(e.to_string()))?;
    files.push(path);
    Ok((files, summary))
}
