//! Captured board poses on disk (format: `docs/dataset.md`).
//!
//! Takes [`StackFrame`]s as the engine delivers them; gives a dataset folder with, per pose
//! and camera, the stack's frames as PNG (8 or 16 bit) and a `stack.json` describing them
//! and the sequence, and reads such stacks back. Every file is written atomically (temporary
//! file + rename); a pose is complete when its `pose.json` exists, so an interrupted capture
//! keeps every finished pose and resumes at the first incomplete one.

use crate::images::{CameraFrame, Pixels};
use crate::invalid::ValidationError;
use crate::limits;
use crate::pattern::Sequence;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The format name in `dataset.json`.
pub const FORMAT: &str = "hexcal-dataset";
/// The format version this build writes and reads.
pub const VERSION: u32 = 1;

/// A dataset problem, naming the file.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        source: std::io::Error,
    },
    /// A file's content is wrong.
    #[error("{path}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A value of a file is wrong: the file, the value's JSON path and what is wrong.
    #[error(transparent)]
    Check(ValidationError),
    /// A frame of a stack is missing, unreadable or does not match the others.
    #[error("camera {camera}, frame {frame} ({path}): {reason}")]
    Frame {
        /// Camera name.
        camera: String,
        /// Frame index.
        frame: usize,
        /// The frame's file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_owned(),
        source,
    }
}

/// A camera of the dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraEntry {
    /// Name.
    pub name: String,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Bits per sample.
    pub bits: u8,
    /// The pixel format the camera delivered, as its driver names it (`Mono12`,
    /// `BayerRG8`, `MJPG (quality 85)`, …; docs/design.md §11); absent in datasets written
    /// before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_format: Option<String>,
}

/// A projector of the dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectorEntry {
    /// Name.
    pub name: String,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
}

/// `dataset.json`: what was captured, with what.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetInfo {
    /// Always [`FORMAT`].
    pub format: String,
    /// Format version.
    pub version: u32,
    /// Rig name.
    pub rig: String,
    /// Board: built-in name or the board file's path relative to the dataset.
    pub board: String,
    /// The sequence every projector showed (projector i shows code i).
    pub sequence: Sequence,
    /// Cameras, in capture order.
    pub cameras: Vec<CameraEntry>,
    /// Projectors, in sequence order.
    pub projectors: Vec<ProjectorEntry>,
}

/// One frame of a stack on disk.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameEntry {
    /// Index k in the sequence.
    pub index: usize,
    /// File name, relative to the stack folder.
    pub file: String,
    /// The camera's frame counter.
    pub counter: u64,
    /// Exposure timestamp (ns, camera clock).
    pub timestamp_ns: u64,
    /// Exposure time (µs).
    pub exposure_us: f64,
}

/// `stack.json`: one camera's stack of one pose (self-contained: `hexcal decode` reads it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StackInfo {
    /// Camera name.
    pub camera: String,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Bits per sample (full scale 2^bits − 1).
    pub bits: u8,
    /// The sequence shown.
    pub sequence: Sequence,
    /// The frames, in sequence order.
    pub frames: Vec<FrameEntry>,
}

/// `pose.json`: a completed pose and its capture timeline (written last).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseInfo {
    /// Pose index.
    pub pose: usize,
    /// Cameras with a stack in the pose folder.
    pub cameras: Vec<String>,
    /// Capture time (s).
    pub seconds: f64,
    /// Frames lost and retaken.
    pub dropped: u64,
    /// Per frame: presented, triggered, collected (ms from the pose's start) and retries.
    pub timeline: Vec<[f64; 4]>,
}

/// A dataset folder.
#[derive(Clone, Debug)]
pub struct Dataset {
    root: PathBuf,
    /// Its description.
    pub info: DatasetInfo,
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), DatasetError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| DatasetError::Invalid {
        path: path.to_owned(),
        reason: e.to_string(),
    })?;
    crate::atomic::write(path, format!("{text}\n").as_bytes()).map_err(io(path))
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, DatasetError> {
    let text = crate::limits::read_text(path).map_err(io(path))?;
    serde_json::from_str(&text).map_err(|e| DatasetError::Invalid {
        path: path.to_owned(),
        reason: e.to_string(),
    })
}

