//! A calibration against a simulated rig's ground truth: focal length, principal point and
//! pose errors, and the lens's projection error over the whole image.

use crate::calib::lens_model::model_difference;
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
    /// Largest projection error over the whole image (px, [`model_difference`]) of the
    /// chosen lens model: each pixel's true ray, a direction in the rig (a point at
    /// infinity, so position errors do not count), projected through the calibrated
    /// device's rotation relative to the reference device and its lens.
    pub image_error_max: f64,
    /// RMS of that error over the whole image (px).
    pub image_error_rms: f64,
    /// Largest lens projection error over the whole image (px) of the model with every
    /// distortion term estimated (the first adjustment, before terms were fixed).
    pub all_terms_error_max: f64,
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
        .zip(&cal.lens)
        .filter_map(|(d, lens)| {
            let t = truth(&d.name)?;
            let (e, k) = (&d.model.intrinsics, &t.model.intrinsics);
            let true_pose = t.pose * reference.pose.inverse();
            let delta = d.pose * true_pose.inverse();
            // Directions (points at infinity) of the true device, through the rig's true
            // and calibrated rotations relative to the reference device.
            let turn =
                |pose: &nalgebra::Isometry3<f64>| pose.rotation * true_pose.rotation.inverse();
            let (image_error_max, image_error_rms) =
                model_difference(&t.model, &d.model, &turn(&d.pose));
            Some(TruthCheck {
                name: d.name.clone(),
                focal_error: ((e.fx / k.fx - 1.0).abs()).max((e.fy / k.fy - 1.0).abs()),
                principal_error: (e.cx - k.cx).hypot(e.cy - k.cy),
                rotation_error_deg: delta.rotation.angle().to_degrees(),
                position_error_mm: (d.pose.inverse().translation.vector
                    - true_pose.inverse().translation.vector)
                    .norm(),
                image_error_max,
                image_error_rms,
                all_terms_error_max: model_difference(
                    &t.model,
                    &lens.all_terms.model,
                    &turn(&lens.all_terms.pose),
                )
                .0,
            })
        })
        .collect()
}

/// The truth checks as a table.
pub fn format_truth(checks: &[TruthCheck]) -> String {
    let mut s = format!(
        "{:<10} {:>12} {:>12} {:>12} {:>12} {:>13} {:>13} {:>15}\n",
        "device",
        "focal err %",
        "pp err px",
        "rot err deg",
        "pos err mm",
        "image max px",
        "image rms px",
        "all terms max"
    );
    for c in checks {
        s += &format!(
            "{:<10} {:>12.4} {:>12.3} {:>12.4} {:>12.3} {:>13.4} {:>13.4} {:>15.4}\n",
            c.name,
            100.0 * c.focal_error,
            c.principal_error,
            c.rotation_error_deg,
            c.position_error_mm,
            c.image_error_max,
            c.image_error_rms,
            c.all_terms_error_max
        );
    }
    s += "image: projection error against the truth over the whole image (48 × 30 \
          points, corners included) of directions through the device's rotation relative to \
          the reference and its lens; all terms: the same for the model with every \
          distortion term estimated, before the undetermined ones were fixed\n";
    s
}
