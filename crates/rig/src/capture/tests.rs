//! The capture engine on a small simulated rig: frames in order and identical to the
//! simulator's own rendering, faults (a camera that stops, dropped frames, a sink that
//! refuses), datasets written atomically, resumed, and read back with errors naming the
//! camera and frame.

use super::*;
use crate::rig::file::RigFile;
use crate::rig::fixture::tiny;
use crate::rig::sim::{Faults, SimWorld};
use hexcal_core::dataset::{
    CameraEntry, Dataset, DatasetError, DatasetInfo, ProjectorEntry, StackReader,
};
use std::path::Path;
use std::sync::Arc;

fn rig() -> RigFile {
    tiny().parse().unwrap()
}

/// A session on the tiny rig with `faults` on camera 1 and fast timeouts.
fn session(faults: Faults) -> (Session, Arc<SimWorld>, Sequence) {
    let rig = rig();
    let opened = crate::rig::open(&rig).unwrap();
    let world = opened.world.clone().unwrap();
    let (mut cams, projs) = world.devices();
    cams[1].set_faults(faults);
    let cameras: Vec<Box<dyn Camera>> = cams.into_iter().map(|c| Box::new(c) as _).collect();
    let projectors: Vec<Box<dyn Projector>> = projs.into_iter().map(|p| Box::new(p) as _).collect();
    let timing = CaptureTiming {
        frame_timeout: Duration::from_millis(200),
        settle: Duration::ZERO,
        ..opened.devices.timing
    };
    let s = Session::start(
        RigDevices {
            cameras,
            configs: opened.devices.configs,
            projectors,
            trigger: None,
            timing,
        },
        &opened.sequence,
    )
    .unwrap();
    (s, world, opened.sequence)
}

fn pixels8(f: &CameraFrame) -> &[u8] {
    match &f.pixels {
        Pixels::Gray8(p) => p,
        Pixels::Gray16(_) => panic!("8-bit expected"),
    }
}

#[test]
fn frames_arrive_in_order_and_match_the_simulator() {
    let (mut s, world, seq) = session(Faults::default());
    world.place(1);
    let mut got: Vec<(usize, usize, CameraFrame)> = Vec::new();
    let timeline = s
        .capture_pose(1, &mut |f| {
            got.push((f.camera, f.index, f.frame));
            Ok(())
        })
        .unwrap();
    s.finish().unwrap();
    let n = seq.frame_count();
    assert_eq!(got.len(), 2 * n);
    assert_eq!(timeline.frames.len(), n);
    assert_eq!(timeline.dropped, 0);
    // Frame k of every camera, in order; counters consecutive per camera.
    for (i, (c, k, f)) in got.iter().enumerate() {
        assert_eq!((*c, *k), (i % 2, i / 2));
        assert_eq!(f.counter, *k as u64);
        assert_eq!((f.width, f.height, f.bits), (320, 240, 8));
        assert_eq!(f.exposure_us, 10_000.0);
    }
    // Pixel for pixel what the stack renderer gives for that camera, pose and frame.
    for c in 0..2 {
        let r = world_renderer(&world, c, 1, &seq);
        for k in [0, 7, n - 1] {
            let expect: Vec<u8> = r.frame(k).data.iter().map(|&v| v as u8).collect();
            assert_eq!(
                pixels8(&got[2 * k + c].2),
                &expect[..],
                "camera {c} frame {k}"
            );
        }
    }
    // The front camera sees projector light: frames differ.
    assert_ne!(pixels8(&got[0].2), pixels8(&got[2].2));
}

