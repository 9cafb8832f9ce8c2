//! `hexcal calibrate`: a dataset folder's views (or its stacks, decoded) or a
//! correspondences file to a calibration, verified on held-out poses, with every output file.

use super::process::{process_stored, PoseViews};
use super::progress::{Event, Outcome};
use super::AppError;
use crate::board::Board;
use crate::calib::bundle::Device;
use crate::calib::diagnostics::{Diagnosis, Target};
use crate::calib::geometric::{calibrate_registering, GeometricParams};
pub use crate::calib::solve::CalibrateOptions;
use crate::calib::solve::Calibration;
use crate::calib::verify::{verify, verify_with_noise, Verification};
use crate::dataset::{Dataset, DatasetInfo};
use crate::observations::CameraView;
use crate::observations::DeviceKind;
use crate::observations::{Correspondences, DeviceInfo};
use std::path::{Path, PathBuf};

/// Board poses a calibration needs: a device sees one side of the board per pose, and
/// Zhang's start needs [`crate::calib::zhang::MIN_VIEWS`] views.
pub const MIN_CALIBRATION_POSES: usize = crate::calib::zhang::MIN_VIEWS;

pub(crate) fn devices_of(info: &DatasetInfo) -> Vec<DeviceInfo> {
    let cameras = info
        .cameras
        .iter()
        .map(|c| (c.name.as_str(), c.width, c.height));
    let projectors = info
        .projectors
        .iter()
        .map(|p| (p.name.as_str(), p.width, p.height));
    devices(cameras, projectors)
}

/// The devices of a rig file (cameras, then projectors), as its dataset will list them.
pub fn devices_of_rig(rig: &crate::rig::file::RigFile) -> Vec<DeviceInfo> {
    let cameras = rig
        .cameras
        .iter()
        .map(|c| (c.name.as_str(), c.width, c.height));
    let projectors = rig
        .projectors
        .iter()
        .map(|p| (p.name.as_str(), p.width, p.height));
    devices(cameras, projectors)
}

/// Cameras, then projectors, from their (name, width, height).
fn devices<'a>(
    cameras: impl Iterator<Item = (&'a str, u32, u32)>,
    projectors: impl Iterator<Item = (&'a str, u32, u32)>,
) -> Vec<DeviceInfo> {
    let kinds = cameras
        .map(|c| (DeviceKind::Camera, c))
        .chain(projectors.map(|p| (DeviceKind::Projector, p)));
    kinds
        .map(|(kind, (name, width, height))| DeviceInfo {
            name: name.into(),
            kind,
            width,
            height,
        })
        .collect()
}

/// Every pose's views, with what they refer to.
pub(crate) struct Collected<'a> {
    pub(crate) board: &'a Board,
    pub(crate) devices: &'a [DeviceInfo],
    /// Per pose (renumbered from 0), its views if it has any.
    pub(crate) all: &'a [Option<PoseViews>],
    /// First held-out pose.
    pub(crate) held_from: usize,
    /// Device pairs ("first,second") to export as stereo pairs.
    pub(crate) stereo: &'a [String],
    /// What the user needs: the warnings are judged against it.
    pub(crate) target: Target,
    /// The rig's self-tests recorded in the dataset.
    pub(crate) self_tests: Vec<super::check::SelfTests>,
}

/// One line per stack of `all` that the decoder repaired ("pose 2, camera cam0: repaired:
/// …"), for the report's notes: the stack was used, the rig wants a look.
fn repaired_stacks(all: &[Option<PoseViews>]) -> impl Iterator<Item = String> + '_ {
    all.iter().flatten().flat_map(|p| {
        p.stacks.iter().flat_map(move |s| {
            (s.verdict.iter().flat_map(|v| &v.notes))
                .filter(|n| matches!(n, crate::phase::check::StackNote::Repaired { .. }))
                .map(move |n| format!("pose {}, camera {}: {}", p.pose, s.camera, n.describe()))
        })
    })
}

