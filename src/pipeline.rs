//! One-button calibration (`hexcal run`, `hexcal calibrate DATASET`): the stages streamed in
//! one process.
//!
//! Takes a rig file (or a dataset on disk); gives a calibration, its verification on
//! held-out poses and the report files. While pose k+1 is captured, pose k's stacks finish
//! decoding and go through detection, grid building and the projector fits, each camera in
//! its own thread fed frame by frame over a bounded crossbeam channel (stacks are never held
//! whole). Every pose's views land in the dataset (`pose-KKK/views.json`, then `pose.json`)
//! before the pose counts as done, so an interrupted run keeps every finished pose and a
//! resumed run or `hexcal calibrate DATASET` completes it.

use crate::board::Board;
use crate::calib::bundle::{Device, DeviceKind};
use crate::calib::pipeline::{calibrate, CalibrateOptions, Calibration, DeviceInfo};
use crate::calib::verify::{verify, PairCheck};
use crate::correspond::{camera_view, CameraView, FitParams, ProjectorMap};
use crate::dataset::{CameraEntry, Dataset, DatasetInfo, PoseInfo, ProjectorEntry};
use crate::detect::{detect, DetectParams};
use crate::grid::{build, GridParams};
use crate::images::{CameraFrame, Pixels};
use crossbeam_channel::{bounded, unbounded, Receiver, Sender};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::thread::JoinHandle;
use {
    crate::capture::{open, Session},
    crate::dataset::Timeline,
};
use {
    crate::pattern::Sequence,
    crate::phase::{DecodedStack, Decoder, FrameRef},
};

/// What one camera's stack of one pose gave.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StackResult {
    /// Camera name.
    pub camera: String,
    /// Circles detected.
    pub circles: usize,
    /// Labelled board points.
    pub points: usize,
    /// Whether the labels are in the board's own frame (the centre cell was seen).
    pub anchored: bool,
    /// Per projector (sequence order): points with a projector pixel.
    pub projector_points: Vec<usize>,
    /// Why the stack gave nothing, if it did not.
    pub error: Option<String>,
    /// The labelled view (none when the board was not found).
    pub view: Option<CameraView>,
}

/// `pose-KKK/views.json`: every camera's result for one pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseViews {
    /// Pose index.
    pub pose: usize,
    /// Per camera, in rig order.
    pub stacks: Vec<StackResult>,
}

/// Detection, grid and projector fits on one camera's decoded stack (circles on the decoded
/// ambient image: evenly lit and averaged over the stack). `camera` is the camera's device
/// index, `first_projector` the device index of projector 0.
pub fn process_decoded(
    decoded: &DecodedStack,
    board: &Board,
    camera: usize,
    pose: usize,
    first_projector: usize,
) -> StackResult {
    let image = &decoded.ambient;
    let circles = detect(image, &DetectParams::default());
    let grid = build(image, &circles, board, &GridParams::default());
    let maps: Vec<ProjectorMap> = decoded
        .projectors
        .iter()
        .enumerate()
        .map(|(p, m)| ProjectorMap::from_decoded(first_projector + p, m))
        .collect();
    let view = camera_view(camera, pose, &grid, &circles, &maps, &FitParams::default());
    let projector_points = (0..decoded.projectors.len())
        .map(|p| {
            view.as_ref().map_or(0, |v| {
                v.points
                    .iter()
                    .filter(|pt| {
                        pt.projectors
                            .iter()
                            .any(|q| q.projector == first_projector + p)
                    })
                    .count()
            })
        })
        .collect();
    StackResult {
        camera: decoded.camera.clone(),
        circles: circles.len(),
        points: grid.points.len(),
        anchored: grid.anchored,
        projector_points,
        error: None,
        view,
    }
}

/// A decoder of 8- or 16-bit frames, chosen by the first frame.
enum AnyDecoder {
    Eight(Decoder<u8>),
    Sixteen(Decoder<u16>),
}

