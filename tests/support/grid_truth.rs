//! Ground truth for grid tests and the grid benchmark: the independent sample images
//! (shared/samples/detect) with their true ellipses standing in for the detector, and a
//! score of a grid against the truth.
#![allow(dead_code)] // Each including crate uses a different part.

use hexcal::board::{Hex, Side};
use hexcal::grid::Grid;
use nalgebra::Point2;
use serde::Deserialize;
use std::collections::HashMap;
use std::path::PathBuf;
use {
    hexcal::detect::Circle,
    hexcal::images::{Ellipse, FloatImage},
};

/// The six sample images.
pub const SAMPLES: [&str; 6] = [
    "g1_frontal_00",
    "g2_tilted_02",
    "g3_extreme_01",
    "g4_partial_04",
    "g5_back_05",
    "g6_occluded_01",
];

/// The part of a sample's ground-truth JSON the grid tests read.
#[derive(Deserialize)]
pub struct Truth {
    /// Side facing the camera.
    pub side: Side,
    /// All seven circles of the seen side's centre cell are whole in view.
    pub centre_visible: bool,
    /// Every whole circle.
    pub circles: Vec<TrueCircle>,
    /// Circles cut by the frame or an occluder, or too small: a label there is neither
    /// required nor wrong.
    pub partial: Vec<CutCircle>,
}

/// A circle of the truth that is not whole in view.
#[derive(Clone, Deserialize)]
pub struct CutCircle {
    /// Lattice position in the seen side's frame.
    pub q: i32,
    /// See `q`.
    pub r: i32,
    /// Centre of the imaged outline (px), when the whole outline is imaged.
    pub ellipse: Option<[f64; 2]>,
}

/// One whole circle of the truth.
#[derive(Clone, Deserialize)]
pub struct TrueCircle {
    /// Lattice position in the seen side's frame.
    pub q: i32,
    /// See `q`.
    pub r: i32,
    /// Centre of the imaged outline (px).
    pub ellipse: [f64; 2],
    /// Semi-axes (px), major first.
    pub axes: [f64; 2],
    /// Angle of the major axis from +x towards +y (degrees).
    pub angle_deg: f64,
    /// Whether it carries a marker ring.
    pub ringed: bool,
}

impl TrueCircle {
    /// Its lattice position.
    pub fn hex(&self) -> Hex {
        Hex::new(self.q, self.r)
    }
}

/// A sample image with its truth.
pub struct Sample {
    /// File stem.
    pub name: &'static str,
    /// The 8-bit image as linear floats.
    pub image: FloatImage,
    /// Its ground truth.
    pub truth: Truth,
}

/// The vendored samples folder (`tests/data/samples`, README there).
fn samples_dir() -> PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/samples")
}

/// Load one sample.
pub fn load(name: &'static str) -> Sample {
    let dir = samples_dir();
    let grey = image::open(dir.join(format!("{name}.png")))
        .unwrap_or_else(|e| panic!("{name}.png: {e}"))
        .into_luma8();
    let image = FloatImage::from_fn(grey.width(), grey.height(), |x, y| {
        image::Luma([f32::from(grey.get_pixel(x, y).0[0])])
    });
    let json = std::fs::read_to_string(dir.join(format!("{name}.json")))
        .unwrap_or_else(|e| panic!("{name}.json: {e}"));
    let truth = serde_json::from_str(&json).unwrap_or_else(|e| panic!("{name}.json: {e}"));
    Sample { name, image, truth }
}

/// The grey level (nearest pixel) at `s` times the ellipse's radius along parameter `t`.
fn level_at(image: &FloatImage, e: &Ellipse, s: f64, t: f64) -> Option<f32> {
    let (sa, ca) = e.angle.sin_cos();
    let (px, py) = (s * e.a * t.cos(), s * e.b * t.sin());
    let x = (e.center.x + px * ca - py * sa).round();
    let y = (e.center.y + px * sa + py * ca).round();
    (x >= 0.0 && y >= 0.0 && x < f64::from(image.width()) && y < f64::from(image.height()))
        .then(|| image.get_pixel(x as u32, y as u32).0[0])
}

