//! A model of a motorised board stage — a turntable carrying a tilt axis — driven over a
//! serial line with a text protocol, as lab positioners are.
//!
//! [`SimulatedStage`] runs the model on a thread serving one end of a pty (or any
//! `Read + Write` stream). Lines end in LF or CR LF; every command gets exactly one reply line:
//!
//! | command | reply |
//! |---|---|
//! | `MOVE a t` | `OK a t` once both axes arrived (angle a, tilt t in degrees) |
//! | `HOME` | as `MOVE 0 0` |
//! | `POS?` | `POS a t` at once (where the axes are now, also while moving) |
//! | `STOP` | `OK a t`: a move under way halts where it is and its `MOVE` gets `STOPPED a t` |
//! | anything else | `ERR …` |
//!
//! The axes move together at a constant speed, so a move of Δ degrees takes |Δ|/speed; the
//! position is interpolated in time, so whoever reads [`StageHandle::position`] during a move
//! sees the board on its way. Faults for tests ([`StageFault`]) start after a number of
//! completed moves: a silent controller, garbage replies, or `ERR motor stalled`.

use std::io::{self, ErrorKind, Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Where the stage's axes are (degrees).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Axes {
    /// Turntable angle about the vertical.
    pub angle_deg: f64,
    /// Tilt of the board about the table's horizontal axis.
    pub tilt_deg: f64,
}

/// A fault the stage shows on every `MOVE` once `after_moves` moves completed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageFault {
    /// Swallows every command, replies nothing.
    Silent,
    /// Replies a line of line noise instead of `OK`.
    Garbage,
    /// Replies `ERR motor stalled`.
    Error,
}

/// What the simulated stage is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageConfig {
    /// Axis speed (degrees per second).
    pub speed_deg_s: f64,
    /// Largest tilt either way (degrees).
    pub tilt_limit_deg: f64,
    /// A fault, and after how many completed moves it starts.
    pub fault: Option<(StageFault, u32)>,
}

impl Default for StageConfig {
    fn default() -> Self {
        StageConfig {
            speed_deg_s: 90.0,
            tilt_limit_deg: 60.0,
            fault: None,
        }
    }
}

/// A move under way.
#[derive(Debug, Clone, Copy)]
struct Motion {
    from: Axes,
    to: Axes,
    start: Instant,
    duration: Duration,
}

impl Motion {
    fn at(&self, now: Instant) -> Axes {
        let d = self.duration.as_secs_f64();
        let f = if d > 0.0 {
            (now.saturating_duration_since(self.start).as_secs_f64() / d).min(1.0)
        } else {
            1.0
        };
        Axes {
            angle_deg: self.from.angle_deg + f * (self.to.angle_deg - self.from.angle_deg),
            tilt_deg: self.from.tilt_deg + f * (self.to.tilt_deg - self.from.tilt_deg),
        }
    }
}

#[derive(Debug, Default)]
struct Shared {
    rest: Mutex<Axes>,
    motion: Mutex<Option<Motion>>,
    moves: AtomicU32,
    stop: AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Reads where a simulated stage's axes are, from any thread.
#[derive(Debug, Clone)]
pub struct StageHandle {
    shared: Arc<Shared>,
}

impl StageHandle {
    /// The axes now (interpolated during a move).
    pub fn position(&self) -> Axes {
        match *lock(&self.shared.motion) {
            Some(m) => m.at(Instant::now()),
            None => *lock(&self.shared.rest),
        }
    }

    /// Moves completed so far.
    pub fn moves(&self) -> u32 {
        self.shared.moves.load(Ordering::SeqCst)
    }
}

/// The stage model running on its own thread.
#[derive(Debug)]
pub struct SimulatedStage {
    handle: StageHandle,
    thread: Option<JoinHandle<io::Result<()>>>,
}

impl SimulatedStage {
    /// Serve `stream` (one end of a pty; its read timeout is the model's time step).
    pub fn spawn<S: Read + Write + Send + 'static>(stream: S, config: StageConfig) -> Self {
        let shared = Arc::new(Shared::default());
        let served = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("sim-stage".into())
            .spawn(move || serve(stream, config, &served))
            .expect("spawning the stage thread");
        SimulatedStage {
            handle: StageHandle { shared },
            thread: Some(thread),
        }
    }

