//! Rendered stacks through the whole chain: three projectors light the board at once under
//! the default stack conditions (docs/design.md §9: ambient 40 DN on white, the projectors
//! sharing the rest up to 235 DN, gamma 2.2 uncorrected, so N = 15 and 90 frames, 8 bit,
//! read noise 2 DN, shot noise, PSF σ 0.8 px), seen through a k1 = −0.3 lens; the decoder
//! turns each stack into (u, v) maps, detection and the grid label the circles on the
//! decoded ambient image, and the correspondence stage fits projector pixels at the ellipse
//! centres — all compared with the exact projector geometry.

use crate::correspond::{camera_view, FitParams, ProjectorMap};
use crate::detect::{detect, DetectParams};
use crate::grid::{build, GridParams};
use crate::phase::DecodedStack;
use hexcal_core::board::Board;
use hexcal_core::camera::CameraModel;
use hexcal_core::camera::{Distortion, Intrinsics};
use hexcal_core::observations::CameraView;
use hexcal_core::pattern::Sequence;
use hexcal_sim::stack::*;
use hexcal_sim::Scene;
use hexcal_sim::{Imaging, PoseSpec};
use hexcal_simulator::Frame;
use nalgebra::Point2;
use nalgebra::{Isometry3, Point3};
use {
    crate::phase::{Decoder, FrameRef},
    hexcal_core::pattern::{ProjectorResponse, ProjectorSetup},
};

fn look(eye: [f64; 3]) -> Isometry3<f64> {
    PoseSpec {
        eye: Some(eye),
        target: Some([0.0, 0.0, 0.0]),
        ..PoseSpec::default()
    }
    .cam_from_board()
    .unwrap()
}

/// Three projectors (the default P = 3 sequence) lighting the whole board, without lens
/// shift so that the board lies inside each raster.
fn projectors() -> Vec<StackProjector> {
    let raster = CameraModel {
        width: 1920,
        height: 1080,
        intrinsics: Intrinsics {
            fx: 2200.0,
            fy: 2200.0,
            cx: 960.0,
            cy: 540.0,
        },
        distortion: Distortion::default(),
    };
    let (ambient, white) = (AMBIENT, 235.0);
    [
        [-350.0, 80.0, 1100.0],
        [380.0, -60.0, 1050.0],
        [20.0, 320.0, 1150.0],
    ]
    .into_iter()
    .map(|eye| StackProjector {
        model: raster,
        proj_from_board: look(eye),
        gain_dn: (white - ambient) / 3.0,
    })
    .collect()
}

/// Ambient light on white (DN), docs/design.md §9.
const AMBIENT: f64 = 40.0;

/// A 640×480 camera with a k1 = −0.3 lens of 50° × 40° field: circles of 11 px radius at the
/// image centre shrink to ≈ 0.7 of that in the corners.
fn camera() -> CameraModel {
    CameraModel {
        width: 640,
        height: 480,
        intrinsics: Intrinsics {
            fx: 560.0,
            fy: 560.0,
            cx: 322.0,
            cy: 238.0,
        },
        distortion: Distortion {
            k1: -0.3,
            k2: 0.09,
            ..Distortion::default()
        },
    }
}

/// One circle's projector pixel under one projector: where the camera saw the circle, its
/// radius (px) and the error (u, v) against the exact geometry at the detected centre.
struct CircleError {
    /// The circle's lattice position in its view.
    hex: hexcal_core::board::Hex,
    image: Point2<f64>,
    radius: f64,
    error: [f64; 2],
    /// The fit's predicted noise (u, v): the decoder's per-pixel noise through the
    /// weighted fit's normal equations.
    sigma: [f64; 2],
    /// Whether the circle carries a marker ring.
    ringed: bool,
}

/// (circle, projector) pairs where the projector lights the whole circle, and of those the
/// pairs with a projector pixel: plain circles, ringed ones, and the ringed ones whose
/// labelled neighbours do not surround them (on a view's edge, [`super::surrounded`]).
#[derive(Clone, Copy, Debug, Default)]
struct Pairs {
    plain: [usize; 2],
    ringed: [usize; 2],
    ringed_edge: [usize; 2],
}

impl std::ops::AddAssign for Pairs {
    fn add_assign(&mut self, o: Pairs) {
        for i in 0..2 {
            self.plain[i] += o.plain[i];
            self.ringed[i] += o.ringed[i];
            self.ringed_edge[i] += o.ringed_edge[i];
        }
    }
}

