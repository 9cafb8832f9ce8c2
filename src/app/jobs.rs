//! The small jobs: the board's summary and printable target, one simulated view, one stack
//! decoded to files, the devices this machine has.
//!
//! Takes each command's settings; gives what it wrote or found, for the binary to print.

use super::AppError;
use crate::board::Board;
pub use crate::board::Side;
use crate::phase::files::DecodeSummary;
use crate::rig::discover::Found;
use std::path::{Path, PathBuf};

/// `hexcal info`: the built-in board's name and circles per side.
pub fn info() -> String {
    let b = Board::hex600();
    format!("{}: {} circles per side", b.name, b.lattice().len())
}

/// `hexcal board`: the printable SVG of `side` of the board `board` (built-in name or board
/// file) at exact size, written to `out` (named `*.svg`); gives the board's name and the
/// side drawn. A single-sided board draws its front when no side is given and refuses the
/// back; a double-sided board needs the side.
pub fn board_svg(board: &str, side: Option<Side>, out: &Path) -> Result<(String, Side), AppError> {
    if out
        .extension()
        .is_none_or(|e| !e.eq_ignore_ascii_case("svg"))
    {
        return Err(AppError::Input(format!(
            "{}: only SVG is written (name it *.svg)",
            out.display()
        )));
    }
    let named = board;
    let board = Board::resolve(named)?;
    let side = match (side, board.sides.list()) {
        (Some(side), sides) if sides.contains(&side) => side,
        (None, &[only]) => only,
        (Some(side), _) => {
            return Err(AppError::Input(format!(
                "board {named} is single-sided (sides = 1): it has no {side} to draw"
            )))
        }
        (None, _) => {
            return Err(AppError::Input(format!(
                "board {named} has two sides: give --side front or --side back"
            )))
        }
    };
    crate::atomic::write(out, board.svg(side).as_bytes()).map_err(AppError::io(out))?;
    Ok((board.name, side))
}

/// `hexcal simulate`: render one view of the scene file `scene` (the built-in scene when
/// absent; `seed` overrides its noise seed) into `out`; gives the line that says what was
/// written.
pub fn simulate(scene: Option<&Path>, out: &Path, seed: Option<u64>) -> Result<String, AppError> {
    let mut scene = self::scene(scene)?;
    scene.seed = seed.unwrap_or(scene.seed);
    let view = crate::sim::render(&scene)?;
    let [png, json] = crate::sim::write_view(&view, out)?;
    let whole = view.truth.circles.iter().filter(|c| c.whole).count();
    Ok(format!(
        "{}: side {}, {} circles imaged ({whole} whole); truth in {}",
        png.display(),
        view.truth.side.map_or("none", |s| s.name()),
        view.truth.circles.len(),
        json.display()
    ))
}

/// The scene file at `path`, or the built-in scene.
pub fn scene(path: Option<&Path>) -> Result<crate::sim::Scene, AppError> {
    Ok(match path {
        Some(p) => crate::sim::Scene::load(p)?,
        None => crate::sim::Scene::default_scene(),
    })
}

/// What `hexcal decode` wrote.
#[derive(Debug)]
pub struct Decoded {
    /// The files written.
    pub files: Vec<PathBuf>,
    /// The stack's noise and per-projector figures.
    pub summary: DecodeSummary,
    /// Time taken (s).
    pub seconds: f64,
    /// Given the board: the stack's view as a run's `views.json` holds it (detection, grid,
    /// each projector's circle-centre observations), also written as `view.json`.
    pub view: Option<super::process::StackResult>,
}

