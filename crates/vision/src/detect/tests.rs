//! Whole-detector tests: the independent sample images with exact ground truth
//! (`tests/data/samples`), and synthetic area-integrated patterns.

use super::synth::{add_noise, blur_psf, quantise8, render, Blob, BlobScene};
use super::*;
use crate::testdata::samples_dir;
use hexcal_core::images::load_gray;
use rand::{Rng, SeedableRng};

/// A ground-truth circle: exact image-ellipse centre and radius √(ab).
struct Truth {
    centre: Point2<f64>,
    radius: f64,
}

/// Detection figures of one image against its ground truth.
#[derive(Debug)]
struct Figures {
    /// Whole circles with radius ≥ the evaluation's minimum.
    whole: usize,
    /// Of those, found with the right size (radius within 20 %).
    found: usize,
    /// Found with the wrong size (e.g. a marker's inner disk taken for the circle).
    wrong_size: usize,
    /// RMS and largest centre error of the found ones (px).
    rms: f64,
    max: f64,
    /// Detections near no ground-truth circle, whole or partial (clutter, distractors).
    extra: usize,
}

/// Matches detections to ground truth: a detection belongs to a circle when its centre is
/// within half the circle's radius (neighbours are ≥ 3.33 radii apart).
fn score(det: &[Circle], truth: &[Truth], others: &[Point2<f64>], min_radius: f64) -> Figures {
    let mut f = Figures {
        whole: 0,
        found: 0,
        wrong_size: 0,
        rms: 0.0,
        max: 0.0,
        extra: 0,
    };
    let mut sq = 0.0;
    for t in truth.iter().filter(|t| t.radius >= min_radius) {
        f.whole += 1;
        match det
            .iter()
            .find(|d| (d.ellipse.center - t.centre).norm() < 0.5 * t.radius)
        {
            Some(d) if (d.ellipse.radius() / t.radius - 1.0).abs() < 0.2 => {
                f.found += 1;
                let e = (d.ellipse.center - t.centre).norm();
                sq += e * e;
                f.max = f.max.max(e);
            }
            Some(_) => f.wrong_size += 1,
            None => {}
        }
    }
    f.rms = (sq / f.found.max(1) as f64).sqrt();
    f.extra = det
        .iter()
        .filter(|d| {
            let c = d.ellipse.center;
            !truth.iter().any(|t| (t.centre - c).norm() < 0.5 * t.radius)
                && !others
                    .iter()
                    .any(|p| (p - c).norm() < 0.5 * d.ellipse.radius().max(3.0))
        })
        .count();
    f
}

/// Runs the detector on a sample and scores it; `others` are the partial circles.
fn evaluate_sample(name: &str, min_radius: f64) -> Figures {
    let dir = samples_dir();
    let img = load_gray(&dir.join(format!("{name}.png"))).expect("sample image");
    let text = std::fs::read_to_string(dir.join(format!("{name}.json"))).expect("sample json");
    let json: serde_json::Value = serde_json::from_str(&text).expect("json");
    let pt = |v: &serde_json::Value| Point2::new(v[0].as_f64().unwrap(), v[1].as_f64().unwrap());
    let truth: Vec<Truth> = json["circles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| Truth {
            centre: pt(&c["ellipse"]),
            radius: c["radius"].as_f64().unwrap(),
        })
        .collect();
    let partial: Vec<Point2<f64>> = json["partial"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| pt(&c["proj"]))
        .collect();
    let det = detect(&img, &DetectParams::default());
    let f = score(&det, &truth, &partial, min_radius);
    let all = score(&det, &truth, &partial, 0.0);
    eprintln!(
        "{name}: r ≥ {min_radius}: {}/{} found ({:.2} %), {} wrong size, centre RMS {:.4} px, max {:.4} px; \
         all radii: {}/{}; {} detections off the ground truth",
        f.found,
        f.whole,
        100.0 * f.found as f64 / f.whole as f64,
        f.wrong_size,
        f.rms,
        f.max,
        all.found,
        all.whole,
        f.extra
    );
    f
}

/// Asserts a sample's figures: recall of whole circles with radius ≥ 4 px, centre RMS
/// against the ground-truth ellipse centres, no marker taken for its inner disk, and few
/// detections off the board's circles (≤ 5 % of the circles).
fn check_sample(name: &str, min_recall: f64, max_rms: f64) {
    let f = evaluate_sample(name, 4.0);
    let recall = f.found as f64 / f.whole as f64;
    assert!(
        recall >= min_recall,
        "{name}: recall {recall:.4} < {min_recall}"
    );
    assert!(
        f.rms <= max_rms,
        "{name}: centre RMS {:.4} px > {max_rms}",
        f.rms
    );
    assert_eq!(f.wrong_size, 0, "{name}: circles found with the wrong size");
    assert!(
        f.extra * 20 <= f.whole,
        "{name}: {} detections off the board's circles",
        f.extra
    );
}

