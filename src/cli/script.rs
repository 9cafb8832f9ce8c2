//! `hexcal run` and `hexcal capture` on a rig file with a capture script: the script places
//! every pose and sets the exposure of the captures that ask for their own, the operator's
//! Enter answers its prompts, and its step timing is printed at the end.

use super::{operator_lines, printer, Progress};
use crossbeam_channel::Receiver;
use hexcal::app::capture::{capture_dataset, CaptureOptions, CaptureSummary, Note};
use hexcal::app::progress::{Event, Outcome};
use hexcal::app::run::RunOptions;
use hexcal::app::script::{Asking, Jitter, ScriptRun};
use hexcal::rig::file::RigFile;
use hexcal::rig::script::{Action, Plan};
use std::cell::RefCell;
use std::path::Path;

/// The operator console's part in a scripted run.
#[derive(Default)]
pub struct ConsoleHooks {
    /// The console's button presses (they answer prompts).
    pub button: Option<Receiver<()>>,
    /// Hears each prompt's text when it starts and `None` when it ends.
    pub prompts: Option<Asking<'static>>,
}

/// Run the rig file `rig` (read as `file`, its script unrolled as `plan`) into `out`;
/// `show` hears every event too, and `console` answers and shows prompts (the operator
/// console).
pub fn run(
    file: RigFile,
    plan: Plan,
    (rig, out): (&Path, &Path),
    options: &RunOptions,
    progress: Progress,
    (show, console): (&mut dyn FnMut(&Event), ConsoleHooks),
) -> anyhow::Result<(Outcome, Option<Jitter>)> {
    let operator = operator(&plan, console.button);
    let options = RunOptions {
        poses: Some(plan.captures),
        exposures: plan.exposures(&file),
        ..options.clone()
    };
    let mut say = |line: &str| match progress {
        Progress::Json => println!("{}", serde_json::json!({"event": "script", "say": line})),
        _ => eprintln!("{line}"),
    };
    let mut script = ScriptRun::new(file, plan, out, operator, options.stop.clone(), &mut say);
    if let Some(prompts) = console.prompts {
        script = script.with_prompts_to(prompts);
    }
    let script = RefCell::new(script);
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

/// The operator's answers to the script's prompts: Enter, read only when the script prompts
/// (an unattended script leaves stdin alone), and, with the console open, its `button`; the
/// end of stdin then leaves the button to answer.
fn operator(plan: &Plan, button: Option<Receiver<()>>) -> Receiver<bool> {
    let prompts = plan
        .steps
        .iter()
        .any(|s| matches!(s.action, Action::Prompt { .. }));
    let lines = match prompts {
        true => operator_lines(),
        false => return crossbeam_channel::never(),
    };
    let Some(button) = button else {
        return lines;
    };
    let (tx, rx) = crossbeam_channel::bounded(1);
    std::thread::spawn(move || {
        // Enter (or the end of stdin: `None`) until stdin ends, then the button alone.
        let mut lines = Some(lines);
        loop {
            let press = match lines.clone() {
                Some(l) => crossbeam_channel::select! {
                    recv(l) -> line => match line {
                        Ok(true) => Ok(()),
                        _ => {
                            lines = None;
                            continue;
                        }
                    },
                    recv(button) -> press => press,
                },
                None => button.recv(),
            };
            if press.is_err() || tx.send(true).is_err() {
                return;
            }
        }
    });
    rx
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
    let operator = operator(&plan, None);
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
