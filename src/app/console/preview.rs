//! The console's live preview (docs/design.md §15 "Live preview"): each preview frame a
//! camera takes while the board is placed (the projectors showing a flat field) is reduced
//! to at most [`DETECT_WIDTH`] pixels across, its circles are detected and labelled there,
//! and it becomes a small picture with the labelled points and lattice drawn over it.
//!
//! Takes one preview frame and the board; gives [`LiveView`]: the picture (PNG), the
//! overlay in the frame's own pixels and whether the camera sees the board.

use super::labels::Overlay;
use super::thumbs::{grey_png, WIDTH};
use crate::app::detect::Settings;
use crate::app::guide::stats::{count_view, ViewCount, MIN_POINTS};
use crate::board::{Board, Hex};
use crate::detect::detect;
use crate::grid::build;
use crate::images::{CameraFrame, FloatImage, Pixels};
use nalgebra::Point2;

/// Preview frames are detected at most this wide (px): a 1920-wide frame at half
/// resolution, where the paper rig's circles (radius ≈ 10 px) keep ≈ 5 px, above the
/// detector's smallest radius (4 px).
pub const DETECT_WIDTH: u32 = 960;

/// One camera's preview frame, seen.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveView {
    /// The picture (PNG, at most [`WIDTH`] across).
    pub png: Vec<u8>,
    /// Circles detected.
    pub circles: usize,
    /// Labelled points and lattice edges, in the frame's pixels.
    pub overlay: Overlay,
    /// What the view counts as, by the rule the captured poses are counted by ([`count_view`]):
    /// seen (the camera sees the board: at least [`MIN_POINTS`] labelled points), its tilt,
    /// steep or not.
    pub count: ViewCount,
    /// What each stage took.
    pub stages: Stages,
}

/// `frame` averaged over `factor` × `factor` blocks (samples as delivered); `None` when its
/// pixels do not fill its size.
pub fn reduced(frame: &CameraFrame, factor: u32) -> Option<FloatImage> {
    let (w, h) = (frame.width as usize, frame.height as usize);
    if frame.pixels.len() != w * h || factor == 0 {
        return None;
    }
    let at = |i: usize| -> f32 {
        match &frame.pixels {
            Pixels::Gray8(v) => f32::from(v[i]),
            Pixels::Gray16(v) => f32::from(v[i]),
        }
    };
    let f = factor as usize;
    let (rw, rh) = ((w / f).max(1), (h / f).max(1));
    if w < f || h < f {
        return None;
    }
    let scale = 1.0 / (f * f) as f32;
    let mut out = FloatImage::new(rw as u32, rh as u32);
    for (x, y, p) in out.enumerate_pixels_mut() {
        let (x0, y0) = (x as usize * f, y as usize * f);
        let mut sum = 0.0;
        for yy in y0..y0 + f {
            for xx in x0..x0 + f {
                sum += at(yy * w + xx);
            }
        }
        p.0[0] = sum * scale;
    }
    Some(out)
}

/// Time (ms) each stage of [`look`] took on one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Stages {
    /// Reducing the frame to the detection size.
    pub reduce: f64,
    /// Circle detection.
    pub detect: f64,
    /// Grid building (labelling).
    pub grid: f64,
    /// The picture: sampling and PNG encoding.
    pub picture: f64,
}

impl std::ops::AddAssign for Stages {
    fn add_assign(&mut self, o: Stages) {
        self.reduce += o.reduce;
        self.detect += o.detect;
        self.grid += o.grid;
        self.picture += o.picture;
    }
}

impl Stages {
    /// Every stage's time times `k`.
    pub fn scaled(self, k: f64) -> Stages {
        Stages {
            reduce: self.reduce * k,
            detect: self.detect * k,
            grid: self.grid * k,
            picture: self.picture * k,
        }
    }
}

/// Milliseconds since `t`, and restart `t`.
fn lap(t: &mut std::time::Instant) -> f64 {
    let now = std::time::Instant::now();
    let ms = 1e3 * (now - *t).as_secs_f64();
    *t = now;
    ms
}

/// Edge rays per circle of the preview's detection (the calibration's detector takes 90):
/// its centres are drawn on a picture of 6 frame pixels per pixel, and 20 rays keep their
/// error far below that.
pub const RAYS: usize = 20;

/// A full search of the frame at least every this many rounds, wherever the board was.
pub const FULL_EVERY: u32 = 5;

