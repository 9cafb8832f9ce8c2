//! The operator console (`hexcal run --console [ADDR]`): a local web page that shows, while
//! a run goes on, one thumbnail per camera with its labelled circles and lattice drawn over
//! it, a live picture per camera while the board is placed, per device the poses seen, a
//! coverage map of its image and the range of board tilts, a big done / not-done sign, and a
//! capture button.
//!
//! Takes the run's progress events, its captured frames (through a [`FrameTap`]), its live
//! preview frames (through a [`PreviewTap`]) and the processed poses the run writes to its
//! dataset (`pose-KKK/views.json`); gives the page (served from the binary, no outside file
//! or network), the capture button's presses and, to a guided simulated operator, the
//! interim calibrations' guidance ([`GuidanceWatch`]).
//! The page follows the run through server-sent events; pages come and go as they like.

mod guidance;
pub mod preview;
mod server;
pub mod state;
pub mod stats;
pub mod thumbs;

use super::guide::Guidance;
use super::process::PoseViews;
use super::progress::Event;
use super::run::{FrameTap, PreviewTap};
use crate::board::Board;
use crate::dataset::Dataset;
use crate::observations::CameraView;
use crate::observations::DeviceInfo;
use crossbeam_channel::{bounded, Receiver, Sender, TrySendError};
use preview::LiveView;
use state::{CameraPanel, Live, Preview, State};
use stats::{observations, DeviceStats, Overlay};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use thumbs::Thumbs;

/// Why the console could not start.
#[derive(Debug, thiserror::Error)]
#[error("console: cannot listen on {addr}: {reason}")]
pub struct ConsoleError {
    /// The address asked for.
    pub addr: String,
    /// Why not.
    pub reason: String,
}

/// Why the capture button was refused (answered as 409).
#[derive(Debug, thiserror::Error)]
enum PressRefused {
    /// The run does not wait for the board to be placed by hand (its status).
    #[error("not waiting for the board ({0})")]
    NotWaiting(String),
    /// The run has ended.
    #[error("the run no longer listens")]
    Gone,
}

/// A mutex that a panicked holder leaves usable (the console's data stays consistent field
/// by field, and the run must go on).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// What the server threads and the run share.
struct Shared {
    state: Mutex<State>,
    snapshot: Mutex<Arc<String>>,
    pngs: Mutex<Vec<Option<Arc<Vec<u8>>>>>,
    live: Mutex<Vec<Option<Arc<Vec<u8>>>>>,
    hub: Mutex<Vec<Sender<()>>>,
    capture: Sender<()>,
    closed: AtomicBool,
    /// The interim calibrations asked for and finished, by the poses they cover.
    interim: Mutex<Interim>,
    interim_done: Condvar,
    /// When the live preview's rounds ended (its rate).
    clock: Mutex<PreviewClock>,
}

/// The poses (index of the last + 1) of the latest interim calibration asked for and of
/// the latest finished.
#[derive(Default)]
struct Interim {
    requested: usize,
    finished: usize,
}

/// Waits for the console's interim calibrations (a guided simulated operator follows them).
#[derive(Clone)]
pub struct GuidanceWatch {
    shared: Arc<Shared>,
}

impl GuidanceWatch {
    /// Once every interim calibration asked for so far has finished (or `stopped` says to
    /// give up): the latest guidance, and whether the page's sign reads DONE.
    pub fn latest(&self, stopped: &dyn Fn() -> bool) -> (Option<Guidance>, bool) {
        let mut i = lock(&self.shared.interim);
        while i.finished < i.requested && !stopped() {
            i = match self
                .shared
                .interim_done
                .wait_timeout(i, std::time::Duration::from_millis(100))
            {
                Ok((i, _)) => i,
                Err(e) => e.into_inner().0,
            };
        }
        drop(i);
        let s = lock(&self.shared.state);
        (s.guidance.clone(), s.done)
    }
}

impl Shared {
    fn snapshot(&self) -> Arc<String> {
        Arc::clone(&lock(&self.snapshot))
    }

