//! The tests of the stack check (docs/design.md §6b): between groups (motion, light steps),
//! per frame (light changes, jolts, another frame's pattern, unexplained disturbance), and
//! clipping; each finding sized in the unit its threshold is set in.

mod alone;
mod groups;
mod leak;
mod lit;
mod means;
mod per_frame;
mod phases;

use super::fit::{chi2_median_ratio, means_median_ratio, robust_noise, Fits, GroupFits, PixelFit};
use super::{CheckFigures, CheckParams, StackFault, StackNote, StackSampler, StackVerdict};
use crate::phase::NoiseModel;
use hexcal_core::pattern::{Direction, Sequence};
use nalgebra::{SMatrix, SVector};
use rayon::prelude::*;

/// Spatial shapes of the regressions: offset, ambient image, mean image, its x and y
/// gradients.
const SHAPES: usize = 5;

/// Smallest per-pixel variance used as a weight (DN²): far below any sensor's, it only keeps
/// the weights of a noise-free stack finite.
const MIN_VAR: f64 = 1e-9;

/// A block's shapes, noise and fit summary.
struct Block {
    /// The shapes at the block: [1, ambient, level, ∂x level, ∂y level] (DN, DN/px).
    shapes: [f64; SHAPES],
    /// Per-pixel noise σ_I² at the block's level (DN²).
    var: f64,
}

impl StackVerdict {
    /// The verdict on a stack that could not be checked (a sequence that leaves nothing
    /// to test).
    pub fn unchecked() -> StackVerdict {
        unchecked(0)
    }
}

/// The verdict of a sequence that leaves nothing to test (`blocks` sampled).
pub(super) fn unchecked(blocks: usize) -> StackVerdict {
    StackVerdict {
        faults: Vec::new(),
        notes: vec![StackNote::Unchecked],
        figures: CheckFigures {
            samples: 4 * blocks,
            noise: NoiseModel {
                offset: 0.0,
                slope: 0.0,
                floor: 0.0,
            },
            displacement: Vec::new(),
            disturbance: Vec::new(),
            clipped: 0.0,
        },
    }
}

/// Everything the tests share: the fits per pixel, the noise model, the blocks.
struct Stack<'a> {
    model: &'a GroupFits,
    /// Residuals, frame-major (pixel i of frame k at [k·m + i], m = [`Fits::len`]).
    residuals: Vec<f32>,
    fits: Fits,
    /// Per pixel, its mean level over the groups (DN).
    levels: Vec<f64>,
    /// Per block: whether it clips.
    clipped: Vec<bool>,
    noise: NoiseModel,
    /// Per unclipped block index, its shapes (`None` for clipped blocks).
    blocks: Vec<Option<Block>>,
    frames: usize,
}