/// `Check` naming `path` with the problem a check found.
fn invalid(path: &Path) -> impl FnOnce(ValidationError) -> DatasetError + '_ {
    move |e| DatasetError::Check(e.in_file(path))
}

/// Device names of the dataset, unique and usable as folder names ([`limits::device_name`]).
fn check_names<'a>(names: impl Iterator<Item = (String, &'a str)>) -> Result<(), ValidationError> {
    let mut seen: std::collections::HashMap<&str, String> = std::collections::HashMap::new();
    for (at, name) in names {
        limits::device_name(name).map_err(|m| m.at(at.clone()))?;
        if let Some(first) = seen.insert(name, at.clone()) {
            return Err(ValidationError::new(
                at,
                format!("{name:?} is already the name of {first}"),
            ));
        }
    }
    Ok(())
}

impl DatasetInfo {
    /// The first problem of a `dataset.json`: the JSON path and what is wrong. Devices within
    /// [`limits::MAX_DEVICES`], names unique and usable as folder names, image sizes within
    /// [`limits::image_size`], 8, 12 or 16 bits, and one sequence code per projector with
    /// the projector's raster size.
    pub fn check(&self) -> Result<(), ValidationError> {
        if self.cameras.is_empty() {
            return Err(ValidationError::new("cameras", "no camera"));
        }
        let devices = self.cameras.len() + self.projectors.len();
        limits::count(devices, limits::MAX_DEVICES, "devices").map_err(|m| m.at("cameras"))?;
        let cameras = self.cameras.iter().enumerate();
        let projectors = self.projectors.iter().enumerate();
        check_names(
            cameras
                .clone()
                .map(|(i, c)| (format!("cameras[{i}].name"), c.name.as_str()))
                .chain(
                    projectors
                        .clone()
                        .map(|(i, p)| (format!("projectors[{i}].name"), p.name.as_str())),
                ),
        )?;
        for (i, c) in cameras {
            limits::image_size(c.width, c.height)
                .map_err(|m| m.at(format!("cameras[{i}].width")))?;
            if ![8, 12, 16].contains(&c.bits) {
                return Err(ValidationError::new(
                    format!("cameras[{i}].bits"),
                    format!("{} bits: 8, 12 or 16", c.bits),
                ));
            }
            if let Some(f) = &c.pixel_format {
                limits::label(f).map_err(|m| m.at(format!("cameras[{i}].pixel_format")))?;
            }
        }
        let codes = self.sequence.projectors();
        if codes.len() != self.projectors.len() {
            return Err(ValidationError::new(
                "sequence.projectors",
                format!(
                    "{} codes for {} projectors",
                    codes.len(),
                    self.projectors.len()
                ),
            ));
        }
        for ((i, p), code) in projectors.zip(codes) {
            if (p.width, p.height) != (code.width, code.height) {
                return Err(ValidationError::new(
                    format!("projectors[{i}].width"),
                    format!(
                        "{}×{} px, but its sequence code is {}×{} px",
                        p.width, p.height, code.width, code.height
                    ),
                ));
            }
        }
        Ok(())
    }
}

impl StackInfo {
    /// The first problem of a `stack.json`: the JSON path and what is wrong. A camera name usable
    /// as a folder name, an image size within [`limits::image_size`], 8, 12 or 16 bits, and
    /// frame files inside the stack folder (relative, no `..`) with finite exposures.
    pub fn check(&self) -> Result<(), ValidationError> {
        limits::device_name(&self.camera).map_err(|m| m.at("camera"))?;
        limits::image_size(self.width, self.height).map_err(|m| m.at("width"))?;
        if ![8, 12, 16].contains(&self.bits) {
            return Err(ValidationError::new(
                "bits",
                format!("{} bits: 8, 12 or 16", self.bits),
            ));
        }
        for (i, f) in self.frames.iter().enumerate() {
            let inside = !f.file.is_empty()
                && Path::new(&f.file)
                    .components()
                    .all(|c| matches!(c, std::path::Component::Normal(_)));
            if !inside {
                return Err(ValidationError::new(
                    format!("frames[{i}].file"),
                    format!("{:?} is not a file inside the stack folder", f.file),
                ));
            }
            limits::non_negative(f.exposure_us, 1e3 * limits::MAX_DURATION_MS)
                .map_err(|m| m.at(format!("frames[{i}].exposure_us")))?;
        }
        Ok(())
    }
}

