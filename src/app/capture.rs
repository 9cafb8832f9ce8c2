//! `hexcal capture`: a rig's poses into a dataset folder, resumable.
//!
//! Takes a rig file and a dataset folder; gives the folder with every captured pose's stacks
//! (docs/dataset.md) and a summary of what was captured now and what was already there.

use super::AppError;
use crate::capture::Session;
use crate::dataset::{Dataset, Leftover, Timeline};
use crate::lock::FolderLock;
use crate::rig::file::RigFile;
use crate::rig::script::PoseExposures;
use crate::rig::OpenedRig;
use std::path::{Path, PathBuf};

/// A rig file read once for a job: where it is, its text (copied into the dataset as read)
/// and what it says.
#[derive(Clone, Debug)]
pub struct LoadedRig {
    /// The rig file's path.
    pub path: PathBuf,
    /// Its text.
    pub text: String,
    /// What it says.
    pub file: RigFile,
}

impl LoadedRig {
    /// Read and check the rig file at `path`.
    pub fn load(path: &Path) -> Result<LoadedRig, AppError> {
        let (file, text) = RigFile::load_with_text(path)?;
        Ok(LoadedRig {
            path: path.to_path_buf(),
            text,
            file,
        })
    }
}

/// A rig file opened for a dataset: the file, its devices and the dataset folder (created,
/// or resumed when it is there) with a copy of the rig file.
pub struct Prepared {
    /// The rig file.
    pub rig: RigFile,
    /// Its devices.
    pub opened: OpenedRig,
    /// The dataset.
    pub data: Dataset,
    /// The dataset folder's lock, held while this is alive.
    pub lock: FolderLock,
}

/// Lock the dataset folder `out` (one writer per folder), open the devices of `rig` and
/// create or resume the dataset for it; the rig file is copied into the folder once, and a
/// board file as `board.toml`.
pub fn prepare(rig: &LoadedRig, out: &Path) -> Result<Prepared, AppError> {
    let lock = FolderLock::acquire(out)?;
    let opened = crate::rig::open(&rig.file)?;
    let mut info = rig.file.dataset_info(&opened.sequence);
    // A board file is copied into the dataset: dataset.json names boards inside its folder.
    let board_file = crate::board::Board::builtin(&info.board).is_none();
    if board_file {
        info.board = super::calibrate::BOARD_FILE.into();
    }
    let data = Dataset::create_or_resume(out, info)?;
    if board_file {
        super::calibrate::board_in_folder(&opened.board, out)?;
    }
    let rig_copy = out.join("rig.toml");
    if !rig_copy.exists() {
        crate::atomic::write(&rig_copy, rig.text.as_bytes()).map_err(AppError::io(&rig_copy))?;
    }
    Ok(Prepared {
        rig: rig.file.clone(),
        opened,
        data,
        lock,
    })
}

/// Puts the board at pose k before it is captured: the simulated world's pose (given when
/// the rig is simulated), or the operator's; `Ok(false)` stops the capture.
pub type PlaceBoard<'a> =
    dyn FnMut(usize, Option<&crate::rig::sim::SimWorld>) -> Result<bool, AppError> + 'a;

/// What [`capture_dataset`] is asked for.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CaptureOptions {
    /// Board poses to capture.
    pub poses: usize,
    /// The poses captured with their own exposure or gain (a capture script's).
    pub exposures: PoseExposures,
}

/// What [`capture_dataset`] tells as it goes.
#[derive(Clone, Debug, PartialEq)]
pub enum Note {
    /// A line for the operator.
    Line(String),
    /// Pose `pose` is captured and stored; `line` says how it went.
    Captured {
        /// Pose index.
        pose: usize,
        /// Its summary.
        line: String,
    },
}

impl std::fmt::Display for Note {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Note::Line(line) | Note::Captured { line, .. } => f.write_str(line),
        }
    }
}

/// What [`capture_dataset`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CaptureSummary {
    /// Poses captured now.
    pub captured: Vec<usize>,
    /// Poses already complete in the dataset (skipped).
    pub skipped: Vec<usize>,
    /// Per captured pose, its timeline.
    pub timelines: Vec<Timeline>,
}