    fn thumbnail(&self, camera: usize) -> Option<Arc<Vec<u8>>> {
        lock(&self.pngs).get(camera).cloned().flatten()
    }

    fn live_picture(&self, camera: usize) -> Option<Arc<Vec<u8>>> {
        lock(&self.live).get(camera).cloned().flatten()
    }

    /// One round of live preview frames (or why the preview stopped) onto the page.
    fn preview(&self, round: Result<Vec<Option<LiveView>>, &str>, started: std::time::Instant) {
        let mut s = lock(&self.state);
        let p = s.preview.get_or_insert_with(Preview::default);
        let views = match round {
            Ok(views) => views,
            Err(e) => {
                p.error = Some(e.to_string());
                self.publish(&mut s);
                return;
            }
        };
        p.rounds += 1;
        p.error = None;
        (p.rate_hz, p.detect_ms) = lock(&self.clock).tick(started);
        let n = p.rounds;
        p.stages = Default::default();
        p.seeing = 0;
        for v in views.iter().flatten() {
            p.stages += v.stages;
            p.seeing += usize::from(v.sees_board);
        }
        let mut pngs = lock(&self.live);
        for (c, view) in views.into_iter().enumerate() {
            let (Some(v), Some(panel)) = (view, s.cameras.get_mut(c)) else {
                continue;
            };
            if pngs.len() <= c {
                pngs.resize(c + 1, None);
            }
            pngs[c] = Some(Arc::new(v.png));
            panel.live = Some(Live {
                thumb: format!("/live/{c}.png?round={n}"),
                round: n,
                circles: v.circles,
                overlay: v.overlay,
                sees_board: v.sees_board,
            });
        }
        drop(pngs);
        self.publish(&mut s);
    }

    fn lock_hub(&self) -> MutexGuard<'_, Vec<Sender<()>>> {
        lock(&self.hub)
    }

    /// The capture button: taken when the run waits for the board and places by hand.
    fn press_capture(&self) -> Result<(), PressRefused> {
        let s = lock(&self.state);
        if s.prompt.is_none() && (s.auto || s.status != "waiting") {
            return Err(PressRefused::NotWaiting(s.status.clone()));
        }
        match self.capture.try_send(()) {
            Ok(()) | Err(TrySendError::Full(())) => Ok(()),
            Err(TrySendError::Disconnected(())) => Err(PressRefused::Gone),
        }
    }

    /// Judge and number the state, and tell every open page it changed (a page that has
    /// not yet read the last change reads this one with it: each event is the whole state).
    fn publish(&self, state: &mut State) {
        state.judge();
        state.version += 1;
        let json = Arc::new(
            serde_json::to_string(&*state)
                .unwrap_or_else(|e| format!("{{\"status\":\"error\",\"message\":\"{e}\"}}")),
        );
        *lock(&self.snapshot) = json;
        lock(&self.hub).retain(|tx| match tx.try_send(()) {
            Ok(()) | Err(TrySendError::Full(_)) => true,
            Err(TrySendError::Disconnected(_)) => false,
        });
    }
}

/// The running console: its server, and what it learnt of the run so far.
pub struct Console {
    shared: Arc<Shared>,
    server: Arc<tiny_http::Server>,
    thread: Option<JoinHandle<()>>,
    thumbs: Arc<Mutex<Thumbs>>,
    captures: Receiver<()>,
    url: String,
    out: PathBuf,
    data: Option<(Dataset, Board)>,
    pending: Vec<(usize, bool)>,
    /// Every calibration view processed so far, and the poses they come from.
    views: Vec<CameraView>,
    poses: std::collections::BTreeSet<usize>,
    worker: guidance::Worker,
}