/// One camera's stack of one pose to decode and process.
struct StackJob {
    sequence: Sequence,
    entry: CameraEntry,
    board: Board,
    camera: usize,
    pose: usize,
    first_projector: usize,
    /// Taken while finishing (one stack at a time).
    finishing: std::sync::Arc<std::sync::Mutex<()>>,
}

/// Decode one camera's stack as its frames arrive on `frames`, then process it.
fn stack_worker(frames: Receiver<CameraFrame>, job: StackJob) -> StackResult {
    let StackJob {
        sequence,
        entry,
        board,
        camera,
        pose,
        first_projector,
        finishing,
    } = job;
    let failed = |error: String| StackResult {
        camera: entry.name.clone(),
        circles: 0,
        points: 0,
        anchored: false,
        projector_points: vec![0; sequence.projectors().len()],
        error: Some(error),
        view: None,
    };
    let full_scale = ((1u32 << entry.bits.min(16)) - 1) as f32;
    let mut decoder = None;
    for k in 0..sequence.frame_count() {
        let Ok(f) = frames.recv() else {
            return failed(format!("stack ended after {k} frames"));
        };
        let dec = decoder.get_or_insert_with(|| match f.pixels {
            Pixels::Gray8(_) => Decoder::new(&sequence, &entry.name, f.width, f.height, full_scale)
                .map(AnyDecoder::Eight),
            Pixels::Gray16(_) => {
                Decoder::new(&sequence, &entry.name, f.width, f.height, full_scale)
                    .map(AnyDecoder::Sixteen)
            }
        });
        let pushed = match (dec, &f.pixels) {
            (Ok(AnyDecoder::Eight(d)), Pixels::Gray8(p)) => d.push_frame(
                k,
                FrameRef {
                    width: f.width,
                    height: f.height,
                    pixels: p,
                },
            ),
            (Ok(AnyDecoder::Sixteen(d)), Pixels::Gray16(p)) => d.push_frame(
                k,
                FrameRef {
                    width: f.width,
                    height: f.height,
                    pixels: p,
                },
            ),
            (Err(e), _) => return failed(e.to_string()),
            _ => return failed(format!("frame {k}: sample depth changed within the stack")),
        };
        if let Err(e) = pushed {
            return failed(e.to_string());
        }
    }
    // One stack at a time turns its phases into maps and detects (bounds the memory of the
    // maps while the next pose's decoders fill up).
    let _turn = finishing.lock().unwrap_or_else(|e| e.into_inner());
    let decoded = match decoder {
        Some(Ok(AnyDecoder::Eight(d))) => d.finish(),
        Some(Ok(AnyDecoder::Sixteen(d))) => d.finish(),
        Some(Err(e)) => return failed(e.to_string()),
        None => return failed("empty sequence".into()),
    };
    match decoded {
        Ok(d) => process_decoded(&d, &board, camera, pose, first_projector),
        Err(e) => failed(e.to_string()),
    }
}

/// Progress of a run, for people (`Display`) and scripts (JSON lines).
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    /// Place the board for this pose (the capture starts next).
    PoseStarted {
        /// Pose index.
        pose: usize,
        /// Poses in all.
        of: usize,
    },
    /// Frames of a pose captured so far.
    Frames {
        /// Pose index.
        pose: usize,
        /// Frames done.
        done: usize,
        /// Frames in the sequence.
        of: usize,
    },
    /// A pose's capture finished (its processing goes on in the background).
    PoseCaptured {
        /// Pose index.
        pose: usize,
        /// Capture time (s).
        seconds: f64,
        /// Camera frames per second.
        frames_per_second: f64,
    },
    /// A pose was processed: what each device got, coverage so far.
    PoseProcessed {
        /// Pose index.
        pose: usize,
        /// Per device (cameras, then projectors): points this pose.
        points: Vec<(String, usize)>,
        /// Devices seen in fewer than 3 poses so far (they still need views).
        need_views: Vec<String>,
        /// Held out for verification.
        held_out: bool,
    },
    /// A pose gave nothing usable; it is skipped.
    PoseSkipped {
        /// Pose index.
        pose: usize,
        /// Why.
        reason: String,
    },
    /// One camera's stack failed in a pose (the pose goes on without it).
    StackFailed {
        /// Pose index.
        pose: usize,
        /// Camera.
        camera: String,
        /// Why.
        reason: String,
    },
    /// Poses already complete in the dataset, reused.
    Resumed {
        /// Their indices.
        poses: Vec<usize>,
    },
    /// Bundle adjustment started.
    Calibrating {
        /// Views used.
        views: usize,
    },
    /// Done: the outputs are written.
    Finished {
        /// Posterior σ of the adjustment (px).
        sigma: f64,
        /// Held-out length error RMS over all pairs (mm), if verified.
        length_rms: Option<f64>,
        /// The output folder.
        out: String,
    },
}