/// `pose.json` and `captured.json`: its own pose index; one or more cameras of the dataset,
/// each once; the capture time within [`limits::MAX_POSE_SECONDS`] and the timeline's
/// times within as many milliseconds; at most one timeline entry per frame of the
/// sequence; retries whole numbers up to [`limits::MAX_FRAME_RETRIES`] per frame (`dropped`
/// is a camera's counter gaps, any count).
impl PoseFile for PoseInfo {
    fn check(&self, pose: usize, info: &DatasetInfo) -> Result<(), ValidationError> {
        if self.pose != pose {
            return Err(ValidationError::new(
                "pose",
                format!("{} in the folder of pose {pose}", self.pose),
            ));
        }
        if self.cameras.is_empty() {
            return Err(ValidationError::new("cameras", "no camera"));
        }
        for (i, c) in self.cameras.iter().enumerate() {
            if !info.cameras.iter().any(|e| &e.name == c) {
                return Err(ValidationError::new(
                    format!("cameras[{i}]"),
                    format!("{c:?} is not a camera of the dataset"),
                ));
            }
            if let Some(first) = self.cameras[..i].iter().position(|e| e == c) {
                return Err(ValidationError::new(
                    format!("cameras[{i}]"),
                    format!("{c:?} is already cameras[{first}]"),
                ));
            }
        }
        limits::non_negative(self.seconds, limits::MAX_POSE_SECONDS)
            .map_err(|m| m.at("seconds"))?;
        let frames = info.sequence.frame_count();
        limits::count(
            self.timeline.len(),
            frames,
            "timeline entries (frames of the sequence)",
        )
        .map_err(|m| m.at("timeline"))?;
        for (i, t) in self.timeline.iter().enumerate() {
            for (j, v) in t[..3].iter().enumerate() {
                limits::non_negative(*v, 1e3 * limits::MAX_POSE_SECONDS)
                    .map_err(|m| m.at(format!("timeline[{i}][{j}]")))?;
            }
            let retries = t[3];
            if retries.fract() != 0.0 {
                return Err(ValidationError::new(
                    format!("timeline[{i}][3]"),
                    format!("{retries} retries is not a whole number"),
                ));
            }
            limits::non_negative(retries, f64::from(limits::MAX_FRAME_RETRIES))
                .map_err(|m| m.at(format!("timeline[{i}][3]")))?;
        }
        Ok(())
    }
}

/// A JSON file of a pose folder, checked against its dataset before use.
pub trait PoseFile: for<'de> Deserialize<'de> {
    /// The first problem of the file of pose `pose` in a dataset of `info`: the JSON path
    /// and what is wrong.
    fn check(&self, pose: usize, info: &DatasetInfo) -> Result<(), ValidationError>;
}

impl Dataset {
    /// Create the dataset at `root`, or resume the one there when it describes the same
    /// capture (same cameras, projectors and sequence); anything else is refused.
    pub fn create_or_resume(root: &Path, info: DatasetInfo) -> Result<Dataset, DatasetError> {
        let path = root.join("dataset.json");
        if path.exists() {
            let found = Dataset::open(root)?;
            let same_camera = |a: &CameraEntry, b: &CameraEntry| {
                (&a.name, a.width, a.height, a.bits) == (&b.name, b.width, b.height, b.bits)
            };
            let same_cameras = found.info.cameras.len() == info.cameras.len()
                && found
                    .info
                    .cameras
                    .iter()
                    .zip(&info.cameras)
                    .all(|(a, b)| same_camera(a, b));
            if !same_cameras
                || (&found.info.projectors, &found.info.sequence)
                    != (&info.projectors, &info.sequence)
            {
                return Err(DatasetError::Invalid {
                    path,
                    reason: "a different capture (cameras, projectors or sequence) is already \
                             here; choose another folder"
                        .into(),
                });
            }
            return Ok(found);
        }
        std::fs::create_dir_all(root).map_err(io(root))?;
        write_json(&path, &info)?;
        Ok(Dataset {
            root: root.to_owned(),
            info,
        })
    }