#[test]
fn previews_between_poses_leave_the_capture_as_it_was() {
    let (mut s, world, seq) = session(Faults::default());
    world.place(1);
    let flat = |c: usize, n: u64| -> Vec<u8> {
        let r = world_renderer(&world, c, 1, &seq);
        r.flat_frame(true, n)
            .data
            .iter()
            .map(|&v| v as u8)
            .collect()
    };
    for round in 0..3u64 {
        let frames = s.preview().unwrap();
        assert_eq!(frames.len(), 2);
        for (c, f) in frames.iter().enumerate() {
            assert_eq!(f.counter, round);
            assert_eq!(
                pixels8(f),
                &flat(c, round)[..],
                "camera {c}, preview {round}"
            );
        }
    }
    let mut got: Vec<(usize, usize, CameraFrame)> = Vec::new();
    let timeline = s
        .capture_pose(1, &mut |f| {
            got.push((f.camera, f.index, f.frame));
            Ok(())
        })
        .unwrap();
    assert_eq!(timeline.dropped, 0);
    assert_eq!(got.len(), 2 * seq.frame_count());
    // The pose's frames are those of a capture without previews: pattern k, in order.
    for c in 0..2 {
        let r = world_renderer(&world, c, 1, &seq);
        for (_, k, f) in got.iter().filter(|(cam, ..)| *cam == c) {
            let expect: Vec<u8> = r.frame(*k).data.iter().map(|&v| v as u8).collect();
            assert_eq!(pixels8(f), &expect[..], "camera {c} frame {k}");
            assert_eq!(f.counter, 3 + *k as u64);
        }
    }
    // The projectors went dark after the pose; the next preview lights them again.
    let after = s.preview().unwrap();
    let n = 3 + seq.frame_count() as u64;
    assert_eq!(pixels8(&after[0]), &flat(0, n)[..]);
    s.finish().unwrap();
}

fn world_renderer(
    world: &SimWorld,
    c: usize,
    pose: usize,
    seq: &Sequence,
) -> hexcal_sim::stack::StackRenderer {
    world.stack_renderer(c, pose, seq).unwrap()
}

#[test]
fn a_camera_that_stops_names_itself_the_pose_and_the_frame() {
    let (mut s, world, _) = session(Faults {
        stop_after: Some(5),
        drop_every: None,
    });
    world.place(0);
    let mut delivered = 0;
    let err = s
        .capture_pose(0, &mut |_| {
            delivered += 1;
            Ok(())
        })
        .unwrap_err();
    let text = err.to_string();
    assert!(
        matches!(
            err,
            CaptureError::Frame {
                pose: 0,
                frame: 5,
                ..
            }
        ),
        "{text}"
    );
    assert!(text.contains("back") && text.contains("no frame"), "{text}");
    // Everything before the failing frame was delivered.
    assert_eq!(delivered, 2 * 5);
}

#[test]
fn dropped_frames_are_taken_again() {
    let (mut s, world, seq) = session(Faults {
        stop_after: None,
        drop_every: Some(4),
    });
    world.place(0);
    let mut counters = Vec::new();
    let timeline = s
        .capture_pose(0, &mut |f| {
            if f.camera == 1 {
                counters.push(f.frame.counter);
            }
            Ok(())
        })
        .unwrap();
    let n = seq.frame_count();
    assert_eq!(counters.len(), n);
    // Every 4th exposure was lost and retaken: counters skip those.
    let lost = counters.last().unwrap() + 1 - n as u64;
    assert_eq!(timeline.dropped, lost);
    assert!(lost >= (n as u64) / 4, "{lost}");
    let retries: u32 = timeline.frames.iter().map(|t| t.retries).sum();
    assert_eq!(u64::from(retries), lost);
}

#[test]
fn a_refusing_sink_names_the_camera_and_frame() {
    let (mut s, world, _) = session(Faults::default());
    world.place(0);
    let err = s
        .capture_pose(0, &mut |f| {
            if f.index == 3 {
                Err("No space left on device".into())
            } else {
                Ok(())
            }
        })
        .unwrap_err();
    assert_eq!(
        err.to_string(),
        "pose 0, frame 3, camera front: No space left on device"
    );
}

