//! Grids split by occluders (issue 21): bars, blobs and a hand-like shape across the centre
//! cell, painted over simulated views (`hexcal::sim::render`) at tilts 10–70°, both sides and a
//! k1 = −0.2 lens, through the real detector and grid builder.
//!
//! Checked per view against the truth:
//! - labelled recall ≥ 0.99 of the circles whose whole cell (the circle and its six
//!   neighbours) is in view, whole and untouched by the occluder, counting only the grid
//!   itself (the joined components), not the pieces left beside it;
//! - no wrong label: in the grid and in every piece, every labelled point is a true circle of
//!   the seen side, all points follow one lattice transform of the truth, and anchored points
//!   carry their true (q, r, side).
//!
//! The recall bound is the acceptance target; the views' circles (radius ≥ 4 px, tilt
//! ≤ 70°) are all detected by the detector's own acceptance (docs/design.md §4), so what a
//! view misses is the grid's.

use hexcal::app::detect::{analyse, Settings};
use hexcal::board::{Board, Hex, Side};
use hexcal::camera::{CameraModel, Distortion, Intrinsics};
use hexcal::grid::{build, Grid, GridParams};
use hexcal::images::FloatImage;
use hexcal::sim::{render, CircleTruth, Imaging, PoseSpec, Scene};
use nalgebra::{Point3, Vector2, Vector3};
use std::collections::{HashMap, HashSet};

/// One part of an occluder (image px).
#[derive(Clone, Copy, Debug)]
enum Part {
    /// The points within `radius` of the segment `a`–`b` (a bar, a finger).
    Capsule {
        a: [f64; 2],
        b: [f64; 2],
        radius: f64,
    },
    /// A filled ellipse: centre, semi-axes, angle of the first axis (rad).
    Ellipse {
        c: [f64; 2],
        axes: [f64; 2],
        angle: f64,
    },
}

impl Part {
    fn contains(&self, p: Vector2<f64>) -> bool {
        match *self {
            Part::Capsule { a, b, radius } => {
                let (a, b) = (Vector2::from(a), Vector2::from(b));
                let t = ((p - a).dot(&(b - a)) / (b - a).norm_squared()).clamp(0.0, 1.0);
                (p - (a + (b - a) * t)).norm() <= radius
            }
            Part::Ellipse { c, axes, angle } => {
                let d = p - Vector2::from(c);
                let (s, co) = angle.sin_cos();
                let (u, v) = (d.x * co + d.y * s, -d.x * s + d.y * co);
                (u / axes[0]).powi(2) + (v / axes[1]).powi(2) <= 1.0
            }
        }
    }
}

/// An occluder: its parts and its grey level (DN), lighter towards +x by `shade` DN per
/// 100 px (a hand or a bar is not evenly lit).
#[derive(Clone, Debug)]
struct Occluder {
    parts: Vec<Part>,
    level: f64,
    shade: f64,
}

/// A bar across the image through `c` at `angle` (deg), `width` px wide.
fn bar(c: [f64; 2], angle: f64, width: f64, level: f64) -> Occluder {
    let (s, co) = angle.to_radians().sin_cos();
    let reach = 2000.0;
    Occluder {
        parts: vec![Part::Capsule {
            a: [c[0] - reach * co, c[1] - reach * s],
            b: [c[0] + reach * co, c[1] + reach * s],
            radius: width / 2.0,
        }],
        level,
        shade: 0.0,
    }
}

/// Blobs: disks and ellipses (centre, semi-axes, angle in degrees).
fn blobs(list: &[([f64; 2], [f64; 2], f64)], level: f64) -> Occluder {
    Occluder {
        parts: list
            .iter()
            .map(|&(c, axes, angle)| Part::Ellipse {
                c,
                axes,
                angle: angle.to_radians(),
            })
            .collect(),
        level,
        shade: 0.0,
    }
}

