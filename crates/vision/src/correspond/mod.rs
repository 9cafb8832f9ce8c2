//! Correspondences (docs/design.md §7): a camera's labelled grid and the projectors' decoded maps
//! in that camera become one [`CameraView`] — every labelled circle with its ellipse centre
//! and, for each projector lighting it, the projector pixel (u, v) at that centre.
//!
//! The projector pixel at an ellipse centre e comes from a least-squares fit of the decoded
//! u(x, y) and v(x, y) over the valid pixels of the circle and its labelled neighbours (one
//! planar patch, ≈ 7× a circle's pixels), evaluated at e. The fit is quadratic in (x − e):
//! lens distortion curves the camera→projector map, and a plain plane or homography over
//! the patch is biased by up to 0.2 projector px in the corners of a k1 = −0.3 lens.
//! Each pixel is weighted by its modulation² (inverse variance). A ringed (marker) circle
//! leaves its ring's band out; its white inside and outside the ring serves as any other.

use crate::grid::{Grid, LabelledPoint};
use crate::stats::median;
use hexcal_core::board::{Hex, Side};
use hexcal_core::observations::{CameraView, Frame, ProjectorPixel, ViewPoint};
use nalgebra::{Point2, SMatrix, SVector};
use std::collections::HashMap;
use {crate::detect::Circle, hexcal_core::images::Ellipse};

/// One projector's decoded maps in one camera, as the fit reads them.
#[derive(Clone, Copy, Debug)]
pub struct ProjectorMap<'a> {
    /// Device index of the projector.
    pub projector: usize,
    /// Map width (camera px).
    pub width: u32,
    /// Map height (camera px).
    pub height: u32,
    /// Projector column per camera pixel, row-major.
    pub u: &'a [f32],
    /// Projector row per camera pixel, row-major.
    pub v: &'a [f32],
    /// Whether (u, v) is valid, row-major.
    pub valid: &'a [bool],
    /// Modulation B per camera pixel (DN), row-major, when known: the fit weighs each
    /// pixel by B² (its phase noise is ∝ 1/B).
    pub modulation: Option<&'a [f32]>,
    /// When given, `u`, `v`, `valid` and `modulation` hold values at some pixels only, and
    /// pixel i's are at index `slots[i]` ([`crate::phase::NO_SLOT`]: none held, invalid);
    /// otherwise at index i.
    pub slots: Option<&'a [u32]>,
}

impl<'a> ProjectorMap<'a> {
    /// The view of a decoder's maps for projector `projector`.
    pub fn from_decoded(projector: usize, maps: &'a crate::phase::ProjectorMaps) -> Self {
        ProjectorMap {
            projector,
            width: maps.u.width(),
            height: maps.u.height(),
            u: maps.u.as_raw(),
            v: maps.v.as_raw(),
            valid: maps.valid.as_slice(),
            modulation: Some(maps.modulation.as_raw()),
            slots: None,
        }
    }

    /// The view of projector p's maps in a compact stack, read in place at the candidates
    /// through `slots` (the stack's [`crate::phase::CompactStack::candidate_slots`]), as
    /// device `projector`.
    pub fn from_compact(
        projector: usize,
        stack: &'a crate::phase::CompactStack,
        p: usize,
        slots: &'a [u32],
    ) -> Self {
        let c = &stack.projectors[p].at_candidates;
        ProjectorMap {
            projector,
            width: stack.ambient.width(),
            height: stack.ambient.height(),
            u: &c.u,
            v: &c.v,
            valid: &c.valid,
            modulation: Some(&c.modulation),
            slots: Some(slots),
        }
    }

    /// Where pixel i's values are held (None: nowhere, the pixel is invalid).
    fn slot(&self, i: usize) -> Option<usize> {
        match self.slots {
            None => Some(i),
            Some(s) => s
                .get(i)
                .filter(|&&k| k != crate::phase::NO_SLOT)
                .map(|&k| k as usize),
        }
    }

    /// Whether pixel i's (u, v) is valid.
    fn valid_at(&self, i: usize) -> bool {
        self.slot(i).is_some_and(|k| self.valid[k])
    }
}

