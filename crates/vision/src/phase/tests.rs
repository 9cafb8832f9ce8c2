//! Acceptance tests of the decoder on synthetic stacks at the default imaging conditions of
//! docs/design.md §9 (8 bit, read noise 2 DN, shot variance 0.1·I, PSF σ 0.8 px, ambient 40 DN on
//! white, P projectors sharing 195 DN, projector gamma 2.2), against ground truth.

use super::accuracy::{accuracy, ProjectorAccuracy};
use super::*;
use hexcal_core::images::FloatImage;
use hexcal_core::pattern::*;
use hexcal_sim::fringe::{FringeScene, Renderer, Truth};

const GAMMA: ProjectorResponse = ProjectorResponse::Gamma { gamma: 2.2 };
const LINEARISED: ProjectorResponse = ProjectorResponse::Linearised { gamma: 2.2 };

fn setups(p: usize, response: ProjectorResponse) -> Vec<ProjectorSetup> {
    vec![
        ProjectorSetup {
            width: 1920,
            height: 1080,
            response,
        };
        p
    ]
}

struct Case {
    seq: Sequence,
    truth: Truth,
    decoded: DecodedStack,
}

fn decode_case(p: usize, response: ProjectorResponse, width: u32, height: u32, seed: u64) -> Case {
    let setups = setups(p, response);
    let seq = Sequence::default_for(&setups).unwrap();
    let scene = FringeScene::standard(width, height, &setups, seed);
    let mut renderer = Renderer::new(&scene, &seq);
    let mut decoder = Decoder::<u8>::new(&seq, "cam0", width, height, 255.0).unwrap();
    for k in 0..seq.frame_count() {
        let frame = renderer.frame(k);
        decoder.push_frame(k, FrameRef::from(&frame)).unwrap();
    }
    Case {
        truth: renderer.truth(),
        decoded: decoder.finish().unwrap(),
        seq,
    }
}

/// The acceptance checks of one decoded case (issue 9).
fn check_case(case: &Case, label: &str) {
    let accs = accuracy(&case.decoded, &case.truth, &case.seq);
    for (p, maps) in case.decoded.projectors.iter().enumerate() {
        check_projector(case, p, maps, accs[p], label);
    }
    check_unwrap_errors(case, label);
    check_ambient(case, label);
    check_noise_model(&case.decoded, label);
    assert_eq!(case.decoded.projectors.len(), case.seq.projectors().len());
}

/// Truth-based prediction of projector p's σ_u, σ_v over its valid interior pixels, and of
/// σ_u over all its valid pixels (docs/design.md §6, RMS over pixels; `compared` interior
/// pixels).
fn predicted_sigmas(case: &Case, p: usize, maps: &ProjectorMaps, compared: usize) -> [f64; 3] {
    let sigma = case.truth.sigma_uv(&case.seq, p);
    let (mut pu, mut pv, mut pu_all, mut cnt_all) = (0f64, 0f64, 0f64, 0usize);
    for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
        if !ok {
            continue;
        }
        let (su, sv) = sigma(i);
        pu_all += su * su;
        cnt_all += 1;
        if case.truth.interior[i] {
            pu += su * su;
            pv += sv * sv;
        }
    }
    let c = compared as f64;
    let (pu, pv) = ((pu / c).sqrt(), (pv / c).sqrt());
    let pu_all = (pu_all / cnt_all as f64).sqrt();
    [pu, pv, pu_all]
}