/// Where one camera saw the board in its last rounds: the next round looks there first.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Hint {
    /// The box (x0, y0, x1, y1; reduced frame px) of the labelled points last seen, with
    /// the largest circle radius among them, if the camera saw the board.
    area: Option<([f64; 4], f64)>,
    /// Rounds until the whole frame is searched again (0: this round).
    due: u32,
}

impl Hint {
    /// The region (x, y, width, height) of a `w` × `h` reduced frame to search this round,
    /// with the largest circle radius to look for; `None`: search the whole frame.
    ///
    /// The last box grows by a quarter of its larger side plus 8 circle radii each way: a
    /// board moved by hand between two rounds (a few tenths of a second, ~0.1 m) stays
    /// inside it, and the grid still gets the ring of circles around the labelled ones.
    fn region(&self, w: u32, h: u32) -> Option<([u32; 4], f64)> {
        let ([x0, y0, x1, y1], r) = self.area.filter(|_| self.due > 0)?;
        let m = 0.25 * (x1 - x0).max(y1 - y0) + 8.0 * r;
        let clamp = |v: f64, hi: u32| v.clamp(0.0, f64::from(hi)) as u32;
        let (a, b) = (clamp(x0 - m, w), clamp(y0 - m, h));
        let (c, d) = (clamp(x1 + m + 1.0, w), clamp(y1 + m + 1.0, h));
        // Circles up to twice the largest seen (the board may come closer or turn).
        (c > a + 16 && d > b + 16).then_some(([a, b, c - a, d - b], (2.0 * r).max(8.0)))
    }
}

/// The circles and grid of `image` (or of its `region`, with circles up to `max_radius`),
/// in the image's pixels.
fn find(
    image: &FloatImage,
    board: &Board,
    region: Option<([u32; 4], f64)>,
    stages: &mut Stages,
    t: &mut std::time::Instant,
) -> (Vec<crate::detect::Circle>, crate::grid::Grid) {
    let mut settings = Settings::default();
    settings.detect.rays = RAYS;
    let (cut, [x, y]) = match region {
        Some(([x, y, w, h], max_radius)) => {
            settings.detect.max_radius = max_radius.min(settings.detect.max_radius);
            let cut = ((w, h) != image.dimensions())
                .then(|| image::imageops::crop_imm(image, x, y, w, h).to_image());
            (cut, [f64::from(x), f64::from(y)])
        }
        None => (None, [0.0, 0.0]),
    };
    let src = cut.as_ref().unwrap_or(image);
    let mut circles = detect(src, &settings.detect);
    stages.detect += lap(t);
    let mut grid = build(src, &circles, board, &settings.grid);
    stages.grid += lap(t);
    let shift = nalgebra::Vector2::new(x, y);
    for c in &mut circles {
        c.ellipse.center += shift;
    }
    for p in &mut grid.points {
        p.image += shift;
    }
    (circles, grid)
}

/// The live view of one preview frame of the pose being placed (`pose`): detection and
/// grid building on the frame reduced to at most [`DETECT_WIDTH`] across, the overlay
/// scaled back to the frame's pixels (pixel centres: x = (x' + ½)·factor − ½).
///
/// `hint` is this camera's from the rounds before: where it saw the board, the search
/// keeps near there (and to circles of the size seen), the whole frame being searched
/// every [`FULL_EVERY`] rounds and whenever the board is not found near where it was. A
/// camera that does not see the board searches its whole frame every [`FULL_EVERY`]
/// rounds only (its picture still every round).
pub fn look(frame: &CameraFrame, board: &Board, pose: usize, hint: &mut Hint) -> Option<LiveView> {
    let mut t = std::time::Instant::now();
    let mut stages = Stages::default();
    let factor = frame.width.div_ceil(DETECT_WIDTH).max(1);
    let image = reduced(frame, factor)?;
    stages.reduce = lap(&mut t);
    let (w, h) = image.dimensions();
    let region = hint.region(w, h);
    let whole = |hint: &mut Hint, stages: &mut Stages, t: &mut std::time::Instant| {
        hint.due = FULL_EVERY;
        find(&image, board, None, stages, t)
    };
    let searched = match region {
        Some(r) => {
            let near = find(&image, board, Some(r), &mut stages, &mut t);
            match near.1.points.len() >= MIN_POINTS {
                true => Some(near),
                false => Some(whole(hint, &mut stages, &mut t)),
            }
        }
        None if hint.due == 0 || hint.area.is_some() => Some(whole(hint, &mut stages, &mut t)),
        None => None,
    };
    hint.due = hint.due.saturating_sub(1);
    let (circles, grid) = match searched {
        Some((circles, grid)) => {
            hint.area = seen_area(&circles, &grid);
            (circles, grid)
        }
        None => Default::default(),
    };
    let f = f64::from(factor);
    let full = |p: Point2<f64>| Point2::new((p.x + 0.5) * f - 0.5, (p.y + 0.5) * f - 0.5);
    let points: Vec<(Hex, Point2<f64>)> =
        grid.points.iter().map(|p| (p.hex, full(p.image))).collect();
    let overlay = Overlay::labelled(pose, circles.len(), grid.anchored, &points);
    let on_board: Vec<Point2<f64>> = points.iter().map(|(h, _)| board.position(*h)).collect();
    let pixels: Vec<Point2<f64>> = points.iter().map(|(_, p)| *p).collect();
    let count = count_view(&on_board, &pixels);
    let png = picture(&image)?;
    stages.picture = lap(&mut t);
    Some(LiveView {
        png,
        circles: circles.len(),
        count,
        overlay,
        stages,
    })
}