fn scratch(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("hexcal-capture-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn info(seq: &Sequence) -> DatasetInfo {
    DatasetInfo {
        format: hexcal_core::dataset::FORMAT.into(),
        version: hexcal_core::dataset::VERSION,
        rig: "tiny".into(),
        board: "hex600".into(),
        sequence: seq.clone(),
        cameras: ["front", "back"]
            .map(|name| CameraEntry {
                name: name.into(),
                width: 320,
                height: 240,
                bits: 8,
                pixel_format: None,
            })
            .to_vec(),
        projectors: ["p0", "p1"]
            .map(|name| ProjectorEntry {
                name: name.into(),
                width: 320,
                height: 200,
            })
            .to_vec(),
    }
}

#[test]
fn datasets_keep_complete_poses_and_read_back_exactly() {
    let dir = scratch("resume");
    let (mut s, world, seq) = session(Faults::default());
    let data = Dataset::create_or_resume(&dir, info(&seq)).unwrap();
    // Pose 0 completes; pose 1 is interrupted after 4 frames (a full disk).
    let mut first = Vec::new();
    for (pose, stop) in [(0, None), (1, Some(4))] {
        world.place(pose);
        let mut w = data.pose_writer(pose).unwrap();
        let r = s.capture_pose(pose, &mut |f| {
            if Some(f.index) == stop {
                return Err("disk full".into());
            }
            if pose == 0 && f.camera == 0 {
                first.push(pixels8(&f.frame).to_vec());
            }
            Ok(w.write(&f)?)
        });
        if let Ok(t) = r {
            let info = w.finish(&t).unwrap();
            data.complete(&info).unwrap();
        }
    }
    s.finish().unwrap();
    // Resuming finds pose 0 complete, pose 1 not; no temporary file is left behind.
    let again = Dataset::create_or_resume(&dir, info(&seq)).unwrap();
    assert_eq!(again.completed().unwrap(), vec![0]);
    for pose in [0, 1] {
        for cam in ["front", "back"] {
            for e in std::fs::read_dir(again.stack_dir(pose, cam)).unwrap() {
                let name = e.unwrap().file_name().to_string_lossy().into_owned();
                assert!(!name.starts_with('.'), "temporary file {name} left");
            }
        }
    }
    // Frames read back bit for bit.
    let stack = StackReader::open(&again.stack_dir(0, "front")).unwrap();
    for (k, expect) in first.iter().enumerate() {
        let got: Vec<u8> = stack.frame(k).unwrap().iter().map(|&v| v as u8).collect();
        assert_eq!(&got, expect, "frame {k}");
    }
    // A different capture in the same folder is refused.
    let mut other = info(&seq);
    other.cameras.pop();
    let err = Dataset::create_or_resume(&dir, other).unwrap_err();
    assert!(err.to_string().contains("dataset.json"), "{err}");

    // Broken stacks: a missing frame file, a frame of another size, a short frame list.
    let stack_dir = again.stack_dir(0, "back");
    std::fs::remove_file(stack_dir.join("frame-006.png")).unwrap();
    let err = StackReader::open(&stack_dir).unwrap().frame(6).unwrap_err();
    assert!(
        matches!(&err, DatasetError::Frame { camera, frame: 6, .. } if camera == "back"),
        "{err}"
    );
    image::GrayImage::new(10, 10)
        .save(stack_dir.join("frame-007.png"))
        .unwrap();
    let err = StackReader::open(&stack_dir).unwrap().frame(7).unwrap_err();
    assert!(
        err.to_string().contains("10×10 in a 320×240 stack"),
        "{err}"
    );
    std::fs::write(stack_dir.join("frame-008.png"), b"\x89PNG truncated").unwrap();
    let err = StackReader::open(&stack_dir).unwrap().frame(8).unwrap_err();
    assert!(err.to_string().starts_with("camera back, frame 8"), "{err}");
    let path = stack_dir.join("stack.json");
    let mut text: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    text["frames"].as_array_mut().unwrap().truncate(20);
    std::fs::write(&path, text.to_string()).unwrap();
    let err = StackReader::open(&stack_dir).unwrap_err();
    assert!(
        matches!(&err, DatasetError::Frame { frame: 20, .. }),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn decoded_stack_folders_match_the_projector_truth() {
    // Capture one pose of the front camera to disk, decode the folder, compare the maps
    // with the simulator's projector coordinates.
    let dir = scratch("decode");
    let (mut s, world, seq) = session(Faults::default());
    let data = Dataset::create_or_resume(&dir, info(&seq)).unwrap();
    world.place(0);
    let mut w = data.pose_writer(0).unwrap();
    let t = s.capture_pose(0, &mut |f| Ok(w.write(&f)?)).unwrap();
    data.complete(&w.finish(&t).unwrap()).unwrap();
    s.finish().unwrap();
    let out = dir.join("decoded");
    let (files, summary) =
        hexcal_vision::phase::files::decode_to_files(&data.stack_dir(0, "front"), &out).unwrap();
    assert_eq!(files.len(), 1 + 2 * 5 + 1);
    let truth = world_renderer(&world, 0, 0, &seq);
    let p = &summary.projectors[0];
    assert!(p.valid_fraction > 0.01, "{p:?}");
    // The u map read back from its TIFF against the truth on valid pixels.
    let u = read_tiff(&out.join("projector0-u.tiff"));
    let valid = image::open(out.join("projector0-valid.png"))
        .unwrap()
        .to_luma8();
    // Interior pixels: uniform albedo within ±3 px (≈ 4 PSF σ).
    let (mut sq, mut n) = (0.0, 0usize);
    for (i, (&u, &ok)) in u.iter().zip(valid.as_raw()).enumerate() {
        if ok == 255 && truth.truth(0).lit(i) && truth.uniform_albedo(i, 3) {
            let e = f64::from(u - truth.truth(0).u(i));
            assert!(e.abs() < (6.0 * p.noise.sigma_u).max(1.0), "pixel {i}: {e}");
            sq += e * e;
            n += 1;
        }
    }
    let rms = (sq / n as f64).sqrt();
    eprintln!(
        "{n} interior pixels: u RMS {rms:.3} px, predicted σ_u {:.3}",
        p.noise.sigma_u
    );
    // docs/design.md §6 acceptance: RMS ≤ 1.2 × the predicted σ_u.
    assert!(n > 200 && rms <= 1.2 * p.noise.sigma_u, "{n} px, rms {rms}");
    let _ = std::fs::remove_dir_all(&dir);
}

fn read_tiff(path: &Path) -> Vec<f32> {
    let mut d = tiff::decoder::Decoder::new(std::fs::File::open(path).unwrap()).unwrap();
    match d.read_image().unwrap() {
        tiff::decoder::DecodingResult::F32(v) => v,
        _ => panic!("float TIFF expected"),
    }
}

#[test]
fn the_simulated_controller_on_a_pty_triggers_the_same_frames() {
    // The tiny rig with the trigger controller: the host driver on one end of a pty, the
    // firmware model on the other, its lines wired to the simulated cameras.
    let text = tiny()
        .table("[trigger]\nport = \"sim\"\npulse_us = 100")
        .edit("front", |c| c.with("trigger_line = 0"))
        .edit("back", |c| c.with("trigger_line = 1"))
        .toml();
    let rig = RigFile::parse(&text, "tiny-hw.toml").unwrap();
    let opened = crate::rig::open(&rig).unwrap();
    assert!(opened.devices.trigger.is_some());
    let world = opened.world.clone().unwrap();
    let mut hw = Session::start(opened.devices, &opened.sequence).unwrap();
    world.place(2);
    // A preview frame between poses goes through the controller too (one armed pulse).
    let preview = hw.preview().unwrap();
    assert_eq!(
        preview.iter().map(|f| f.counter).collect::<Vec<_>>(),
        [0, 0]
    );
    let mut frames = Vec::new();
    let timeline = hw
        .capture_pose(2, &mut |f| {
            frames.push(f);
            Ok(())
        })
        .unwrap();
    hw.finish().unwrap();
    let n = opened.sequence.frame_count();
    assert_eq!(frames.len(), 2 * n);
    assert_eq!(timeline.frames.iter().map(|t| t.retries).sum::<u32>(), 0);
    // The same pixels as software triggering gives.
    let (mut sw, world2, _) = session(Faults::default());
    world2.place(2);
    let mut k = 0;
    sw.capture_pose(2, &mut |f| {
        assert_eq!(
            pixels8(&f.frame),
            pixels8(&frames[k].frame),
            "camera {} frame {}",
            f.camera,
            f.index
        );
        k += 1;
        Ok(())
    })
    .unwrap();
    assert_eq!(k, 2 * n);
}

/// RMS and mean of `a − b` over the pixels of a 320-wide frame that `keep` selects.
fn difference(a: &[u8], b: &[u8], keep: impl Fn(usize, usize) -> bool) -> (f64, f64) {
    let d: Vec<f64> = (0..a.len())
        .filter(|&i| keep(i % 320, i / 320))
        .map(|i| f64::from(a[i]) - f64::from(b[i]))
        .collect();
    let n = d.len() as f64;
    (
        (d.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
        d.iter().sum::<f64>() / n,
    )
}

#[test]
fn simulated_bayer_and_mjpeg_cameras_deliver_grey_close_to_the_monochrome_frame() {
    let rig = tiny()
        .edit("front", |c| c.with("format = \"BayerRG\""))
        .edit("back", |c| {
            c.with("format = \"MJPG\"").with("jpeg_quality = 95")
        })
        .parse()
        .unwrap();
    let opened = crate::rig::open(&rig).unwrap();
    let world = opened.world.clone().unwrap();
    let names: Vec<Option<String>> = opened
        .devices
        .cameras
        .iter()
        .map(|c| c.pixel_format())
        .collect();
    assert_eq!(
        names,
        [Some("BayerRG8".into()), Some("MJPG (quality 95)".into())]
    );
    let mut s = Session::start(opened.devices, &opened.sequence).unwrap();
    world.place(1);
    let mut got: Vec<(usize, usize, CameraFrame)> = Vec::new();
    s.capture_pose(1, &mut |f| {
        got.push((f.camera, f.index, f.frame));
        Ok(())
    })
    .unwrap();
    s.finish().unwrap();
    for c in 0..2 {
        let r = world_renderer(&world, c, 1, &opened.sequence);
        for (_, k, f) in got.iter().filter(|g| g.0 == c && g.1 % 5 == 0) {
            let mono: Vec<u8> = r.frame(*k).data.iter().map(|&v| v as u8).collect();
            let grey = pixels8(f);
            if c == 0 {
                // Green pixels respond 1 and keep gain 1: the same noise draw as the
                // monochrome sensor, so the same values.
                let (rms, _) = difference(grey, &mono, |x, y| (x + y) % 2 == 1);
                assert_eq!(rms, 0.0, "frame {k}: green pixels differ");
                // Red and blue (responses 0.6, 0.8) balanced back: unbiased, their noise
                // scaled up by at most 1/0.6 (σ ≤ 5.2 DN at white: < 3.5 DN apart).
                let (rms, mean) = difference(grey, &mono, |x, y| (x + y) % 2 == 0);
                assert!(rms < 3.5 && mean.abs() < 0.5, "frame {k}: {rms} {mean}");
            } else {
                // Quality 95 quantises with steps of 1–5 DN: errors of a DN or two.
                let (rms, mean) = difference(grey, &mono, |_, _| true);
                assert!(rms < 2.5 && mean.abs() < 0.5, "frame {k}: {rms} {mean}");
            }
        }
    }
}