impl std::fmt::Display for Pairs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "pairs lit whole with a projector pixel: plain {} of {}, ringed {} of {}, ringed on \
             a view's edge {} of {}",
            self.plain[1],
            self.plain[0],
            self.ringed[1],
            self.ringed[0],
            self.ringed_edge[1],
            self.ringed_edge[0]
        )
    }
}

/// The default stack scene seen from `eye` towards `target`, rendered and decoded: the
/// scene, the projectors, the renderer (the truth) and the decoded stack.
fn decode_pose(
    eye: [f64; 3],
    target: [f64; 3],
    seed: u64,
) -> (Scene, Vec<StackProjector>, StackRenderer, DecodedStack) {
    let scene = Scene {
        name: "stack".into(),
        seed,
        camera: camera(),
        pose: PoseSpec {
            eye: Some(eye),
            target: Some(target),
            ..PoseSpec::default()
        },
        imaging: Imaging::default(),
        board: Board::hex600(),
    };
    let projectors = projectors();
    let setup = ProjectorSetup {
        width: 1920,
        height: 1080,
        response: ProjectorResponse::Gamma { gamma: 2.2 },
    };
    let seq = Sequence::default_for(&[setup; 3]).unwrap();
    let renderer = StackRenderer::new(&scene, &projectors, AMBIENT, &seq).unwrap();
    let size = renderer.size();
    let mut decoder = Decoder::<u16>::new(&seq, "cam", size.width, size.height, 255.0).unwrap();
    for k in 0..seq.frame_count() {
        let frame = renderer.frame(k);
        decoder
            .push_frame(
                k,
                FrameRef {
                    width: size.width,
                    height: size.height,
                    pixels: &frame.data,
                },
            )
            .unwrap();
    }
    let decoded = decoder.finish().unwrap();
    (scene, projectors, renderer, decoded)
}

/// Per pixel: decoded against true (u, v) on valid pixels inside uniform regions (no
/// albedo change within ±3 px ≈ 4 PSF σ: near an edge the PSF mixes the phases of
/// differently bright neighbours, which is optics, not decoding), against the predicted σ_u,
/// over more than `min_pixels` pixels of each projector.
fn check_pixels(renderer: &StackRenderer, decoded: &DecodedStack, min_pixels: usize) {
    let size = renderer.size();
    let (w, h) = (size.width as usize, size.height as usize);
    for (p, maps) in decoded.projectors.iter().enumerate() {
        let truth = renderer.truth(p);
        let (mut sq, mut n, mut worst) = (0.0, 0usize, 0.0f64);
        let (mut interior, mut interior_valid) = (0usize, 0usize);
        for i in 0..w * h {
            if !(truth.lit(i) && renderer.albedo(i) > 0.9 && renderer.uniform_albedo(i, 3)) {
                continue;
            }
            interior += 1;
            if maps.valid.as_slice()[i] {
                interior_valid += 1;
                let e = f64::from(maps.u.as_raw()[i] - truth.u(i));
                sq += e * e;
                n += 1;
                worst = worst.max(e.abs());
            }
        }
        let rms = (sq / n as f64).sqrt();
        let predicted = maps.noise.sigma_u;
        // ≥ 99 % of the lit circles' interior pixels valid.
        assert!(
            interior_valid as f64 >= 0.99 * interior as f64,
            "{interior_valid} of {interior}"
        );
        // docs/design.md §6 acceptance: RMS ≤ 1.2 × prediction, no unwrapping error.
        assert!(
            n > min_pixels && rms <= 1.2 * predicted,
            "projector {p}: {rms} vs {predicted}"
        );
        assert!(
            worst <= (6.0 * predicted).max(1.0),
            "projector {p}: worst {worst}"
        );
    }
}

/// Detection and the grid on the decoded ambient image (evenly lit, and averaged over the
/// whole stack), and the camera view of the grid under the decoded maps.
fn view_of(
    scene: &Scene,
    decoded: &DecodedStack,
) -> (Vec<crate::detect::Circle>, crate::grid::Grid, CameraView) {
    let image = decoded.ambient.clone();
    let circles = detect(&image, &DetectParams::default());
    let grid = build(&image, &circles, &scene.board, &GridParams::default());
    assert!(grid.anchored && grid.points.len() > 200, "{:?}", grid.stats);
    let maps: Vec<ProjectorMap> = decoded
        .projectors
        .iter()
        .enumerate()
        .map(|(p, m)| ProjectorMap::from_decoded(p, m))
        .collect();
    let params = FitParams::for_board(&scene.board);
    let view = camera_view(0, 0, &grid, &circles, &maps, &params).unwrap();
    (circles, grid, view)
}

