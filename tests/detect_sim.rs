//! Acceptance of detection + grid building (issue 3) on the project's own simulated views
//! (`hexcal::sim::render`, ground truth from the exact projected outlines): frontal, tilts
//! 30–75°, partial views with and without the centre, the back side, an occluding patch,
//! strong barrel distortion (k1 = −0.3), noise and blur, radii 4–40 px, and distractor blobs
//! (single and in a hexagonal cluster) off the board.
//!
//! Checked per view and pooled, against the truth:
//! - recall of whole, unoccluded circles with radius ≥ 4 px: ≥ 99.5 % at tilt ≤ 60°, ≥ 97 %
//!   at 60–75° (pooled over the views of each band, and per view);
//! - no anchored point with a wrong (q, r, side); the points of an unanchored grid are one
//!   lattice transform of the truth; no labelled point off the board (every labelled point
//!   is a true circle of the seen side, anchored labels are on the board);
//! - centre RMS against the truth's outline-ellipse centre ≤ 0.03 px in views with 2 DN
//!   read noise (no shot noise) and PSF σ ≤ 1 px;
//! - anchored whenever the centre cell (centre and six neighbours) is whole and unoccluded;
//! - circles cut by the frame edge, when labelled, within 0.1 px of their outline centre.
//!
//! The tolerances are the acceptance targets. For the centre error the noise floor
//! lies well below it: an edge point's radial error is σ_n / slope, the slope of a step of
//! contrast h blurred by σ_PSF being h/(√(2π)·σ_PSF) = 180/(2.5·1.0) ≈ 72 DN/px, so 2 DN
//! give 0.028 px per point; a centre from ~90 points spread over the rim averages that down
//! by √(90/2) to ≈ 0.004 px. What remains is model error (the edge-level estimate, sampling
//! at small radii, the non-elliptic outline under distortion), which the target bounds.

use hexcal::app::detect::{analyse, Analysis, Settings};
use hexcal::board::{Board, Hex, Side};
use hexcal::camera::{CameraModel, Distortion, Intrinsics};
use hexcal::images::FloatImage;
use hexcal::sim::{render, CircleTruth, Imaging, PoseSpec, Scene};
use nalgebra::{Point2, Point3};
use std::collections::HashMap;

/// Tilt bands of the recall target.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Band {
    /// Tilt ≤ 60°: recall ≥ 99.5 %.
    UpTo60,
    /// Tilt 60–75°: recall ≥ 97 %.
    To75,
    /// Tilt 60–73° with circles of 3–4.5 px (issue 32 item 4 (b)): recall and interior
    /// labels ≥ 99 % per view, labels of all counted circles ≥ 99 % pooled.
    Steep,
}

impl Band {
    fn min_recall(self) -> f64 {
        match self {
            Band::UpTo60 => 0.995,
            Band::To75 => 0.97,
            Band::Steep => 0.99,
        }
    }

    /// The bound on the labelled share of every counted circle, pooled over the band's views.
    fn min_pooled_labelled(self) -> Option<f64> {
        (self == Band::Steep).then_some(0.99)
    }

    fn name(self) -> &'static str {
        match self {
            Band::UpTo60 => "tilt ≤ 60°",
            Band::To75 => "tilt 60–75°",
            Band::Steep => "tilt 60–73°, r ≥ 3 px",
        }
    }
}

/// 2 DN read noise, no shot noise, PSF σ as given: the conditions of the accuracy target.
fn two_dn(psf_sigma: f64) -> Imaging {
    Imaging {
        shot_gain: 0.0,
        read_noise: 2.0,
        psf_sigma,
        ..Imaging::default()
    }
}

/// A pinhole (+ distortion) camera of the given size and focal length, principal point near
/// the centre.
fn camera(size: (u32, u32), f: f64, distortion: Distortion) -> CameraModel {
    CameraModel {
        width: size.0,
        height: size.1,
        intrinsics: Intrinsics {
            fx: f,
            fy: f,
            cx: f64::from(size.0) / 2.0 + 1.3,
            cy: f64::from(size.1) / 2.0 - 2.1,
        },
        distortion,
    }
}

