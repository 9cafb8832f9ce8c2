//! The stack check against rendered stacks with known faults (docs/design.md §6b): clean
//! stacks pass with no note, each fault is named with its size.

use super::*;
use crate::phase::{DecodedStack, Decoder, FrameRef};
use hexcal_core::pattern::{ProjectorResponse, ProjectorSetup};
use hexcal_sim::fringe::{Disturbance, FringeScene, Renderer, Truth};

fn sequence(p: usize, response: ProjectorResponse) -> Sequence {
    let setups = vec![
        ProjectorSetup {
            width: 1920,
            height: 1080,
            response,
        };
        p
    ];
    Sequence::default_for(&setups).unwrap()
}

const GAMMA: ProjectorResponse = ProjectorResponse::Gamma { gamma: 2.2 };

/// Decode a `width` × `height` stack of the standard scene whose frame k is disturbed as
/// `fault(k)` says.
fn decode(
    seq: &Sequence,
    size: (u32, u32),
    seed: u64,
    fault: impl Fn(usize) -> Disturbance,
) -> DecodedStack {
    decode_with_truth(seq, size, seed, fault).0
}

/// [`decode`], with the scene's ground truth.
fn decode_with_truth(
    seq: &Sequence,
    (width, height): (u32, u32),
    seed: u64,
    fault: impl Fn(usize) -> Disturbance,
) -> (DecodedStack, Truth) {
    let scene = FringeScene::standard(width, height, &setups(seq), seed);
    decode_scene(seq, &scene, fault)
}

/// The verdict on a `width` × `height` stack of the standard scene for `seq` lit as
/// `[ambient, white, read noise, PSF σ]` say, each projector's gain (white − ambient)/`share`,
/// frame k disturbed as `fault(k)` says.
fn verdict_lit(
    seq: &Sequence,
    (width, height): (u32, u32),
    seed: u64,
    [ambient, white, read_noise, psf]: [f64; 4],
    share: f64,
    fault: impl Fn(usize) -> Disturbance,
) -> StackVerdict {
    let mut scene = FringeScene::standard(width, height, &setups(seq), seed);
    let im = &mut scene.imaging;
    (im.ambient, im.white, im.read_noise, im.psf_sigma) = (ambient, white, read_noise, psf);
    for sp in &mut scene.projectors {
        sp.gain = (white - ambient) / share;
    }
    decode_scene(seq, &scene, fault).0.verdict
}

/// The projectors of `seq` as the scene takes them.
fn setups(seq: &Sequence) -> Vec<ProjectorSetup> {
    (seq.projectors().iter())
        .map(|c| ProjectorSetup {
            width: c.width,
            height: c.height,
            response: c.response,
        })
        .collect()
}

/// Decode `scene`'s stack of `seq` with frame k disturbed as `fault(k)` says.
fn decode_scene(
    seq: &Sequence,
    scene: &FringeScene,
    fault: impl Fn(usize) -> Disturbance,
) -> (DecodedStack, Truth) {
    let mut renderer = Renderer::new(scene, seq);
    let (width, height) = (scene.width, scene.height);
    let mut decoder = Decoder::<u8>::new(seq, "cam0", width, height, 255.0).unwrap();
    for k in 0..seq.frame_count() {
        let frame = renderer.frame_with(k, &fault(k));
        decoder.push_frame(k, FrameRef::from(&frame)).unwrap();
    }
    (decoder.finish().unwrap(), renderer.truth())
}

fn clean(p: usize) -> impl Fn(usize) -> Disturbance {
    move |_| Disturbance::none(p)
}

fn show(v: &StackVerdict) -> String {
    format!(
        "faults: [{}]; notes: [{}]; disturbance max {:.3}; displacement {:?}",
        v.summary(),
        v.notes
            .iter()
            .map(StackNote::describe)
            .collect::<Vec<_>>()
            .join("; "),
        v.figures.disturbance.iter().cloned().fold(0.0, f64::max),
        v.figures.displacement
    )
}