    /// A handle that reads the axes.
    pub fn handle(&self) -> StageHandle {
        self.handle.clone()
    }
}

impl Drop for SimulatedStage {
    fn drop(&mut self) {
        self.handle.shared.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The model's loop: read bytes, answer complete lines, finish moves when they arrive.
fn serve<S: Read + Write>(mut stream: S, config: StageConfig, shared: &Shared) -> io::Result<()> {
    let mut line = Vec::new();
    let mut buf = [0u8; 256];
    while !shared.stop.load(Ordering::SeqCst) {
        match stream.read(&mut buf) {
            Ok(0) => std::thread::sleep(Duration::from_millis(1)),
            Ok(n) => {
                for &b in &buf[..n] {
                    if b == b'\n' || b == b'\r' {
                        if !line.is_empty() {
                            let text = String::from_utf8_lossy(&line).trim().to_string();
                            line.clear();
                            if let Some(reply) = command(&text, &config, shared) {
                                writeln!(stream, "{reply}")?;
                            }
                        }
                    } else if line.len() < 256 {
                        line.push(b);
                    }
                }
            }
            Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {}
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            // The host closed its end.
            Err(_) => return Ok(()),
        }
        if let Some(reply) = arrive(shared) {
            writeln!(stream, "{reply}")?;
        }
    }
    Ok(())
}

fn format_axes(word: &str, a: Axes) -> String {
    format!("{word} {:.3} {:.3}", a.angle_deg, a.tilt_deg)
}

/// A move that arrived: its reply.
fn arrive(shared: &Shared) -> Option<String> {
    let mut motion = lock(&shared.motion);
    let m = (*motion)?;
    let now = Instant::now();
    if now < m.start + m.duration {
        return None;
    }
    *lock(&shared.rest) = m.to;
    *motion = None;
    shared.moves.fetch_add(1, Ordering::SeqCst);
    Some(format_axes("OK", m.to))
}

/// One command line: the reply to send at once, if any (a `MOVE` replies when it arrives).
fn command(text: &str, config: &StageConfig, shared: &Shared) -> Option<String> {
    let words: Vec<&str> = text.split_whitespace().collect();
    let is_move = matches!(words.first(), Some(&"MOVE") | Some(&"HOME"));
    if let Some((fault, after)) = config.fault {
        if shared.moves.load(Ordering::SeqCst) >= after && (is_move || fault == StageFault::Silent)
        {
            return match fault {
                StageFault::Silent => None,
                StageFault::Garbage => Some("\u{7f}#?~+~ 0x3F?? ~~".into()),
                StageFault::Error => Some("ERR motor stalled".into()),
            };
        }
    }
    let now = Instant::now();
    let here = match *lock(&shared.motion) {
        Some(m) => m.at(now),
        None => *lock(&shared.rest),
    };
    match words.as_slice() {
        ["POS?"] => Some(format_axes("POS", here)),
        ["STOP"] => {
            let stopped = lock(&shared.motion).take().is_some();
            *lock(&shared.rest) = here;
            let ok = format_axes("OK", here);
            Some(match stopped {
                true => format!("{}\n{ok}", format_axes("STOPPED", here)),
                false => ok,
            })
        }
        ["HOME"] => start_move(shared, config, here, Axes::default()),
        ["MOVE", a, t] => match (a.parse::<f64>(), t.parse::<f64>()) {
            (Ok(a), Ok(t)) if a.is_finite() && t.is_finite() => {
                let to = Axes {
                    angle_deg: a,
                    tilt_deg: t,
                };
                start_move(shared, config, here, to)
            }
            _ => Some(format!("ERR not a position: {a} {t}")),
        },
        _ => Some(format!("ERR unknown command: {text}")),
    }
}

fn start_move(shared: &Shared, config: &StageConfig, here: Axes, to: Axes) -> Option<String> {
    if to.tilt_deg.abs() > config.tilt_limit_deg {
        return Some(format!(
            "ERR tilt {} beyond ±{}",
            to.tilt_deg, config.tilt_limit_deg
        ));
    }
    let mut motion = lock(&shared.motion);
    if motion.is_some() {
        return Some("ERR busy".into());
    }
    let travel = (to.angle_deg - here.angle_deg)
        .abs()
        .max((to.tilt_deg - here.tilt_deg).abs());
    *motion = Some(Motion {
        from: here,
        to,
        start: Instant::now(),
        duration: Duration::from_secs_f64(travel / config.speed_deg_s.max(1e-3)),
    });
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{BufRead, BufReader};

    /// A stage on a pty pair; the host end reads lines.
    fn stage(config: StageConfig) -> (SimulatedStage, BufReader<serialport::TTYPort>) {
        use serialport::SerialPort;
        let (mut master, mut slave) = serialport::TTYPort::pair().unwrap();
        master.set_timeout(Duration::from_millis(1)).unwrap();
        slave.set_timeout(Duration::from_secs(3)).unwrap();
        (SimulatedStage::spawn(master, config), BufReader::new(slave))
    }

    fn ask(host: &mut BufReader<serialport::TTYPort>, line: &str) -> String {
        host.get_mut().write_all(line.as_bytes()).unwrap();
        let mut reply = String::new();
        host.read_line(&mut reply).unwrap();
        reply.trim().to_string()
    }

    #[test]
    fn moves_take_their_time_and_the_axes_follow() {
        let config = StageConfig {
            speed_deg_s: 200.0,
            ..StageConfig::default()
        };
        let (stage, mut host) = stage(config);
        let t = Instant::now();
        assert_eq!(ask(&mut host, "MOVE 40 -20\n"), "OK 40.000 -20.000");
        // 40° at 200°/s: 0.2 s.
        assert!(
            t.elapsed() >= Duration::from_millis(195),
            "{:?}",
            t.elapsed()
        );
        let p = stage.handle().position();
        assert_eq!((p.angle_deg, p.tilt_deg), (40.0, -20.0));
        assert_eq!(ask(&mut host, "POS?\r\n"), "POS 40.000 -20.000");
        assert_eq!(ask(&mut host, "MOVE 0 99\n"), "ERR tilt 99 beyond ±60");
        assert!(ask(&mut host, "SPIN\n").starts_with("ERR unknown command"));
        assert_eq!(ask(&mut host, "HOME\n"), "OK 0.000 0.000");
        assert_eq!(stage.handle().moves(), 2);
    }

    #[test]
    fn a_stop_halts_a_move_on_its_way() {
        let config = StageConfig {
            speed_deg_s: 50.0,
            ..StageConfig::default()
        };
        let (stage, mut host) = stage(config);
        host.get_mut().write_all(b"MOVE 90 0\n").unwrap();
        std::thread::sleep(Duration::from_millis(300));
        let mid = stage.handle().position().angle_deg;
        assert!(mid > 5.0 && mid < 40.0, "{mid}");
        assert!(ask(&mut host, "STOP\n").starts_with("STOPPED"));
        let mut ok = String::new();
        host.read_line(&mut ok).unwrap();
        assert!(ok.starts_with("OK"), "{ok}");
        let after = stage.handle().position().angle_deg;
        std::thread::sleep(Duration::from_millis(100));
        assert_eq!(stage.handle().position().angle_deg, after);
    }

    #[test]
    fn faults_start_after_the_given_moves() {
        let config = StageConfig {
            speed_deg_s: 1000.0,
            fault: Some((StageFault::Error, 1)),
            ..StageConfig::default()
        };
        let (_stage, mut host) = stage(config);
        assert_eq!(ask(&mut host, "MOVE 10 0\n"), "OK 10.000 0.000");
        assert_eq!(ask(&mut host, "MOVE 20 0\n"), "ERR motor stalled");
        assert_eq!(ask(&mut host, "POS?\n"), "POS 10.000 0.000");
    }
}