/// Capture `options.poses` board poses of `rig` into the dataset folder
/// `out` (created, or resumed: complete poses are skipped), those in `options.exposures`
/// with their own exposure and gain. `place(k)` puts the board at pose k (the simulated
/// world's pose, the operator's or a script's) and may refuse to go on (`Ok(false)` stops
/// the capture, keeping every complete pose); `log` hears what happens, a
/// [`Note::Captured`] per pose.
pub fn capture_dataset(
    rig: &LoadedRig,
    out: &Path,
    options: &CaptureOptions,
    place: &mut PlaceBoard,
    log: &mut dyn FnMut(Note),
) -> Result<CaptureSummary, AppError> {
    let (poses, exposures) = (options.poses, &options.exposures);
    let rig_path = rig.path.clone();
    let Prepared {
        rig,
        opened,
        mut data,
        lock: _lock,
    } = prepare(rig, out)?;
    let pause = std::time::Duration::from_secs_f64(rig.timing.pose_pause_s);
    data.remove_stale_temporaries()?;
    finish_leftovers(&data, poses, log)?;
    let done = data.completed()?;
    let world = opened.world.clone();
    let cameras = opened.devices.cameras.len();
    let mut session = Session::start(opened.devices, &opened.sequence)?;
    data.record_formats(&session.pixel_formats())?;
    let mut summary = CaptureSummary::default();
    for k in 0..poses {
        if done.contains(&k) {
            summary.skipped.push(k);
            continue;
        }
        if !place(k, world.as_deref())? {
            break;
        }
        // The board settles after it is placed.
        std::thread::sleep(pause);
        if summary.captured.is_empty() {
            if let Some(t) =
                super::check::at_start((&rig, &rig_path), &mut session, data.root(), k)?
            {
                log(Note::Line(format!(
                    "self-tests before pose {k}:\n{}",
                    t.to_string().trim_end()
                )));
                for w in t.warnings() {
                    log(Note::Line(format!("warning: {w}")));
                }
            }
        }
        let mut writer = data.pose_writer(k)?;
        let timeline = exposed(&mut session, exposures.get(&k), |s| {
            Ok(s.capture_pose(k, &mut |f| Ok(writer.write(&f)?))?)
        })?;
        let info = writer.finish(&timeline)?;
        data.mark_captured(&info)?;
        data.complete(&info)?;
        log(Note::Captured {
            pose: k,
            line: format!("pose {k}: {}", timeline.summary(cameras)),
        });
        summary.captured.push(k);
        summary.timelines.push(timeline);
    }
    session.finish()?;
    Ok(summary)
}

/// Run `capture` with every camera set to its `settings` (`None`: the cameras' own), and
/// set them back after, whatever the capture gave.
pub fn exposed<T>(
    session: &mut Session,
    settings: Option<&Vec<Option<(f64, f64)>>>,
    capture: impl FnOnce(&mut Session) -> Result<T, AppError>,
) -> Result<T, AppError> {
    session.set_exposures(settings.map_or(&[], Vec::as_slice))?;
    let captured = capture(session);
    let restored = session.set_exposures(&[]);
    let value = captured?;
    restored?;
    Ok(value)
}

