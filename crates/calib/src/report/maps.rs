//! Maps of one device over its image (docs/design.md §8, "Maps"), as mrcal's tools draw
//! them: the projection uncertainty with the region where it meets the user's target, and
//! the lens's displacement field (where the lens puts each ray against a pinhole).
//!
//! Takes a device's lens model and the covariance of its free lens parameters (from a
//! [`Calibration`](crate::calib::solve::Calibration) or a `calibration.json` record);
//! gives the maps as values on a grid of cells and as self-contained SVG pictures with
//! pixel axes, for the report and `hexcal show`.

use super::html::viridis;
use super::DeviceRecord;
use crate::calib::diagnostics::lens_uncertainty;
use hexcal_core::camera::{CameraModel, LensParam};
use nalgebra::{DMatrix, Point2, Point3};
use std::fmt::Write;

/// Cells across the longer image side.
const CELLS: usize = 48;

/// A value per cell of a grid over the image.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageMap {
    /// Image width and height (px).
    pub size: [u32; 2],
    /// Cells across and down.
    pub cells: [usize; 2],
    /// Row-major values (`None` where the model has no ray).
    pub values: Vec<Option<f64>>,
}

/// The cell counts (across, down) of a grid of about [`CELLS`] cells across the longer side
/// of `model`'s image, and `f` at every cell centre, row by row.
fn on_cells<T>(model: &CameraModel, f: impl Fn(Point2<f64>) -> T) -> ([usize; 2], Vec<T>) {
    let (w, h) = (model.width as f64, model.height as f64);
    let cell = w.max(h) / CELLS as f64;
    let cells = [
        (w / cell).round().max(1.0) as usize,
        (h / cell).round().max(1.0) as usize,
    ];
    let values = (0..cells[0] * cells[1])
        .map(|i| {
            let (cx, cy) = ((i % cells[0]) as f64 + 0.5, (i / cells[0]) as f64 + 0.5);
            f(Point2::new(
                cx * w / cells[0] as f64 - 0.5,
                cy * h / cells[1] as f64 - 0.5,
            ))
        })
        .collect();
    (cells, values)
}

impl ImageMap {
    /// `f` at every cell centre of a grid of about [`CELLS`] cells across the longer side.
    fn of(model: &CameraModel, f: impl Fn(Point2<f64>) -> Option<f64>) -> ImageMap {
        let (cells, values) = on_cells(model, f);
        ImageMap {
            size: [model.width, model.height],
            cells,
            values,
        }
    }

    /// The largest value.
    pub fn max(&self) -> Option<f64> {
        self.values.iter().flatten().copied().reduce(f64::max)
    }

    /// The fraction of cells whose value is at most `limit`.
    pub fn fraction_within(&self, limit: f64) -> f64 {
        let ok = self
            .values
            .iter()
            .flatten()
            .filter(|v| **v <= limit)
            .count();
        ok as f64 / self.values.len().max(1) as f64
    }
}

/// A device's lens and the covariance of its free parameters.
#[derive(Clone, Debug)]
pub struct LensWithCovariance {
    /// The lens model.
    pub model: CameraModel,
    /// The estimated parameters.
    pub free: Vec<LensParam>,
    /// Their covariance.
    pub cov: DMatrix<f64>,
}

impl LensWithCovariance {
    /// From a `calibration.json` record; `None` when it holds no covariance or names a
    /// parameter hexcal does not know.
    pub fn of_record(r: &DeviceRecord) -> Option<LensWithCovariance> {
        let free: Option<Vec<LensParam>> = (r.lens_params.iter())
            .map(|n| LensParam::ALL.iter().copied().find(|p| p.name() == n))
            .collect();
        let n = r.lens_params.len();
        let square =
            r.lens_covariance.len() == n && r.lens_covariance.iter().all(|row| row.len() == n);
        (n > 0 && square).then_some(())?;
        Some(LensWithCovariance {
            model: r.model(),
            free: free?,
            cov: DMatrix::from_fn(n, n, |i, j| r.lens_covariance[i][j]),
        })
    }

    /// The projection uncertainty (px, 1σ along the worst direction) over the image.
    pub fn uncertainty_map(&self) -> ImageMap {
        ImageMap::of(&self.model, |p| {
            lens_uncertainty(&self.model, &self.free, &self.cov, p)
        })
    }
}

/// The lens's displacement over the image (px): per cell, |distorted − pinhole| of the ray
/// through the cell centre, and the vector itself for the arrows.
pub fn distortion_map(model: &CameraModel) -> (ImageMap, Vec<Option<[f64; 2]>>) {
    let pinhole = CameraModel {
        distortion: Default::default(),
        ..*model
    };
    let shift = |p: Point2<f64>| -> Option<[f64; 2]> {
        let ray = model.ray(p)?;
        let q = pinhole.project(&Point3::from(ray))?;
        Some([p.x - q.x, p.y - q.y])
    };
    let (cells, vectors) = on_cells(model, shift);
    let values = vectors.iter().map(|v| v.map(|[x, y]| x.hypot(y))).collect();
    let map = ImageMap {
        size: [model.width, model.height],
        cells,
        values,
    };
    (map, vectors)
}

