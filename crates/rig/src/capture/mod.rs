//! Lockstep capture (docs/design.md §11): drive every projector and camera of a rig through the
//! phase-shift sequence, one board pose at a time.
//!
//! Takes boxed [`Camera`]s, [`Projector`]s and an optional hardware [`Trigger`]; gives, per
//! pose, every camera's frame k of the sequence in order to a caller's sink, and the pose's
//! measured [`Timeline`]. Per frame k: every projector shows pattern k, the engine waits for
//! the projectors' latency and the settle time, triggers (the controller's pulse, or one
//! software trigger per camera), and collects frame k from every camera over one crossbeam
//! channel per camera (each camera runs in its own thread). A frame that times out or
//! arrives incomplete is triggered again, a bounded number of times; stale frames (a
//! counter not newer than the last accepted) are dropped; any failure names the device,
//! the pose and the frame. Repeats of a frame are averaged.
//!
//! [`hexcal_core::dataset`] stores captured poses on disk.

use crossbeam_channel::{bounded, Receiver, Sender};
use hexcal_core::dataset::{FrameTiming, StackFrame, Timeline};
use hexcal_core::pattern::Sequence;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use {
    crate::rig::{
        Camera, CameraConfig, CaptureTiming, DeviceError, Projector, RigDevices, Slide, Trigger,
        TriggerSource,
    },
    hexcal_core::images::{CameraFrame, Pixels},
};

/// Why a caller's sink refused a frame (e.g. a full disk): any error.
pub type SinkError = Box<dyn std::error::Error + Send + Sync>;

/// Why a capture failed.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// A device failed while starting or stopping.
    #[error("{0}")]
    Device(#[from] DeviceError),
    /// A frame could not be captured.
    #[error("pose {pose}, frame {frame}: {source}")]
    Frame {
        /// Board pose index.
        pose: usize,
        /// Frame index k in the sequence.
        frame: usize,
        /// What the device said.
        source: DeviceError,
    },
    /// A camera's thread ended (it panicked or its channel closed).
    #[error("camera {camera}: its capture thread ended")]
    ThreadEnded {
        /// Camera name.
        camera: String,
    },
    /// The caller's sink refused a frame (e.g. a full disk).
    #[error("pose {pose}, frame {frame}, camera {camera}: {reason}")]
    Sink {
        /// Board pose index.
        pose: usize,
        /// Frame index k.
        frame: usize,
        /// Camera name.
        camera: String,
        /// What went wrong.
        reason: String,
    },
    /// The rig cannot run this capture.
    #[error("{0}")]
    Setup(String),
    /// A preview frame could not be taken (between poses; no pose is harmed).
    #[error("preview: {0}")]
    Preview(DeviceError),
    /// A self-test's frame could not be taken ([`Session::probe`]).
    #[error("self-test, slide {slide}: {source}")]
    Probe {
        /// Index of the slide set shown.
        slide: usize,
        /// What the device said.
        source: DeviceError,
    },
}

/// One exposure of [`Session::probe`]: every camera's frame of one slide set, at one wait.
#[derive(Clone, Debug)]
pub struct ProbeTake {
    /// Index of the slide set shown.
    pub slide: usize,
    /// Index of the wait asked for.
    pub wait: usize,
    /// Time from the projectors told to show the slides to the trigger, as it happened.
    pub after: Duration,
    /// Every camera's frame, in camera order.
    pub frames: Vec<CameraFrame>,
}

enum Command {
    /// Discard frames already delivered (late ones of an earlier retry).
    Drain,
    /// Take a frame: trigger it first when software-triggered.
    Take {
        software: bool,
    },
    /// Set the exposure (µs) and gain (dB).
    Expose(f64, f64),
    Stop,
}

enum Reply {
    Drained,
    Frame(Result<CameraFrame, DeviceError>),
    Exposed(Result<(), DeviceError>),
}

struct Worker {
    name: String,
    commands: Sender<Command>,
    frames: Receiver<Reply>,
    thread: Option<JoinHandle<Result<(), DeviceError>>>,
    last_counter: Option<u64>,
    /// The configured (exposure µs, gain dB), and the one set now.
    configured: (f64, f64),
    current: (f64, f64),
    /// The pixel format the configured camera delivers, as its driver names it.
    pixel_format: Option<String>,
}

