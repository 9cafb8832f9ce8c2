//! What the console page shows, as one JSON snapshot: the run's status, each camera's
//! thumbnail and overlay, and the run's verdict (each device's progress, the guidance, done
//! or not done) as the run decided it.
//!
//! Takes the run's events, the processed poses, the thumbnails and the verdict; gives
//! [`State`].

use super::labels::Overlay;
use crate::app::guide::stats::ViewCount;
use crate::app::guide::verdict::Verdict;
use serde::Serialize;

/// One camera's picture on the page.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CameraPanel {
    /// Name.
    pub name: String,
    /// Image size (px).
    pub size: [u32; 2],
    /// URL of its latest thumbnail (changes with every new one).
    pub thumb: Option<String>,
    /// The pose the thumbnail shows.
    pub thumb_pose: Option<usize>,
    /// Source pixels per thumbnail pixel.
    pub thumb_step: u32,
    /// Labelled points of the latest processed pose.
    pub overlay: Option<Overlay>,
    /// The latest live preview frame, while the board is placed.
    pub live: Option<Live>,
}

/// One camera's latest live preview frame (taken while the board is placed).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Live {
    /// URL of its picture (changes with every round).
    pub thumb: String,
    /// The preview round it comes from (counts up over the run).
    pub round: u64,
    /// Circles detected on it.
    pub circles: usize,
    /// Labelled points and lattice edges (frame px).
    pub overlay: Overlay,
    /// What the view counts as, by the rule the captured poses are counted by: `seen` (the
    /// camera sees the board now), its `tilt`, `steep` or not.
    #[serde(flatten)]
    pub count: ViewCount,
}

/// The live preview's progress.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Preview {
    /// Rounds (one frame from every camera) so far.
    pub rounds: u64,
    /// Rounds per second over the last few.
    pub rate_hz: f64,
    /// Time to detect and draw the last round (ms).
    pub detect_ms: f64,
    /// What each stage of the last round took, summed over its cameras (ms of CPU).
    pub stages: super::preview::Stages,
    /// Cameras that saw the board in the last round.
    pub seeing: usize,
    /// Why the preview stopped, if it failed.
    pub error: Option<String>,
}

/// The page's whole state.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct State {
    /// Increases with every change.
    pub version: u64,
    /// "starting", "waiting" (for the board), "countdown" (the board placed, the capture
    /// about to start), "capturing", "calibrating", "finished" or "stopped".
    pub status: String,
    /// One sentence for the operator.
    pub message: String,
    /// Poses are placed without waiting (`--auto`): no capture button.
    pub auto: bool,
    /// A capture script's prompt waiting for the operator (the button answers it).
    pub prompt: Option<String>,
    /// The pose being placed or captured, and the poses in all.
    pub pose: Option<[usize; 2]>,
    /// Frames captured of the current pose, and the frames of a pose.
    pub frames: Option<[usize; 2]>,
    /// Whole seconds until the capture of the placed pose starts, as the run counts them
    /// down (0: it starts now); `None` outside a countdown.
    pub countdown: Option<u64>,
    /// Cameras, in rig order.
    pub cameras: Vec<CameraPanel>,
    /// Problems reading what the run wrote (shown, never fatal).
    pub warnings: Vec<String>,
    /// The live preview, once it has run.
    pub preview: Option<Preview>,
    /// The preview round from which the live pictures were taken after the last capture
    /// (Capture waits for it: a picture from before the capture shows an old placement).
    pub fresh_from: u64,
    /// Capture waits for fresh live pictures.
    pub stale: bool,
    /// Failures the operator must act on (red in the page's header): each says what went
    /// wrong and what to do. The sign never reads DONE over one.
    pub failures: Vec<String>,
    /// The operator pressed Finish: what the run does now, and what was not yet met.
    pub finishing: Option<String>,
    /// Calibration poses processed so far.
    pub processed: usize,
    /// The run's verdict: each device's progress, the latest guidance, done or not.
    #[serde(flatten)]
    pub verdict: Verdict,
}
