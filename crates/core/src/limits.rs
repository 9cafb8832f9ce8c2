//! The limits on what hexcal reads (docs/limits.md): every count, size and name in a rig,
//! board, scene, dataset, correspondences or calibration file is checked against these
//! before anything is allocated from it, and a refusal names the limit.
//!
//! The limits are far beyond any real rig (the paper's rig has 9 devices, 1920×1200 images,
//! 10 poses and 614 circles per side); they exist so that a typo or a corrupted file is
//! refused with one line instead of an out-of-memory abort or an hour of work.

use crate::invalid::Invalid;

/// Board poses of a rig file's `[poses] count`, `--poses`, a correspondences file's `poses`
/// and a dataset's pose folders.
pub const MAX_POSES: usize = 10_000;

/// Devices (cameras and projectors together) of a rig, dataset or correspondences file.
pub const MAX_DEVICES: usize = 256;

/// Width or height of an image, camera or projector raster (px).
pub const MAX_IMAGE_SIDE: u32 = 65_536;

/// Pixels of an image, camera or projector raster (2²⁸ = 268 435 456).
pub const MAX_IMAGE_PIXELS: u64 = 1 << 28;

/// Circles on one side of a board.
pub const MAX_BOARD_CIRCLES: f64 = 100_000.0;

/// The smallest lattice pitch of a board (mm).
pub const MIN_BOARD_PITCH_MM: f64 = 1.0;

/// Largest |q| or |r| of a lattice position in a view.
pub const MAX_LATTICE_COORD: i32 = 100_000;

/// Memory one camera's phase decoder may hold (bytes): its frames of one group, phases
/// and modulations of every group and projector, per-pixel statistics (8 GiB; the paper
/// rig's 1920×1200 camera with 3 projectors needs about 0.2 GiB).
pub const MAX_DECODER_BYTES: u64 = 8 << 30;

/// Phase steps N of a sequence.
pub const MAX_PHASE_STEPS: u32 = 1_000;

/// Frames taken and averaged per pattern (`[timing] repeats`).
pub const MAX_REPEATS: u32 = 1_000;

/// The longest time any rig-file duration may give (ms): one hour.
pub const MAX_DURATION_MS: f64 = 3.6e6;

/// The longest capture of one board pose (`seconds` of pose.json, s): one day.
pub const MAX_POSE_SECONDS: f64 = 86_400.0;

/// Triggers repeated for one frame of a sequence (over its repeats), as pose.json records.
pub const MAX_FRAME_RETRIES: u32 = 1_000_000;

/// The shortest focal length of a camera or projector model (px): below one pixel per
/// unit of normalised image coordinate no lens images anything.
pub const MIN_FOCAL_PX: f64 = 1.0;

/// The longest focal length of a camera or projector model (px): 10⁷ px is a 10 m lens
/// on 1 µm pixels.
pub const MAX_FOCAL_PX: f64 = 1e7;

/// The largest |cx|, |cy| of a model (px): ten times the largest image side (a
/// projector's principal point may lie well outside its raster, not that far).
pub const MAX_PRINCIPAL_POINT_PX: f64 = 10.0 * MAX_IMAGE_SIDE as f64;

/// The largest |coefficient| of a lens distortion model (dimensionless).
pub const MAX_DISTORTION: f64 = 1e6;

/// The longest distance of a device pose or board transform (mm): one kilometre.
pub const MAX_DISTANCE_MM: f64 = 1e6;

/// The widest camera gain (dB), either sign: 100 dB is a factor of 10⁵ in amplitude,
/// beyond any sensor's analogue and digital gain together.
pub const MAX_GAIN_DB: f64 = 100.0;

/// The widest blur of a simulated sensor (Gaussian σ, px).
pub const MAX_PSF_SIGMA_PX: f64 = 100.0;

/// The finest feature of a simulated background (px).
pub const MIN_BACKGROUND_SCALE_PX: f64 = 1.0;

/// Bytes of a device name (names become folder and file names).
pub const MAX_NAME_BYTES: usize = 100;

/// Bytes of a text file hexcal reads (rig, board, scene, JSON): 256 MiB.
pub const MAX_TEXT_BYTES: u64 = 256 << 20;

