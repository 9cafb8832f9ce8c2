//! What each device has seen so far: poses seen, a coverage map of its image, the range
//! of board tilts and the steep views — half of the done rule ([`super::verdict`]), and
//! what the console shows. One rule ([`count_view`]) says what a view counts as, for the
//! captured poses here and for the console's live preview alike.
//!
//! Takes the processed poses' views and the devices; gives [`DeviceStats`] per device.

use crate::board::Board;
use crate::observations::CameraView;
use crate::observations::DeviceInfo;
use crate::observations::DeviceKind;
use nalgebra::{Matrix2, Point2};
use serde::Serialize;

/// Columns and rows of a device's coverage map.
pub const GRID: (usize, usize) = (8, 5);
/// Points a device needs in a pose for the pose to count as seen by it.
pub const MIN_POINTS: usize = 12;

/// What one view of the board counts as ([`count_view`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct ViewCount {
    /// At least [`MIN_POINTS`] points: the device sees the board.
    pub seen: bool,
    /// The board's tilt against the device's image plane (deg, [`tilt_degrees`]).
    pub tilt: Option<f64>,
    /// Seen at a tilt beyond [`super::MAX_VIEW_ANGLE_DEG`], the steepest view the guidance
    /// trusts a detector with.
    pub steep: bool,
}

/// What a view with these board points (mm) and the device's pixels of them counts as.
pub fn count_view(board: &[Point2<f64>], pixels: &[Point2<f64>]) -> ViewCount {
    let seen = pixels.len() >= MIN_POINTS;
    let tilt = tilt_degrees(board, pixels);
    ViewCount {
        seen,
        tilt,
        steep: seen && tilt.is_some_and(|t| t > super::MAX_VIEW_ANGLE_DEG),
    }
}

/// One device's progress.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DeviceStats {
    /// Name.
    pub name: String,
    /// "camera" or "projector".
    pub kind: &'static str,
    /// Image (raster) size (px).
    pub size: [u32; 2],
    /// Calibration poses (not held out) in which it saw at least [`MIN_POINTS`] points.
    pub poses: usize,
    /// Points per coverage cell, row by row ([`GRID`] columns and rows).
    pub cells: Vec<u32>,
    /// Fraction of the coverage cells holding a point (the done rule's figure).
    pub coverage: f64,
    /// Smallest and largest board tilt seen (degrees), once a pose was seen.
    pub tilt: Option<[f64; 2]>,
    /// Of the poses seen, those seen steeply ([`ViewCount::steep`]).
    pub steep: usize,
    /// Points in the latest processed pose.
    pub latest: usize,
}

impl DeviceStats {
    /// A device that has seen nothing yet.
    pub fn new(d: &DeviceInfo) -> DeviceStats {
        DeviceStats {
            name: d.name.clone(),
            kind: match d.kind {
                DeviceKind::Camera => "camera",
                DeviceKind::Projector => "projector",
            },
            size: [d.width, d.height],
            poses: 0,
            cells: vec![0; GRID.0 * GRID.1],
            coverage: 0.0,
            tilt: None,
            steep: 0,
            latest: 0,
        }
    }

    /// Take in one pose's observations by this device: board points (mm, in their side's
    /// frame) and the device's pixels of them, counted by [`count_view`]. Held-out poses
    /// only count as the latest.
    pub fn add(&mut self, board: &[Point2<f64>], pixels: &[Point2<f64>], held_out: bool) {
        self.latest = pixels.len();
        let view = count_view(board, pixels);
        if held_out || !view.seen {
            return;
        }
        self.poses += 1;
        self.steep += usize::from(view.steep);
        let [w, h] = self.size;
        for p in pixels {
            let cx = (p.x + 0.5) / f64::from(w) * GRID.0 as f64;
            let cy = (p.y + 0.5) / f64::from(h) * GRID.1 as f64;
            if (0.0..GRID.0 as f64).contains(&cx) && (0.0..GRID.1 as f64).contains(&cy) {
                self.cells[cy as usize * GRID.0 + cx as usize] += 1;
            }
        }
        let covered = self.cells.iter().filter(|&&n| n > 0).count();
        self.coverage = covered as f64 / self.cells.len() as f64;
        if let Some(t) = view.tilt {
            self.tilt = Some(match self.tilt {
                None => [t, t],
                Some([lo, hi]) => [lo.min(t), hi.max(t)],
            });
        }
    }
}