/// Settings of the local fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitParams {
    /// Pixels used lie inside each patch circle's ellipse shrunk by this factor (keeps the
    /// blurred rim, where white and black mix, out of the fit).
    pub shrink: f64,
    /// Valid pixels a fit needs.
    pub min_pixels: usize,
    /// Fraction of the centre circle's own pixels that must be valid (a projector that
    /// lights only part of a circle gives no observation of it); of a ringed circle, the
    /// fraction of its patch's pixels (its own are too few and dimmed by the ring).
    pub min_own_valid: f64,
    /// A marker ring's band (inner, outer) as fractions of the circle's radius (the board's
    /// `ring`). On a ringed circle the band is left out of the circle's own pixels and of
    /// every fit: it is dark (no valid decoding). The white beside it, dimmed by the blur,
    /// stays in: the modulation weighting gives it its due (docs/design.md §7, "Ringed
    /// circles").
    pub ring: [f64; 2],
}

impl Default for FitParams {
    fn default() -> Self {
        FitParams {
            shrink: 0.85,
            min_pixels: 30,
            min_own_valid: 0.8,
            ring: [0.45, 0.75],
        }
    }
}

impl FitParams {
    /// The defaults with `board`'s ring band.
    pub fn for_board(board: &hexcal_core::board::Board) -> FitParams {
        FitParams {
            ring: board.ring,
            ..FitParams::default()
        }
    }

    /// The white of a circle: pixels (x, y) whose centres lie inside `e` shrunk by
    /// `shrink`, without the ring band when the circle is `ringed`.
    pub(crate) fn white_pixels(
        &self,
        e: &Ellipse,
        ringed: bool,
        width: u32,
        height: u32,
    ) -> Vec<(u32, u32)> {
        let band = ringed.then_some((self.ring[0], self.ring[1]));
        pixels_inside(e, self.shrink, band, width, height)
    }
}

/// Pixels (x, y) whose centres lie inside `e` shrunk by `shrink`, leaving out those whose
/// normalised radius (1 on the outline of `e`) lies strictly within `band`.
fn pixels_inside(
    e: &Ellipse,
    shrink: f64,
    band: Option<(f64, f64)>,
    width: u32,
    height: u32,
) -> Vec<(u32, u32)> {
    let (c, s) = (e.angle.cos(), e.angle.sin());
    let reach = (e.a * shrink).ceil() as i64 + 1;
    let (cx, cy) = (e.center.x.round() as i64, e.center.y.round() as i64);
    let mut out = Vec::new();
    for y in (cy - reach).max(0)..=(cy + reach).min(i64::from(height) - 1) {
        for x in (cx - reach).max(0)..=(cx + reach).min(i64::from(width) - 1) {
            let (dx, dy) = (x as f64 - e.center.x, y as f64 - e.center.y);
            let (p, q) = (dx * c + dy * s, -dx * s + dy * c);
            let rho = ((p / e.a).powi(2) + (q / e.b).powi(2)).sqrt();
            let in_band = band.is_some_and(|(lo, hi)| rho > lo && rho < hi);
            if rho <= shrink && !in_band {
                out.push((x as u32, y as u32));
            }
        }
    }
    out
}

/// A pixel whose (u, v) lies farther than this many robust standard deviations of the
/// patch's residuals from the first fit (and beyond [`GROSS_FLOOR`]) is left out of the
/// second: a wrong fringe order (a gross error, hundreds of projector px) is not noise, and
/// one among a thousand pixels would move the fit by a fraction of a pixel.
const GROSS_SIGMAS: f64 = 6.0;

/// Smallest residual taken for gross (projector px).
const GROSS_FLOOR: f64 = 1.0;

/// One valid pixel of a patch: the fit's row (24), its weight, and its (u, v).
type PatchRow = (SVector<f64, 6>, f64, [f64; 2]);

