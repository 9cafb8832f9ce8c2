//! A dataset on a disk that fills up mid-capture (a small tmpfs): the capture stops with an
//! error naming the file, camera and frame; every pose written before reads back bit for
//! bit; no partial, corrupt or temporary file is left; and with room again the capture
//! resumes where it stopped. Needs permission to mount (root, as in CI); without it the test
//! says why and skips.

use hexcal::app::capture::capture_dataset;
use hexcal::dataset::{Dataset, StackReader};
use hexcal::rig::fixture::{tiny, SimRig};
use hexcal::rig::sim::SimWorld;
use std::path::{Path, PathBuf};
use std::process::Command;

/// The tiny rig's front camera and one linear projector (18 frames a pose), ten poses.
fn rig() -> SimRig {
    tiny()
        .named("disk")
        .with("poses.count = 10")
        .with("poses.seed = 5")
        .without(&["back", "p1"])
        .edit("p0", |p| p.with("gamma = 1.0"))
}

const POSES: usize = 10;

/// A tmpfs mounted at a fresh folder, unmounted (and the folder removed) on drop.
struct Tmpfs {
    dir: PathBuf,
}

impl Tmpfs {
    /// Mount a `size` tmpfs, or say why not.
    fn mount(name: &str, size: &str) -> Result<Tmpfs, String> {
        let dir = std::env::temp_dir().join(format!("hexcal-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(&dir)
            .output()
            .map_err(|e| format!("cannot run mount: {e}"))?;
        if !out.status.success() {
            let _ = std::fs::remove_dir(&dir);
            return Err(format!(
                "mount -t tmpfs failed ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ));
        }
        Ok(Tmpfs { dir })
    }

    /// Give it `size` (data kept).
    fn resize(&self, size: &str) {
        let status = Command::new("mount")
            .args(["-o", &format!("remount,size={size}")])
            .arg(&self.dir)
            .status()
            .expect("mount runs");
        assert!(status.success(), "remount {}: {status}", self.dir.display());
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let unmounted = Command::new("umount")
            .arg(&self.dir)
            .status()
            .is_ok_and(|s| s.success());
        if unmounted {
            let _ = std::fs::remove_dir(&self.dir);
        } else {
            eprintln!("warning: could not unmount {}", self.dir.display());
        }
    }
}

/// Every file under `dir`, recursively.
fn files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let path = e.unwrap().path();
        if path.is_dir() {
            out.extend(files(&path));
        } else {
            out.push(path);
        }
    }
    out
}

fn capture(rig: &Path, out: &Path) -> Result<hexcal::app::capture::CaptureSummary, String> {
    capture_dataset(
        &hexcal::app::capture::LoadedRig::load(rig).map_err(|e| e.to_string())?,
        out,
        &hexcal::app::capture::CaptureOptions {
            poses: POSES,
            ..Default::default()
        },
        &mut |k, world| {
            world.expect("a simulated rig").place(k);
            Ok(true)
        },
        &mut |line| eprintln!("{line}"),
    )
    .map_err(|e| e.to_string())
}

/// Every file whole: no temporary file, every PNG decodes, every JSON parses.
fn assert_no_partial_files(root: &Path) {
    for path in files(root) {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert!(
            !name.starts_with('.'),
            "temporary file {} left",
            path.display()
        );
        match path.extension().and_then(|e| e.to_str()) {
            Some("png") => {
                image::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            }
            Some("json") => {
                let text = std::fs::read_to_string(&path).unwrap();
                serde_json::from_str::<serde_json::Value>(&text)
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            }
            _ => {}
        }
    }
}

/// Every frame of each completed pose reads back exactly as the simulator rendered it.
fn assert_poses_read_back(data: &Dataset, world: &SimWorld, poses: &[usize]) {
    for &pose in poses {
        let stack = StackReader::open(&data.stack_dir(pose, "front")).unwrap();
        let renderer = world.stack_renderer(0, pose, &data.info.sequence).unwrap();
        for k in 0..data.info.sequence.frame_count() {
            let got = stack.frame(k).unwrap();
            assert!(
                got == renderer.frame(k).data,
                "pose {pose}, frame {k} does not read back as captured"
            );
        }
    }
}

#[test]
fn a_full_disk_stops_the_capture_naming_file_camera_and_frame_and_loses_nothing() {
    let disk = match Tmpfs::mount("full-disk", "2m") {
        Ok(d) => d,
        Err(why) => {
            eprintln!("skipped: a full disk needs a small tmpfs: {why}");
            return;
        }
    };
    let rig_path = std::env::temp_dir().join(format!("hexcal-disk-{}.toml", std::process::id()));
    std::fs::write(&rig_path, rig().toml()).unwrap();
    let out = disk.dir.join("dataset");

    let err = capture(&rig_path, &out).expect_err("2 MB cannot hold 10 poses");
    eprintln!("{err}");
    assert!(err.contains("No space left on device"), "{err}");
    let data = Dataset::open(&out).unwrap();
    let done = data.completed().unwrap();
    let failed = done.len();
    assert!(failed >= 1, "not even one pose fit: {err}");
    assert_eq!(done, (0..failed).collect::<Vec<_>>(), "{err}");
    // The error names the pose, camera, frame and file of the frame that did not fit (or,
    // when the frames fit and the stack description did not, that file).
    let prefix = format!("pose {failed}, frame ");
    if let Some(rest) = err.strip_prefix(&prefix) {
        let frame: usize = rest.split(',').next().unwrap().parse().unwrap();
        let file = data
            .stack_dir(failed, "front")
            .join(format!("frame-{frame:03}.png"));
        assert!(
            rest.contains(&format!(
                ", camera front: camera front, frame {frame} ({})",
                file.display()
            )),
            "{err}"
        );
    } else {
        let path = data.stack_dir(failed, "front").join("stack.json");
        assert!(err.starts_with(&format!("{}: ", path.display())), "{err}");
    }
    assert!(data.pose(failed).unwrap().is_none());
    assert_no_partial_files(&out);
    let world = SimWorld::new(
        &rig().parse().unwrap(),
        hexcal::board::Board::builtin("hex600").unwrap(),
    )
    .unwrap();
    assert_poses_read_back(&data, &world, &done);

    // Room again: the capture resumes at the pose that failed.
    disk.resize("64m");
    let summary = capture(&rig_path, &out).expect("resumes");
    assert_eq!(summary.skipped, done);
    assert_eq!(summary.captured, (failed..POSES).collect::<Vec<_>>());
    let all: Vec<usize> = (0..POSES).collect();
    assert_eq!(data.completed().unwrap(), all);
    assert_no_partial_files(&out);
    assert_poses_read_back(&data, &world, &all);
    let _ = std::fs::remove_file(&rig_path);
}

#[test]
fn a_frame_written_to_a_full_disk_is_an_error_and_leaves_no_file() {
    use hexcal::dataset::StackFrame;
    use hexcal::dataset::{CameraEntry, DatasetInfo, ProjectorEntry};
    use hexcal::images::{CameraFrame, Pixels};
    let disk = match Tmpfs::mount("full-frame", "256k") {
        Ok(d) => d,
        Err(why) => {
            eprintln!("skipped: a full disk needs a small tmpfs: {why}");
            return;
        }
    };
    let rig = rig().parse().unwrap();
    let sequence = rig.sequence().unwrap();
    let info = DatasetInfo {
        format: hexcal::dataset::FORMAT.into(),
        version: hexcal::dataset::VERSION,
        rig: "disk".into(),
        board: "hex600".into(),
        sequence,
        cameras: vec![CameraEntry {
            name: "small".into(),
            width: 16,
            height: 16,
            bits: 8,
            pixel_format: None,
        }],
        projectors: vec![ProjectorEntry {
            name: "p0".into(),
            width: 320,
            height: 200,
        }],
    };
    let data = Dataset::create_or_resume(&disk.dir, info).unwrap();
    let mut writer = data.pose_writer(0).unwrap();
    // Fill the disk to the last byte.
    let filler = disk.dir.join("filler");
    let mut f = std::fs::File::create(&filler).unwrap();
    let chunk = vec![0u8; 4096];
    while std::io::Write::write_all(&mut f, &chunk).is_ok() {}
    while std::io::Write::write_all(&mut f, &[0]).is_ok() {}
    drop(f);
    // A frame small enough to sit in any write buffer until the file is closed.
    let frame = StackFrame {
        camera: 0,
        index: 0,
        frame: CameraFrame {
            width: 16,
            height: 16,
            bits: 8,
            pixels: Pixels::Gray8((0..=255).collect()),
            counter: 0,
            timestamp_ns: 0,
            exposure_us: 1000.0,
        },
    };
    let path = data.stack_dir(0, "small").join("frame-000.png");
    let err = writer.write(&frame).expect_err("no room for the frame");
    assert_eq!(
        err.to_string(),
        format!(
            "camera small, frame 0 ({}): No space left on device (os error 28)",
            path.display()
        )
    );
    assert!(!path.exists(), "a frame file was left on a full disk");
    assert_no_partial_files(&disk.dir);
}