/// The text of the file at `path`, refused (`InvalidData`, naming the limit) when it holds
/// more than [`MAX_TEXT_BYTES`]: reading stops there, so `/dev/zero` ends too.
pub fn read_text(path: &std::path::Path) -> std::io::Result<String> {
    use std::io::Read;
    let mut text = String::new();
    std::fs::File::open(path)?
        .take(MAX_TEXT_BYTES + 1)
        .read_to_string(&mut text)?;
    if text.len() as u64 > MAX_TEXT_BYTES {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("larger than {MAX_TEXT_BYTES} bytes (limits::MAX_TEXT_BYTES)"),
        ));
    }
    Ok(text)
}

/// `Err` naming the limit when `n` exceeds `max`, e.g. "20000 poses: at most 10000".
pub fn count(n: usize, max: usize, what: &str) -> Result<(), Invalid> {
    if n > max {
        return Err(Invalid(format!("{n} {what}: at most {max}")));
    }
    Ok(())
}

/// `Err` unless a `width`×`height` image is non-empty and within [`MAX_IMAGE_SIDE`] and
/// [`MAX_IMAGE_PIXELS`].
pub fn image_size(width: u32, height: u32) -> Result<(), Invalid> {
    if width == 0 || height == 0 {
        return Err(Invalid(format!("{width}×{height} px is empty")));
    }
    if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(Invalid(format!(
            "{width}×{height} px: width and height at most {MAX_IMAGE_SIDE}"
        )));
    }
    if u64::from(width) * u64::from(height) > MAX_IMAGE_PIXELS {
        return Err(Invalid(format!(
            "{width}×{height} px: at most {MAX_IMAGE_PIXELS} (2²⁸) pixels"
        )));
    }
    Ok(())
}

/// A number as a refusal shows it: plainly, or as `1e308` when very large or small (Rust
/// writes every digit of a large `f64`).
pub fn shown(v: f64) -> String {
    match v != 0.0 && v.is_finite() && !(1e-6..1e9).contains(&v.abs()) {
        true => format!("{v:e}"),
        false => format!("{v}"),
    }
}

/// `Err` unless every value is finite.
pub fn finite(values: &[f64]) -> Result<(), Invalid> {
    match values.iter().find(|v| !v.is_finite()) {
        Some(v) => Err(Invalid(format!("{} is not a finite number", shown(*v)))),
        None => Ok(()),
    }
}

/// `Err` unless `v` is finite and in `[0, max]`.
pub fn non_negative(v: f64, max: f64) -> Result<(), Invalid> {
    if !(v.is_finite() && (0.0..=max).contains(&v)) {
        return Err(Invalid(format!(
            "{} is not a number in [0, {}]",
            shown(v),
            shown(max)
        )));
    }
    Ok(())
}

/// `Err` unless `v` is finite and in `[min, max]`.
pub fn within(v: f64, min: f64, max: f64) -> Result<(), Invalid> {
    if !(v.is_finite() && (min..=max).contains(&v)) {
        return Err(Invalid(format!(
            "{} is not a number in [{}, {}]",
            shown(v),
            shown(min),
            shown(max)
        )));
    }
    Ok(())
}

/// `Err` unless a rigid transform read as a rotation vector `rvec` (rad) and a translation
/// `tvec` (mm) is one: finite, the rotation at most 2π (a longer vector is no rotation
/// anyone writes) and the translation within [`MAX_DISTANCE_MM`]. The error names `rvec`
/// or `tvec`.
pub fn rigid(rvec: &[f64; 3], tvec: &[f64; 3]) -> Result<(), crate::ValidationError> {
    finite(rvec).map_err(|m| m.at("rvec"))?;
    finite(tvec).map_err(|m| m.at("tvec"))?;
    let norm = |v: &[f64; 3]| v[0].hypot(v[1]).hypot(v[2]);
    let angle = norm(rvec);
    if angle > std::f64::consts::TAU + 1e-9 {
        let angle = shown(angle);
        return Err(Invalid(format!("a rotation of {angle} rad: at most 2π")).at("rvec"));
    }
    let distance = norm(tvec);
    if distance > MAX_DISTANCE_MM {
        return Err(Invalid(format!(
            "a translation of {} mm: at most {MAX_DISTANCE_MM:e} mm",
            shown(distance)
        ))
        .at("tvec"));
    }
    Ok(())
}

