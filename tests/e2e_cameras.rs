//! End to end for the cameras of the paper-like rig: render every camera's view of every
//! board pose at the default imaging conditions (DESIGN.md §9), detect circles, build grids,
//! calibrate, and compare with the rig's ground truth.
//!
//! Acceptance (issue 5): camera RMS ≤ 0.1 px, focal error ≤ 0.1 %.

use hexcal::calib::bundle::DeviceKind;
use hexcal::calib::pipeline::{calibrate, CalibrateOptions};
use hexcal::calib::synthetic::SyntheticRig;
use hexcal::calib::views::{CameraView, Frame, ViewPoint};
use hexcal::detect::{detect, DetectParams, GrayImage};
use hexcal::grid::{build, GridParams};
use hexcal::sim::scene::{Imaging, PoseSpec, Scene};
use rayon::prelude::*;

/// One camera's view of one pose, rendered and labelled.
fn view(rig: &SyntheticRig, camera: usize, pose: usize) -> Option<CameraView> {
    let dev = &rig.devices[camera];
    let t = dev.pose * rig.boards[pose];
    let r = t.rotation.scaled_axis();
    let v = t.translation.vector;
    let scene = Scene {
        name: format!("c{camera}p{pose}"),
        seed: (100 * camera + pose) as u64,
        camera: dev.model,
        pose: PoseSpec {
            rvec: Some([r.x, r.y, r.z]),
            tvec: Some([v.x, v.y, v.z]),
            ..PoseSpec::default()
        },
        imaging: Imaging::default(),
        board: rig.board.clone(),
    };
    let rendered = hexcal::sim::render(&scene).ok()?;
    let (w, h) = (rendered.frame.size.width, rendered.frame.size.height);
    let image = GrayImage::from_fn(w, h, |x, y| {
        image::Luma([f32::from(rendered.frame.data[(y * w + x) as usize])])
    });
    let circles = detect(&image, &DetectParams::default());
    let grid = build(&image, &circles, &rig.board, &GridParams::default());
    let side = grid.side?;
    grid.anchored.then(|| CameraView {
        camera,
        pose,
        frame: Frame::Anchored(side),
        points: grid
            .points
            .iter()
            .map(|p| ViewPoint {
                hex: p.hex,
                image: p.image,
                projectors: Vec::new(),
            })
            .collect(),
    })
}

#[test]
fn rendered_views_calibrate_the_cameras() {
    let rig = SyntheticRig::paper(8, 0.0, 71);
    let cameras: Vec<usize> = (0..rig.devices.len())
        .filter(|&d| rig.devices[d].kind == DeviceKind::Camera)
        .collect();
    let jobs: Vec<(usize, usize)> = cameras
        .iter()
        .flat_map(|&c| (0..rig.boards.len()).map(move |k| (c, k)))
        .collect();
    let views: Vec<CameraView> = jobs
        .par_iter()
        .filter_map(|&(c, k)| view(&rig, c, k))
        .collect();
    let infos: Vec<_> = cameras
        .iter()
        .map(|&c| rig.device_infos()[c].clone())
        .collect();
    let cal = calibrate(
        &rig.board,
        &infos,
        rig.boards.len(),
        &views,
        &CalibrateOptions::default(),
    )
    .unwrap();
    assert_eq!(cal.devices.len(), cameras.len(), "{:?}", cal.excluded);
    let table = hexcal::report::residual_table(&cal);
    eprint!("{}", hexcal::report::format_table(&table));
    for row in &table {
        // RMS of residual norms is √2 × the per-coordinate RMS the issue bounds by 0.1 px.
        assert!(
            row.rms / 2f64.sqrt() <= 0.1,
            "{}: RMS {} px",
            row.name,
            row.rms
        );
    }
    for (est, &c) in cal.devices.iter().zip(&cameras) {
        let truth = &rig.devices[c].model.intrinsics;
        let e = est.model.intrinsics.fx / truth.fx - 1.0;
        eprintln!("{}: focal error {:.4} %", est.name, 100.0 * e);
        assert!(e.abs() <= 1e-3, "{} focal error {e}", est.name);
    }
}
