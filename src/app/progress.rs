//! What the application layer tells its caller: progress events (for people and, as JSON
//! lines, for scripts) and the outcome of a run or a calibration.

use super::truth::TruthCheck;
use crate::calib::solve::Calibration;
use crate::calib::verify::PairCheck;
use crate::dataset::Timeline;
use crate::observations::DeviceInfo;
use serde::Serialize;

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
    /// The capture of a pose starts in this many whole seconds (the wait after the board is
    /// placed: the rig file's `pose_pause_s` or the operator's countdown); told every
    /// second, 0 as the capture starts.
    Countdown {
        /// Pose index.
        pose: usize,
        /// Whole seconds left.
        seconds: u64,
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
    /// A camera's stack had a fault the decoder repaired exactly: the stack is used.
    StackRepaired {
        /// Pose index.
        pose: usize,
        /// Camera.
        camera: String,
        /// What was found, what was done and what to do.
        what: String,
    },
    /// A camera's stack failed the stack check: the pose is captured again.
    StackRefused {
        /// Pose index.
        pose: usize,
        /// Camera.
        camera: String,
        /// What the check found and what to do.
        reason: String,
        /// The capture about to start (2 for the first recapture).
        attempt: u32,
        /// Captures in all at most.
        of: u32,
    },
    /// A captured pose whose stacks were on disk but not yet processed: processed now.
    Recovered {
        /// Pose index.
        pose: usize,
    },
    /// A pose captured (or partly) when the last run stopped, whose frames were not saved:
    /// the board must be placed again; its partial files are kept aside.
    NotSaved {
        /// Pose index.
        pose: usize,
        /// Where its partial files were moved, if it had any.
        kept: Option<String>,
    },
    /// Ctrl-C: the capture stopped; every pose already captured was finished.
    Interrupted {
        /// Complete poses in the dataset.
        kept: Vec<usize>,
        /// The pose being captured when it came, to be placed again.
        place_again: Option<usize>,
    },
    /// Poses already complete in the dataset, reused.
    Resumed {
        /// Their indices.
        poses: Vec<usize>,
    },
    /// The rig's self-tests ran before the pose's capture (sync, exposure).
    SelfTested {
        /// The pose captured next.
        pose: usize,
        /// Their report (several lines).
        report: String,
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
            Event::Countdown { pose, seconds: 0 } => write!(f, "pose {pose}: capture starts"),
            Event::Countdown { pose, seconds } => {
                write!(
                    f,
                    "pose {pose}: capture in {seconds} s: hold the board still"
                )
            }
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
            Event::StackRepaired { pose, camera, what } => {
                write!(f, "{camera}, pose {pose}: {what}")
            }
            Event::StackRefused {
                pose,
                camera,
                reason,
                attempt,
                of,
            } => write!(
                f,
                "{camera}, pose {pose}: {reason}; capturing again ({attempt} of {of})"
            ),
            Event::Recovered { pose } => {
                write!(
                    f,
                    "pose {pose}: its stacks were on disk unprocessed: processed now"
                )
            }
            Event::NotSaved { pose, kept } => {
                write!(f, "pose {pose} was not saved: place the board again")?;
                match kept {
                    Some(k) => write!(f, " (its partial files are kept in {k})"),
                    None => Ok(()),
                }
            }
            Event::Interrupted { kept, place_again } => {
                write!(f, "interrupted: complete poses {kept:?} are kept")?;
                match place_again {
                    Some(k) => write!(f, "; pose {k} was not finished: place the board again"),
                    None => Ok(()),
                }?;
                write!(f, "; run the same command to resume")
            }
            Event::Resumed { poses } => write!(f, "resuming: poses {poses:?} already complete"),
            Event::SelfTested { pose, report } => {
                write!(f, "self-tests before pose {pose}:\n{}", report.trim_end())
            }
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
    /// The run's own warnings (skipped poses, failed stacks).
    pub warnings: Vec<String>,
    /// The residual table and every warning (the report's and the run's), as the report
    /// shows them.
    pub diagnosis: crate::calib::diagnostics::Diagnosis,
    /// Against the ground truth, when the rig is simulated.
    pub truth: Vec<TruthCheck>,
    /// How well the cameras agree on each projector's pixels.
    pub agreement: Vec<crate::correspond::Agreement>,
}
