//! The lattice check on exact lattice images: a perspective view of the lattice, a few
//! centres moved off their positions.

use super::*;
use crate::grid::join::plane;
use hexcal_core::board::Hex;
use hexcal_core::images::Ellipse;
use nalgebra::{Matrix3, Vector2};

/// Radius √(ab) of every circle (px): the view's pitch is 20–24 px, ν = 3.33.
const R: f64 = 6.0;

/// A perspective view of the lattice plane: pitch units → pixels.
fn view() -> Matrix3<f64> {
    Matrix3::new(24.0, 3.0, 400.0, -2.0, 20.0, 300.0, 0.004, 0.012, 1.0)
}

/// The circles with |q|, |r|, |q + r| ≤ 6, labelled in the true frame, each centre moved by
/// the listed (circle, offset in px).
fn lattice(moved: &[(usize, Vector2<f64>)]) -> (Component, Vec<Circle>) {
    let mut comp = Component::default();
    let mut circles = Vec::new();
    for q in -6..=6 {
        for r in -6..=6 {
            let hex = Hex::new(q, r);
            if (q + r).abs() > 6 {
                continue;
            }
            let i = circles.len();
            let shift = moved
                .iter()
                .find(|m| m.0 == i)
                .map_or(Vector2::zeros(), |m| m.1);
            let center = Point2::from(apply(&view(), plane(hex)).unwrap() + shift);
            comp.points.push((i as u32, hex));
            circles.push(Circle {
                ellipse: Ellipse {
                    center,
                    a: R,
                    b: R,
                    angle: 0.0,
                },
                score: 0.1,
                background: 0.1,
                foreground: 0.9,
                edge_rms: 0.05,
            });
        }
    }
    (comp, circles)
}

/// The circles left after the check.
fn kept(moved: &[(usize, Vector2<f64>)]) -> Vec<u32> {
    let (mut comp, circles) = lattice(moved);
    drop_off_lattice(&mut comp, &circles, &GridParams::default());
    comp.points.iter().map(|p| p.0).collect()
}

#[test]
fn whole_lattices_keep_every_centre() {
    assert_eq!(kept(&[]).len(), 127);
}

#[test]
fn a_centre_a_third_of_its_radius_off_is_dropped() {
    let off = Vector2::new(R / 3.0, 0.0);
    let left = kept(&[(60, off)]);
    assert_eq!(left.len(), 126);
    assert!(!left.contains(&60));
    // Two such neighbours: each judged by a fit that leaves the other out.
    let left = kept(&[(60, off), (61, -off)]);
    assert_eq!(left.len(), 125);
    assert!(!left.contains(&60) && !left.contains(&61));
}

#[test]
fn a_centre_a_tenth_of_its_radius_off_is_kept() {
    // Far off its neighbourhood's (zero) residuals, but within what the lattice check allows.
    assert_eq!(kept(&[(60, Vector2::new(0.0, 0.1 * R))]).len(), 127);
}