/// `Err` unless `name` can name a device, and so a folder or file: not empty, at most
/// [`MAX_NAME_BYTES`], no `/`, `\`, control character, and not `.` or `..`.
pub fn device_name(name: &str) -> Result<(), Invalid> {
    plain_name(name, "a device needs a name", "cannot name a folder")
}

/// `Err` unless `name` is not empty (else `empty`), at most [`MAX_NAME_BYTES`], and has no
/// `/`, `\`, control character and is not `.` or `..` (else "`name` `not`").
pub(crate) fn plain_name(name: &str, empty: &str, not: &str) -> Result<(), Invalid> {
    if name.is_empty() {
        return Err(Invalid::new(empty));
    }
    if name.len() > MAX_NAME_BYTES {
        return Err(Invalid(format!(
            "a name of {} bytes: at most {MAX_NAME_BYTES}",
            name.len()
        )));
    }
    if name == "."
        || name == ".."
        || name
            .chars()
            .any(|c| c == '/' || c == '\\' || c.is_control())
    {
        return Err(Invalid(format!(
            "{name:?} {not} (no /, \\, control characters, . or ..)"
        )));
    }
    Ok(())
}

/// `Err` unless `text` is a one-line label (a pixel format's name, …): not empty, at most
/// [`MAX_NAME_BYTES`], no control character.
pub fn label(text: &str) -> Result<(), Invalid> {
    if text.is_empty() || text.len() > MAX_NAME_BYTES {
        return Err(Invalid(format!(
            "a label of {} bytes: 1 to {MAX_NAME_BYTES}",
            text.len()
        )));
    }
    if text.chars().any(char::is_control) {
        return Err(Invalid(format!("{text:?} holds a control character")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_name_the_limit() {
        assert_eq!(
            count(20_000, MAX_POSES, "poses").unwrap_err(),
            "20000 poses: at most 10000"
        );
        assert!(count(MAX_POSES, MAX_POSES, "poses").is_ok());
        assert!(image_size(4_294_967_295, 10)
            .unwrap_err()
            .message()
            .contains("65536"));
        assert!(image_size(65_536, 65_536)
            .unwrap_err()
            .message()
            .contains("2²⁸"));
        assert!(image_size(0, 10).unwrap_err().contains("empty"));
        assert!(image_size(16_384, 16_384).is_ok());
        assert!(finite(&[1.0, f64::NAN]).is_err() && finite(&[1.0, -2.0]).is_ok());
        assert!(non_negative(f64::INFINITY, 10.0).is_err());
        assert!(non_negative(-1.0, 10.0).is_err() && non_negative(0.0, 10.0).is_ok());
        for bad in ["", ".", "..", "a/b", "a\\b", "a\nb"] {
            assert!(device_name(bad).is_err(), "{bad:?}");
        }
        assert!(device_name(&"x".repeat(101))
            .unwrap_err()
            .message()
            .contains("100"));
        assert!(device_name("cam 0").is_ok());
        assert!(within(3.0, 1.0, 3.0).is_ok() && within(0.5, 1.0, 3.0).is_err());
        assert!(within(f64::NAN, 1.0, 3.0).is_err());
        assert_eq!(shown(1e308), "1e308");
        assert_eq!(shown(1e-320), "1e-320");
        assert_eq!(shown(-2.5), "-2.5");
        assert_eq!(shown(f64::NAN), "NaN");
        assert!(rigid(&[0.0, 3.0, 0.0], &[1e5, 0.0, 0.0]).is_ok());
        let e = rigid(&[0.0; 3], &[1e308, 0.0, 0.0]).unwrap_err();
        assert_eq!(e.at, "tvec");
        assert!(e.message.contains("at most 1e6 mm"), "{e}");
        assert_eq!(rigid(&[7.0, 0.0, 0.0], &[0.0; 3]).unwrap_err().at, "rvec");
        assert_eq!(rigid(&[0.0; 3], &[f64::NAN; 3]).unwrap_err().at, "tvec");
    }
}
