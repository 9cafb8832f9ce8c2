//! `hexcal bench capture`, `bench aravis`, `bench window`: the capture engine on a simulated
//! rig, the loopback GigE Vision camera's frame rate and a window projector's slide time.

use crate::app::AppError;
use crate::capture::Session;
use std::fmt::Write as _;
use std::path::Path;

/// `hexcal bench capture`: one pose of the simulated rig at `rig_path` through the capture
/// engine, frames discarded; gives its timeline.
pub fn bench_capture(rig_path: &Path) -> Result<String, AppError> {
    let rig = crate::rig::file::RigFile::load(rig_path)?;
    let opened = crate::rig::open(&rig)?;
    let world = opened
        .world
        .clone()
        .ok_or_else(|| AppError::Input("bench capture needs a simulated rig".into()))?;
    let cameras = opened.devices.cameras.len();
    let mut session = Session::start(opened.devices, &opened.sequence)?;
    let mut out = format!(
        "rig {}: {cameras} cameras, {} projectors, {} frames per pose, {} threads",
        rig.name,
        opened.sequence.projectors().len(),
        opened.sequence.frame_count(),
        rayon::current_num_threads()
    );
    out.push('\n');
    world.place(0);
    let timeline = session.capture_pose(0, &mut |f| {
        std::hint::black_box(f);
        Ok(())
    })?;
    session.finish()?;
    let _ = writeln!(out, "pose 0: {}", timeline.summary(cameras));
    let frames: Vec<String> = timeline
        .frames
        .iter()
        .take(3)
        .map(|t| {
            format!(
                "frame {}: shown {:.1} ms, triggered {:.1} ms, collected {:.1} ms",
                t.index,
                1e3 * t.shown.as_secs_f64(),
                1e3 * t.triggered.as_secs_f64(),
                1e3 * t.collected.as_secs_f64()
            )
        })
        .collect();
    let _ = writeln!(out, "timeline (first frames): {}", frames.join("; "));
    Ok(out)
}

/// `hexcal bench aravis`: the loopback GigE Vision camera's frame rate.
pub fn bench_aravis(width: u32, height: u32, bits: u8, frames: usize) -> Result<String, AppError> {
    #[cfg(feature = "loopback")]
    {
        let b = crate::rig::aravis::loopback::bench_loopback(width, height, bits, frames)
            .map_err(crate::capture::CaptureError::from)?;
        Ok(b.to_string())
    }
    #[cfg(not(feature = "loopback"))]
    {
        let _ = (width, height, bits, frames);
        Err(AppError::Input(
            "built without the loopback feature: cargo run --release --features bench,loopback -- bench aravis".into(),
        ))
    }
}

/// `hexcal bench window`: time from `show` to the slide drawn, on a monitor of `$DISPLAY`.
pub fn bench_window(monitor: Option<&str>, slides: usize) -> Result<String, AppError> {
    #[cfg(feature = "window")]
    {
        let b = crate::rig::window::bench_show(monitor, slides)
            .map_err(crate::capture::CaptureError::from)?;
        Ok(b.to_string())
    }
    #[cfg(not(feature = "window"))]
    {
        let _ = (monitor, slides);
        Err(AppError::Input(
            "built without the window feature: cargo run --release --features window -- bench window".into(),
        ))
    }
}