/// A running capture: cameras started in their threads, projectors prepared.
pub struct Session {
    workers: Vec<Worker>,
    projectors: Vec<Box<dyn Projector>>,
    trigger: Option<Box<dyn Trigger>>,
    sequence: Sequence,
    timing: CaptureTiming,
    /// What every projector shows, when the session set one slide on all (none during a
    /// pose).
    shown: Option<Slide>,
    /// A camera balances its Bayer mosaic by the scene and has not yet seen a white-lit
    /// frame ([`crate::rig::Camera::balances_colour`]).
    unbalanced: bool,
}

impl Session {
    /// Configure and start a rig's cameras (one config each), prepare its projectors for
    /// `sequence` (projector i shows code i), arm nothing yet.
    pub fn start(devices: RigDevices, sequence: &Sequence) -> Result<Session, CaptureError> {
        let RigDevices {
            cameras,
            configs,
            projectors,
            trigger,
            timing,
        } = devices;
        let configs = &configs[..];
        if configs.len() != cameras.len() || projectors.len() != sequence.projectors().len() {
            return Err(CaptureError::Setup(format!(
                "{} cameras with {} settings, {} projectors for a sequence of {}",
                cameras.len(),
                configs.len(),
                projectors.len(),
                sequence.projectors().len()
            )));
        }
        if timing.latency.len() != projectors.len() || timing.repeats == 0 {
            return Err(CaptureError::Setup(
                "a latency per projector and at least one repeat are needed".into(),
            ));
        }
        let mut projectors = projectors;
        for (code, p) in projectors.iter_mut().enumerate() {
            p.prepare(sequence, code)?;
        }
        let hardware = trigger.is_some();
        let mut unbalanced = false;
        let mut workers = Vec::with_capacity(cameras.len());
        for (mut cam, config) in cameras.into_iter().zip(configs) {
            let config = CameraConfig {
                trigger: if hardware {
                    TriggerSource::Line
                } else {
                    TriggerSource::Software
                },
                ..*config
            };
            cam.configure(&config)?;
            cam.start()?;
            let name = cam.name().to_string();
            let pixel_format = cam.pixel_format();
            unbalanced |= cam.balances_colour();
            let (cmd_tx, cmd_rx) = bounded::<Command>(4);
            let (frame_tx, frame_rx) = bounded(4);
            let timeout = timing.frame_timeout;
            let thread = std::thread::Builder::new()
                .name(format!("camera {name}"))
                .spawn(move || camera_loop(cam, cmd_rx, frame_tx, timeout))
                .map_err(|e| CaptureError::Setup(format!("camera {name}: no thread: {e}")))?;
            workers.push(Worker {
                name,
                commands: cmd_tx,
                frames: frame_rx,
                thread: Some(thread),
                last_counter: None,
                configured: (config.exposure_us, config.gain_db),
                current: (config.exposure_us, config.gain_db),
                pixel_format,
            });
        }
        Ok(Session {
            workers,
            projectors,
            trigger,
            sequence: sequence.clone(),
            timing,
            shown: None,
            unbalanced,
        })
    }

    /// One preview frame from every camera (camera order) with every projector showing a
    /// flat white field (docs/design.md §15 "Live preview"): a frame outside any pose, one
    /// exposure per camera (no repeats), started by the software trigger or, on a rig with
    /// a trigger controller, by one armed pulse. The next [`Session::capture_pose`] shows
    /// its patterns and discards late frames first, so it runs as it would without it.
    pub fn preview(&mut self) -> Result<Vec<CameraFrame>, CaptureError> {
        if self.shown != Some(Slide::White) {
            self.shown = None;
            for p in &mut self.projectors {
                p.show(Slide::White).map_err(CaptureError::Preview)?;
            }
            self.shown = Some(Slide::White);
            std::thread::sleep(self.settle_time());
        }
        self.drain()?;
        if let Some(t) = self.trigger.as_mut() {
            t.arm(1 + self.timing.retries)
                .map_err(CaptureError::Preview)?;
        }
        let taken = self.take_all(0, 0);
        if let Some(t) = self.trigger.as_mut() {
            let disarmed = t.disarm().map_err(CaptureError::Preview);
            if taken.is_ok() {
                disarmed?;
            }
        }
        match taken {
            Ok((frames, _, _)) => {
                self.unbalanced = false;
                Ok(frames)
            }
            Err(CaptureError::Frame { source, .. }) => Err(CaptureError::Preview(source)),
            Err(e) => Err(e),
        }
    }

