//! The printable target of one side: an SVG document in millimetres at exact physical size.

use super::{Board, BoardCircle, Side};
use std::fmt::Write;

/// Height of the strip holding the scale bar and the label (mm).
const STRIP: f64 = 12.0;
/// Length of the scale bar (mm).
const BAR: f64 = 100.0;

/// A length in mm for SVG: 4 decimals (0.1 µm), trailing zeros dropped.
fn mm(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" { "0" } else { s }.to_owned()
}

/// Text with XML's special characters escaped.
fn xml(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Where the scale bar and label go: in the board's margin below the circles, white on
/// black, or in a white strip added below a board whose margin is too narrow.
struct Strip {
    /// Whether the strip lies inside the board.
    inside: bool,
    /// Document height (mm).
    page_h: f64,
    /// Top of the 12 mm strip (mm, SVG y down).
    top: f64,
    /// Colour of the bar and the text.
    ink: &'static str,
}

impl Board {
    /// The printable target of one side as an SVG document, 1 user unit = 1 mm and the
    /// document `size[0]` mm × `size[1]` mm: the black board, a white circle of radius R at
    /// every lattice point, a dark annulus (inner, outer ring radii, one even-odd path each)
    /// in every ringed circle, a 100 mm scale bar with ticks every 10 mm and a label with the
    /// board's name and the side.
    ///
    /// The side is drawn as seen looking at it, in its own frame: board point (x, y) of the
    /// side is at SVG (size\[0\]/2 + x, size\[1\]/2 − y). Scale bar and label sit in the margin
    /// below the circles, white on black; a board whose margin is narrower than 12 mm gets a
    /// 12 mm white strip added below it for them (the only case where the document is larger
    /// than the board). The back of a single-sided board has no circles: it is the plain
    /// board (`hexcal board` refuses to draw it).
    pub fn svg(&self, side: Side) -> String {
        let [w, h] = self.size;
        let circles = self.circles(side);
        let strip = self.strip(&circles);
        let title = format!("{} — {} side", xml(&self.name), side);
        let mut s = String::new();
        let _ = writeln!(s, r#"<?xml version="1.0" encoding="UTF-8"?>"#);
        let _ = writeln!(
            s,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{0}mm" height="{1}mm" viewBox="0 0 {0} {1}">"#,
            mm(w),
            mm(strip.page_h)
        );
        let _ = writeln!(s, "<title>hexcal board {title}</title>");
        let _ = writeln!(
            s,
            r##"<rect id="board" x="0" y="0" width="{}" height="{}" fill="#000"/>"##,
            mm(w),
            mm(h)
        );
        self.write_circles(&mut s, &circles);
        self.write_rings(&mut s, &circles);
        if !strip.inside {
            let _ = writeln!(
                s,
                r##"<rect x="0" y="{}" width="{}" height="{}" fill="#fff"/>"##,
                mm(h),
                mm(w),
                mm(STRIP)
            );
        }
        write_scale_bar(&mut s, w, &strip, &title);
        let _ = writeln!(s, "</svg>");
        s
    }

    /// The strip for the scale bar and label below the lowest of `circles`.
    fn strip(&self, circles: &[BoardCircle]) -> Strip {
        let [_, h] = self.size;
        // Lowest circle edge, in SVG coordinates (y down).
        let circle_bottom = circles
            .iter()
            .map(|c| h / 2.0 - c.center_2d.y + self.radius)
            .fold(h / 2.0, f64::max);
        let inside = h - circle_bottom >= STRIP;
        let (page_h, top, ink) = if inside {
            (h, circle_bottom + (h - circle_bottom - STRIP) / 2.0, "#fff")
        } else {
            (h + STRIP, h, "#000")
        };
        Strip {
            inside,
            page_h,
            top,
            ink,
        }
    }

    /// The white circles, one `<circle>` each, as group "circles" into `s`.
    fn write_circles(&self, s: &mut String, circles: &[BoardCircle]) {
        let [w, h] = self.size;
        let _ = writeln!(s, r##"<g id="circles" fill="#fff">"##);
        for c in circles {
            let (x, y) = (w / 2.0 + c.center_2d.x, h / 2.0 - c.center_2d.y);
            let _ = writeln!(
                s,
                r#"<circle cx="{}" cy="{}" r="{}"/>"#,
                mm(x),
                mm(y),
                mm(self.radius)
            );
        }
        let _ = writeln!(s, "</g>");
    }

    /// The dark annuli of the ringed `circles`, as group "rings" into `s`.
    fn write_rings(&self, s: &mut String, circles: &[BoardCircle]) {
        let [w, h] = self.size;
        let (ro, ri) = (self.ring[1] * self.radius, self.ring[0] * self.radius);
        // One annulus per ringed circle: outer and inner circle as one even-odd path, so the
        // dark area is exactly ri ≤ ρ ≤ ro whatever the renderer's painting order.
        let _ = writeln!(s, r##"<g id="rings" fill="#000" fill-rule="evenodd">"##);
        for c in circles.iter().filter(|c| c.ringed) {
            let (x, y) = (w / 2.0 + c.center_2d.x, h / 2.0 - c.center_2d.y);
            let mut d = String::new();
            for r in [ro, ri] {
                let (a, b, rr, yy) = (mm(x + r), mm(x - r), mm(r), mm(y));
                let _ = write!(
                    d,
                    "M{a} {yy}A{rr} {rr} 0 1 0 {b} {yy}A{rr} {rr} 0 1 0 {a} {yy}Z"
                );
            }
            let _ = writeln!(s, r#"<path d="{d}"/>"#);
        }
        let _ = writeln!(s, "</g>");
    }
}

/// The scale bar of a board `w` mm wide and the label `title`, in `strip`, into `s`.
fn write_scale_bar(s: &mut String, w: f64, strip: &Strip, title: &str) {
    let ink = strip.ink;
    // Scale bar: numbers (baseline +3), ticks (+4…+6, minor +5…+6), bar (+6…+7.5),
    // a hint (baseline +11), all within [strip_top, strip_top + 12].
    let x0 = (w / 2.0 - BAR) / 2.0;
    let t = strip.top;
    let _ = writeln!(
        s,
        r#"<g id="scale-bar" fill="{ink}" font-family="sans-serif" font-size="3" text-anchor="middle">"#
    );
    let _ = writeln!(
        s,
        r#"<rect id="bar" x="{}" y="{}" width="{}" height="1.5"/>"#,
        mm(x0),
        mm(t + 6.0),
        mm(BAR)
    );
    for i in 0..=10 {
        let x = x0 + 10.0 * f64::from(i);
        let top = if i % 5 == 0 { t + 4.0 } else { t + 5.0 };
        let _ = writeln!(
            s,
            r#"<rect x="{}" y="{}" width="0.3" height="{}"/>"#,
            mm(x - 0.15),
            mm(top),
            mm(t + 6.0 - top)
        );
        if i % 5 == 0 {
            let unit = if i == 10 { " mm" } else { "" };
            let _ = writeln!(
                s,
                r#"<text x="{}" y="{}">{}{unit}</text>"#,
                mm(x),
                mm(t + 3.0),
                10 * i
            );
        }
    }
    let _ = writeln!(
        s,
        r#"<text x="{}" y="{}" font-size="2.5" text-anchor="start">print at 100 %: this bar must measure 100 mm</text>"#,
        mm(x0),
        mm(t + 11.0)
    );
    let _ = writeln!(s, "</g>");
    let _ = writeln!(
        s,
        r#"<text id="label" x="{}" y="{}" fill="{ink}" font-family="sans-serif" font-size="5" text-anchor="end">{title}</text>"#,
        mm(w - x0),
        mm(t + 8.0)
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point2;

    /// The value of attribute `name` in the element text `el`.
    fn attr(el: &str, name: &str) -> Option<String> {
        let key = format!(" {name}=\"");
        let start = el.find(&key)? + key.len();
        Some(el[start..].split('"').next()?.to_owned())
    }

    fn num(el: &str, name: &str) -> f64 {
        attr(el, name).unwrap().parse().unwrap()
    }

    /// Every element `<tag …>` of the document, as the text up to its closing `>`.
    fn elements<'a>(doc: &'a str, tag: &str) -> Vec<&'a str> {
        let open = format!("<{tag} ");
        doc.match_indices(&open)
            .map(|(i, _)| &doc[i..i + doc[i..].find('>').unwrap()])
            .collect()
    }

    /// Board point of an SVG point: the inverse of (w/2 + x, h/2 − y).
    fn board_point(b: &Board, x: f64, y: f64) -> Point2<f64> {
        Point2::new(x - b.size[0] / 2.0, b.size[1] / 2.0 - y)
    }

    #[test]
    fn hex600_svg_is_the_board_at_size() {
        let b = Board::hex600();
        for (side, rings) in [(Side::Front, 71), (Side::Back, 69)] {
            let doc = b.svg(side);
            let root = elements(&doc, "svg")[0];
            assert_eq!(attr(root, "width").as_deref(), Some("600mm"));
            assert_eq!(attr(root, "height").as_deref(), Some("500mm"));
            assert_eq!(attr(root, "viewBox").as_deref(), Some("0 0 600 500"));

            // Circles: all 797, radius 6, each at its lattice position (4 decimals: 5e-5 mm).
            let circles = elements(&doc, "circle");
            assert_eq!(circles.len(), 797, "{side}");
            let expect: Vec<Point2<f64>> = b.circles(side).iter().map(|c| c.center_2d).collect();
            for (el, want) in circles.iter().zip(&expect) {
                assert_eq!(num(el, "r"), 6.0);
                let p = board_point(&b, num(el, "cx"), num(el, "cy"));
                assert!((p - want).norm() < 1e-4, "{side}: {p} vs {want}");
            }
            // Spot checks against Board::position directly.
            for (q, r) in [(0, 0), (1, 0), (0, 1), (-8, -13), (21, -13)] {
                let want = b.position(crate::board::Hex::new(q, r));
                let (x, y) = (300.0 + want.x, 250.0 - want.y);
                let at = |el: &&&str| {
                    (num(el, "cx") - x).abs() < 1e-4 && (num(el, "cy") - y).abs() < 1e-4
                };
                assert_eq!(circles.iter().filter(at).count(), 1, "({q}, {r})");
            }

            // Rings: one even-odd path per ringed circle, centred on it, radii 4.5 and 2.7.
            let paths = elements(&doc, "path");
            assert_eq!(paths.len(), rings, "{side}");
            // Every ring sits on a distinct ringed lattice point, and all of them are drawn.
            let mut want: Vec<Point2<f64>> =
                b.ringed(side).iter().map(|&h| b.position(h)).collect();
            for el in &paths {
                let d = attr(el, "d").unwrap();
                let sub: Vec<&str> = d.split('M').filter(|p| !p.is_empty()).collect();
                assert_eq!(sub.len(), 2, "{d}");
                let mut radii = Vec::new();
                let mut centres = Vec::new();
                for p in sub {
                    let v: Vec<f64> = p
                        .split(['A', ' ', 'Z'])
                        .filter(|t| !t.is_empty())
                        .map(|t| t.parse().unwrap())
                        .collect();
                    // M x+r y A r r 0 1 0 x−r y A r r 0 1 0 x+r y Z
                    assert_eq!(v.len(), 16, "{d}");
                    let r = v[2];
                    radii.push(r);
                    centres.push(board_point(&b, v[0] - r, v[1]));
                }
                assert_eq!(radii, [4.5, 2.7]);
                assert!((centres[0] - centres[1]).norm() < 1e-4, "{d}");
                let i = want
                    .iter()
                    .position(|p| (p - centres[0]).norm() < 1e-4)
                    .unwrap_or_else(|| panic!("{side}: ring at {} on no ringed point", centres[0]));
                want.swap_remove(i);
            }
            assert!(want.is_empty(), "{side}: rings missing at {want:?}");

            // Scale bar exactly 100 mm; label names board and side.
            let bar = elements(&doc, "rect")
                .into_iter()
                .find(|el| attr(el, "id").as_deref() == Some("bar"))
                .unwrap();
            assert_eq!(num(bar, "width"), 100.0);
            let label = doc.split("id=\"label\"").nth(1).unwrap();
            let text = label.split('>').nth(1).unwrap().split('<').next().unwrap();
            assert_eq!(text, format!("hex600 — {side} side"));
        }
    }

    /// Scale bar and label lie in the margin: every text's glyph band (baseline − 1.0·size
    /// covers ascenders and accents, + 0.3·size descenders) and every rect but the board below
    /// the lowest circle edge and inside the page.
    #[test]
    fn annotations_do_not_touch_circles() {
        let b = Board::hex600();
        let doc = b.svg(Side::Front);
        let circle_bottom = elements(&doc, "circle")
            .iter()
            .map(|el| num(el, "cy") + num(el, "r"))
            .fold(f64::MIN, f64::max);
        assert!((circle_bottom - (250.0 + 13.0 * 20.0 * 0.75f64.sqrt() + 6.0)).abs() < 1e-4);
        let mut n = 0;
        for el in elements(&doc, "text") {
            let size = attr(el, "font-size").map_or(3.0, |s| s.parse().unwrap());
            let y = num(el, "y");
            assert!(y - size > circle_bottom && y + 0.3 * size < 500.0, "{el}");
            n += 1;
        }
        for el in elements(&doc, "rect").into_iter().skip(1) {
            let y = num(el, "y");
            assert!(y > circle_bottom && y + num(el, "height") < 500.0, "{el}");
            n += 1;
        }
        assert_eq!(n, 3 + 1 + 1 + 1 + 11);
    }

    #[test]
    fn narrow_margin_gets_a_strip_below() {
        let b = Board {
            size: [600.0, 480.0],
            ..Board::hex600()
        };
        let doc = b.svg(Side::Back);
        let root = elements(&doc, "svg")[0];
        assert_eq!(attr(root, "height").as_deref(), Some("492mm"));
        let board = elements(&doc, "rect")[0];
        assert_eq!(num(board, "height"), 480.0);
        for el in elements(&doc, "text") {
            assert!(num(el, "y") > 480.0 && num(el, "y") < 492.0, "{el}");
        }
    }

    #[test]
    fn names_are_escaped() {
        let b = Board {
            name: "a<b&c".into(),
            ..Board::hex600()
        };
        assert!(b.svg(Side::Front).contains("a&lt;b&amp;c — front side"));
    }
}