/// Quadratic fit (24) of u and v over `pixels` around `e`, evaluated at `e` (the constant
/// term); each pixel weighted by its modulation² when the map has it (its phase noise is
/// ∝ 1/B, so this is the inverse-variance weighting), else alike. Pixels the first fit
/// finds grossly off ([`GROSS_SIGMAS`]) are left out of a second.
fn fit_at(
    map: &ProjectorMap,
    pixels: &[(u32, u32)],
    e: Point2<f64>,
    scale: f64,
) -> Option<Point2<f64>> {
    let mut rows: Vec<PatchRow> = Vec::with_capacity(pixels.len());
    for &(x, y) in pixels {
        let Some(i) = map.slot((y * map.width + x) as usize) else {
            continue;
        };
        let (u, v) = (map.u[i], map.v[i]);
        if !map.valid[i] || !u.is_finite() || !v.is_finite() {
            continue;
        }
        let (dx, dy) = ((x as f64 - e.x) / scale, (y as f64 - e.y) / scale);
        let row = SVector::<f64, 6>::from([1.0, dx, dy, dx * dx, dx * dy, dy * dy]);
        let w = map
            .modulation
            .map_or(1.0, |b| f64::from(b[i]).max(0.0).powi(2));
        rows.push((row, w, [f64::from(u), f64::from(v)]));
    }
    let [cu, cv] = solve_rows(&rows)?;
    let residual = |(row, _, uv): &PatchRow| (uv[0] - cu.dot(row)).hypot(uv[1] - cv.dot(row));
    let r: Vec<f64> = rows.iter().map(residual).collect();
    // The median residual length of 2-D normal noise is 1.18σ.
    let sigma = median(&mut r.clone()) / 1.1774;
    let limit = (GROSS_SIGMAS * sigma).max(GROSS_FLOOR);
    if r.iter().all(|&ri| ri <= limit) {
        return Some(Point2::new(cu[0], cv[0]));
    }
    let kept: Vec<PatchRow> = (rows.into_iter().zip(r))
        .filter(|&(_, ri)| ri <= limit)
        .map(|(row, _)| row)
        .collect();
    let [cu, cv] = solve_rows(&kept)?;
    Some(Point2::new(cu[0], cv[0]))
}

/// The weighted least-squares coefficients of u and v over `rows` (at least 6).
fn solve_rows(rows: &[PatchRow]) -> Option<[SVector<f64, 6>; 2]> {
    if rows.len() < 6 {
        return None;
    }
    let mut ata = SMatrix::<f64, 6, 6>::zeros();
    let (mut atu, mut atv) = (SVector::<f64, 6>::zeros(), SVector::<f64, 6>::zeros());
    for (row, w, [u, v]) in rows {
        ata += row * row.transpose() * *w;
        atu += row * (w * u);
        atv += row * (w * v);
    }
    let chol = ata.cholesky()?;
    Some([chol.solve(&atu), chol.solve(&atv)])
}

/// Valid pixels of `pixels` under the map.
fn count_valid(map: &ProjectorMap, pixels: &[(u32, u32)]) -> usize {
    pixels
        .iter()
        .filter(|&&(x, y)| map.valid_at((y * map.width + x) as usize))
        .count()
}

/// How far off the circle the mean of its neighbours may lie, in neighbour spacings, for
/// them to surround it: 0 with all six, 0.2 with one missing, 0.43 on a row's edge (two
/// along the row, two inward).
const MAX_PATCH_OFFSET: f64 = 0.3;

/// Whether the neighbours of `patch` (its first entry the circle) lie around the circle
/// rather than to one side ([`MAX_PATCH_OFFSET`]).
fn surrounded(patch: &[(&Ellipse, bool)]) -> bool {
    let c = patch[0].0.center;
    let n = patch.len() - 1;
    if n == 0 {
        return false;
    }
    let offsets = patch[1..].iter().map(|(e, _)| e.center - c);
    let sum = offsets
        .clone()
        .fold(nalgebra::Vector2::zeros(), |s, d| s + d);
    let spacing = offsets.map(|d| d.norm()).sum::<f64>() / n as f64;
    sum.norm() / (n as f64 * spacing) <= MAX_PATCH_OFFSET
}

/// The projector pixel of the labelled circle `p` under one projector's map, fitted over
/// `patch` (the circle and its labelled neighbours, each with whether it is ringed); `None`
/// when the projector does not light the circle whole or the patch has too few valid pixels.
///
/// Whether it lights the circle whole is judged from the circle's own white pixels: at least
/// `min_own_valid` of them valid. A ringed circle its neighbours surround is judged over its
/// whole patch instead:
/// beside its ring the blur dims the white below the decoder's modulation floor, and at
/// radii of 5 px (9–22 white pixels left beside the ring band) a third of them are invalid
/// however wholly lit (docs/design.md §7). A projector edge across the circle still leaves
/// about half the patch unlit.
fn observe(
    m: &ProjectorMap,
    p: &LabelledPoint,
    patch: &[(&Ellipse, bool)],
    params: &FitParams,
) -> Option<ProjectorPixel> {
    let own = patch[0].0;
    let own_px = params.white_pixels(own, p.ringed, m.width, m.height);
    let own_valid = count_valid(m, &own_px);
    let pixels: Vec<(u32, u32)> = patch
        .iter()
        .flat_map(|&(e, ringed)| params.white_pixels(e, ringed, m.width, m.height))
        .collect();
    // Over the patch only where the neighbours surround the circle: a fit from one side
    // extrapolates into the ring's gap (up to 0.8 projector px in v at the edge of a view).
    let (valid, judged) = if p.ringed && surrounded(patch) {
        (count_valid(m, &pixels), pixels.len())
    } else {
        (own_valid, own_px.len())
    };
    if own_valid == 0
        || (valid as f64) < params.min_own_valid * judged as f64
        || pixels.len() < params.min_pixels
    {
        return None;
    }
    // Coordinates scaled to the patch size keep the normal equations tame.
    let scale = 3.0 * own.a.max(1.0);
    fit_at(m, &pixels, p.image, scale).map(|pixel| ProjectorPixel {
        projector: m.projector,
        pixel,
    })
}

