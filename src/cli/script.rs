//! `hexcal run` and `hexcal capture` on a rig file with a capture script: the script places
//! every pose and sets the exposure of the captures that ask for their own, the operator's
//! Enter answers its prompts, and its step timing is printed at the end.

use super::{operator_lines, printer, Progress};
use hexcal::app::capture::{capture_dataset, CaptureOptions, CaptureSummary, Note};
use hexcal::app::progress::{Event, Outcome};
use hexcal::app::run::RunOptions;
use hexcal::app::script::{Jitter, ScriptRun};
use hexcal::rig::file::RigFile;
use hexcal::rig::script::{Action, Plan};
use std::cell::RefCell;
use std::path::Path;

/// Run the rig file `rig` (read as `file`, its script unrolled as `plan`) into `out`;
/// `show` hears every event too (the operator console).
pub fn run(
    file: RigFile,
    plan: Plan,
    (rig, out): (&Path, &Path),
    options: &RunOptions,
    progress: Progress,
    show: &mut dyn FnMut(&Event),
) -> anyhow::Result<(Outcome, Option<Jitter>)> {
    let operator = operator(&plan);
    let options = RunOptions {
        poses: Some(plan.captures),
        exposures: plan.exposures(&file),
        ..options.clone()
    };
    let mut say = |line: &str| match progress {
        Progress::Json => println!("{}", serde_json::json!({"event": "script", "say": line})),
        _ => eprintln!("{line}"),
    };
    let script = RefCell::new(ScriptRun::new(
        file,
        plan,
        out,
        operator,
        options.stop.clone(),
        &mut say,
    ));
    let mut print = printer(progress);
    let mut events = |e: &Event| {
        script.borrow_mut().event(e);
        show(e);
        print(e);
    };
    let mut place =
        |k, world: Option<&hexcal::rig::sim::SimWorld>| script.borrow_mut().place(k, world);
    let outcome = hexcal::app::run::run(rig, out, &options, &mut place, &mut events);
    let jitter = script.into_inner().finish();
    let outcome = outcome?;
    Ok((outcome, jitter?))
}

/// The operator's Enter, read only when the script prompts (an unattended script leaves
/// stdin alone).
fn operator(plan: &Plan) -> crossbeam_channel::Receiver<bool> {
    let prompts = plan
        .steps
        .iter()
        .any(|s| matches!(s.action, Action::Prompt { .. }));
    match prompts {
        true => operator_lines(),
        false => crossbeam_channel::never(),
    }
}

/// `hexcal capture` of the rig file `rig` (read as `file`, its script unrolled as `plan`)
/// into the dataset folder `out`: the script's steps place the poses, its timing goes to
/// `out/script.json`; gives what was captured and the step timing.
pub fn capture(
    file: RigFile,
    plan: Plan,
    (rig, out): (&Path, &Path),
) -> anyhow::Result<(CaptureSummary, Option<Jitter>)> {
    let options = CaptureOptions {
        poses: plan.captures,
        exposures: plan.exposures(&file),
    };
    let operator = operator(&plan);
    let mut say = |line: &str| eprintln!("{line}");
    let script = RefCell::new(ScriptRun::new(file, plan, out, operator, None, &mut say));
    let mut place =
        |k, world: Option<&hexcal::rig::sim::SimWorld>| script.borrow_mut().place(k, world);
    let mut log = |note: Note| {
        if let Note::Captured { pose, .. } = note {
            script.borrow_mut().captured(pose);
        }
        eprintln!("{note}");
    };
    let summary = capture_dataset(rig, out, &options, &mut place, &mut log);
    let jitter = script.into_inner().finish();
    let summary = summary.map_err(anyhow::Error::msg)?;
    Ok((summary, jitter?))
}
