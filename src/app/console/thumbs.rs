//! Camera thumbnails for the console: every captured frame of a pose, sampled on a coarse
//! grid and summed, gives the pose's mean image (the phase-shift patterns average out to an
//! even light), encoded as a PNG when the pose is captured.
//!
//! Takes the frames the capture hands over; gives one small PNG per camera and pose.

use crate::dataset::StackFrame;
use crate::images::Pixels;

/// Thumbnails are at most this wide (px).
pub const WIDTH: u32 = 320;

/// One camera's thumbnail being summed.
#[derive(Clone, Debug, Default)]
struct Sum {
    pose: usize,
    width: u32,
    height: u32,
    step: u32,
    sum: Vec<u32>,
    frames: u32,
}

/// A finished thumbnail.
#[derive(Clone, Debug, PartialEq)]
pub struct Thumbnail {
    /// The pose it shows.
    pub pose: usize,
    /// Size (px).
    pub size: [u32; 2],
    /// Source pixels per thumbnail pixel along each axis.
    pub step: u32,
    /// PNG bytes.
    pub png: Vec<u8>,
}

/// Every camera's thumbnail of the pose being captured.
#[derive(Clone, Debug, Default)]
pub struct Thumbs {
    sums: Vec<Sum>,
}

impl Thumbs {
    /// Add one frame of pose `pose` (a frame of a new pose restarts its camera's sum).
    pub fn add(&mut self, pose: usize, f: &StackFrame) {
        if self.sums.len() <= f.camera {
            self.sums.resize(f.camera + 1, Sum::default());
        }
        let frame = &f.frame;
        let s = &mut self.sums[f.camera];
        let step = frame.width.div_ceil(WIDTH).max(1);
        let (w, h) = (frame.width / step, frame.height / step);
        if s.frames == 0 || s.pose != pose || (s.width, s.height, s.step) != (w, h, step) {
            *s = Sum {
                pose,
                width: w,
                height: h,
                step,
                sum: vec![0; (w * h) as usize],
                frames: 0,
            };
        }
        let shift = u32::from(frame.bits.saturating_sub(8));
        let at = |x: u32, y: u32| -> u32 {
            let i = (y * frame.width + x) as usize;
            match &frame.pixels {
                Pixels::Gray8(v) => v.get(i).map_or(0, |&p| u32::from(p)),
                Pixels::Gray16(v) => v.get(i).map_or(0, |&p| u32::from(p) >> shift),
            }
        };
        for y in 0..h {
            for x in 0..w {
                s.sum[(y * w + x) as usize] += at(x * step + step / 2, y * step + step / 2);
            }
        }
        s.frames += 1;
    }

    /// Camera `camera`'s thumbnail of the frames summed so far (contrast stretched between
    /// the 1st and 99th percentile), if it has any.
    pub fn finish(&self, camera: usize) -> Option<Thumbnail> {
        let s = self
            .sums
            .get(camera)
            .filter(|s| s.frames > 0 && !s.sum.is_empty())?;
        let sum: Vec<f32> = s.sum.iter().map(|&v| v as f32).collect();
        let png = grey_png(&sum, s.width, s.height)?;
        Some(Thumbnail {
            pose: s.pose,
            size: [s.width, s.height],
            step: s.step,
            png,
        })
    }
}

/// A PNG of `values` (`width` × `height`, row-major), contrast stretched between their 1st
/// and 99th percentile; `None` for no values or an encoder failure.
pub fn grey_png(values: &[f32], width: u32, height: u32) -> Option<Vec<u8>> {
    if values.is_empty() || values.len() != (width as usize) * (height as usize) {
        return None;
    }
    let mut sorted = values.to_vec();
    sorted.sort_unstable_by(f32::total_cmp);
    let lo = f64::from(sorted[sorted.len() / 100]);
    let hi = f64::from(sorted[sorted.len() * 99 / 100]).max(lo + 1.0);
    let grey: Vec<u8> = values
        .iter()
        .map(|&v| ((f64::from(v) - lo) / (hi - lo) * 255.0).clamp(0.0, 255.0) as u8)
        .collect();
    let mut png = Vec::new();
    let encoder = image::codecs::png::PngEncoder::new(&mut png);
    image::ImageEncoder::write_image(encoder, &grey, width, height, image::ExtendedColorType::L8)
        .ok()?;
    Some(png)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::images::CameraFrame;

    fn frame(camera: usize, phase: u32) -> StackFrame {
        let (w, h) = (960u32, 600u32);
        // A left half dark, a right half bright, striped differently in each frame.
        let pixels = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let stripe = ((x + y + phase) / 3 % 2) as u16 * 400;
                if x < w / 2 {
                    100 + stripe
                } else {
                    3000 + stripe
                }
            })
            .collect();
        StackFrame {
            camera,
            index: phase as usize,
            frame: CameraFrame {
                width: w,
                height: h,
                bits: 12,
                pixels: Pixels::Gray16(pixels),
                counter: 0,
                timestamp_ns: 0,
                exposure_us: 1000.0,
            },
        }
    }

    #[test]
    fn thumbnail_is_the_mean_image_scaled_down() {
        let mut t = Thumbs::default();
        for k in 0..6 {
            t.add(4, &frame(1, k));
        }
        assert!(t.finish(0).is_none(), "camera 0 sent nothing");
        let th = t.finish(1).unwrap();
        assert_eq!((th.pose, th.size, th.step), (4, [320, 200], 3));
        let img = image::load_from_memory(&th.png).unwrap().to_luma8();
        assert_eq!(img.dimensions(), (320, 200));
        // Dark left, bright right, whatever the stripes did.
        assert!(img.get_pixel(40, 100).0[0] < 60 && img.get_pixel(280, 100).0[0] > 200);
        // A new pose starts a new sum.
        t.add(5, &frame(1, 0));
        assert_eq!(t.finish(1).unwrap().pose, 5);
    }
}
