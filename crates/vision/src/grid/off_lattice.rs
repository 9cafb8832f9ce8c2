//! The lattice check of labelled centres (docs/design.md §5, "Centres off the lattice"): a
//! circle an occluder cuts can keep a closed fit to what is left of it, labelled at its
//! lattice position but with its centre moved away from the cut (by up to a third of its
//! radius and more on 3 px circles at 70° of tilt). Each labelled centre is compared with
//! where a local homography fitted to its labelled neighbours puts its lattice position in
//! the image; a centre far off both its neighbourhood's residuals and its own size is
//! dropped.
//!
//! Takes a component (labelled circles in one lattice frame) and the detections; gives the
//! component without those points.

use super::assemble::Component;
use super::join::{apply, plane, residuals, sound_fit, Reference, OUTLIER_MEDIANS};
use super::GridParams;
use crate::detect::Circle;
use nalgebra::Point2;

/// Largest distance (image px) of a labelled centre from its lattice prediction, as a fraction
/// of its radius √(ab). Predictions of whole circles (noise, ellipse-centre bias and lens
/// distortion over the support, which a homography does not model) fall within 0.10 r across
/// tests/detect_sim.rs and tests/grid_occluders.rs, k1 = −0.3 included; a fit off by more
/// than 0.2 r is therefore at least 0.1 r off its circle, and every centre kept lies within
/// 0.2 r + 0.1 r of its circle, short of a third of its radius (where a detection no longer
/// marks its circle).
const MAX_OFFSET: f64 = 0.2;

/// Whether the `i`-th point of `r` lies off the lattice its neighbours predict: its plane
/// residual under a sound local fit (the `join_support` other points nearest it, as for
/// joining) exceeds [`OUTLIER_MEDIANS`] times the fit's median residual, and its image
/// centre lies more than [`MAX_OFFSET`]·`radius` from the image of its lattice position.
/// No sound fit: no verdict (kept).
fn off_lattice(r: &Reference, i: usize, radius: f64, params: &GridParams) -> bool {
    let (x, h) = r.points[i];
    let support: Vec<usize> = r
        .nearest(x, params.join_support + 1)
        .into_iter()
        .filter(|&j| j != i)
        .collect();
    let pairs = r.pairs(&support);
    let Some(fit) = sound_fit(
        pairs.clone(),
        params.join_fit_tolerance,
        params.join_fit_outliers,
    ) else {
        return false;
    };
    let mut res = residuals(&fit, &pairs);
    res.sort_by(f64::total_cmp);
    let median = res[res.len() / 2];
    let own = apply(&fit, x).map_or(f64::INFINITY, |p| (p - plane(h)).norm());
    let predicted = fit.try_inverse().and_then(|back| apply(&back, plane(h)));
    let offset = predicted.map_or(f64::INFINITY, |p| (p - x).norm());
    own > OUTLIER_MEDIANS * median && offset > MAX_OFFSET * radius
}

/// Drop the points of `comp` whose centres lie off the lattice (all judged against the
/// component as it stands, so the order does not matter). Gives the number dropped.
pub(crate) fn drop_off_lattice(
    comp: &mut Component,
    circles: &[Circle],
    params: &GridParams,
) -> usize {
    let centres: Vec<Point2<f64>> = circles.iter().map(|c| c.ellipse.center).collect();
    let r = Reference::new(comp, &centres);
    let off: Vec<bool> = comp
        .points
        .iter()
        .enumerate()
        .map(|(i, &(c, _))| off_lattice(&r, i, circles[c as usize].ellipse.radius(), params))
        .collect();
    let before = comp.points.len();
    let mut k = 0;
    comp.points.retain(|_| {
        k += 1;
        !off[k - 1]
    });
    before - comp.points.len()
}

#[cfg(test)]
mod tests;