#[test]
fn clean_stacks_pass_without_a_note() {
    for (p, response, seed) in [
        (3, GAMMA, 1),
        (3, ProjectorResponse::Linearised { gamma: 2.2 }, 2),
        (2, ProjectorResponse::Linear, 3),
        (1, GAMMA, 4),
    ] {
        let seq = sequence(p, response);
        let d = decode(&seq, (480, 384), seed, clean(p));
        eprintln!("P {p} {response:?}: {}", show(&d.verdict));
        assert!(d.verdict.passed(), "{}", show(&d.verdict));
        assert!(d.verdict.notes.is_empty(), "{}", show(&d.verdict));
    }
}

/// Projector 1 one frame late in frames 31–33 (fringe group 3, count 25).
fn late_in_group_3(k: usize) -> Disturbance {
    let mut d = Disturbance::none(3);
    if (31..=33).contains(&k) {
        d.shown[1] = Some(k - 1);
    }
    d
}

#[test]
fn a_projector_one_frame_late_is_named_and_repaired() {
    let seq = sequence(3, GAMMA);
    let d = decode(&seq, (480, 384), 5, late_in_group_3);
    eprintln!("{}", show(&d.verdict));
    let fault = StackFault::WrongPattern {
        projector: 1,
        group: 2,
        frames: [30, 44],
        count: 3,
        offset: -1,
    };
    assert!(d.verdict.passed(), "{}", show(&d.verdict));
    assert_eq!(
        d.verdict.notes,
        vec![StackNote::Repaired { fault }],
        "{}",
        show(&d.verdict)
    );
}

/// Mean and RMS error of u over projector p's valid interior pixels, and their count.
fn u_errors(d: &DecodedStack, truth: &Truth, p: usize) -> (f64, f64, usize) {
    let maps = &d.projectors[p];
    let (mut n, mut s, mut s2) = (0usize, 0f64, 0f64);
    for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
        if ok && truth.interior[i] {
            let e = f64::from(maps.u.as_raw()[i]) - truth.u[p][i];
            (n, s, s2) = (n + 1, s + e, s2 + e * e);
        }
    }
    let c = n.max(1) as f64;
    (s / c, (s2 / c).sqrt(), n)
}

#[test]
fn a_repaired_lag_leaves_no_bias_and_the_noise_its_information_predicts() {
    // Left out, the count-25 group takes its share of Σn² = 20² + 21² + 25² from every
    // projector's columns: σ_u grows by √(1466/841) = 1.320; the rows keep every group.
    let seq = sequence(3, GAMMA);
    let (clean, truth) = decode_with_truth(&seq, (640, 512), 21, clean(3));
    let (late, _) = decode_with_truth(&seq, (640, 512), 21, late_in_group_3);
    assert!(late.verdict.passed(), "{}", show(&late.verdict));
    let ratio = (1466.0f64 / 841.0).sqrt();
    for p in 0..3 {
        let (mean_c, rms_c, n_c) = u_errors(&clean, &truth, p);
        let (mean_l, rms_l, n_l) = u_errors(&late, &truth, p);
        eprintln!(
            "projector {p}: clean mean {mean_c:+.4} rms {rms_c:.4} ({n_c}); repaired mean {mean_l:+.4} rms {rms_l:.4} ({n_l}); ratio {:.3} (predicted {ratio:.3})",
            rms_l / rms_c
        );
        // No bias: the mean error within 4 standard errors of the clean stack's.
        let se = rms_l / (n_l as f64).sqrt() + rms_c / (n_c as f64).sqrt();
        assert!((mean_l - mean_c).abs() < 4.0 * se, "projector {p}");
        // The RMS as its information predicts: the estimate's relative standard error is
        // 1/√(2n) ≈ 0.2 % at n ≈ 10⁵, pixels correlate over the PSF (σ 0.8 px: ~4 pixels
        // per independent sample), so 5 % is > 10 standard errors.
        assert!((rms_l / rms_c / ratio - 1.0).abs() < 0.05, "projector {p}");
        // Pixels the kept counts alone unwrap otherwise are lost (2.0–2.2 % here).
        assert!(n_l as f64 > 0.95 * n_c as f64, "projector {p}: pixels lost");
    }
}

