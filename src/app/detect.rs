//! The `hexcal detect` stage on image files: circle detection ([`crate::detect`]) and grid
//! building ([`crate::grid`]) per image, as the serialisable records of the command's JSON
//! output, with an optional overlay PNG per image for a person to look at.
//!
//! Takes image paths (8- or 16-bit, grey or colour PNG/JPEG/TIFF, read by
//! [`crate::images`]) and a board; gives one [`ImageRecord`] per readable image, in input
//! order, and an error naming the file for each image that cannot be read. Pixel (0, 0) is
//! the centre of the top-left pixel (docs/design.md §2).

pub use overlay::draw_overlay;

mod overlay;

use crate::board::{Board, Side};
use crate::grid::{build, Grid, GridParams};
use crate::images::{load_gray, ImageIoError};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use {
    crate::detect::{detect, Circle, DetectParams},
    crate::images::FloatImage,
};

/// A failure on one image.
#[derive(Debug, thiserror::Error)]
pub enum DetectionError {
    /// The image could not be read.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// The overlay PNG could not be written.
    #[error("cannot write overlay {path}: {message}")]
    Overlay {
        /// The overlay file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// One detected circle in the JSON output.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CircleRecord {
    /// Subpixel centre x (px), 0 at the centre of the left pixel column.
    pub x: f64,
    /// Subpixel centre y (px), 0 at the centre of the top pixel row.
    pub y: f64,
    /// Geometric-mean radius √(a·b) of the fitted outline ellipse (px).
    pub radius: f64,
    /// Circleness at the detection peak (≤ 0.303 for a perfect disk).
    pub score: f64,
}

/// One labelled lattice point in the JSON output.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointRecord {
    /// Centre x (px), as in [`CircleRecord`].
    pub x: f64,
    /// Centre y (px).
    pub y: f64,
    /// Lattice q: in the side's board frame when `anchored`, else in an arbitrary lattice
    /// frame shared by the image's points.
    pub q: i32,
    /// Lattice r, as `q`.
    pub r: i32,
    /// The side seen, when markers fixed it.
    pub side: Option<Side>,
    /// Whether (q, r) and side are in that side's own board frame (docs/design.md §3).
    pub anchored: bool,
}

/// Everything found in one image: the JSON object of one input.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImageRecord {
    /// The image path as given.
    pub image: String,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Every detected circle, strongest first.
    pub circles: Vec<CircleRecord>,
    /// Every labelled circle.
    pub points: Vec<PointRecord>,
}

/// The JSON object of an input that could not be processed: its path and the error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FailedRecord {
    /// The image path as given.
    pub image: String,
    /// Why it failed (the message names the file).
    pub error: String,
}

/// Settings of detection and grid building.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Settings {
    /// Circle detection.
    pub detect: DetectParams,
    /// Grid building.
    pub grid: GridParams,
}

/// The detections and the grid of one image.
#[derive(Clone, Debug, PartialEq)]
pub struct Analysis {
    /// Detected circles, strongest first.
    pub circles: Vec<Circle>,
    /// The labelled grid built from them (its points index `circles`).
    pub grid: Grid,
}

/// Detect the circles of an image and build its grid.
pub fn analyse(image: &FloatImage, board: &Board, settings: &Settings) -> Analysis {
    let circles = detect(image, &settings.detect);
    let grid = build(image, &circles, board, &settings.grid);
    Analysis { circles, grid }
}

impl ImageRecord {
    /// The record of an analysed image named `image` of the given size.
    pub fn new(image: String, size: (u32, u32), analysis: &Analysis) -> ImageRecord {
        ImageRecord {
            image,
            width: size.0,
            height: size.1,
            circles: analysis
                .circles
                .iter()
                .map(|c| CircleRecord {
                    x: c.ellipse.center.x,
                    y: c.ellipse.center.y,
                    radius: c.ellipse.radius(),
                    score: c.score,
                })
                .collect(),
            points: analysis
                .grid
                .points
                .iter()
                .map(|p| PointRecord {
                    x: p.image.x,
                    y: p.image.y,
                    q: p.hex.q,
                    r: p.hex.r,
                    side: p.side,
                    anchored: p.anchored,
                })
                .collect(),
        }
    }
}