impl std::fmt::Display for Event {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Event::PoseStarted { pose, of } => write!(f, "pose {pose} of {of}: capturing"),
            Event::Frames { pose, done, of } => write!(f, "pose {pose}: frame {done}/{of}"),
            Event::PoseCaptured {
                pose,
                seconds,
                frames_per_second,
            } => write!(
                f,
                "pose {pose}: captured in {seconds:.1} s ({frames_per_second:.0} frames/s); \
                 processing while the next pose is captured"
            ),
            Event::PoseProcessed {
                pose,
                points,
                need_views,
                held_out,
            } => {
                let seen: Vec<String> = points
                    .iter()
                    .filter(|(_, n)| *n > 0)
                    .map(|(d, n)| format!("{d} {n}"))
                    .collect();
                write!(
                    f,
                    "pose {pose}{}: points {}",
                    if *held_out { " (held out)" } else { "" },
                    if seen.is_empty() {
                        "none".to_string()
                    } else {
                        seen.join(", ")
                    }
                )?;
                if !need_views.is_empty() {
                    write!(f, "; still need views: {}", need_views.join(", "))?;
                }
                Ok(())
            }
            Event::PoseSkipped { pose, reason } => write!(f, "pose {pose} skipped: {reason}"),
            Event::StackFailed {
                pose,
                camera,
                reason,
            } => write!(f, "pose {pose}, camera {camera}: {reason}"),
            Event::Resumed { poses } => write!(f, "resuming: poses {poses:?} already complete"),
            Event::Calibrating { views } => write!(f, "calibrating from {views} camera views"),
            Event::Finished {
                sigma,
                length_rms,
                out,
            } => {
                write!(f, "done: σ {sigma:.4} px")?;
                if let Some(l) = length_rms {
                    write!(f, ", held-out length error RMS {l:.4} mm")?;
                }
                write!(f, "; outputs in {out}")
            }
        }
    }
}

