//! The lens model chosen by the data (docs/design.md §8, "Lens model"): a radial term the
//! data cannot determine is fixed at zero and the adjustment repeated.
//!
//! Takes a bundle-adjustment [`Problem`] and its [`Options`]; gives the final [`Solution`]
//! and, per device, which distortion terms it uses and why ([`LensChoice`]). The
//! radial terms above k1 are tested from the top (k6, k5, k4, k3, then k2): the highest
//! one still estimated is fixed at zero when its estimate lies within [`SIGNIFICANCE`]
//! standard deviations of zero, and the adjustment repeated; every round retests each
//! device's highest estimated term against the latest solution, until a round fixes
//! nothing (a term that is determined ends the device's tests: the terms below it stay).
//! A fixed term's bias is at most [`SIGNIFICANCE`] of its own standard deviations, which
//! is what the data could not tell from zero anyway; estimating it instead lets its
//! uncertainty, largest where there are no points, bend the image corners (the issue's
//! cam0: k3 = 0.177 ± 0.062, truth 0, 1.63 px off in the corners). k1 and the tangential
//! p1, p2 are always estimated: they are the first-order terms of every real lens.

use super::bundle::{adjust, Device, Options, Problem, Solution};
use super::CalibError;
use hexcal_core::board::SideTransform;
use hexcal_core::camera::{CameraModel, LensParam};
use nalgebra::{Point2, Point3, UnitQuaternion};
use serde::{Deserialize, Serialize};

/// A term whose estimate lies within this many of its standard deviations of zero is not
/// determined by the data (a two-sided test at the 0.27 % level for Gaussian errors).
pub const SIGNIFICANCE: f64 = 3.0;

/// The terms tested, highest order first.
const CANDIDATES: [LensParam; 5] = [
    LensParam::K6,
    LensParam::K5,
    LensParam::K4,
    LensParam::K3,
    LensParam::K2,
];

/// The distortion terms a model has (k4–k6 only in the rational model).
fn distortion_terms(model: &CameraModel) -> Vec<LensParam> {
    let rational = model.distortion.is_rational();
    LensParam::ALL
        .into_iter()
        .filter(|p| p.index() >= 4 && (rational || p.index() < 9))
        .collect()
}

/// What became of one distortion term of a device.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TermChoice {
    /// The term.
    pub param: LensParam,
    /// Whether the final adjustment estimated it.
    pub estimated: bool,
    /// Its estimate in the last adjustment that estimated it (the final value when
    /// estimated; the evidence when fixed).
    pub estimate: f64,
    /// Standard deviation of that estimate (0 when never estimated).
    pub std: f64,
    /// Whether the data tested it (`CANDIDATES`): a term fixed by the test, or the
    /// highest candidate still estimated (tested against the final adjustment); false
    /// for k1, p1, p2, for terms below a determined one and for terms the user fixed.
    pub tested: bool,
}

impl TermChoice {
    /// Why the term is estimated or fixed, in words.
    pub fn reason(&self) -> String {
        let (name, v, s) = (self.param.name(), self.estimate, self.std);
        let z = if s > 0.0 { v.abs() / s } else { f64::INFINITY };
        match (self.estimated, self.tested) {
            (true, true) => {
                format!("{name} = {v:.4} ± {s:.4} is {z:.1}σ from zero: determined, estimated")
            }
            (true, false) => format!("{name} = {v:.4} ± {s:.4}: always estimated"),
            (false, true) => format!(
                "{name} was {v:.4} ± {s:.4}, {z:.1}σ from zero (below {SIGNIFICANCE}σ): the \
                 data cannot determine it, fixed at 0"
            ),
            (false, false) => format!("{name} fixed at {v:.4} by the options"),
        }
    }
}

/// The lens model chosen for one device.
#[derive(Clone, Debug, PartialEq)]
pub struct LensChoice {
    /// Every distortion term of its model, in parameter order.
    pub terms: Vec<TermChoice>,
    /// The device (model and pose) from the first adjustment, with every term estimated.
    pub all_terms: Device,
}

impl LensChoice {
    /// The terms fixed at zero because the data could not determine them.
    pub fn dropped(&self) -> impl Iterator<Item = &TermChoice> {
        self.terms.iter().filter(|t| !t.estimated && t.tested)
    }

    /// One line: the terms estimated and the terms fixed.
    pub fn summary(&self) -> String {
        let names = |f: &dyn Fn(&TermChoice) -> bool| {
            let v: Vec<&str> = self
                .terms
                .iter()
                .filter(|t| f(t))
                .map(|t| t.param.name())
                .collect();
            if v.is_empty() {
                "none".to_string()
            } else {
                v.join(" ")
            }
        };
        format!(
            "estimates {}; fixed: {}",
            names(&|t| t.estimated),
            names(&|t| !t.estimated)
        )
    }
}