/// Render, decode, detect, label and fit one board pose seen from `eye`; checks the per-pixel
/// decoding on the way (over more than `min_pixels` pixels of each projector).
fn circle_errors(
    eye: [f64; 3],
    target: [f64; 3],
    seed: u64,
    min_pixels: usize,
) -> (Vec<CircleError>, Pairs) {
    let camera = camera();
    let (scene, projectors, renderer, decoded) = decode_pose(eye, target, seed);
    check_pixels(&renderer, &decoded, min_pixels);
    let (circles, grid, view) = view_of(&scene, &decoded);
    let params = FitParams::for_board(&scene.board);
    let pairs = lit_pairs(&renderer, &grid, &circles, &view);

    // Projector pixels at the detected ellipse centres against the exact geometry there.
    let board_from_cam = scene.pose.cam_from_board().unwrap().inverse();
    let exact = |p: usize, e: Point2<f64>| {
        let ray = camera.ray(e)?;
        let (o, d) = (board_from_cam * Point3::origin(), board_from_cam * ray);
        let x = o + d * (-o.z / d.z);
        projectors[p]
            .model
            .project(&(projectors[p].proj_from_board * x))
    };
    let mut out = Vec::new();
    for (pt, lp) in view.points.iter().zip(&grid.points) {
        let e = &circles[lp.circle].ellipse;
        for pp in &pt.projectors {
            let t = exact(pp.projector, pt.image).unwrap();
            let m = &decoded.projectors[pp.projector];
            let s0 = fit_sigma(&grid, &circles, lp, m, &params);
            // σ_u(x) = σ_u·B̄/B(x): the decoder's run-level prediction at its mean modulation.
            let k = m.noise.modulation * s0;
            out.push(CircleError {
                hex: pt.hex,
                image: pt.image,
                radius: (e.a * e.b).sqrt(),
                error: [pp.pixel.x - t.x, pp.pixel.y - t.y],
                sigma: [k * m.noise.sigma_u, k * m.noise.sigma_v],
                ringed: lp.ringed,
            });
        }
    }
    (out, pairs)
}

/// √[(AᵀWA)⁻¹]₀₀ of the correspondence fit (24) at `lp` under one projector's maps: its
/// patch (the circle and its labelled neighbours, ring bands left out), valid pixels
/// weighted by modulation² as the fit weighs them. With per-pixel noise σ(x) = k/B(x) the
/// fitted constant has σ = k times this.
fn fit_sigma(
    grid: &crate::grid::Grid,
    circles: &[crate::detect::Circle],
    lp: &crate::grid::LabelledPoint,
    maps: &crate::phase::ProjectorMaps,
    params: &FitParams,
) -> f64 {
    let (w, h) = (maps.u.width(), maps.u.height());
    let by_hex: std::collections::HashMap<_, _> = grid.points.iter().map(|q| (q.hex, q)).collect();
    let neighbours = lp.hex.neighbours();
    let members =
        std::iter::once(lp).chain(neighbours.iter().filter_map(|h| by_hex.get(h).copied()));
    let scale = 3.0 * circles[lp.circle].ellipse.a.max(1.0);
    let mut ata = nalgebra::SMatrix::<f64, 6, 6>::zeros();
    for q in members {
        for (x, y) in params.white_pixels(&circles[q.circle].ellipse, q.ringed, w, h) {
            let i = (y * w + x) as usize;
            if !maps.valid.as_slice()[i] {
                continue;
            }
            let b = f64::from(maps.modulation.as_raw()[i]);
            let (dx, dy) = (
                (f64::from(x) - lp.image.x) / scale,
                (f64::from(y) - lp.image.y) / scale,
            );
            let row = nalgebra::SVector::<f64, 6>::from([1.0, dx, dy, dx * dx, dx * dy, dy * dy]);
            ata += row * row.transpose() * (b * b);
        }
    }
    ata.try_inverse()
        .map_or(f64::INFINITY, |m| m[(0, 0)].sqrt())
}