/// A view of `side` from distance `d` (mm) towards the side point `look` (mm, in the side's
/// own frame), tilted by `tilt` degrees from the side's normal towards azimuth `azimuth`
/// (degrees), image "up" turned by `spin` degrees.
#[allow(clippy::too_many_arguments)]
fn scene(
    name: &str,
    seed: u64,
    camera: CameraModel,
    side: Side,
    look: [f64; 2],
    d: f64,
    tilt: f64,
    azimuth: f64,
    spin: f64,
    imaging: Imaging,
) -> Scene {
    let board = Board::hex600();
    let (t, a, s) = (tilt.to_radians(), azimuth.to_radians(), spin.to_radians());
    // Side frame → board frame (the back is mirrored in x and sits at z = −thickness).
    let iso = board.side_transform(side);
    let target = iso * Point3::new(look[0], look[1], 0.0);
    let eye_side = Point3::new(
        look[0] + d * t.sin() * a.cos(),
        look[1] + d * t.sin() * a.sin(),
        d * t.cos(),
    );
    let eye = iso * eye_side;
    let up = iso.rotation * nalgebra::Vector3::new(s.sin(), s.cos(), 0.0);
    Scene {
        name: name.into(),
        seed,
        camera,
        pose: PoseSpec {
            eye: Some([eye.x, eye.y, eye.z]),
            target: Some([target.x, target.y, target.z]),
            up: Some([up.x, up.y, up.z]),
            ..PoseSpec::default()
        },
        imaging,
        board,
    }
}

/// An axis-aligned image rectangle (px).
#[derive(Clone, Copy, Debug)]
struct Rect {
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
}

/// What a case adds to the rendered view.
#[derive(Clone, Debug, Default)]
struct Extras {
    /// Patches painted over the view at the board's black level.
    occluders: Vec<Rect>,
    /// White disks (centre, radius, px) painted off the board.
    distractors: Vec<(Point2<f64>, f64)>,
}

struct Case {
    scene: Scene,
    band: Band,
    extras: Extras,
    /// Whether the imaging is that of the accuracy target (2 DN, PSF σ ≤ 1 px).
    accuracy: bool,
    /// Smallest radius √(ab) (px) of the circles the recall counts.
    min_radius: f64,
}

/// Figures of one view.
#[derive(Debug, Default)]
struct Figures {
    /// Whole, unoccluded circles with radius ≥ 4 px.
    expected: usize,
    /// Of these, detected.
    detected: usize,
    /// Of these, labelled.
    labelled: usize,
    /// Expected circles whose six lattice neighbours are expected too (a whole cell in
    /// view), and how many of them are labelled.
    interior: usize,
    interior_labelled: usize,
    /// Squared centre errors of the detected expected circles.
    sq_errors: Vec<f64>,
    /// Anchored points with a wrong (q, r) or side.
    wrong_anchored: usize,
    /// Labelled points that are no circle of the seen side (distractors, occluder corners).
    off_board: usize,
    /// Points outside the one lattice transform that maps most labels onto the truth.
    inconsistent: usize,
    /// Points whose side differs from the truth.
    wrong_side: usize,
    /// Labelled circles cut by the frame edge (not whole), and their largest centre error
    /// against the truth's ellipse centre (px).
    cut_labelled: usize,
    cut_max_error: f64,
    anchored: bool,
    centre_whole: bool,
}

fn rms(sq: &[f64]) -> f64 {
    (sq.iter().sum::<f64>() / sq.len().max(1) as f64).sqrt()
}

