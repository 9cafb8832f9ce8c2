//! V4L2 frame conversion speed: a 1920×1200 buffer (rows padded to a 64-byte stride) to
//! hexcal pixels — `YUYV` to its luma, `GREY` copied, `Y16` read little-endian. Single
//! thread; prints ms per frame and input MB/s.
//!
//! Run: `cargo bench --features v4l2 --bench v4l2`

use hexcal::rig::v4l2::{frame_pixels, FourCc};
use std::hint::black_box;
use std::time::Instant;

const WIDTH: usize = 1920;
const HEIGHT: usize = 1200;

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
    for (fourcc, bytes_per_pixel) in [(FourCc::YUYV, 2), (FourCc::GREY, 1), (FourCc::Y16, 2)] {
        let stride = (WIDTH * bytes_per_pixel).next_multiple_of(64);
        let data: Vec<u8> = (0..stride * HEIGHT)
            .map(|i| (i * 7 + i / 4099) as u8)
            .collect();
        let seconds = median_seconds(101, || {
            black_box(frame_pixels(
                fourcc,
                black_box(&data),
                WIDTH,
                HEIGHT,
                stride,
            ));
        });
        println!(
            "{fourcc} {WIDTH}×{HEIGHT}: {:.3} ms per frame, {:.0} MB/s in",
            1e3 * seconds,
            (stride * HEIGHT) as f64 / seconds / 1e6
        );
    }
}