    /// Record the pixel format each camera delivers (`formats`, in camera order; `None`
    /// where the driver does not say) in `dataset.json`. A camera whose recorded format
    /// differs is refused by name: frames of two formats would share one stack.
    pub fn record_formats(&mut self, formats: &[Option<String>]) -> Result<(), DatasetError> {
        let path = self.root.join("dataset.json");
        let mut info = self.info.clone();
        for (entry, now) in info.cameras.iter_mut().zip(formats) {
            match (&entry.pixel_format, now) {
                (Some(was), Some(now)) if was != now => {
                    return Err(DatasetError::Invalid {
                        path,
                        reason: format!(
                            "camera {} delivered {was} here and now delivers {now}; choose \
                             another folder",
                            entry.name
                        ),
                    })
                }
                (_, Some(now)) => entry.pixel_format = Some(now.clone()),
                (_, None) => {}
            }
        }
        if info != self.info {
            info.check().map_err(invalid(&path))?;
            write_json(&path, &info)?;
            self.info = info;
        }
        Ok(())
    }

    /// Open the dataset at `root`.
    pub fn open(root: &Path) -> Result<Dataset, DatasetError> {
        let path = root.join("dataset.json");
        let info: DatasetInfo = read_json(&path)?;
        if info.format != FORMAT || info.version != VERSION {
            return Err(DatasetError::Invalid {
                path,
                reason: format!(
                    "format {} version {}; this build reads {FORMAT} version {VERSION}",
                    info.format, info.version
                ),
            });
        }
        info.check().map_err(invalid(&path))?;
        Ok(Dataset {
            root: root.to_owned(),
            info,
        })
    }

    /// The dataset folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Folder of pose `pose`.
    pub fn pose_dir(&self, pose: usize) -> PathBuf {
        self.root.join(format!("pose-{pose:03}"))
    }

    /// Stack folder of camera `camera` at pose `pose`.
    pub fn stack_dir(&self, pose: usize, camera: &str) -> PathBuf {
        self.pose_dir(pose).join(camera)
    }

    /// The stack of camera `camera` at pose `pose`, opened as [`StackReader::open`] opens it
    /// and refused, naming its `stack.json` and field, unless it belongs there: the camera
    /// of its folder, with that camera's size and bits and the dataset's sequence (a stack
    /// copied from another camera's folder or another capture is not read).
    pub fn stack(&self, pose: usize, camera: &str) -> Result<StackReader, DatasetError> {
        let dir = self.stack_dir(pose, camera);
        let stack = StackReader::open(&dir)?;
        let refuse = |at: &str, message: String| {
            DatasetError::Check(ValidationError::new(at, message).in_file(dir.join("stack.json")))
        };
        let info = &stack.info;
        let Some(entry) = self.info.cameras.iter().find(|c| c.name == camera) else {
            return Err(refuse(
                "camera",
                format!("{camera:?} is not a camera of the dataset"),
            ));
        };
        if info.camera != camera {
            return Err(refuse(
                "camera",
                format!(
                    "the stack of camera {:?} in the folder of camera {camera:?}",
                    info.camera
                ),
            ));
        }
        if (info.width, info.height, info.bits) != (entry.width, entry.height, entry.bits) {
            return Err(refuse(
                "width",
                format!(
                    "{}×{} px, {} bits; camera {camera:?} of the dataset is {}×{} px, {} bits",
                    info.width, info.height, info.bits, entry.width, entry.height, entry.bits
                ),
            ));
        }
        if info.sequence != self.info.sequence {
            return Err(refuse(
                "sequence",
                "not the sequence of dataset.json (a stack of another capture)".into(),
            ));
        }
        Ok(stack)
    }