/// The camera view of one grid: labelled circles with their ellipse centres and the
/// projector pixels at them. `circles` are the detections the grid was built from; `None`
/// when the grid has no labelled point. An unanchored grid gives an unanchored view (to be
/// registered by the calibration stage).
pub fn camera_view(
    camera: usize,
    pose: usize,
    grid: &Grid,
    circles: &[Circle],
    maps: &[ProjectorMap],
    params: &FitParams,
) -> Option<CameraView> {
    if grid.points.is_empty() {
        return None;
    }
    let frame = match (grid.anchored, grid.side) {
        (true, Some(side)) => Frame::Anchored(side),
        _ => Frame::Unanchored,
    };
    let by_hex: HashMap<_, _> = grid.points.iter().map(|p| (p.hex, p)).collect();
    let points = grid
        .points
        .iter()
        .map(|p| {
            let own = &circles[p.circle].ellipse;
            // The patch: this circle and its labelled neighbours, each without its ring.
            let patch: Vec<(&Ellipse, bool)> = std::iter::once((own, p.ringed))
                .chain(
                    p.hex
                        .neighbours()
                        .iter()
                        .filter_map(|h| by_hex.get(h))
                        .map(|q| (&circles[q.circle].ellipse, q.ringed)),
                )
                .collect();
            let projectors = maps
                .iter()
                .filter_map(|m| observe(m, p, &patch, params))
                .collect();
            ViewPoint {
                hex: p.hex,
                image: p.image,
                projectors,
            }
        })
        .collect();
    Some(CameraView {
        camera,
        pose,
        frame,
        points,
    })
}

#[cfg(test)]
mod rendered_stacks;
#[cfg(test)]
mod tests;

/// How well the cameras agree on one projector's pixels (docs/design.md §7): the same board
/// circle of the same pose, lit by the projector and seen by two cameras, should decode to
/// the same projector pixel.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Agreement {
    /// Device index of the projector.
    pub projector: usize,
    /// Camera pairs × shared circles compared.
    pub pairs: usize,
    /// RMS over those pairs of the difference per axis, divided by √2: one camera's
    /// observation noise if both are alike (projector px).
    pub rms: f64,
}

/// The agreement between cameras for every projector in `views` (anchored views only:
/// their labels name the same circle in every camera).
pub fn agreement(views: &[CameraView]) -> Vec<Agreement> {
    use std::collections::BTreeMap;
    // (projector, pose, side, hex) → the pixels the cameras decoded there.
    let mut seen: BTreeMap<(usize, usize, Side, Hex), Vec<Point2<f64>>> = BTreeMap::new();
    for v in views {
        let Frame::Anchored(side) = v.frame else {
            continue;
        };
        for p in &v.points {
            for q in &p.projectors {
                seen.entry((q.projector, v.pose, side, p.hex))
                    .or_default()
                    .push(q.pixel);
            }
        }
    }
    let mut per: BTreeMap<usize, (usize, f64)> = BTreeMap::new();
    for ((projector, ..), pixels) in &seen {
        for (i, a) in pixels.iter().enumerate() {
            for b in &pixels[i + 1..] {
                let e = per.entry(*projector).or_default();
                e.0 += 1;
                e.1 += (a - b).norm_squared();
            }
        }
    }
    per.into_iter()
        .map(|(projector, (pairs, sq))| Agreement {
            projector,
            pairs,
            // Two axes and two cameras' noise in each difference.
            rms: (sq / (4.0 * pairs.max(1) as f64)).sqrt(),
        })
        .collect()
}
