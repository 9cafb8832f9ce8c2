//! `hexcal bench check`: the stack check's false alarms on clean simulated stacks of varied
//! scenes (docs/design.md §6b): projectors (1–3, gamma uncorrected, linearised or linear),
//! image size, light levels, ambient, noise, blur and dark albedo drawn per stack.

use crate::pattern::{ProjectorResponse, ProjectorSetup, Sequence};
use crate::phase::{Decoder, FrameRef};
use crate::sim::fringe::{FringeScene, Renderer};
use rand::{Rng, SeedableRng};

/// What the clean stacks gave.
#[derive(Clone, Debug, Default)]
pub struct CheckBench {
    /// Stacks decoded.
    pub stacks: usize,
    /// Stacks the check refused, with the scene and the faults named.
    pub refused: Vec<String>,
    /// Stacks with a note (harmless), with the notes.
    pub noted: Vec<String>,
    /// Seconds in all (rendering and decoding).
    pub seconds: f64,
}

/// Decode `stacks` clean stacks of scenes drawn from `seed`, from stack `from` on (the scenes
/// before it drawn, not decoded: one stack can be looked at again alone), and count the
/// check's verdicts.
pub fn bench_check(stacks: usize, seed: u64, from: usize) -> CheckBench {
    let t = std::time::Instant::now();
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut out = CheckBench::default();
    for i in 0..from + stacks {
        let (scene, seq, label) = draw(&mut rng, i as u64);
        if i < from {
            continue;
        }
        let mut renderer = Renderer::new(&scene, &seq);
        let mut decoder = Decoder::<u8>::new(&seq, "bench", scene.width, scene.height, 255.0)
            .expect("a valid frame format");
        for k in 0..seq.frame_count() {
            let frame = renderer.frame(k);
            decoder
                .push_frame(k, FrameRef::from(&frame))
                .expect("frames match the sequence");
        }
        let verdict = decoder.finish().expect("complete stack").verdict;
        if !verdict.passed() {
            out.refused.push(format!("{label}: {}", verdict.summary()));
        }
        if !verdict.notes.is_empty() {
            let notes: Vec<String> = verdict.notes.iter().map(|n| n.describe()).collect();
            out.noted.push(format!("{label}: {}", notes.join("; ")));
        }
        out.stacks += 1;
    }
    out.seconds = t.elapsed().as_secs_f64();
    out
}

/// One scene: its projectors, sequence and imaging drawn at random; a label naming them.
pub(super) fn draw(rng: &mut impl Rng, seed: u64) -> (FringeScene, Sequence, String) {
    let p = rng.random_range(1..=3usize);
    let gamma = rng.random_range(1.8..2.6);
    let response = match rng.random_range(0..3) {
        0 => ProjectorResponse::Gamma { gamma },
        1 => ProjectorResponse::Linearised { gamma },
        _ => ProjectorResponse::Linear,
    };
    let setups = vec![
        ProjectorSetup {
            width: 1920,
            height: 1080,
            response,
        };
        p
    ];
    let seq = Sequence::default_for(&setups).expect("the default sequence is valid");
    let (w, h) = [(320, 256), (400, 300), (480, 384)][rng.random_range(0..3)];
    let mut scene = FringeScene::standard(w, h, &setups, seed);
    let im = &mut scene.imaging;
    im.ambient = rng.random_range(5.0..80.0);
    im.white = rng.random_range(120.0..240.0);
    im.read_noise = rng.random_range(1.0..3.0);
    im.psf_sigma = rng.random_range(0.5..1.5);
    im.dark_albedo = rng.random_range(0.05..0.3);
    let share = (im.white - im.ambient).max(10.0) / p as f64;
    for sp in &mut scene.projectors {
        sp.gain = share;
    }
    let label = format!(
        "stack {seed} ({w}×{h}, P = {p}, {response:?}, ambient {:.0}, white {:.0}, read noise {:.1}, PSF {:.2})",
        im.ambient, im.white, im.read_noise, im.psf_sigma
    );
    (scene, seq, label)
}
