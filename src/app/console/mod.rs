//! The operator console (`hexcal run --console [ADDR]`): a local web page that shows, while
//! a run goes on, one thumbnail per camera with its labelled circles and lattice drawn over
//! it, a live picture per camera while the board is placed, per device the poses seen, a
//! coverage map of its image and the range of board tilts, a big done / not-done sign, and a
//! capture button.
//!
//! Takes the run's progress events, its captured frames (through a [`FrameTap`]), its live
//! preview frames (through a [`PreviewTap`]), the processed poses as the run makes them and
//! the run's [`Verdict`] (each device's progress, the guidance, done or not: decided by the
//! run's guidance loop, [`crate::app::guide::interim`]); gives the page (served from the
//! binary, no outside file or network) and the capture button's presses. It shows what the
//! run decides; it decides nothing.
//! The page follows the run through server-sent events; pages come and go as they like.

pub mod labels;
pub mod preview;
mod server;
pub mod state;
pub mod thumbs;

use super::guide::verdict::Verdict;
use super::process::PoseViews;
use super::progress::Event;
use super::run::{FrameTap, PreviewTap};
use crate::app::lock;
use crate::board::Board;
use crossbeam_channel::{bounded, Receiver, Sender, TrySendError};
use labels::Overlay;
use preview::LiveView;
use state::{CameraPanel, Live, Preview, State};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
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
    /// The live pictures were taken before the last capture.
    #[error("the live pictures are not fresh yet (taken before the last capture): wait a moment")]
    Stale,
}

/// What the server threads and the run share.
struct Shared {
    state: Mutex<State>,
    snapshot: Mutex<Arc<String>>,
    pngs: Mutex<Vec<Option<Arc<Vec<u8>>>>>,
    live: Mutex<Vec<Option<Arc<Vec<u8>>>>>,
    hub: Mutex<Vec<Sender<()>>>,
    capture: Sender<()>,
    finish: Sender<()>,
    /// The access token every request must carry (`?token=`).
    token: String,
    closed: AtomicBool,
    /// When the live preview's rounds ended (its rate).
    clock: Mutex<PreviewClock>,
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
        let fresh_from = s.fresh_from;
        let p = s.preview.get_or_insert_with(Preview::default);
        let views = match round {
            Ok(views) => views,
            Err(e) => {
                p.error = Some(e.to_string());
                // No fresh picture will come: Capture no longer waits for one.
                s.stale = false;
                self.publish(&mut s);
                return;
            }
        };
        p.rounds += 1;
        p.error = None;
        let stale = p.rounds < fresh_from;
        (p.rate_hz, p.detect_ms) = lock(&self.clock).tick(started);
        let n = p.rounds;
        p.stages = Default::default();
        p.seeing = 0;
        for v in views.iter().flatten() {
            p.stages += v.stages;
            p.seeing += usize::from(v.count.seen);
        }
        s.stale = stale;
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
                count: v.count,
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
        if s.prompt.is_none() && s.stale {
            return Err(PressRefused::Stale);
        }
        match self.capture.try_send(()) {
            Ok(()) | Err(TrySendError::Full(())) => Ok(()),
            Err(TrySendError::Disconnected(())) => Err(PressRefused::Gone),
        }
    }

    /// The Finish button: taken while the run captures (waiting for the board, counting down
    /// or capturing);
    /// the capture ends at the next placement and the run calibrates from the poses so far.
    /// The page then says what the run does and, before DONE, what is not yet met.
    fn press_finish(&self) -> Result<(), PressRefused> {
        let mut s = lock(&self.state);
        if !matches!(s.status.as_str(), "waiting" | "countdown" | "capturing") {
            return Err(PressRefused::NotWaiting(s.status.clone()));
        }
        match self.finish.try_send(()) {
            Ok(()) | Err(TrySendError::Full(())) => {}
            Err(TrySendError::Disconnected(())) => return Err(PressRefused::Gone),
        }
        s.finishing = Some(match s.verdict.done {
            true => "Finish: the capture ends; calibrating now".into(),
            false => format!(
                "Finish before done: the capture ends and the run calibrates now; not yet met: {}",
                s.verdict.missing.join("; ")
            ),
        });
        self.publish(&mut s);
        Ok(())
    }

    /// Number the state, and tell every open page it changed (a page that has not yet read
    /// the last change reads this one with it: each event is the whole state).
    fn publish(&self, state: &mut State) {
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
    finishes: Receiver<()>,
    url: String,
}

