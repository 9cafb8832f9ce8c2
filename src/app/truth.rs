//! A calibration against a simulated rig's ground truth.

use crate::calib::solve::Calibration;
use serde::Serialize;

/// A calibrated device against a simulated rig's ground truth.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TruthCheck {
    /// Device name.
    pub name: String,
    /// Relative focal length error max(|Δfx/fx|, |Δfy/fy|).
    pub focal_error: f64,
    /// Principal point error (px).
    pub principal_error: f64,
    /// Rotation error of the pose relative to the reference device (deg).
    pub rotation_error_deg: f64,
    /// Position error relative to the reference device (mm).
    pub position_error_mm: f64,
}

/// Every calibrated device of `cal` against the simulated `world`'s truth (devices named
/// as in the world; poses relative to the calibration's reference device).
pub fn check_truth(cal: &Calibration, world: &crate::rig::sim::SimWorld) -> Vec<TruthCheck> {
    let truth = |name: &str| {
        world
            .cameras
            .iter()
            .chain(&world.projectors)
            .find(|d| d.name == name)
    };
    // T_ref_rig of the calibration's reference device.
    let Some(reference) = truth(&cal.devices[cal.reference].name) else {
        return Vec::new();
    };
    cal.devices
        .iter()
        .filter_map(|d| {
            let t = truth(&d.name)?;
            let (e, k) = (&d.model.intrinsics, &t.model.intrinsics);
            let true_pose = t.pose * reference.pose.inverse();
            let delta = d.pose * true_pose.inverse();
            Some(TruthCheck {
                name: d.name.clone(),
                focal_error: ((e.fx / k.fx - 1.0).abs()).max((e.fy / k.fy - 1.0).abs()),
                principal_error: (e.cx - k.cx).hypot(e.cy - k.cy),
                rotation_error_deg: delta.rotation.angle().to_degrees(),
                position_error_mm: (d.pose.inverse().translation.vector
                    - true_pose.inverse().translation.vector)
                    .norm(),
            })
        })
        .collect()
}

/// The truth checks as a table.
pub fn format_truth(checks: &[TruthCheck]) -> String {
    let mut s = format!(
        "{:<10} {:>12} {:>12} {:>12} {:>12}\n",
        "device", "focal err %", "pp err px", "rot err deg", "pos err mm"
    );
    for c in checks {
        s += &format!(
            "{:<10} {:>12.4} {:>12.3} {:>12.4} {:>12.3}\n",
            c.name,
            100.0 * c.focal_error,
            c.principal_error,
            c.rotation_error_deg,
            c.position_error_mm
        );
    }
    s
}