/// The rendered view as linear grey levels, with the extras painted in.
fn image_of(case: &Case) -> (FloatImage, Vec<CircleTruth>, Option<Side>) {
    let view = render(&case.scene).unwrap();
    let (w, h) = (view.frame.size.width, view.frame.size.height);
    let mut img = FloatImage::from_raw(w, h, view.frame.data.iter().map(|&v| v as f32).collect())
        .expect("frame size");
    let black = case.scene.imaging.black_dn as f32;
    for r in &case.extras.occluders {
        for y in r.y0.max(0.0) as u32..(r.y1.min(f64::from(h))) as u32 {
            for x in r.x0.max(0.0) as u32..(r.x1.min(f64::from(w))) as u32 {
                img.put_pixel(x, y, image::Luma([black]));
            }
        }
    }
    // Distractors: white disks, 4×4 supersampled coverage over what is there.
    let white = case.scene.imaging.white_dn as f32;
    for &(c, rad) in &case.extras.distractors {
        let (xa, xb) = ((c.x - rad - 1.0).floor(), (c.x + rad + 1.0).ceil());
        let (ya, yb) = ((c.y - rad - 1.0).floor(), (c.y + rad + 1.0).ceil());
        for y in ya.max(0.0) as u32..=(yb.min(f64::from(h) - 1.0)) as u32 {
            for x in xa.max(0.0) as u32..=(xb.min(f64::from(w) - 1.0)) as u32 {
                let mut cover = 0.0;
                for i in 0..4 {
                    for j in 0..4 {
                        let sx = f64::from(x) - 0.375 + 0.25 * f64::from(i);
                        let sy = f64::from(y) - 0.375 + 0.25 * f64::from(j);
                        if (sx - c.x).hypot(sy - c.y) <= rad {
                            cover += 1.0 / 16.0;
                        }
                    }
                }
                let p = img.get_pixel_mut(x, y);
                p.0[0] += (white - p.0[0]) * cover;
            }
        }
    }
    (img, view.truth.circles, view.truth.side)
}

/// Whether a truth circle is touched by an occluder (its bounding box, grown by 2 px).
fn occluded(t: &CircleTruth, extras: &Extras) -> bool {
    let (Some(c), Some(ax)) = (t.ellipse, t.axes) else {
        return false;
    };
    let m = ax[0] + 2.0;
    extras
        .occluders
        .iter()
        .any(|r| c[0] + m > r.x0 && c[0] - m < r.x1 && c[1] + m > r.y0 && c[1] - m < r.y1)
}

/// Run detection and grid building on one case and measure it against the truth.
fn measure(case: &Case) -> (Figures, Analysis) {
    let (img, truth, side) = image_of(case);
    let side = side.expect("a side faces the camera");
    let board = &case.scene.board;
    let analysis = analyse(&img, board, &Settings::default());
    let centre_of = |t: &CircleTruth| t.ellipse.unwrap_or(t.proj);
    // Each detection's true circle: the nearest truth centre within a third of its radius.
    let truth_of: Vec<Option<usize>> = analysis
        .circles
        .iter()
        .map(|c| {
            let p = c.ellipse.center;
            truth
                .iter()
                .enumerate()
                .map(|(j, t)| {
                    let q = centre_of(t);
                    (j, (p.x - q[0]).hypot(p.y - q[1]))
                })
                .filter(|&(j, d)| d < truth[j].radius.unwrap_or(4.0) / 3.0)
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(j, _)| j)
        })
        .collect();
    let mut detection_of: HashMap<usize, usize> = HashMap::new();
    for (i, t) in truth_of.iter().enumerate() {
        if let Some(j) = *t {
            detection_of.entry(j).or_insert(i);
        }
    }
    let expected: Vec<usize> = (0..truth.len())
        .filter(|&j| {
            let t = &truth[j];
            t.whole && t.radius.is_some_and(|r| r >= case.min_radius) && !occluded(t, &case.extras)
        })
        .collect();
    let labelled_circles: HashMap<usize, &hexcal::grid::LabelledPoint> =
        analysis.grid.points.iter().map(|p| (p.circle, p)).collect();
    let mut fig = Figures {
        expected: expected.len(),
        anchored: analysis.grid.anchored,
        ..Figures::default()
    };
    for &j in &expected {
        if let Some(&i) = detection_of.get(&j) {
            fig.detected += 1;
            let c = analysis.circles[i].ellipse.center;
            let e = truth[j].ellipse.unwrap();
            fig.sq_errors
                .push((c.x - e[0]).powi(2) + (c.y - e[1]).powi(2));
            if labelled_circles.contains_key(&i) {
                fig.labelled += 1;
            }
        }
    }
    let whole: std::collections::HashSet<Hex> = expected
        .iter()
        .map(|&j| Hex::new(truth[j].q, truth[j].r))
        .collect();
    for &j in &expected {
        let h = Hex::new(truth[j].q, truth[j].r);
        if h.neighbours().into_iter().all(|n| whole.contains(&n)) {
            fig.interior += 1;
            let labelled = detection_of
                .get(&j)
                .is_some_and(|i| labelled_circles.contains_key(i));
            fig.interior_labelled += usize::from(labelled);
        }
    }
    fig.centre_whole = std::iter::once(Hex::new(0, 0))
        .chain(Hex::new(0, 0).neighbours())
        .all(|h| whole.contains(&h));
    let mut votes: HashMap<(usize, Hex), usize> = HashMap::new();
    let mut pairs = 0;
    for p in &analysis.grid.points {
        let Some(j) = truth_of[p.circle] else {
            fig.off_board += 1;
            continue;
        };
        let t = Hex::new(truth[j].q, truth[j].r);
        if !truth[j].whole {
            fig.cut_labelled += 1;
            if let Some(e) = truth[j].ellipse {
                let err = (p.image.x - e[0]).hypot(p.image.y - e[1]);
                fig.cut_max_error = fig.cut_max_error.max(err);
            }
        }
        if p.side.is_some_and(|s| s != side) {
            fig.wrong_side += 1;
        }
        if p.anchored && (p.hex != t || p.side != Some(side) || !board.contains(p.hex)) {
            fig.wrong_anchored += 1;
        }
        pairs += 1;
        for s in 0..6 {
            *votes.entry((s, t - p.hex.rotate(s))).or_default() += 1;
        }
    }
    fig.inconsistent = pairs - votes.values().copied().max().unwrap_or(0);
    (fig, analysis)
}