#[test]
fn a_drifting_board_is_named() {
    let seq = sequence(3, GAMMA);
    let k = seq.frame_count() as f64;
    let d = decode(&seq, (480, 384), 6, |f| Disturbance {
        shift: [0.2 * f as f64 / k, 0.0],
        ..Disturbance::none(3)
    });
    eprintln!("{}", show(&d.verdict));
    assert!(
        d.verdict
            .faults
            .iter()
            .any(|f| matches!(f, StackFault::Motion { px, .. } if (0.1..0.3).contains(px))),
        "{}",
        show(&d.verdict)
    );
}

#[test]
fn a_jolt_is_named() {
    let seq = sequence(3, GAMMA);
    let d = decode(&seq, (480, 384), 7, |f| Disturbance {
        shift: [0.0, if f >= 50 { 0.2 } else { 0.0 }],
        ..Disturbance::none(3)
    });
    eprintln!("{}", show(&d.verdict));
    assert!(!d.verdict.passed(), "{}", show(&d.verdict));
    assert!(
        d.verdict
            .faults
            .iter()
            .any(|f| matches!(f, StackFault::Motion { .. } | StackFault::Jolt { .. })),
        "{}",
        show(&d.verdict)
    );
}

#[test]
fn flickering_room_light_is_named() {
    let seq = sequence(3, GAMMA);
    let d = decode(&seq, (480, 384), 8, |f| Disturbance {
        ambient: 1.0 + 0.1 * (std::f64::consts::TAU * f as f64 / 7.0).sin(),
        ..Disturbance::none(3)
    });
    eprintln!("{}", show(&d.verdict));
    assert!(
        d.verdict
            .faults
            .iter()
            .any(|f| matches!(f, StackFault::LightChange { .. })),
        "{}",
        show(&d.verdict)
    );
}

#[test]
fn a_light_step_inside_a_group_fails_and_between_groups_is_a_note() {
    let seq = sequence(3, GAMMA);
    let inside = decode(&seq, (480, 384), 9, |f| Disturbance {
        ambient: if f >= 50 { 1.05 } else { 1.0 },
        ..Disturbance::none(3)
    });
    eprintln!("inside: {}", show(&inside.verdict));
    assert!(
        inside
            .verdict
            .faults
            .iter()
            .any(|f| matches!(f, StackFault::LightChange { .. })),
        "{}",
        show(&inside.verdict)
    );
    let between = decode(&seq, (480, 384), 9, |f| Disturbance {
        ambient: if f >= 45 { 1.3 } else { 1.0 },
        ..Disturbance::none(3)
    });
    eprintln!("between: {}", show(&between.verdict));
    assert!(between.verdict.passed(), "{}", show(&between.verdict));
    // The decoder's own noise model, from the spread of the group means, would take the step
    // for noise and leave no pixel valid; with the check's it keeps what a clean stack keeps
    // but for the pixels the brighter room light pushes under the validity floor.
    let valid = |d: &DecodedStack| {
        d.projectors[0]
            .valid
            .as_slice()
            .iter()
            .filter(|&&v| v)
            .count()
    };
    let clean_valid = valid(&decode(&seq, (480, 384), 9, clean(3)));
    eprintln!(
        "valid: {} after the step, {clean_valid} clean",
        valid(&between)
    );
    assert!(valid(&between) as f64 >= 0.99 * clean_valid as f64);
    assert!(
        matches!(
            between.verdict.notes[..],
            [StackNote::LightStep {
                from_group: 2,
                to_group: 3,
                ..
            }]
        ),
        "{}",
        show(&between.verdict)
    );
}

