//! The overlay picture of one analysed image: the image dimmed to grey, each detected
//! circle's fitted ellipse (green when labelled, red when not), lattice links between
//! labelled neighbours (cyan when anchored, yellow when not) and each point's "q,r" label
//! in a 3×5 pixel font.

use super::Analysis;
use crate::board::Hex;
use crate::images::{Ellipse, FloatImage};
use image::{Rgb, RgbImage};
use std::collections::HashMap;

const LABELLED: Rgb<u8> = Rgb([40, 230, 40]);
const UNLABELLED: Rgb<u8> = Rgb([240, 40, 40]);
const ANCHORED_LINK: Rgb<u8> = Rgb([40, 200, 240]);
const FREE_LINK: Rgb<u8> = Rgb([240, 210, 40]);
const TEXT: Rgb<u8> = Rgb([255, 80, 255]);
const TEXT_BACK: Rgb<u8> = Rgb([0, 0, 0]);

/// Draw the overlay of an analysed image (see the module doc).
pub fn draw_overlay(image: &FloatImage, analysis: &Analysis) -> RgbImage {
    let mut out = dimmed(image);
    let labelled: HashMap<usize, Hex> = analysis
        .grid
        .points
        .iter()
        .map(|p| (p.circle, p.hex))
        .collect();
    // Links first so that outlines and labels stay on top.
    let by_hex: HashMap<Hex, usize> = analysis
        .grid
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| (p.hex, i))
        .collect();
    for p in &analysis.grid.points {
        // Directions 0–2 reach each link once.
        for k in 0..3 {
            if let Some(&j) = by_hex.get(&p.hex.neighbour(k)) {
                let colour = if p.anchored { ANCHORED_LINK } else { FREE_LINK };
                let o = analysis.grid.points[j].image;
                line(&mut out, (p.image.x, p.image.y), (o.x, o.y), colour);
            }
        }
    }
    for (i, c) in analysis.circles.iter().enumerate() {
        let colour = if labelled.contains_key(&i) {
            LABELLED
        } else {
            UNLABELLED
        };
        ellipse(&mut out, &c.ellipse, colour);
    }
    for p in &analysis.grid.points {
        let r = analysis.circles[p.circle].ellipse.radius();
        let scale = ((r / 10.0).round() as u32).clamp(1, 4);
        let text = format!("{},{}", p.hex.q, p.hex.r);
        // Centred on the circle centre.
        let w = text.len() as f64 * 4.0 * f64::from(scale);
        let x0 = (p.image.x - w / 2.0).round() as i64;
        let y0 = (p.image.y - 2.5 * f64::from(scale)).round() as i64;
        label(&mut out, x0, y0, &text, scale);
    }
    out
}

/// The image mapped from its 1st–99th percentile range to 0–180 grey.
fn dimmed(image: &FloatImage) -> RgbImage {
    let mut v: Vec<f32> = image.as_raw().iter().step_by(7).copied().collect();
    v.sort_by(f32::total_cmp);
    let at = |f: f64| v.get(((v.len() - 1) as f64 * f) as usize).copied();
    let (lo, hi) = (at(0.01).unwrap_or(0.0), at(0.99).unwrap_or(1.0));
    let span = (hi - lo).max(f32::EPSILON);
    RgbImage::from_fn(image.width(), image.height(), |x, y| {
        let g = ((image.get_pixel(x, y).0[0] - lo) / span).clamp(0.0, 1.0) * 180.0;
        Rgb([g as u8; 3])
    })
}

fn put(img: &mut RgbImage, x: i64, y: i64, colour: Rgb<u8>) {
    if x >= 0 && y >= 0 && x < i64::from(img.width()) && y < i64::from(img.height()) {
        img.put_pixel(x as u32, y as u32, colour);
    }
}

/// A straight line between two pixel positions, one dot per pixel along its longer extent.
fn line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), colour: Rgb<u8>) {
    let n = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().max(1.0) as usize;
    for i in 0..=n {
        let t = i as f64 / n as f64;
        let x = a.0 + t * (b.0 - a.0);
        let y = a.1 + t * (b.1 - a.1);
        put(img, x.round() as i64, y.round() as i64, colour);
    }
}