impl Console {
    /// Serve the console on `addr` (e.g. 127.0.0.1:8765; port 0 picks a free one) for the
    /// run whose dataset is `out`; `auto`: the run places poses itself (no capture button).
    pub fn start(addr: &str, out: &Path, auto: bool) -> Result<Console, ConsoleError> {
        let fail = |reason: String| ConsoleError {
            addr: addr.to_string(),
            reason,
        };
        let server = tiny_http::Server::http(addr).map_err(|e| fail(e.to_string()))?;
        let url = match server.server_addr().to_ip() {
            Some(a) => format!("http://{a}/"),
            None => return Err(fail("not an IP address".into())),
        };
        let (capture, captures) = bounded(1);
        let state = State {
            status: "starting".into(),
            message: "opening the rig".into(),
            auto,
            threshold: crate::rig::file::DEFAULT_UNCERTAINTY_PX,
            ..State::default()
        };
        let shared = Arc::new(Shared {
            state: Mutex::new(state),
            snapshot: Mutex::new(Arc::new(String::new())),
            pngs: Mutex::new(Vec::new()),
            live: Mutex::new(Vec::new()),
            hub: Mutex::new(Vec::new()),
            capture,
            closed: AtomicBool::new(false),
            interim: Mutex::new(Interim::default()),
            interim_done: Condvar::new(),
            clock: Mutex::new(PreviewClock::default()),
        });
        shared.publish(&mut lock(&shared.state));
        let server = Arc::new(server);
        let sh = Arc::clone(&shared);
        let worker = guidance::Worker::start(move |poses, outcome| {
            let mut s = lock(&sh.state);
            s.guiding = false;
            match outcome {
                Ok(g) => {
                    s.guidance = Some(g);
                    s.guidance_error = None;
                }
                Err(e) => s.guidance_error = Some(e),
            }
            sh.publish(&mut s);
            drop(s);
            let mut i = lock(&sh.interim);
            i.finished = i.finished.max(poses);
            sh.interim_done.notify_all();
        });
        let (srv, sh) = (Arc::clone(&server), Arc::clone(&shared));
        let thread = std::thread::Builder::new()
            .name("console".into())
            .spawn(move || server::serve(&srv, &sh))
            .map_err(|e| fail(e.to_string()))?;
        Ok(Console {
            shared,
            server,
            thread: Some(thread),
            thumbs: Arc::new(Mutex::new(Thumbs::default())),
            captures,
            url,
            out: out.to_path_buf(),
            data: None,
            pending: Vec::new(),
            views: Vec::new(),
            poses: Default::default(),
            worker,
        })
    }

    /// Set the done threshold on every device's projection uncertainty (px; the rig
    /// file's `[guidance] uncertainty_px`).
    pub fn set_threshold(&mut self, px: f64) {
        let mut s = lock(&self.shared.state);
        s.threshold = px;
        self.shared.publish(&mut s);
    }

    /// The page's address.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// A watcher of the interim calibrations.
    pub fn guidance_watch(&self) -> GuidanceWatch {
        GuidanceWatch {
            shared: Arc::clone(&self.shared),
        }
    }

    /// The capture button's presses (one message per press taken).
    pub fn captures(&self) -> Receiver<()> {
        self.captures.clone()
    }