/// Picture width (SVG units) of a map.
const PICTURE: f64 = 480.0;

/// The SVG frame around a map: the cells coloured by `scale` (value → [0, 1]), grey where
/// there is none, pixel axes; gives the picture so far and the scale factor px → units.
fn cells_svg(map: &ImageMap, title: &str, scale: impl Fn(f64) -> f64) -> (String, f64) {
    let [w, h] = map.size.map(f64::from);
    let k = PICTURE / w;
    let (pw, ph) = (PICTURE, h * k);
    let mut s = String::new();
    let _ = write!(
        s,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"-50 -30 {} {}\" \
         font-family=\"sans-serif\" font-size=\"12\" shape-rendering=\"crispEdges\">\
         <text x=\"0\" y=\"-10\">{title}</text>",
        pw + 170.0,
        ph + 70.0
    );
    let [cw, ch] = map.cells;
    let (dx, dy) = (pw / cw as f64, ph / ch as f64);
    for (i, v) in map.values.iter().enumerate() {
        let fill = v.map_or("#888888".to_string(), |v| viridis(scale(v)));
        let _ = write!(
            s,
            "<rect x=\"{:.2}\" y=\"{:.2}\" width=\"{:.2}\" height=\"{:.2}\" fill=\"{fill}\"/>",
            (i % cw) as f64 * dx,
            (i / cw) as f64 * dy,
            dx + 0.05,
            dy + 0.05
        );
    }
    let _ = write!(
        s,
        "<rect x=\"0\" y=\"0\" width=\"{pw:.1}\" height=\"{ph:.1}\" fill=\"none\" stroke=\"black\"/>\
         <text x=\"0\" y=\"{:.1}\">0</text><text x=\"{pw:.1}\" y=\"{:.1}\" text-anchor=\"end\">{w} px</text>\
         <text x=\"-5\" y=\"{ph:.1}\" text-anchor=\"end\">{h} px</text>",
        ph + 15.0,
        ph + 15.0
    );
    (s, k)
}

/// A colour bar from `lo` to `hi` labelled with `labels` (value, text) at the right of a
/// picture `height` high; `scale` maps a value to [0, 1].
fn colour_bar(s: &mut String, height: f64, labels: &[(f64, String)], scale: impl Fn(f64) -> f64) {
    let x = PICTURE + 20.0;
    for i in 0..50 {
        let t = 1.0 - (i as f64 + 0.5) / 50.0;
        let _ = write!(
            s,
            "<rect x=\"{x}\" y=\"{:.2}\" width=\"16\" height=\"{:.2}\" fill=\"{}\"/>",
            i as f64 * height / 50.0,
            height / 50.0 + 0.05,
            viridis(t)
        );
    }
    for (v, text) in labels {
        let y = (1.0 - scale(*v).clamp(0.0, 1.0)) * height;
        let _ = write!(
            s,
            "<text x=\"{}\" y=\"{:.1}\">{text}</text>",
            x + 22.0,
            y + 4.0
        );
    }
}

/// The projection-uncertainty map as SVG: log colour scale from target/10 to target·10, the
/// cells within `target` px outlined (the valid region at the user's target).
pub fn uncertainty_svg(map: &ImageMap, name: &str, target: f64) -> String {
    let scale = |v: f64| ((v / target).log10() + 1.0) / 2.0;
    let title = format!(
        "{name}: projection uncertainty (px, 1σ); within {target} px in {:.0} % of the image",
        100.0 * map.fraction_within(target)
    );
    let (mut s, k) = cells_svg(map, &title, scale);
    let [cw, ch] = map.cells;
    let [w, h] = map.size.map(f64::from);
    let (dx, dy) = (w * k / cw as f64, h * k / ch as f64);
    let ok = |x: usize, y: usize| map.values[y * cw + x].is_some_and(|v| v <= target);
    s.push_str("<path fill=\"none\" stroke=\"white\" stroke-width=\"2\" d=\"");
    for y in 0..ch {
        for x in 0..cw {
            if !ok(x, y) {
                continue;
            }
            let (x0, y0) = (x as f64 * dx, y as f64 * dy);
            if x == 0 || !ok(x - 1, y) {
                let _ = write!(s, "M{x0:.1} {y0:.1}v{dy:.1}");
            }
            if x + 1 == cw || !ok(x + 1, y) {
                let _ = write!(s, "M{:.1} {y0:.1}v{dy:.1}", x0 + dx);
            }
            if y == 0 || !ok(x, y - 1) {
                let _ = write!(s, "M{x0:.1} {y0:.1}h{dx:.1}");
            }
            if y + 1 == ch || !ok(x, y + 1) {
                let _ = write!(s, "M{x0:.1} {:.1}h{dx:.1}", y0 + dy);
            }
        }
    }
    s.push_str("\"/>");
    let labels: Vec<(f64, String)> = [0.1, 0.3, 1.0, 3.0, 10.0]
        .iter()
        .map(|f| (f * target, format!("{:.3} px", f * target)))
        .collect();
    colour_bar(&mut s, h * k, &labels, scale);
    s.push_str("</svg>\n");
    s
}