// Issue 3 acceptance: recall ≥ 99.5 % of whole circles with r ≥ 4 px at tilt ≤ 60°,
// ≥ 97 % at 60–75°; centre RMS ≤ 0.03 px at 2 DN noise and PSF σ ≤ 1 px. The samples'
// conditions (README, `render` in each JSON) decide which bound applies; where a sample is
// harder than the acceptance conditions the bound is the same number, stated as such.

/// Near-frontal, r 3.8–4.8 px, PSF σ 1.00, noise 1.2 DN: within the acceptance conditions.
#[test]
fn sample_g1_frontal() {
    check_sample("g1_frontal_00", 0.995, 0.03);
}

/// Tilt 30–60°, PSF σ 1.17 (above the acceptance's 1 px), noise 2.2 DN, vignetting.
#[test]
fn sample_g2_tilted() {
    check_sample("g2_tilted_02", 0.995, 0.03);
}

/// Tilt 60–75°, r 3.3–14 px, PSF σ 0.95, noise 1.5 DN, distractor disks: the 97 % bound.
#[test]
fn sample_g3_extreme() {
    check_sample("g3_extreme_01", 0.97, 0.03);
}

/// Board cut by the frame, PSF σ 0.87, noise 1.7 DN, vignetting.
#[test]
fn sample_g4_partial() {
    check_sample("g4_partial_04", 0.995, 0.03);
}

/// Back side, PSF σ 0.84, noise 1.9 DN, distractors.
#[test]
fn sample_g5_back() {
    check_sample("g5_back_05", 0.995, 0.03);
}

/// Harder than the acceptance: PSF σ 1.32, noise 3.3 DN, gamma 0.85, an occluder, strong
/// distortion. Same bounds, stated honestly as exceeding the acceptance conditions.
#[test]
fn sample_g6_occluded() {
    check_sample("g6_occluded_01", 0.995, 0.03);
}

/// A synthetic sheet of ellipses of geometric-mean radius `r`, tilts 0–60° (b/a = cos θ),
/// random orientation and subpixel position, every third one ringed; levels 30 / 200.
fn ellipse_sheet(r: f64, rng: &mut rand::rngs::StdRng) -> BlobScene {
    let (cols, rows) = (5, 4);
    // Pitch ≥ 10/3 of the largest semi-axis (a = r/√cos 60° = 1.41 r), as on the board.
    let pitch = (3.4 * 1.42 * r).max(24.0);
    let mut blobs = Vec::new();
    for i in 0..rows {
        for j in 0..cols {
            let cos_t = rng.random_range(60f64.to_radians().cos()..=1.0);
            let centre = Point2::new(
                pitch * (j as f64 + 0.75) + rng.random_range(-0.5..0.5),
                pitch * (i as f64 + 0.75) + rng.random_range(-0.5..0.5),
            );
            let e = Ellipse {
                center: centre,
                a: r / cos_t.sqrt(),
                b: r * cos_t.sqrt(),
                angle: rng.random_range(0.0..std::f64::consts::PI),
            };
            blobs.push(Blob {
                ellipse: e,
                ringed: (i * cols + j) % 3 == 0,
            });
        }
    }
    let (w, h) = (
        (pitch * (cols as f64 + 0.5)) as u32,
        (pitch * (rows as f64 + 0.5)) as u32,
    );
    BlobScene {
        width: w,
        height: h,
        background: 30.0,
        foreground: 200.0,
        blobs,
    }
}

/// Renders a scene as an 8-bit camera would: area-integrated, Gaussian PSF, noise, rounding.
fn camera_image(scene: &BlobScene, psf: f64, noise: f32, seed: u64) -> FloatImage {
    let mut img = blur_psf(&render(scene), psf);
    add_noise(&mut img, noise, seed);
    quantise8(&mut img);
    img
}

