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
    url: String,
}

/// The access token a console reachable from other machines requires: 128 random bits as
/// hex; `None` on a loopback address (only this machine can reach it).
fn access_token(addr: std::net::SocketAddr) -> Option<String> {
    (!addr.ip().is_loopback()).then(|| {
        let bits: [u8; 16] = rand::random();
        bits.iter().map(|b| format!("{b:02x}")).collect()
    })
}

impl Console {
    /// Serve the console on `addr` (e.g. 127.0.0.1:8765; port 0 picks a free one) for a run
    /// with these `cameras` (name, image size); `auto`: the run places poses itself (no
    /// capture button).
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
        let Some(bound) = server.server_addr().to_ip() else {
            return Err(fail("not an IP address".into()));
        };
        let token = access_token(bound);
        let url = match &token {
            Some(t) => format!("http://{bound}/?token={t}"),
            None => format!("http://{bound}/"),
        };
        let (capture, captures) = bounded(1);
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
            closed: AtomicBool::new(false),
            clock: Mutex::new(PreviewClock::default()),
        });
        shared.publish(&mut lock(&shared.state));
        let server = Arc::new(server);
        let (srv, sh) = (Arc::clone(&server), Arc::clone(&shared));
        let thread = std::thread::Builder::new()
            .name("console".into())
            .spawn(move || server::serve(&srv, &sh, token.as_deref()))
            .map_err(|e| fail(e.to_string()))?;
        Ok(Console {
            shared,
            server,
            thread: Some(thread),
            thumbs: Arc::new(Mutex::new(Thumbs::default())),
            captures,
            url,
        })
    }

    /// What shows the run's verdicts on the page (give it to the run's guidance loop).
    pub fn verdicts(&self) -> impl Fn(&Verdict) + Send + 'static {
        let shared = Arc::clone(&self.shared);
        move |v| {
            let mut s = lock(&shared.state);
            s.verdict = v.clone();
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

    /// The page's address (with its access token when the console listens beyond this
    /// machine).
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
                // A new placement: the preview's rate starts afresh (a capture lay between).
                lock(&self.shared.clock).ends.clear();
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
            Event::PoseProcessed { .. } => {}
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
            Event::StackFailed { .. } => s.warnings.push(e.to_string()),
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
