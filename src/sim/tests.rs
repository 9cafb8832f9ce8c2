//! Tests of simulated views against their ground truth and the shared samples.

use super::*;
use crate::board::Hex;
use crate::camera::{Distortion, Intrinsics};
use nalgebra::{Matrix3, Point3, Rotation3, Translation3, UnitQuaternion};
use serde_json::Value;

const SAMPLES: &str = "/work/shared/samples/detect";

/// A sample's camera, pose and JSON.
fn sample(name: &str) -> (CameraModel, Isometry3<f64>, Value) {
    let path = format!("{SAMPLES}/{name}.json");
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let f = |x: &Value| x.as_f64().unwrap();
    let k = &v["camera"]["K"];
    let dist: Vec<f64> = v["camera"]["dist"]
        .as_array()
        .unwrap()
        .iter()
        .map(f)
        .collect();
    let camera = CameraModel {
        width: v["width"].as_u64().unwrap() as u32,
        height: v["height"].as_u64().unwrap() as u32,
        intrinsics: Intrinsics {
            fx: f(&k[0][0]),
            fy: f(&k[1][1]),
            cx: f(&k[0][2]),
            cy: f(&k[1][2]),
        },
        distortion: Distortion::from_opencv(&dist).unwrap(),
    };
    let r = Matrix3::from_fn(|i, j| f(&v["pose"]["R"][i][j]));
    let t = Vector3::from_fn(|i, _| f(&v["pose"]["t"][i]));
    let pose = Isometry3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)),
    );
    (camera, pose, v)
}

/// A scene for a sample's camera and pose, noise-free, with its PSF and levels.
fn sample_scene(camera: CameraModel, pose: &Isometry3<f64>, v: &Value) -> Scene {
    let f = |k: &str| v["render"][k].as_f64().unwrap();
    let rvec = pose.rotation.scaled_axis();
    let t = pose.translation.vector;
    Scene {
        name: "sample".into(),
        seed: 0,
        camera,
        pose: PoseSpec {
            rvec: Some([rvec.x, rvec.y, rvec.z]),
            tvec: Some([t.x, t.y, t.z]),
            ..PoseSpec::default()
        },
        imaging: Imaging {
            white_dn: f("white_dn"),
            black_dn: f("black_dn"),
            edge_dn: f("side_dn"),
            psf_sigma: f("psf_sigma"),
            ..Imaging::default()
        }
        .noise_free(),
        board: Board::hex600(),
    }
}

/// The samples' ground truth is an independent implementation of the same conventions:
/// pixel origin, lens model, board and back-side frames, lattice, rings.
#[test]
fn ground_truth_agrees_with_the_shared_samples() {
    for name in ["g1_frontal_00", "g5_back_05"] {
        let (camera, pose, v) = sample(name);
        let scene = sample_scene(camera, &pose, &v);
        let truth = ground_truth(&scene).unwrap();
        assert_eq!(truth.side.unwrap().name(), v["side"].as_str().unwrap());
        let ours: std::collections::HashMap<(i32, i32), &CircleTruth> =
            truth.circles.iter().map(|c| ((c.q, c.r), c)).collect();
        let xy = |x: &Value| Point2::new(x[0].as_f64().unwrap(), x[1].as_f64().unwrap());
        let mut checked = 0;
        for (list, whole) in [("circles", true), ("partial", false)] {
            for c in v[list].as_array().unwrap() {
                let key = (
                    c["q"].as_i64().unwrap() as i32,
                    c["r"].as_i64().unwrap() as i32,
                );
                let reasons: Vec<&str> = c["reason"]
                    .as_array()
                    .map_or(vec![], |r| r.iter().map(|x| x.as_str().unwrap()).collect());
                let Some(o) = ours.get(&key) else {
                    panic!("{name}: circle {key:?} of {list} missing");
                };
                assert_eq!(o.side.name(), c["side"].as_str().unwrap());
                assert_eq!(
                    o.ringed,
                    c["ringed"].as_bool().unwrap(),
                    "{name} {key:?} ringed"
                );
                // Cut by the frame exactly when the sample says so (radius or occluder reasons
                // do not concern the frame).
                if whole || reasons.contains(&"frame") {
                    assert_eq!(o.whole, whole, "{name} {key:?} whole");
                }
                // The samples round to 1e-6 px: |error| ≤ 0.5e-6 per coordinate.
                let proj = Point2::from(o.proj);
                assert!(
                    (proj - xy(&c["proj"])).norm() < 1e-6,
                    "{name} {key:?} proj {proj} vs {}",
                    c["proj"]
                );
                if c["ellipse"].is_array() {
                    let e = Point2::from(o.ellipse.unwrap());
                    assert!(
                        (e - xy(&c["ellipse"])).norm() < 1e-6,
                        "{name} {key:?} ellipse {e} vs {}",
                        c["ellipse"]
                    );
                    assert!((o.radius.unwrap() - c["radius"].as_f64().unwrap()).abs() < 1e-6);
                    let axes = o.axes.unwrap();
                    let (a, b) = (
                        c["axes"][0].as_f64().unwrap(),
                        c["axes"][1].as_f64().unwrap(),
                    );
                    assert!((axes[0] - a).abs() < 1e-6 && (axes[1] - b).abs() < 1e-6);
                    // The angle is defined when the axes differ; its error is ~1e-6/(a − b) rad.
                    if a - b > 0.01 {
                        let d = o.angle_deg.unwrap() - c["angle_deg"].as_f64().unwrap();
                        let d = d - 180.0 * (d / 180.0).round();
                        assert!(d.abs() < 1e-3, "{name} {key:?} angle {d}");
                    }
                }
                checked += 1;
            }
        }
        assert!(checked > 400, "{name}: {checked}");
    }
}

