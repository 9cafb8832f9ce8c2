//! Scene files: one camera looking at the board in one pose, with imaging conditions and a
//! seed (TOML). Every table but `[camera]` and `[pose]` is optional:
//!
//! ```toml
//! name = "view"            # output files NAME.png, NAME.json
//! seed = 1                 # noise seed
//!
//! [camera]                 # hexcal's CameraModel: OpenCV pinhole + distortion
//! width = 1920
//! height = 1200
//! intrinsics = { fx = 1600.0, fy = 1600.0, cx = 962.3, cy = 597.8 }
//! distortion = { k1 = -0.12, k2 = 0.05, p1 = 0.0004, p2 = -0.0003, k3 = 0.0 }
//!
//! [pose]                   # either rvec + tvec (X_cam = R·X_board + t, mm) …
//! rvec = [2.73, -0.056, -0.276]
//! tvec = [0.0, 0.0, 975.0]
//! # … or a look-at in the board frame (mm): eye, target, optional up (default +y)
//! # eye = [180.0, -380.0, 880.0]
//! # target = [0.0, 0.0, 0.0]
//!
//! [imaging]                # defaults: docs/design.md §9, single frames
//! white_dn = 200.0         # DN on an 8-bit scale, whatever `bits` is
//! black_dn = 20.0
//! edge_dn = 40.0           # the board's edge faces
//! background_dn = 60.0
//! background_variation = 0.5
//! background_scale_px = 80.0
//! psf_sigma = 0.8
//! vignetting = 0.0         # relative light loss in the image corners
//! shot_gain = 0.1          # shot noise variance per DN of signal
//! read_noise = 2.0
//! gamma = 1.0
//! bits = 8                 # 8, 12 or 16
//!
//! [board]                  # optional: a board description (default hex600)
//! ```

use super::SimError;
use hexcal_core::board::Board;
use hexcal_core::camera::CameraModel;
use hexcal_core::limits::{MAX_PSF_SIGMA_PX, MIN_BACKGROUND_SCALE_PX};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The built-in scene: 1920×1200, f = 1600 px, mild barrel distortion, the front of hex600
/// about 1 m away and tilted ~25°, circles ≈ 9–11 px in radius.
pub const DEFAULT_SCENE: &str = r#"
name = "view"
seed = 1

[camera]
width = 1920
height = 1200

[camera.intrinsics]
fx = 1600.0
fy = 1600.0
cx = 962.3
cy = 597.8

[camera.distortion]
k1 = -0.12
k2 = 0.05
p1 = 0.0004
p2 = -0.0003
k3 = 0.0

[pose]
eye = [180.0, -380.0, 880.0]
target = [0.0, 0.0, 0.0]
up = [0.0, 1.0, 0.0]
"#;

/// A scene: camera, board pose, imaging, seed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Base name of the written files (`NAME.png`, `NAME.json`).
    #[serde(default = "default_name")]
    pub name: String,
    /// Noise seed.
    #[serde(default)]
    pub seed: u64,
    /// The camera.
    pub camera: CameraModel,
    /// Where the board is.
    pub pose: PoseSpec,
    /// Imaging conditions (defaults: docs/design.md §9, single frames).
    #[serde(default)]
    pub imaging: Imaging,
    /// The board (default hex600).
    #[serde(default = "Board::hex600")]
    pub board: Board,
}

fn default_name() -> String {
    "view".into()
}

/// The board pose, either `rvec` + `tvec` (X_cam = R·X_board + t, mm, as OpenCV) or a look-at:
/// the camera at `eye` looking at `target` (board frame, mm) with the board direction `up`
/// (default +y) pointing up in the image.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseSpec {
    /// Rotation vector of R (rad).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rvec: Option<[f64; 3]>,
    /// Translation t (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tvec: Option<[f64; 3]>,
    /// Camera centre in the board frame (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eye: Option<[f64; 3]>,
    /// Board-frame point on the optical axis (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<[f64; 3]>,
    /// Board-frame direction shown upwards.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub up: Option<[f64; 3]>,
}