impl Console {
    /// Serve the console on `addr` (e.g. 127.0.0.1:8765; port 0 picks a free one) for a run
    /// with these `cameras` (name, image size); `auto`: the run places poses itself (no
    /// capture button). A fresh random access token guards it: [`Console::url`] carries it,
    /// and every request without it is refused (403), on loopback as on any other address.
    pub fn start(
        addr: &str,
        cameras: &[(String, [u32; 2])],
        auto: bool,
    ) -> Result<Console, ConsoleError> {
        let fail = |reason: String| ConsoleError {
            addr: addr.to_string(),
            reason,
        };
        let server = tiny_http::Server::http(addr).map_err(|e| fail(e.to_string()))?;
        let token = format!("{:032x}", rand::random::<u128>());
        let url = match server.server_addr().to_ip() {
            Some(a) => format!("http://{a}/?token={token}"),
            None => return Err(fail("not an IP address".into())),
        };
        let (capture, captures) = bounded(1);
        let (finish, finishes) = bounded(1);
        let state = State {
            status: "starting".into(),
            message: "opening the rig".into(),
            auto,
            cameras: cameras
                .iter()
                .map(|(name, size)| CameraPanel {
                    name: name.clone(),
                    size: *size,
                    ..CameraPanel::default()
                })
                .collect(),
            ..State::default()
        };
        let shared = Arc::new(Shared {
            state: Mutex::new(state),
            snapshot: Mutex::new(Arc::new(String::new())),
            pngs: Mutex::new(Vec::new()),
            live: Mutex::new(Vec::new()),
            hub: Mutex::new(Vec::new()),
            capture,
            finish,
            token,
            closed: AtomicBool::new(false),
            clock: Mutex::new(PreviewClock::default()),
        });
        shared.publish(&mut lock(&shared.state));
        let server = Arc::new(server);
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
            finishes,
            url,
        })
    }

    /// What shows the run's verdicts on the page (give it to the run's guidance loop).
    pub fn verdicts(&self) -> impl Fn(&Verdict) + Send + 'static {
        let shared = Arc::clone(&self.shared);
        move |v| {
            let mut s = lock(&shared.state);
            s.verdict = v.clone();
            blind_devices(&mut s);
            shared.publish(&mut s);
        }
    }

    /// What draws each processed pose's labelled points over its cameras' pictures.
    pub fn overlays(&self) -> impl Fn(&PoseViews) + Send + Sync + 'static {
        let shared = Arc::clone(&self.shared);
        move |views| {
            let mut s = lock(&shared.state);
            for (c, stack) in views.stacks.iter().enumerate() {
                if let Some(panel) = s.cameras.get_mut(c) {
                    let view = stack.view.as_ref();
                    panel.overlay = Some(Overlay::of(views.pose, stack.circles, view));
                }
            }
            shared.publish(&mut s);
        }
    }

    /// The Finish button's presses (one message per press taken).
    pub fn finishes(&self) -> Receiver<()> {
        self.finishes.clone()
    }

    /// The run ended: `Ok` with the rig's devices the calibration left out (exit 2), or the
    /// run's error; either becomes a failure in the page's header. Open pages get a moment
    /// to read this last state before the console closes.
    pub fn ended(&mut self, result: Result<&[String], &str>) {
        let mut s = lock(&self.shared.state);
        match result {
            Ok([]) => {}
            Ok(out) => s.failures.push(format!(
                "The calibration leaves out {}: show the board to {} in more poses (its \
                 coverage and tilts) and run again (exit 2)",
                out.join(", "),
                if out.len() == 1 { "it" } else { "them" }
            )),
            Err(e) => {
                s.status = "failed".into();
                s.failures.push(format!("The run failed: {e}"));
            }
        }
        let pages = !lock(&self.shared.hub).is_empty();
        self.shared.publish(&mut s);
        drop(s);
        if pages {
            std::thread::sleep(std::time::Duration::from_millis(300));
        }
    }

    /// The page's address.
    pub fn url(&self) -> &str {
        &self.url
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
        self.apply(e, &mut state);
        shared.publish(&mut state);
    }

    fn apply(&self, e: &Event, s: &mut State) {
        match e {
            Event::PoseStarted { pose, of } => {
                // A new placement: the preview's rate starts afresh (a capture lay between),
                // and Capture waits for a round of pictures taken from now on.
                lock(&self.shared.clock).ends.clear();
                if let Some(p) = &s.preview {
                    s.fresh_from = p.rounds + 1;
                    s.stale = p.error.is_none();
                }
                s.status = "waiting".into();
                s.pose = Some([*pose, *of]);
                s.frames = None;
                s.countdown = None;
                s.message = match s.auto {
                    true => format!("pose {pose} ({} of {of})", pose + 1),
                    false => format!(
                        "Place the board for pose {pose} ({} of {of}), then press Capture (or Enter)",
                        pose + 1
                    ),
                };
            }
            Event::Countdown { seconds, .. } => {
                s.status = match seconds {
                    0 => "capturing",
                    _ => "countdown",
                }
                .into();
                s.countdown = Some(*seconds);
                s.message = e.to_string();
            }
            Event::Frames { pose, done, of } => {
                s.status = "capturing".into();
                s.countdown = None;
                s.frames = Some([*done, *of]);
                s.message = format!("capturing pose {pose}: keep the board still");
            }
            Event::PoseCaptured { pose, .. } => {
                self.thumbnails(*pose, s);
                s.message = format!("pose {pose} captured; finding the board");
            }
            Event::PoseProcessed { pose, held_out, .. } => {
                s.processed += usize::from(!held_out);
                // The pose was captured again and kept: its refusal is over.
                let tag = format!(", pose {pose}: ");
                s.failures
                    .retain(|f| !(f.contains(&tag) && f.contains("capturing again")));
                blind_devices(s);
            }
            Event::StackRefused { .. } => s.failures.push(e.to_string()),
            Event::Calibrating { .. } => {
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
            Event::StackFailed { .. } | Event::StackRepaired { .. } => {
                s.warnings.push(e.to_string())
            }
            _ => s.message = e.to_string(),
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

/// Calibration poses after which a device that has seen none is a failure.
const BLIND_AFTER: usize = crate::app::calibrate::MIN_CALIBRATION_POSES;

/// The failure of each device that has not seen the board in [`BLIND_AFTER`] or more
/// calibration poses (replacing the last verdict's).
fn blind_devices(s: &mut State) {
    s.failures.retain(|f| !f.contains("has not seen the board"));
    if s.processed < BLIND_AFTER {
        return;
    }
    for d in s.verdict.devices.iter().filter(|d| d.poses == 0) {
        s.failures.push(format!(
            "{} has not seen the board in {} poses: check that it is on, focused and aimed \
             at where the board goes",
            d.name, s.processed
        ));
    }
}
