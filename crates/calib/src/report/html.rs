//! The one-page HTML calibration report (docs/design.md §8, §10).
//!
//! Takes a [`Calibration`], optional held-out verification figures ([`PairCheck`]s), a title
//! and the caller's warnings; gives one self-contained HTML page (inline CSS, figures as
//! inline SVG, no network references) with: warnings, the per-device residual table (the
//! paper's Table I), the rig seen from above with the board poses, per device its residual
//! vectors over the image, a histogram of residual norms and a coverage heatmap, every
//! parameter with its standard deviation, and the verification table.

use super::ReportError;
use crate::calib::bundle::Device;
use crate::calib::diagnostics::{kind_name, Diagnosis, ResidualRow};
use crate::calib::solve::Calibration;
use crate::calib::verify::PairCheck;
use hexcal_core::camera::LensParam;
use hexcal_core::observations::DeviceKind;
use nalgebra::{Point2, Point3, Vector2, Vector3};
use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::Path;

/// What the report shows.
#[derive(Clone, Debug)]
pub struct ReportInput<'a> {
    /// The calibration.
    pub calibration: &'a Calibration,
    /// Verification on held-out poses; may be empty.
    pub verification: &'a [PairCheck],
    /// Page title.
    pub title: &'a str,
    /// The residual table and every warning, the report's own and the caller's.
    pub diagnosis: &'a Diagnosis,
    /// The rig's self-test reports (sync, exposure), as text; may be empty.
    pub self_tests: &'a [String],
}

const CAMERA_COLOUR: &str = "#1f77b4";
const PROJECTOR_COLOUR: &str = "#e8710a";
const OUTLIER_COLOUR: &str = "#d62728";

const STYLE: &str = "
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;
 color:#222;background:#fff;margin:0 auto;padding:14px 20px 40px;max-width:1360px}
