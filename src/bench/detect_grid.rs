//! `hexcal bench detect-grid`: detection + grid building timed on rendered board views
//! (1920×1200 and 4096×3000), with the recall and centre error against the renderer's truth;
//! the views, their truth and these figures are written to a directory where
//! `scripts/bench_opencv_blobs.py` runs OpenCV's SimpleBlobDetector on the same images
//! ([`opencv_side_by_side`]).

use crate::app::detect::{analyse, Settings};
use crate::board::Board;
use crate::detect::Circle;
use crate::grid::build;
use crate::sim::{render, write_view, GroundTruth, Scene, SimError};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Instant;
use {crate::detect::detect, crate::images::FloatImage};

/// A failure of the benchmark.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// Rendering or writing a view failed.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// Coding or decoding a frame in a camera format failed.
    #[error("pixel format: {0}")]
    Encode(String),
    /// Writing the figures failed.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: std::path::PathBuf,
        /// What went wrong.
        source: std::io::Error,
    },
}

/// The two built-in benchmark scenes: the default 1920×1200 view (circles 8–11 px), and a
/// 4096×3000 camera (f = 3300 px) seeing the front tilted ~30° from 1.1 m (circles ≈ 17 px).
pub fn scenes() -> Vec<Scene> {
    let mut small = Scene::default_scene();
    small.name = "bench_1920x1200".into();
    let mut large = Scene::default_scene();
    large.name = "bench_4096x3000".into();
    large.camera.width = 4096;
    large.camera.height = 3000;
    let k = &mut large.camera.intrinsics;
    (k.fx, k.fy, k.cx, k.cy) = (3300.0, 3300.0, 2051.7, 1496.2);
    large.pose.eye = Some([260.0, -480.0, 980.0]);
    large.seed = 2;
    vec![small, large]
}

/// Figures of one image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BenchRow {
    /// The image file name (as written with `--out`).
    pub image: String,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Circles detected.
    pub circles: usize,
    /// Points labelled.
    pub points: usize,
    /// Whole circles in the truth.
    pub whole: usize,
    /// Whole circles with a detection within a third of their radius.
    pub matched: usize,
    /// RMS distance of those detections from the truth's outline-ellipse centres (px).
    pub centre_rms: f64,
    /// Median time of detection (ms).
    pub detect_ms: f64,
    /// Median time of grid building (ms).
    pub grid_ms: f64,
    /// Median time of detection + grid building, timed together (ms).
    pub total_ms: f64,
    /// Fastest detection + grid building (ms).
    pub total_min_ms: f64,
}

/// The benchmark's figures.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BenchReport {
    /// Rayon threads.
    pub threads: usize,
    /// Timed runs per image (medians reported).
    pub runs: usize,
    /// /proc/loadavg before the runs.
    pub load_average: String,
    /// One row per image.
    pub rows: Vec<BenchRow>,
}

impl std::fmt::Display for BenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "detect + grid: {} threads, median of {} runs; load average before: {}",
            self.threads, self.runs, self.load_average
        )?;
        writeln!(
            f,
            "{:>10} {:>8} {:>7} {:>13} {:>10} {:>9} {:>7} {:>9} {:>8}  image",
            "size",
            "circles",
            "points",
            "recall",
            "rms px",
            "detect ms",
            "grid ms",
            "total ms",
            "min ms"
        )?;
        for r in &self.rows {
            writeln!(
                f,
                "{:>10} {:>8} {:>7} {:>13} {:>10.4} {:>9.1} {:>7.1} {:>9.1} {:>8.1}  {}",
                format!("{}x{}", r.width, r.height),
                r.circles,
                r.points,
                format!("{}/{}", r.matched, r.whole),
                r.centre_rms,
                r.detect_ms,
                r.grid_ms,
                r.total_ms,
                r.total_min_ms,
                r.image
            )?;
        }
        Ok(())
    }
}