#[test]
fn clipping_is_named() {
    let seq = sequence(3, GAMMA);
    let d = decode(&seq, (480, 384), 10, |_| Disturbance {
        gain: 1.5,
        ..Disturbance::none(3)
    });
    eprintln!("{}", show(&d.verdict));
    assert!(
        d.verdict
            .faults
            .iter()
            .any(|f| matches!(f, StackFault::Clipped { fraction } if *fraction > 0.1)),
        "{}",
        show(&d.verdict)
    );
}

#[test]
fn lags_are_named_in_a_linearised_sequence_and_for_every_projector() {
    // N = 7 for three linearised projectors: the model takes every step, so only the phases
    // across groups can tell.
    let seq = sequence(3, ProjectorResponse::Linearised { gamma: 2.2 });
    let d = decode(&seq, (480, 384), 11, |k| {
        let mut d = Disturbance::none(3);
        if (16..=18).contains(&k) {
            d.shown[0] = Some(k - 1);
        }
        d
    });
    eprintln!("one late: {}", show(&d.verdict));
    // Named, and not repaired: group 3 has count 25, and the counts 20 and 21 kept alone
    // find the fringe orders at only ~86 % of the pixels at N = 7 (σ_φ is √(15/7) times
    // that of N = 15), so the repair would cost ~1.4× in σ (eq. 6b.10): refused.
    assert!(!d.verdict.passed(), "{}", show(&d.verdict));
    assert!(
        d.verdict.faults.iter().any(|f| matches!(
            f,
            StackFault::WrongPattern {
                projector: 0,
                group: 2,
                offset: -1,
                ..
            }
        )),
        "{}",
        show(&d.verdict)
    );
    // Every projector one frame late once, in one frame each of another group.
    let seq = sequence(3, GAMMA);
    let d = decode(&seq, (480, 384), 12, |k| {
        let mut d = Disturbance::none(3);
        for (p, frame) in [(0, 62), (1, 63), (2, 64)] {
            if k == frame {
                d.shown[p] = Some(k - 1);
            }
        }
        d
    });
    eprintln!("every one late once: {}", show(&d.verdict));
    // Group 5 has count 21: the counts left, 20 and 25, share a factor, so no repair.
    assert!(!d.verdict.passed(), "{}", show(&d.verdict));
}

#[test]
fn light_changing_within_a_group_is_named_where_the_model_uses_every_step() {
    // N = 5 for two linear projectors: no residual per frame, so the light is seen only in
    // the pattern it leaves in the phases (eq. 6b.8). ±2 % of 40 DN of ambient light moves
    // a pixel's phase by ≈ 0.1 of its noise, coherently over a circle.
    let seq = sequence(2, ProjectorResponse::Linear);
    let (flicker, truth) = decode_with_truth(&seq, (480, 384), 13, |f| Disturbance {
        ambient: 1.0 + 0.02 * (std::f64::consts::TAU * f as f64 / 7.0).sin(),
        ..Disturbance::none(2)
    });
    eprintln!("flicker: {}", show(&flicker.verdict));
    assert!(
        (flicker.verdict.faults.iter()).any(|f| matches!(f, StackFault::LightChange { .. })),
        "{}",
        show(&flicker.verdict)
    );
    // The same stack without the flicker passes: the finding is the light's.
    let (clean, _) = decode_with_truth(&seq, (480, 384), 13, clean(2));
    assert!(clean.verdict.passed(), "{}", show(&clean.verdict));
    // And the flicker did bias the decode: patch means of 16 × 16 px off by more than the
    // clean stack's.
    let patch_rms = |d: &DecodedStack| {
        let maps = &d.projectors[0];
        let mut sums = std::collections::HashMap::<(usize, usize), (f64, usize)>::new();
        for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
            if ok && truth.interior[i] {
                let e = sums.entry((i % 480 / 16, i / 480 / 16)).or_default();
                *e = (e.0 + f64::from(maps.u.as_raw()[i]) - truth.u[0][i], e.1 + 1);
            }
        }
        let means: Vec<f64> = (sums.values())
            .filter(|(_, n)| *n >= 64)
            .map(|(s, n)| s / *n as f64)
            .collect();
        (means.iter().map(|m| m * m).sum::<f64>() / means.len() as f64).sqrt()
    };
    let (faulty, good) = (patch_rms(&flicker), patch_rms(&clean));
    eprintln!("patch-mean u error RMS: {faulty:.4} px flickering, {good:.4} px clean");
    assert!(faulty > 1.5 * good);
}

