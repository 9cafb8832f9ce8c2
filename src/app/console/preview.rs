//! The console's live preview (docs/design.md §15 "Live preview"): each preview frame a
//! camera takes while the board is placed (the projectors showing a flat field) is reduced
//! to at most [`DETECT_WIDTH`] pixels across, its circles are detected and labelled there,
//! and it becomes a small picture with the labelled points and lattice drawn over it.
//!
//! Takes one preview frame and the board; gives [`LiveView`]: the picture (PNG), the
//! overlay in the frame's own pixels and whether the camera sees the board.

use super::stats::{Overlay, MIN_POINTS};
use super::thumbs::{grey_png, WIDTH};
use crate::app::detect::{analyse, Settings};
use crate::board::{Board, Hex};
use crate::images::{CameraFrame, GrayImage, Pixels};
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
    /// The camera sees the board: at least [`MIN_POINTS`] labelled points.
    pub sees_board: bool,
}

/// `frame` averaged over `factor` × `factor` blocks (samples as delivered); `None` when its
/// pixels do not fill its size.
pub fn reduced(frame: &CameraFrame, factor: u32) -> Option<GrayImage> {
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
    let mut out = GrayImage::new(rw as u32, rh as u32);
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

/// The live view of one preview frame of the pose being placed (`pose`): detection and
/// grid building on the frame reduced to at most [`DETECT_WIDTH`] across, the overlay
/// scaled back to the frame's pixels (pixel centres: x = (x' + ½)·factor − ½).
pub fn look(frame: &CameraFrame, board: &Board, pose: usize) -> Option<LiveView> {
    let factor = frame.width.div_ceil(DETECT_WIDTH).max(1);
    let image = reduced(frame, factor)?;
    let analysis = analyse(&image, board, &Settings::default());
    let f = f64::from(factor);
    let full = |p: Point2<f64>| Point2::new((p.x + 0.5) * f - 0.5, (p.y + 0.5) * f - 0.5);
    let grid = &analysis.grid;
    let points: Vec<(Hex, Point2<f64>)> =
        grid.points.iter().map(|p| (p.hex, full(p.image))).collect();
    let overlay = Overlay::labelled(pose, analysis.circles.len(), grid.anchored, &points);
    let (rw, rh) = image.dimensions();
    let step = rw.div_ceil(WIDTH).max(1);
    let (tw, th) = ((rw / step).max(1), (rh / step).max(1));
    let mut small = Vec::with_capacity((tw * th) as usize);
    for y in 0..th {
        for x in 0..tw {
            small.push(image.get_pixel(x * step + step / 2, y * step + step / 2).0[0]);
        }
    }
    Some(LiveView {
        png: grey_png(&small, tw, th)?,
        circles: analysis.circles.len(),
        sees_board: points.len() >= MIN_POINTS,
        overlay,
    })
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
        let a = look(&small, &board, 3).unwrap();
        let b = look(&big, &board, 3).unwrap();
        assert_eq!(a.overlay.points.len(), b.overlay.points.len());
        assert!(a.sees_board && b.sees_board);
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
        assert!(!a.overlay.edges.is_empty());
        let png = image::load_from_memory(&b.png).unwrap();
        assert_eq!((png.width(), png.height()), (320, 240));
        // A frame of nothing but noise-free grey sees no board.
        let grey = CameraFrame {
            pixels: Pixels::Gray16(vec![100; (big.width * big.height) as usize]),
            ..big.clone()
        };
        let none = look(&grey, &board, 3).unwrap();
        assert!(!none.sees_board && none.overlay.points.is_empty());
        let cut = CameraFrame {
            pixels: Pixels::Gray16(vec![100; 10]),
            ..big
        };
        assert!(look(&cut, &board, 3).is_none());
    }
}