/// Projector p's accuracy `acc` against the truth's and its own predicted σ, and no gross
/// errors.
fn check_projector(
    case: &Case,
    p: usize,
    maps: &ProjectorMaps,
    acc: ProjectorAccuracy,
    label: &str,
) {
    // Truth-based prediction over the same valid pixels (docs/design.md §6), RMS over pixels.
    let [pu, pv, pu_all] = predicted_sigmas(case, p, maps, acc.compared);
    eprintln!(
        "{label} projector {p}: valid {} compared {} | rms u {:.3} v {:.3} | truth σ_u {:.3} σ_v {:.3} | reported σ_u {:.3} σ_v {:.3} (truth over valid {:.3}) | B {:.1} σ_I {:.2} σ_φ {:.4}",
        acc.valid, acc.compared, acc.rms_u, acc.rms_v, pu, pv, maps.noise.sigma_u,
        maps.noise.sigma_v, pu_all, maps.noise.modulation, maps.noise.sigma_i, maps.noise.sigma_phi
    );
    // Enough pixels for the RMS to mean something (its relative standard error is
    // 1/√(2·compared) < 1 %).
    assert!(
        acc.compared > 5000,
        "{label} p{p}: only {} compared",
        acc.compared
    );
    // Issue 9: RMS ≤ 1.2× the predicted σ, against both the truth-based prediction and the
    // decoder's own report.
    assert!(
        acc.rms_u <= 1.2 * pu,
        "{label} p{p}: rms u {} vs {pu}",
        acc.rms_u
    );
    assert!(
        acc.rms_v <= 1.2 * pv,
        "{label} p{p}: rms v {} vs {pv}",
        acc.rms_v
    );
    assert!(
        acc.rms_u <= 1.2 * maps.noise.sigma_u,
        "{label} p{p}: reported σ_u"
    );
    assert!(
        acc.rms_v <= 1.2 * maps.noise.sigma_v,
        "{label} p{p}: reported σ_v"
    );
    // The decoder's prediction from its measured B and σ_I agrees with the truth's: B is
    // unbiased after the noise correction and σ_I comes from a fit over all pixels, so a
    // 10 % band is wide (their own statistical error is < 1 %).
    assert!(
        (maps.noise.sigma_u / pu_all - 1.0).abs() < 0.1,
        "{label} p{p}: reported σ_u {} vs truth {pu_all}",
        maps.noise.sigma_u
    );
    // No unwrapping error: interior valid pixels within max(6σ, 1 px) of the truth (σ per
    // pixel from the true B; a Gaussian exceeds 6σ with probability 2·10⁻⁹).
    assert_eq!(acc.gross, 0, "{label} p{p}: gross errors");
}

/// No unwrapping error on any valid pixel, edge pixels included, against max(6σ, 1 px).
fn check_unwrap_errors(case: &Case, label: &str) {
    // At albedo and coverage edges the decoded coordinate is the lit part's centroid, up to
    // ≈ 1 camera px (0.9 projector px here) from the pixel centre's: with the 1 px floor that
    // leaves little room (measured worst: 0.89 of the bound over 64 k edge pairs at
    // 1280×960, P = 3; 0.99 at 320×240, P = 1, where 6σ < 1 px), but it holds.
    let (_, [interior, edge]) = unwrap_errors(case);
    eprintln!(
        "{label}: interior {} pairs, worst {:.2} of max(6σ, 1 px); edge {} pairs, worst {:.2}",
        interior[0], interior[2], edge[0], edge[2]
    );
    assert_eq!(
        interior[1], 0.0,
        "{label}: interior pixels beyond max(6σ, 1 px)"
    );
    assert_eq!(edge[1], 0.0, "{label}: edge pixels beyond max(6σ, 1 px)");
}