/// Calibrate from the views of `all` poses (those from `held_from` on are held out and
/// verified), write the outputs to `dir`.
pub(crate) fn finish(
    c: Collected,
    dir: &Path,
    options: &CalibrateOptions,
    warnings: &[String],
    events: &mut dyn FnMut(&Event),
) -> Result<Outcome, AppError> {
    let Collected {
        board,
        devices,
        all,
        held_from,
        stereo,
        target,
        self_tests,
    } = c;
    let views_of = |range: std::ops::Range<usize>| -> Vec<CameraView> {
        all[range]
            .iter()
            .flatten()
            .flat_map(|p| p.stacks.iter().filter_map(|s| s.view.clone()))
            .collect()
    };
    let used = views_of(0..held_from.min(all.len()));
    let held = views_of(held_from.min(all.len())..all.len());
    events(&Event::Calibrating { views: used.len() });
    let geometric = GeometricParams::default();
    let poses = held_from.min(all.len());
    let cal = calibrate_registering(board, devices, poses, &used, options, &geometric)?;
    let Verification {
        checks: verification,
        skipped,
    } = verify_held_out(board, &cal, &held, held_from);
    let mut warnings = warnings.to_vec();
    warnings.extend(self_tests.iter().flat_map(|t| t.warnings()));
    warnings.extend(skipped.iter().map(|s| format!("verification: {s}")));
    let warnings = &warnings[..];
    let mut diagnosis = Diagnosis::of(&cal, &verification, warnings, &target);
    diagnosis.notes.extend(repaired_stacks(all));
    std::fs::create_dir_all(dir).map_err(AppError::io(dir))?;
    let mut files = crate::report::write_outputs(&cal, &diagnosis.rows, dir, stereo)?.files;
    if !held.is_empty() {
        let path = dir.join(HELD_OUT_FILE);
        let board_value = board_in_folder(board, dir)?;
        let text = held_out_file(&board_value, devices, &held, held_from, all.len());
        crate::atomic::write(&path, text.as_bytes()).map_err(AppError::io(&path))?;
        files.push(path);
    }
    let text = crate::report::format_verification(&verification);
    let path = dir.join("verification.txt");
    crate::atomic::write(&path, text.as_bytes()).map_err(AppError::io(&path))?;
    files.push(path);
    let path = dir.join("report.html");
    crate::report::html::write_html(
        &crate::report::html::ReportInput {
            calibration: &cal,
            verification: &verification,
            title: &format!("hexcal calibration: {}", dir.display()),
            diagnosis: &diagnosis,
            self_tests: &self_tests.iter().map(|t| t.to_string()).collect::<Vec<_>>(),
        },
        &path,
    )?;
    files.push(path);
    let length_rms = crate::report::verification_rms(&verification);
    events(&Event::Finished {
        sigma: cal.solution.sigma,
        length_rms,
        out: dir.display().to_string(),
    });
    Ok(Outcome {
        devices: devices.to_vec(),
        calibration: cal,
        verification,
        files,
        timelines: Vec::new(),
        warnings: warnings.to_vec(),
        diagnosis,
        truth: Vec::new(),
        agreement: crate::correspond::agreement(&used),
    })
}

/// The file in a calibration folder that holds the held-out poses' views, for
/// `hexcal verify DIR`.
pub const HELD_OUT_FILE: &str = "held-out.json";

/// The name of the board file a board file written into `dir` is known by.
pub const BOARD_FILE: &str = "board.toml";

/// The `board` value a file written into `dir` gives for `board`: a built-in board's name,
/// else [`BOARD_FILE`], written into `dir` (files name boards inside their own folder).
pub fn board_in_folder(board: &Board, dir: &Path) -> Result<String, AppError> {
    if Board::builtin(&board.name).as_ref() == Some(board) {
        return Ok(board.name.clone());
    }
    let path = dir.join(BOARD_FILE);
    crate::atomic::write(&path, board.to_toml().as_bytes()).map_err(AppError::io(&path))?;
    Ok(BOARD_FILE.into())
}