/// The value and standard deviation of `param` of device `d` in `sol`, when estimated.
fn estimate(sol: &Solution, d: usize, param: LensParam) -> Option<(f64, f64)> {
    let k = sol.free[d].iter().position(|p| p == param)?;
    let value = sol.devices[d].model.lens_vector()[param.index()];
    Some((value, sol.intrinsic_std[d][k]))
}

/// The next term to test on device `d`: the highest-order candidate still estimated.
fn next_candidate(sol: &Solution, d: usize) -> Option<LensParam> {
    CANDIDATES
        .into_iter()
        .find(|&p| sol.free[d].is_free(p) && estimate(sol, d, p).is_some())
}

/// The problem restarted from `sol` (devices, board poses, side transform), with the
/// terms of `fixed` set to zero.
fn restart(p: &Problem, sol: &Solution, fixed: &[Vec<LensParam>]) -> Problem {
    let mut devices = sol.devices.clone();
    for (dev, terms) in devices.iter_mut().zip(fixed) {
        let mut v = dev.model.lens_vector();
        for t in terms {
            v[t.index()] = 0.0;
        }
        dev.model.set_lens_vector(&v);
    }
    let mut board = p.board.clone();
    board.front_back = sol.front_back.map(|fb| SideTransform {
        rotation: fb.rotation.scaled_axis().into(),
        translation: fb.translation.vector.into(),
    });
    Problem {
        board,
        devices,
        boards: sol.boards.clone(),
        observations: p.observations.clone(),
    }
}

/// Adjust `p`, fixing at zero, round by round, every device's highest-order radial term
/// the data cannot determine (module comment), when `select`; say per device what it uses
/// and why.
pub fn adjust_selecting(
    p: &Problem,
    options: &Options,
    select: bool,
) -> Result<(Solution, Vec<LensChoice>), CalibError> {
    let n = p.devices.len();
    let mut o = options.clone();
    o.fixed.resize(n, Vec::new());
    let mut sol = adjust(p, &o)?;
    let all_terms = sol.devices.clone();
    let mut evidence: Vec<Vec<TermChoice>> = vec![Vec::new(); n];
    // Every round retests each device's highest estimated candidate against the latest
    // solution (fixing one device's term moves the others'), until no term is fixed.
    let rounds = if select { CANDIDATES.len() * n } else { 0 };
    for _round in 0..rounds {
        let mut changed = false;
        for (d, tested) in evidence.iter_mut().enumerate() {
            let Some(param) = next_candidate(&sol, d) else {
                continue;
            };
            let (estimate, std) = estimate(&sol, d, param).expect("a candidate is estimated");
            if std > 0.0 && estimate.abs() < SIGNIFICANCE * std {
                tested.push(TermChoice {
                    param,
                    estimated: false,
                    estimate,
                    std,
                    tested: true,
                });
                o.fixed[d].push(param);
                changed = true;
            }
        }
        if !changed {
            break;
        }
        sol = adjust(&restart(p, &sol, &o.fixed), &o)?;
    }
    let choices = (0..n)
        .zip(all_terms)
        .map(|(d, all_terms)| choice(&sol, d, &evidence[d], all_terms))
        .collect();
    Ok((sol, choices))
}

/// Device `d`'s [`LensChoice`] from the final solution and the tests' evidence.
fn choice(sol: &Solution, d: usize, evidence: &[TermChoice], all_terms: Device) -> LensChoice {
    let model = &sol.devices[d].model;
    let terms = distortion_terms(model)
        .into_iter()
        .map(|param| {
            let tested = evidence.iter().find(|t| t.param == param);
            match (estimate(sol, d, param), tested) {
                (Some((estimate, std)), _) => TermChoice {
                    param,
                    estimated: true,
                    estimate,
                    std,
                    tested: next_candidate(sol, d) == Some(param),
                },
                (None, Some(t)) => *t,
                (None, None) => TermChoice {
                    param,
                    estimated: false,
                    estimate: model.lens_vector()[param.index()],
                    std: 0.0,
                    tested: false,
                },
            }
        })
        .collect();
    LensChoice { terms, all_terms }
}

/// Points across and down the image at which [`model_difference`] compares two models.
const GRID: (usize, usize) = (48, 30);