/// Count the (circle, projector) pairs where the projector lights every pixel of a labelled
/// circle that lies wholly in the image, and those of them with a projector pixel.
fn lit_pairs(
    renderer: &StackRenderer,
    grid: &crate::grid::Grid,
    circles: &[crate::detect::Circle],
    view: &hexcal_core::observations::CameraView,
) -> Pairs {
    let size = renderer.size();
    let mut pairs = Pairs::default();
    let by_hex: std::collections::HashMap<_, _> = grid.points.iter().map(|q| (q.hex, q)).collect();
    for (pt, lp) in view.points.iter().zip(&grid.points) {
        let e = &circles[lp.circle].ellipse;
        let patch: Vec<(&hexcal_core::images::Ellipse, bool)> = std::iter::once((e, lp.ringed))
            .chain(
                (lp.hex.neighbours().iter())
                    .filter_map(|h| by_hex.get(h))
                    .map(|q| (&circles[q.circle].ellipse, q.ringed)),
            )
            .collect();
        let edge = lp.ringed && !super::surrounded(&patch);
        let m = e.a + 2.0;
        if e.center.x < m
            || e.center.y < m
            || e.center.x + m > f64::from(size.width)
            || e.center.y + m > f64::from(size.height)
        {
            continue;
        }
        let whole = FitParams {
            shrink: 1.0,
            ..FitParams::default()
        }
        .white_pixels(e, false, size.width, size.height);
        for p in 0..projectors().len() {
            let truth = renderer.truth(p);
            if whole
                .iter()
                .all(|&(x, y)| truth.lit((y * size.width + x) as usize))
            {
                let count = match (lp.ringed, edge) {
                    (true, true) => &mut pairs.ringed_edge,
                    (true, false) => &mut pairs.ringed,
                    (false, _) => &mut pairs.plain,
                };
                count[0] += 1;
                count[1] += usize::from(pt.projectors.iter().any(|q| q.projector == p));
            }
        }
    }
    pairs
}

