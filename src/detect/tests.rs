//! Whole-detector tests: the independent sample images with exact ground truth, and
//! synthetic area-integrated patterns.

use super::synth::{add_noise, blur_psf, quantise8, render, Blob, Scene};
use super::*;
use crate::imageio::load_gray;
use std::path::PathBuf;

/// `shared/samples/detect`: `$HEXCAL_SAMPLES_DIR`, else found beside an ancestor of the
/// crate (the project layout puts `shared/` next to the repository or its worktrees).
fn samples_dir() -> PathBuf {
    if let Ok(d) = std::env::var("HEXCAL_SAMPLES_DIR") {
        return PathBuf::from(d);
    }
    let here = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    here.ancestors()
        .map(|a| a.join("shared/samples/detect"))
        .find(|p| p.join("README.md").exists())
        .expect("shared/samples/detect not found beside the repository; set HEXCAL_SAMPLES_DIR")
}

/// One ground-truth circle.
struct Truth {
    centre: Point2<f64>,
    radius: f64,
    ringed: bool,
}

/// Detection figures of one image against its ground truth.
#[derive(Debug)]
struct Figures {
    /// Whole circles (radius ≥ `min_radius`) in the ground truth.
    whole: usize,
    /// Of those, found with the right size (radius within 20 %).
    found: usize,
    /// Found with the wrong size (e.g. a marker's inner disk).
    wrong_size: usize,
    /// RMS and max centre error of the found ones against the ground-truth ellipse centre.
    rms: f64,
    max: f64,
    /// Detections near no ground-truth circle (whole or partial): clutter, distractors.
    extra: usize,
    detections: usize,
}

fn load_truth(name: &str) -> (GrayImage, Vec<Truth>, Vec<Point2<f64>>, serde_json::Value) {
    let dir = samples_dir();
    let img = load_gray(&dir.join(format!("{name}.png"))).expect("sample image");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(format!("{name}.json"))).expect("sample json")).expect("json");
    let pt = |v: &serde_json::Value| Point2::new(v[0].as_f64().unwrap(), v[1].as_f64().unwrap());
    let whole = json["circles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| Truth { centre: pt(&c["ellipse"]), radius: c["radius"].as_f64().unwrap(), ringed: c["ringed"].as_bool().unwrap() })
        .collect();
    let partial = json["partial"].as_array().unwrap().iter().map(|c| pt(&c["proj"])).collect();
    (img, whole, partial, json)
}

fn evaluate(name: &str, min_radius: f64) -> Figures {
    let (img, truth, partial, _) = load_truth(name);
    let det = detect(&img, &DetectParams::default());
    let mut f = Figures { whole: 0, found: 0, wrong_size: 0, rms: 0.0, max: 0.0, extra: 0, detections: det.len() };
    let mut sq = 0.0;
    for t in truth.iter().filter(|t| t.radius >= min_radius) {
        f.whole += 1;
        let near = det.iter().find(|d| (d.ellipse.center - t.centre).norm() < 0.5 * t.radius);
        match near {
            Some(d) if (d.ellipse.radius() / t.radius - 1.0).abs() < 0.2 => {
                f.found += 1;
                let e = (d.ellipse.center - t.centre).norm();
                if e > 0.1 && std::env::var("DBG").is_ok() {
                    eprintln!("  big error {e} at {:?} r {} ringed {} det {:?} rms {}", t.centre, t.radius, t.ringed, d.ellipse, d.edge_rms);
                }
                sq += e * e;
                f.max = f.max.max(e);
            }
            Some(d) => {
                f.wrong_size += 1;
                if std::env::var("DBG").is_ok() {
                    eprintln!("  wrong size at {:?} r {:.2} ringed {} det {:?} rms {}", t.centre, t.radius, t.ringed, d.ellipse, d.edge_rms);
                }
            }
            None => {
                if std::env::var("DBG").is_ok() {
                    eprintln!("  missed at {:?} r {:.2} ringed {}", t.centre, t.radius, t.ringed);
                }
            }
        }
    }
    f.rms = (sq / f.found.max(1) as f64).sqrt();
    if std::env::var("DBG").is_ok() {
        let mut rms: Vec<f32> = det
            .iter()
            .filter(|d| truth.iter().any(|t| (t.centre - d.ellipse.center).norm() < 0.5 * t.radius))
            .map(|d| d.edge_rms / (0.1 + 0.02 * d.ellipse.radius() as f32))
            .collect();
        rms.sort_by(f32::total_cmp);
        for d in det.iter() {
            if let Some(t) = truth.iter().find(|t| (t.centre - d.ellipse.center).norm() < 0.5 * t.radius) {
                if d.edge_rms / (0.1 + 0.02 * d.ellipse.radius() as f32) > 0.3 {
                    eprintln!("  high rms {} ringed {} r {} err {}", d.edge_rms, t.ringed, t.radius, (t.centre - d.ellipse.center).norm());
                }
            }
        }
        let q = |p: f64| rms[((rms.len() - 1) as f64 * p) as usize];
        eprintln!("  true rms/(0.1+0.02r) quantiles {} {} {} {} max {}", q(0.5), q(0.9), q(0.99), q(0.999), q(1.0));
    }
    f.extra = det
        .iter()
        .filter(|d| {
            let c = d.ellipse.center;
            !truth.iter().any(|t| (t.centre - c).norm() < 0.5 * t.radius) && !partial.iter().any(|p| (p - c).norm() < 0.5 * d.ellipse.radius().max(3.0))
        })
        .inspect(|d| {
            if std::env::var("DBG").is_ok() {
                eprintln!("  extra {:?} score {} rms {} rel {} fg {} bg {}", d.ellipse, d.score, d.edge_rms, d.edge_rms / (0.1 + 0.02 * d.ellipse.radius() as f32), d.foreground, d.background)
            }
        })
        .count();
    eprintln!("{name}: {f:?}");
    f
}