/// Largest and RMS distance (px) over a 48 × 30 grid of pixel centres spanning the whole
/// image (corners included) between each pixel and `other`'s projection of `model`'s ray
/// through it, turned by `rotation` (`model`'s frame to `other`'s; the identity compares
/// the lenses alone). A pixel whose ray `other` cannot project counts as infinitely far.
pub fn model_difference(
    model: &CameraModel,
    other: &CameraModel,
    rotation: &UnitQuaternion<f64>,
) -> (f64, f64) {
    let (nx, ny) = GRID;
    let (w, h) = (model.width as f64 - 1.0, model.height as f64 - 1.0);
    let (mut max, mut sum) = (0f64, 0.0);
    for j in 0..ny {
        for i in 0..nx {
            let p = Point2::new(
                w * i as f64 / (nx - 1) as f64,
                h * j as f64 / (ny - 1) as f64,
            );
            let e = model
                .ray(p)
                .and_then(|r| other.project(&Point3::from(rotation * r)))
                .map_or(f64::INFINITY, |q| (q - p).norm());
            max = max.max(e);
            sum += e * e;
        }
    }
    (max, (sum / (nx * ny) as f64).sqrt())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::calib::diagnostics::projection_uncertainty;
    use crate::calib::solve::{calibrate, Calibration};
    use crate::calib::synthetic::SyntheticRig;

    fn calibrated(rig: &SyntheticRig) -> Calibration {
        calibrate(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &rig.views(),
            &Default::default(),
        )
        .expect("the rig calibrates")
    }

    /// Per device: the chosen and the all-terms model's largest whole-image error against
    /// the truth, and the largest projection uncertainty over the image (px).
    fn errors(rig: &SyntheticRig, cal: &Calibration) -> Vec<(f64, f64, f64)> {
        cal.devices
            .iter()
            .enumerate()
            .map(|(d, dev)| {
                let truth = &rig.devices[cal.device_index[d]].model;
                let m = &dev.model;
                let worst = (0..=8)
                    .flat_map(|i| (0..=8).map(move |j| (i, j)))
                    .filter_map(|(i, j)| {
                        let p = Point2::new(
                            (m.width - 1) as f64 * i as f64 / 8.0,
                            (m.height - 1) as f64 * j as f64 / 8.0,
                        );
                        projection_uncertainty(cal, d, p)
                    })
                    .fold(0.0, f64::max);
                let e = (
                    model_difference(truth, m, &UnitQuaternion::identity()).0,
                    model_difference(
                        truth,
                        &cal.lens[d].all_terms.model,
                        &UnitQuaternion::identity(),
                    )
                    .0,
                    worst,
                );
                eprintln!(
                    "{}: {} | chosen {:.4} px, all terms {:.4} px, uncertainty ≤ {:.4} px",
                    dev.name,
                    cal.lens[d].summary(),
                    e.0,
                    e.1,
                    e.2
                );
                e
            })
            .collect()
    }

    /// The synthetic paper rig (truth k3 = 0, 10 poses, σ = 0.1 px) leaves its image
    /// corners without points. Every term the data cannot determine is fixed, the chosen
    /// models' errors against the truth over each whole image lie within 4 projection
    /// standard deviations (the covariance describes them), and the worst device is
    /// closer to the truth than with every term estimated. Run on `cal`, the paper rig
    /// `rig` calibrated, by `diagnostics::tests` (which calibrates it anyway).
    pub(crate) fn the_paper_rig_fixes_what_its_data_cannot_determine(
        rig: &SyntheticRig,
        cal: &Calibration,
    ) {
        let e = errors(rig, cal);
        for (d, c) in cal.lens.iter().enumerate() {
            for t in c.terms.iter().filter(|t| t.tested) {
                let undetermined = t.estimate.abs() < SIGNIFICANCE * t.std;
                assert_eq!(t.estimated, !undetermined, "{}: {t:?}", cal.devices[d].name);
            }
            assert!(
                e[d].0 <= 4.0 * e[d].2,
                "{}: {:?}",
                cal.devices[d].name,
                e[d]
            );
        }
        assert!(cal.lens.iter().any(|c| c.dropped().count() > 0));
        let worst = |f: fn(&(f64, f64, f64)) -> f64| e.iter().map(f).fold(0.0, f64::max);
        assert!(worst(|e| e.0) < worst(|e| e.1), "{e:?}");
    }

    /// With its corners covered, a camera whose k3 is 0.05 keeps k3 (the data determine
    /// it), the projector (k3 = 0) has it fixed, and every chosen model is within 4
    /// projection standard deviations of the truth over its whole image.
    #[test]
    fn a_determined_term_is_kept() {
        let rig = SyntheticRig::covered(0.1, 5, 0.05);
        let cal = calibrated(&rig);
        let e = errors(&rig, &cal);
        for (d, c) in cal.lens.iter().enumerate() {
            let k3 = c.terms.iter().find(|t| t.param == LensParam::K3).unwrap();
            let camera = cal.devices[d].kind == hexcal_core::observations::DeviceKind::Camera;
            assert!(
                k3.tested && k3.estimated == camera,
                "{}: {k3:?}",
                cal.devices[d].name
            );
            assert!(
                e[d].0 <= 4.0 * e[d].2,
                "{}: {:?}",
                cal.devices[d].name,
                e[d]
            );
        }
    }
}