/// An ellipse outline, dots about half a pixel apart.
fn ellipse(img: &mut RgbImage, e: &Ellipse, colour: Rgb<u8>) {
    let n = ((std::f64::consts::TAU * e.a * 2.0).ceil() as usize).clamp(16, 4096);
    let (s, c) = e.angle.sin_cos();
    for i in 0..n {
        let t = std::f64::consts::TAU * i as f64 / n as f64;
        let (u, v) = (e.a * t.cos(), e.b * t.sin());
        let x = e.center.x + u * c - v * s;
        let y = e.center.y + u * s + v * c;
        put(img, x.round() as i64, y.round() as i64, colour);
    }
}

/// The 3×5 glyph of a label character, rows top first, bit 2 the left column.
fn glyph(ch: char) -> [u8; 5] {
    match ch {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '-' => [0, 0, 7, 0, 0],
        ',' => [0, 0, 0, 2, 4],
        _ => [0; 5],
    }
}

/// Text at top-left (x0, y0), each font pixel a `scale`×`scale` block, on a dark box.
fn label(img: &mut RgbImage, x0: i64, y0: i64, text: &str, scale: u32) {
    let s = i64::from(scale);
    let width = 4 * s * text.chars().count() as i64;
    for y in y0 - 1..y0 + 5 * s + 1 {
        for x in x0 - 1..x0 + width {
            put(img, x, y, TEXT_BACK);
        }
    }
    for (i, ch) in text.chars().enumerate() {
        let rows = glyph(ch);
        for (row, bits) in rows.iter().enumerate() {
            for col in 0..3 {
                if bits & (4 >> col) == 0 {
                    continue;
                }
                for dy in 0..s {
                    for dx in 0..s {
                        put(
                            img,
                            x0 + 4 * s * i as i64 + col * s + dx,
                            y0 + row as i64 * s + dy,
                            TEXT,
                        );
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::Circle;
    use crate::grid::{Grid, LabelledPoint};
    use nalgebra::Point2;

    fn circle(x: f64, y: f64) -> Circle {
        Circle {
            ellipse: Ellipse {
                center: Point2::new(x, y),
                a: 10.0,
                b: 10.0,
                angle: 0.0,
            },
            score: 0.2,
            background: 0.0,
            foreground: 1.0,
            edge_rms: 0.0,
        }
    }

    #[test]
    fn glyphs_of_label_characters_are_distinct() {
        let chars: Vec<char> = "0123456789-,".chars().collect();
        for (i, a) in chars.iter().enumerate() {
            assert_ne!(glyph(*a), [0; 5], "{a}");
            for b in &chars[i + 1..] {
                assert_ne!(glyph(*a), glyph(*b), "{a} vs {b}");
            }
        }
    }

    #[test]
    fn draws_outlines_links_and_labels() {
        let image = FloatImage::from_pixel(100, 60, image::Luma([5.0]));
        let analysis = Analysis {
            circles: vec![circle(25.0, 30.0), circle(70.0, 30.0), circle(50.0, 50.0)],
            grid: Grid {
                points: [(0, 25.0, 0), (1, 70.0, 1)]
                    .map(|(i, x, q)| LabelledPoint {
                        circle: i,
                        image: Point2::new(x, 30.0),
                        hex: Hex::new(q, 0),
                        side: None,
                        anchored: true,
                        ringed: false,
                    })
                    .to_vec(),
                anchored: true,
                ..Grid::default()
            },
        };
        let out = draw_overlay(&image, &analysis);
        // Outline pixels: labelled green on circle 0's rim, red on the unlabelled one's.
        assert_eq!(*out.get_pixel(35, 30), LABELLED);
        assert_eq!(*out.get_pixel(50, 40), UNLABELLED);
        // The link between the two labelled points, midway.
        assert_eq!(*out.get_pixel(47, 30), ANCHORED_LINK);
        // Label "0,0" centred on circle 0: scale 1, 12 px wide from x = 19; the first "0"
        // has its top row lit and its middle hollow.
        assert_eq!(*out.get_pixel(19, 28), TEXT);
        assert_eq!(*out.get_pixel(20, 29), TEXT_BACK);
    }
}