impl PoseSpec {
    /// `T_cam_board`.
    pub fn cam_from_board(&self) -> Result<Isometry3<f64>, SimError> {
        let bad = |m: &str| SimError::Scene(format!("[pose]: {m}"));
        match (self.rvec, self.tvec, self.eye, self.target) {
            (Some(r), Some(t), None, None) if self.up.is_none() => Ok(Isometry3::from_parts(
                Translation3::from(Vector3::from(t)),
                UnitQuaternion::from_scaled_axis(Vector3::from(r)),
            )),
            (None, None, Some(eye), Some(target)) => {
                let eye = Vector3::from(eye);
                let z = Vector3::from(target) - eye;
                let up = Vector3::from(self.up.unwrap_or([0.0, 1.0, 0.0]));
                // Image y points down: opposite to `up` projected across the optical axis.
                let y = -(up - z * (up.dot(&z) / z.norm_squared()));
                if z.norm() == 0.0 || y.norm() < 1e-9 * up.norm().max(1e-300) {
                    return Err(bad("eye equals target, or up is parallel to the view"));
                }
                let (z, y) = (z.normalize(), y.normalize());
                let board_from_cam = Matrix3::from_columns(&[y.cross(&z), y, z]);
                let rot = Rotation3::from_matrix_unchecked(board_from_cam.transpose());
                Ok(Isometry3::from_parts(
                    Translation3::from(-(rot * eye)),
                    UnitQuaternion::from_rotation_matrix(&rot),
                ))
            }
            _ => Err(bad(
                "give either rvec and tvec, or eye and target (and optionally up)",
            )),
        }
    }
}

/// Imaging conditions. Intensities in DN of an 8-bit scale (a 12- or 16-bit image stores
/// them ×(2^bits − 1)/255).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Imaging {
    /// White of the circles at the image centre (DN).
    pub white_dn: f64,
    /// Black of the board and the rings (DN).
    pub black_dn: f64,
    /// The board's edge faces (DN).
    pub edge_dn: f64,
    /// Mean background outside the board (DN).
    pub background_dn: f64,
    /// Relative amplitude of the background's smooth variation.
    pub background_variation: f64,
    /// Feature size of the background variation (px).
    pub background_scale_px: f64,
    /// Gaussian PSF σ (px).
    pub psf_sigma: f64,
    /// Relative light loss in the image corners.
    pub vignetting: f64,
    /// Shot noise variance per DN of signal (DN).
    pub shot_gain: f64,
    /// Read noise σ (DN).
    pub read_noise: f64,
    /// Camera gamma (out = 255·(I/255)^(1/γ)).
    pub gamma: f64,
    /// Output depth: 8, 12 or 16 bits (12 is stored in a 16-bit PNG, values < 4096).
    pub bits: u8,
}

impl Default for Imaging {
    fn default() -> Self {
        Imaging {
            white_dn: 200.0,
            black_dn: 20.0,
            edge_dn: 40.0,
            background_dn: 60.0,
            background_variation: 0.5,
            background_scale_px: 80.0,
            psf_sigma: 0.8,
            vignetting: 0.0,
            shot_gain: 0.1,
            read_noise: 2.0,
            gamma: 1.0,
            bits: 8,
        }
    }
}

impl Imaging {
    /// The same conditions without noise.
    pub fn noise_free(self) -> Imaging {
        Imaging {
            shot_gain: 0.0,
            read_noise: 0.0,
            ..self
        }
    }

    fn check(&self) -> Result<(), SimError> {
        let bad = |m: String| Err(SimError::Scene(format!("[imaging]: {m}")));
        if !matches!(self.bits, 8 | 12 | 16) {
            return bad(format!("bits = {} (expected 8, 12 or 16)", self.bits));
        }
        if !(self.white_dn.is_finite() && self.white_dn > 0.0) {
            return bad(format!("white_dn = {} must be positive", self.white_dn));
        }
        hexcal_core::limits::finite(&[
            self.black_dn,
            self.edge_dn,
            self.background_dn,
            self.background_variation,
            self.background_scale_px,
            self.psf_sigma,
            self.vignetting,
            self.shot_gain,
            self.read_noise,
            self.gamma,
        ])
        .map_err(|m| SimError::Scene(format!("[imaging]: {m}")))?;
        if self.psf_sigma > MAX_PSF_SIGMA_PX {
            return bad(format!(
                "psf_sigma = {} px: at most {MAX_PSF_SIGMA_PX}",
                self.psf_sigma
            ));
        }
        if self.background_scale_px < MIN_BACKGROUND_SCALE_PX {
            return bad(format!(
                "background_scale_px = {} px: at least {MIN_BACKGROUND_SCALE_PX}",
                self.background_scale_px
            ));
        }
        for (name, v) in [
            ("black_dn", self.black_dn),
            ("edge_dn", self.edge_dn),
            ("background_dn", self.background_dn),
            ("psf_sigma", self.psf_sigma),
            ("shot_gain", self.shot_gain),
            ("read_noise", self.read_noise),
        ] {
            if v.is_nan() || v < 0.0 {
                return bad(format!("{name} = {v} must be ≥ 0"));
            }
        }
        if [self.gamma, self.background_scale_px]
            .iter()
            .any(|v| v.is_nan() || *v <= 0.0)
        {
            return bad("gamma and background_scale_px must be positive".into());
        }
        Ok(())
    }
}

