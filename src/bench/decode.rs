//! `hexcal bench decode`: one camera's default phase-shift stack (synthetic scene, gamma 2.2)
//! decoded, timed and checked against the truth.

use crate::pattern::{ProjectorResponse, ProjectorSetup, Sequence};
use crate::phase::accuracy::{accuracy, ProjectorAccuracy};
use crate::phase::check::{CheckParams, StackSampler};
use crate::phase::{Decoder, FrameRef};
use crate::sim::fringe::{FringeScene, Renderer};

/// Timing of one decode.
#[derive(Clone, Copy, Debug)]
pub struct DecodeRun {
    /// Seconds from the first frame pushed to the decoded maps.
    pub wall_seconds: f64,
    /// CPU seconds (all threads, user + system; Linux, 10 ms ticks) spent in the frame
    /// pushes (copies and per-group DFTs).
    pub push_cpu_seconds: Option<f64>,
    /// CPU seconds spent in `finish` (noise fit, unwrapping, fusion, maps).
    pub finish_cpu_seconds: Option<f64>,
}

/// Figures of one decode benchmark run.
#[derive(Clone, Debug)]
pub struct DecodeBench {
    /// Camera width × height (px).
    pub size: (u32, u32),
    /// Frames in the stack.
    pub frames: usize,
    /// Seconds to render the stack (not part of the decode).
    pub render_seconds: f64,
    /// Each timed decode.
    pub runs: Vec<DecodeRun>,
    /// Each timed decode without the stack check (interleaved with `runs`).
    pub unchecked_runs: Vec<DecodeRun>,
    /// Bytes the decoder holds at its peak (frame buffer + phases + statistics).
    pub decoder_bytes: usize,
    /// Bytes of the decoded maps.
    pub output_bytes: usize,
    /// Growth of the process's peak resident memory over the first decode (bytes; Linux).
    pub peak_growth_bytes: Option<usize>,
    /// Accuracy of the last decode against the ground truth.
    pub accuracy: Vec<ProjectorAccuracy>,
    /// Seconds the stack check takes alone (its frame sampling and its verdict), which
    /// each decode above includes.
    pub check_seconds: f64,
    /// CPU seconds of the same (all threads; Linux).
    pub check_cpu_seconds: Option<f64>,
    /// The last decode's verdict on the (clean) stack.
    pub verdict: crate::phase::check::StackVerdict,
}

/// CPU time of this process so far, user + system (Linux only).
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name: utime and stime are the 12th and 13th.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// A field of /proc/self/status in bytes (Linux only).
fn proc_status_bytes(field: &str) -> Option<usize> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    let kib: usize = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Decode `frames` of `seq` at `size` once, with the stack check when `checked`: the
/// timing, the decoded stack and the decoder's peak buffer bytes.
fn timed_decode(
    seq: &Sequence,
    frames: &[image::GrayImage],
    (width, height): (u32, u32),
    checked: bool,
) -> (DecodeRun, crate::phase::DecodedStack, usize) {
    let cpu0 = process_cpu_seconds();
    let t1 = std::time::Instant::now();
    let mut decoder =
        Decoder::<u8>::new(seq, "bench", width, height, 255.0).expect("a valid frame format");
    if !checked {
        decoder = decoder.without_check();
    }
    let mut bytes = 0;
    for (k, f) in frames.iter().enumerate() {
        // The peak is just before the last frame frees the frame buffer.
        bytes = bytes.max(decoder.buffer_bytes());
        decoder
            .push_frame(k, FrameRef::from(f))
            .expect("frames match the sequence");
    }
    let cpu1 = process_cpu_seconds();
    let decoded = decoder.finish().expect("complete stack");
    let wall_seconds = t1.elapsed().as_secs_f64();
    let cpu2 = process_cpu_seconds();
    let run = DecodeRun {
        wall_seconds,
        push_cpu_seconds: cpu0.zip(cpu1).map(|(a, b)| b - a),
        finish_cpu_seconds: cpu1.zip(cpu2).map(|(a, b)| b - a),
    };
    (run, decoded, bytes)
}

/// Render the default stack of the standard scene (P projectors of 1920×1080 with gamma 2.2
/// uncorrected, default sequence) for a `width` × `height` camera, then decode it
/// `repeats` times, timing each decode, each beside a decode without the stack check.
pub fn bench_decode(width: u32, height: u32, projectors: usize, repeats: usize) -> DecodeBench {
    let setups = vec![
        ProjectorSetup {
            width: 1920,
            height: 1080,
            response: ProjectorResponse::Gamma { gamma: 2.2 },
        };
        projectors
    ];
    let seq = Sequence::default_for(&setups).expect("the default sequence is valid");
    let scene = FringeScene::standard(width, height, &setups, 1);
    let t0 = std::time::Instant::now();
    let mut renderer = Renderer::new(&scene, &seq);
    let frames: Vec<image::GrayImage> = (0..seq.frame_count()).map(|k| renderer.frame(k)).collect();
    let render_seconds = t0.elapsed().as_secs_f64();
    let mut runs = Vec::new();
    let mut unchecked_runs = Vec::new();
    let mut decoder_bytes = 0;
    let mut peak_growth_bytes = None;
    let mut last = None;
    for _ in 0..repeats.max(1) {
        // Free the previous maps before decoding again; without the check first, then with
        // it, under the same conditions.
        drop(last.take());
        let (run, unchecked, _) = timed_decode(&seq, &frames, (width, height), false);
        unchecked_runs.push(run);
        drop(unchecked);
        let before = proc_status_bytes("VmRSS:");
        let (run, decoded, bytes) = timed_decode(&seq, &frames, (width, height), true);
        runs.push(run);
        decoder_bytes = decoder_bytes.max(bytes);
        if peak_growth_bytes.is_none() {
            peak_growth_bytes = before
                .zip(proc_status_bytes("VmHWM:"))
                .map(|(b, h)| h.saturating_sub(b));
        }
        last = Some(decoded);
    }
    let decoded = last.expect("at least one decode");
    let cpu0 = process_cpu_seconds();
    let t2 = std::time::Instant::now();
    let mut sampler = StackSampler::new(&seq, width, height, 255.0);
    for (k, f) in frames.iter().enumerate() {
        sampler.push(k, &FrameRef::from(f));
    }
    drop(sampler.verdict(&CheckParams::default()));
    let check_seconds = t2.elapsed().as_secs_f64();
    let check_cpu_seconds = cpu0.zip(process_cpu_seconds()).map(|(a, b)| b - a);
    let npx = width as usize * height as usize;
    let output_bytes = npx * (4 + 1 + projectors * (4 * 4 + 1));
    let truth = renderer.truth();
    DecodeBench {
        size: (width, height),
        frames: frames.len(),
        render_seconds,
        runs,
        unchecked_runs,
        decoder_bytes,
        output_bytes,
        peak_growth_bytes,
        accuracy: accuracy(&decoded, &truth, &seq),
        check_seconds,
        check_cpu_seconds,
        verdict: decoded.verdict,
    }
}