/// The ambient image's errors against the truth, per class of pixel (lit by all projectors,
/// unlit by some): [count, Σe², Σe, Σσ², beyond 3σ].
///
/// The truth is A − Σ κ_p·B_p, κ_p = a_0/a_1 (0.727 for γ = 2.2). Where projector p lights
/// the pixel (B ≫ σ_I): Var(Ā) = σ_I²/(G·N) and B_p, the RMS over G groups of a modulation
/// with variance 2σ_I²/N, has variance 2σ_I²/(G·N), so the error is Gaussian with
/// σ_amb² = σ_I²·(1 + 2·Σκ_p²)/(G·N) (docs/design.md §6 for G = 1, κ = 1). Where p lights
/// nothing, B_p² = θ·(Y − 1)₊ with θ = 4σ_I²/N and Y ~ Gamma(G, 1/G), whose mean square is
/// θ·E(Y − 1)₊ = θ·e^{−G}·G^G/G!: not Gaussian, so only its RMS is checked. Shot noise
/// correlates A with B_p (brighter frames are noisier), which lowers the ambient's variance
/// by ≈ 2·Σκ_p·0.1·B_p/(G·N): the predictions are upper bounds.
fn ambient_classes(case: &Case) -> [[f64; 5]; 2] {
    let Case {
        seq,
        truth,
        decoded,
    } = case;
    let n = f64::from(seq.steps());
    let g = seq.groups() as f64;
    let np = seq.projectors().len();
    let kappa: Vec<f64> = seq
        .projectors()
        .iter()
        .map(|c| {
            let gm = c.response.effective_gamma();
            pattern_harmonic(gm, 0) / pattern_harmonic(gm, 1)
        })
        .collect();
    let gi = seq.groups() as i32;
    let unlit_ms = (-g).exp() * g.powi(gi) / (1..=gi).map(f64::from).product::<f64>();
    // [count, Σe², Σe, Σσ², beyond 3σ] for pixels lit by all, and unlit by some.
    let mut classes = [[0f64; 5]; 2];
    let amb = decoded.ambient.as_raw();
    for (i, &amb_i) in amb.iter().enumerate() {
        let s2 = truth.sigma_i[i].powi(2);
        let lit = |p: usize| truth.modulation[p][i] >= 5.0 * truth.sigma_i[i];
        let unlit = |p: usize| truth.full_white[p][i] == 0.0;
        let class = if (0..np).all(lit) {
            0
        } else if (0..np).all(|p| lit(p) || unlit(p)) {
            1
        } else {
            continue; // partly lit through the PSF: neither regime
        };
        let var: f64 = s2 / (g * n)
            + (0..np)
                .map(|p| {
                    let k2 = kappa[p] * kappa[p];
                    if lit(p) {
                        k2 * 2.0 * s2 / (g * n)
                    } else {
                        k2 * 4.0 * s2 / n * unlit_ms
                    }
                })
                .sum::<f64>();
        let e = f64::from(amb_i) - truth.ambient[i];
        let c = &mut classes[class];
        c[0] += 1.0;
        c[1] += e * e;
        c[2] += e;
        c[3] += var;
        c[4] += f64::from(u8::from(e.abs() > 3.0 * var.sqrt()));
    }
    classes
}

/// The ambient image against the truth ([`ambient_classes`]): RMS within 1.2× the
/// prediction, and where all projectors light the pixel, Gaussian and unbiased.
fn check_ambient(case: &Case, label: &str) {
    for (class, c) in ambient_classes(case).iter().enumerate() {
        if c[0] == 0.0 {
            continue;
        }
        let (rms, pred) = ((c[1] / c[0]).sqrt(), (c[3] / c[0]).sqrt());
        let (bias, frac) = (c[2] / c[0], c[4] / c[0]);
        let name = ["lit by all", "unlit by some"][class];
        eprintln!(
            "{label} ambient {name}: {} px rms {rms:.3} predicted {pred:.3} bias {bias:.3} beyond 3σ {frac:.4}",
            c[0]
        );
        assert!(
            rms < 1.2 * pred,
            "{label} {name}: ambient rms {rms} vs {pred}"
        );
        if class == 0 {
            // Gaussian: 0.27 % beyond 3σ. The PSF lowers the fringe contrast by
            // 1 − e^{−(2πσ_psf/48)²/2} ≤ 0.55 % for ≥ 48 px fringes, biasing the ambient by
            // ≤ 0.0055·Σκ_p·B_p ≈ 0.3σ_amb; 1 % beyond 3σ and |bias| < 0.5σ_amb allow for it.
            assert!(frac < 0.01, "{label}: {frac} of ambient pixels beyond 3σ");
            assert!(
                bias.abs() < 0.5 * pred,
                "{label}: ambient bias {bias} vs σ {pred}"
            );
        }
    }
}

/// The measured noise model against read² + 0.1·A + 1/12.
fn check_noise_model(decoded: &DecodedStack, label: &str) {
    for a in [40.0, 150.0] {
        let want = (4.0 + 0.1 * a + 1.0 / 12.0f64).sqrt();
        let got = decoded.noise.sigma(a);
        assert!(
            (got / want - 1.0).abs() < 0.05,
            "{label}: σ_I({a}) {got} vs {want}"
        );
    }
}

#[test]
fn decodes_one_to_four_projectors_gamma_uncorrected_and_linearised() {
    for p in 1..=4 {
        for (response, name) in [(GAMMA, "gamma 2.2"), (LINEARISED, "linearised")] {
            let case = decode_case(p, response, 320, 240, 10 + p as u64);
            check_case(&case, &format!("P={p} {name} N={}", case.seq.steps()));
        }
    }
}