/// Bilinear sample of a row-major float image (pixel centres at integers).
fn bilinear(img: &[f32], w: usize, p: Point2<f64>) -> f64 {
    let (x0, y0) = (p.x.floor(), p.y.floor());
    let (fx, fy) = (p.x - x0, p.y - y0);
    let at = |x: f64, y: f64| f64::from(img[y as usize * w + x as usize]);
    (at(x0, y0) * (1.0 - fx) + at(x0 + 1.0, y0) * fx) * (1.0 - fy)
        + (at(x0, y0 + 1.0) * (1.0 - fx) + at(x0 + 1.0, y0 + 1.0) * fx) * fy
}

/// Pearson correlation of two equally long samples.
fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}

/// Our render of a sample's camera and pose looks like the sample around every circle.
#[test]
fn renders_correlate_with_the_shared_samples() {
    for name in ["g1_frontal_00", "g5_back_05"] {
        let (camera, pose, v) = sample(name);
        let scene = sample_scene(camera, &pose, &v);
        let view = render(&scene).unwrap();
        let theirs = image::open(format!("{SAMPLES}/{name}.png"))
            .unwrap()
            .into_luma8();
        let w = camera.width as usize;
        let (mut worst, mut sum, mut n) = (1.0f64, 0.0, 0);
        for c in view.truth.circles.iter().filter(|c| c.whole) {
            // Pixels within 1.5 radii of the centre: the circle, its ring, the black around.
            let (e, rad) = (c.ellipse.unwrap(), c.radius.unwrap());
            let reach = 1.5 * rad;
            let (mut a, mut b) = (Vec::new(), Vec::new());
            for y in (e[1] - reach).ceil() as i64..=(e[1] + reach).floor() as i64 {
                for x in (e[0] - reach).ceil() as i64..=(e[0] + reach).floor() as i64 {
                    if x < 0 || y < 0 || x >= w as i64 || y >= camera.height as i64 {
                        continue;
                    }
                    if (x as f64 - e[0]).hypot(y as f64 - e[1]) <= reach {
                        a.push(f64::from(view.signal[y as usize * w + x as usize]));
                        b.push(f64::from(theirs.get_pixel(x as u32, y as u32)[0]));
                    }
                }
            }
            let r = correlation(&a, &b);
            worst = worst.min(r);
            sum += r;
            n += 1;
        }
        let mean = sum / n as f64;
        eprintln!("{name}: {n} circles, correlation mean {mean:.5} worst {worst:.5}");
        // Their noise (σ = 1.2–1.9 DN) against a patch whose white fraction is (1/1.5)² has a
        // std ≈ ½·contrast ≈ 80–100 DN: noise alone caps the correlation at
        // 1/√(1 + (1.9/80)²) = 0.9997 (measured: 0.99985 and 0.99980, i.e. at that cap). Their
        // illumination gradient changes a patch's levels by < 1 %, which a correlation ignores
        // to first order. Resampling the sample by a 0.1 px shift lowers the means to 0.9989
        // and 0.9993 (measured), so a mean above 0.9995 places the circles to better than
        // 0.1 px; a missing or extra ring drops that patch far below 0.997.
        assert!(mean > 0.9995, "{name}: mean correlation {mean}");
        assert!(worst > 0.997, "{name}: worst correlation {worst}");
    }
}

#[test]
fn explore_ellipse_definitions() {
    let board = Board::hex600();
    for name in [
        "g1_frontal_00",
        "g2_tilted_02",
        "g3_extreme_01",
        "g4_partial_04",
        "g5_back_05",
        "g6_occluded_01",
    ] {
        let (camera, pose, v) = sample(name);
        let side = truth::side_seen(&board, &pose).unwrap();
        let face = pose * board.side_transform(side);
        let mut errs = [0.0f64; 4];
        let mut maxe = [0.0f64; 4];
        let mut n = 0;
        for c in v["circles"].as_array().unwrap() {
            let h = Hex::new(
                c["q"].as_i64().unwrap() as i32,
                c["r"].as_i64().unwrap() as i32,
            );
            let e = Point2::new(
                c["ellipse"][0].as_f64().unwrap(),
                c["ellipse"][1].as_f64().unwrap(),
            );
            let ctr = board.position(h);
            let rim = truth::outline(&camera, &face, ctr, board.radius, 256).unwrap();
            let fit = truth::fit_ellipse(&rim).unwrap().center;
            let rim4 = truth::outline(&camera, &face, ctr, board.radius, 4096).unwrap();
            let poly = truth::polygon_centroid(&rim4);
            let pole = truth::pinhole_outline_centre(&face, ctr, board.radius).unwrap();
            let polep = camera.project(&Point3::new(pole.x, pole.y, 1.0)).unwrap();
            let fit64 =
                truth::fit_ellipse(&truth::outline(&camera, &face, ctr, board.radius, 64).unwrap())
                    .unwrap()
                    .center;
            for (i, p) in [fit, poly, polep, fit64].iter().enumerate() {
                let d = (p - e).norm();
                errs[i] += d;
                maxe[i] = maxe[i].max(d);
            }
            n += 1;
        }
        eprintln!("{name} side {side} n {n}: mean fit256 {:.2e} poly {:.2e} pole {:.2e} fit64 {:.2e} | max {:.2e} {:.2e} {:.2e} {:.2e}",
            errs[0] / n as f64, errs[1] / n as f64, errs[2] / n as f64, errs[3] / n as f64, maxe[0], maxe[1], maxe[2], maxe[3]);
    }
}
