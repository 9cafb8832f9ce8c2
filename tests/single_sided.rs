//! A single-sided board (issue 32, item 5) through the simulator and detection: its front is
//! found and anchored as the double-sided board's is; its plain back shows nothing; and no
//! view analysed with it, even one of a printed back, is labelled on the back.

use hexcal::app::detect::{analyse, Settings};
use hexcal::board::{Board, Hex, Side};
use hexcal::camera::{CameraModel, Distortion, Intrinsics};
use hexcal::grid::Grid;
use hexcal::images::FloatImage;
use hexcal::sim::{render, Imaging, PoseSpec, Scene};
use nalgebra::{Point3, Vector3};

/// A 640 × 480 view of `board`'s `side` from `d` mm towards the side point `look` (its own
/// frame, mm), tilted `tilt`° towards +x of that side; 2 DN read noise, PSF σ 0.8 px.
fn scene(board: &Board, side: Side, look: [f64; 2], d: f64, tilt: f64) -> Scene {
    let iso = board.side_transform(side);
    let t = tilt.to_radians();
    let target = iso * Point3::new(look[0], look[1], 0.0);
    let eye = iso * Point3::new(look[0] + d * t.sin(), look[1], d * t.cos());
    let up = iso.rotation * Vector3::new(0.2, 1.0, 0.0);
    Scene {
        name: format!("{} {side}", board.name),
        seed: 11,
        camera: CameraModel {
            width: 640,
            height: 480,
            intrinsics: Intrinsics {
                fx: 900.0,
                fy: 900.0,
                cx: 321.3,
                cy: 237.9,
            },
            distortion: Distortion::default(),
        },
        pose: PoseSpec {
            eye: Some([eye.x, eye.y, eye.z]),
            target: Some([target.x, target.y, target.z]),
            up: Some([up.x, up.y, up.z]),
            ..PoseSpec::default()
        },
        imaging: Imaging {
            shot_gain: 0.0,
            read_noise: 2.0,
            psf_sigma: 0.8,
            ..Imaging::default()
        },
        board: board.clone(),
    }
}

/// The truth's whole circles of a view: label and image centre (px).
type Whole = Vec<(Hex, [f64; 2])>;

/// Render `scene` and analyse it with `board`: the grid, the truth's whole circles and the
/// side the truth says faces the camera.
fn detect(scene: &Scene, board: &Board) -> (Grid, Whole, Option<Side>) {
    let view = render(scene).unwrap();
    let (w, h) = (view.frame.size.width, view.frame.size.height);
    let img = FloatImage::from_raw(w, h, view.frame.data.iter().map(|&v| v as f32).collect())
        .expect("frame size");
    let grid = analyse(&img, board, &Settings::default()).grid;
    let whole = view
        .truth
        .circles
        .iter()
        .filter(|c| c.whole)
        .filter_map(|c| Some((Hex::new(c.q, c.r), c.ellipse?)))
        .collect();
    (grid, whole, view.truth.side)
}

/// The single-sided board's front, whole centre in view: anchored on the front, every whole
/// circle labelled with its true lattice position.
#[test]
fn the_front_of_a_single_sided_board_is_anchored() {
    let board = Board::hex600().front_only();
    let (grid, whole, side) = detect(
        &scene(&board, Side::Front, [10.0, -5.0], 750.0, 35.0),
        &board,
    );
    assert_eq!(side, Some(Side::Front));
    assert!(
        grid.anchored && grid.side == Some(Side::Front),
        "{:?}",
        grid.side
    );
    assert!(whole.len() > 200, "{} whole circles", whole.len());
    let mut labelled = 0;
    for (hex, c) in &whole {
        let near = grid
            .points
            .iter()
            .find(|p| (p.image.x - c[0]).hypot(p.image.y - c[1]) < 1.0);
        if let Some(p) = near {
            assert_eq!((p.hex, p.side, p.anchored), (*hex, Some(Side::Front), true));
            labelled += 1;
        }
    }
    let recall = labelled as f64 / whole.len() as f64;
    assert!(recall >= 0.99, "{labelled} of {} labelled", whole.len());
    assert!(grid
        .points
        .iter()
        .all(|p| p.anchored && p.side == Some(Side::Front)));
}

/// Its plain back: the truth sees the back face and no circle; detection labels nothing on
/// the back. And a printed back (hex600's) analysed as the single-sided board: its rings
/// decode as no marker of that board, so nothing is anchored and no point is on the back.
#[test]
fn a_single_sided_board_is_never_seen_from_the_back() {
    let single = Board::hex600().front_only();
    let (grid, whole, side) = detect(
        &scene(&single, Side::Back, [10.0, -5.0], 750.0, 35.0),
        &single,
    );
    assert_eq!(side, Some(Side::Back));
    assert!(whole.is_empty(), "{} circles on a plain back", whole.len());
    assert!(grid.points.iter().all(|p| p.side != Some(Side::Back)));
    assert_ne!(grid.side, Some(Side::Back));

    let double = Board::hex600();
    let back = scene(&double, Side::Back, [10.0, -5.0], 750.0, 35.0);
    let (as_printed, whole, _) = detect(&back, &double);
    // The same view with the double-sided board: anchored on the back (so the rings are
    // there to be read).
    assert!(as_printed.anchored && as_printed.side == Some(Side::Back));
    assert!(whole.len() > 200);
    let (grid, _, _) = detect(&back, &single);
    assert!(grid.points.len() > 200, "{} points", grid.points.len());
    assert!(!grid.anchored && grid.side.is_none(), "{:?}", grid.side);
    assert!(grid.points.iter().all(|p| p.side.is_none() && !p.anchored));
}