/// The verdict on a sampled stack.
pub(super) fn judge(
    mut sampler: StackSampler,
    model: &GroupFits,
    params: &CheckParams,
) -> StackVerdict {
    let mut stack = Stack::fit(&mut sampler, model);
    let mut faults = Vec::new();
    let mut notes = Vec::new();
    let displacement = stack.between_groups(params, &mut faults, &mut notes);
    let (within, disturbance) = stack.within_groups(params);
    let phases = stack.phase_consistency(&sampler.seq, params);
    faults.extend(merge(within, phases, stack.model.steps));
    // A lag changes its group's mean image too (by (1/N)·Σ of the pattern change), which the
    // gradient shapes partly take for motion: the lag is the cause, and so are phases that
    // do not unwrap (a whole group shown late).
    let lagged: Vec<usize> = (faults.iter())
        .filter_map(|f| match *f {
            StackFault::WrongPattern { group, .. } => Some(group..=group),
            StackFault::Unwrapping { groups, .. } => Some(groups[0]..=groups[1]),
            _ => None,
        })
        .flatten()
        .collect();
    faults.retain(|f| match f {
        StackFault::Motion {
            from_group,
            to_group,
            ..
        } => !lagged.contains(from_group) && !lagged.contains(to_group),
        _ => true,
    });
    let clipped = stack.clipped_fraction(sampler.full_scale);
    if clipped > params.clipped {
        faults.push(StackFault::Clipped { fraction: clipped });
    }
    // A repair measures the noise without the groups it leaves out (a lag's group mean or
    // residuals would count as noise) and the decoder takes that noise.
    if let Some(out) = super::repair::plan(&faults, &sampler.seq) {
        let noise = stack.set_noise(stack.noise_without(out));
        match stack.repair_holds(&sampler.seq, params, out) {
            true => notes.extend(faults.drain(..).map(|fault| StackNote::Repaired { fault })),
            false => _ = stack.set_noise(noise),
        }
    }
    // After the repair: a lag the fusion hid took its direction's orders astray, which a
    // repair (orders from every group) would not undo.
    name_hidden_lags(&stack, &sampler.seq, params, &mut faults);
    name_light_inside(&mut notes, stack.model.steps, &mut faults);
    stack.modulation_notes(sampler.full_scale, params, &mut notes);
    // A figure of a stack with nothing usable (every block clipped) may be 0/0: kept as 0.
    let finite = |v: f64| if v.is_finite() { v } else { 0.0 };
    StackVerdict {
        faults,
        notes,
        figures: CheckFigures {
            samples: stack.fits.len(),
            noise: NoiseModel {
                offset: finite(stack.noise.offset),
                slope: finite(stack.noise.slope),
                floor: finite(stack.noise.floor),
            },
            displacement: displacement.iter().map(|d| d.map(finite)).collect(),
            disturbance: disturbance.into_iter().map(finite).collect(),
            clipped: finite(clipped),
        },
    }
}