/// Decoded (u, v) against the truth on every valid pixel of every projector, interior and
/// edge alike, with the bound max(6σ, 1 px) of issue 9 (σ per pixel and axis from the true
/// modulation): (distinct camera pixels valid for some projector, [interior, edge] ×
/// [checked (pixel, projector) pairs, beyond the bound, worst error/bound]).
fn unwrap_errors(case: &Case) -> (usize, [[f64; 3]; 2]) {
    let Case {
        seq,
        truth,
        decoded,
    } = case;
    let pixels = truth.interior.len();
    let mut any = vec![false; pixels];
    let mut classes = [[0f64; 3]; 2];
    for (p, maps) in decoded.projectors.iter().enumerate() {
        let sigma = truth.sigma_uv(seq, p);
        for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
            if !ok {
                continue;
            }
            any[i] = true;
            let (su, sv) = sigma(i);
            let (bu, bv) = ((6.0 * su).max(1.0), (6.0 * sv).max(1.0));
            let eu = (f64::from(maps.u.as_raw()[i]) - truth.u[p][i]).abs() / bu;
            let ev = (f64::from(maps.v.as_raw()[i]) - truth.v[p][i]).abs() / bv;
            let c = &mut classes[usize::from(!truth.interior[i])];
            c[0] += 1.0;
            c[1] += f64::from(u8::from(eu.max(ev) > 1.0));
            c[2] = c[2].max(eu.max(ev));
        }
    }
    (any.iter().filter(|a| **a).count(), classes)
}

/// No unwrapping error over ≥ 10⁶ distinct valid camera pixels: one 1280×960 default P = 3
/// stack; each pixel valid for some projector counts once, and every valid (pixel,
/// projector) pair — interior and edge — is checked in u and v against max(6σ, 1 px).
#[test]
fn no_unwrapping_error_over_a_million_pixels() {
    let case = decode_case(3, GAMMA, 1280, 960, 99);
    check_case(&case, "P=3 1280×960");
    let (distinct, [interior, edge]) = unwrap_errors(&case);
    eprintln!(
        "{distinct} distinct valid pixels; interior: {} pairs, {} beyond, worst {:.2} of the bound; \
         edge: {} pairs, {} beyond, worst {:.2} of the bound",
        interior[0], interior[1], interior[2], edge[0], edge[1], edge[2]
    );
    assert!(distinct >= 1_000_000, "only {distinct} valid pixels");
    assert_eq!(interior[1] + edge[1], 0.0, "pixels beyond max(6σ, 1 px)");
}

#[test]
fn lit_images_are_each_projectors_full_white_alone() {
    let case = decode_case(2, GAMMA, 320, 240, 5);
    for (p, maps) in case.decoded.projectors.iter().enumerate() {
        let lit = maps.lit_image();
        let a1 = pattern_harmonic(2.2, 1);
        // The decoder's lit image is B_p/a_1 (2·B_p/0.989 for γ = 2.2); its truth is the
        // projector's full-white image after the PSF, times the PSF's fringe-contrast loss
        // (which no decoder can see): truth B_p/a_1.
        let (mut num, mut den, mut mtf, mut cnt) = (0f64, 0f64, 0f64, 0);
        for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
            if ok && case.truth.interior[i] {
                let want = case.truth.modulation[p][i] / a1;
                num += f64::from(lit.as_raw()[i]) - want;
                den += want;
                mtf += want / case.truth.full_white[p][i];
                cnt += 1;
            }
        }
        // Mean relative bias over > 10⁴ pixels: each pixel's noise is ≈ 2σ_I/√(G·N)/(2a_1) ≈
        // 1 DN of ≈ 100 DN, so the mean is good to 10⁻⁴; the 8-bit pattern levels add < 0.2 %.
        // Using 2·B_p (the linear formula) would be 1.1 % off.
        let rel = num / den;
        eprintln!(
            "p{p}: lit bias {rel:.5} over {cnt} px; PSF contrast {:.4}",
            mtf / f64::from(cnt)
        );
        assert!(
            cnt > 10_000 && rel.abs() < 0.003,
            "p{p}: lit bias {rel} over {cnt}"
        );
    }
}