/// A hand reaching over the board close to the camera: a palm over `c`, four long fingers and
/// a thumb spread out from it and the forearm out of the view, turned by `angle` (deg);
/// `scale` 1 is a palm 110 × 130 px with fingers 20 px wide and up to 300 px long, a forearm
/// 90 px wide.
fn hand(c: [f64; 2], angle: f64, scale: f64) -> Occluder {
    let (s, co) = angle.to_radians().sin_cos();
    let at = |x: f64, y: f64| {
        [
            c[0] + scale * (x * co - y * s),
            c[1] + scale * (x * s + y * co),
        ]
    };
    let mut parts = vec![Part::Ellipse {
        c,
        axes: [55.0 * scale, 65.0 * scale],
        angle: angle.to_radians(),
    }];
    // Fingers from the palm's top edge, fanned; the thumb from its side.
    for (x0, dx, len) in [
        (-36.0, -0.3, 250.0),
        (-12.0, -0.1, 300.0),
        (12.0, 0.1, 290.0),
        (34.0, 0.3, 230.0),
    ] {
        parts.push(Part::Capsule {
            a: at(x0, -50.0),
            b: at(x0 + dx * len, -50.0 - len),
            radius: 10.0 * scale,
        });
    }
    parts.push(Part::Capsule {
        a: at(45.0, 10.0),
        b: at(150.0, -60.0),
        radius: 12.0 * scale,
    });
    // The forearm, out of the view.
    parts.push(Part::Capsule {
        a: at(0.0, 40.0),
        b: at(30.0, 900.0),
        radius: 45.0 * scale,
    });
    Occluder {
        parts,
        level: 150.0,
        shade: 12.0,
    }
}

/// One view: a side seen from `d` mm towards `look` (mm, the side's frame), tilted by `tilt`
/// degrees towards azimuth `azimuth`, image "up" turned by `spin`; the occluders painted over.
struct Case {
    name: &'static str,
    side: Side,
    look: [f64; 2],
    d: f64,
    tilt: f64,
    azimuth: f64,
    spin: f64,
    k1: f64,
    occluders: Vec<Occluder>,
    /// PSF σ (px) and read noise (DN) of the camera.
    psf: f64,
    read_noise: f64,
}

const SIZE: (u32, u32) = (800, 600);

fn scene(case: &Case, seed: u64) -> Scene {
    let board = Board::hex600();
    let (t, a, s) = (
        case.tilt.to_radians(),
        case.azimuth.to_radians(),
        case.spin.to_radians(),
    );
    let iso = board.side_transform(case.side);
    let target = iso * Point3::new(case.look[0], case.look[1], 0.0);
    let eye = iso
        * Point3::new(
            case.look[0] + case.d * t.sin() * a.cos(),
            case.look[1] + case.d * t.sin() * a.sin(),
            case.d * t.cos(),
        );
    let up = iso.rotation * Vector3::new(s.sin(), s.cos(), 0.0);
    Scene {
        name: case.name.into(),
        seed,
        camera: CameraModel {
            width: SIZE.0,
            height: SIZE.1,
            intrinsics: Intrinsics {
                fx: 900.0,
                fy: 900.0,
                cx: 401.3,
                cy: 298.2,
            },
            distortion: Distortion {
                k1: case.k1,
                ..Distortion::default()
            },
        },
        pose: PoseSpec {
            eye: Some([eye.x, eye.y, eye.z]),
            target: Some([target.x, target.y, target.z]),
            up: Some([up.x, up.y, up.z]),
            ..PoseSpec::default()
        },
        imaging: Imaging {
            shot_gain: 0.0,
            read_noise: case.read_noise,
            psf_sigma: case.psf,
            ..Imaging::default()
        },
        board,
    }
}

/// The rendered view with the occluders painted in (4×4 supersampled coverage), and the mask
/// of pixels they touch.
fn image_of(case: &Case, seed: u64) -> (FloatImage, Vec<bool>, Vec<CircleTruth>) {
    let view = render(&scene(case, seed)).unwrap();
    let (w, h) = SIZE;
    let mut img = FloatImage::from_raw(w, h, view.frame.data.iter().map(|&v| v as f32).collect())
        .expect("frame size");
    let mut mask = vec![false; (w * h) as usize];
    for y in 0..h {
        for x in 0..w {
            for o in &case.occluders {
                let mut cover = 0.0;
                for i in 0..4 {
                    for j in 0..4 {
                        let p = Vector2::new(
                            f64::from(x) - 0.375 + 0.25 * f64::from(i),
                            f64::from(y) - 0.375 + 0.25 * f64::from(j),
                        );
                        if o.parts.iter().any(|part| part.contains(p)) {
                            cover += 1.0 / 16.0;
                        }
                    }
                }
                if cover > 0.0 {
                    mask[(y * w + x) as usize] = true;
                    let level = (o.level + o.shade * f64::from(x) / 100.0) as f32;
                    let px = img.get_pixel_mut(x, y);
                    px.0[0] += (level - px.0[0]) * cover as f32;
                }
            }
        }
    }
    (img, mask, view.truth.circles)
}