/// The held-out views as a correspondences file (devices as given, poses renumbered from 0;
/// `board` the board value, [`board_in_folder`]).
fn held_out_file(
    board: &str,
    devices: &[DeviceInfo],
    held: &[CameraView],
    held_from: usize,
    poses: usize,
) -> String {
    let views = held
        .iter()
        .map(|v| CameraView {
            pose: v.pose - held_from,
            ..v.clone()
        })
        .collect();
    let c = Correspondences {
        board: board.to_owned(),
        devices: devices.to_vec(),
        poses: poses - held_from,
        views,
    };
    serde_json::to_string(&c).expect("plain data serialises")
}

/// Verify held-out views against the calibrated devices (views re-indexed to the kept
/// devices; poses renumbered from 0 for the check, then named by their index in the run).
fn verify_held_out(
    board: &Board,
    cal: &Calibration,
    held: &[CameraView],
    held_from: usize,
) -> Verification {
    let kept = |d: usize| cal.device_index.iter().position(|&i| i == d);
    let views: Vec<CameraView> = held
        .iter()
        .filter_map(|v| {
            let mut v = v.clone();
            v.camera = kept(v.camera)?;
            v.pose -= held_from;
            for p in &mut v.points {
                p.projectors.retain_mut(|q| match kept(q.projector) {
                    Some(i) => {
                        q.projector = i;
                        true
                    }
                    None => false,
                });
            }
            Some(v)
        })
        .collect();
    let devices: Vec<Device> = cal.devices.clone();
    // Each check names its pose as the run numbered it (the held-out poses' real index).
    let noise = crate::calib::diagnostics::observation_noise(cal);
    let mut verification = verify_with_noise(board, &devices, &views, &noise);
    for k in &mut verification.checks {
        k.pose += held_from;
    }
    for k in &mut verification.skipped {
        k.pose += held_from;
    }
    verification
}

/// `hexcal calibrate DATASET`: every complete pose's views (from `views.json`, or decoded
/// from its stacks), calibrated with `options` and the last `held_out` poses verified;
/// outputs in `out`.
pub fn calibrate_dataset(
    root: &Path,
    out: &Path,
    held_out: usize,
    options: &CalibrateOptions,
    (stereo, target): (&[String], Target),
    events: &mut dyn FnMut(&Event),
) -> Result<Outcome, AppError> {
    let data = Dataset::open(root)?;
    let board = Board::resolve_in(&data.info.board, &root.join("dataset.json"), "board")?;
    let devices = devices_of(&data.info);
    check_stereo(stereo, &devices)?;
    let poses = data.completed()?;
    if poses.is_empty() {
        return Err(AppError::Input(format!(
            "{}: no complete pose",
            root.display()
        )));
    }
    check_held_out(poses.len(), held_out)?;
    let _lock = crate::lock::FolderLock::acquire(out)?;
    // Renumber the complete poses 0…n−1 in order.
    let mut all = Vec::new();
    let mut warnings = Vec::new();
    for (i, &k) in poses.iter().enumerate() {
        if options.bundle.stop.requested() {
            return Err(crate::calib::CalibError::Stopped.into());
        }
        let views = match data.read_pose_file::<PoseViews>(k, "views.json")? {
            Some(v) => v,
            None => process_stored(&data, &board, k),
        };
        for s in &views.stacks {
            if let Some(e) = &s.error {
                warnings.push(format!("pose {k}, camera {}: {e}", s.camera));
            }
        }
        let mut views = views;
        views.pose = i;
        for s in &mut views.stacks {
            if let Some(v) = &mut s.view {
                v.pose = i;
            }
        }
        all.push(Some(views));
    }
    let held_from = all.len().saturating_sub(held_out);
    finish(
        Collected {
            board: &board,
            devices: &devices,
            all: &all,
            held_from,
            stereo,
            target,
            self_tests: super::check::read_records(
                &data.root().join(super::check::SELF_TESTS_FILE),
            )?,
        },
        out,
        options,
        &warnings,
        events,
    )
}

