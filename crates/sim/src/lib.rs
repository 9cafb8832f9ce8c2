//! Simulated board views (docs/design.md §9): hexcal's board, camera model and scene files
//! plugged into the `hexcal-simulator` renderer.
//!
//! Takes a [`Scene`] (camera, board pose, imaging conditions, seed) and gives a rendered
//! 8-, 12- or 16-bit image of the board side facing the camera with its [`GroundTruth`]; writes
//! both atomically as `NAME.png` and `NAME.json`.

#![warn(missing_docs)]

#[cfg(any(test, feature = "fringe"))]
pub mod fringe;
pub mod scene;
pub mod stack;
pub mod texture;
pub mod truth;

pub use scene::{Imaging, PoseSpec, Scene, DEFAULT_SCENE};
pub use texture::{board_target, face_side, BoardAlbedo, BoardTexture};
pub use truth::CircleTruth;

use hexcal_core::board::{Board, Side};
use hexcal_core::camera::CameraModel;
use hexcal_simulator::{
    render_geometry, Background, Frame, Geometry, ImageSize, Lens, RayGrid, RenderOptions, Sensor,
};
use nalgebra::{Point2, Vector3};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Errors of the simulation stage.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A scene file does not parse.
    #[error("{path}: {message}")]
    Toml {
        /// The file (or "built-in scene").
        path: String,
        /// The parser's message.
        message: String,
    },
    /// A scene is inconsistent (the message names the scene file and table).
    #[error("scene {0}")]
    Scene(String),
    /// The image could not be encoded.
    #[error("{path}: {message}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// The encoder's message.
        message: String,
    },
}

/// hexcal's camera model as the renderer's lens: its image size and the ray of each pixel.
#[derive(Clone, Copy, Debug)]
pub struct CameraLens<'a>(pub &'a CameraModel);

impl Lens for CameraLens<'_> {
    fn size(&self) -> ImageSize {
        ImageSize {
            width: self.0.width,
            height: self.0.height,
        }
    }

    fn ray(&self, pixel: Point2<f64>) -> Option<Vector3<f64>> {
        self.0.ray(pixel)
    }
}

/// Camera in the samples' JSON form.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CameraTruth {
    /// Camera matrix.
    #[serde(rename = "K")]
    pub k: [[f64; 3]; 3],
    /// OpenCV distortion coefficients.
    pub dist: Vec<f64>,
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
}

/// Board pose in the samples' JSON form.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PoseTruth {
    /// Rotation matrix R.
    #[serde(rename = "R")]
    pub r: [[f64; 3]; 3],
    /// Translation t (mm).
    pub t: [f64; 3],
    /// Rotation vector of R (rad).
    pub rvec: [f64; 3],
    /// Always "mm".
    pub units: &'static str,
    /// Always "X_cam = R X_board + t".
    pub note: &'static str,
}

/// Ground truth written beside an image.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GroundTruth {
    /// Image file name.
    pub image: String,
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
    /// Noise seed.
    pub seed: u64,
    /// Board side facing the camera (`None` edge-on).
    pub side: Option<Side>,
    /// The camera.
    pub camera: CameraTruth,
    /// The board pose.
    pub pose: PoseTruth,
    /// The board.
    pub board: Board,
    /// Imaging conditions.
    pub render: Imaging,
    /// Every circle of the seen side that is imaged (wholly or in part).
    pub circles: Vec<CircleTruth>,
}

/// A rendered view.
pub struct View {
    /// The image.
    pub frame: Frame,
    /// The noise-free signal before gamma and quantisation (DN, 8-bit scale).
    pub signal: Vec<f32>,
    /// Its ground truth.
    pub truth: GroundTruth,
}

/// Camera-independent parts of a scene's rendering.
fn albedo(imaging: &Imaging) -> (BoardAlbedo, Background) {
    let rel = |dn: f64| (dn / imaging.white_dn) as f32;
    (
        BoardAlbedo {
            white: 1.0,
            black: rel(imaging.black_dn),
            edge: rel(imaging.edge_dn),
        },
        Background {
            albedo: rel(imaging.background_dn),
            variation: imaging.background_variation as f32,
            scale_px: imaging.background_scale_px,
            seed: 0x6261_636b,
        },
    )
}

/// The sensor of a scene's imaging conditions.
pub fn sensor(imaging: &Imaging) -> Sensor {
    Sensor {
        psf_sigma: imaging.psf_sigma,
        vignetting: imaging.vignetting,
        shot_gain: imaging.shot_gain,
        read_noise: imaging.read_noise,
        gamma: imaging.gamma,
        bits: imaging.bits,
        cfa: None,
    }
}