/// Settings of [`run`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RunOptions {
    /// Board poses to capture (default: the rig file's `[poses] count`).
    pub poses: Option<usize>,
    /// Poses held out for verification (the last ones).
    pub held_out: usize,
    /// Write every frame to the dataset as well (PNG; gigabytes per pose).
    pub keep_stacks: bool,
}

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
    // T_ref_rig of the reference: the device whose calibrated pose is the identity.
    let Some(reference) = cal
        .devices
        .iter()
        .find(|d| d.pose.translation.vector.norm() == 0.0 && d.pose.rotation.angle() == 0.0)
        .and_then(|d| truth(&d.name))
    else {
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

/// The result of a run or of calibrating a dataset.
#[derive(Debug)]
pub struct Outcome {
    /// The devices (cameras, then projectors).
    pub devices: Vec<DeviceInfo>,
    /// The calibration.
    pub calibration: Calibration,
    /// Checks on the held-out poses.
    pub verification: Vec<PairCheck>,
    /// Files written.
    pub files: Vec<std::path::PathBuf>,
    /// Per captured pose, its capture timeline (empty for poses read from disk).
    pub timelines: Vec<(usize, Timeline)>,
    /// Warnings for the report (skipped poses, failed stacks).
    pub warnings: Vec<String>,
    /// Against the ground truth, when the rig is simulated.
    pub truth: Vec<TruthCheck>,
    /// How well the cameras agree on each projector's pixels.
    pub agreement: Vec<crate::correspond::Agreement>,
}

fn devices_of(info: &DatasetInfo) -> Vec<DeviceInfo> {
    info.cameras
        .iter()
        .map(|c| DeviceInfo {
            name: c.name.clone(),
            kind: DeviceKind::Camera,
            width: c.width,
            height: c.height,
        })
        .chain(info.projectors.iter().map(|p| DeviceInfo {
            name: p.name.clone(),
            kind: DeviceKind::Projector,
            width: p.width,
            height: p.height,
        }))
        .collect()
}

/// Per-device coverage as poses come in.
struct Coverage {
    names: Vec<String>,
    poses_seen: Vec<usize>,
    cameras: usize,
}

impl Coverage {
    fn add(&mut self, views: &PoseViews, held_out: bool) -> Event {
        let mut points = vec![0usize; self.names.len()];
        for (c, s) in views.stacks.iter().enumerate() {
            points[c] = s.points;
            for (p, n) in s.projector_points.iter().enumerate() {
                points[self.cameras + p] += n;
            }
        }
        if !held_out {
            for (seen, &n) in self.poses_seen.iter_mut().zip(&points) {
                *seen += usize::from(n > 0);
            }
        }
        Event::PoseProcessed {
            pose: views.pose,
            points: self.names.iter().cloned().zip(points).collect(),
            need_views: self
                .names
                .iter()
                .zip(&self.poses_seen)
                .filter(|(_, &n)| n < 3)
                .map(|(d, _)| d.clone())
                .collect(),
            held_out,
        }
    }
}

/// What the background processing of one pose sends back.
struct Processed {
    views: PoseViews,
    info: PoseInfo,
}

/// `hexcal run`: capture every pose of the rig file at `rig_path` into the dataset `out`
/// (resuming one that is there), process each pose while the next is captured, calibrate,
/// verify on the held-out poses and write the outputs to `out/calibration`. `place(k, world)`
/// puts the board at pose k (the simulated world's, or the operator's) and may stop the
/// capture (`Ok(false)`); `events` hears the progress.
pub fn run(
    rig_path: &Path,
    out: &Path,
    options: &RunOptions,
    place: &mut crate::capture::PlaceBoard,
    events: &mut dyn FnMut(&Event),
) -> Result<Outcome, String> {
    let rig = crate::rig::file::RigFile::load(rig_path).map_err(|e| e.to_string())?;
    let base = rig_path.parent().unwrap_or(Path::new("."));
    let opened = open::open(&rig, base)?;
    let info = DatasetInfo {
        format: crate::dataset::FORMAT.into(),
        version: crate::dataset::VERSION,
        rig: rig.name.clone(),
        board: rig.board.clone(),
        sequence: opened.sequence.clone(),
        cameras: rig
            .cameras
            .iter()
            .map(|c| CameraEntry {
                name: c.name.clone(),
                width: c.width,
                height: c.height,
                bits: c.bits,
            })
            .collect(),
        projectors: rig
            .projectors
            .iter()
            .map(|p| ProjectorEntry {
                name: p.name.clone(),
                width: p.width,
                height: p.height,
            })
            .collect(),
    };
    let data = Dataset::create_or_resume(out, info).map_err(|e| e.to_string())?;
    let rig_copy = out.join("rig.toml");
    if !rig_copy.exists() {
        let text = std::fs::read(rig_path).map_err(|e| format!("{}: {e}", rig_path.display()))?;
        crate::atomic::write(&rig_copy, &text)
            .map_err(|e| format!("{}: {e}", rig_copy.display()))?;
    }
    let poses = options
        .poses
        .or(rig.poses.map(|p| p.count))
        .ok_or("say how many poses (the rig file has no [poses] table)")?;
    let held_from = poses.saturating_sub(options.held_out);
    let devices = devices_of(&data.info);
    let cameras = data.info.cameras.len();
    let mut coverage = Coverage {
        names: devices.iter().map(|d| d.name.clone()).collect(),
        poses_seen: vec![0; devices.len()],
        cameras,
    };
    let mut all: Vec<Option<PoseViews>> = vec![None; poses];
    let done = data.completed().map_err(|e| e.to_string())?;
    let mut resumed = Vec::new();
    for &k in done.iter().filter(|&&k| k < poses) {
        if let Some(v) = data
            .read_pose_file::<PoseViews>(k, "views.json")
            .map_err(|e| e.to_string())?
        {
            events(&coverage.add(&v, k >= held_from));
            all[k] = Some(v);
            resumed.push(k);
        }
    }
    if !resumed.is_empty() {
        events(&Event::Resumed { poses: resumed });
    }

    let board = opened.board.clone();
    let sequence = opened.sequence.clone();
    let world = opened.world.clone();
    let mut session = Session::start(
        opened.cameras,
        &opened.configs,
        opened.projectors,
        opened.trigger,
        &opened.sequence,
        opened.timing,
    )
    .map_err(|e| e.to_string())?;
    let frames = sequence.frame_count();
    let (done_tx, done_rx) = unbounded::<Result<Processed, String>>();
    let mut in_flight: Option<JoinHandle<()>> = None;
    let mut timelines = Vec::new();
    let mut warnings = Vec::new();
    let mut handle = |p: Result<Processed, String>,
                      all: &mut Vec<Option<PoseViews>>,
                      warnings: &mut Vec<String>,
                      events: &mut dyn FnMut(&Event)|
     -> Result<(), String> {
        let p = p?;
        for s in &p.views.stacks {
            if let Some(reason) = &s.error {
                warnings.push(format!(
                    "pose {}, camera {}: {reason}",
                    p.views.pose, s.camera
                ));
                events(&Event::StackFailed {
                    pose: p.views.pose,
                    camera: s.camera.clone(),
                    reason: reason.clone(),
                });
            }
        }
        let k = p.views.pose;
        events(&coverage.add(&p.views, k >= held_from));
        if p.views.stacks.iter().all(|s| s.view.is_none()) {
            let reason = "no camera found the board".to_string();
            warnings.push(format!("pose {k}: {reason}"));
            events(&Event::PoseSkipped { pose: k, reason });
        }
        data.write_pose_file(k, "views.json", &p.views)
            .and_then(|()| data.complete(&p.info))
            .map_err(|e| e.to_string())?;
        all[k] = Some(p.views);
        Ok(())
    };
    for k in 0..poses {
        if all[k].is_some() {
            continue;
        }
        events(&Event::PoseStarted { pose: k, of: poses });
        if !place(k, world.as_deref())? {
            break;
        }
        // One decoding thread per camera, fed frame by frame.
        let mut senders: Vec<Sender<CameraFrame>> = Vec::new();
        let mut workers = Vec::new();
        let finishing = std::sync::Arc::new(std::sync::Mutex::new(()));
        for (c, entry) in data.info.cameras.iter().enumerate() {
            let (tx, rx) = bounded(2);
            senders.push(tx);
            let job = StackJob {
                sequence: sequence.clone(),
                entry: entry.clone(),
                board: board.clone(),
                camera: c,
                pose: k,
                first_projector: cameras,
                finishing: std::sync::Arc::clone(&finishing),
            };
            workers.push(
                std::thread::Builder::new()
                    .name(format!("stack {}", entry.name))
                    .spawn(move || stack_worker(rx, job))
                    .map_err(|e| e.to_string())?,
            );
        }
        let mut writer = data.pose_writer(k).map_err(|e| e.to_string())?;
        let mut last = 0;
        let timeline = session
            .capture_pose(k, &mut |f| {
                if options.keep_stacks {
                    writer.write(&f).map_err(|e| e.to_string())?;
                }
                if f.camera == cameras - 1 && (f.index + 1) * 10 / frames > last {
                    last = (f.index + 1) * 10 / frames;
                    events(&Event::Frames {
                        pose: k,
                        done: f.index + 1,
                        of: frames,
                    });
                }
                senders[f.camera]
                    .send(f.frame)
                    .map_err(|_| "its decoding thread ended".to_string())
            })
            .map_err(|e| e.to_string())?;
        drop(senders);
        let info = writer.finish(&timeline).map_err(|e| e.to_string())?;
        events(&Event::PoseCaptured {
            pose: k,
            seconds: timeline.total.as_secs_f64(),
            frames_per_second: timeline.frames_per_second(cameras),
        });
        timelines.push((k, timeline));
        // At most one pose in processing while the next is captured (memory stays bounded).
        if let Some(h) = in_flight.take() {
            h.join().map_err(|_| "a processing thread panicked")?;
        }
        while let Ok(p) = done_rx.try_recv() {
            handle(p, &mut all, &mut warnings, events)?;
        }
        let tx = done_tx.clone();
        in_flight = Some(
            std::thread::Builder::new()
                .name(format!("pose {k}"))
                .spawn(move || {
                    let stacks: Result<Vec<StackResult>, String> = workers
                        .into_iter()
                        .map(|w| w.join().map_err(|_| "a stack thread panicked".to_string()))
                        .collect();
                    let _ = tx.send(stacks.map(|stacks| Processed {
                        views: PoseViews { pose: k, stacks },
                        info,
                    }));
                })
                .map_err(|e| e.to_string())?,
        );
    }
    if let Some(h) = in_flight.take() {
        h.join().map_err(|_| "a processing thread panicked")?;
    }
    drop(done_tx);
    for p in done_rx.iter() {
        handle(p, &mut all, &mut warnings, events)?;
    }
    session.finish().map_err(|e| e.to_string())?;
    let mut outcome = finish(
        Collected {
            board: &board,
            devices: &devices,
            all: &all,
            held_from,
        },
        &out.join("calibration"),
        &CalibrateOptions::default(),
        &warnings,
        events,
    )?;
    outcome.timelines = timelines;
    outcome.warnings = warnings;
    if let Some(w) = &world {
        outcome.truth = check_truth(&outcome.calibration, w);
        let path = out.join("calibration").join("truth.txt");
        crate::atomic::write(&path, format_truth(&outcome.truth).as_bytes())
            .map_err(|e| format!("{}: {e}", path.display()))?;
        outcome.files.push(path);
    }
    Ok(outcome)
}

/// Calibrate from the views of `all` poses (those from `held_from` on are held out and
/// verified), write the outputs to `dir`.
/// Every pose's views, with what they refer to.
struct Collected<'a> {
    board: &'a Board,
    devices: &'a [DeviceInfo],
    /// Per pose (renumbered from 0), its views if it has any.
    all: &'a [Option<PoseViews>],
    /// First held-out pose.
    held_from: usize,
}