impl Scene {
    /// The output name (a plain file name, [`hexcal_core::paths::file_name`]), the camera
    /// (as [`CameraModel::check`](hexcal_core::camera::CameraModel::check) requires), the
    /// pose (finite) and the board (as [`Board::validate`] requires).
    fn check(&self) -> Result<(), SimError> {
        hexcal_core::paths::file_name(&self.name)
            .map_err(|m| SimError::Scene(format!("name: {m} (it names the output files)")))?;
        self.camera
            .check()
            .map_err(|e| SimError::Scene(format!("[camera] {e}")))?;
        let p = &self.pose;
        for (key, v) in [
            ("rvec", p.rvec),
            ("tvec", p.tvec),
            ("eye", p.eye),
            ("target", p.target),
            ("up", p.up),
        ] {
            if let Some(v) = v {
                hexcal_core::limits::finite(&v)
                    .map_err(|m| SimError::Scene(format!("[pose] {key}: {m}")))?;
            }
        }
        self.board
            .validate()
            .map_err(|e| SimError::Scene(format!("[board] {e}")))
    }

    /// The built-in scene.
    pub fn default_scene() -> Scene {
        Scene::parse(DEFAULT_SCENE, "built-in scene").expect("the built-in scene parses")
    }

    /// Parse a scene; `origin` names the source in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Scene, SimError> {
        let scene: Scene = toml::from_str(text).map_err(|e| SimError::Toml {
            path: origin.into(),
            message: e.to_string(),
        })?;
        let named = |e: SimError| match e {
            SimError::Scene(m) => SimError::Scene(format!("{origin} {m}")),
            e => e,
        };
        scene.imaging.check().map_err(named)?;
        scene.check().map_err(named)?;
        scene.pose.cam_from_board().map_err(named)?;
        Ok(scene)
    }

    /// Read a scene file.
    pub fn load(path: &Path) -> Result<Scene, SimError> {
        let text = hexcal_core::limits::read_text(path).map_err(|source| SimError::Io {
            path: path.into(),
            source,
        })?;
        Scene::parse(&text, &path.display().to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn look_at_puts_the_target_on_the_axis_and_up_upwards() {
        let pose = Scene::default_scene().pose;
        let t = pose.cam_from_board().unwrap();
        let c = t * Point3::origin();
        assert!(c.x.abs() < 1e-9 && c.y.abs() < 1e-9 && c.z > 0.0);
        // The eye is the camera centre.
        let eye = t.inverse() * Point3::origin();
        assert!((eye.coords - Vector3::from(pose.eye.unwrap())).norm() < 1e-9);
        // A point above the target on the board appears higher in the image (smaller y).
        let above = t * Point3::new(0.0, 10.0, 0.0);
        assert!(above.y / above.z < 0.0);
    }

    #[test]
    fn rvec_tvec_and_errors() {
        let p = PoseSpec {
            rvec: Some([0.1, -0.2, 0.3]),
            tvec: Some([1.0, 2.0, 900.0]),
            ..PoseSpec::default()
        };
        let t = p.cam_from_board().unwrap();
        assert!((t.translation.vector - Vector3::new(1.0, 2.0, 900.0)).norm() < 1e-12);
        assert!((t.rotation.scaled_axis() - Vector3::new(0.1, -0.2, 0.3)).norm() < 1e-12);
        let both = PoseSpec {
            eye: Some([0.0, 0.0, 1.0]),
            ..p
        };
        assert!(both.cam_from_board().is_err());
        let e = Scene::parse("seed = 1\n[camera]\nwidth = 10\n", "x.toml").unwrap_err();
        assert!(e.to_string().contains("x.toml"), "{e}");
    }
}