impl<'a> Stack<'a> {
    /// Fit every sampled pixel (on all cores), measure the noise, form the blocks' shapes;
    /// the sampler's samples become the residuals.
    fn fit(sampler: &mut StackSampler, model: &'a GroupFits) -> Stack<'a> {
        let k = sampler.seq.frame_count();
        let mut residuals = std::mem::take(&mut sampler.samples);
        let fits = model.fit(&mut residuals, 4 * sampler.blocks.len());
        let levels: Vec<f64> = (0..fits.len())
            .into_par_iter()
            .map(|i| fits.pixel(i).level())
            .collect();
        let noise = measure_noise(&fits, &levels, &sampler.clipped, model, 0);
        let blocks = (0..sampler.blocks.len())
            .into_par_iter()
            .map(|b| (!sampler.clipped[b]).then(|| block(&fits, &levels, b, model, &noise)))
            .collect();
        Stack {
            model,
            residuals,
            fits,
            levels,
            clipped: sampler.clipped.clone(),
            noise,
            blocks,
            frames: k,
        }
    }

    /// The noise model measured without the groups in `left_out` (a bit each).
    fn noise_without(&self, left_out: u32) -> NoiseModel {
        measure_noise(
            &self.fits,
            &self.levels,
            &self.clipped,
            self.model,
            left_out,
        )
    }

    /// Give every block the variance of `noise`; the noise it replaces is returned.
    fn set_noise(&mut self, noise: NoiseModel) -> NoiseModel {
        for blk in self.blocks.iter_mut().flatten() {
            blk.var = block_var(&noise, blk.shapes[2]);
        }
        std::mem::replace(&mut self.noise, noise)
    }

    /// The unclipped blocks with their index.
    fn usable(&self) -> impl Iterator<Item = (usize, &Block)> {
        self.blocks
            .iter()
            .enumerate()
            .filter_map(|(b, x)| x.as_ref().map(|x| (b, x)))
    }

    /// Regress a per-block target on the shapes with per-block variances: the coefficients,
    /// their covariance, and the sum of squares they explain (in units of the variances);
    /// `cov` is [`Self::covariance`] of `var`, computed once for many targets.
    fn regress(
        &self,
        cov: &SMatrix<f64, SHAPES, SHAPES>,
        target: impl Fn(usize) -> f64,
        var: impl Fn(&Block) -> f64,
    ) -> Fit {
        let mut atb = SVector::<f64, SHAPES>::zeros();
        for (b, blk) in self.usable() {
            atb += target(b) / var(blk) * SVector::<f64, SHAPES>::from(blk.shapes);
        }
        Fit::new(*cov, atb)
    }

    /// (Σ_b x_b x_bᵀ / var_b)⁻¹ over the usable blocks' shapes x_b: scaled to unit diagonal,
    /// then a pseudo-inverse, so shapes the image cannot tell apart (no unlit region, a flat
    /// image) get no coefficient rather than a wild one.
    fn covariance(&self, var: impl Fn(&Block) -> f64) -> SMatrix<f64, SHAPES, SHAPES> {
        let mut ata = SMatrix::<f64, SHAPES, SHAPES>::zeros();
        for (_, blk) in self.usable() {
            let x = SVector::<f64, SHAPES>::from(blk.shapes);
            ata += x * x.transpose() / var(blk);
        }
        if !ata.iter().all(|v| v.is_finite()) {
            return SMatrix::zeros();
        }
        let d = SVector::<f64, SHAPES>::from_fn(|i, _| 1.0 / ata[(i, i)].max(1e-300).sqrt());
        let scaled = SMatrix::<f64, SHAPES, SHAPES>::from_fn(|i, j| ata[(i, j)] * d[i] * d[j]);
        let cov_s = scaled
            .pseudo_inverse(1e-9)
            .unwrap_or_else(|_| SMatrix::zeros());
        SMatrix::<f64, SHAPES, SHAPES>::from_fn(|i, j| cov_s[(i, j)] * d[i] * d[j])
    }
}

/// A regression's result.
struct Fit {
    coef: SVector<f64, SHAPES>,
    cov: SMatrix<f64, SHAPES, SHAPES>,
    /// Sum of squares explained (χ² units).
    explained: f64,
}

impl Fit {
    /// The fit of right-hand side Σ_b x_b·target_b/var_b with covariance `cov`.
    fn new(cov: SMatrix<f64, SHAPES, SHAPES>, atb: SVector<f64, SHAPES>) -> Fit {
        let coef = cov * atb;
        Fit {
            explained: coef.dot(&atb),
            coef,
            cov,
        }
    }

    /// The displacement it implies (the image moved by d: Δ ≈ −∇A·d) and its standard
    /// error (camera px).
    fn displacement(&self) -> ([f64; 2], [f64; 2]) {
        (
            [-self.coef[3], -self.coef[4]],
            [self.cov[(3, 3)].sqrt(), self.cov[(4, 4)].sqrt()],
        )
    }

    /// The light part (offset, ambient, level) at a block (DN).
    fn light(&self, blk: &Block) -> f64 {
        (0..3).map(|i| self.coef[i] * blk.shapes[i]).sum()
    }