/// Median and minimum of timed runs of `f` (ms), after one warm-up run.
fn time_ms(runs: usize, mut f: impl FnMut()) -> (f64, f64) {
    f();
    let mut ms: Vec<f64> = (0..runs.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    ms.sort_by(f64::total_cmp);
    (ms[ms.len() / 2], ms[0])
}

/// Render each scene, time detection + grid building `runs` times, and measure recall and
/// centre error against the truth. With `out`, each view is written there as `NAME.png` and
/// `NAME.json` (the renderer's truth) and the figures as `hexcal_bench.json`.
pub fn bench_detect_grid(
    scenes: &[Scene],
    runs: usize,
    out: Option<&Path>,
) -> Result<BenchReport, BenchError> {
    let settings = Settings::default();
    let load_average = std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.trim().to_owned())
        .unwrap_or_else(|_| "n/a".into());
    let mut rows = Vec::new();
    for scene in scenes {
        let view = render(scene)?;
        if let Some(dir) = out {
            write_view(&view, dir)?;
        }
        let (w, h) = (view.frame.size.width, view.frame.size.height);
        let image = FloatImage::from_raw(w, h, view.frame.data.iter().map(|&v| v as f32).collect())
            .expect("frame size matches its data");
        let board: &Board = &scene.board;
        let analysis = analyse(&image, board, &settings);
        let (detect_ms, _) = time_ms(runs, || {
            std::hint::black_box(detect(&image, &settings.detect));
        });
        let (grid_ms, _) = time_ms(runs, || {
            std::hint::black_box(build(&image, &analysis.circles, board, &settings.grid));
        });
        let (total_ms, total_min_ms) = time_ms(runs, || {
            std::hint::black_box(analyse(&image, board, &settings));
        });
        let (whole, matched, centre_rms) = centre_error(&view.truth, &analysis.circles);
        rows.push(BenchRow {
            image: view.truth.image.clone(),
            width: w,
            height: h,
            circles: analysis.circles.len(),
            points: analysis.grid.points.len(),
            whole,
            matched,
            centre_rms,
            detect_ms,
            grid_ms,
            total_ms,
            total_min_ms,
        });
    }
    let report = BenchReport {
        threads: rayon::current_num_threads(),
        runs,
        load_average,
        rows,
    };
    if let Some(dir) = out {
        let path = dir.join("hexcal_bench.json");
        let text = serde_json::to_string_pretty(&report).expect("figures serialise");
        std::fs::write(&path, text).map_err(|source| BenchError::Write { path, source })?;
    }
    Ok(report)
}

/// The whole circles of `truth`, how many have a detection among `found` within a third of
/// their radius, and the RMS distance of those from the truth's outline-ellipse centres (px).
pub fn centre_error(truth: &GroundTruth, found: &[Circle]) -> (usize, usize, f64) {
    let whole: Vec<([f64; 2], f64)> = truth
        .circles
        .iter()
        .filter(|c| c.whole)
        .filter_map(|c| c.ellipse.zip(c.radius))
        .collect();
    let mut sq = Vec::new();
    for (t, r) in &whole {
        let nearest = found
            .iter()
            .map(|c| (c.ellipse.center.x - t[0]).hypot(c.ellipse.center.y - t[1]))
            .fold(f64::INFINITY, f64::min);
        if nearest < r / 3.0 {
            sq.push(nearest * nearest);
        }
    }
    let rms = (sq.iter().sum::<f64>() / sq.len().max(1) as f64).sqrt();
    (whole.len(), sq.len(), rms)
}

/// The Python that runs OpenCV (Debian's `python3-opencv`; a pyenv `python3` on PATH would
/// shadow it).
pub const OPENCV_PYTHON: &str = "/usr/bin/python3";

/// Runs `scripts/bench_opencv_blobs.py` (embedded) with [`OPENCV_PYTHON`] on the views and
/// figures that [`bench_detect_grid`] wrote to `dir`: OpenCV's SimpleBlobDetector timed
/// `runs` times per image, its recall and centre error side by side with hexcal's. Its
/// printed table, or why it could not run (no such Python, no `cv2`, the script failed).
pub fn opencv_side_by_side(dir: &Path, runs: usize) -> Result<String, OpenCvError> {
    let python = Path::new(OPENCV_PYTHON);
    let probe = std::process::Command::new(python)
        .args(["-c", "import cv2"])
        .output()
        .map_err(OpenCvError::NoPython)?;
    if !probe.status.success() {
        return Err(OpenCvError::NoCv2);
    }
    let out = std::process::Command::new(python)
        .args(["-c", include_str!("../../scripts/bench_opencv_blobs.py")])
        .arg(dir)
        .args(["--runs", &runs.to_string()])
        .output()
        .map_err(OpenCvError::NoPython)?;
    if out.status.success() {
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    } else {
        let stderr = String::from_utf8_lossy(&out.stderr).trim().to_string();
        Err(OpenCvError::Script(stderr))
    }
}

/// Why OpenCV's side of the benchmark did not run.
#[derive(Debug, thiserror::Error)]
pub enum OpenCvError {
    /// The Python interpreter could not be started.
    #[error("{OPENCV_PYTHON} not runnable ({0})")]
    NoPython(std::io::Error),
    /// It has no OpenCV.
    #[error("{OPENCV_PYTHON} has no cv2 (apt-get install python3-opencv)")]
    NoCv2,
    /// The script failed (its standard error).
    #[error("scripts/bench_opencv_blobs.py failed: {0}")]
    Script(String),
}