/// Centre accuracy on area-integrated ellipses, r 4–40 px, tilt ≤ 60°, a third of them
/// ringed, PSF σ 0.8–1 px, 2 DN noise, 8-bit: every circle found, with the outer ellipse's
/// size, and centre RMS ≤ 0.03 px against the exact ellipse centre.
///
/// Noise budget: an edge of contrast h = 170 DN blurred to σ_t = √(σ_psf² + 1/12) ≤ 1.05 px
/// has slope h/(√(2π)·σ_t) ≥ 65 DN/px, so 2 DN (+0.3 DN rounding) moves an edge point by
/// ≲ 0.035 px; over N ≈ min(90, 2πr) independent points the centre moves by
/// 0.035·√(2/N) ≲ 0.01 px per axis at r = 4. The acceptance bound 0.03 px is thus ≥ 2×
/// what noise explains; a systematic error (ring edges, sampling) would break it.
#[test]
fn synthetic_centres_and_outer_ellipses() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    for (k, r) in [4.0, 5.0, 6.5, 8.0, 11.0, 15.0, 20.0, 28.0, 40.0]
        .into_iter()
        .enumerate()
    {
        let psf = 0.8 + 0.2 * (k % 2) as f64;
        let scene = ellipse_sheet(r, &mut rng);
        let img = camera_image(&scene, psf, 2.0, 100 + k as u64);
        let det = detect(&img, &DetectParams::default());
        let mut sq = 0.0;
        for blob in &scene.blobs {
            let e = &blob.ellipse;
            let d = det
                .iter()
                .find(|d| (d.ellipse.center - e.center).norm() < 0.5 * r)
                .unwrap_or_else(|| {
                    panic!(
                        "r {r}: ellipse at {:?} (ringed {}) not found",
                        e.center, blob.ringed
                    )
                });
            // The outer ellipse, not a marker's inner disk (0.45 R): a crossing of any level
            // between 10 % and 90 % of a blurred edge lies within 1.3 σ_psf of the outline
            // (a marker's dimmed annulus lowers the level), while the inner disk is
            // ≥ 0.55 b ≥ 1.6 px inside it here.
            let tol = 1.3 * psf + 0.1;
            assert!(
                (d.ellipse.a - e.a).abs() < tol && (d.ellipse.b - e.b).abs() < tol,
                "r {r}: axes {:.3}×{:.3} vs {:.3}×{:.3} (ringed {})",
                d.ellipse.a,
                d.ellipse.b,
                e.a,
                e.b,
                blob.ringed
            );
            sq += (d.ellipse.center - e.center).norm_squared();
        }
        let rms = (sq / scene.blobs.len() as f64).sqrt();
        eprintln!(
            "r {r:4.1} px, PSF {psf}: centre RMS {rms:.4} px over {} ellipses",
            scene.blobs.len()
        );
        assert!(rms <= 0.03, "r {r}: centre RMS {rms:.4} px");
        let extra = det
            .iter()
            .filter(|d| {
                !scene
                    .blobs
                    .iter()
                    .any(|b| (b.ellipse.center - d.ellipse.center).norm() < 0.5 * r)
            })
            .count();
        assert_eq!(
            extra, 0,
            "r {r}: detections that are no ellipse of the scene"
        );
    }
}

/// Clutter without circles — bars, squares, triangles, single-direction gratings — on a
/// textured background: outlines that are not ellipses fail the edge-fit test, so at most
/// a few detections are allowed (the grid stage rejects what is not on a lattice).
#[test]
fn clutter_gives_few_detections() {
    let (w, h) = (800u32, 600u32);
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    // Shapes as half-plane sets in a rotated frame: (centre, angle, half sizes, kind, level).
    struct Shape {
        c: (f64, f64),
        angle: f64,
        half: (f64, f64),
        kind: u8,
        level: f32,
        period: f64,
    }
    let shapes: Vec<Shape> = (0..40)
        .map(|_| Shape {
            c: (
                rng.random_range(0.0..w as f64),
                rng.random_range(0.0..h as f64),
            ),
            angle: rng.random_range(0.0..std::f64::consts::PI),
            half: (rng.random_range(3.0..60.0), rng.random_range(2.0..60.0)),
            kind: rng.random_range(0..3),
            level: rng.random_range(40.0..220.0),
            period: rng.random_range(5.0..20.0),
        })
        .collect();
    let value = |x: f64, y: f64| -> f32 {
        let mut v = 30.0 + 10.0 * ((x * 0.013).sin() * (y * 0.017).cos()) as f32;
        for s in &shapes {
            let (dx, dy) = (x - s.c.0, y - s.c.1);
            let (sn, cs) = s.angle.sin_cos();
            let (u, q) = (cs * dx + sn * dy, -sn * dx + cs * dy);
            let inside = match s.kind {
                0 => u.abs() <= s.half.0 && q.abs() <= s.half.1, // bar or square
                1 => {
                    q >= -s.half.1
                        && q <= s.half.1
                        && u.abs() <= s.half.0 * (s.half.1 - q) / (2.0 * s.half.1)
                } // triangle
                _ => {
                    u.abs() <= s.half.0
                        && q.abs() <= s.half.1
                        && (u / s.period).rem_euclid(1.0) < 0.5
                } // grating
            };
            if inside {
                v = s.level;
            }
        }
        v
    };
    let mut img = FloatImage::new(w, h);
    for (x, y, p) in img.enumerate_pixels_mut() {
        let mut sum = 0.0;
        for i in 0..4 {
            for j in 0..4 {
                sum += value(
                    x as f64 - 0.375 + 0.25 * i as f64,
                    y as f64 - 0.375 + 0.25 * j as f64,
                );
            }
        }
        p.0[0] = sum / 16.0;
    }
    let mut img = blur_psf(&img, 0.9);
    add_noise(&mut img, 2.0, 5);
    quantise8(&mut img);
    let det = detect(&img, &DetectParams::default());
    for d in &det {
        eprintln!(
            "clutter detection {:?} rms {:.3} score {:.3}",
            d.ellipse, d.edge_rms, d.score
        );
    }
    assert!(det.len() <= 5, "{} detections in clutter", det.len());
}
