//! Between groups (docs/design.md §6b, eq. 6b.3): each group's mean image minus the overall
//! mean, regressed on the shapes, gives its light level and the board's displacement.

use super::{Block, Stack, StackFault, StackNote};
use crate::phase::check::CheckParams;

/// Light changes below this fraction of the mean level are not worth a note.
const LIGHT_NOTE: f64 = 0.01;

/// One group's regression summary.
struct GroupShift {
    /// Displacement from the mean position and its standard error (px).
    d: [f64; 2],
    se: f64,
    /// Light change relative to the mean level, and its standard error.
    light: f64,
    light_se: f64,
}

impl Stack<'_> {
    /// Motion faults and light-step notes between groups; gives each group's displacement.
    pub(super) fn between_groups(
        &self,
        params: &CheckParams,
        faults: &mut Vec<StackFault>,
        notes: &mut Vec<StackNote>,
    ) -> Vec<[f64; 2]> {
        let m = self.model;
        let (n, g) = (m.steps as f64, m.groups as f64);
        let mean_shapes = self.mean_shapes();
        // The group mean of a block: σ²/(4N), less the part the overall mean shares.
        let var = |blk: &Block| blk.var / (4.0 * n) * (1.0 - 1.0 / g);
        let cov = self.covariance(var);
        let shifts: Vec<GroupShift> = (0..m.groups)
            .map(|grp| {
                let target = |b: usize| {
                    (0..4)
                        .map(|j| {
                            f64::from(self.fits.pixel(4 * b + j).mean(grp)) - self.levels[4 * b + j]
                        })
                        .sum::<f64>()
                        / 4.0
                };
                let fit = self.regress(&cov, target, var);
                let (d, se) = fit.displacement();
                let light: f64 = (0..3).map(|i| fit.coef[i] * mean_shapes[i]).sum();
                let light_var: f64 = (0..3)
                    .flat_map(|i| (0..3).map(move |j| (i, j)))
                    .map(|(i, j)| mean_shapes[i] * fit.cov[(i, j)] * mean_shapes[j])
                    .sum();
                GroupShift {
                    d,
                    se: se[0].hypot(se[1]),
                    light: light / mean_shapes[2],
                    light_se: light_var.max(0.0).sqrt() / mean_shapes[2],
                }
            })
            .collect();
        if let Some(f) = motion(&shifts, params) {
            faults.push(f);
        }
        if let Some(note) = light_step(&shifts, params) {
            notes.push(note);
        }
        shifts.iter().map(|s| s.d).collect()
    }

    /// The mean of each shape over the usable blocks.
    pub(super) fn mean_shapes(&self) -> [f64; 5] {
        let mut s = [0.0; 5];
        let mut count = 0.0;
        for (_, blk) in self.usable() {
            for (a, b) in s.iter_mut().zip(blk.shapes) {
                *a += b;
            }
            count += 1.0;
        }
        s.map(|v| v / f64::max(count, 1.0))
    }
}

/// The motion fault, if the board moved more than the threshold (and significantly):
/// the step between consecutive groups when one dominates (≥ 60 % of the largest
/// separation), else the drift between the two groups farthest apart.
fn motion(shifts: &[GroupShift], params: &CheckParams) -> Option<StackFault> {
    let dist = |a: &GroupShift, b: &GroupShift| (a.d[0] - b.d[0]).hypot(a.d[1] - b.d[1]);
    let se = |a: &GroupShift, b: &GroupShift| a.se.hypot(b.se);
    let mut far = (0, 0, 0.0, 0.0);
    for (i, a) in shifts.iter().enumerate() {
        for (j, b) in shifts.iter().enumerate().skip(i + 1) {
            if dist(a, b) > far.2 {
                far = (i, j, dist(a, b), se(a, b));
            }
        }
    }
    let (i, j, px, sd) = far;
    if px <= params.motion_px || px <= params.z * sd {
        return None;
    }
    let step = (1..shifts.len())
        .map(|g| (g, dist(&shifts[g - 1], &shifts[g])))
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    Some(match step.1 >= 0.6 * px {
        true => StackFault::Motion {
            from_group: step.0 - 1,
            to_group: step.0,
            px: step.1,
        },
        false => StackFault::Motion {
            from_group: i,
            to_group: j,
            px,
        },
    })
}

/// The largest significant light step between consecutive groups, as a note.
fn light_step(shifts: &[GroupShift], params: &CheckParams) -> Option<StackNote> {
    (1..shifts.len())
        .map(|g| {
            let (a, b) = (&shifts[g - 1], &shifts[g]);
            (g, b.light - a.light, a.light_se.hypot(b.light_se))
        })
        .filter(|&(_, step, se)| step.abs() > LIGHT_NOTE && step.abs() > params.z * se)
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .map(|(g, step, _)| StackNote::LightStep {
            from_group: g - 1,
            to_group: g,
            percent: 100.0 * step,
        })
}
