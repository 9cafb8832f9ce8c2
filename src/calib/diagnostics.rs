//! Diagnostics of a calibration: per-device residual statistics (the paper's Table I), the
//! RMS the joint fit expects, and the warnings a user should act on.
//!
//! Takes a [`Calibration`]; gives numbers and sentences. The report only formats them.

use super::bundle::DeviceKind;
use super::solve::Calibration;
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

/// Devices seen in fewer board poses than this are warned about.
pub const MIN_POSES: usize = 3;
/// A device's RMS above this multiple of its kind's median, or of the RMS the joint fit
/// expects, is warned about.
pub const RMS_RATIO: f64 = 1.5;
/// More than this fraction of a device's observations rejected is warned about.
pub const OUTLIER_FRACTION: f64 = 0.05;

/// One row of the paper's Table I: a device's residual statistics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualRow {
    /// Device name.
    pub name: String,
    /// Camera or projector.
    pub kind: DeviceKind,
    /// Observations used (inliers).
    pub points: usize,
    /// Observations rejected as outliers.
    pub outliers: usize,
    /// Mean of the inliers' residual norms (px).
    pub mean: f64,
    /// Standard deviation of the inliers' residual norms (px).
    pub std: f64,
    /// RMS of the inliers' residual norms (px).
    pub rms: f64,
    /// Board poses in which the device has observations.
    pub poses: usize,
}

/// The per-device residual table of a calibration.
pub fn residual_table(cal: &Calibration) -> Vec<ResidualRow> {
    cal.devices
        .iter()
        .enumerate()
        .map(|(d, dev)| {
            let (mut norms, mut outliers, mut poses) = (Vec::new(), 0, BTreeSet::new());
            for (o, r) in cal.observations.iter().zip(&cal.solution.residuals) {
                if o.device == d {
                    poses.insert(o.pose);
                    if r.outlier {
                        outliers += 1;
                    } else {
                        norms.push(r.error.norm());
                    }
                }
            }
            let n = norms.len().max(1) as f64;
            let mean = norms.iter().sum::<f64>() / n;
            let var = norms.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
            let rms = (norms.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
            ResidualRow {
                name: dev.name.clone(),
                kind: dev.kind,
                points: norms.len(),
                outliers,
                mean,
                std: var.sqrt(),
                rms,
                poses: poses.len(),
            }
        })
        .collect()
}

/// RMS of 2D residual norms the joint fit expects: √2·σ̂·√(1 − p/n) (docs/design.md §8).
pub fn expected_rms(cal: &Calibration) -> f64 {
    let (n, p) = cal.solution.dof;
    let keep = if n > 0 {
        (1.0 - p as f64 / n as f64).max(0.0)
    } else {
        1.0
    };
    std::f64::consts::SQRT_2 * cal.solution.sigma * keep.sqrt()
}

/// The report's own warnings: few poses, high RMS, many outliers, excluded devices,
/// unregistered views.
pub fn warnings(cal: &Calibration, rows: &[ResidualRow]) -> Vec<String> {
    let mut w = Vec::new();
    let expected = expected_rms(cal);
    for (dev, row) in cal.devices.iter().zip(rows) {
        if row.poses < MIN_POSES {
            w.push(format!(
                "{} ({}) is seen in only {} board pose{} (at least {MIN_POSES} wanted): its \
                 model rests on few views; capture more poses that it sees.",
                dev.name,
                kind_name(dev.kind),
                row.poses,
                if row.poses == 1 { "" } else { "s" }
            ));
        }
        let mut same: Vec<f64> = rows
            .iter()
            .filter(|r| r.kind == dev.kind && r.points > 0)
            .map(|r| r.rms)
            .collect();
        if same.len() >= 3 && row.points > 0 {
            same.sort_by(f64::total_cmp);
            let median = same[same.len() / 2];
            if row.rms > RMS_RATIO * median {
                w.push(format!(
                    "{}: RMS {:.4} px is {:.1}× the median {:.4} px of the {}s.",
                    dev.name,
                    row.rms,
                    row.rms / median,
                    median,
                    kind_name(dev.kind)
                ));
            }
        }
        if row.points > 0 && expected > 0.0 && row.rms > RMS_RATIO * expected {
            w.push(format!(
                "{}: RMS {:.4} px is {:.1}× the {:.4} px the joint fit expects \
                 (√2·σ̂·√(1 − p/n)): its noise is above the rig's, or its model does not fit.",
                dev.name,
                row.rms,
                row.rms / expected,
                expected
            ));
        }
        let total = row.points + row.outliers;
        if total > 0 && row.outliers as f64 > OUTLIER_FRACTION * total as f64 {
            w.push(format!(
                "{}: {} of {} observations ({:.1} %) rejected as outliers.",
                dev.name,
                row.outliers,
                total,
                100.0 * row.outliers as f64 / total as f64
            ));
        }
    }
    for e in &cal.excluded {
        w.push(format!("{} was not calibrated: {}.", e.name, e.reason));
    }
    for u in &cal.registration.unregistered {
        let camera = cal
            .device_index
            .iter()
            .position(|&i| i == u.camera)
            .map_or_else(
                || format!("camera #{}", u.camera),
                |d| cal.devices[d].name.clone(),
            );
        w.push(format!(
            "The unanchored view of {camera} in board pose {} was not registered and is not \
             used: {}.",
            u.pose, u.reason
        ));
    }
    w
}

/// "camera" or "projector".
pub fn kind_name(k: DeviceKind) -> &'static str {
    match k {
        DeviceKind::Camera => "camera",
        DeviceKind::Projector => "projector",
    }
}