/// Whether the occluder touches a truth circle (its ellipse grown by 2 px).
fn touched(t: &CircleTruth, mask: &[bool]) -> bool {
    let (Some(c), Some(ax), Some(angle)) = (t.ellipse, t.axes, t.angle_deg) else {
        return true;
    };
    let (s, co) = angle.to_radians().sin_cos();
    let (a, b) = (ax[0] + 2.0, ax[1] + 2.0);
    let (w, h) = (SIZE.0 as i64, SIZE.1 as i64);
    for y in (c[1] - a).floor() as i64..=(c[1] + a).ceil() as i64 {
        for x in (c[0] - a).floor() as i64..=(c[0] + a).ceil() as i64 {
            let (dx, dy) = (x as f64 - c[0], y as f64 - c[1]);
            let (u, v) = (dx * co + dy * s, -dx * s + dy * co);
            let inside = (u / a).powi(2) + (v / b).powi(2) <= 1.0;
            if inside && x >= 0 && y >= 0 && x < w && y < h && mask[(y * w + x) as usize] {
                return true;
            }
        }
    }
    false
}

/// Label errors of one grid (or piece) against the truth: points on no true circle of the
/// seen side, points outside the one lattice transform that maps most labels onto the
/// truth, anchored points with a wrong (q, r, side).
fn wrong_labels(grid: &Grid, truth_of: &[Option<Hex>], side: Side) -> usize {
    let mut wrong = 0;
    let mut votes: HashMap<(usize, Hex), usize> = HashMap::new();
    let mut pairs = 0;
    for p in &grid.points {
        let Some(t) = truth_of[p.circle] else {
            wrong += 1;
            continue;
        };
        if p.side.is_some_and(|s| s != side) || (p.anchored && p.hex != t) {
            wrong += 1;
        }
        pairs += 1;
        for s in 0..6 {
            *votes.entry((s, t - p.hex.rotate(s))).or_default() += 1;
        }
    }
    wrong + pairs - votes.values().copied().max().unwrap_or(0)
}

/// Figures of one view.
struct Figures {
    interior: usize,
    labelled: usize,
    /// Interior circles labelled without joining.
    unjoined: usize,
    pieces: usize,
    wrong: usize,
}

fn measure(case: &Case, seed: u64) -> Figures {
    let (img, mask, truth) = image_of(case, seed);
    let board = Board::hex600();
    let a = analyse(&img, &board, &Settings::default());
    // The same circles without joining: the grid is the component it started in.
    let unjoined = build(
        &img,
        &a.circles,
        &board,
        &GridParams {
            min_join_points: usize::MAX,
            ..GridParams::default()
        },
    );
    // Each detection's true circle: the nearest truth centre within a third of its radius.
    let truth_of: Vec<Option<Hex>> = a
        .circles
        .iter()
        .map(|c| {
            let p = c.ellipse.center;
            truth
                .iter()
                .filter(|t| t.side == case.side)
                .filter_map(|t| {
                    let q = t.ellipse.unwrap_or(t.proj);
                    let d = (p.x - q[0]).hypot(p.y - q[1]);
                    (d < t.radius.unwrap_or(4.0) / 3.0).then_some((d, Hex::new(t.q, t.r)))
                })
                .min_by(|x, y| x.0.total_cmp(&y.0))
                .map(|(_, h)| h)
        })
        .collect();
    let visible: HashSet<Hex> = truth
        .iter()
        .filter(|t| t.whole && t.radius.is_some_and(|r| r >= 4.0) && !touched(t, &mask))
        .map(|t| Hex::new(t.q, t.r))
        .collect();
    let interior: HashSet<Hex> = visible
        .iter()
        .copied()
        .filter(|h| h.neighbours().iter().all(|n| visible.contains(n)))
        .collect();
    let labelled = |g: &Grid| {
        g.points
            .iter()
            .filter(|p| truth_of[p.circle].is_some_and(|h| interior.contains(&h)))
            .count()
    };
    let wrong = wrong_labels(&a.grid, &truth_of, case.side)
        + a.grid
            .pieces
            .iter()
            .map(|p| wrong_labels(p, &truth_of, case.side))
            .sum::<usize>();
    Figures {
        interior: interior.len(),
        labelled: labelled(&a.grid),
        unjoined: labelled(&unjoined),
        pieces: a.grid.pieces.len(),
        wrong,
    }
}