/// Run the cases, print their figures, and check every target.
fn check(cases: &[Case]) {
    let mut failures = Vec::new();
    let mut pooled: HashMap<Band, (usize, usize, usize)> = HashMap::new();
    for case in cases {
        let name = &case.scene.name;
        let (f, a) = measure(case);
        let recall = f.detected as f64 / f.expected.max(1) as f64;
        let interior_recall = f.interior_labelled as f64 / f.interior.max(1) as f64;
        let centre_rms = rms(&f.sq_errors);
        println!(
            "{name}: {} expected, detected {} (recall {:.4}), labelled {} ({:.4}), centre RMS \
             {centre_rms:.4} px, interior labelled {}/{} ({interior_recall:.4}), anchored {} (centre \
             cell whole {}), side {:?}, detections {}, \
             points {} ({} cut by the frame, centre error ≤ {:.2} px), wrong anchored {}, off \
             board {}, inconsistent {}, wrong side {}",
            f.expected,
            f.detected,
            recall,
            f.labelled,
            f.labelled as f64 / f.expected.max(1) as f64,
            f.interior_labelled,
            f.interior,
            f.anchored,
            f.centre_whole,
            a.grid.side,
            a.circles.len(),
            a.grid.points.len(),
            f.cut_labelled,
            f.cut_max_error,
            f.wrong_anchored,
            f.off_board,
            f.inconsistent,
            f.wrong_side,
        );
        let e = pooled.entry(case.band).or_default();
        e.0 += f.expected;
        e.1 += f.detected;
        e.2 += f.labelled;
        if recall < case.band.min_recall() {
            failures.push(format!("{name}: recall {recall:.4}"));
        }
        // Labels, not only detections: every circle whose cell is whole in view.
        if interior_recall < case.band.min_recall() {
            failures.push(format!("{name}: interior labelled {interior_recall:.4}"));
        }
        if f.wrong_anchored + f.off_board + f.inconsistent + f.wrong_side > 0 {
            failures.push(format!(
                "{name}: label errors: wrong anchored {}, off board {}, inconsistent {}, wrong side {}",
                f.wrong_anchored, f.off_board, f.inconsistent, f.wrong_side
            ));
        }
        // A labelled circle cut by the frame edge must still have a usable centre: 0.1 px,
        // 3× the whole circles' RMS target (part of its outline is missing).
        if f.cut_max_error > 0.1 {
            failures.push(format!(
                "{name}: a labelled circle cut by the frame is {:.3} px off",
                f.cut_max_error
            ));
        }
        if case.accuracy && centre_rms > 0.03 {
            failures.push(format!("{name}: centre RMS {centre_rms:.4} px"));
        }
        if f.centre_whole && !f.anchored {
            failures.push(format!(
                "{name}: centre cell whole in view but not anchored"
            ));
        }
    }
    for (band, (expected, detected, labelled)) in &pooled {
        let share = *labelled as f64 / *expected as f64;
        println!(
            "{}: pooled recall {detected}/{expected} = {:.4}, labelled {labelled} = {share:.4}",
            band.name(),
            *detected as f64 / *expected as f64
        );
        if band.min_pooled_labelled().is_some_and(|m| share < m) {
            failures.push(format!("{}: pooled labelled {share:.4}", band.name()));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

fn plain(size: (u32, u32), f: f64) -> CameraModel {
    camera(size, f, Distortion::default())
}

/// A front view with the accuracy target's imaging, no extras.
#[allow(clippy::too_many_arguments)]
fn front(
    name: &str,
    seed: u64,
    cam: CameraModel,
    look: [f64; 2],
    d: f64,
    tilt: f64,
    azimuth: f64,
    spin: f64,
) -> Case {
    Case {
        scene: scene(
            name,
            seed,
            cam,
            Side::Front,
            look,
            d,
            tilt,
            azimuth,
            spin,
            two_dn(0.8),
        ),
        band: if tilt > 60.0 {
            Band::To75
        } else {
            Band::UpTo60
        },
        extras: Extras::default(),
        accuracy: true,
        min_radius: 4.0,
    }
}

const VGA: (u32, u32) = (800, 600);

#[test]
fn frontal_and_tilted_to_70_degrees() {
    check(&[
        // r ≈ 4.1 px: the whole board in view.
        front(
            "frontal r4",
            1,
            plain((1024, 768), 1000.0),
            [5.0, -3.0],
            1450.0,
            0.0,
            0.0,
            7.0,
        ),
        front(
            "frontal r9",
            2,
            plain(VGA, 1000.0),
            [12.0, 8.0],
            650.0,
            3.0,
            40.0,
            -20.0,
        ),
        front(
            "tilt 30",
            3,
            plain(VGA, 900.0),
            [-20.0, 10.0],
            800.0,
            30.0,
            20.0,
            35.0,
        ),
        front(
            "tilt 45",
            4,
            plain(VGA, 900.0),
            [15.0, -25.0],
            700.0,
            45.0,
            110.0,
            100.0,
        ),
        front(
            "tilt 60",
            5,
            plain(VGA, 900.0),
            [0.0, 15.0],
            600.0,
            60.0,
            200.0,
            -150.0,
        ),
        front(
            "tilt 70",
            6,
            plain(VGA, 900.0),
            [10.0, 0.0],
            520.0,
            70.0,
            290.0,
            60.0,
        ),
    ]);
}

/// 60–75°: the band's own recall bound (97 %) and the accuracy target. Circles reach minor
/// semi-axes of 2 px here, at the detector's first scale (σ = r_min/√max_aspect = 2 px).
#[test]
fn tilt_65_to_75_degrees() {
    let barrel = Distortion {
        k1: -0.2,
        k2: 0.05,
        ..Distortion::default()
    };
    let mut back = front(
        "back tilt 72, k1 -0.2",
        8,
        camera((1280, 960), 1100.0, barrel),
        [20.0, -10.0],
        600.0,
        72.0,
        200.0,
        -35.0,
    );
    back.scene = scene(
        "back tilt 72, k1 -0.2",
        8,
        camera((1280, 960), 1100.0, barrel),
        Side::Back,
        [20.0, -10.0],
        600.0,
        72.0,
        200.0,
        -35.0,
        two_dn(0.8),
    );
    check(&[
        front(
            "tilt 75",
            7,
            plain(VGA, 1000.0),
            [-10.0, 5.0],
            500.0,
            75.0,
            60.0,
            10.0,
        ),
        // Close range: strong perspective, circle sizes vary 2× across the board.
        front(
            "tilt 65 close",
            9,
            plain((1024, 768), 800.0),
            [0.0, 0.0],
            330.0,
            65.0,
            330.0,
            80.0,
        ),
        back,
    ]);
}

#[test]
fn partial_views_radii_to_40_px() {
    check(&[
        // r ≈ 20 px around the centre cell.
        front(
            "partial with centre r20",
            11,
            plain(VGA, 1000.0),
            [25.0, -15.0],
            300.0,
            20.0,
            70.0,
            15.0,
        ),
        // r ≈ 24 px, far from the centre: an unanchored (side-fixed at most) frame.
        front(
            "partial no centre r24",
            12,
            plain(VGA, 1000.0),
            [190.0, 120.0],
            250.0,
            25.0,
            250.0,
            -40.0,
        ),
        // r ≈ 40 px: a handful of circles.
        front(
            "partial no centre r40",
            13,
            plain(VGA, 1000.0),
            [-150.0, -90.0],
            150.0,
            10.0,
            0.0,
            80.0,
        ),
        // r ≈ 40 px on the centre cell.
        front(
            "partial centre r40",
            14,
            plain((1024, 768), 1000.0),
            [3.0, 4.0],
            150.0,
            5.0,
            0.0,
            -30.0,
        ),
    ]);
}

#[test]
fn back_side() {
    let mk = |name: &str, seed, look, d, tilt, az, spin| Case {
        scene: scene(
            name,
            seed,
            plain(VGA, 900.0),
            Side::Back,
            look,
            d,
            tilt,
            az,
            spin,
            two_dn(0.8),
        ),
        band: Band::UpTo60,
        extras: Extras::default(),
        accuracy: true,
        min_radius: 4.0,
    };
    check(&[
        mk("back tilt 35", 21, [10.0, -5.0], 750.0, 35.0, 150.0, 25.0),
        mk(
            "back partial no centre",
            22,
            [-180.0, 90.0],
            350.0,
            40.0,
            300.0,
            -70.0,
        ),
    ]);
}

#[test]
fn occlusion() {
    let mut centre_free = front(
        "occluded off centre",
        31,
        plain(VGA, 900.0),
        [0.0, 0.0],
        700.0,
        25.0,
        45.0,
        10.0,
    );
    centre_free.extras.occluders = vec![
        Rect {
            x0: 480.0,
            y0: 80.0,
            x1: 640.0,
            y1: 260.0,
        },
        Rect {
            x0: 100.0,
            y0: 380.0,
            x1: 260.0,
            y1: 430.0,
        },
    ];
    // The centre cell hidden: labels in an arbitrary (or side-fixed) frame, still consistent.
    let mut centre_hidden = front(
        "occluded centre",
        32,
        plain(VGA, 900.0),
        [10.0, 10.0],
        700.0,
        30.0,
        200.0,
        -25.0,
    );
    centre_hidden.extras.occluders = vec![Rect {
        x0: 330.0,
        y0: 230.0,
        x1: 470.0,
        y1: 370.0,
    }];
    check(&[centre_free, centre_hidden]);
}

#[test]
fn strong_distortion() {
    let barrel = Distortion {
        k1: -0.3,
        k2: 0.08,
        ..Distortion::default()
    };
    check(&[
        front(
            "k1 -0.3 tilt 20",
            41,
            camera((1024, 768), 700.0, barrel),
            [0.0, 10.0],
            600.0,
            20.0,
            60.0,
            5.0,
        ),
        front(
            "k1 -0.3 tilt 45",
            42,
            camera((1024, 768), 700.0, barrel),
            [-30.0, 0.0],
            550.0,
            45.0,
            160.0,
            -30.0,
        ),
    ]);
}

#[test]
fn noise_and_blur() {
    let mk = |name: &str, seed, imaging: Imaging, accuracy| {
        let mut c = front(
            name,
            seed,
            plain(VGA, 1000.0),
            [8.0, -6.0],
            800.0,
            35.0,
            30.0,
            20.0,
        );
        c.scene.imaging = imaging;
        c.accuracy = accuracy;
        c
    };
    check(&[
        // The accuracy target's limit: 2 DN, PSF σ = 1 px.
        mk("2 DN, PSF 1.0", 51, two_dn(1.0), true),
        // Shot noise (σ ≈ 4.5 DN on white) and 4 DN read noise, PSF σ = 1.5 px: recall and
        // labels only.
        mk(
            "shot + 4 DN, PSF 1.5",
            52,
            Imaging {
                shot_gain: 0.1,
                read_noise: 4.0,
                psf_sigma: 1.5,
                ..Imaging::default()
            },
            false,
        ),
        // 16-bit output, vignetting 30 %, default noise.
        mk(
            "16 bit, vignetting",
            53,
            Imaging {
                bits: 16,
                vignetting: 0.3,
                ..Imaging::default()
            },
            false,
        ),
    ]);
}

#[test]
fn distractor_blobs_off_the_board() {
    let mut case = front(
        "distractors",
        61,
        plain((1024, 768), 900.0),
        [0.0, 0.0],
        1300.0,
        15.0,
        80.0,
        5.0,
    );
    // Single white disks of radius 5–25 px, and a hexagonal cluster of seven (radius 5 px,
    // pitch d/R = 10/3 radii as on the board): it forms a full lattice cell of its own.
    let mut blobs: Vec<(Point2<f64>, f64)> = [
        (60.0, 100.0, 8.0),
        (180.0, 660.0, 12.0),
        (900.0, 120.0, 5.0),
        (940.0, 600.0, 15.0),
        (900.0, 380.0, 25.0),
    ]
    .iter()
    .map(|&(x, y, r)| (Point2::new(x, y), r))
    .collect();
    let centre = Point2::new(140.0, 380.0);
    blobs.push((centre, 5.0));
    for k in 0..6 {
        let a = std::f64::consts::FRAC_PI_3 * f64::from(k) + 0.2;
        blobs.push((
            centre + nalgebra::Vector2::new(a.cos(), a.sin()) * 50.0 / 3.0,
            5.0,
        ));
    }
    // Guard: every blob clear of the board's image (bounding box of its projected corners).
    let pose = case.scene.pose.cam_from_board().unwrap();
    let corners: Vec<Point2<f64>> = [
        [-300.0, -250.0],
        [300.0, -250.0],
        [300.0, 250.0],
        [-300.0, 250.0],
    ]
    .iter()
    .map(|&[x, y]| {
        case.scene
            .camera
            .project(&(pose * Point3::new(x, y, 0.0)))
            .unwrap()
    })
    .collect();
    let (x0, x1) = corners
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.x), b.max(p.x)));
    let (y0, y1) = corners
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.y), b.max(p.y)));
    for (c, r) in &blobs {
        let outside = c.x + r + 10.0 < x0
            || c.x - r - 10.0 > x1
            || c.y + r + 10.0 < y0
            || c.y - r - 10.0 > y1;
        assert!(
            outside,
            "blob at {c} overlaps the board's image [{x0}, {x1}] × [{y0}, {y1}]"
        );
    }
    case.extras.distractors = blobs;
    check(&[case]);
}