#[test]
fn a_whole_group_shown_late_is_named_not_taken_for_light() {
    // Projector 0 shows the previous frame's pattern in every frame of the last row group:
    // that group's phases are off by a fifth of a cycle, which takes most pixels to no or the
    // wrong fringe orders (6b.9); its first frame shows the last frame of the group before,
    // which leaves projector 0's fringes in the group's mean image (6b.12), which names it.
    let seq = sequence(2, ProjectorResponse::Linear);
    let d = decode(&seq, (480, 384), 14, |k| {
        let mut d = Disturbance::none(2);
        if (25..30).contains(&k) {
            d.shown[0] = Some(k - 1);
        }
        d
    });
    eprintln!("{}", show(&d.verdict));
    assert!(names_lag(&d.verdict, 0, 5), "{}", show(&d.verdict));
    assert!(
        d.verdict.faults.iter().all(|f| !matches!(
            f,
            StackFault::LightChange { .. } | StackFault::Motion { .. }
        )),
        "{}",
        show(&d.verdict)
    );
}

#[test]
fn a_lag_that_takes_its_direction_to_wrong_orders_is_named_against_the_other_counts() {
    // A dim, blurred scene (PSF σ 1.27 px, read noise 2.7 DN): projector 0 shows the next
    // frame's pattern in 4 of the 15 frames of fringe group 4 (rows, count 20). The rows'
    // fusion spreads the bias over all three groups and, at many pixels, into wrong orders,
    // so that no group stands out against the fused position: the check read it as light
    // changing in its group and the board moving next to it. Judged against the position
    // the other counts give alone, a group of the rows is off by what a lag gives (6b.11),
    // and the group's mean image holds projector 0's fringes (6b.12), which names the lag
    // and its group; not repaired (the repair takes its orders from every group).
    let seq = sequence(3, ProjectorResponse::Gamma { gamma: 2.6 });
    let v = verdict_lit(&seq, (320, 256), 180, [26.0, 197.0, 2.7, 1.27], 3.0, |k| {
        let mut d = Disturbance::none(3);
        if (50..=53).contains(&k) {
            d.shown[0] = Some(k + 1);
        }
        d
    });
    eprintln!("{}", show(&v));
    assert!(!v.passed(), "{}", show(&v));
    assert!(names_lag(&v, 0, 3), "{}", show(&v));
    // What the lag explains is not named besides it.
    assert!(
        !(v.faults.iter()).any(|f| matches!(
            f,
            StackFault::Motion { .. } | StackFault::LightChange { .. }
        )),
        "{}",
        show(&v)
    );
}

/// Whether `v` names a lag of projector p in group g: its mean image holding p's fringes
/// (6b.12, p among the projectors named) or p's direction holding a lag (6b.11).
fn names_lag(v: &StackVerdict, p: usize, g: usize) -> bool {
    v.faults.iter().any(|f| match f {
        StackFault::FringesInMean {
            projectors, group, ..
        } => projectors.contains(&p) && *group == g,
        StackFault::LagInGroups {
            projector, groups, ..
        } => *projector == p && groups[0] <= g && g <= groups[1],
        _ => false,
    })
}