fn finish(
    c: Collected,
    dir: &Path,
    options: &CalibrateOptions,
    warnings: &[String],
    events: &mut dyn FnMut(&Event),
) -> Result<Outcome, String> {
    let Collected {
        board,
        devices,
        all,
        held_from,
    } = c;
    let views_of = |range: std::ops::Range<usize>| -> Vec<CameraView> {
        all[range]
            .iter()
            .flatten()
            .flat_map(|p| p.stacks.iter().filter_map(|s| s.view.clone()))
            .collect()
    };
    let used = views_of(0..held_from.min(all.len()));
    let held = views_of(held_from.min(all.len())..all.len());
    events(&Event::Calibrating { views: used.len() });
    let cal = calibrate(board, devices, held_from.min(all.len()), &used, options)
        .map_err(|e| format!("calibration: {e}"))?;
    let verification = verify_held_out(board, &cal, &held, held_from);
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut files = crate::report::write_outputs(&cal, dir).map_err(|e| e.to_string())?;
    let text = crate::report::format_verification(&verification);
    let path = dir.join("verification.txt");
    crate::atomic::write(&path, text.as_bytes()).map_err(|e| format!("{}: {e}", path.display()))?;
    files.push(path);
    let path = dir.join("report.html");
    crate::report::html::write_html(
        &crate::report::html::ReportInput {
            calibration: &cal,
            verification: &verification,
            title: &format!("hexcal calibration: {}", dir.display()),
            warnings: warnings.to_vec(),
        },
        &path,
    )
    .map_err(|e| e.to_string())?;
    files.push(path);
    let length_rms = crate::report::verification_rms(&verification);
    events(&Event::Finished {
        sigma: cal.solution.sigma,
        length_rms,
        out: dir.display().to_string(),
    });
    Ok(Outcome {
        devices: devices.to_vec(),
        calibration: cal,
        verification,
        files,
        timelines: Vec::new(),
        warnings: Vec::new(),
        truth: Vec::new(),
        agreement: crate::correspond::agreement(&used),
    })
}