/// Read, analyse and (with `overlay_dir`) draw one image file; the overlay goes to
/// [`overlay_path`].
pub fn process(
    path: &Path,
    board: &Board,
    settings: &Settings,
    overlay_dir: Option<&Path>,
) -> Result<ImageRecord, DetectionError> {
    let image = load_gray(path)?;
    let analysis = analyse(&image, board, settings);
    if let Some(dir) = overlay_dir {
        let out = overlay_path(dir, path);
        write_png_atomic(&draw_overlay(&image, &analysis), &out)?;
    }
    Ok(ImageRecord::new(
        path.display().to_string(),
        image.dimensions(),
        &analysis,
    ))
}

/// Process every image in order; one failure does not stop the others. Overlays of inputs
/// with the same file stem overwrite each other: give them distinct names.
pub fn process_all(
    paths: &[PathBuf],
    board: &Board,
    settings: &Settings,
    overlay_dir: Option<&Path>,
) -> Vec<Result<ImageRecord, DetectionError>> {
    paths
        .iter()
        .map(|p| process(p, board, settings, overlay_dir))
        .collect()
}

/// `hexcal detect`: every image in turn with the board `board` (built-in name or board
/// file), overlays into `overlay` (created), the JSON written to `json` even when some
/// images fail; gives each image's result.
pub fn detect_files(
    board: &str,
    json: &Path,
    overlay: Option<&Path>,
    images: &[PathBuf],
) -> Result<Vec<Result<ImageRecord, DetectionError>>, super::AppError> {
    let board = Board::resolve(board)?;
    if let Some(dir) = overlay {
        std::fs::create_dir_all(dir).map_err(super::AppError::io(dir))?;
    }
    let results = process_all(images, &board, &Settings::default(), overlay);
    crate::atomic::write(json, to_json(images, &results).as_bytes())
        .map_err(super::AppError::io(json))?;
    Ok(results)
}

/// The command's JSON: an array with one object per input in order, an [`ImageRecord`] or,
/// for a failed input, a [`FailedRecord`].
pub fn to_json(paths: &[PathBuf], results: &[Result<ImageRecord, DetectionError>]) -> String {
    /// One array element, fields in schema order.
    #[derive(Serialize)]
    #[serde(untagged)]
    enum Entry<'a> {
        Done(&'a ImageRecord),
        Failed(FailedRecord),
    }
    let entries: Vec<Entry> = paths
        .iter()
        .zip(results)
        .map(|(path, r)| match r {
            Ok(rec) => Entry::Done(rec),
            Err(e) => Entry::Failed(FailedRecord {
                image: path.display().to_string(),
                error: e.to_string(),
            }),
        })
        .collect();
    serde_json::to_string_pretty(&entries).expect("records serialise")
}

/// The overlay file of an input: `DIR/STEM_overlay.png`.
pub fn overlay_path(dir: &Path, image: &Path) -> PathBuf {
    let stem = image
        .file_stem()
        .map_or_else(|| "image".into(), |s| s.to_string_lossy());
    dir.join(format!("{stem}_overlay.png"))
}

/// Write an RGB image as PNG through a temporary file beside `path` and a rename.
fn write_png_atomic(img: &image::RgbImage, path: &Path) -> Result<(), DetectionError> {
    let err = |message: String| DetectionError::Overlay {
        path: path.to_owned(),
        message,
    };
    crate::atomic::write_encoded(
        path,
        |bytes| {
            img.write_to(bytes, image::ImageFormat::Png)
                .map_err(|e| err(e.to_string()))
        },
        |e| err(e.to_string()),
    )
}
