//! One writer per folder (issue 33, item 1): while a `hexcal run` holds its `--out` folder, a
//! second run, a capture or a calibration into the same folder is refused in one line naming
//! the folder and the process holding it; a killed holder leaves no stale lock.

use hexcal::calib::synthetic::SyntheticRig;
use hexcal::lock::FolderLock;
use hexcal::observations::Correspondences;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

/// The repository's tiny simulated rig.
fn rig() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/rigs/sim-tiny.toml")
}

fn hexcal(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("hexcal runs")
}

/// A run that opens the rig, locks `out` and then waits for the operator's Enter (stdin
/// stays open); returned once it asks for the first pose.
fn waiting_run(out: &Path) -> Child {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["run", "--rig", rig().to_str().unwrap(), "--out"])
        .arg(out)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("hexcal runs");
    let stderr = BufReader::new(child.stderr.take().unwrap());
    for line in stderr.lines() {
        let line = line.unwrap();
        if line.contains("press Enter") {
            return child;
        }
    }
    let _ = child.kill();
    let status = child.wait();
    panic!("the run ended before asking for a pose: {status:?}");
}

#[test]
fn a_second_job_on_a_held_folder_is_refused_naming_the_holder() {
    let dir = std::env::temp_dir().join(format!("hexcal-folder-lock-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.join("data");
    let mut first = waiting_run(&out);
    let holder = format!("process {}", first.id());
    let out_s = out.to_str().unwrap();
    let rig = rig();
    let rig_s = rig.to_str().unwrap();
    // A correspondences file that calibrates: refused only for the folder.
    let synthetic = SyntheticRig::paper(4, 0.1, 7);
    let input = dir.join("correspondences.json");
    let c = Correspondences {
        board: "hex600".into(),
        devices: synthetic.device_infos(),
        poses: synthetic.boards.len(),
        views: synthetic.views(),
    };
    std::fs::write(&input, serde_json::to_string(&c).unwrap()).unwrap();
    let input_s = input.to_str().unwrap();
    let jobs: [&[&str]; 3] = [
        &["run", "--rig", rig_s, "--out", out_s, "--auto"],
        &[
            "capture", "--rig", rig_s, "--out", out_s, "--auto", "--poses", "1",
        ],
        &["calibrate", input_s, "--out", out_s],
    ];
    for args in jobs {
        let o = hexcal(args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {stderr}");
        assert_eq!(stderr.lines().count(), 1, "{args:?}: one line: {stderr}");
        assert!(
            stderr.contains(out_s) && stderr.contains(&holder),
            "{args:?} names the folder and {holder}: {stderr}"
        );
    }
    // The holder's files were left alone: its dataset is still there, its run still waits.
    assert!(out.join("dataset.json").exists());
    assert!(first.try_wait().unwrap().is_none(), "the first run goes on");
    // SIGKILL: the kernel releases the lock with the process.
    first.kill().unwrap();
    first.wait().unwrap();
    let lock = FolderLock::acquire(&out).expect("no stale lock after a kill");
    drop(lock);
    std::fs::remove_dir_all(&dir).unwrap();
}