    /// What a capture script calls with its prompt's text when the prompt starts and with
    /// `None` when it ends: the page shows the text, and its button answers the prompt.
    pub fn prompts(&self) -> impl FnMut(Option<&str>) + Send + 'static {
        let shared = Arc::clone(&self.shared);
        move |text| {
            let mut state = lock(&shared.state);
            state.prompt = text.map(str::to_string);
            shared.publish(&mut state);
        }
    }

    /// The tap that makes the thumbnails from the captured frames.
    pub fn frame_tap(&self) -> FrameTap {
        let thumbs = Arc::clone(&self.thumbs);
        FrameTap(Arc::new(move |pose, f| lock(&thumbs).add(pose, f)))
    }

    /// The tap that turns live preview frames into the cameras' live pictures with the
    /// circles and lattice of `board` found on them (each camera's frame on a thread of its
    /// own; the preview's next round waits for this one).
    pub fn preview_tap(&self, board: Board) -> PreviewTap {
        use rayon::prelude::*;
        let shared = Arc::clone(&self.shared);
        let hints: Mutex<Vec<preview::Hint>> = Mutex::new(Vec::new());
        PreviewTap(Arc::new(move |round| {
            let started = std::time::Instant::now();
            let pose = lock(&shared.state).pose.map_or(0, |[k, _]| k);
            let mut hints = lock(&hints);
            let views = round.map(|frames| {
                hints.resize(frames.len(), preview::Hint::default());
                frames
                    .par_iter()
                    .zip(hints.par_iter_mut())
                    .map(|(f, hint)| preview::look(f, &board, pose, hint))
                    .collect()
            });
            drop(hints);
            shared.preview(views, started);
        }))
    }

    /// The live preview's figures so far (rounds, rate, the last round's stages), if a
    /// preview round arrived.
    pub fn preview_figures(&self) -> Option<Preview> {
        lock(&self.shared.state).preview.clone()
    }

    /// Take in one of the run's events and update every open page.
    pub fn event(&mut self, e: &Event) {
        let shared = Arc::clone(&self.shared);
        let mut state = lock(&shared.state);
        self.open_dataset(&mut state);
        self.apply(e, &mut state);
        shared.publish(&mut state);
    }

    fn apply(&mut self, e: &Event, s: &mut State) {
        match e {
            Event::PoseStarted { pose, of } => {
                // A new placement: the preview's rate starts afresh (a capture lay between).
                lock(&self.shared.clock).ends.clear();
                self.read_pending(s);
                s.status = "waiting".into();
                s.pose = Some([*pose, *of]);
                s.frames = None;
                s.message = match s.auto {
                    true => format!("pose {} of {of}", pose + 1),
                    false => format!(
                        "Place the board for pose {} of {of}, then press Capture (or Enter)",
                        pose + 1
                    ),
                };
            }
            Event::Frames { pose, done, of } => {
                s.status = "capturing".into();
                s.frames = Some([*done, *of]);
                s.message = format!("capturing pose {}: keep the board still", pose + 1);
            }
            Event::PoseCaptured { pose, .. } => {
                self.thumbnails(*pose, s);
                s.message = format!("pose {} captured; finding the board", pose + 1);
            }
            Event::PoseProcessed { pose, held_out, .. } => self.pending.push((*pose, *held_out)),
            Event::Calibrating { .. } => {
                self.read_pending(s);
                s.status = "calibrating".into();
                s.message = e.to_string();
            }
            Event::Finished { .. } => {
                s.status = "finished".into();
                s.message = e.to_string();
            }
            Event::Interrupted { .. } => {
                s.status = "stopped".into();
                s.message = e.to_string();
            }
            Event::StackFailed { .. } => s.warnings.push(e.to_string()),
            _ => s.message = e.to_string(),
        }
    }

    /// The dataset (and its board and devices) once the run has created it.
    fn open_dataset(&mut self, s: &mut State) {
        if self.data.is_some() || !self.out.join("dataset.json").exists() {
            return;
        }
        let opened = Dataset::open(&self.out)
            .map_err(|e| e.to_string())
            .and_then(|d| {
                let board = Board::resolve(&d.info.board).map_err(|e| e.to_string())?;
                Ok((d, board))
            });
        match opened {
            Ok((data, board)) => {
                let devices: Vec<DeviceInfo> = super::calibrate::devices_of(&data.info);
                s.devices = devices.iter().map(DeviceStats::new).collect();
                s.cameras = data
                    .info
                    .cameras
                    .iter()
                    .map(|c| CameraPanel {
                        name: c.name.clone(),
                        size: [c.width, c.height],
                        ..CameraPanel::default()
                    })
                    .collect();
                self.data = Some((data, board));
            }
            Err(e) => s.warnings.push(format!("cannot read the dataset: {e}")),
        }
    }

    /// Every camera's thumbnail of pose `pose`.
    fn thumbnails(&self, pose: usize, s: &mut State) {
        let thumbs = lock(&self.thumbs);
        let mut pngs = lock(&self.shared.pngs);
        for (c, panel) in s.cameras.iter_mut().enumerate() {
            let Some(t) = thumbs.finish(c).filter(|t| t.pose == pose) else {
                continue;
            };
            if pngs.len() <= c {
                pngs.resize(c + 1, None);
            }
            pngs[c] = Some(Arc::new(t.png));
            panel.thumb = Some(format!("/thumb/{c}.png?pose={pose}"));
            panel.thumb_pose = Some(pose);
            panel.thumb_step = t.step;
        }
    }

    /// The processed poses whose views the run has written by now.
    fn read_pending(&mut self, s: &mut State) {
        let Some((data, board)) = &self.data else {
            return;
        };
        let mut later = Vec::new();
        let mut new = false;
        for (pose, held_out) in std::mem::take(&mut self.pending) {
            match data.read_pose_file::<PoseViews>(pose, "views.json") {
                Ok(Some(v)) => {
                    take_views(board, &v, held_out, s);
                    if !held_out {
                        let views = v.stacks.iter().filter_map(|st| st.view.clone());
                        self.views.extend(views);
                        self.poses.insert(pose);
                        new = true;
                    }
                }
                Ok(None) => later.push((pose, held_out)),
                Err(e) => s.warnings.push(format!("pose {pose}: {e}")),
            }
        }
        self.pending = later;
        if new && self.poses.len() >= super::calibrate::MIN_CALIBRATION_POSES {
            s.guiding = true;
            let poses = self.poses.last().map_or(0, |p| p + 1);
            lock(&self.shared.interim).requested = poses;
            self.worker.request(guidance::Request {
                board: board.clone(),
                devices: super::calibrate::devices_of(&data.info),
                views: self.views.clone(),
                poses,
                threshold: s.threshold,
            });
        }
    }
}

