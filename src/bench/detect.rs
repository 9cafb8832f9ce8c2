//! `hexcal bench detect`: the circle detector timed on synthetic boards or given images.

use crate::detect::{detect, synth, DetectParams};
use crate::images::{load_gray, FloatImage, ImageIoError};
use std::fmt::Write as _;
use std::path::PathBuf;

/// `hexcal bench detect`: per image, the median and fastest time of `detect` and the
/// throughput.
pub fn bench_detect(images: &[PathBuf], runs: usize) -> Result<String, ImageIoError> {
    let inputs: Vec<(String, FloatImage)> = if images.is_empty() {
        vec![
            (
                "synthetic board, r=10 px, tilt 40°".into(),
                synth::lattice_image(1920, 1200, 10.0, 40.0, 1),
            ),
            (
                "synthetic board, r=4 px, frontal".into(),
                synth::lattice_image(1920, 1200, 4.0, 0.0, 2),
            ),
            (
                "synthetic board, r=24 px, tilt 40°".into(),
                synth::lattice_image(4096, 3000, 24.0, 40.0, 3),
            ),
            (
                "synthetic board, r=10 px, frontal".into(),
                synth::lattice_image(4096, 3000, 10.0, 0.0, 4),
            ),
        ]
    } else {
        images
            .iter()
            .map(|p| Ok((p.display().to_string(), load_gray(p)?)))
            .collect::<Result<_, ImageIoError>>()?
    };
    let params = DetectParams::default();
    let mut out = format!("threads: {}\n", rayon::current_num_threads());
    let _ = writeln!(
        out,
        "{:>11} {:>6} {:>8} {:>10} {:>10} {:>8}  image",
        "size", "MP", "circles", "median ms", "min ms", "MP/s"
    );
    for (name, img) in &inputs {
        let n = detect(img, &params).len();
        let mut ms: Vec<f64> = (0..runs.max(1))
            .map(|_| {
                let t = std::time::Instant::now();
                std::hint::black_box(detect(img, &params));
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        ms.sort_by(f64::total_cmp);
        let mp = img.width() as f64 * img.height() as f64 / 1e6;
        let med = ms[ms.len() / 2];
        let _ = writeln!(
            out,
            "{:>11} {:>6.2} {:>8} {:>10.1} {:>10.1} {:>8.1}  {name}",
            format!("{}x{}", img.width(), img.height()),
            mp,
            n,
            med,
            ms[0],
            mp / (med / 1e3)
        );
    }
    Ok(out)
}