    /// The completed pose `pose`, if it is (its `pose.json` checked).
    pub fn pose(&self, pose: usize) -> Result<Option<PoseInfo>, DatasetError> {
        let path = self.pose_dir(pose).join("pose.json");
        if !path.exists() {
            return Ok(None);
        }
        let info: PoseInfo = read_json(&path)?;
        info.check(pose, &self.info).map_err(invalid(&path))?;
        Ok(Some(info))
    }

    /// Indices of the completed poses, ascending; a pose folder beyond
    /// [`limits::MAX_POSES`] is refused.
    pub fn completed(&self) -> Result<Vec<usize>, DatasetError> {
        let mut poses = Vec::new();
        for entry in std::fs::read_dir(&self.root).map_err(io(&self.root))? {
            let entry = entry.map_err(io(&self.root))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let Some(digits) = name.strip_prefix("pose-") else {
                continue;
            };
            if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
                continue;
            }
            let k = digits
                .parse::<usize>()
                .ok()
                .filter(|&k| k < limits::MAX_POSES);
            let Some(k) = k else {
                return Err(DatasetError::Invalid {
                    path: entry.path(),
                    reason: format!("pose {digits}: at most {} poses", limits::MAX_POSES),
                });
            };
            if entry.path().join("pose.json").exists() {
                poses.push(k);
            }
        }
        poses.sort_unstable();
        Ok(poses)
    }

    /// Mark a pose complete: write its `pose.json`.
    pub fn complete(&self, info: &PoseInfo) -> Result<(), DatasetError> {
        write_json(&self.pose_dir(info.pose).join("pose.json"), info)
    }

    /// Write a JSON file `name` into pose `pose`'s folder (atomically).
    pub fn write_pose_file<T: Serialize>(
        &self,
        pose: usize,
        name: &str,
        value: &T,
    ) -> Result<(), DatasetError> {
        let dir = self.pose_dir(pose);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        write_json(&dir.join(name), value)
    }

    /// Read JSON file `name` of pose `pose`, if it exists, checked against the dataset.
    pub fn read_pose_file<T: PoseFile>(
        &self,
        pose: usize,
        name: &str,
    ) -> Result<Option<T>, DatasetError> {
        let path = self.pose_dir(pose).join(name);
        if !path.exists() {
            return Ok(None);
        }
        let value: T = read_json(&path)?;
        value.check(pose, &self.info).map_err(invalid(&path))?;
        Ok(Some(value))
    }

    /// A writer of pose `pose` (its folder is created). A folder that already holds files
    /// is refused: an earlier attempt is moved aside first ([`Dataset::leftover`]), never
    /// overwritten.
    pub fn pose_writer(&self, pose: usize) -> Result<PoseWriter, DatasetError> {
        let dir = self.pose_dir(pose);
        if dir.exists() {
            return Err(DatasetError::Invalid {
                path: dir,
                reason: "the pose folder is not empty: an earlier attempt would be overwritten"
                    .into(),
            });
        }
        let stacks = self
            .info
            .cameras
            .iter()
            .map(|c| {
                let d = dir.join(&c.name);
                std::fs::create_dir_all(&d).map_err(io(&d))?;
                Ok(StackInfo {
                    camera: c.name.clone(),
                    width: c.width,
                    height: c.height,
                    bits: c.bits,
                    sequence: self.info.sequence.clone(),
                    frames: Vec::new(),
                })
            })
            .collect::<Result<Vec<_>, DatasetError>>()?;
        Ok(PoseWriter { pose, dir, stacks })
    }
}

/// Writes one pose's stacks frame by frame.
#[derive(Debug)]
pub struct PoseWriter {
    pose: usize,
    dir: PathBuf,
    stacks: Vec<StackInfo>,
}