/// The lens's displacement field as SVG: the magnitude in colour (0 to the largest), an
/// arrow per few cells (scaled so the longest is two cells long).
pub fn distortion_svg(map: &ImageMap, vectors: &[Option<[f64; 2]>], name: &str) -> String {
    let top = map.max().unwrap_or(0.0).max(1e-9);
    let scale = |v: f64| v / top;
    let title = format!("{name}: lens displacement against a pinhole (px); largest {top:.1} px");
    let (mut s, k) = cells_svg(map, &title, scale);
    let [cw, ch] = map.cells;
    let [w, h] = map.size.map(f64::from);
    let (dx, dy) = (w * k / cw as f64, h * k / ch as f64);
    let arrow = 2.0 * dx / top;
    s.push_str("<path stroke=\"white\" stroke-width=\"1\" d=\"");
    for (i, v) in vectors.iter().enumerate() {
        let (x, y) = (i % cw, i / cw);
        let Some([vx, vy]) = v else { continue };
        if x % 4 != 2 || y % 4 != 2 {
            continue;
        }
        let (px, py) = ((x as f64 + 0.5) * dx, (y as f64 + 0.5) * dy);
        let _ = write!(s, "M{px:.1} {py:.1}l{:.1} {:.1}", vx * arrow, vy * arrow);
    }
    s.push_str("\"/>");
    let labels: Vec<(f64, String)> = [0.0, 0.5, 1.0]
        .iter()
        .map(|f| (f * top, format!("{:.1} px", f * top)))
        .collect();
    colour_bar(&mut s, h * k, &labels, scale);
    s.push_str("</svg>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use hexcal_core::camera::{Distortion, Intrinsics};

    fn lens() -> CameraModel {
        CameraModel {
            width: 640,
            height: 480,
            intrinsics: Intrinsics {
                fx: 600.0,
                fy: 600.0,
                cx: 319.5,
                cy: 239.5,
            },
            distortion: Distortion {
                k1: -0.2,
                ..Default::default()
            },
        }
    }

    #[test]
    fn the_displacement_field_is_radial_and_zero_at_the_principal_point() {
        let m = lens();
        let (map, vectors) = distortion_map(&m);
        assert_eq!(map.cells, [48, 36]);
        // At a corner cell the barrel lens (k1 < 0) pulls the point in towards the centre
        // by about |k1|·r³/f² (r the pinhole radius): against the pinhole, inward.
        let corner = vectors[0].unwrap();
        assert!(corner[0] > 0.0 && corner[1] > 0.0, "{corner:?}");
        // Near the centre almost nothing moves.
        let centre = map.values[18 * 48 + 24].unwrap();
        assert!(centre < 0.05, "{centre}");
        let svg = distortion_svg(&map, &vectors, "cam0");
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>\n"));
    }

    #[test]
    fn the_uncertainty_map_follows_the_covariance_and_outlines_the_target() {
        let m = lens();
        // fx alone uncertain, 0.5 px: a pixel's uncertainty is 0.5·|x − cx|/fx (J = x_n).
        let with = LensWithCovariance {
            model: m,
            free: vec![LensParam::Fx],
            cov: DMatrix::from_element(1, 1, 0.25),
        };
        let map = with.uncertainty_map();
        let [cw, _] = map.cells;
        for (i, v) in map.values.iter().enumerate() {
            let x = ((i % cw) as f64 + 0.5) * 640.0 / cw as f64 - 0.5;
            let p = Point2::new(x, ((i / cw) as f64 + 0.5) * 480.0 / 36.0 - 0.5);
            // u = fx·x_d + cx: ∂u/∂fx = x_d = (u − cx)/fx; v does not depend on fx.
            let want = 0.5 * (p.x - 319.5).abs() / 600.0;
            assert!(
                (v.unwrap() - want).abs() < 1e-9,
                "cell {i}: {v:?} vs {want}"
            );
        }
        // The target 0.2 px: within it |x_n| ≤ 0.4, a band around the centre column.
        let f = map.fraction_within(0.2);
        assert!(f > 0.5 && f < 0.9, "{f}");
        let svg = uncertainty_svg(&map, "cam0", 0.2);
        assert!(svg.contains("stroke=\"white\""));
    }
}