/// The board's tilt against a device's image plane (degrees) from its points: the affine
/// map from board to pixels fitted by least squares (weak perspective), whose singular values
/// s1 ≥ s2 give cos(tilt) = s2/s1. `None` with fewer than 6 points or a degenerate fit.
pub fn tilt_degrees(board: &[Point2<f64>], pixels: &[Point2<f64>]) -> Option<f64> {
    let n = board.len().min(pixels.len());
    if n < 6 {
        return None;
    }
    let mean = |ps: &[Point2<f64>]| {
        ps[..n]
            .iter()
            .map(|p| p.coords)
            .sum::<nalgebra::Vector2<f64>>()
            / n as f64
    };
    let (mb, mp) = (mean(board), mean(pixels));
    let (mut bb, mut pb) = (Matrix2::zeros(), Matrix2::zeros());
    for (b, p) in board.iter().zip(pixels).take(n) {
        let (db, dp) = (b.coords - mb, p.coords - mp);
        bb += db * db.transpose();
        pb += dp * db.transpose();
    }
    let a = pb * bb.try_inverse()?;
    let s = a.singular_values();
    let (s1, s2) = (s[0].max(s[1]), s[0].min(s[1]));
    (s1 > 0.0 && s2.is_finite()).then(|| (s2 / s1).clamp(0.0, 1.0).acos().to_degrees())
}

/// Board points (mm) and a device's pixels of them.
pub type PointPairs = (Vec<Point2<f64>>, Vec<Point2<f64>>);

/// Every device's observations in one camera view: per device index, the board points
/// (mm) and the device's pixels (the camera's own, and each projector's decoded ones).
pub fn observations(board: &Board, view: &CameraView, devices: usize) -> Vec<PointPairs> {
    let mut out = vec![(Vec::new(), Vec::new()); devices];
    for p in &view.points {
        let x = board.position(p.hex);
        if let Some(o) = out.get_mut(view.camera) {
            o.0.push(x);
            o.1.push(p.image);
        }
        for q in &p.projectors {
            if let Some(o) = out.get_mut(q.projector) {
                o.0.push(x);
                o.1.push(q.pixel);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::Hex;
    use nalgebra::{Rotation3, Vector3};

    /// Board points tilted by `tilt` about a skew axis, seen by a pinhole (f 1500 px) from
    /// `distance` mm.
    fn view(tilt: f64, distance: f64) -> (Vec<Point2<f64>>, Vec<Point2<f64>>) {
        let board = Board::hex600();
        let axis = Vector3::new(0.6, 0.8, 0.0).normalize();
        let r = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), tilt.to_radians());
        let (mut b, mut p) = (Vec::new(), Vec::new());
        for h in board
            .lattice()
            .into_iter()
            .filter(|h| h.distance(Hex::new(0, 0)) < 6)
        {
            let x = board.position(h);
            let c = r * Vector3::new(x.x, x.y, 0.0) + Vector3::new(0.0, 0.0, distance);
            b.push(x);
            p.push(Point2::new(
                1500.0 * c.x / c.z + 960.0,
                1500.0 * c.y / c.z + 600.0,
            ));
        }
        (b, p)
    }

    #[test]
    fn tilt_is_read_from_the_foreshortening() {
        // A patch of ±120 mm at 1.5 m: perspective changes the scale across it by up to
        // ±8 % · sin(tilt), which bounds the weak-perspective error to about 3°.
        for tilt in [0.0, 20.0, 40.0, 60.0] {
            let (b, p) = view(tilt, 1500.0);
            let t = tilt_degrees(&b, &p).unwrap();
            assert!((t - tilt).abs() < 3.0, "tilt {tilt}: read {t}");
        }
        let (b, p) = view(30.0, 1500.0);
        assert!(tilt_degrees(&b[..5], &p[..5]).is_none());
    }

    #[test]
    fn coverage_cells_count_the_points_of_seen_poses_only() {
        let d = DeviceInfo {
            name: "cam0".into(),
            kind: DeviceKind::Camera,
            width: 1920,
            height: 1200,
        };
        let mut s = DeviceStats::new(&d);
        let (b, p) = view(40.0, 1500.0);
        s.add(&b, &p, true);
        assert_eq!((s.poses, s.coverage, s.tilt), (0, 0.0, None));
        s.add(&b, &p, false);
        assert_eq!(s.poses, 1);
        assert_eq!(s.cells.iter().sum::<u32>() as usize, p.len());
        // The patch spans about ±250 px around the centre: the middle cells only.
        assert!(s.coverage > 0.0 && s.coverage < 0.5, "{}", s.coverage);
        let [lo, hi] = s.tilt.unwrap();
        assert!((lo - 40.0).abs() < 3.0 && lo == hi);
        s.add(&b[..MIN_POINTS - 1], &p[..MIN_POINTS - 1], false);
        assert_eq!((s.poses, s.latest), (1, MIN_POINTS - 1));
        // A steep view counts as seen, and as steep.
        assert_eq!(s.steep, 0);
        let (b, p) = view(70.0, 1500.0);
        s.add(&b, &p, false);
        assert_eq!((s.poses, s.steep), (2, 1));
        assert!(count_view(&b, &p).steep && !count_view(&b[..5], &p[..5]).steep);
    }
}