impl PoseWriter {
    /// Write one frame atomically as `CAMERA/frame-KKK.png`.
    pub fn write(&mut self, f: &StackFrame) -> Result<(), DatasetError> {
        let stack = self
            .stacks
            .get_mut(f.camera)
            .ok_or_else(|| DatasetError::Invalid {
                path: self.dir.clone(),
                reason: format!("no camera {} in the dataset", f.camera),
            })?;
        let file = format!("frame-{:03}.png", f.index);
        let path = self.dir.join(&stack.camera).join(&file);
        let frame_error = |reason: String| DatasetError::Frame {
            camera: stack.camera.clone(),
            frame: f.index,
            path: path.clone(),
            reason,
        };
        let fr = &f.frame;
        if (fr.width, fr.height) != (stack.width, stack.height) {
            return Err(frame_error(format!(
                "{}×{} frame in a {}×{} stack",
                fr.width, fr.height, stack.width, stack.height
            )));
        }
        crate::atomic::write_encoded(
            &path,
            |bytes| encode_png(bytes, fr).map_err(|e| frame_error(e.to_string())),
            |e| frame_error(e.to_string()),
        )?;
        stack.frames.push(FrameEntry {
            index: f.index,
            file,
            counter: fr.counter,
            timestamp_ns: fr.timestamp_ns,
            exposure_us: fr.exposure_us,
        });
        Ok(())
    }

    /// Write every camera's `stack.json` (when frames were written) and give the pose's
    /// record, which [`Dataset::complete`] writes once everything of the pose is on disk.
    pub fn finish(self, timeline: &Timeline) -> Result<PoseInfo, DatasetError> {
        for s in self.stacks.iter().filter(|s| !s.frames.is_empty()) {
            write_json(&self.dir.join(&s.camera).join("stack.json"), s)?;
        }
        let ms = |d: std::time::Duration| 1e3 * d.as_secs_f64();
        let info = PoseInfo {
            pose: self.pose,
            cameras: self.stacks.iter().map(|s| s.camera.clone()).collect(),
            seconds: timeline.total.as_secs_f64(),
            dropped: timeline.dropped,
            timeline: timeline
                .frames
                .iter()
                .map(|t| {
                    [
                        ms(t.shown),
                        ms(t.triggered),
                        ms(t.collected),
                        f64::from(t.retries),
                    ]
                })
                .collect(),
        };
        Ok(info)
    }
}

/// Encode `f` as PNG (fast compression: frames are large and many).
fn encode_png(out: &mut impl std::io::Write, f: &CameraFrame) -> image::ImageResult<()> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::{ExtendedColorType, ImageEncoder};
    let enc = PngEncoder::new_with_quality(out, CompressionType::Fast, FilterType::Sub);
    match &f.pixels {
        Pixels::Gray8(p) => enc.write_image(p, f.width, f.height, ExtendedColorType::L8),
        Pixels::Gray16(p) => {
            let samples: Vec<u8> = p.iter().flat_map(|v| v.to_be_bytes()).collect();
            enc.write_image(&samples, f.width, f.height, ExtendedColorType::L16)
        }
    }
}

/// A stack folder opened for reading (`stack.json` checked against its sequence).
#[derive(Clone, Debug)]
pub struct StackReader {
    dir: PathBuf,
    /// Its description.
    pub info: StackInfo,
}

impl StackReader {
    /// Open the stack in `dir`; a frame list that does not cover the sequence in order is
    /// an error naming the camera and the first missing frame.
    pub fn open(dir: &Path) -> Result<StackReader, DatasetError> {
        StackReader::new(dir, read_json(&dir.join("stack.json"))?)
    }

    /// The stack in `dir` described by `info` (its `stack.json`), checked as [`Self::open`]
    /// checks it.
    pub fn new(dir: &Path, info: StackInfo) -> Result<StackReader, DatasetError> {
        info.check().map_err(invalid(&dir.join("stack.json")))?;
        let n = info.sequence.frame_count();
        for k in 0..n {
            match info.frames.get(k) {
                Some(f) if f.index == k => {}
                _ => {
                    return Err(DatasetError::Frame {
                        camera: info.camera.clone(),
                        frame: k,
                        path: dir.join(format!("frame-{k:03}.png")),
                        reason: format!(
                            "missing from stack.json ({} frames listed, the sequence has {n})",
                            info.frames.len()
                        ),
                    })
                }
            }
        }
        if info.frames.len() > n {
            return Err(DatasetError::Invalid {
                path: dir.join("stack.json"),
                reason: format!("{} frames for a sequence of {n}", info.frames.len()),
            });
        }
        Ok(StackReader {
            dir: dir.to_owned(),
            info,
        })
    }

