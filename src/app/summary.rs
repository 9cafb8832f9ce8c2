//! The printed summary of a calibration: the residual table, the lens models, what was left
//! out, the verification and the report's warning count — written once, from the
//! [`Diagnosis`] the page and the files were written from.
//!
//! Takes a run's [`Outcome`] or a correspondences file's [`FileOutcome`]; gives the text the
//! binary prints.

use super::calibrate::FileOutcome;
use super::progress::Outcome;
use crate::calib::diagnostics::Diagnosis;
use crate::calib::solve::Calibration;
use crate::observations::DeviceInfo;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The parts every calibration's summary opens with: the residual table and lens models,
/// the devices left out, what the data could not determine and the views not registered.
fn calibration_lines(
    s: &mut String,
    cal: &Calibration,
    diagnosis: &Diagnosis,
    devices: &[DeviceInfo],
) {
    s.push_str(&crate::report::format_table(&diagnosis.rows));
    s.push_str(&crate::report::format_lens_models(cal));
    for e in &cal.excluded {
        let _ = writeln!(s, "not calibrated: {}: {}", e.name, e.reason);
    }
    for h in &cal.solution.held {
        let _ = writeln!(s, "held: {h}");
    }
    let reg = &cal.registration;
    if reg.unanchored > 0 {
        let _ = writeln!(
            s,
            "{} of {} unanchored views registered",
            reg.registered.len(),
            reg.unanchored
        );
    }
    for u in &reg.unregistered {
        let camera = devices.get(u.camera).map_or("?", |d| d.name.as_str());
        let _ = writeln!(s, "unregistered: {camera} pose {}: {}", u.pose, u.reason);
    }
}

/// Every warning the report counts, then its notes, one line each.
fn warning_lines(s: &mut String, diagnosis: &Diagnosis) {
    for w in &diagnosis.warnings {
        let _ = writeln!(s, "warning: {w}");
    }
    for n in &diagnosis.notes {
        let _ = writeln!(s, "note: {n}");
    }
}

/// "report: PATH (N warnings)" when `files` hold the HTML report.
fn report_line(s: &mut String, diagnosis: &Diagnosis, files: &[PathBuf]) {
    if let Some(page) = files.iter().find(|f| f.ends_with("report.html")) {
        let n = diagnosis.warnings.len();
        let _ = writeln!(
            s,
            "report: {} ({n} warning{})",
            page.display(),
            if n == 1 { "" } else { "s" }
        );
    }
}

/// The summary of a run or of calibrating a dataset: the calibration, the verification, the
/// cameras' agreement on projector pixels, the ground truth of a simulated rig, the run's
/// own warnings, the files written.
pub fn of_run(outcome: &Outcome) -> String {
    let mut s = String::new();
    let cal = &outcome.calibration;
    calibration_lines(&mut s, cal, &outcome.diagnosis, &outcome.devices);
    if !outcome.verification.is_empty() {
        s.push_str(&crate::report::format_verification(&outcome.verification));
    }
    for a in &outcome.agreement {
        let _ = writeln!(
            s,
            "{}: cameras agree on its pixels to {:.4} px RMS per camera ({} camera pairs × circles)",
            outcome.devices[a.projector].name, a.rms, a.pairs
        );
    }
    if !outcome.truth.is_empty() {
        s.push_str("against the simulated rig's ground truth:\n");
        s.push_str(&super::truth::format_truth(&outcome.truth));
    }
    warning_lines(&mut s, &outcome.diagnosis);
    let _ = writeln!(s, "wrote {} files", outcome.files.len());
    report_line(&mut s, &outcome.diagnosis, &outcome.files);
    s
}

/// The summary of calibrating a correspondences file into `out`.
pub fn of_file(done: &FileOutcome, out: &Path) -> String {
    let mut s = String::new();
    let cal = &done.calibration;
    calibration_lines(&mut s, cal, &done.diagnosis, &done.input.devices);
    let _ = writeln!(s, "σ {:.4} px", cal.solution.sigma);
    for (name, px) in done.radtan.iter().filter(|(_, px)| *px > 0.0) {
        let _ = writeln!(
            s,
            "camchain.yaml: {name} refitted to radtan, largest deviation {px:.4} px"
        );
    }
    let _ = writeln!(s, "wrote {} files to {}", done.files.len(), out.display());
    warning_lines(&mut s, &done.diagnosis);
    report_line(&mut s, &done.diagnosis, &done.files);
    s
}