#[test]
fn samples_explore() {
    for name in ["g1_frontal_00", "g2_tilted_02", "g3_extreme_01", "g4_partial_04", "g5_back_05", "g6_occluded_01"] {
        let t = std::time::Instant::now();
        evaluate(name, 4.0);
        eprintln!("  {:?}", t.elapsed());
    }
}

#[test]
fn debug_at() {
    let Ok(spec) = std::env::var("DBG_AT") else { return };
    let parts: Vec<&str> = spec.split(',').collect();
    let (img, _, _, _) = load_truth(parts[0]);
    let (x, y): (f64, f64) = (parts[1].parse().unwrap(), parts[2].parse().unwrap());
    let params = DetectParams::default();
    let full = View { data: img.as_raw(), width: img.width() as usize, height: img.height() as usize };
    let h_ref = circleness::reference_contrast(full);
    eprintln!("h_ref {h_ref}");
    let peaks = circleness_peaks(full, &DetectParams { min_circleness: 0.001, ..params.clone() }, Constants::new(h_ref));
    eprintln!("n peaks {}", peaks.len());
    let crop = image::imageops::crop_imm(&img, (x as u32).saturating_sub(60), (y as u32).saturating_sub(50), 120, 100).to_image();
    let crop8 = image::ImageBuffer::from_fn(crop.width() * 4, crop.height() * 4, |i, j| image::Luma([crop.get_pixel(i / 4, j / 4).0[0].clamp(0.0, 255.0) as u8]));
    crop8.save("/tmp/crop.png").unwrap();
    let det: Vec<Circle> = Vec::new();
    for d in det.iter().filter(|d| (d.ellipse.center.x - x).hypot(d.ellipse.center.y - y) < 30.0) {
        eprintln!("det {:?}", d.ellipse);
    }
    for p in peaks.iter().filter(|p| (p.x - x).hypot(p.y - y) < 30.0) {
        eprintln!("peak {p:?}");
    }
    let kept = suppress(circleness_peaks(full, &params, Constants::new(h_ref)));
    let settings = refine::Settings { rays: 90, min_contrast: (0.25 * h_ref) as f32, radius_range: (2.0, 60.0), max_rms: (0.3, 0.03) };
    for p in kept.iter().filter(|p| (p.x - x).hypot(p.y - y) < 12.0) {
        eprintln!("kept {p:?}");
        let r = refine::refine(full, Point2::new(p.x, p.y), SQRT_2 * p.sigma, p.score, &settings, &mut refine::Scratch::default());
        eprintln!("  -> {r:?}");
    }
}
