//! Joining on exact lattice images: a perspective view of the lattice, split by a gap, the far
//! side labelled in a frame of its own.

use super::*;

/// A perspective view of the lattice plane: pitch units → pixels.
fn view() -> Matrix3<f64> {
    Matrix3::new(24.0, 3.0, 400.0, -2.0, 20.0, 300.0, 0.004, 0.012, 1.0)
}

/// Lattice positions with |q|, |r|, |q + r| ≤ 9.
fn disc() -> Vec<Hex> {
    (-9..=9)
        .flat_map(|q| (-9..=9).map(move |r| Hex::new(q, r)))
        .filter(|h| (h.q + h.r).abs() <= 9)
        .collect()
}

/// Two components of the view: the circles left of the gap (plane x < −`gap`/2), labelled
/// in the true frame, and those right of it (x > `gap`/2) labelled by `relabel`; `centres`
/// holds their image centres, `scale` stretches the right side's lattice about the gap.
fn split(gap: f64, relabel: LatticeMap, scale: f64) -> (Component, Component, Vec<Point2<f64>>) {
    let h = view();
    let (mut left, mut right, mut centres) =
        (Component::default(), Component::default(), Vec::new());
    for hex in disc() {
        let p = plane(hex);
        let (comp, label, p) = if p.x < -gap / 2.0 {
            (&mut left, hex, p)
        } else if p.x > gap / 2.0 {
            let p = Vector2::new(gap / 2.0 + (p.x - gap / 2.0) * scale, p.y * scale);
            (&mut right, relabel.apply(hex), p)
        } else {
            continue;
        };
        comp.points.push((centres.len() as u32, label));
        centres.push(Point2::from(apply(&h, p).unwrap()));
    }
    (left, right, centres)
}

#[test]
fn nearest_lattice_position_and_homography() {
    for hex in [Hex::new(0, 0), Hex::new(3, -5), Hex::new(-7, 2)] {
        let (h, d) = nearest_hex(plane(hex) + Vector2::new(0.2, -0.1));
        assert_eq!(h, hex);
        assert!((d - 0.2236).abs() < 1e-3);
    }
    let h = view();
    let pairs: Vec<_> = disc()
        .into_iter()
        .map(|x| (plane(x), apply(&h, plane(x)).unwrap()))
        .collect();
    let fit = fit_homography(&pairs).unwrap();
    assert!(residuals(&fit, &pairs).into_iter().fold(0.0, f64::max) < 1e-9);
}

/// Image → lattice plane pairs of the 16 circles of `disc()` nearest (3, −2), each image
/// centre moved by `shift` px for the listed circles.
fn support(shifted: &[usize], shift: f64) -> Vec<(Vector2<f64>, Vector2<f64>)> {
    let h = view();
    let mut near = disc();
    near.sort_by(|a, b| {
        let d = |x: &Hex| (plane(*x) - plane(Hex::new(3, -2))).norm();
        d(a).total_cmp(&d(b))
    });
    near.truncate(16);
    near.into_iter()
        .enumerate()
        .map(|(i, x)| {
            let s = if shifted.contains(&i) { shift } else { 0.0 };
            (apply(&h, plane(x)).unwrap() + Vector2::new(s, -s), plane(x))
        })
        .collect()
}

#[test]
fn a_local_fit_leaves_out_a_circle_far_off_it() {
    let tol = GridParams::default().join_fit_tolerance;
    // One centre 1.5 px off (≈ 0.09 pitch): unsound as it stands, sound without it.
    assert!(sound_fit(support(&[15], 1.5), tol, 0).is_none());
    let h = sound_fit(support(&[15], 1.5), tol, 2).unwrap();
    let p = apply(&h, apply(&view(), plane(Hex::new(6, -6))).unwrap()).unwrap();
    assert!((p - plane(Hex::new(6, -6))).norm() < 1e-6);
    // Three such circles are more than two may be left out.
    assert!(sound_fit(support(&[3, 9, 15], 1.5), tol, 2).is_none());
}

#[test]
fn a_component_across_a_gap_joins_in_the_true_frame() {
    let relabel = LatticeMap {
        rotation: 4,
        offset: Hex::new(17, -3),
    };
    let (mut left, right, centres) = split(3.0, relabel, 1.0);
    let (n_left, n_right) = (left.points.len(), right.points.len());
    let mut others = vec![right];
    let joined = join_into(
        &mut left,
        &mut others,
        &centres,
        &GridParams::default(),
        &|_, _| true,
    );
    assert_eq!((joined, others.len()), (1, 0));
    assert_eq!(left.points.len(), n_left + n_right);
    // Every label is the true one: the right side's relabelling undone.
    let truth = {
        let (l, r, _) = split(
            3.0,
            LatticeMap {
                rotation: 0,
                offset: Hex::new(0, 0),
            },
            1.0,
        );
        let mut t: Vec<(u32, Hex)> = l.points.into_iter().chain(r.points).collect();
        t.sort();
        t
    };
    let mut got = left.points.clone();
    got.sort();
    assert_eq!(got, truth);
}

#[test]
fn a_component_off_the_lattice_or_refused_stays_apart() {
    let identity = LatticeMap {
        rotation: 0,
        offset: Hex::new(0, 0),
    };
    let params = GridParams::default();
    // The far side on a lattice 15 % larger: it does not fall on predicted positions.
    let (mut left, right, centres) = split(3.0, identity, 1.15);
    let mut others = vec![right];
    assert_eq!(
        join_into(&mut left, &mut others, &centres, &params, &|_, _| true),
        0
    );
    assert_eq!(others.len(), 1);
    // A transform the caller refuses (the board's rings disagree) is not taken.
    let (mut left, right, centres) = split(3.0, identity, 1.0);
    let mut others = vec![right];
    assert_eq!(
        join_into(&mut left, &mut others, &centres, &params, &|_, _| false),
        0
    );
}

#[test]
fn a_component_on_held_positions_conflicts() {
    // A copy of part of the left side, moved in the image by two lattice steps onto the left
    // side's own circles and labelled one step on: it lands on positions the reference holds.
    let (mut left, _, centres) = split(
        3.0,
        LatticeMap {
            rotation: 0,
            offset: Hex::new(0, 0),
        },
        1.0,
    );
    let h = view();
    let mut copy = Component::default();
    let mut centres = centres;
    for &(_, hex) in left.points.iter().filter(|(_, x)| plane(*x).x > -6.0) {
        copy.points
            .push((centres.len() as u32, hex + Hex::new(1, 0)));
        let p = plane(hex) + Vector2::new(2.0, 0.0);
        centres.push(Point2::from(apply(&h, p).unwrap()));
    }
    let mut others = vec![copy];
    let params = GridParams::default();
    assert_eq!(
        join_into(&mut left, &mut others, &centres, &params, &|_, _| true),
        0
    );
}