/// The box of `grid`'s labelled points and their largest circle radius, when they are
/// enough to call the board seen.
fn seen_area(
    circles: &[crate::detect::Circle],
    grid: &crate::grid::Grid,
) -> Option<([f64; 4], f64)> {
    if grid.points.len() < MIN_POINTS {
        return None;
    }
    let mut b = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    let mut r = 0.0f64;
    for p in &grid.points {
        b = [
            b[0].min(p.image.x),
            b[1].min(p.image.y),
            b[2].max(p.image.x),
            b[3].max(p.image.y),
        ];
        r = r.max(circles.get(p.circle).map_or(0.0, |c| c.ellipse.a));
    }
    Some((b, r))
}

/// The picture of a reduced frame: sampled to at most [`WIDTH`] across, as a PNG.
fn picture(image: &FloatImage) -> Option<Vec<u8>> {
    let (rw, rh) = image.dimensions();
    let step = rw.div_ceil(WIDTH).max(1);
    let (tw, th) = ((rw / step).max(1), (rh / step).max(1));
    let mut small = Vec::with_capacity((tw * th) as usize);
    for y in 0..th {
        for x in 0..tw {
            small.push(image.get_pixel(x * step + step / 2, y * step + step / 2).0[0]);
        }
    }
    grey_png(&small, tw, th)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{render, PoseSpec, Scene};

    /// A rendered view of the board (640×480, circles of ≈ 8 px radius) as a camera frame,
    /// scaled up `times` along each axis (nearest neighbour), as a larger sensor of the
    /// same field would give it.
    fn frame(times: u32) -> (CameraFrame, crate::sim::View) {
        let scene = Scene {
            name: "preview".into(),
            seed: 4,
            camera: crate::camera::CameraModel {
                width: 640,
                height: 480,
                intrinsics: crate::camera::Intrinsics {
                    fx: 560.0,
                    fy: 560.0,
                    cx: 320.0,
                    cy: 240.0,
                },
                distortion: crate::camera::Distortion::default(),
            },
            pose: PoseSpec {
                eye: Some([40.0, -30.0, 420.0]),
                target: Some([0.0, 0.0, 0.0]),
                ..PoseSpec::default()
            },
            imaging: crate::sim::Imaging::default(),
            board: Board::hex600(),
        };
        let view = render(&scene).unwrap();
        let (w, h) = (view.frame.size.width, view.frame.size.height);
        let src = &view.frame.data;
        let pixels = (0..w * times * h * times)
            .map(|i| {
                let (x, y) = (i % (w * times) / times, i / (w * times) / times);
                src[(y * w + x) as usize]
            })
            .collect();
        let frame = CameraFrame {
            width: w * times,
            height: h * times,
            bits: view.frame.bits,
            pixels: Pixels::Gray16(pixels),
            counter: 0,
            timestamp_ns: 0,
            exposure_us: 1000.0,
        };
        (frame, view)
    }

    #[test]
    fn a_preview_frame_shows_the_board_found_at_reduced_size() {
        // The same view at 640 px and at 1280 px, which is reduced by 2 to the same image:
        // the same circles, placed back in each frame's own pixels.
        let board = Board::hex600();
        let (small, view) = frame(1);
        let (big, _) = frame(2);
        let a = look(&small, &board, 3, &mut Hint::default()).unwrap();
        let b = look(&big, &board, 3, &mut Hint::default()).unwrap();
        assert_eq!(a.overlay.points.len(), b.overlay.points.len());
        assert!(a.count.seen && b.count.seen);
        assert_eq!(a.overlay.pose, 3);
        // Most of the circles imaged whole are labelled (the grid leaves out a few at its
        // border).
        let whole = view.truth.circles.iter().filter(|c| c.whole).count();
        let labelled = a.overlay.points.len();
        assert!(labelled * 100 >= whole * 85, "{labelled} of {whole}");
        // Each point of the small frame, doubled, is one of the big frame's (a 2×2 block
        // average of a nearest-neighbour copy is the small frame; points are rounded to 0.1).
        let mut far = 0;
        for p in &a.overlay.points {
            let q = [(p[0] + 0.5) * 2.0 - 0.5, (p[1] + 0.5) * 2.0 - 0.5];
            let near = b
                .overlay
                .points
                .iter()
                .any(|r| (r[0] - q[0]).hypot(r[1] - q[1]) < 0.5);
            far += usize::from(!near);
        }
        assert_eq!(far, 0, "points moved");
        // Centres from the preview's fewer rays: each within 0.15 px of the true outline
        // centre (the noise moves a 90-ray centre by ≈ 0.03 px here; 20 rays average
        // 4.5 times fewer edge points, √4.5 ≈ 2.1 times the scatter, and points are rounded
        // to 0.05 px).
        let truth: Vec<[f64; 2]> = view
            .truth
            .circles
            .iter()
            .filter_map(|c| c.ellipse)
            .collect();
        let error = |p: &[f32; 2]| {
            truth
                .iter()
                .map(|t| (f64::from(p[0]) - t[0]).hypot(f64::from(p[1]) - t[1]))
                .fold(f64::INFINITY, f64::min)
        };
        let worst = a.overlay.points.iter().map(error).fold(0.0, f64::max);
        assert!(worst < 0.15, "worst centre error {worst} px");
        assert!(!a.overlay.edges.is_empty());
        let png = image::load_from_memory(&b.png).unwrap();
        assert_eq!((png.width(), png.height()), (320, 240));
        // A frame of nothing but noise-free grey sees no board.
        let grey = CameraFrame {
            pixels: Pixels::Gray16(vec![100; (big.width * big.height) as usize]),
            ..big.clone()
        };
        let none = look(&grey, &board, 3, &mut Hint::default()).unwrap();
        assert!(!none.count.seen && none.overlay.points.is_empty());
        let cut = CameraFrame {
            pixels: Pixels::Gray16(vec![100; 10]),
            ..big
        };
        assert!(look(&cut, &board, 3, &mut Hint::default()).is_none());
    }

    #[test]
    fn hinted_rounds_find_the_board_where_it_was_and_search_everywhere_now_and_then() {
        let board = Board::hex600();
        let (big, _) = frame(2);
        let mut hint = Hint::default();
        let first = look(&big, &board, 0, &mut hint).unwrap();
        assert!(hint.area.is_some() && hint.due == FULL_EVERY - 1);
        // Near where it was: the same points as the whole frame's search.
        let near = look(&big, &board, 0, &mut hint).unwrap();
        assert_eq!(near.overlay.points, first.overlay.points);
        assert_eq!(hint.due, FULL_EVERY - 2);
        // The board gone: the near search fails, the whole frame is searched at once.
        let grey = CameraFrame {
            pixels: Pixels::Gray16(vec![100; (big.width * big.height) as usize]),
            ..big.clone()
        };
        assert!(!look(&grey, &board, 0, &mut hint).unwrap().count.seen);
        assert!(hint.area.is_none() && hint.due == FULL_EVERY - 1);
        // A camera without the board searches only every FULL_EVERY-th round: the board
        // back in view is found then.
        let rounds: Vec<bool> = (0..FULL_EVERY)
            .map(|_| look(&big, &board, 0, &mut hint).unwrap().count.seen)
            .collect();
        let mut want = vec![false; FULL_EVERY as usize];
        want[FULL_EVERY as usize - 1] = true;
        assert_eq!(rounds, want);
    }
}