    /// How long a slide takes to be seen: the slowest projector's latency and the settle
    /// time.
    fn settle_time(&self) -> Duration {
        self.timing
            .latency
            .iter()
            .max()
            .copied()
            .unwrap_or_default()
            + self.timing.settle
    }

    /// Camera names, in order.
    pub fn camera_names(&self) -> Vec<String> {
        self.workers.iter().map(|w| w.name.clone()).collect()
    }

    /// Projector names, in order.
    pub fn projector_names(&self) -> Vec<String> {
        self.projectors
            .iter()
            .map(|p| p.name().to_string())
            .collect()
    }

    /// The timing the session captures with.
    pub fn timing(&self) -> &CaptureTiming {
        &self.timing
    }

    /// Each camera's (exposure µs, gain dB) set now, in order.
    pub fn exposures(&self) -> Vec<(f64, f64)> {
        self.workers.iter().map(|w| w.current).collect()
    }

    /// From now on, captures use `settings[i]` as camera i's configured exposure (µs) and
    /// gain (dB) — what [`Session::set_exposures`] restores — and set it now.
    pub fn configure_exposures(&mut self, settings: &[(f64, f64)]) -> Result<(), CaptureError> {
        for (w, s) in self.workers.iter_mut().zip(settings) {
            w.configured = *s;
        }
        self.set_exposures(&[])
    }

    /// The pixel format each configured camera delivers (its driver's name), in order.
    pub fn pixel_formats(&self) -> Vec<Option<String>> {
        self.workers
            .iter()
            .map(|w| w.pixel_format.clone())
            .collect()
    }

    /// The sequence shown.
    pub fn sequence(&self) -> &Sequence {
        &self.sequence
    }

    /// Set each camera's exposure (µs) and gain (dB) for the captures that follow:
    /// `settings[i]` for camera i, `None` for its configured ones (so `&[]` restores every
    /// camera). Only cameras whose setting changes are told.
    pub fn set_exposures(&mut self, settings: &[Option<(f64, f64)>]) -> Result<(), CaptureError> {
        for (i, w) in self.workers.iter_mut().enumerate() {
            let want = settings.get(i).copied().flatten().unwrap_or(w.configured);
            if want == w.current {
                continue;
            }
            let ended = || CaptureError::ThreadEnded {
                camera: w.name.clone(),
            };
            w.commands
                .send(Command::Expose(want.0, want.1))
                .map_err(|_| ended())?;
            match w.frames.recv() {
                Ok(Reply::Exposed(r)) => r?,
                _ => return Err(ended()),
            }
            w.current = want;
        }
        Ok(())
    }