    /// The motion part (gradients) at a block (DN).
    fn motion(&self, blk: &Block) -> f64 {
        (3..5).map(|i| self.coef[i] * blk.shapes[i]).sum()
    }
}

/// The noise model of the unclipped pixels' residuals, or group means, of the groups not in
/// `left_out` (a bit each).
fn measure_noise(
    fits: &Fits,
    levels: &[f64],
    clipped: &[bool],
    model: &GroupFits,
    left_out: u32,
) -> NoiseModel {
    // The unclipped pixels by level, ties by index: the (level, variance) pairs come in
    // the order robust_noise sorts them in, and only a sixth as many are sorted.
    let mut by_level: Vec<(f64, usize)> = (0..fits.len())
        .filter(|i| !clipped[i / 4])
        .map(|i| (levels[i], i))
        .collect();
    by_level.par_sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let pairs: Vec<(f64, f64)> = (by_level.par_iter())
        .flat_map_iter(|&(level, i)| {
            (fits.pixel(i).variances(model.dof(), model.steps, left_out)).map(move |v| (level, v))
        })
        .collect();
    let kept = model.groups - left_out.count_ones() as usize;
    let ratio = match model.dof() >= 2 {
        true => chi2_median_ratio(model.dof() as f64),
        false => means_median_ratio(kept),
    };
    robust_noise(pairs, ratio)
}

/// Block b's shapes from its four pixels' fits and `levels` (corners (0,0), (1,0), (0,1),
/// (1,1)).
fn block(fits: &Fits, levels: &[f64], b: usize, model: &GroupFits, noise: &NoiseModel) -> Block {
    let pixels = || (4 * b..4 * b + 4).map(|i| fits.pixel(i));
    let levels = &levels[4 * b..4 * b + 4];
    let level = levels.iter().sum::<f64>() / 4.0;
    let lit: f64 = (0..model.projectors)
        .map(|p| {
            let b = pixels().map(|f| f.modulation(p)).sum::<f64>() / 4.0;
            model.mean_ratio[p] * b
        })
        .sum();
    let gx = 0.5 * ((levels[1] + levels[3]) - (levels[0] + levels[2]));
    let gy = 0.5 * ((levels[2] + levels[3]) - (levels[0] + levels[1]));
    Block {
        shapes: [1.0, (level - lit).max(0.0), level, gx, gy],
        var: block_var(noise, level),
    }
}

/// A block's per-pixel noise variance σ_I² at its mean `level`: a noise-free stack
/// (rendered without noise) still gets finite weights.
fn block_var(noise: &NoiseModel, level: f64) -> f64 {
    noise.sigma(level).powi(2).max(MIN_VAR)
}

impl Block {
    /// Projector p's B² in group g at the block's pixel `f` (N `steps`): |C|² = B² + 4σ_I²/N
    /// on average, so B² without the noise's share.
    fn modulation_sq(&self, f: PixelFit, g: usize, p: usize, steps: usize) -> f64 {
        let [re, im] = f.fundamental(g, p);
        let c2 = f64::from(re).powi(2) + f64::from(im).powi(2);
        (c2 - 4.0 * self.var / steps as f64).max(0.0)
    }