    /// Frame k as 16-bit samples (8-bit files widen); any size or depth other than the
    /// stack's, an unreadable file, or a symbolic link out of the stack folder is an error
    /// naming the camera and frame.
    pub fn frame(&self, k: usize) -> Result<Vec<u16>, DatasetError> {
        let entry = &self.info.frames[k];
        let path = self.dir.join(&entry.file);
        let err = |reason: String| DatasetError::Frame {
            camera: self.info.camera.clone(),
            frame: k,
            path: path.clone(),
            reason,
        };
        crate::paths::inside(&self.dir, &entry.file).map_err(|m| err(m.0))?;
        let reader = image::ImageReader::open(&path).map_err(|e| err(e.to_string()))?;
        let img = crate::images::decode(reader).map_err(|e| err(e.to_string()))?;
        if (img.width(), img.height()) != (self.info.width, self.info.height) {
            return Err(err(format!(
                "{}×{} in a {}×{} stack",
                img.width(),
                img.height(),
                self.info.width,
                self.info.height
            )));
        }
        match img {
            image::DynamicImage::ImageLuma8(i) if self.info.bits <= 8 => {
                Ok(i.into_raw().into_iter().map(u16::from).collect())
            }
            image::DynamicImage::ImageLuma16(i) if self.info.bits > 8 => Ok(i.into_raw()),
            other => Err(err(format!(
                "{:?} pixels in a {}-bit grey stack",
                other.color(),
                self.info.bits
            ))),
        }
    }

    /// The stack folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Full scale of the samples (2^bits − 1).
    pub fn full_scale(&self) -> f32 {
        ((1u32 << self.info.bits) - 1) as f32
    }
}

/// One camera's frame k of a pose.
#[derive(Clone, Debug)]
pub struct StackFrame {
    /// Camera index.
    pub camera: usize,
    /// Frame index k in the sequence.
    pub index: usize,
    /// The frame (averaged over the repeats).
    pub frame: CameraFrame,
}

/// When frame k's steps happened, from the start of the pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameTiming {
    /// Frame index k.
    pub index: usize,
    /// Every projector presented pattern k.
    pub shown: Duration,
    /// The (first) trigger.
    pub triggered: Duration,
    /// Every camera's frame k was in.
    pub collected: Duration,
    /// Triggers repeated for this frame.
    pub retries: u32,
}

/// The measured timeline of one pose.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Timeline {
    /// Per frame, in order.
    pub frames: Vec<FrameTiming>,
    /// Whole pose.
    pub total: Duration,
    /// Frames lost on the way (counter gaps).
    pub dropped: u64,
}

impl Timeline {
    /// Frames per second through the engine (sequence frames × cameras / total time).
    pub fn frames_per_second(&self, cameras: usize) -> f64 {
        (self.frames.len() * cameras) as f64 / self.total.as_secs_f64().max(1e-9)
    }

    /// A one-line summary.
    pub fn summary(&self, cameras: usize) -> String {
        let n = self.frames.len().max(1) as f64;
        let mean = |f: fn(&FrameTiming, Duration) -> Duration| {
            let mut prev = Duration::ZERO;
            let mut sum = 0.0;
            for t in &self.frames {
                sum += f(t, prev).as_secs_f64();
                prev = t.collected;
            }
            1e3 * sum / n
        };
        let show = mean(|t, prev| t.shown.saturating_sub(prev));
        let expose = mean(|t, _| t.collected.saturating_sub(t.triggered));
        let retries: u32 = self.frames.iter().map(|t| t.retries).sum();
        format!(
            "{} frames × {cameras} cameras in {:.2} s ({:.1} frames/s): show {show:.1} ms, \
             trigger → all frames {expose:.1} ms per frame; {retries} retries, {} dropped",
            self.frames.len(),
            self.total.as_secs_f64(),
            self.frames_per_second(cameras),
            self.dropped
        )
    }
}

/// `captured.json` of a pose: written as soon as its capture ended (the pose record), before
/// it is processed; `pose.json` follows when everything of the pose is on disk.
const CAPTURED: &str = "captured.json";