    /// Capture pose `pose`: every frame of the sequence from every camera, each handed to
    /// `sink` as soon as all cameras delivered it (frame by frame, in order).
    pub fn capture_pose(
        &mut self,
        pose: usize,
        sink: &mut dyn FnMut(StackFrame) -> Result<(), SinkError>,
    ) -> Result<Timeline, CaptureError> {
        if self.unbalanced {
            // A Bayer camera measures its white balance on the first frame it sees and holds
            // it: let that be a white-lit frame, not the first of a stack (which may be too
            // dark to measure, leaving the frames before the measurement unbalanced).
            self.preview()?;
        }
        let start = Instant::now();
        let frames = self.sequence.frame_count();
        let repeats = self.timing.repeats;
        if let Some(t) = self.trigger.as_mut() {
            // Room for every retry: a retried frame fires again.
            t.arm(frames as u32 * repeats * (1 + self.timing.retries))
                .map_err(|source| CaptureError::Frame {
                    pose,
                    frame: 0,
                    source,
                })?;
        }
        let mut timeline = Timeline::default();
        self.shown = None;
        for k in 0..frames {
            let err = |source| CaptureError::Frame {
                pose,
                frame: k,
                source,
            };
            for p in &mut self.projectors {
                p.show(Slide::Pattern(k)).map_err(err)?;
            }
            let shown = start.elapsed();
            std::thread::sleep(self.settle_time());
            self.drain()?;
            let triggered = start.elapsed();
            let mut sums: Vec<Option<Accumulator>> = vec![None; self.workers.len()];
            let mut retries = 0;
            for _ in 0..repeats {
                let (got, r, dropped) = self.take_all(pose, k)?;
                retries += r;
                timeline.dropped += dropped;
                for (i, (s, f)) in sums.iter_mut().zip(got).enumerate() {
                    match s {
                        None => *s = Some(Accumulator::new(f)),
                        Some(a) => a.add(&f).map_err(|e| CaptureError::Frame {
                            pose,
                            frame: k,
                            source: DeviceError::Incomplete {
                                device: self.workers[i].name.clone(),
                                reason: e.to_string(),
                            },
                        })?,
                    }
                }
            }
            for (camera, acc) in sums.into_iter().enumerate() {
                let frame = acc.expect("at least one repeat").finish();
                sink(StackFrame {
                    camera,
                    index: k,
                    frame,
                })
                .map_err(|e| CaptureError::Sink {
                    pose,
                    frame: k,
                    camera: self.workers[camera].name.clone(),
                    reason: e.to_string(),
                })?;
            }
            timeline.frames.push(FrameTiming {
                index: k,
                shown,
                triggered,
                collected: start.elapsed(),
                retries,
            });
        }
        for p in &mut self.projectors {
            p.show(Slide::Black).map_err(|source| CaptureError::Frame {
                pose,
                frame: frames,
                source,
            })?;
        }
        self.shown = Some(Slide::Black);
        if let Some(t) = self.trigger.as_mut() {
            t.disarm().map_err(|source| CaptureError::Frame {
                pose,
                frame: frames,
                source,
            })?;
        }
        timeline.total = start.elapsed();
        Ok(timeline)
    }

    /// The self-tests' lockstep (docs/design.md §11b): show `slides[i]` (one slide per
    /// projector) for i in order, and after each, at every delay of `waits` (ascending, from
    /// the moment the projectors were told), take one frame from every camera (no repeats)
    /// and hand it to `sink`. The timing of the rig file is not used: `waits` is.
    pub fn probe(
        &mut self,
        slides: &[Vec<Slide>],
        waits: &[Duration],
        sink: &mut dyn FnMut(ProbeTake) -> Result<(), SinkError>,
    ) -> Result<(), CaptureError> {
        if slides.iter().any(|s| s.len() != self.projectors.len()) {
            return Err(CaptureError::Setup(format!(
                "a self-test slide set per projector ({}) is needed",
                self.projectors.len()
            )));
        }
        self.shown = None;
        if let Some(t) = self.trigger.as_mut() {
            let takes = (slides.len() * waits.len()) as u32;
            t.arm(takes * (1 + self.timing.retries))
                .map_err(|source| CaptureError::Probe { slide: 0, source })?;
        }
        let taken = self.probe_all(slides, waits, sink);
        if let Some(t) = self.trigger.as_mut() {
            let disarmed = t.disarm().map_err(|source| CaptureError::Probe {
                slide: slides.len(),
                source,
            });
            if taken.is_ok() {
                disarmed?;
            }
        }
        taken
    }