/// The poses an interrupted capture left incomplete: complete the ones whose stacks are
/// whole on disk; move aside (never overwrite) the others, which are captured again.
fn finish_leftovers(
    data: &Dataset,
    poses: usize,
    log: &mut dyn FnMut(Note),
) -> Result<(), AppError> {
    let done = data.completed()?;
    for k in (0..poses).filter(|k| !done.contains(k)) {
        match data.leftover(k)? {
            Leftover::Nothing => {}
            Leftover::Processed(info) | Leftover::Stacks(info) => {
                data.complete(&info)?;
                log(Note::Line(format!(
                    "pose {k}: its stacks were whole on disk: kept"
                )));
            }
            Leftover::Unsaved { kept } => log(Note::Line(match kept {
                Some(p) => format!(
                    "pose {k} was not saved: place the board again (its partial files are \
                     kept in {})",
                    p.display()
                ),
                None => format!("pose {k} was not saved: place the board again"),
            })),
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{capture_dataset, CaptureOptions, LoadedRig};
    use crate::dataset::Dataset;
    use crate::rig::fixture::{SimDevice, SimRig};

    /// Two simulated 64×48 cameras, one Bayer and one MJPEG, and no projector.
    fn formats_rig() -> SimRig {
        let camera = |name, eye| {
            SimDevice::new(name, (64, 48), [300.0, 300.0, 31.5, 23.5])
                .at(eye)
                .with("exposure_ms = 10.0")
        };
        SimRig::new("formats")
            .table("[timing]\nframe_period_ms = 20.0")
            .table("[poses]\ncount = 3\nyaw_deg = 10.0\ntilt_deg = 10.0\nshift_mm = 10.0\nseed = 1")
            .camera(camera("colour", [0.0, 0.0, 1500.0]).with("format = \"BayerGB\""))
            .camera(
                camera("webcam", [100.0, 0.0, 1500.0])
                    .with("format = \"MJPG\"")
                    .with("jpeg_quality = 90"),
            )
    }

    /// Capture `poses` poses of `rig` into `out`; the error's text if it fails.
    fn capture(rig: &std::path::Path, out: &std::path::Path, poses: usize) -> Result<(), String> {
        let options = CaptureOptions {
            poses,
            ..CaptureOptions::default()
        };
        let mut place = |k: usize, world: Option<&crate::rig::sim::SimWorld>| {
            world.expect("a simulated rig").place(k);
            Ok(true)
        };
        LoadedRig::load(rig)
            .and_then(|rig| capture_dataset(&rig, out, &options, &mut place, &mut |_| {}))
            .map(|_| ())
            .map_err(|e| e.to_string())
    }

    #[test]
    fn the_dataset_records_each_cameras_pixel_format_and_a_resume_must_match_it() {
        let dir = std::env::temp_dir().join(format!("hexcal-formats-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let rig = dir.join("rig.toml");
        std::fs::write(&rig, formats_rig().toml()).unwrap();
        let out = dir.join("data");
        capture(&rig, &out, 1).unwrap();
        let data = Dataset::open(&out).unwrap();
        let cameras = &data.info.cameras;
        let formats: Vec<Option<String>> = cameras.iter().map(|c| c.pixel_format.clone()).collect();
        let bits = cameras[0].bits;
        assert_eq!(
            formats,
            [
                Some(format!("BayerGB{bits}")),
                Some("MJPG (quality 90)".into())
            ]
        );
        // Resumed with the same formats: pose 1 joins pose 0.
        capture(&rig, &out, 2).unwrap();
        assert_eq!(Dataset::open(&out).unwrap().completed().unwrap(), [0, 1]);
        // The webcam now delivers another quality: refused by name, nothing written.
        std::fs::write(
            &rig,
            formats_rig()
                .edit("webcam", |c| c.with("jpeg_quality = 80"))
                .toml(),
        )
        .unwrap();
        let err = capture(&rig, &out, 3).unwrap_err();
        assert!(
            err.contains("dataset.json")
                && err.contains(
                    "camera webcam delivered MJPG (quality 90) here and now delivers MJPG \
                     (quality 80)"
                ),
            "{err}"
        );
        assert_eq!(Dataset::open(&out).unwrap().completed().unwrap(), [0, 1]);
        // A dataset written before formats were recorded resumes and records them.
        let path = out.join("dataset.json");
        let mut json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        for c in json["cameras"].as_array_mut().unwrap() {
            c.as_object_mut().unwrap().remove("pixel_format");
        }
        std::fs::write(&path, json.to_string()).unwrap();
        capture(&rig, &out, 3).unwrap();
        let data = Dataset::open(&out).unwrap();
        assert_eq!(
            data.info.cameras[1].pixel_format.as_deref(),
            Some("MJPG (quality 80)")
        );
        assert_eq!(data.completed().unwrap(), [0, 1, 2]);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