/// What an interrupted run left of a pose that is not complete.
#[derive(Clone, Debug, PartialEq)]
pub enum Leftover {
    /// Nothing: the pose was never started.
    Nothing,
    /// Captured and processed (`views.json` written), only not marked complete: complete it.
    Processed(PoseInfo),
    /// Every camera's stack is on disk and the capture ended: process it, don't recapture.
    Stacks(PoseInfo),
    /// Captured (or partly), but its frames were in memory only or are incomplete on disk:
    /// the pose must be captured again. Whatever was on disk was moved to `kept`.
    Unsaved {
        /// Where the pose's files went (`pose-KKK.interrupted-N`), if it had any.
        kept: Option<PathBuf>,
    },
}

impl Dataset {
    /// Write-ahead: pose `info.pose` was captured (its record, before processing).
    pub fn mark_captured(&self, info: &PoseInfo) -> Result<(), DatasetError> {
        self.write_pose_file(info.pose, CAPTURED, info)
    }

    /// What is left of the incomplete pose `pose`. Partial or unsaved poses are moved aside
    /// whole to `pose-KKK.interrupted-N` (never overwritten, never deleted), so the pose can
    /// be captured again into an empty folder.
    pub fn leftover(&self, pose: usize) -> Result<Leftover, DatasetError> {
        let dir = self.pose_dir(pose);
        if !dir.exists() {
            return Ok(Leftover::Nothing);
        }
        let captured: Option<PoseInfo> = self.read_pose_file(pose, CAPTURED)?;
        let stacks_whole = self
            .info
            .cameras
            .iter()
            .all(|c| self.stack_dir(pose, &c.name).join("stack.json").exists());
        match (captured, stacks_whole) {
            (Some(info), _) if dir.join("views.json").exists() => {
                return Ok(Leftover::Processed(info))
            }
            (Some(info), true) => return Ok(Leftover::Stacks(info)),
            _ => {}
        }
        let empty = std::fs::read_dir(&dir).map_err(io(&dir))?.next().is_none();
        if empty {
            std::fs::remove_dir(&dir).map_err(io(&dir))?;
            return Ok(Leftover::Unsaved { kept: None });
        }
        let kept = (1..)
            .map(|n| dir.with_file_name(format!("pose-{pose:03}.interrupted-{n}")))
            .find(|p| !p.exists())
            .expect("a free name");
        std::fs::rename(&dir, &kept).map_err(io(&dir))?;
        Ok(Leftover::Unsaved { kept: Some(kept) })
    }

    /// Set aside the captured pose `pose` whose stacks failed the stack check: `refused`
    /// (the verdicts) is written into its folder as `refused.json`, and the folder moved
    /// whole to `pose-KKK.refused-N` (kept, never overwritten), so the pose can be captured
    /// again into an empty folder. Gives where it went.
    pub fn refuse<T: Serialize>(&self, pose: usize, refused: &T) -> Result<PathBuf, DatasetError> {
        let dir = self.pose_dir(pose);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        self.write_pose_file(pose, "refused.json", refused)?;
        let kept = (1..)
            .map(|n| dir.with_file_name(format!("pose-{pose:03}.refused-{n}")))
            .find(|p| !p.exists())
            .expect("a free name");
        std::fs::rename(&dir, &kept).map_err(io(&dir))?;
        Ok(kept)
    }

    /// Remove temporary files a killed writer left (`.NAME.tmpPID` of another process) in
    /// the pose folders; they never held a finished file. Gives how many were removed.
    pub fn remove_stale_temporaries(&self) -> Result<usize, DatasetError> {
        let own = format!(".tmp{}", std::process::id());
        let mut removed = 0;
        let mut dirs = vec![self.root.clone()];
        while let Some(dir) = dirs.pop() {
            for entry in std::fs::read_dir(&dir).map_err(io(&dir))? {
                let path = entry.map_err(io(&dir))?.path();
                let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
                let name = name.unwrap_or_default();
                if path.is_dir() {
                    dirs.push(path);
                } else if name.starts_with('.') && name.contains(".tmp") && !name.ends_with(&own) {
                    std::fs::remove_file(&path).map_err(io(&path))?;
                    removed += 1;
                }
            }
        }
        Ok(removed)
    }
}