/// The geometry pass of a scene (ray grid built here; reuse [`geometry_with`] across poses).
pub fn geometry(scene: &Scene) -> Result<Geometry, SimError> {
    let lens = CameraLens(&scene.camera);
    let rays = RayGrid::new(&lens);
    geometry_with(&rays, scene)
}

/// The geometry pass of a scene with a prepared ray grid of its camera.
pub fn geometry_with(rays: &RayGrid, scene: &Scene) -> Result<Geometry, SimError> {
    let pose = scene.pose.cam_from_board()?;
    let (alb, background) = albedo(&scene.imaging);
    let target = board_target(&scene.board, alb);
    Ok(render_geometry(
        rays,
        &target,
        &pose,
        &background,
        RenderOptions::default(),
    ))
}

/// The ground truth of a scene.
pub fn ground_truth(scene: &Scene) -> Result<GroundTruth, SimError> {
    let pose = scene.pose.cam_from_board()?;
    let cam = &scene.camera;
    let k = &cam.intrinsics;
    let r = pose.rotation.to_rotation_matrix();
    let m = r.matrix();
    let t = pose.translation.vector;
    let rvec = pose.rotation.scaled_axis();
    Ok(GroundTruth {
        image: format!("{}.png", scene.name),
        width: cam.width,
        height: cam.height,
        seed: scene.seed,
        side: truth::side_seen(&scene.board, &pose),
        camera: CameraTruth {
            k: [[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]],
            dist: cam.distortion.to_opencv(),
            width: cam.width,
            height: cam.height,
        },
        pose: PoseTruth {
            r: std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)])),
            t: [t.x, t.y, t.z],
            rvec: [rvec.x, rvec.y, rvec.z],
            units: "mm",
            note: "X_cam = R X_board + t",
        },
        board: scene.board.clone(),
        render: scene.imaging,
        circles: truth::circles(&scene.board, cam, &pose),
    })
}

/// Render a scene: geometry, one frame, ground truth.
pub fn render(scene: &Scene) -> Result<View, SimError> {
    let geo = geometry(scene)?;
    let sensor = sensor(&scene.imaging);
    let signal = sensor.optics(geo.size, &geo.irradiance(scene.imaging.white_dn as f32));
    let frame = sensor.expose(geo.size, &signal, scene.seed);
    Ok(View {
        frame,
        signal,
        truth: ground_truth(scene)?,
    })
}

/// Write a frame as a grey PNG, atomically: 8-bit frames as 8-bit, 12- and 16-bit frames as
/// 16-bit (12-bit values stay < 4096).
pub fn write_png(frame: &Frame, path: &Path) -> Result<(), SimError> {
    let (w, h) = (frame.size.width, frame.size.height);
    let io = |source| SimError::Io {
        path: path.into(),
        source,
    };
    hexcal_core::atomic::write_encoded(
        path,
        |bytes| {
            let res = if frame.bits == 8 {
                let data: Vec<u8> = frame.data.iter().map(|&v| v as u8).collect();
                image::GrayImage::from_raw(w, h, data)
                    .map(|img| img.write_to(bytes, image::ImageFormat::Png))
            } else {
                image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, frame.data.clone())
                    .map(|img| img.write_to(bytes, image::ImageFormat::Png))
            };
            match res {
                Some(Ok(())) => Ok(()),
                Some(Err(e)) => Err(SimError::Encode {
                    path: path.into(),
                    message: e.to_string(),
                }),
                None => Err(SimError::Encode {
                    path: path.into(),
                    message: "frame size does not match its data".into(),
                }),
            }
        },
        io,
    )
}

/// Write a view as `DIR/NAME.png` and `DIR/NAME.json` (created atomically); returns the
/// two paths.
pub fn write_view(view: &View, dir: &Path) -> Result<[PathBuf; 2], SimError> {
    std::fs::create_dir_all(dir).map_err(|source| SimError::Io {
        path: dir.into(),
        source,
    })?;
    let png = dir.join(&view.truth.image);
    let json = png.with_extension("json");
    write_png(&view.frame, &png)?;
    let text = serde_json::to_string_pretty(&view.truth).expect("ground truth serialises");
    hexcal_core::atomic::write(&json, text.as_bytes()).map_err(|source| SimError::Io {
        path: json.clone(),
        source,
    })?;
    Ok([png, json])
}

#[cfg(test)]
mod tests;

/// Paths of the test data vendored in the repository (`tests/data`).
#[cfg(test)]
pub(crate) mod testdata {
    use std::path::PathBuf;

    /// The independent sample images with ground truth (`tests/data/samples`, README there).
    pub(crate) fn samples_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/samples")
    }
}
