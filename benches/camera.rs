//! Camera model speed: undistortion of every pixel of an image (the simulator casts one ray
//! per pixel, ~2.3 M per 1920×1200 image), and projection with and without Jacobians.
//! Single thread; prints ns per call.
//!
//! Run: `cargo bench --bench camera`

use hexcal::camera::{CameraModel, Distortion, Intrinsics};
use nalgebra::{Isometry3, Point2, Point3, Vector3};
use std::hint::black_box;
use std::time::Instant;

fn model(width: u32, height: u32, f: [f64; 2], c: [f64; 2], dist: &[f64]) -> CameraModel {
    CameraModel {
        width,
        height,
        intrinsics: Intrinsics {
            fx: f[0],
            fy: f[1],
            cx: c[0],
            cy: c[1],
        },
        distortion: Distortion::from_opencv(dist).expect("4, 5 or 8 coefficients"),
    }
}

/// Median of `runs` timings of `f`, in seconds.
fn median_seconds(runs: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn main() {
    let cameras = [
        (
            "standard5",
            model(
                1920,
                1200,
                [1500.0, 1502.5],
                [955.3, 604.7],
                &[-0.12, 0.05, 0.0008, -0.0005, -0.01],
            ),
        ),
        (
            "rational8",
            model(
                2448,
                2048,
                [2400.0, 2395.0],
                [1230.4, 1019.8],
                &[0.8, -0.2, 0.0004, -0.0006, 0.05, 0.95, 0.1, 0.02],
            ),
        ),
        (
            "strong_barrel",
            model(
                1280,
                1024,
                [900.0, 899.0],
                [641.2, 509.6],
                &[-0.3, 0.1, 0.001, -0.002, -0.01],
            ),
        ),
    ];
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "camera model, single thread (load average: {})",
        load.trim()
    );
    println!(
        "{:<14} {:>10} {:>12} {:>12} {:>12} {:>14}",
        "model", "pixels", "image ms", "undist ns", "project ns", "proj+jac ns"
    );
    let pose = Isometry3::new(
        Vector3::new(60.0, -40.0, 1500.0),
        Vector3::new(0.3, -0.5, 0.2),
    );
    for (name, m) in &cameras {
        let (w, h) = (m.width, m.height);
        // Undistort every pixel once per run.
        let image = median_seconds(5, || {
            let mut sum = 0.0;
            for y in 0..h {
                for x in 0..w {
                    if let Some(n) = m.undistort(Point2::new(x as f64, y as f64)) {
                        sum += n.x;
                    }
                }
            }
            black_box(sum);
        });
        let pixels = w as usize * h as usize;
        // Board points on the rays of a pixel grid, projected through the pose.
        let points: Vec<Point3<f64>> = (0..h)
            .step_by(8)
            .flat_map(|y| {
                (0..w)
                    .step_by(8)
                    .map(move |x| Point2::new(x as f64, y as f64))
            })
            .map(|p| pose.inverse_transform_point(&Point3::from(m.ray(p).unwrap() * 1200.0)))
            .collect();
        let project = median_seconds(5, || {
            for x in &points {
                black_box(m.project_from(&pose, black_box(x)));
            }
        });
        let jacobians = median_seconds(5, || {
            for x in &points {
                black_box(m.project_with_jacobians(&pose, black_box(x)));
            }
        });
        let per = |s: f64, n: usize| s / n as f64 * 1e9;
        println!(
            "{name:<14} {:>10} {:>12.1} {:>12.1} {:>12.1} {:>14.1}",
            pixels,
            image * 1e3,
            per(image, pixels),
            per(project, points.len()),
            per(jacobians, points.len())
        );
    }
}
