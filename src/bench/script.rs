//! `hexcal bench script`: step timing of a rig file's capture script on its devices, the
//! captures left out (each counts as done the moment it starts), so the figures are the
//! executor's and the positioners': when each step started against when it was due, and
//! how long moves and waits took against their plan. Prompts are answered at once.

use crate::app::progress::Event;
use crate::app::script::{jitter, plan_of, Jitter, ScriptRun};
use crate::app::AppError;
use crate::rig::file::RigFile;
use crate::rig::sim::SimWorld;
use std::path::Path;

/// Timing of one kind of step.
#[derive(Clone, Debug, PartialEq)]
pub struct KindTiming {
    /// `move`, `wait`, `capture`, …
    pub kind: String,
    /// Steps of the kind.
    pub steps: usize,
    /// Mean and largest start − due (s).
    pub late_mean_s: f64,
    /// Largest.
    pub late_max_s: f64,
    /// Mean of duration − planned duration (s); captures excluded (they take no time here).
    pub overrun_mean_s: f64,
}

/// What [`bench_script`] measured.
#[derive(Clone, Debug, PartialEq)]
pub struct ScriptBench {
    /// All steps.
    pub jitter: Jitter,
    /// Per kind of step.
    pub kinds: Vec<KindTiming>,
}

/// Run the script of the rig file at `rig_path` on its simulated world (when it has one)
/// and its positioners, the captures taking no time; `scratch` receives `script.json`.
pub fn bench_script(rig_path: &Path, scratch: &Path) -> Result<ScriptBench, AppError> {
    let rig = RigFile::load(rig_path)?;
    let plan = plan_of(&rig)?
        .ok_or_else(|| AppError::Input(format!("{}: no script", rig_path.display())))?;
    let world = match rig.cameras.iter().any(|c| c.sim.is_some()) {
        true => Some(SimWorld::new(&rig, rig.board()?).map_err(crate::rig::OpenError::from)?),
        false => None,
    };
    let (enter, operator) = crossbeam_channel::unbounded();
    for _ in &plan.steps {
        let _ = enter.send(true);
    }
    std::fs::create_dir_all(scratch).map_err(AppError::io(scratch))?;
    let captures = plan.captures;
    let mut say = |_: &str| {};
    let mut run = ScriptRun::new(rig, plan, scratch, operator, None, &mut say);
    for k in 0..captures {
        if !run.place(k, world.as_ref())? {
            break;
        }
        run.event(&Event::PoseCaptured {
            pose: k,
            seconds: 0.0,
            frames_per_second: 0.0,
        });
    }
    let records = run.records().to_vec();
    run.finish()?;
    let jitter =
        jitter(&records).ok_or_else(|| AppError::Input("the script ran no step".into()))?;
    let mut kinds: Vec<KindTiming> = Vec::new();
    for kind in ["move", "wait", "prompt", "capture", "restore"] {
        let of: Vec<_> = records.iter().filter(|r| r.kind == kind).collect();
        if of.is_empty() {
            continue;
        }
        let n = of.len() as f64;
        let late: Vec<f64> = of.iter().map(|r| r.jitter_s()).collect();
        let overrun = of
            .iter()
            .map(|r| r.end_s.unwrap_or(r.start_s) - r.start_s - r.planned_s)
            .sum::<f64>()
            / n;
        kinds.push(KindTiming {
            kind: kind.into(),
            steps: of.len(),
            late_mean_s: late.iter().sum::<f64>() / n,
            late_max_s: late.iter().fold(0.0, |m, &l| m.max(l.abs())),
            overrun_mean_s: if kind == "capture" { 0.0 } else { overrun },
        });
    }
    Ok(ScriptBench { jitter, kinds })
}
