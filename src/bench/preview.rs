//! `hexcal bench preview`: the console's live preview on a simulated rig, round by round.
//!
//! Takes a rig file with simulated devices; places its first pose, starts a real console
//! (on a free loopback port) and runs preview rounds as `hexcal run --console` does between
//! poses: one frame from every camera with the projectors white ([`Session::preview`]),
//! then the console's preview tap (each camera's frame reduced, its circles detected, its
//! grid built, its picture encoded, the page's state published). Gives rounds per second
//! and where a round's time goes.

use crate::app::console::preview::Stages;
use crate::app::console::Console;
use crate::app::AppError;
use crate::board::Board;
use crate::capture::Session;
use crate::rig::file::RigFile;
use std::path::Path;
use std::time::Instant;

/// What [`bench_preview`] measured (means per round).
#[derive(Clone, Debug, Default)]
pub struct PreviewBench {
    /// Cameras of the rig.
    pub cameras: usize,
    /// Rounds timed.
    pub rounds: usize,
    /// Rounds per second (rounds over their whole time).
    pub rate_hz: f64,
    /// Taking one frame from every camera (ms, wall; on a simulated rig this includes
    /// rendering the frames).
    pub grab_ms: f64,
    /// The console's tap: every camera's frame seen and the state published (ms, wall).
    pub tap_ms: f64,
    /// The tap's stages, summed over the cameras (ms of CPU).
    pub stages: Stages,
    /// Cameras that saw the board in the last round.
    pub seeing: usize,
}

/// `rounds` preview rounds (after one untimed) of the rig file at `rig_path`, its board at
/// pose `pose`; `log` hears each round.
pub fn bench_preview(
    rig_path: &Path,
    pose: usize,
    rounds: usize,
    log: &mut dyn FnMut(&str),
) -> Result<PreviewBench, AppError> {
    let input = |e: &dyn std::fmt::Display| AppError::Input(format!("{}: {e}", rig_path.display()));
    let rig = RigFile::load(rig_path)?;
    let board = Board::resolve(&rig.board)?;
    let opened = crate::rig::open(&rig).map_err(|e| input(&e))?;
    let world = opened
        .world
        .clone()
        .ok_or_else(|| input(&"bench preview needs a simulated rig"))?;
    if pose >= world.board_poses.len() {
        return Err(input(&format!(
            "no pose {pose} (the rig has {})",
            world.board_poses.len()
        )));
    }
    world.place(pose);
    let cameras = opened.devices.cameras.len();
    let mut session = Session::start(opened.devices, &opened.sequence).map_err(|e| input(&e))?;
    let panels = crate::app::session::camera_panels(&rig);
    let console = Console::start("127.0.0.1:0", &panels, true).map_err(|e| input(&e))?;
    let tap = console.preview_tap(board);
    let mut b = PreviewBench {
        cameras,
        ..PreviewBench::default()
    };
    let mut timed = std::time::Duration::ZERO;
    // Round 0 builds the simulator's renderers: left out of the figures.
    for round in 0..=rounds {
        let t = Instant::now();
        let frames = session.preview().map_err(|e| input(&e))?;
        let grab = t.elapsed();
        (tap.0)(Ok(&frames));
        let tapped = t.elapsed() - grab;
        let p = console.preview_figures().unwrap_or_default();
        log(&format!(
            "round {round}: grab {:.0} ms, tap {:.0} ms (CPU: reduce {:.0}, detect {:.0}, grid {:.0}, picture {:.0} ms)",
            1e3 * grab.as_secs_f64(),
            1e3 * tapped.as_secs_f64(),
            p.stages.reduce,
            p.stages.detect,
            p.stages.grid,
            p.stages.picture
        ));
        if round == 0 {
            continue;
        }
        timed += t.elapsed();
        b.rounds += 1;
        b.grab_ms += 1e3 * grab.as_secs_f64();
        b.tap_ms += 1e3 * tapped.as_secs_f64();
        b.stages += p.stages;
        b.seeing = p.seeing;
    }
    let n = b.rounds.max(1) as f64;
    b.rate_hz = b.rounds as f64 / timed.as_secs_f64().max(1e-9);
    b.grab_ms /= n;
    b.tap_ms /= n;
    b.stages = b.stages.scaled(1.0 / n);
    session.finish().map_err(|e| input(&e))?;
    drop(console);
    Ok(b)
}