/// What calibrating a correspondences file gave.
pub struct FileOutcome {
    /// The correspondences.
    pub input: Correspondences,
    /// The calibration.
    pub calibration: Calibration,
    /// Its residual table and warnings.
    pub diagnosis: Diagnosis,
    /// Files written.
    pub files: Vec<PathBuf>,
    /// Per device, the Kalibr radtan refit's largest deviation from the full model (px).
    pub radtan: Vec<(String, f64)>,
}

/// Read a correspondences file (README: "A correspondences file").
pub fn read_correspondences(path: &Path) -> Result<Correspondences, AppError> {
    let text = crate::limits::read_text(path).map_err(AppError::io(path))?;
    let c: Correspondences = serde_json::from_str(&text).map_err(|source| AppError::Json {
        path: path.to_owned(),
        what: "correspondences file",
        source,
    })?;
    c.check().map_err(|e| AppError::Invalid(e.in_file(path)))?;
    Ok(c)
}

/// The board a correspondences file names, its views checked against it (none on the back
/// of a single-sided board); errors name `path`.
fn board_of(c: &Correspondences, path: &Path) -> Result<Board, AppError> {
    let board = Board::resolve_in(&c.board, path, "board")?;
    crate::observations::check_sides(&board, &c.views)
        .map_err(|e| AppError::Invalid(e.in_file(path)))?;
    Ok(board)
}

/// Refuses `held_out` poses of `poses` when fewer than [`MIN_CALIBRATION_POSES`] remain to
/// calibrate (checked before a capture starts).
pub fn check_held_out(poses: usize, held_out: usize) -> Result<(), AppError> {
    let left = poses.saturating_sub(held_out);
    if left < MIN_CALIBRATION_POSES {
        return Err(AppError::Input(format!(
            "--held-out {held_out} leaves {left} calibration pose{} of {poses}: at least \
             {MIN_CALIBRATION_POSES} needed (every device needs {MIN_CALIBRATION_POSES} views)",
            if left == 1 { "" } else { "s" }
        )));
    }
    Ok(())
}

/// The index of the device called `name` among `names`, for `--reference`.
pub fn device_index<'a>(
    input: &Path,
    mut names: impl Iterator<Item = &'a str>,
    name: &str,
) -> Result<usize, AppError> {
    names
        .position(|d| d == name)
        .ok_or_else(|| AppError::Input(format!("{}: no device named {name:?}", input.display())))
}

/// `hexcal calibrate CORRESPONDENCES.json`: calibrate every device, write the outputs and
/// the report to `out`; `reference` names the gauge device, `stereo` the pairs to export.
pub fn calibrate_file(
    input: &Path,
    out: &Path,
    reference: Option<&str>,
    mut options: CalibrateOptions,
    stereo: &[String],
    target: &Target,
) -> Result<FileOutcome, AppError> {
    let c = read_correspondences(input)?;
    check_stereo(stereo, &c.devices)?;
    let board = board_of(&c, input)?;
    let _lock = crate::lock::FolderLock::acquire(out)?;
    if let Some(name) = reference {
        let names = c.devices.iter().map(|d| d.name.as_str());
        options.bundle.reference = device_index(input, names, name)?;
    }
    let geometric = GeometricParams::default();
    let cal = calibrate_registering(&board, &c.devices, c.poses, &c.views, &options, &geometric)?;
    let diagnosis = Diagnosis::of(&cal, &[], &[], target);
    let written = crate::report::write_outputs(&cal, &diagnosis.rows, out, stereo)?;
    let mut files = written.files;
    let html = out.join("report.html");
    crate::report::html::write_html(
        &crate::report::html::ReportInput {
            calibration: &cal,
            verification: &[],
            title: &format!("hexcal calibration of {}", input.display()),
            diagnosis: &diagnosis,
            self_tests: &[],
        },
        &html,
    )?;
    files.push(html);
    Ok(FileOutcome {
        input: c,
        calibration: cal,
        diagnosis,
        files,
        radtan: written.radtan,
    })
}

