//! What the data cannot determine, found from the structure of the views before the
//! adjustment (docs/design.md §8, "Observability").
//!
//! Takes a bundle-adjustment [`Problem`] and its [`Options`]; gives the options with every
//! unobservable parameter held at its prior, and one [`Unobserved`] note per parameter
//! held, or refuses a device the data cannot calibrate at all. A held parameter is absent
//! from the adjustment's columns, so the covariance of the rest is the covariance with it
//! fixed.

use super::bundle::{Options, Problem};
use super::CalibError;
use hexcal_core::board::Side;
use std::collections::BTreeSet;
use std::fmt;

/// Distinct board-plane views (pose, side) a device needs: Zhang's count, below which its
/// focal lengths and principal point are not determined ([`super::zhang::MIN_VIEWS`]).
pub const MIN_DEVICE_VIEWS: usize = super::zhang::MIN_VIEWS;

/// A parameter the data cannot determine, held at its prior; `Display` gives the one line
/// the report and the command line print.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Unobserved {
    /// Both sides are seen, but never both in one board pose: the front→back transform
    /// trades off against the poses that show the back. Held at the board file's value.
    SideTransformNoPoseShowsBoth,
    /// Only one side of the board is seen: no observation depends on the front→back
    /// transform. Held at the board file's value.
    SideTransformOneSideSeen,
    /// Poses show both sides, but the information matrix is singular in the front→back
    /// transform (found after the adjustment, [`super::schur::Scaled::null_columns`]).
    /// Held at the board file's value.
    SideTransformInformation,
    /// The information matrix is singular in the board bend (29). Held flat.
    Bend,
}

impl fmt::Display for Unobserved {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Unobserved::SideTransformNoPoseShowsBoth => write!(
                f,
                "front→back transform not observed: no pose is seen from both sides; held at \
                 the board file's value — add a pose seen from both sides to measure it"
            ),
            Unobserved::SideTransformOneSideSeen => write!(
                f,
                "front→back transform not observed: only one side of the board is seen; held \
                 at the board file's value"
            ),
            Unobserved::SideTransformInformation => write!(
                f,
                "front→back transform not determined by the views that show both sides; held \
                 at the board file's value — add poses seen from both sides at other angles"
            ),
            Unobserved::Bend => write!(
                f,
                "board bend not determined by the views; held flat — add poses at other \
                 tilts and distances to measure it"
            ),
        }
    }
}

/// The sides seen in each board pose of `p`.
fn sides_per_pose(p: &Problem) -> Vec<[bool; 2]> {
    let mut seen = vec![[false; 2]; p.boards.len()];
    for ob in &p.observations {
        if let Some(s) = seen.get_mut(ob.pose) {
            s[usize::from(ob.side == Side::Back)] = true;
        }
    }
    seen
}

/// Whether the front→back transform is observable in `p`: `None` when it is, else why not.
fn side_transform(p: &Problem) -> Option<Unobserved> {
    let seen = sides_per_pose(p);
    if seen.iter().any(|s| s[0] && s[1]) {
        return None;
    }
    let front = seen.iter().any(|s| s[0]);
    let back = seen.iter().any(|s| s[1]);
    Some(if front && back {
        Unobserved::SideTransformNoPoseShowsBoth
    } else {
        Unobserved::SideTransformOneSideSeen
    })
}

/// Refuses a device with observations in fewer than [`MIN_DEVICE_VIEWS`] board-plane
/// views (pose, side), naming it: its intrinsics are not determined.
fn check_devices(p: &Problem) -> Result<(), CalibError> {
    let mut views = vec![BTreeSet::new(); p.devices.len()];
    for ob in &p.observations {
        views[ob.device].insert((ob.pose, ob.side == Side::Back));
    }
    match views
        .iter()
        .enumerate()
        .find(|(_, v)| v.len() < MIN_DEVICE_VIEWS)
    {
        Some((d, v)) => Err(CalibError::DeviceNotObserved {
            name: p.devices[d].name.clone(),
            views: v.len(),
            needed: MIN_DEVICE_VIEWS,
        }),
        None => Ok(()),
    }
}

/// The options `o` with every parameter `p`'s views cannot determine held at its prior,
/// and a note for each; refuses a device too few views see (its index and names checked
/// by the caller). A single-sided board has no side transform: none is refined and none is
/// noted.
pub fn hold_unobservable(
    p: &Problem,
    o: &Options,
) -> Result<(Options, Vec<Unobserved>), CalibError> {
    check_devices(p)?;
    let mut o = o.clone();
    let mut held = Vec::new();
    if !p.board.has(Side::Back) {
        o.refine_side_transform = false;
    } else if o.refine_side_transform {
        if let Some(why) = side_transform(p) {
            o.refine_side_transform = false;
            held.push(why);
        }
    }
    Ok((o, held))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::synthetic::SyntheticRig;

    #[test]
    fn the_side_transform_is_held_exactly_when_no_pose_shows_both_sides() {
        let rig = SyntheticRig::paper(8, 0.1, 3);
        let p = rig.perturbed_start(4);
        let o = Options::default();
        // The paper rig has cameras facing both sides: every pose shows both.
        let (kept, held) = hold_unobservable(&p, &o).unwrap();
        assert!(kept.refine_side_transform && held.is_empty());
        // The back only in poses 0–3, the front only in poses 4–7.
        let mut q = p.clone();
        q.observations
            .retain(|ob| (ob.side == Side::Back) == (ob.pose < 4));
        let (kept, held) = hold_unobservable(&q, &o).unwrap();
        assert!(!kept.refine_side_transform);
        assert_eq!(held, [Unobserved::SideTransformNoPoseShowsBoth]);
        // The front only.
        let q = Problem {
            observations: p
                .observations
                .iter()
                .filter(|ob| ob.side == Side::Front)
                .copied()
                .collect(),
            ..p.clone()
        };
        // (The cameras facing the back see nothing: only the structure is asked.)
        assert_eq!(
            side_transform(&q),
            Some(Unobserved::SideTransformOneSideSeen)
        );
    }

    #[test]
    fn a_device_seen_in_two_views_is_refused_by_name() {
        let rig = SyntheticRig::paper(4, 0.1, 3);
        let mut p = rig.perturbed_start(4);
        p.observations
            .retain(|ob| ob.pose < 2 || (ob.device != 4 && ob.via.is_none_or(|v| v.camera != 4)));
        let e = hold_unobservable(&p, &Options::default()).unwrap_err();
        assert!(e.to_string().contains("cam4"), "{e}");
    }
}