    fn probe_all(
        &mut self,
        slides: &[Vec<Slide>],
        waits: &[Duration],
        sink: &mut dyn FnMut(ProbeTake) -> Result<(), SinkError>,
    ) -> Result<(), CaptureError> {
        for (i, set) in slides.iter().enumerate() {
            let err = |source| CaptureError::Probe { slide: i, source };
            for (p, slide) in self.projectors.iter_mut().zip(set) {
                p.show(*slide).map_err(err)?;
            }
            let shown = Instant::now();
            for (j, wait) in waits.iter().enumerate() {
                std::thread::sleep(wait.saturating_sub(shown.elapsed()));
                self.drain()?;
                let after = shown.elapsed();
                let frames = match self.take_all(0, i) {
                    Ok((frames, _, _)) => frames,
                    Err(CaptureError::Frame { source, .. }) => return Err(err(source)),
                    Err(e) => return Err(e),
                };
                let take = ProbeTake {
                    slide: i,
                    wait: j,
                    after,
                    frames,
                };
                sink(take).map_err(|e| CaptureError::Setup(format!("self-test: {e}")))?;
            }
        }
        Ok(())
    }

    /// Discard late frames in every camera (acknowledged, so none is pending after).
    fn drain(&mut self) -> Result<(), CaptureError> {
        for w in &self.workers {
            let ended = || CaptureError::ThreadEnded {
                camera: w.name.clone(),
            };
            w.commands.send(Command::Drain).map_err(|_| ended())?;
        }
        for w in &self.workers {
            match w.frames.recv() {
                Ok(Reply::Drained) => {}
                _ => {
                    return Err(CaptureError::ThreadEnded {
                        camera: w.name.clone(),
                    })
                }
            }
        }
        Ok(())
    }

    /// One frame from every camera, retrying failed ones; gives the frames, the retries
    /// and the frames lost on the way.
    fn take_all(
        &mut self,
        pose: usize,
        k: usize,
    ) -> Result<(Vec<CameraFrame>, u32, u64), CaptureError> {
        let n = self.workers.len();
        let mut got: Vec<Option<CameraFrame>> = vec![None; n];
        let mut retries = 0;
        let mut dropped = 0;
        let mut attempt = 0;
        loop {
            // Hardware: one pulse reaches every camera, so all take a frame (those that
            // already have theirs discard the extra one). Software: only the missing.
            let hardware = self.trigger.is_some();
            let takers: Vec<usize> = (0..n).filter(|&i| hardware || got[i].is_none()).collect();
            for &i in &takers {
                let w = &self.workers[i];
                w.commands
                    .send(Command::Take {
                        software: !hardware,
                    })
                    .map_err(|_| CaptureError::ThreadEnded {
                        camera: w.name.clone(),
                    })?;
            }
            if let Some(t) = self.trigger.as_mut() {
                t.fire().map_err(|source| CaptureError::Frame {
                    pose,
                    frame: k,
                    source,
                })?;
            }
            let mut failure = None;
            for &i in &takers {
                let w = &mut self.workers[i];
                let reply = match w.frames.recv() {
                    Ok(Reply::Frame(r)) => r,
                    _ => {
                        return Err(CaptureError::ThreadEnded {
                            camera: w.name.clone(),
                        })
                    }
                };
                match reply {
                    Ok(frame) => {
                        if w.last_counter.is_some_and(|c| frame.counter <= c) {
                            // Stale: a late delivery of a frame already given up on.
                            failure.get_or_insert(DeviceError::Incomplete {
                                device: w.name.clone(),
                                reason: format!("stale frame (counter {})", frame.counter),
                            });
                            continue;
                        }
                        if let Some(c) = w.last_counter {
                            dropped += frame.counter - c - 1;
                        }
                        w.last_counter = Some(frame.counter);
                        if got[i].is_none() {
                            got[i] = Some(frame);
                        }
                    }
                    Err(e) if e.retryable() => {
                        failure.get_or_insert(e);
                    }
                    Err(source) => {
                        return Err(CaptureError::Frame {
                            pose,
                            frame: k,
                            source,
                        })
                    }
                }
            }
            if got.iter().all(Option::is_some) {
                return Ok((got.into_iter().flatten().collect(), retries, dropped));
            }
            attempt += 1;
            if attempt > self.timing.retries {
                let source = failure.unwrap_or_else(|| DeviceError::Failed {
                    device: self.workers[got.iter().position(Option::is_none).unwrap_or(0)]
                        .name
                        .clone(),
                    reason: "no frame".into(),
                });
                return Err(CaptureError::Frame {
                    pose,
                    frame: k,
                    source,
                });
            }
            retries += 1;
        }
    }