/// `hexcal verify INPUT [--calibration FILE]`: INPUT is a correspondences file (then
/// `calibration` is needed), a calibration folder or a run's folder (its `calibration/`);
/// a folder gives its [`HELD_OUT_FILE`] and, unless `calibration` names another, its
/// `calibration.json`.
pub fn verify_input(input: &Path, calibration: Option<&Path>) -> Result<Verification, AppError> {
    if !input.is_dir() {
        let calibration = calibration.ok_or_else(|| {
            AppError::Input(format!(
                "{}: --calibration FILE is needed with a correspondences file (or give a \
                 calibration or run folder)",
                input.display()
            ))
        })?;
        return verify_file(calibration, input);
    }
    let dir = match input.join("calibration").join("calibration.json").exists() {
        true => input.join("calibration"),
        false => input.to_owned(),
    };
    let held = dir.join(HELD_OUT_FILE);
    if !held.exists() {
        return Err(AppError::Input(format!(
            "{}: no {HELD_OUT_FILE} (is it a calibration or run folder, calibrated with \
             --held-out 1 or more?)",
            input.display()
        )));
    }
    let own = dir.join("calibration.json");
    verify_file(calibration.unwrap_or(&own), &held)
}

/// The held-out poses of the correspondences file `input` triangulated with the devices of
/// the calibration file `calibration`; refused when no pair gives figures (naming why each
/// pair gave none).
pub fn verify_file(calibration: &Path, input: &Path) -> Result<Verification, AppError> {
    let text = crate::limits::read_text(calibration).map_err(AppError::io(calibration))?;
    let cal = crate::report::CalibrationFile::from_json(&text, &calibration.display().to_string())?;
    let c = read_correspondences(input)?;
    let devices = c
        .devices
        .iter()
        .map(|d| {
            let r = cal
                .devices
                .iter()
                .find(|r| r.name == d.name)
                .ok_or_else(|| {
                    AppError::Input(format!(
                        "{}: device {:?} is not in {}",
                        input.display(),
                        d.name,
                        calibration.display()
                    ))
                })?;
            Ok(Device {
                name: r.name.clone(),
                kind: r.kind,
                model: r.model(),
                pose: r.pose.isometry(),
            })
        })
        .collect::<Result<Vec<_>, AppError>>()?;
    let board = board_of(&c, input)?;
    let verification = verify(&board, &devices, &c.views);
    if verification.checks.is_empty() {
        let why = match verification.skipped.first() {
            None => "no device pair shares ten circles of a pose".to_string(),
            Some(first) => format!(
                "no device pair gives figures with the devices of {} ({} pairs; {first})",
                calibration.display(),
                verification.skipped.len()
            ),
        };
        return Err(AppError::Input(format!("{}: {why}", input.display())));
    }
    Ok(verification)
}

/// The devices of the dataset at `out` (of `hexcal run`) that its calibration
/// (`out/calibration/calibration.json`) lacks.
pub fn uncalibrated(out: &Path) -> Result<Vec<String>, AppError> {
    let data = Dataset::open(out)?;
    let path = out.join("calibration").join("calibration.json");
    let text = crate::limits::read_text(&path).map_err(AppError::io(&path))?;
    let cal = crate::report::CalibrationFile::from_json(&text, &path.display().to_string())?;
    Ok(devices_of(&data.info)
        .into_iter()
        .filter(|d| !cal.devices.iter().any(|c| c.name == d.name))
        .map(|d| d.name)
        .collect())
}

/// What `hexcal calibrate` gave: its printed summary and the devices left uncalibrated.
#[derive(Debug)]
pub struct Calibrated {
    /// The summary ([`super::summary`]).
    pub summary: String,
    /// Devices the calibration left out.
    pub uncalibrated: Vec<String>,
}