impl std::fmt::Display for Decoded {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = &self.summary;
        writeln!(
            f,
            "camera {}: {}×{}, decoded in {:.2} s; noise σ_I² = {:.2} + {:.3}·I",
            s.camera, s.width, s.height, self.seconds, s.noise.offset, s.noise.slope
        )?;
        for p in &s.projectors {
            writeln!(
                f,
                "projector {}: valid {:.1} %, B {:.1} DN, σ_I {:.2} DN, predicted σ_φ {:.4} rad, \
                 σ_u {:.3} px, σ_v {:.3} px",
                p.projector,
                100.0 * p.valid_fraction,
                p.noise.modulation,
                p.noise.sigma_i,
                p.noise.sigma_phi,
                p.noise.sigma_u,
                p.noise.sigma_v
            )?;
        }
        if let Some(v) = &self.view {
            let pairs: Vec<String> = (v.projector_points.iter().enumerate())
                .map(|(p, n)| format!("projector {p} {n}"))
                .collect();
            writeln!(
                f,
                "board: {} circles, {} labelled points; circle centres with projector \
                 coordinates: {}",
                v.circles,
                v.points,
                pairs.join(", ")
            )?;
        }
        match s.verdict.passed() {
            true => writeln!(f, "stack check: passed")?,
            false => writeln!(f, "stack check: FAILED: {}", s.verdict.summary())?,
        }
        for note in &s.verdict.notes {
            writeln!(f, "note: {}", note.describe())?;
        }
        Ok(())
    }
}

/// `hexcal decode`: one camera's stack folder to maps, images and a summary in `out`;
/// given `board`, also the stack's view (`view.json`: detection, grid and each projector's
/// circle-centre observations, as a run's `views.json` holds a stack; the camera as device
/// 0 of pose 0, projector p as device 1 + p), so one stack can be judged on its own, whether
/// it passed the stack check or not.
pub fn decode(stack: &Path, out: &Path, board: Option<&str>) -> Result<Decoded, AppError> {
    let t = std::time::Instant::now();
    let board = board.map(Board::resolve).transpose()?;
    let decoded = crate::phase::files::decode_dir(stack)?;
    let (mut files, summary) = crate::phase::files::write_decoded(stack, &decoded, out)?;
    let view = board.map(|b| super::process::view_of_decoded(&decoded, &b, 0, 0, 1));
    if let Some(v) = &view {
        let path = out.join("view.json");
        let text = serde_json::to_string_pretty(v).expect("a view serialises");
        crate::atomic::write(&path, format!("{text}\n").as_bytes()).map_err(AppError::io(&path))?;
        files.push(path);
    }
    Ok(Decoded {
        files,
        summary,
        seconds: t.elapsed().as_secs_f64(),
        view,
    })
}

/// `hexcal devices`: what this machine has, as rig-file addresses, and notes on what could
/// not be listed.
pub fn devices() -> (Vec<Found>, Vec<String>) {
    use crate::rig::discover::{serial_ports, video_nodes};
    let mut all: Vec<Found> = Vec::new();
    let mut notes = Vec::new();
    match serial_ports() {
        Ok(p) => all.extend(p),
        Err(e) => notes.push(e.to_string()),
    }
    all.extend(video_nodes());
    driver_devices(&mut all, &mut notes);
    (all, notes)
}

/// Devices of the drivers built in (cargo features).
fn driver_devices(all: &mut Vec<Found>, notes: &mut Vec<String>) {
    #[cfg(feature = "aravis")]
    all.extend(crate::rig::aravis::list_cameras().into_iter().map(|c| {
        let formats = crate::rig::aravis::describe_formats(&c.id)
            .unwrap_or_else(|e| format!("formats unknown: {e}"));
        Found {
            kind: "aravis",
            description: format!(
                "{} {} #{} ({}): {formats}",
                c.vendor, c.model, c.serial, c.protocol
            ),
            address: if c.address.is_empty() {
                c.id
            } else {
                c.address
            },
        }
    }));
    #[cfg(not(feature = "aravis"))]
    notes.push("GenICam cameras are listed by builds with --features aravis".into());
    #[cfg(feature = "window")]
    match crate::rig::window::monitors() {
        Ok(m) => all.extend(m.into_iter().map(|m| Found {
            kind: "monitor",
            description: format!("{}×{} at {},{}", m.width, m.height, m.x, m.y),
            address: m.name,
        })),
        Err(e) => notes.push(format!("monitors: {e}")),
    }
    #[cfg(not(feature = "window"))]
    notes.push("monitors are listed by builds with --features window".into());
    let _ = (&all, &notes);
}