    /// Stop every camera and blank every projector; the first failure is returned after
    /// all were asked.
    pub fn finish(mut self) -> Result<(), CaptureError> {
        let mut first = None;
        for p in &mut self.projectors {
            if let Err(e) = p.show(Slide::Black) {
                first.get_or_insert(CaptureError::Device(e));
            }
        }
        for w in &mut self.workers {
            let _ = w.commands.send(Command::Stop);
            if let Some(t) = w.thread.take() {
                match t.join() {
                    Ok(Ok(())) => {}
                    Ok(Err(e)) => {
                        first.get_or_insert(CaptureError::Device(e));
                    }
                    Err(_) => {
                        first.get_or_insert(CaptureError::ThreadEnded {
                            camera: w.name.clone(),
                        });
                    }
                }
            }
        }
        first.map_or(Ok(()), Err)
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        for w in &mut self.workers {
            let _ = w.commands.send(Command::Stop);
            if let Some(t) = w.thread.take() {
                let _ = t.join();
            }
        }
    }
}

fn camera_loop(
    mut cam: Box<dyn Camera>,
    commands: Receiver<Command>,
    frames: Sender<Reply>,
    timeout: Duration,
) -> Result<(), DeviceError> {
    loop {
        let reply = match commands.recv() {
            Ok(Command::Drain) => {
                while cam.next_frame(Duration::ZERO).is_ok() {}
                Reply::Drained
            }
            Ok(Command::Take { software }) => Reply::Frame(if software {
                cam.trigger().and_then(|()| cam.next_frame(timeout))
            } else {
                cam.next_frame(timeout)
            }),
            Ok(Command::Expose(exposure_us, gain_db)) => {
                Reply::Exposed(cam.set_exposure_gain(exposure_us, gain_db))
            }
            Ok(Command::Stop) | Err(_) => break,
        };
        if frames.send(reply).is_err() {
            break;
        }
    }
    cam.stop()
}

/// Sum of repeated frames of one camera.
#[derive(Clone)]
struct Accumulator {
    first: CameraFrame,
    sum: Vec<u32>,
    count: u32,
}

/// Repeats of a frame that differ in size or depth.
#[derive(Debug, thiserror::Error)]
#[error("repeats of different sizes")]
struct RepeatMismatch;

impl Accumulator {
    fn new(first: CameraFrame) -> Accumulator {
        Accumulator {
            first,
            sum: Vec::new(),
            count: 1,
        }
    }

    /// Add a repeat; `Err` when its size or depth differs from the first.
    fn add(&mut self, f: &CameraFrame) -> Result<(), RepeatMismatch> {
        if (f.width, f.height, f.bits) != (self.first.width, self.first.height, self.first.bits) {
            return Err(RepeatMismatch);
        }
        if self.sum.is_empty() {
            self.sum = samples(&self.first.pixels);
        }
        for (s, v) in self.sum.iter_mut().zip(samples(&f.pixels)) {
            *s += v;
        }
        self.count += 1;
        Ok(())
    }

    fn finish(self) -> CameraFrame {
        if self.count == 1 {
            return self.first;
        }
        let (c, half) = (self.count, self.count / 2);
        let pixels = match self.first.pixels {
            Pixels::Gray8(_) => {
                Pixels::Gray8(self.sum.iter().map(|s| ((s + half) / c) as u8).collect())
            }
            Pixels::Gray16(_) => {
                Pixels::Gray16(self.sum.iter().map(|s| ((s + half) / c) as u16).collect())
            }
        };
        CameraFrame {
            pixels,
            ..self.first
        }
    }
}

fn samples(p: &Pixels) -> Vec<u32> {
    match p {
        Pixels::Gray8(v) => v.iter().map(|&x| u32::from(x)).collect(),
        Pixels::Gray16(v) => v.iter().map(|&x| u32::from(x)).collect(),
    }
}

#[cfg(test)]
pub(crate) mod tests;