#[test]
fn decoded_stack_gives_projector_pixels_at_circle_centres() {
    // Issue 9: RMS per axis ≤ 0.03 projector px for circles of radius ≥ 8 px, ≤ 0.06 px for
    // 5–8 px; mean error ≤ 0.005 px everywhere in the image, corners of a k1 = −0.3 lens
    // included. Four board poses at 300 and 400 mm fill the image (the board reaches every
    // corner) with circles of 5–12 px.
    let views = [
        ([20.0, -15.0, 300.0], [10.0, 0.0, 0.0]),
        ([-25.0, 20.0, 310.0], [-10.0, 5.0, 0.0]),
        ([30.0, 25.0, 400.0], [5.0, -5.0, 0.0]),
        ([-30.0, -20.0, 410.0], [0.0, 5.0, 0.0]),
    ];
    let mut pairs = Pairs::default();
    let mut all: Vec<(usize, CircleError)> = Vec::new();
    for (k, &(eye, target)) in views.iter().enumerate() {
        let (errors, p) = circle_errors(eye, target, 11 + k as u64, 10_000);
        all.extend(errors.into_iter().map(|c| (k, c)));
        pairs += p;
    }
    // Issue 21: every pair where the projector lights the whole circle gives a projector
    // pixel, marker (ringed) circles included.
    eprintln!("{pairs}");
    assert!(pairs.ringed[0] >= 100, "{pairs:?}");
    assert_eq!(pairs.ringed[0], pairs.ringed[1], "{pairs:?}");
    assert_eq!(pairs.plain[0], pairs.plain[1], "{pairs:?}");
    for (name, range, limit) in [
        ("r ≥ 8", 8.0..f64::INFINITY, 0.03),
        ("5 ≤ r < 8", 5.0..8.0, 0.06),
    ] {
        let bin: Vec<&CircleError> = all
            .iter()
            .filter(|(_, c)| range.contains(&c.radius))
            .map(|(_, c)| c)
            .collect();
        // Enough circles that the RMS means something (relative standard error 1/√(2n) of
        // n ≥ 100 observations ≤ 7 %) and the bin cannot pass empty.
        let circles: std::collections::HashSet<_> = all
            .iter()
            .filter(|(_, c)| range.contains(&c.radius))
            .map(|(k, c)| (*k, c.hex))
            .collect();
        eprintln!("{name}: {} circles", circles.len());
        assert!(
            circles.len() >= 100,
            "{name}: only {} circles",
            circles.len()
        );
        for axis in 0..2 {
            let rms =
                (bin.iter().map(|c| c.error[axis].powi(2)).sum::<f64>() / bin.len() as f64).sqrt();
            eprintln!(
                "{name}: {} observations, axis {axis}: RMS {rms:.4} px (limit {limit})",
                bin.len()
            );
            assert!(rms <= limit, "{name} axis {axis}: RMS {rms} > {limit}");
            // The ringed circles' share (their fits have fewer pixels: checked below
            // against their own fit's noise).
            let ringed: Vec<f64> = bin
                .iter()
                .filter(|c| c.ringed)
                .map(|c| c.error[axis])
                .collect();
            let ringed_rms =
                (ringed.iter().map(|e| e * e).sum::<f64>() / ringed.len().max(1) as f64).sqrt();
            eprintln!(
                "{name}: of which {} ringed, axis {axis}: RMS {ringed_rms:.4} px",
                ringed.len()
            );
        }
    }
    // Issue 21: a ringed circle's fit is as sound as any: measured against the noise its own
    // fit predicts (fewer pixels, the dim white beside the ring weighted down), its errors
    // are those of a plain circle. Plain fits: normalised RMS within the decoder's own
    // acceptance (≤ 1.2 × prediction, §6) and not below 0.8; ringed: no more than the plain
    // circles' plus 4 standard errors of an RMS over their n observations (1/√(2n)).
    let normalised = |ringed: bool, axis: usize| {
        let z: Vec<f64> = all
            .iter()
            .map(|(_, c)| c)
            .filter(|c| c.ringed == ringed && c.radius >= 5.0)
            .map(|c| c.error[axis] / c.sigma[axis])
            .collect();
        let rms = (z.iter().map(|e| e * e).sum::<f64>() / z.len().max(1) as f64).sqrt();
        (rms, z.len())
    };
    for axis in 0..2 {
        let (plain, np) = normalised(false, axis);
        let (ringed, nr) = normalised(true, axis);
        let bound = plain * (1.0 + 4.0 / (2.0 * nr as f64).sqrt());
        eprintln!(
            "axis {axis}: normalised RMS plain {plain:.3} ({np}), ringed {ringed:.3} ({nr}, \
             bound {bound:.3})"
        );
        assert!(
            nr >= 100 && (0.8..=1.2).contains(&plain),
            "axis {axis}: {plain}"
        );
        assert!(ringed <= bound, "axis {axis}: ringed {ringed} > {bound}");
    }
    // Mean per axis in each ninth of the image (corners included): ≤ 0.005 px plus 4 standard
    // errors of that mean (Bonferroni over 18 means: a correct fit fails with P < 1.2·10⁻³).
    let camera = camera();
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    for gy in 0..3 {
        for gx in 0..3 {
            let region: Vec<&CircleError> = all
                .iter()
                .map(|(_, c)| c)
                .filter(|c| {
                    (3.0 * c.image.x / w).floor() as i32 == gx
                        && (3.0 * c.image.y / h).floor() as i32 == gy
                })
                .collect();
            let n = region.len() as f64;
            assert!(region.len() >= 30, "region ({gx}, {gy}): {n} observations");
            for axis in 0..2 {
                let mean = region.iter().map(|c| c.error[axis]).sum::<f64>() / n;
                let var = region
                    .iter()
                    .map(|c| (c.error[axis] - mean).powi(2))
                    .sum::<f64>()
                    / (n - 1.0);
                let se = (var / n).sqrt();
                eprintln!("region ({gx}, {gy}), {n} observations, axis {axis}: mean {mean:+.4} ± {se:.4} px");
                assert!(
                    mean.abs() <= 0.005 + 4.0 * se,
                    "region ({gx}, {gy}) axis {axis}: mean {mean} (SE {se})"
                );
            }
        }
    }
}

