//! `hexcal bench render`: the simulator's stages (ray grid, geometry, one frame) timed on a
//! scene.

use crate::sim::{geometry_with, ground_truth, sensor, CameraLens, Scene, SimError};
use hexcal_simulator::{ImageSize, Lens, RayGrid};

/// Wall-clock and CPU (all threads) seconds of one stage, medians over the repeats.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StageTime {
    /// Elapsed time.
    pub wall: f64,
    /// Process CPU time (user + system, all threads; 10 ms resolution); `None` where
    /// /proc/self/stat is unavailable.
    pub cpu: Option<f64>,
}

/// Process CPU seconds from /proc/self/stat (utime + stime at 100 ticks/s, Linux's USER_HZ).
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Timings of one view's rendering (the median of the repeats).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderTimings {
    /// Ray grid of the camera (once per camera).
    pub ray_grid: StageTime,
    /// Geometry pass (once per camera and board pose).
    pub geometry: StageTime,
    /// One frame: shading, PSF, noise, gamma, quantisation.
    pub frame: StageTime,
    /// Ground truth of all circles.
    pub truth: StageTime,
    /// Pixels integrated as texture-edge pixels.
    pub edge_pixels: usize,
    /// Pixels integrated as outline pixels.
    pub outline_pixels: usize,
    /// Image size.
    pub size: ImageSize,
    /// Worker threads.
    pub threads: usize,
    /// Repetitions behind the medians.
    pub repeats: usize,
}

impl std::fmt::Display for RenderTimings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (w, h) = (self.size.width, self.size.height);
        writeln!(
            f,
            "render {w}x{h}, {} threads, median of {} (wall ms, CPU ms all threads):",
            self.threads, self.repeats
        )?;
        let mut row = |name: &str, t: StageTime| {
            let cpu = t.cpu.map_or("-".into(), |c| format!("{:.0}", c * 1e3));
            writeln!(f, "  {name:<30} {:8.1} {cpu:>8}", t.wall * 1e3)
        };
        row("ray grid (once per camera)", self.ray_grid)?;
        row("geometry (once per pose)", self.geometry)?;
        row("frame (shade, PSF, noise)", self.frame)?;
        let sum = StageTime {
            wall: self.geometry.wall + self.frame.wall,
            cpu: self.geometry.cpu.zip(self.frame.cpu).map(|(a, b)| a + b),
        };
        row("geometry + one frame", sum)?;
        row("ground truth", self.truth)?;
        write!(
            f,
            "  ({} edge px, {} outline px)",
            self.edge_pixels, self.outline_pixels
        )
    }
}

/// Time the stages of [`crate::sim::render`] on a scene, `repeats` times each.
pub fn bench_render(scene: &Scene, repeats: usize) -> Result<RenderTimings, SimError> {
    let median = |v: Vec<(f64, Option<f64>)>| {
        let mid = |mut x: Vec<f64>| {
            x.sort_by(f64::total_cmp);
            x[x.len() / 2]
        };
        let cpu: Option<Vec<f64>> = v.iter().map(|t| t.1).collect();
        StageTime {
            wall: mid(v.iter().map(|t| t.0).collect()),
            cpu: cpu.map(mid),
        }
    };
    let time = |f: &mut dyn FnMut()| {
        let (t, c) = (std::time::Instant::now(), process_cpu_seconds());
        f();
        let cpu = c.zip(process_cpu_seconds()).map(|(a, b)| b - a);
        (t.elapsed().as_secs_f64(), cpu)
    };
    let repeats = repeats.max(1);
    let (mut tr, mut tg, mut tf, mut tt) = (vec![], vec![], vec![], vec![]);
    let (mut edges, mut outlines) = (0, 0);
    let sensor = sensor(&scene.imaging);
    for k in 0..repeats {
        let mut rays = None;
        let lens = CameraLens(&scene.camera);
        tr.push(time(&mut || rays = Some(RayGrid::new(&lens))));
        let rays = rays.expect("built");
        let mut geo = None;
        tg.push(time(&mut || geo = Some(geometry_with(&rays, scene))));
        let geo = geo.expect("ran")?;
        (edges, outlines) = (geo.edge_pixels, geo.outline_pixels);
        tf.push(time(&mut || {
            let signal = sensor.optics(geo.size, &geo.irradiance(scene.imaging.white_dn as f32));
            std::hint::black_box(sensor.expose(geo.size, &signal, scene.seed + k as u64));
        }));
        tt.push(time(&mut || {
            std::hint::black_box(ground_truth(scene).map(|t| t.circles.len()).ok());
        }));
    }
    Ok(RenderTimings {
        ray_grid: median(tr),
        geometry: median(tg),
        frame: median(tf),
        truth: median(tt),
        edge_pixels: edges,
        outline_pixels: outlines,
        size: CameraLens(&scene.camera).size(),
        threads: rayon::current_num_threads(),
        repeats,
    })
}
