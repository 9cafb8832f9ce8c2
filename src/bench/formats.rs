//! `hexcal bench formats`: what a camera's pixel format costs detection (docs/design.md §11
//! "Colour, packed and compressed formats"). Takes rendered board views (the detect-grid
//! scenes, several noise seeds) and gives, per format, the recall, labelled points and
//! centre error against the renderer's truth, and the conversion's time per frame: the
//! monochrome sensor; a Bayer sensor (filters before the noise, [`CFA_RESPONSE`]) as a raw
//! mosaic read as grey and as the balanced mosaic the drivers deliver; MJPEG at qualities
//! 85 and 95 decoded to luma.

use super::detect_grid::{centre_error, scenes, BenchError};
use crate::app::detect::{analyse, Settings};
use crate::images::to_grey::{jpeg_luma, BayerBalance, Cfa};
use crate::images::FloatImage;
use crate::rig::sim::CFA_RESPONSE;
use crate::sim::{geometry, ground_truth, sensor, Scene};
use hexcal_simulator::Sensor;
use std::time::Instant;

/// The formats compared.
const FORMATS: [&str; 5] = [
    "mono",
    "bayer raw",
    "bayer balanced",
    "mjpeg q95",
    "mjpeg q85",
];

/// Figures of one format over every view.
#[derive(Clone, Debug, PartialEq)]
pub struct FormatRow {
    /// The format.
    pub format: &'static str,
    /// Whole circles in the truth, over all views.
    pub whole: usize,
    /// Of those, detected within a third of their radius.
    pub matched: usize,
    /// Labelled points, over all views.
    pub points: usize,
    /// RMS centre error of the matched circles (px).
    pub centre_rms: f64,
    /// Median time of the conversion to grey of one frame (ms; 0 for mono).
    pub convert_ms: f64,
}

/// The comparison: one row per format.
#[derive(Clone, Debug, PartialEq)]
pub struct FormatsReport {
    /// Views per format.
    pub views: usize,
    /// One row per format, in `FORMATS` order.
    pub rows: Vec<FormatRow>,
}

impl std::fmt::Display for FormatsReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "pixel formats over {} rendered views:", self.views)?;
        writeln!(
            f,
            "{:<16} {:>13} {:>8} {:>10} {:>11}",
            "format", "recall", "points", "rms px", "convert ms"
        )?;
        for r in &self.rows {
            writeln!(
                f,
                "{:<16} {:>13} {:>8} {:>10.4} {:>11.2}",
                r.format,
                format!("{}/{}", r.matched, r.whole),
                r.points,
                r.centre_rms,
                r.convert_ms
            )?;
        }
        Ok(())
    }
}

/// One view's frame in each of [`FORMATS`] (8-bit grey), and each conversion's time (ms).
fn frames(scene: &Scene) -> Result<Vec<(Vec<u16>, f64)>, BenchError> {
    let geo = geometry(scene)?;
    let mono_sensor = sensor(&scene.imaging);
    let signal = mono_sensor.optics(geo.size, &geo.irradiance(scene.imaging.white_dn as f32));
    let (w, h) = (geo.size.width as usize, geo.size.height as usize);
    let mono = mono_sensor.expose(geo.size, &signal, scene.seed).data;
    let cfa = Cfa::Rggb;
    let response = [(0, 0), (1, 0), (0, 1), (1, 1)].map(|(x, y)| CFA_RESPONSE[cfa.channel(x, y)]);
    let colour = Sensor {
        cfa: Some(response),
        ..mono_sensor
    };
    let raw = colour.expose(geo.size, &signal, scene.seed).data;
    let mut balanced = raw.clone();
    let t = Instant::now();
    BayerBalance::default().apply(&mut balanced, w, cfa, scene.imaging.bits);
    let balance_ms = t.elapsed().as_secs_f64() * 1e3;
    let mut out = vec![(mono.clone(), 0.0), (raw, 0.0), (balanced, balance_ms)];
    let bytes: Vec<u8> = mono.iter().map(|&v| v.min(255) as u8).collect();
    for quality in [95, 85] {
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, quality)
            .encode(&bytes, w as u32, h as u32, image::ExtendedColorType::L8)
            .map_err(|e| BenchError::Encode(e.to_string()))?;
        let mut times = Vec::new();
        let mut luma = Vec::new();
        for _ in 0..5 {
            let t = Instant::now();
            luma = jpeg_luma(&jpeg, w, h).map_err(|e| BenchError::Encode(e.to_string()))?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        out.push((luma.into_iter().map(u16::from).collect(), times[2]));
    }
    Ok(out)
}

/// Detection on `seeds` noise draws of each detect-grid scene, rendered in every format.
pub fn bench_formats(seeds: u64) -> Result<FormatsReport, BenchError> {
    let settings = Settings::default();
    let mut rows: Vec<FormatRow> = FORMATS
        .iter()
        .map(|&format| FormatRow {
            format,
            whole: 0,
            matched: 0,
            points: 0,
            centre_rms: 0.0,
            convert_ms: 0.0,
        })
        .collect();
    let mut sq = vec![0.0; FORMATS.len()];
    let mut times = vec![Vec::new(); FORMATS.len()];
    let mut views = 0;
    for base in scenes() {
        for seed in 0..seeds {
            let scene = Scene {
                seed: base.seed.wrapping_add(1000 * seed),
                ..base.clone()
            };
            let truth = ground_truth(&scene)?;
            views += 1;
            for (i, (data, ms)) in frames(&scene)?.into_iter().enumerate() {
                let (w, h) = (truth.width, truth.height);
                let image =
                    FloatImage::from_raw(w, h, data.iter().map(|&v| f32::from(v)).collect())
                        .expect("frame size matches its data");
                let analysis = analyse(&image, &scene.board, &settings);
                let (whole, matched, rms) = centre_error(&truth, &analysis.circles);
                let row = &mut rows[i];
                row.whole += whole;
                row.matched += matched;
                row.points += analysis.grid.points.len();
                sq[i] += rms * rms * matched as f64;
                times[i].push(ms);
            }
        }
    }
    for ((row, sq), mut t) in rows.iter_mut().zip(sq).zip(times) {
        row.centre_rms = (sq / row.matched.max(1) as f64).sqrt();
        t.sort_by(f64::total_cmp);
        row.convert_ms = t.get(t.len() / 2).copied().unwrap_or(0.0);
    }
    Ok(FormatsReport { views, rows })
}