#[test]
fn flat_frames_light_the_board_evenly_and_leave_the_stack_as_it_was() {
    let scene = Scene {
        name: "flat".into(),
        seed: 3,
        camera: camera(),
        pose: PoseSpec {
            eye: Some([20.0, -15.0, 420.0]),
            target: Some([0.0, 0.0, 0.0]),
            ..PoseSpec::default()
        },
        imaging: Imaging::default(),
        board: Board::hex600(),
    };
    let setup = ProjectorSetup {
        width: 1920,
        height: 1080,
        response: ProjectorResponse::Gamma { gamma: 2.2 },
    };
    let seq = Sequence::default_for(&[setup; 3]).unwrap();
    let renderer = StackRenderer::new(&scene, &projectors(), AMBIENT, &seq).unwrap();
    let before = renderer.frame(7);
    let (white, black) = (renderer.flat_frame(true, 0), renderer.flat_frame(false, 0));
    // Where every projector lights a white part of the board (albedo near 1 at the pixel),
    // white reaches ambient + every projector's full light (235 DN), black the ambient.
    let n = renderer.size().width as usize * renderer.size().height as usize;
    let lit_white: Vec<usize> = (0..n)
        .filter(|&i| renderer.albedo(i) > 0.95 && (0..3).all(|p| renderer.truth(p).lit(i)))
        .collect();
    assert!(lit_white.len() > 1000, "{} pixels", lit_white.len());
    let mean = |f: &Frame| {
        lit_white.iter().map(|&i| f64::from(f.data[i])).sum::<f64>() / lit_white.len() as f64
    };
    // Gamma 2.2 of the camera and shot noise aside, the levels are the irradiances: a few
    // DN of blur from the dark gaps nearby (PSF σ 0.8 px) at most.
    let (w, b) = (mean(&white), mean(&black));
    eprintln!("flat white {w:.1} DN, black {b:.1} DN on lit white board");
    assert!((w - 235.0).abs() < 12.0, "white {w}");
    assert!((b - AMBIENT).abs() < 8.0, "black {b}");
    // Each flat frame has noise of its own; the same number renders the same frame.
    assert_ne!(white.data, renderer.flat_frame(true, 1).data);
    assert_eq!(white.data, renderer.flat_frame(true, 0).data);
    // Flat frames leave the stack's frames as they were.
    assert_eq!(renderer.frame(7).data, before.data);
    // The board's circles are found on the flat field, as a preview needs.
    let image =
        hexcal_core::images::FloatImage::from_fn(camera().width, camera().height, |x, y| {
            image::Luma([f32::from(white.data[(y * camera().width + x) as usize])])
        });
    let circles = detect(&image, &DetectParams::default());
    assert!(circles.len() > 100, "{} circles", circles.len());
}

/// Issue 32 item 4 (c): a 45° view whose ringed circles have radii of 3.5–9 px, 4.8–5.4 px
/// among them. The white beside such a ring is too few pixels and too dimmed by the blur for
/// 80 % of them to decode valid (9–22 pixels, 60–75 % valid), so these circles had no
/// projector pixel (48 of the 336 lit ringed pairs of these two views, radii 3.6–5.0 px). Every
/// pair where the projector lights the whole circle must have one — but for ringed circles on
/// a view's edge, whose neighbours lie to one side: judged over such a patch, the fit
/// extrapolates into the ring's gap (up to 0.8 projector px in v), so they are judged by
/// their own pixels as before, and counted apart — and from r = 4.5 px on
/// the ringed observations must be as sound as the plain ones against the noise their own
/// fits predict (as in the test above: the plain circles' normalised RMS plus 4 standard
/// errors).
#[test]
fn small_ringed_circles_in_a_45_degree_view() {
    let t = 45f64.to_radians();
    let (mut all, mut pairs) = (Vec::new(), Pairs::default());
    for (k, d) in [420.0, 460.0].into_iter().enumerate() {
        let eye = [30.0, -d * t.sin(), d * t.cos()];
        let (errors, p) = circle_errors(eye, [30.0, 0.0, 0.0], 40 + k as u64, 1000);
        pairs += p;
        all.extend(errors);
    }
    eprintln!("{pairs}");
    assert_eq!(pairs.ringed[0], pairs.ringed[1], "{pairs:?}");
    assert_eq!(pairs.plain[0], pairs.plain[1], "{pairs:?}");
    let small = all
        .iter()
        .filter(|c| c.ringed && (4.8..5.4).contains(&c.radius))
        .count();
    assert!(small >= 30, "{small} ringed observations of 4.8–5.4 px");
    let normalised = |ringed: bool, axis: usize| {
        let z: Vec<f64> = all
            .iter()
            .filter(|c| c.ringed == ringed && c.radius >= 4.5)
            .map(|c| c.error[axis] / c.sigma[axis])
            .collect();
        let rms = (z.iter().map(|e| e * e).sum::<f64>() / z.len().max(1) as f64).sqrt();
        (rms, z.len())
    };
    for axis in 0..2 {
        let ((plain, np), (ringed, nr)) = (normalised(false, axis), normalised(true, axis));
        let bound = plain * (1.0 + 4.0 / (2.0 * nr as f64).sqrt());
        eprintln!(
            "axis {axis}, r ≥ 4.5: normalised RMS plain {plain:.3} ({np}), ringed {ringed:.3} \
             ({nr}, bound {bound:.3})"
        );
        assert!(
            nr >= 100 && ringed <= bound,
            "axis {axis}: ringed {ringed} > {bound}"
        );
    }
}