/// When the live preview's last rounds ended, to tell its rate.
#[derive(Default)]
struct PreviewClock {
    ends: std::collections::VecDeque<std::time::Instant>,
}

impl PreviewClock {
    /// Rounds to average the rate over.
    const ROUNDS: usize = 8;

    /// A round whose frames arrived at `started` ended now: the rate over the rounds since
    /// the placement began (at most the last [`PreviewClock::ROUNDS`]; per second, 0 until
    /// two), and this round's time from its frames to its pictures (ms).
    fn tick(&mut self, started: std::time::Instant) -> (f64, f64) {
        let now = std::time::Instant::now();
        self.ends.push_back(now);
        if self.ends.len() > Self::ROUNDS {
            self.ends.pop_front();
        }
        let rate = match (self.ends.front(), self.ends.len()) {
            (Some(&first), n) if n >= 2 && now > first => {
                (n - 1) as f64 / (now - first).as_secs_f64()
            }
            _ => 0.0,
        };
        (rate, 1e3 * (now - started).as_secs_f64())
    }
}

/// One processed pose into the panels and device statistics.
fn take_views(board: &Board, views: &PoseViews, held_out: bool, s: &mut State) {
    let n = s.devices.len();
    let mut per_device = vec![(Vec::new(), Vec::new()); n];
    for (c, stack) in views.stacks.iter().enumerate() {
        if let Some(panel) = s.cameras.get_mut(c) {
            panel.overlay = Some(Overlay::of(views.pose, stack.circles, stack.view.as_ref()));
        }
        let Some(view) = &stack.view else { continue };
        for (d, (b, p)) in observations(board, view, n).into_iter().enumerate() {
            per_device[d].0.extend(b);
            per_device[d].1.extend(p);
        }
    }
    for (d, (b, p)) in s.devices.iter_mut().zip(per_device) {
        d.add(&b, &p, held_out);
    }
}

impl Drop for Console {
    fn drop(&mut self) {
        self.shared.closed.store(true, Ordering::SeqCst);
        lock(&self.shared.hub).clear();
        self.server.unblock();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests;