/// A detection of `ellipse` as a detector would report it, levels measured in the image: the
/// foreground as the 90th percentile inside 0.9 R (white both inside and outside a marker
/// ring), the background as the median of the band 1.4–1.7 R (between the circle and its
/// lattice neighbours, which start at 2.33 R).
pub fn detection(image: &FloatImage, ellipse: Ellipse) -> Circle {
    let band = |s0: f64, s1: f64| {
        let mut v: Vec<f32> = (0..8)
            .flat_map(|i| (0..48).map(move |m| (i, m)))
            .filter_map(|(i, m)| {
                let s = s0 + (s1 - s0) * f64::from(i) / 7.0;
                level_at(
                    image,
                    &ellipse,
                    s,
                    std::f64::consts::TAU * f64::from(m) / 48.0,
                )
            })
            .collect();
        v.sort_by(f32::total_cmp);
        v
    };
    let (inside, outside) = (band(0.0, 0.9), band(1.4, 1.7));
    Circle {
        ellipse,
        score: 0.3,
        background: outside.get(outside.len() / 2).copied().unwrap_or(0.0),
        foreground: inside.get(inside.len() * 9 / 10).copied().unwrap_or(0.0),
        edge_rms: 0.0,
    }
}

/// The true ellipse of a circle.
pub fn true_ellipse(t: &TrueCircle) -> Ellipse {
    Ellipse {
        center: Point2::new(t.ellipse[0], t.ellipse[1]),
        a: t.axes[0],
        b: t.axes[1],
        angle: t.angle_deg.to_radians(),
    }
}

/// Detections of every true whole circle, in truth order.
pub fn true_detections(s: &Sample) -> Vec<Circle> {
    s.truth
        .circles
        .iter()
        .map(|t| detection(&s.image, true_ellipse(t)))
        .collect()
}

/// How a grid compares with the truth.
#[derive(Debug)]
pub struct Score {
    /// Points labelled on true circles.
    pub labelled: usize,
    /// Labelled true circles / true circles given to the builder.
    pub recall: f64,
    /// Anchored points whose (q, r, side) differ from the truth.
    pub wrong_anchored: usize,
    /// Points with a side that differs from the truth.
    pub wrong_side: usize,
    /// Labelled points that are false detections.
    pub stray: usize,
    /// Points that disagree with the one lattice transform (rotation and translation) that
    /// maps most labels onto the truth.
    pub inconsistent: usize,
    /// That transform's rotation (60° steps).
    pub rotation: usize,
    /// That transform's translation.
    pub translation: Hex,
}

/// Compare a grid with the truth: `truth_of[i]` is the true circle behind detection i (None
/// for false detections); `given` is the number of true circles among the detections.
pub fn score(grid: &Grid, truth: &Truth, truth_of: &[Option<usize>], given: usize) -> Score {
    let mut sc = Score {
        labelled: 0,
        recall: 0.0,
        wrong_anchored: 0,
        wrong_side: 0,
        stray: 0,
        inconsistent: 0,
        rotation: 0,
        translation: Hex::new(0, 0),
    };
    let mut pairs = Vec::new();
    for p in &grid.points {
        let Some(t) = truth_of[p.circle] else {
            sc.stray += 1;
            continue;
        };
        let true_hex = truth.circles[t].hex();
        if p.side.is_some_and(|s| s != truth.side) {
            sc.wrong_side += 1;
        }
        if p.anchored && (p.hex != true_hex || p.side != Some(truth.side)) {
            sc.wrong_anchored += 1;
        }
        pairs.push((p.hex, true_hex));
    }
    let mut votes: HashMap<(usize, Hex), usize> = HashMap::new();
    for &(label, t) in &pairs {
        for sigma in 0..6 {
            *votes.entry((sigma, t - label.rotate(sigma))).or_default() += 1;
        }
    }
    if let Some((&(rotation, translation), &n)) = votes.iter().max_by_key(|(_, &n)| n) {
        sc.inconsistent = pairs.len() - n;
        sc.rotation = rotation;
        sc.translation = translation;
    }
    sc.labelled = pairs.len();
    sc.recall = pairs.len() as f64 / given.max(1) as f64;
    sc
}