/// `hexcal calibrate`: a dataset folder (its last `held_out` poses held out; `events` hears
/// the progress) or a correspondences file to a calibration in `out`; `reference` names the
/// gauge device, `stereo` the pairs to export, `target` what the user needs (the warnings
/// are judged against it).
pub fn calibrate_input(
    input: &Path,
    out: &Path,
    reference: Option<&str>,
    mut options: CalibrateOptions,
    (held_out, stereo, target): (usize, &[String], Target),
    events: &mut dyn FnMut(&Event),
) -> Result<Calibrated, AppError> {
    if input.is_dir() && !input.join("dataset.json").exists() {
        return Err(AppError::Input(format!(
            "{}: not a hexcal dataset (no dataset.json): give a folder `hexcal run` or \
             `hexcal capture` wrote (dataset.json and its pose-KKK folders), or a \
             correspondences file (docs/dataset.md)",
            input.display()
        )));
    }
    if !input.is_dir() {
        let done = calibrate_file(input, out, reference, options, stereo, &target)?;
        return Ok(Calibrated {
            summary: super::summary::of_file(&done, out),
            uncalibrated: excluded(&done.calibration),
        });
    }
    if let Some(name) = reference {
        let data = Dataset::open(input)?;
        let names = devices_of(&data.info).into_iter().map(|d| d.name);
        let names: Vec<String> = names.collect();
        options.bundle.reference = device_index(input, names.iter().map(String::as_str), name)?;
    }
    let outcome = calibrate_dataset(input, out, held_out, &options, (stereo, target), events)?;
    Ok(Calibrated {
        summary: super::summary::of_run(&outcome),
        uncalibrated: excluded(&outcome.calibration),
    })
}

/// Every `--stereo FIRST,SECOND` pair names two different devices of `devices`: checked
/// before anything is captured or calibrated, naming the valid names.
pub fn check_stereo(stereo: &[String], devices: &[DeviceInfo]) -> Result<(), AppError> {
    let names: Vec<&str> = devices.iter().map(|d| d.name.as_str()).collect();
    for pair in stereo {
        let Some((a, b)) = pair.split_once(',').map(|(a, b)| (a.trim(), b.trim())) else {
            return Err(AppError::Input(format!(
                "--stereo {pair}: give two device names as FIRST,SECOND"
            )));
        };
        for name in [a, b] {
            if !names.contains(&name) {
                return Err(AppError::Input(format!(
                    "--stereo {pair}: no device {name:?}; the devices are {}",
                    names.join(", ")
                )));
            }
        }
        if a == b {
            return Err(AppError::Input(format!(
                "--stereo {pair}: a device cannot pair with itself"
            )));
        }
    }
    Ok(())
}

/// The user's target from `hexcal calibrate --target-px --target-mm`, checked.
pub fn target(uncertainty_px: f64, length_mm: f64) -> Result<Target, AppError> {
    if !(uncertainty_px.is_finite() && uncertainty_px > 0.0 && uncertainty_px <= 100.0) {
        return Err(AppError::Input(format!(
            "--target-px {uncertainty_px}: a projection uncertainty, 0 < u ≤ 100 px"
        )));
    }
    if !(length_mm.is_finite() && length_mm > 0.0 && length_mm <= 1000.0) {
        return Err(AppError::Input(format!(
            "--target-mm {length_mm}: a length error, 0 < t ≤ 1000 mm"
        )));
    }
    Ok(Target {
        uncertainty_px,
        length_mm,
    })
}

/// The names of the devices `cal` left out.
fn excluded(cal: &Calibration) -> Vec<String> {
    cal.excluded.iter().map(|e| e.name.clone()).collect()
}

/// `hexcal verify`: [`verify_input`]'s checks as the verification table.
pub fn verification_table(input: &Path, calibration: Option<&Path>) -> Result<String, AppError> {
    let verification = verify_input(input, calibration)?;
    let mut table = crate::report::format_verification(&verification.checks);
    for skipped in &verification.skipped {
        table += &format!("note: {skipped}\n");
    }
    Ok(table)
}