#[test]
fn saturated_pixels_are_invalid() {
    let setups = setups(1, GAMMA);
    let seq = Sequence::default_for(&setups).unwrap();
    let mut scene = FringeScene::standard(160, 120, &setups, 3);
    scene.projectors[0].gain *= 1.6; // 40 + 312 DN at full white: clipped at 255
    let mut renderer = Renderer::new(&scene, &seq);
    let mut decoder = Decoder::<u8>::new(&seq, "cam", 160, 120, 255.0).unwrap();
    for k in 0..seq.frame_count() {
        decoder
            .push_frame(k, FrameRef::from(&renderer.frame(k)))
            .unwrap();
    }
    let d = decoder.finish().unwrap();
    let sat = d.saturated.count();
    assert!(sat > 1000, "{sat} saturated");
    let maps = &d.projectors[0];
    for (s, v) in d.saturated.as_slice().iter().zip(maps.valid.as_slice()) {
        assert!(!(*s && *v));
    }
}

fn small_stack() -> (Sequence, Vec<image::GrayImage>) {
    let setups = setups(1, GAMMA);
    let seq = Sequence::default_for(&setups).unwrap();
    let scene = FringeScene::standard(64, 48, &setups, 1);
    let mut r = Renderer::new(&scene, &seq);
    let frames = (0..seq.frame_count()).map(|k| r.frame(k)).collect();
    (seq, frames)
}

#[test]
fn missing_truncated_and_missized_frames_name_camera_and_frame() {
    let (seq, frames) = small_stack();
    let new = || Decoder::<u8>::new(&seq, "left-7", 64, 48, 255.0).unwrap();

    // Frame 2 missing.
    let mut d = new();
    d.push_frame(0, FrameRef::from(&frames[0])).unwrap();
    d.push_frame(1, FrameRef::from(&frames[1])).unwrap();
    let e = d.push_frame(3, FrameRef::from(&frames[3])).unwrap_err();
    assert_eq!(
        e.to_string(),
        "camera left-7: frame 3 arrived while frame 2 was due (frame 2 is missing or out of order)"
    );

    // Frame 1 truncated.
    let mut d = new();
    d.push_frame(0, FrameRef::from(&frames[0])).unwrap();
    let cut = FrameRef {
        width: 64,
        height: 48,
        pixels: &frames[1].as_raw()[..64 * 30],
    };
    let e = d.push_frame(1, cut).unwrap_err();
    assert_eq!(
        e.to_string(),
        "camera left-7: frame 1 is truncated: 1920 pixel values for 3072 pixels"
    );

    // Frame 4 of another size.
    let mut d = new();
    for (k, f) in frames.iter().enumerate().take(4) {
        d.push_frame(k, FrameRef::from(f)).unwrap();
    }
    let small = image::GrayImage::new(32, 48);
    let e = d.push_frame(4, FrameRef::from(&small)).unwrap_err();
    assert_eq!(
        e.to_string(),
        "camera left-7: frame 4 is 32×48, the stack is 64×48"
    );

    // The stack stops after 29 of 30 frames.
    let mut d = new();
    for (k, f) in frames.iter().enumerate().take(29) {
        d.push_frame(k, FrameRef::from(f)).unwrap();
    }
    let e = d.finish().unwrap_err();
    assert_eq!(
        e.to_string(),
        "camera left-7: stack ends after 29 frames, the sequence has 30 (frame 29 is missing)"
    );

    // One frame too many.
    let mut d = new();
    for (k, f) in frames.iter().enumerate() {
        d.push_frame(k, FrameRef::from(f)).unwrap();
    }
    let e = d.push_frame(30, FrameRef::from(&frames[0])).unwrap_err();
    assert!(matches!(
        e,
        DecodeError::TooMany {
            frame: 30,
            count: 30,
            ..
        }
    ));
    assert!(d.finish().is_ok());

    // An empty frame size.
    let e = Decoder::<u8>::new(&seq, "left-7", 0, 48, 255.0)
        .err()
        .unwrap();
    assert_eq!(
        e.to_string(),
        "camera left-7: frames of 0×48 with full scale 255 cannot be decoded"
    );

    // The plain frame of a rig without projectors has no phase.
    let e = Decoder::<u8>::new(&Sequence::camera_only(), "left-7", 64, 48, 255.0)
        .err()
        .unwrap();
    assert!(matches!(e, DecodeError::CameraOnly { .. }), "{e}");
}