/// Verify held-out views against the calibrated devices (views re-indexed to the kept
/// devices; poses renumbered from 0).
fn verify_held_out(
    board: &Board,
    cal: &Calibration,
    held: &[CameraView],
    held_from: usize,
) -> Vec<PairCheck> {
    let kept = |d: usize| cal.device_index.iter().position(|&i| i == d);
    let views: Vec<CameraView> = held
        .iter()
        .filter_map(|v| {
            let mut v = v.clone();
            v.camera = kept(v.camera)?;
            v.pose -= held_from;
            for p in &mut v.points {
                p.projectors.retain_mut(|q| match kept(q.projector) {
                    Some(i) => {
                        q.projector = i;
                        true
                    }
                    None => false,
                });
            }
            Some(v)
        })
        .collect();
    let devices: Vec<Device> = cal.devices.clone();
    verify(board, &devices, &views)
}

/// `hexcal calibrate DATASET`: every complete pose's views (from `views.json`, or decoded
/// from its stacks), calibrated with `options` and the last `held_out` poses verified;
/// outputs in `out`.
pub fn calibrate_dataset(
    root: &Path,
    out: &Path,
    held_out: usize,
    options: &CalibrateOptions,
    events: &mut dyn FnMut(&Event),
) -> Result<Outcome, String> {
    let data = Dataset::open(root).map_err(|e| e.to_string())?;
    let board = Board::resolve(&data.info.board).map_err(|e| e.to_string())?;
    let devices = devices_of(&data.info);
    let cameras = data.info.cameras.len();
    let poses = data.completed().map_err(|e| e.to_string())?;
    if poses.is_empty() {
        return Err(format!("{}: no complete pose", root.display()));
    }
    // Renumber the complete poses 0…n−1 in order.
    let mut all = Vec::new();
    let mut warnings = Vec::new();
    for (i, &k) in poses.iter().enumerate() {
        let views = match data
            .read_pose_file::<PoseViews>(k, "views.json")
            .map_err(|e| e.to_string())?
        {
            Some(v) => v,
            None => {
                let stacks = data
                    .info
                    .cameras
                    .iter()
                    .enumerate()
                    .map(|(c, entry)| {
                        let dir = data.stack_dir(k, &entry.name);
                        match crate::phase::files::decode_dir(&dir) {
                            Ok(d) => process_decoded(&d, &board, c, k, cameras),
                            Err(e) => StackResult {
                                camera: entry.name.clone(),
                                circles: 0,
                                points: 0,
                                anchored: false,
                                projector_points: vec![0; data.info.projectors.len()],
                                error: Some(e.to_string()),
                                view: None,
                            },
                        }
                    })
                    .collect();
                PoseViews { pose: k, stacks }
            }
        };
        for s in &views.stacks {
            if let Some(e) = &s.error {
                warnings.push(format!("pose {k}, camera {}: {e}", s.camera));
            }
        }
        let mut views = views;
        views.pose = i;
        for s in &mut views.stacks {
            if let Some(v) = &mut s.view {
                v.pose = i;
            }
        }
        all.push(Some(views));
    }
    let held_from = all.len().saturating_sub(held_out);
    let mut outcome = finish(
        Collected {
            board: &board,
            devices: &devices,
            all: &all,
            held_from,
        },
        out,
        options,
        &warnings,
        events,
    )?;
    outcome.warnings = warnings;
    Ok(outcome)
}