/// Issue 32 item 4 (b): steep views (60–73°) of a board far enough that its circles have
/// √(ab) = 3–4.5 px, the far side's foreshortened by perspective to a/b ≈ 4.5, minor
/// semi-axes ≈ 1.5 px; every whole, unoccluded circle of √(ab) ≥ 3 px counts, against the
/// issue's targets. With the detector's scales reaching a/b = 5 (σ = 1.68 px) these views
/// reach 0.9979 detected and 0.9946 labelled pooled, 0.9925 / 0.9820 at 72° (with scales to
/// a/b = 4: 0.9912 / 0.9866 pooled, 0.9715 / 0.9565 at 72°), and labels ≥ 0.9912 of the
/// circles whose cell is whole in view in every view. The fits to what an
/// occluder leaves of a circle that those scales also find are dropped by the grid's lattice
/// check (`bars_split_the_board` in tests/grid_occluders.rs).
#[test]
fn steep_views_of_small_circles() {
    let views = [
        (60.0, 20.0, 10.0, 1000.0),
        (63.0, 100.0, -30.0, 950.0),
        (66.0, 200.0, 45.0, 900.0),
        (68.0, 300.0, 0.0, 850.0),
        (70.0, 45.0, 80.0, 800.0),
        (71.0, 150.0, -60.0, 780.0),
        (72.0, 250.0, 20.0, 760.0),
        (73.0, 340.0, -10.0, 740.0),
    ];
    let cases: Vec<Case> = views
        .iter()
        .zip(300..)
        .map(|(&(tilt, azimuth, spin, d), seed)| {
            let name = format!("steep {tilt}°, r 3–4.5");
            let mut c = front(
                &name,
                seed,
                plain(VGA, 900.0),
                [0.0, 0.0],
                d,
                tilt,
                azimuth,
                spin,
            );
            (c.band, c.min_radius) = (Band::Steep, 3.0);
            c
        })
        .collect();
    check(&cases);
}