#[test]
fn sixteen_bit_and_float_frames_decode_like_eight_bit() {
    let (seq, frames) = small_stack();
    let mut d8 = Decoder::<u8>::new(&seq, "c", 64, 48, 255.0).unwrap();
    let mut d16 = Decoder::<u16>::new(&seq, "c", 64, 48, 255.0).unwrap();
    let mut df = Decoder::<f32>::new(&seq, "c", 64, 48, 255.0).unwrap();
    for (k, f) in frames.iter().enumerate() {
        d8.push_frame(k, FrameRef::from(f)).unwrap();
        let wide: Vec<u16> = f.as_raw().iter().map(|&v| u16::from(v)).collect();
        let float: Vec<f32> = f.as_raw().iter().map(|&v| f32::from(v)).collect();
        let fr = |pixels| FrameRef {
            width: 64,
            height: 48,
            pixels,
        };
        d16.push_frame(k, fr(&wide[..])).unwrap();
        df.push_frame(
            k,
            FrameRef {
                width: 64,
                height: 48,
                pixels: &float[..],
            },
        )
        .unwrap();
    }
    let (a, b, c) = (
        d8.finish().unwrap(),
        d16.finish().unwrap(),
        df.finish().unwrap(),
    );
    // Bitwise, so that the NaN of pixels that were not unwrapped compare equal.
    let bits = |img: &FloatImage| img.as_raw().iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.projectors[0].u), bits(&b.projectors[0].u));
    assert_eq!(bits(&a.projectors[0].u), bits(&c.projectors[0].u));
    assert_eq!(bits(&a.ambient), bits(&c.ambient));
    assert_eq!(a.projectors[0].valid, c.projectors[0].valid);
}

#[test]
fn compact_stack_gives_the_full_maps_at_its_candidates() {
    // 150 rows: four whole bands of BAND_ROWS and a partial one.
    let (w, h) = (200, 150);
    let setups = setups(2, GAMMA);
    let seq = Sequence::default_for(&setups).unwrap();
    let scene = FringeScene::standard(w, h, &setups, 3);
    let mut renderer = Renderer::new(&scene, &seq);
    let mut full = Decoder::<u8>::new(&seq, "c", w, h, 255.0).unwrap();
    let mut compact = Decoder::<u8>::new(&seq, "c", w, h, 255.0).unwrap();
    for k in 0..seq.frame_count() {
        let f = renderer.frame(k);
        full.push_frame(k, FrameRef::from(&f)).unwrap();
        compact.push_frame(k, FrameRef::from(&f)).unwrap();
    }
    let (full, compact) = (full.finish().unwrap(), compact.finish_compact().unwrap());
    let npx = (w * h) as usize;
    // The board covers part of the image: some pixels are candidates, not all.
    assert!((1..npx).contains(&compact.candidates()));
    assert!(compact.bytes() < npx * (6 + 2 * 17));
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(full.ambient.as_raw()), bits(compact.ambient.as_raw()));
    assert_eq!(full.saturated, compact.saturated);
    assert_eq!(full.noise, compact.noise);
    // Every pixel's values in the compact maps, through its slot (NaN, invalid and 0 away
    // from the candidates).
    let slots = compact.candidate_slots();
    for (p, maps) in full.projectors.iter().enumerate() {
        let c = &compact.projectors[p].at_candidates;
        let at = |i: usize| (slots[i] != NO_SLOT).then(|| slots[i] as usize);
        let u: Vec<f32> = (0..npx)
            .map(|i| at(i).map_or(f32::NAN, |k| c.u[k]))
            .collect();
        let v: Vec<f32> = (0..npx)
            .map(|i| at(i).map_or(f32::NAN, |k| c.v[k]))
            .collect();
        let valid: Vec<bool> = (0..npx)
            .map(|i| at(i).is_some_and(|k| c.valid[k]))
            .collect();
        assert_eq!(bits(maps.u.as_raw()), bits(&u), "projector {p}: u");
        assert_eq!(bits(maps.v.as_raw()), bits(&v), "projector {p}: v");
        assert_eq!(maps.valid.as_slice(), &valid[..], "projector {p}: valid");
        assert!(
            maps.valid.count() > 1000,
            "projector {p}: {}",
            maps.valid.count()
        );
        assert_eq!(maps.noise, compact.projectors[p].noise);
        // The modulation: the same wherever the pixel is a candidate.
        for (i, &b) in maps.modulation.as_raw().iter().enumerate() {
            match at(i) {
                Some(k) => assert_eq!(b, c.modulation[k], "pixel {i}"),
                None => assert!(maps.u.as_raw()[i].is_nan(), "pixel {i}"),
            }
        }
    }
}