    /// Whether the block is away from albedo edges (its level changes by under 2 % per
    /// pixel): there every group's phase is the pixel centre's, not a mix of differently
    /// bright neighbours'.
    fn interior(&self) -> bool {
        let level = self.shapes[2];
        self.shapes[3].hypot(self.shapes[4]) < 0.02 * level
    }
}

/// The within-group faults (from the residuals) and the phase faults (group, fault) as one
/// list, one name per disturbance: a light change or jolt the residuals name explains its
/// group's phase disagreement; a phase fault names what the residuals only call disturbed.
fn merge(
    within: Vec<StackFault>,
    phases: Vec<(usize, StackFault)>,
    steps: usize,
) -> Vec<StackFault> {
    let in_group = |f: &StackFault, g: usize| {
        let frames = match *f {
            StackFault::LightChange {
                first_frame,
                last_frame,
                ..
            }
            | StackFault::Jolt {
                first_frame,
                last_frame,
                ..
            }
            | StackFault::Disturbed {
                first_frame,
                last_frame,
                ..
            } => first_frame..=last_frame,
            _ => return false,
        };
        frames.start() / steps <= g && g <= frames.end() / steps
    };
    let named = |g: usize| {
        within.iter().any(|f| {
            matches!(f, StackFault::LightChange { .. } | StackFault::Jolt { .. }) && in_group(f, g)
        })
    };
    let kept: Vec<(usize, StackFault)> = phases.into_iter().filter(|(g, _)| !named(*g)).collect();
    let explained = |f: &StackFault| {
        matches!(f, StackFault::Disturbed { .. }) && kept.iter().any(|(g, _)| in_group(f, *g))
    };
    let mut out: Vec<StackFault> = within.iter().filter(|f| !explained(f)).cloned().collect();
    out.extend(kept.into_iter().map(|(_, f)| f));
    out
}

/// A refused stack: the wrong patterns the phases named checked against the groups' means
/// ([`drop_misplaced_patterns`]); with none left, the lags its groups' mean images show
/// (6b.12, named per group) and those its groups show against their direction's other counts alone
/// (6b.11, named per direction) replace what the other tests made of them there (light
/// changing or phases disagreeing in their groups, positions that do not unwrap, disturbed
/// frames, motion next to them). A group with a jolt named keeps it: a jolt moves the fringes
/// too, which leaves them in the group's mean.
fn name_hidden_lags(
    stack: &Stack,
    seq: &Sequence,
    params: &CheckParams,
    faults: &mut Vec<StackFault>,
) {
    if faults.is_empty() {
        return;
    }
    let n = stack.model.steps;
    let jolted = |g: usize| {
        (faults.iter())
            .any(|f| matches!(*f, StackFault::Jolt { first_frame, .. } if first_frame / n == g))
    };
    let mut lags: Vec<Placed> = (stack.lags_in_means(params).into_iter())
        .filter_map(|f| Some((lag_place(&f)?, f)))
        .filter(|((_, [g, _]), _)| !jolted(*g))
        .map(|((p, groups), f)| (p, groups, f))
        .collect();
    if !drop_misplaced_patterns(faults, &lags) {
        return;
    }
    // A direction's lag that a group's mean places is named there (6b.11 names the
    // projector of the largest bias, which the lag's leak into the others' bins may make
    // another's); what it explains in the direction (its fusion went astray) stays explained.
    let mut spans: Vec<[usize; 2]> = lags.iter().map(|l| l.1).collect();
    for f in stack.lags_alone(seq, params) {
        let Some((p, [a, b])) = lag_place(&f) else {
            continue;
        };
        spans.push([a, b]);
        if !lags.iter().any(|(_, [g, _], _)| a <= *g && *g <= b) {
            lags.push((p, [a, b], f));
        }
    }
    // A lag biases its projector's fused positions, and through them the phases of its
    // direction's other groups.
    let n_col = seq.counts(Direction::Columns).len();
    let direction = |g: usize| match g < n_col {
        true => [0, n_col - 1],
        false => [n_col, stack.model.groups - 1],
    };
    let within = |[a, b]: [usize; 2]| spans.iter().any(|&[g, h]| g <= a && b <= h);
    let overlaps = |p: usize, [a, b]: [usize; 2]| {
        lags.iter()
            .any(|(q, [g, h], _)| q.contains(&p) && a <= *h && *g <= b)
    };
    faults.retain(|f| match *f {
        StackFault::Motion {
            from_group,
            to_group,
            ..
        } => !within([from_group, from_group]) && !within([to_group, to_group]),
        StackFault::LightChange {
            first_frame,
            last_frame,
            ..
        }
        | StackFault::Disturbed {
            first_frame,
            last_frame,
            ..
        }
        | StackFault::Jolt {
            first_frame,
            last_frame,
            ..
        } => !within([first_frame / n, last_frame / n]),
        StackFault::PhaseDisagreement {
            projector, group, ..
        } => !within([group, group]) && !overlaps(projector, direction(group)),
        StackFault::Unwrapping {
            projector, groups, ..
        } => !within(groups) && !overlaps(projector, groups),
        _ => true,
    });
    faults.extend(lags.into_iter().map(|l| l.2));
}

/// The wrong patterns the phases named (6b.5) against the lags the groups' means show
/// (6b.12): the phases place a lag through its projector's phase and modulation change,
/// which its leak into the other projectors' bins of the group can mimic, and through the
/// fusion, which can spread it to another group; the mean places it directly. A wrong
/// pattern that no lag in the `means` matches (its group, its projector among theirs) is
/// dropped, for those lags to be named instead. Whether the stack is left with no wrong
/// pattern (true also when it had none).
fn drop_misplaced_patterns(faults: &mut Vec<StackFault>, means: &[Placed]) -> bool {
    let matched = |p: usize, g: usize| {
        (means.iter()).any(|(projectors, [group, _], _)| *group == g && projectors.contains(&p))
    };
    faults.retain(|f| match *f {
        StackFault::WrongPattern {
            projector, group, ..
        } => means.is_empty() || matched(projector, group),
        _ => true,
    });
    !faults
        .iter()
        .any(|f| matches!(f, StackFault::WrongPattern { .. }))
}

/// A light step between groups next to a group whose light changed or whose phases
/// disagree: the step happened inside that group. A step exactly between groups leaves
/// every group's phases alone (each group is measured against its own mean); one inside
/// group g adds the light's shape to g's bins (6b.8), and where it is large its phases go to
/// wrong fringe orders, which 6b.8 cannot read. On a stack with no lag named, the light
/// change (sized by the step between the groups' means: less than the step inside) replaces
/// g's phase faults and its direction's unwrapping; and the note that called the step
/// harmless goes.
fn name_light_inside(notes: &mut Vec<StackNote>, n: usize, faults: &mut Vec<StackFault>) {
    let lag = |f: &StackFault| {
        matches!(
            f,
            StackFault::WrongPattern { .. }
                | StackFault::LagInGroups { .. }
                | StackFault::FringesInMean { .. }
        )
    };
    let no_lag = !faults.iter().any(lag);
    let mut inside = Vec::new();
    for (i, note) in notes.iter().enumerate() {
        let StackNote::LightStep {
            from_group,
            to_group,
            percent,
        } = *note
        else {
            continue;
        };
        let light = |g: usize| {
            (faults.iter()).any(|f| matches!(*f, StackFault::LightChange { first_frame, last_frame, .. } if first_frame / n <= g && g <= last_frame / n))
        };
        let disagrees = |g: usize| {
            (faults.iter())
                .any(|f| matches!(*f, StackFault::PhaseDisagreement { group, .. } if group == g))
        };
        if light(from_group) || light(to_group) {
            inside.push(i);
            continue;
        }
        let Some(g) = [from_group, to_group].into_iter().find(|&g| disagrees(g)) else {
            continue;
        };
        if !no_lag {
            continue;
        }
        faults.retain(|f| match *f {
            StackFault::PhaseDisagreement { group, .. } => group != g,
            StackFault::Unwrapping { groups, .. } => !(groups[0] <= g && g <= groups[1]),
            _ => true,
        });
        faults.push(StackFault::LightChange {
            first_frame: g * n,
            last_frame: g * n + n - 1,
            percent: percent.abs(),
        });
        inside.push(i);
    }
    for i in inside.into_iter().rev() {
        notes.remove(i);
    }
}

/// A lag with its projectors and first and last group.
type Placed = (Vec<usize>, [usize; 2], StackFault);

/// A lag's projectors and groups.
fn lag_place(f: &StackFault) -> Option<(Vec<usize>, [usize; 2])> {
    match f {
        StackFault::LagInGroups {
            projector, groups, ..
        } => Some((vec![*projector], *groups)),
        StackFault::FringesInMean {
            projectors, group, ..
        } => Some((projectors.clone(), [*group, *group])),
        _ => None,
    }
}

/// Consecutive runs of equal keys: (first, last, key) for indices with `Some(key)`.
pub(super) fn runs<K: PartialEq + Copy>(keys: &[Option<K>]) -> Vec<(usize, usize, K)> {
    let mut out: Vec<(usize, usize, K)> = Vec::new();
    for (i, k) in keys.iter().enumerate() {
        let Some(k) = *k else { continue };
        match out.last_mut() {
            Some(last) if last.1 + 1 == i && last.2 == k => last.1 = i,
            _ => out.push((i, i, k)),
        }
    }
    out
}