h1{font-size:24px;margin:8px 0 4px}h2{font-size:19px;margin:28px 0 8px;
 border-bottom:2px solid #ddd;padding-bottom:3px}h3{font-size:15px;margin:0 0 6px}
.stats{display:flex;flex-wrap:wrap;gap:8px;margin:8px 0 4px}
.stat{border:1px solid #dde3ea;border-radius:5px;padding:4px 10px;background:#f7f9fb}
.stat span{display:block;font-size:11px;color:#666}.stat b{font-size:15px}
.row{display:flex;flex-wrap:wrap;gap:24px;align-items:flex-start}
table{border-collapse:collapse;margin:6px 0 10px;font-variant-numeric:tabular-nums}
th,td{padding:3px 9px;border-bottom:1px solid #e4e4e4;text-align:right;white-space:nowrap}
th{background:#f3f5f8;font-weight:600}td.l,th.l{text-align:left}
tr:hover td{background:#fafbfd}
.cam{color:#1f77b4;font-weight:600}.proj{color:#c25e00;font-weight:600}
ul.warn{margin:4px 0;padding:8px 12px 8px 30px;background:#fff6e0;border:1px solid #f0c36d;
 border-radius:4px}ul.warn li{margin:2px 0}p.ok{color:#2a7a2a}
.device{border:1px solid #ddd;border-radius:6px;padding:10px 12px;margin:12px 0}
.figs{display:flex;flex-wrap:wrap;gap:18px;align-items:flex-start}
figure{margin:0}figcaption{font-size:12px;color:#555;max-width:410px;margin-top:2px}
svg text{font-family:system-ui,'DejaVu Sans',sans-serif}
.note{font-size:12px;color:#555}
.scroll{overflow-x:auto;max-width:100%}td.why{white-space:normal;min-width:360px}
";

/// The report as one self-contained HTML page.
pub fn html_report(input: &ReportInput) -> String {
    let cal = input.calibration;
    let rows = &input.diagnosis.rows;
    let mut h = String::with_capacity(1 << 20);
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>{}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>{}</h1>\n",
        esc(input.title),
        esc(input.title)
    );
    summary(&mut h, cal);
    h.push_str("<h2 id=\"warnings\">Warnings</h2>\n");
    let warnings = &input.diagnosis.warnings;
    if warnings.is_empty() {
        h.push_str("<p class=\"ok\">None: every device is seen in enough poses, fits as well as the others and meets the target.</p>\n");
    } else {
        h.push_str("<ul class=\"warn\">\n");
        for w in warnings {
            let _ = writeln!(h, "<li>{}</li>", esc(w));
        }
        h.push_str("</ul>\n");
    }
    for n in &input.diagnosis.notes {
        let _ = writeln!(h, "<p class=\"note\">Note: {}</p>", esc(n));
    }
    h.push_str("<div class=\"row\">\n<div>\n");
    residual_section(&mut h, rows);
    h.push_str("</div>\n<div>\n");
    rig_section(&mut h, cal);
    h.push_str("</div>\n</div>\n");
    lens_section(&mut h, cal);
    device_sections(&mut h, cal, rows, input.diagnosis.target.uncertainty_px);
    uncertainty_section(&mut h, cal);
    if !input.verification.is_empty() {
        verification_section(&mut h, cal, input.verification);
    }
    if !input.self_tests.is_empty() {
        h.push_str("<h2 id=\"self-tests\">Rig self-tests</h2>\n");
        for t in input.self_tests {
            let _ = writeln!(h, "<pre>{}</pre>", esc(t));
        }
    }
    let _ = write!(
        h,
        "<p class=\"note\">Written by hexcal {}. Pixel (0, 0) is the centre of the top-left \
         pixel; lengths in mm.</p>\n</body>\n</html>\n",
        env!("CARGO_PKG_VERSION")
    );
    h
}

/// Write [`html_report`] to `path` atomically.
pub fn write_html(input: &ReportInput, path: &Path) -> Result<(), ReportError> {
    hexcal_core::atomic::write(path, html_report(input).as_bytes()).map_err(|source| {
        ReportError::Io {
            path: path.display().to_string(),
            source,
        }
    })
}

/// HTML-escape text (also fit for attribute values and SVG text).
fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            c => o.push(c),
        }
    }
    o
}

fn kind_class(k: DeviceKind) -> &'static str {
    match k {
        DeviceKind::Camera => "cam",
        DeviceKind::Projector => "proj",
    }
}

fn kind_colour(k: DeviceKind) -> &'static str {
    match k {
        DeviceKind::Camera => CAMERA_COLOUR,
        DeviceKind::Projector => PROJECTOR_COLOUR,
    }
}

/// The key figures under the title: board, reference, counts, σ̂.
fn summary(h: &mut String, cal: &Calibration) {
    let sol = &cal.solution;
    let reference = cal.devices[cal.reference].name.as_str();
    let count = |k: DeviceKind| cal.devices.iter().filter(|d| d.kind == k).count();
    let outliers = sol.residuals.iter().filter(|r| r.outlier).count();
    let stats = [
        ("board", cal.board.name.clone()),
        ("reference frame", reference.to_string()),
        (
            "devices",
            format!(
                "{} cameras, {} projectors",
                count(DeviceKind::Camera),
                count(DeviceKind::Projector)
            ),
        ),
        ("board poses", sol.boards.len().to_string()),
        (
            "observations",
            format!("{} ({outliers} outliers)", cal.observations.len()),
        ),
        ("σ̂ per coordinate", format!("{:.4} px", sol.sigma)),
        (
            "expected RMS √2·σ̂·√(1−p/n)",
            format!("{:.4} px", crate::calib::diagnostics::expected_rms(cal)),
        ),
        ("n, p", format!("{}, {}", sol.dof.0, sol.dof.1)),
        (
            "LM iterations",
            format!(
                "{} (after {} on a ninth of the circles)",
                sol.iterations, sol.coarse_iterations
            ),
        ),
    ];
    h.push_str("<div class=\"stats\">");
    for (label, value) in stats {
        let _ = write!(
            h,
            "<div class=\"stat\"><span>{}</span><b>{}</b></div>",
            esc(label),
            esc(&value)
        );
    }
    h.push_str("</div>\n");
}

/// The paper's Table I.
fn residual_section(h: &mut String, rows: &[ResidualRow]) {
    h.push_str(
        "<h2 id=\"residuals\">Residuals per device</h2>\n<table>\n<tr><th class=\"l\">device\
         </th><th class=\"l\">kind</th><th>points</th><th>outliers</th><th>mean ± std of \
         |r| (px)</th><th>RMS (px)</th><th>poses</th></tr>\n",
    );
    for r in rows {
        let _ = writeln!(
            h,
            "<tr><td class=\"l {}\">{}</td><td class=\"l\">{}</td><td>{}</td><td>{}</td>\
             <td>{:.4} ± {:.4}</td><td>{:.4}</td><td>{}</td></tr>",
            kind_class(r.kind),
            esc(&r.name),
            kind_name(r.kind),
            r.points,
            r.outliers,
            r.mean,
            r.std,
            r.rms,
            r.poses
        );
    }
    h.push_str(
        "</table>\n<p class=\"note\">|r|: norm of observed − predicted pixel over the \
         observations kept (outliers excluded); a projector's pixels are its decoded raster \
         coordinates.</p>\n",
    );
}

/// A small SVG writer: coordinates in the figure's own pixels.
struct Svg {
    s: String,
}

impl Svg {
    fn new(width: f64, height: f64) -> Svg {
        let mut s = String::new();
        let _ = write!(
            s,
            "<svg width=\"{width:.0}\" height=\"{height:.0}\" viewBox=\"0 0 {width:.0} \
             {height:.0}\" role=\"img\">"
        );
        Svg { s }
    }

    fn rect(&mut self, x: f64, y: f64, w: f64, h: f64, style: &str) {
        let _ = write!(
            self.s,
            "<rect x=\"{x:.1}\" y=\"{y:.1}\" width=\"{w:.1}\" height=\"{h:.1}\" {style}/>"
        );
    }

    fn line(&mut self, a: (f64, f64), b: (f64, f64), style: &str) {
        let _ = write!(
            self.s,
            "<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" {style}/>",
            a.0, a.1, b.0, b.1
        );
    }

    fn path(&mut self, d: &str, style: &str) {
        if !d.is_empty() {
            let _ = write!(self.s, "<path d=\"{d}\" {style}/>");
        }
    }

    fn polygon(&mut self, points: &[(f64, f64)], style: &str) {
        let pts: Vec<String> = points
            .iter()
            .map(|p| format!("{:.1},{:.1}", p.0, p.1))
            .collect();
        let _ = write!(self.s, "<polygon points=\"{}\" {style}/>", pts.join(" "));
    }

    fn circle(&mut self, c: (f64, f64), r: f64, style: &str) {
        let _ = write!(
            self.s,
            "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"{r:.1}\" {style}/>",
            c.0, c.1
        );
    }

    /// Text at (x, y); `anchor` is start, middle or end.
    fn text(&mut self, x: f64, y: f64, size: f64, anchor: &str, style: &str, t: &str) {
        let _ = write!(
            self.s,
            "<text x=\"{x:.1}\" y=\"{y:.1}\" font-size=\"{size}\" text-anchor=\"{anchor}\" \
             {style}>{}</text>",
            esc(t)
        );
    }

    /// An arrow from `a` to `b` with a head of `head` px.
    fn arrow(&mut self, a: (f64, f64), b: (f64, f64), head: f64, style: &str) {
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let len = dx.hypot(dy);
        let mut d = format!("M{:.1} {:.1}L{:.1} {:.1}", a.0, a.1, b.0, b.1);
        if len > 1e-9 {
            let h = head.min(0.6 * len);
            let (ux, uy) = (dx / len, dy / len);
            for s in [-1.0, 1.0] {
                let (px, py) = (
                    b.0 - h * (ux * 0.87 - s * uy * 0.5),
                    b.1 - h * (uy * 0.87 + s * ux * 0.5),
                );
                let _ = write!(d, "M{:.1} {:.1}L{:.1} {:.1}", b.0, b.1, px, py);
            }
        }
        self.path(&d, style);
    }

    fn finish(mut self) -> String {
        self.s.push_str("</svg>");
        self.s
    }
}

/// The nearest of 1, 2, 5 × 10ᵏ at or below `x` (x > 0).
fn nice_below(x: f64) -> f64 {
    let e = 10f64.powf(x.log10().floor());
    let m = x / e;
    e * if m >= 5.0 {
        5.0
    } else if m >= 2.0 {
        2.0
    } else {
        1.0
    }
}

/// A compact number for axis labels.
fn short(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else if x.abs() >= 100.0 {
        format!("{x:.0}")
    } else if x.abs() >= 1.0 {
        format!("{}", (x * 100.0).round() / 100.0)
    } else {
        let digits = (2.0 - x.abs().log10().floor()).clamp(0.0, 8.0) as usize;
        format!("{x:.digits$}")
    }
}

/// Viridis at t ∈ [0, 1] (five control points, linear in between).
pub(super) fn viridis(t: f64) -> String {
    const STOPS: [(f64, f64, f64); 5] = [
        (68.0, 1.0, 84.0),
        (59.0, 82.0, 139.0),
        (33.0, 145.0, 140.0),
        (94.0, 201.0, 98.0),
        (253.0, 231.0, 37.0),
    ];
    let x = t.clamp(0.0, 1.0) * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f64;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    let mix = |p: f64, q: f64| (p + f * (q - p)).round() as u8;
    format!(
        "#{:02x}{:02x}{:02x}",
        mix(a.0, b.0),
        mix(a.1, b.1),
        mix(a.2, b.2)
    )
}

/// One device's observations: pixel, residual, outlier flag.
struct DeviceData {
    pixels: Vec<Point2<f64>>,
    errors: Vec<Vector2<f64>>,
    outlier: Vec<bool>,
}

fn device_data(cal: &Calibration, d: usize) -> DeviceData {
    let mut data = DeviceData {
        pixels: Vec::new(),
        errors: Vec::new(),
        outlier: Vec::new(),
    };
    for (o, r) in cal.observations.iter().zip(&cal.solution.residuals) {
        if o.device == d && r.error.iter().all(|x| x.is_finite()) {
            data.pixels.push(o.pixel);
            data.errors.push(r.error);
            data.outlier.push(r.outlier);
        }
    }
    data
}

/// Height of the pixel axis under an image frame (px).
const AXIS_HEIGHT: f64 = 30.0;
/// Width of the per-device image figures (px).
const IMAGE_FIG_WIDTH: f64 = 400.0;
/// Longest residual vector drawn (figure px); longer ones are cut.
const MAX_VECTOR: f64 = 40.0;
/// Most inlier residual vectors drawn per device.
const MAX_VECTORS: usize = 2500;
/// Inliers a grid cell needs for its mean residual arrow.
const MIN_CELL_POINTS: usize = 8;
/// Grid of the coverage heatmap and of the mean residual arrows: cells across the width.
const GRID_COLUMNS: usize = 24;

/// The image frame's geometry on a figure: offset and scale from image to figure pixels.
struct ImageFrame {
    x0: f64,
    y0: f64,
    k: f64,
    w: f64,
    h: f64,
}

impl ImageFrame {
    fn new(dev: &Device) -> ImageFrame {
        let (w, h) = (
            f64::from(dev.model.width.max(1)),
            f64::from(dev.model.height.max(1)),
        );
        ImageFrame {
            x0: 40.0,
            y0: 6.0,
            k: IMAGE_FIG_WIDTH / w,
            w,
            h,
        }
    }

    fn at(&self, p: Point2<f64>) -> (f64, f64) {
        (
            self.x0 + self.k * (p.x + 0.5),
            self.y0 + self.k * (p.y + 0.5),
        )
    }

    /// The figure vector `d` drawn from figure point `a`, cut to [`MAX_VECTOR`] px and to
    /// the image frame (an outlier's magnified residual would cross the page).
    fn clip(&self, a: (f64, f64), d: Vector2<f64>) -> Vector2<f64> {
        let (w, h) = self.size();
        let mut t = (MAX_VECTOR / d.norm().max(1e-12)).min(1.0);
        for (from, step, lo, hi) in [
            (a.0, d.x, self.x0, self.x0 + w),
            (a.1, d.y, self.y0, self.y0 + h),
        ] {
            if from + t * step > hi {
                t = t.min((hi - from) / step);
            } else if from + t * step < lo {
                t = t.min((lo - from) / step);
            }
        }
        d * t.max(0.0)
    }

    fn size(&self) -> (f64, f64) {
        (self.k * self.w, self.k * self.h)
    }

    /// Grid cells (columns, rows) and the cell size in image pixels.
    fn grid(&self) -> (usize, usize, f64) {
        let cell = self.w / GRID_COLUMNS as f64;
        let rows = ((self.h / cell).round() as usize).max(1);
        (GRID_COLUMNS, rows, self.h / rows as f64)
    }

    fn cell_of(&self, p: Point2<f64>) -> Option<(usize, usize)> {
        let (cols, rows, ch) = self.grid();
        let cw = self.w / cols as f64;
        let (i, j) = (((p.x + 0.5) / cw).floor(), ((p.y + 0.5) / ch).floor());
        (i >= 0.0 && j >= 0.0 && (i as usize) < cols && (j as usize) < rows)
            .then_some((i as usize, j as usize))
    }

    /// An SVG with room for the frame, its pixel axes and `below` px of text under them.
    fn svg(&self, below: f64) -> Svg {
        let (w, h) = self.size();
        Svg::new(w + self.x0 + 12.0, h + self.y0 + AXIS_HEIGHT + below)
    }

    /// Pixel axes along the frame's bottom and left edges: ticks every 250, 500, … px
    /// (about four per side) labelled in image pixels, and "x (px)", "y (px)".
    fn axes(&self, svg: &mut Svg) {
        let (w, h) = self.size();
        let (bottom, grey) = (self.y0 + h, "stroke=\"#777\"");
        let step = nice_below(self.w / 3.0);
        let mut t = 0.0;
        while t <= self.w {
            let x = self.x0 + self.k * t;
            svg.line((x, bottom), (x, bottom + 4.0), grey);
            svg.text(x, bottom + 14.0, 10.0, "middle", "fill=\"#444\"", &short(t));
            t += step;
        }
        svg.text(
            self.x0 + w,
            bottom + 26.0,
            10.0,
            "end",
            "fill=\"#444\"",
            "x (px)",
        );
        let mut t = 0.0;
        while t <= self.h {
            let y = self.y0 + self.k * t;
            svg.line((self.x0 - 4.0, y), (self.x0, y), grey);
            svg.text(
                self.x0 - 6.0,
                y + 4.0,
                10.0,
                "end",
                "fill=\"#444\"",
                &short(t),
            );
            t += step;
        }
        svg.text(
            self.x0 - 6.0,
            bottom + 26.0,
            10.0,
            "end",
            "fill=\"#444\"",
            "y (px)",
        );
    }
}

/// Residual vectors over the image: every residual (inliers grey, outliers red) and the
/// mean per grid cell as blue arrows, at stated magnifications.
fn residual_figure(dev: &Device, data: &DeviceData) -> (String, String) {
    let f = ImageFrame::new(dev);
    let (w, h) = f.size();
    let mut svg = f.svg(44.0);
    svg.rect(f.x0, f.y0, w, h, "fill=\"#fafafa\" stroke=\"#888\"");
    let mut norms = inlier_norms(data);
    norms.sort_by(f64::total_cmp);
    let p95 = norms
        .get((norms.len() * 95 / 100).min(norms.len().saturating_sub(1)))
        .copied()
        .unwrap_or(0.0);
    // Magnify so a 95th-percentile residual spans ~3 % of the image width.
    let scale = if p95 > 0.0 {
        nice_below(0.03 * f.w / p95)
    } else {
        1.0
    };
    let mean_scale = 4.0 * scale;
    // Every stride-th inlier (all outliers): the figure stays light and readable.
    let stride = norms.len().div_ceil(MAX_VECTORS).max(1);
    residual_vectors(&mut svg, &f, data, scale, stride);
    cell_mean_arrows(&mut svg, &f, data, mean_scale);
    f.axes(&mut svg);
    residual_legend(&mut svg, &f, dev, scale, mean_scale);
    let (cols, rows, _) = f.grid();
    let caption = format!(
        "Residual vectors (observed − predicted){}, magnified ×{}; blue: the mean of each \
         {}×{} grid cell with {MIN_CELL_POINTS} or more, ×{}; red: outliers. Systematic patterns in the blue arrows point to \
         an unmodelled error. Vectors are cut at {MAX_VECTOR} figure px and at the image \
         border.",
        if stride > 1 {
            format!(" of one in {stride} of the {} inliers", norms.len())
        } else {
            " at each observation".into()
        },
        short(scale),
        cols,
        rows,
        short(mean_scale)
    );
    (svg.finish(), caption)
}

/// The norms of the inliers' residuals (px), in observation order.
fn inlier_norms(data: &DeviceData) -> Vec<f64> {
    data.errors
        .iter()
        .zip(&data.outlier)
        .filter(|(_, o)| !**o)
        .map(|(e, _)| e.norm())
        .collect()
}

/// Every `stride`-th inlier's residual (grey) and every outlier's (red, with a dot at its
/// pixel), magnified by `scale`, into `svg` over the image frame `f`.
fn residual_vectors(svg: &mut Svg, f: &ImageFrame, data: &DeviceData, scale: f64, stride: usize) {
    let (mut inl, mut out) = (String::new(), String::new());
    let mut inlier = 0;
    for ((p, e), o) in data.pixels.iter().zip(&data.errors).zip(&data.outlier) {
        if !*o {
            inlier += 1;
            if (inlier - 1) % stride != 0 {
                continue;
            }
        }
        let a = f.at(*p);
        let d = f.clip(a, e * scale * f.k);
        let _ = write!(
            if *o { &mut out } else { &mut inl },
            "M{:.1} {:.1}l{:.1} {:.1}",
            a.0,
            a.1,
            d.x,
            d.y
        );
    }
    svg.path(
        &inl,
        "stroke=\"#9aa3ad\" stroke-width=\"0.7\" fill=\"none\"",
    );
    svg.path(
        &out,
        &format!("stroke=\"{OUTLIER_COLOUR}\" stroke-width=\"1.2\" fill=\"none\""),
    );
    for (p, _) in data.pixels.iter().zip(&data.outlier).filter(|(_, o)| **o) {
        svg.circle(f.at(*p), 1.8, &format!("fill=\"{OUTLIER_COLOUR}\""));
    }
}

/// The mean inlier residual of every grid cell with [`MIN_CELL_POINTS`] or more, as a blue
/// arrow magnified by `mean_scale`, into `svg` over the image frame `f`.
fn cell_mean_arrows(svg: &mut Svg, f: &ImageFrame, data: &DeviceData, mean_scale: f64) {
    // Mean residual per cell (inliers; cells with few are left out: their means are noise).
    let (cols, rows, ch) = f.grid();
    let cw = f.w / cols as f64;
    let mut sum = vec![(Vector2::zeros(), 0usize); cols * rows];
    for ((p, e), o) in data.pixels.iter().zip(&data.errors).zip(&data.outlier) {
        if let (Some((i, j)), false) = (f.cell_of(*p), *o) {
            sum[j * cols + i].0 += e;
            sum[j * cols + i].1 += 1;
        }
    }
    for (c, (s, n)) in sum.iter().enumerate() {
        if *n >= MIN_CELL_POINTS {
            let centre = Point2::new(
                (c % cols) as f64 * cw + cw / 2.0,
                (c / cols) as f64 * ch + ch / 2.0,
            );
            let a = f.at(centre);
            let d = s / *n as f64 * mean_scale * f.k;
            svg.arrow(
                a,
                (a.0 + d.x, a.1 + d.y),
                3.5,
                "stroke=\"#1a4f9c\" stroke-width=\"1.4\" fill=\"none\"",
            );
        }
    }
}

/// Below the image frame `f`: scale bars of the residuals (magnified by `scale`) and of the
/// cell means (by `mean_scale`), and the image size of `dev`.
fn residual_legend(svg: &mut Svg, f: &ImageFrame, dev: &Device, scale: f64, mean_scale: f64) {
    let (w, h) = f.size();
    // Scale bar: the residual length that is 10 % of the width at each magnification.
    let y = f.y0 + h + AXIS_HEIGHT + 12.0;
    let len = nice_below(0.12 * f.w / scale);
    svg.line(
        (f.x0, y),
        (f.x0 + len * scale * f.k, y),
        "stroke=\"#9aa3ad\" stroke-width=\"2\"",
    );
    svg.text(
        f.x0 + len * scale * f.k + 6.0,
        y + 4.0,
        11.0,
        "start",
        "fill=\"#444\"",
        &format!("{} px residual (×{})", short(len), short(scale)),
    );
    let mlen = nice_below(0.12 * f.w / mean_scale);
    let y2 = y + 18.0;
    svg.arrow(
        (f.x0, y2),
        (f.x0 + mlen * mean_scale * f.k, y2),
        3.5,
        "stroke=\"#1a4f9c\" stroke-width=\"1.4\" fill=\"none\"",
    );
    svg.text(
        f.x0 + mlen * mean_scale * f.k + 6.0,
        y2 + 4.0,
        11.0,
        "start",
        "fill=\"#444\"",
        &format!("{} px mean per cell (×{})", short(mlen), short(mean_scale)),
    );
    svg.text(
        f.x0 + w,
        y + 4.0,
        11.0,
        "end",
        "fill=\"#444\"",
        &format!("{} × {} px", dev.model.width, dev.model.height),
    );
}

/// Coverage heatmap: observations per grid cell over the image; empty cells light grey.
fn coverage_figure(dev: &Device, data: &DeviceData) -> (String, String) {
    let f = ImageFrame::new(dev);
    let (w, h) = f.size();
    let (cols, rows, _) = f.grid();
    let mut count = vec![0usize; cols * rows];
    for p in &data.pixels {
        if let Some((i, j)) = f.cell_of(*p) {
            count[j * cols + i] += 1;
        }
    }
    let max = count.iter().copied().max().unwrap_or(0).max(1);
    let empty = count.iter().filter(|c| **c == 0).count();
    let mut svg = f.svg(44.0);
    let (cw, chh) = (w / cols as f64, h / rows as f64);
    svg.rect(f.x0, f.y0, w, h, "fill=\"#ececec\"");
    for (c, n) in count.iter().enumerate() {
        if *n > 0 {
            svg.rect(
                f.x0 + (c % cols) as f64 * cw,
                f.y0 + (c / cols) as f64 * chh,
                cw + 0.3,
                chh + 0.3,
                &format!("fill=\"{}\"", viridis(*n as f64 / max as f64)),
            );
        }
    }
    svg.rect(f.x0, f.y0, w, h, "fill=\"none\" stroke=\"#888\"");
    f.axes(&mut svg);
    // Colour bar.
    let y = f.y0 + h + AXIS_HEIGHT + 6.0;
    let steps = 40;
    let bar = 200.0;
    for s in 0..steps {
        svg.rect(
            f.x0 + bar * s as f64 / steps as f64,
            y,
            bar / steps as f64 + 0.3,
            10.0,
            &format!("fill=\"{}\"", viridis(s as f64 / (steps - 1) as f64)),
        );
    }
    svg.text(f.x0, y + 24.0, 11.0, "start", "fill=\"#444\"", "1");
    svg.text(
        f.x0 + bar,
        y + 24.0,
        11.0,
        "end",
        "fill=\"#444\"",
        &format!("{max} per cell"),
    );
    svg.rect(
        f.x0 + bar + 24.0,
        y,
        14.0,
        10.0,
        "fill=\"#ececec\" stroke=\"#aaa\"",
    );
    svg.text(
        f.x0 + bar + 42.0,
        y + 9.0,
        11.0,
        "start",
        "fill=\"#444\"",
        "no observation",
    );
    let caption = format!(
        "Where the observations fall: count per {cols}×{rows} grid cell; {empty} of {} cells \
         ({:.0} %) are empty.",
        cols * rows,
        100.0 * empty as f64 / (cols * rows) as f64
    );
    (svg.finish(), caption)
}

/// Histogram of the inliers' residual norms with the Rayleigh density of the device's own
/// σ per coordinate, √(Σ|r|²/2n), beside the rig's σ̂.
fn histogram_figure(data: &DeviceData, rig_sigma: f64) -> (String, String) {
    let norms = inlier_norms(data);
    let sigma = (norms.iter().map(|r| r * r).sum::<f64>() / (2 * norms.len().max(1)) as f64)
        .sqrt()
        .max(1e-12);
    let plot = Plot {
        w: 300.0,
        h: 200.0,
        left: 54.0,
        bottom: 36.0,
        top: 10.0,
    };
    let mut svg = Svg::new(plot.w + plot.left + 12.0, plot.h + plot.top + plot.bottom);
    let mut sorted = norms.clone();
    sorted.sort_by(f64::total_cmp);
    let p995 = sorted
        .get((sorted.len() * 995 / 1000).min(sorted.len().saturating_sub(1)))
        .copied()
        .unwrap_or(0.0);
    let hi = p995.max(3.5 * sigma).max(1e-9);
    let bins = 30;
    let bw = hi / bins as f64;
    let mut count = vec![0usize; bins];
    let mut beyond = 0;
    for r in &norms {
        let b = (r / bw).floor() as usize;
        if b < bins {
            count[b] += 1;
        } else {
            beyond += 1;
        }
    }
    let expect = rayleigh_counts(norms.len() as f64, sigma, hi, bins);
    let ymax = count
        .iter()
        .map(|c| *c as f64)
        .chain(expect.iter().copied())
        .fold(1.0, f64::max)
        * 1.08;
    plot.bars_and_curve(&mut svg, &count, &expect, ymax);
    plot.axes(&mut svg, hi, ymax);
    let caption = format!(
        "Residual norms |r| (px) of the {} inliers, count per {} px bin{}; red: the \
         Rayleigh distribution of this device's σ = {:.4} px per coordinate (the whole rig's \
         σ̂ = {:.4} px).",
        norms.len(),
        short(bw),
        if beyond > 0 {
            format!(" ({beyond} beyond {} px not shown)", short(hi))
        } else {
            String::new()
        },
        sigma,
        rig_sigma
    );
    (svg.finish(), caption)
}

/// Expected counts of `n` Rayleigh(`sigma`) norms in histogram bins of width hi/`bins`, at
/// 4·`bins` + 1 points over [0, `hi`].
fn rayleigh_counts(n: f64, sigma: f64, hi: f64, bins: usize) -> Vec<f64> {
    let bw = hi / bins as f64;
    (0..=(4 * bins))
        .map(|i| {
            let r = hi * i as f64 / (4 * bins) as f64;
            let s2 = (sigma * sigma).max(1e-300);
            n * bw * r / s2 * (-r * r / (2.0 * s2)).exp()
        })
        .collect()
}

/// A plot area of `w` × `h` px with margins left, below and above it.
struct Plot {
    w: f64,
    h: f64,
    left: f64,
    bottom: f64,
    top: f64,
}

impl Plot {
    /// Bottom left corner of the plot area.
    fn origin(&self) -> (f64, f64) {
        (self.left, self.top + self.h)
    }

    /// The histogram bars `count` and the expected density `expect` (4 points per bar), up
    /// to `ymax`, into `svg`.
    fn bars_and_curve(&self, svg: &mut Svg, count: &[usize], expect: &[f64], ymax: f64) {
        let (w, h) = (self.w, self.h);
        let (x0, y0) = self.origin();
        let bins = count.len();
        let bx = w / bins as f64;
        for (b, c) in count.iter().enumerate() {
            let bh = h * *c as f64 / ymax;
            svg.rect(
                x0 + b as f64 * bx + 0.5,
                y0 - bh,
                bx - 1.0,
                bh,
                "fill=\"#7fa7d4\"",
            );
        }
        let curve: Vec<String> = expect
            .iter()
            .enumerate()
            .map(|(i, e)| {
                format!(
                    "{}{:.1} {:.1}",
                    if i == 0 { "M" } else { "L" },
                    x0 + w * i as f64 / (4 * bins) as f64,
                    y0 - h * e / ymax
                )
            })
            .collect();
        svg.path(
            &curve.concat(),
            "stroke=\"#c0392b\" stroke-width=\"1.6\" fill=\"none\"",
        );
    }

    /// Axes with ticks: |r| over [0, `hi`] px, counts over [0, `ymax`], into `svg`.
    fn axes(&self, svg: &mut Svg, hi: f64, ymax: f64) {
        let (w, h) = (self.w, self.h);
        let (x0, y0) = self.origin();
        svg.line((x0, y0), (x0 + w, y0), "stroke=\"#555\"");
        svg.line((x0, y0), (x0, self.top), "stroke=\"#555\"");
        let xt = nice_below(hi / 3.0);
        let mut t = 0.0;
        while t <= hi + 1e-12 {
            let x = x0 + w * t / hi;
            svg.line((x, y0), (x, y0 + 4.0), "stroke=\"#555\"");
            svg.text(x, y0 + 16.0, 11.0, "middle", "fill=\"#444\"", &short(t));
            t += xt;
        }
        svg.text(
            x0 + w / 2.0,
            y0 + 31.0,
            11.0,
            "middle",
            "fill=\"#444\"",
            "|r| (px)",
        );
        svg.text(
            x0 - 42.0,
            self.top + h / 2.0,
            11.0,
            "middle",
            &format!(
                "fill=\"#444\" transform=\"rotate(-90 {:.1} {:.1})\"",
                x0 - 42.0,
                self.top + h / 2.0
            ),
            "count",
        );
        let yt = nice_below(ymax / 3.0).max(1.0);
        let mut c = 0.0;
        while c <= ymax {
            let y = y0 - h * c / ymax;
            svg.line((x0 - 4.0, y), (x0, y), "stroke=\"#555\"");
            svg.text(x0 - 6.0, y + 4.0, 11.0, "end", "fill=\"#444\"", &short(c));
            c += yt;
        }
    }
}

/// Per device: residual vectors, histogram, coverage.
fn device_sections(h: &mut String, cal: &Calibration, rows: &[ResidualRow], target: f64) {
    h.push_str("<h2 id=\"devices\">Residuals and coverage per device</h2>\n");
    for (d, (dev, row)) in cal.devices.iter().zip(rows).enumerate() {
        let data = device_data(cal, d);
        let _ = write!(
            h,
            "<div class=\"device\">\n<h3><span class=\"{}\">{}</span> — {}, {} × {} px, RMS \
             {:.4} px over {} points</h3>\n",
            kind_class(dev.kind),
            esc(&dev.name),
            kind_name(dev.kind),
            dev.model.width,
            dev.model.height,
            row.rms,
            row.points
        );
        if data.pixels.is_empty() {
            h.push_str("<p>No observations.</p>\n</div>\n");
            continue;
        }
        h.push_str("<div class=\"figs\">\n");
        for (svg, caption) in [
            residual_figure(dev, &data),
            histogram_figure(&data, cal.solution.sigma),
            coverage_figure(dev, &data),
        ]
        .into_iter()
        .chain(map_figures(cal, d, target))
        {
            let _ = writeln!(
                h,
                "<figure>{svg}<figcaption>{}</figcaption></figure>",
                esc(&caption)
            );
        }
        h.push_str("</div>\n</div>\n");
    }
}

/// Device `d`'s projection-uncertainty map (the region within `target` px outlined) and
/// its lens's displacement field ([`super::maps`]).
fn map_figures(cal: &Calibration, d: usize, target: f64) -> Vec<(String, String)> {
    let dev = &cal.devices[d];
    let (free, cov) = crate::calib::diagnostics::lens_covariance(cal, d);
    let lens = super::maps::LensWithCovariance {
        model: dev.model,
        free,
        cov,
    };
    let (field, vectors) = super::maps::distortion_map(&dev.model);
    // Inline in HTML an <svg> needs no namespace (and the page names no outside address).
    let inline = |svg: String| svg.replacen(" xmlns=\"http://www.w3.org/2000/svg\"", "", 1);
    vec![
        (
            inline(super::maps::uncertainty_svg(
                &lens.uncertainty_map(),
                &dev.name,
                target,
            )),
            format!(
                "Projection uncertainty over the image (log scale); the outline holds the \
                 pixels within your {target} px target (hexcal show uncertainty {})",
                dev.name
            ),
        ),
        (
            inline(super::maps::distortion_svg(&field, &vectors, &dev.name)),
            format!(
                "The lens's displacement against a pinhole (hexcal show distortion {})",
                dev.name
            ),
        ),
    ]
}

/// The rig seen from above in the reference frame: devices with their horizontal field of
/// view and viewing direction, and the board poses as outlines.
fn rig_section(h: &mut String, cal: &Calibration) {
    let view = TopView::new(cal);
    let half = (cal.board.size[0] / 2.0, cal.board.size[1] / 2.0);
    let outlines: Vec<Vec<(f64, f64)>> = cal
        .solution
        .boards
        .iter()
        .map(|b| {
            [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
                .iter()
                .map(|(sx, sy)| view.plane(&(b * Point3::new(sx * half.0, sy * half.1, 0.0))))
                .collect()
        })
        .collect();
    let centres: Vec<(f64, f64)> = cal
        .devices
        .iter()
        .map(|d| view.plane(&(d.pose.inverse() * Point3::origin())))
        .collect();
    let all: Vec<(f64, f64)> = outlines.iter().flatten().chain(&centres).copied().collect();
    let canvas = Canvas::around(&all);
    let (fw, fh) = canvas.size();
    let mut svg = Svg::new(fw, fh + 30.0);
    svg.rect(0.0, 0.0, fw, fh, "fill=\"#fcfcfc\" stroke=\"#ccc\"");
    board_outlines(&mut svg, cal, &outlines, &canvas);
    for (dev, c) in cal.devices.iter().zip(&centres) {
        device_from_above(&mut svg, dev, *c, &view, &canvas);
    }
    // Scale bar.
    let (lo, hi, k) = (canvas.lo, canvas.hi, canvas.k);
    let bar = nice_below(0.25 * (hi.0 - lo.0));
    let y = fh + 18.0;
    svg.line(
        (10.0, y),
        (10.0 + bar * k, y),
        "stroke=\"#333\" stroke-width=\"2\"",
    );
    svg.text(
        16.0 + bar * k,
        y + 4.0,
        11.0,
        "start",
        "fill=\"#333\"",
        &format!("{} mm", short(bar)),
    );
    let _ = write!(
        h,
        "<h2 id=\"rig\">The rig from above</h2>\n<figure>{}<figcaption>In the reference \
         frame, seen from above: each device's position, its horizontal field of view (wedge) \
         and viewing direction (arrow), <span class=\"cam\">cameras</span> and \
         <span class=\"proj\">projectors</span>; grey: the {} board poses' outlines \
         ({} × {} mm), numbered. \"Up\" is against the mean of the devices' image y \
         axes.</figcaption></figure>\n",
        svg.finish(),
        cal.solution.boards.len(),
        cal.board.size[0],
        cal.board.size[1]
    );
}

/// The horizontal plane of the view from above, in the reference frame.
struct TopView {
    /// The view's right axis.
    right: Vector3<f64>,
    /// The view's forward axis (up in the figure).
    forward: Vector3<f64>,
}

impl TopView {
    /// "Up" is against the mean of the devices' image y axes (y points down in a device).
    fn new(cal: &Calibration) -> Self {
        let rot = |d: &Device| d.pose.inverse().rotation;
        let mut down: Vector3<f64> = cal.devices.iter().map(|d| rot(d) * Vector3::y()).sum();
        if down.norm() < 1e-6 {
            down = Vector3::y();
        }
        let down = down.normalize();
        let ref_x = Vector3::x() - down * down.x;
        let right = if ref_x.norm() > 1e-6 {
            ref_x.normalize()
        } else {
            down.cross(&Vector3::z()).normalize()
        };
        // Right-handed view from above: right × forward = up.
        let forward = right.cross(&down);
        TopView { right, forward }
    }

    /// A point of the reference frame in the view's plane (mm, y down the figure).
    fn plane(&self, p: &Point3<f64>) -> (f64, f64) {
        (p.coords.dot(&self.right), -p.coords.dot(&self.forward))
    }
}

/// The figure's scale: plane coordinates (mm) to figure px.
struct Canvas {
    /// Lower and upper corners of the shown area (mm).
    lo: (f64, f64),
    hi: (f64, f64),
    /// px per mm.
    k: f64,
    /// Length of a device's field-of-view wedge (mm).
    ray: f64,
}

impl Canvas {
    /// The canvas around the plane points `all` with a margin of 12 % of their extent, 560 px
    /// on its longer side.
    fn around(all: &[(f64, f64)]) -> Self {
        let (mut lo, mut hi) = ((f64::MAX, f64::MAX), (f64::MIN, f64::MIN));
        for p in all {
            lo = (lo.0.min(p.0), lo.1.min(p.1));
            hi = (hi.0.max(p.0), hi.1.max(p.1));
        }
        let extent = (hi.0 - lo.0).max(hi.1 - lo.1).max(1.0);
        let ray = 0.12 * extent;
        let margin = 0.12 * extent;
        let (lo, hi) = (
            (lo.0 - margin, lo.1 - margin),
            (hi.0 + margin, hi.1 + margin),
        );
        let size = 560.0;
        let k = size / (hi.0 - lo.0).max(hi.1 - lo.1);
        Canvas { lo, hi, k, ray }
    }

    /// Width and height (px).
    fn size(&self) -> (f64, f64) {
        let (lo, hi, k) = (self.lo, self.hi, self.k);
        (k * (hi.0 - lo.0), k * (hi.1 - lo.1))
    }

    /// A plane point in figure px.
    fn map(&self, p: (f64, f64)) -> (f64, f64) {
        (self.k * (p.0 - self.lo.0), self.k * (p.1 - self.lo.1))
    }
}

/// The board poses' `outlines` (plane points), numbered when there are at most 40, into
/// `svg`. The poses overlap near the rig's centre, so each number sits just outside its
/// outline's corner farthest from the poses' common centre, in dark text on a white halo.
fn board_outlines(svg: &mut Svg, cal: &Calibration, outlines: &[Vec<(f64, f64)>], canvas: &Canvas) {
    let mapped: Vec<Vec<(f64, f64)>> = outlines
        .iter()
        .map(|o| o.iter().map(|p| canvas.map(*p)).collect())
        .collect();
    let n = mapped.iter().map(Vec::len).sum::<usize>().max(1) as f64;
    let mid = mapped
        .iter()
        .flatten()
        .fold((0.0, 0.0), |s, p| (s.0 + p.0 / n, s.1 + p.1 / n));
    for pts in &mapped {
        svg.polygon(
            pts,
            "fill=\"#88888818\" stroke=\"#8a8a8a\" stroke-width=\"1\"",
        );
    }
    if outlines.len() > 40 {
        return;
    }
    for (i, pts) in mapped.iter().enumerate() {
        let dist = |p: &&(f64, f64)| (p.0 - mid.0).hypot(p.1 - mid.1);
        let Some(far) = pts.iter().max_by(|a, b| dist(a).total_cmp(&dist(b))) else {
            continue;
        };
        let (dx, dy) = (far.0 - mid.0, far.1 - mid.1);
        let len = dx.hypot(dy).max(1e-9);
        svg.text(
            far.0 + 9.0 * dx / len,
            far.1 + 9.0 * dy / len + 4.0,
            11.0,
            "middle",
            "fill=\"#333\" stroke=\"#fff\" stroke-width=\"3\" paint-order=\"stroke\"",
            &cal.pose_index[i].to_string(),
        );
    }
}

/// Device `dev` at plane point `centre`: its horizontal field of view (wedge), viewing
/// direction (arrow), position and name, into `svg`.
fn device_from_above(
    svg: &mut Svg,
    dev: &Device,
    centre: (f64, f64),
    view: &TopView,
    canvas: &Canvas,
) {
    let ray = canvas.ray;
    let inv = dev.pose.inverse();
    let k_ = &dev.model.intrinsics;
    let edge = |x: f64| {
        let d = inv.rotation * Vector3::new((x - k_.cx) / k_.fx, 0.0, 1.0).normalize();
        let p = inv * Point3::origin() + d * ray;
        canvas.map(view.plane(&p))
    };
    let o = canvas.map(centre);
    let colour = kind_colour(dev.kind);
    let l = edge(-0.5);
    let r = edge(f64::from(dev.model.width) - 0.5);
    svg.polygon(
        &[o, l, r],
        &format!("fill=\"{colour}33\" stroke=\"{colour}\" stroke-width=\"1\""),
    );
    let axis = inv * Point3::origin() + inv.rotation * Vector3::z() * (1.3 * ray);
    svg.arrow(
        o,
        canvas.map(view.plane(&axis)),
        6.0,
        &format!("stroke=\"{colour}\" stroke-width=\"2\" fill=\"none\""),
    );
    svg.circle(o, 4.0, &format!("fill=\"{colour}\""));
    // Label behind the device, away from its view.
    let back = inv * Point3::origin() - inv.rotation * Vector3::z() * (0.35 * ray);
    let b = canvas.map(view.plane(&back));
    svg.text(
        b.0,
        b.1 + 4.0,
        12.0,
        "middle",
        &format!("fill=\"{colour}\" font-weight=\"600\""),
        &dev.name,
    );
}

/// "value ± std" with the std's two significant digits setting the decimals; "fixed" for
/// a zero std.
fn with_std(value: f64, std: f64) -> String {
    if std > 0.0 && std.is_finite() {
        let decimals = (1.0 - std.log10().floor()).clamp(0.0, 12.0) as usize;
        format!("{value:.decimals$} ± {std:.decimals$}")
    } else {
        format!("{} (fixed)", short(value))
    }
}

/// Per device, the distortion terms it estimates and those fixed, with the evidence
/// (docs/design.md §8, "Lens model").
fn lens_section(h: &mut String, cal: &Calibration) {
    h.push_str(
        "<h2 id=\"lens-model\">Lens model chosen by the data</h2>\n<p class=\"note\">\
         The highest radial term still estimated is fixed at 0 when its estimate lies within \
         3σ of zero, and the adjustment repeated; k1, p1, p2 are always estimated.</p>\n\
         <div class=\"scroll\"><table>\n<tr><th class=\"l\">device</th><th class=\"l\">\
         estimates</th><th class=\"l\">fixed</th><th class=\"l\">why</th></tr>\n",
    );
    for (dev, choice) in cal.devices.iter().zip(&cal.lens) {
        let names = |estimated: bool| {
            let v: Vec<&str> = choice
                .terms
                .iter()
                .filter(|t| t.estimated == estimated)
                .map(|t| t.param.name())
                .collect();
            if v.is_empty() {
                "—".to_string()
            } else {
                v.join(" ")
            }
        };
        let why: Vec<String> = choice
            .terms
            .iter()
            .filter(|t| t.tested || !t.estimated)
            .map(|t| esc(&t.reason()))
            .collect();
        let _ = writeln!(
            h,
            "<tr><td class=\"l {}\">{}</td><td class=\"l\">{}</td><td class=\"l\">{}</td>\
             <td class=\"l why\">{}</td></tr>",
            kind_class(dev.kind),
            esc(&dev.name),
            names(true),
            names(false),
            if why.is_empty() {
                "every term estimated".to_string()
            } else {
                why.join("<br>")
            }
        );
    }
    h.push_str("</table></div>\n");
}

/// Every device's parameters with standard deviations, and its pose.
fn uncertainty_section(h: &mut String, cal: &Calibration) {
    let sol = &cal.solution;
    let rational = cal.devices.iter().any(|d| d.model.distortion.is_rational());
    let params: Vec<LensParam> = LensParam::ALL
        .into_iter()
        .filter(|p| rational || p.index() < 9)
        .collect();
    h.push_str(
        "<h2 id=\"parameters\">Parameters and standard deviations</h2>\n<p class=\"note\">\
         Standard deviations from σ̂²(JᵀJ)⁻¹ of the final adjustment; focal lengths and \
         principal points in px.</p>\n<div class=\"scroll\"><table>\n<tr><th class=\"l\">\
         device</th>",
    );
    for p in &params {
        let _ = write!(h, "<th>{p}</th>");
    }
    h.push_str("</tr>\n");
    for (d, dev) in cal.devices.iter().enumerate() {
        let stds = &sol.intrinsic_std[d];
        let free = sol.free[d];
        let v = dev.model.lens_vector();
        let _ = write!(
            h,
            "<tr><td class=\"l {}\">{}</td>",
            kind_class(dev.kind),
            esc(&dev.name)
        );
        for p in &params {
            let std = free
                .iter()
                .position(|q| q == *p)
                .and_then(|i| stds.get(i).copied())
                .unwrap_or(0.0);
            let _ = write!(h, "<td>{}</td>", with_std(v[p.index()], std));
        }
        h.push_str("</tr>\n");
    }
    h.push_str(
        "</table></div>\n<div class=\"scroll\"><table>\n<tr><th class=\"l\">device</th>\
         <th>position in the reference \
         frame (mm)</th><th>viewing direction</th><th>σ rotation (mrad)</th><th>σ \
         translation (mm)</th></tr>\n",
    );
    for (d, dev) in cal.devices.iter().enumerate() {
        let inv = dev.pose.inverse();
        let c = inv.translation.vector;
        let z = inv.rotation * Vector3::z();
        let s = sol.pose_std[d];
        let (rot, tr) = if s.iter().all(|x| *x == 0.0) {
            ("reference".to_string(), "reference".to_string())
        } else {
            (
                format!("{:.3}, {:.3}, {:.3}", 1e3 * s[0], 1e3 * s[1], 1e3 * s[2]),
                format!("{:.3}, {:.3}, {:.3}", s[3], s[4], s[5]),
            )
        };
        let _ = writeln!(
            h,
            "<tr><td class=\"l {}\">{}</td><td>{:.1}, {:.1}, {:.1}</td><td>{:.3}, {:.3}, \
             {:.3}</td><td>{rot}</td><td>{tr}</td></tr>",
            kind_class(dev.kind),
            esc(&dev.name),
            c.x,
            c.y,
            c.z,
            z.x,
            z.y,
            z.z
        );
    }
    h.push_str(
        "</table></div>\n<p class=\"note\">Pose σ: of the left increment of T_device_ref, rotation \
         (ω) about and translation (τ) along the device's x, y, z axes.</p>\n",
    );
    if sol.bend_std.iter().any(|s| *s > 0.0) {
        let b = sol.bend.coefficients;
        let _ = writeln!(
            h,
            "<p>Board bend at {:.0} mm from the centre (mm): bowl {}, saddle {}, saddle (xy) {}</p>",
            sol.bend.scale,
            with_std(b.x, sol.bend_std[0]),
            with_std(b.y, sol.bend_std[1]),
            with_std(b.z, sol.bend_std[2])
        );
    }
}

/// Held-out verification per device pair over its poses: length and flatness errors.
fn verification_section(h: &mut String, cal: &Calibration, checks: &[PairCheck]) {
    let rms = |x: &mut dyn Iterator<Item = f64>| {
        let (s, n) = x.fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
        (s / n.max(1) as f64).sqrt()
    };
    // Camera–camera pairs first, then camera–projector, each in name order.
    let mut pairs: Vec<(&str, &str)> = checks
        .iter()
        .map(|c| (c.first.as_str(), c.second.as_str()))
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    let projector = |name: &str| {
        cal.devices
            .iter()
            .any(|d| d.name == name && d.kind == DeviceKind::Projector)
    };
    pairs.sort_by_key(|&(a, b)| (projector(b), a, b));
    let poses: BTreeSet<usize> = checks.iter().map(|c| c.pose).collect();
    let _ = write!(
        h,
        "<h2 id=\"verification\">Verification on held-out poses</h2>\n<p>{} device pairs \
         on {} held-out pose{}: length error RMS <b>{:.4} mm</b> (largest single error {:.4} \
         mm), flatness RMS <b>{:.4} mm</b>.</p>\n<table>\n<tr><th class=\"l\">first</th>\
         <th class=\"l\">second</th><th>poses</th><th>points</th><th>length error RMS (mm)\
         </th><th>largest (mm)</th><th>flatness RMS (mm)</th></tr>\n",
        pairs.len(),
        poses.len(),
        if poses.len() == 1 { "" } else { "s" },
        rms(&mut checks.iter().map(|c| c.length_rms)),
        checks.iter().map(|c| c.length_max).fold(0.0, f64::max),
        rms(&mut checks.iter().map(|c| c.flatness_rms))
    );
    for (a, b) in pairs {
        let of: Vec<&PairCheck> = checks
            .iter()
            .filter(|c| c.first == a && c.second == b)
            .collect();
        let _ = writeln!(
            h,
            "<tr><td class=\"l\">{}</td><td class=\"l\">{}</td><td>{}</td><td>{}</td>\
             <td>{:.4}</td><td>{:.4}</td><td>{:.4}</td></tr>",
            esc(a),
            esc(b),
            of.len(),
            of.iter().map(|c| c.points).sum::<usize>(),
            rms(&mut of.iter().map(|c| c.length_rms)),
            of.iter().map(|c| c.length_max).fold(0.0, f64::max),
            rms(&mut of.iter().map(|c| c.flatness_rms))
        );
    }
    h.push_str(
        "</table>\n<p class=\"note\">Circles triangulated by each pair, against the board's \
         nominal point-to-point distances (VDI/VDE 2634 style) and their best-fit plane; RMS \
         over the pair's poses.</p>\n",
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::diagnostics::residual_table;
    use crate::calib::solve::{calibrate, Excluded};
    use crate::calib::synthetic::SyntheticRig;
    use std::sync::OnceLock;

    /// The paper rig calibrated once for all tests.
    fn calibration() -> &'static Calibration {
        static CAL: OnceLock<Calibration> = OnceLock::new();
        CAL.get_or_init(|| {
            let rig = SyntheticRig::paper(5, 0.1, 3);
            calibrate(
                &rig.board,
                &rig.device_infos(),
                rig.boards.len(),
                &rig.views(),
                &Default::default(),
            )
            .expect("paper rig calibrates")
        })
    }

    fn page(cal: &Calibration, verification: &[PairCheck], warnings: Vec<String>) -> String {
        html_report(&ReportInput {
            calibration: cal,
            verification,
            title: "Rig <A> & \"B\"",
            diagnosis: &Diagnosis::of(cal, verification, &warnings, &Default::default()),
            self_tests: &["sync OK: every frame shows its own slide".into()],
        })
    }

    #[test]
    fn page_is_one_self_contained_document_with_every_device_and_number() {
        let cal = calibration();
        let check = PairCheck {
            first: "cam0".into(),
            second: "proj1".into(),
            pose: 7,
            points: 321,
            length_rms: 0.01234,
            length_max: 0.05678,
            flatness_rms: 0.00912,
            predicted_rms: None,
        };
        let html = page(cal, &[check], vec!["board not seen in pose 9".into()]);
        assert_eq!(html.matches("<html").count(), 1);
        assert!(html.contains("Rig self-tests</h2>\n<pre>sync OK: every frame"));
        assert_eq!(html.matches("</html>").count(), 1);
        assert_eq!(html.matches("<svg").count(), html.matches("</svg>").count());
        // Rig view plus five figures per device (residuals, histogram, coverage, the
        // uncertainty map and the displacement field).
        assert_eq!(html.matches("<svg").count(), 1 + 5 * cal.devices.len());
        assert_eq!(
            html.matches("projection uncertainty (px, 1σ)").count(),
            cal.devices.len()
        );
        assert!(!html.contains("http://") && !html.contains("https://"));
        assert!(!html.contains("<script") && !html.contains("<link") && !html.contains("<img"));
        // The title is escaped.
        assert!(html.contains("Rig &lt;A&gt; &amp; &quot;B&quot;"));
        assert!(!html.contains("<A>"));
        for r in residual_table(cal) {
            assert!(html.contains(&format!(">{}</td>", r.name)), "{}", r.name);
            let numbers = format!("{:.4} ± {:.4}</td><td>{:.4}", r.mean, r.std, r.rms);
            assert!(html.contains(&numbers), "{} row: {numbers}", r.name);
        }
        assert!(html.contains("board not seen in pose 9"));
        for figure in ["0.0123", "0.0568", "0.0091", ">321<"] {
            assert!(html.contains(figure), "verification {figure}");
        }
        // fx of every device with its standard deviation.
        for (d, dev) in cal.devices.iter().enumerate() {
            let fx = with_std(dev.model.intrinsics.fx, cal.solution.intrinsic_std[d][0]);
            assert!(html.contains(&fx), "{fx}");
        }
    }

    /// The paper rig (at ten times the real noise) meets the default target: the page says
    /// so. Its poses leave its image corners empty, so against the noise of one observation
    /// (0.1 px) the page warns that the lens models extrapolate there (calib::diagnostics'
    /// tests) and of nothing else.
    #[test]
    fn the_paper_rig_is_warned_of_its_corners_only_and_no_verification_without_checks() {
        let html = page(calibration(), &[], Vec::new());
        assert!(html.contains("<p class=\"ok\">None"));
        let strict = crate::calib::diagnostics::Target {
            uncertainty_px: 0.1,
            ..Default::default()
        };
        let html = html_report(&ReportInput {
            calibration: calibration(),
            verification: &[],
            title: "strict",
            diagnosis: &Diagnosis::of(calibration(), &[], &[], &strict),
            self_tests: &[],
        });
        assert!(!html.contains("<p class=\"ok\">None"));
        assert!(html.contains("the lens model extrapolates in its"));
        assert!(!html.contains("outliers,") && !html.contains("the median"));
        assert!(!html.contains("id=\"verification\""));
    }

    #[test]
    fn warns_about_a_device_in_few_poses_excluded_devices_and_high_rms() {
        let mut cal = calibration().clone();
        // Keep proj2's observations of pose 0 only, and make cam1's residuals 3× larger.
        let keep: Vec<bool> = cal
            .observations
            .iter()
            .map(|o| cal.devices[o.device].name != "proj2" || o.pose == 0)
            .collect();
        let mut it = keep.iter();
        cal.observations.retain(|_| *it.next().unwrap());
        let mut it = keep.iter();
        cal.solution.residuals.retain(|_| *it.next().unwrap());
        for (o, r) in cal.observations.iter().zip(&mut cal.solution.residuals) {
            if cal.devices[o.device].name == "cam1" {
                r.error *= 3.0;
            }
        }
        cal.excluded.push(Excluded {
            name: "cam9".into(),
            reason: "Zhang initialisation from 2 views: too few".into(),
        });
        let html = page(&cal, &[], Vec::new());
        assert!(
            html.contains("proj2 (projector) is seen in only 1 board pose "),
            "few poses"
        );
        assert!(html.contains("cam1: RMS"), "high RMS");
        assert!(html.contains("cam9 was not calibrated: Zhang initialisation"));
        assert!(!html.contains("cam0: RMS"));
    }

    #[test]
    fn numbers_carry_the_precision_of_their_std() {
        assert_eq!(with_std(2400.12345, 0.0567), "2400.123 ± 0.057");
        assert_eq!(with_std(-0.1234567, 0.000234), "-0.12346 ± 0.00023");
        assert_eq!(with_std(960.4, 12.0), "960 ± 12");
        assert_eq!(with_std(0.0, 0.0), "0 (fixed)");
        assert_eq!(nice_below(0.37), 0.2);
        assert_eq!(nice_below(730.0), 500.0);
        assert_eq!(esc("a<b>&'\""), "a&lt;b&gt;&amp;&#39;&quot;");
    }
}