#[test]
fn a_lag_in_a_short_dim_sequence_is_named_by_the_fringes_in_its_groups_mean() {
    // One linearised projector, N = 3 (no residual per frame), a dim and blurred board: the
    // projector shows the previous frame's pattern in frames 1 and 2. The fusion of three
    // counts takes the columns to wrong orders at a fifth of the pixels and spreads the
    // bias over the groups, so the phase tests name the wrong group's phases and positions
    // that do not unwrap, and the other counts alone find too few orders to judge (6b.11).
    // Group 1's mean image holds the projector's fringes (1/3 of P_0 − P_2): that names the
    // lag and its group, and explains the rest.
    let seq = sequence(1, ProjectorResponse::Linearised { gamma: 2.1 });
    let v = verdict_lit(&seq, (400, 300), 31, [30.0, 160.0, 2.5, 1.3], 2.0, |k| {
        let mut d = Disturbance::none(1);
        if (1..=2).contains(&k) {
            d.shown[0] = Some(k - 1);
        }
        d
    });
    eprintln!("{}", show(&v));
    assert_eq!(seq.steps(), 3);
    assert!(
        v.faults.iter().any(|f| matches!(f, StackFault::FringesInMean { projectors, group: 0, frames: [0, 2] } if projectors == &[0])),
        "{}",
        show(&v)
    );
    assert_eq!(v.faults.len(), 1, "{}", show(&v));
}

#[test]
fn a_lag_the_phases_place_in_another_group_is_placed_by_the_means() {
    // Two linear projectors, N = 5, a dim board: projector 0 shows the previous frame's
    // pattern through the whole last group (frames 25–29; its first frame shows group 5's
    // last). The fusion spreads the bias over the rows, and the phases name a lag in group
    // 4 (0-based 3); the mean image of group 5 holds projector 0's fringes, which places it.
    let seq = sequence(2, ProjectorResponse::Linear);
    let v = verdict_lit(&seq, (400, 300), 116, [30.0, 160.0, 2.5, 1.3], 2.0, |k| {
        let mut d = Disturbance::none(2);
        if (25..30).contains(&k) {
            d.shown[0] = Some(k - 1);
        }
        d
    });
    eprintln!("{}", show(&v));
    assert!(!v.passed(), "{}", show(&v));
    assert!(names_lag(&v, 0, 5), "{}", show(&v));
    let elsewhere = |f: &StackFault| match f {
        StackFault::WrongPattern { group, .. } => *group != 5,
        StackFault::FringesInMean { group, .. } => *group != 5,
        _ => false,
    };
    assert!(!v.faults.iter().any(elsewhere), "{}", show(&v));
}

#[test]
fn a_large_light_step_inside_a_short_group_is_named_as_light() {
    // One linear projector, N = 3 (no residual per frame): the room light rises by a
    // quarter from frame 1 on, inside fringe group 1. The light's shape in group 1's bin
    // takes its phases to wrong orders at some pixels, which 6b.8 cannot read; the step
    // between the groups' means, next to the group whose phases disagree, with no lag in
    // any group's mean, names it.
    let seq = sequence(1, ProjectorResponse::Linear);
    let v = verdict_lit(&seq, (480, 384), 126, [79.0, 139.0, 1.0, 0.55], 1.0, |k| {
        Disturbance {
            ambient: if k >= 1 { 1.23 } else { 1.0 },
            ..Disturbance::none(1)
        }
    });
    eprintln!("{}", show(&v));
    assert_eq!(seq.steps(), 3);
    assert!(!v.passed(), "{}", show(&v));
    assert!(
        (v.faults.iter()).any(|f| matches!(
            f,
            StackFault::LightChange {
                first_frame: 0,
                last_frame: 2,
                ..
            }
        )),
        "{}",
        show(&v)
    );
    let other = |f: &StackFault| !matches!(f, StackFault::LightChange { .. });
    assert!(!v.faults.iter().any(other), "{}", show(&v));
    assert!(v.notes.is_empty(), "{}", show(&v));
}