/// Measure and print one case.
fn figures(case: &Case, seed: u64) -> Figures {
    let f = measure(case, seed);
    let recall = f.labelled as f64 / f.interior.max(1) as f64;
    println!(
        "{}: {} circles with their whole cell in view, labelled {} (recall {recall:.4}; \
         without joining {} = {:.4}), pieces left {}, wrong labels {}",
        case.name,
        f.interior,
        f.labelled,
        f.unjoined,
        f.unjoined as f64 / f.interior.max(1) as f64,
        f.pieces,
        f.wrong
    );
    f
}

fn check(cases: &[Case]) {
    let seeded: Vec<(&Case, u64)> = cases.iter().zip(100..).collect();
    check_seeded(&seeded);
}

/// [`check`] with a noise seed per view.
fn check_seeded(cases: &[(&Case, u64)]) {
    let mut failures = Vec::new();
    for &(case, seed) in cases {
        let f = figures(case, seed);
        let recall = f.labelled as f64 / f.interior.max(1) as f64;
        if f.interior < 100 {
            failures.push(format!(
                "{}: only {} interior circles",
                case.name, f.interior
            ));
        }
        if recall < 0.99 {
            failures.push(format!("{}: recall {recall:.4}", case.name));
        }
        if f.wrong > 0 {
            failures.push(format!("{}: {} wrong labels", case.name, f.wrong));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

fn front(name: &'static str, tilt: f64, azimuth: f64, spin: f64, occluders: Vec<Occluder>) -> Case {
    Case {
        name,
        side: Side::Front,
        look: [0.0, 0.0],
        d: 700.0,
        tilt,
        azimuth,
        spin,
        k1: 0.0,
        occluders,
        psf: 0.8,
        read_noise: 2.0,
    }
}

#[test]
fn bars_split_the_board() {
    check(&[
        front(
            "black bar, tilt 20",
            20.0,
            30.0,
            10.0,
            vec![bar([420.0, 300.0], 80.0, 60.0, 20.0)],
        ),
        front(
            "grey diagonal bar, tilt 45",
            45.0,
            120.0,
            -20.0,
            vec![bar([380.0, 320.0], 35.0, 45.0, 90.0)],
        ),
        front(
            "two crossing bars, tilt 55",
            55.0,
            210.0,
            40.0,
            vec![
                bar([300.0, 300.0], 70.0, 40.0, 20.0),
                bar([400.0, 250.0], -10.0, 35.0, 60.0),
            ],
        ),
        front(
            "bar, tilt 70",
            70.0,
            300.0,
            0.0,
            vec![bar([400.0, 300.0], 85.0, 50.0, 30.0)],
        ),
    ]);
}

/// A bar 150 px wide at 60° of tilt through a k1 = −0.3 lens: the far side's circles are a
/// third of the near side's, so the gap spans a dozen of their lattice steps. Predictions
/// that far out are not trusted: the far side stays a piece of its own, with no wrong label.
#[test]
fn a_gap_too_wide_to_bridge_is_left_alone() {
    let mut wide = front(
        "wide bar, tilt 60, k1 -0.3",
        60.0,
        20.0,
        -50.0,
        vec![bar([400.0, 300.0], 100.0, 150.0, 20.0)],
    );
    wide.k1 = -0.3;
    let f = figures(&wide, 99);
    assert_eq!(f.wrong, 0);
    assert!(f.pieces >= 1);
}

#[test]
fn blobs_cut_islands() {
    // A band cutting off the top-left corner, a ring of six blobs around an island of a few
    // cells, and two blobs at the right edge meeting to cut off a strip.
    let some = |level, ring: [f64; 2]| {
        let mut list = vec![
            ([170.0, 130.0], [230.0, 30.0], -40.0),
            ([760.0, 150.0], [60.0, 120.0], 30.0),
            ([730.0, 420.0], [50.0, 150.0], -20.0),
        ];
        for k in 0..6 {
            let a = f64::from(k) * std::f64::consts::FRAC_PI_3 + 0.3;
            list.push((
                [ring[0] + 95.0 * a.cos(), ring[1] + 95.0 * a.sin()],
                [55.0, 50.0],
                0.0,
            ));
        }
        blobs(&list, level)
    };
    check(&[
        front(
            "dark blobs, tilt 30",
            30.0,
            60.0,
            15.0,
            vec![some(25.0, [500.0, 380.0])],
        ),
        front(
            "grey blobs, tilt 65",
            65.0,
            160.0,
            -60.0,
            vec![some(110.0, [380.0, 170.0])],
        ),
    ]);
}

#[test]
fn a_hand_across_the_centre_cell() {
    let mut back = front(
        "hand, back side, tilt 40, k1 -0.2",
        40.0,
        250.0,
        25.0,
        vec![hand([410.0, 320.0], 15.0, 1.0)],
    );
    back.side = Side::Back;
    back.k1 = -0.2;
    check(&[
        front(
            "hand, tilt 10",
            10.0,
            0.0,
            0.0,
            vec![hand([400.0, 330.0], 0.0, 1.0)],
        ),
        front(
            "hand, tilt 50",
            50.0,
            90.0,
            -30.0,
            vec![hand([390.0, 300.0], -35.0, 0.9)],
        ),
        back,
    ]);
}

/// Issue 32 item 4 (a): a bar splitting the board in a view with heavy blur (PSF σ 1.4 px)
/// and noise (3.5 DN), at 700–1300 mm, so circles of 4–8 px. The circles the bar cuts keep
/// fits under such blur, with centres up to 2.7 px off; as the circles nearest the gap they
/// sat in every local homography predicting across it, and the far part stayed a piece
/// (recall 0.43–0.98 in these views before the fits left such circles out).
#[test]
fn bars_under_heavy_blur_and_noise() {
    let blurred = |name, d: f64, side: Side, tilt, azimuth, spin, angle, width, level| {
        let mut c = front(
            name,
            tilt,
            azimuth,
            spin,
            vec![bar([400.0, 300.0], angle, width, level)],
        );
        (c.d, c.side, c.psf, c.read_noise) = (d, side, 1.4, 3.5);
        c
    };
    let views = [
        (
            blurred(
                "700 mm, tilt 60",
                700.0,
                Side::Front,
                60.0,
                250.0,
                -45.0,
                60.0,
                55.0,
                15.0,
            ),
            532,
        ),
        (
            blurred(
                "1000 mm, tilt 60",
                1000.0,
                Side::Front,
                60.0,
                250.0,
                -45.0,
                60.0,
                55.0,
                15.0,
            ),
            534,
        ),
        (
            blurred(
                "1000 mm, tilt 60, back",
                1000.0,
                Side::Back,
                60.0,
                250.0,
                -45.0,
                60.0,
                55.0,
                15.0,
            ),
            542,
        ),
        (
            blurred(
                "1300 mm, tilt 30",
                1300.0,
                Side::Front,
                30.0,
                60.0,
                60.0,
                10.0,
                70.0,
                25.0,
            ),
            549,
        ),
        (
            blurred(
                "1300 mm, tilt 20",
                1300.0,
                Side::Front,
                20.0,
                30.0,
                10.0,
                80.0,
                60.0,
                20.0,
            ),
            553,
        ),
        (
            blurred(
                "700 mm, tilt 55, back",
                700.0,
                Side::Back,
                55.0,
                300.0,
                0.0,
                85.0,
                80.0,
                20.0,
            ),
            518,
        ),
    ];
    let seeded: Vec<(&Case, u64)> = views.iter().map(|(c, s)| (c, *s)).collect();
    check_seeded(&seeded);
}
