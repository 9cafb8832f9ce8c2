//! Pose-graph initialisation (docs/design.md §8): a maximum spanning tree over (device, board
//! pose) pairs weighted by point counts chains per-view pose estimates into one frame.
//!
//! Takes, per (device, board pose) pair, an estimate of T_device_board and the number of
//! points behind it; gives every reachable device's pose T_device_ref (the reference device
//! is the identity) and every reachable board pose T_ref_board.

use nalgebra::Isometry3;
use std::collections::BinaryHeap;

/// One device's pose estimate in one board pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PairEstimate {
    /// Device index.
    pub device: usize,
    /// Board-pose index.
    pub pose: usize,
    /// T_device_board: board frame (front side) into the device frame.
    pub device_from_board: Isometry3<f64>,
    /// Points behind the estimate (the edge weight).
    pub points: usize,
}

/// Poses chained through the spanning tree; `None` where a device or board pose is not
/// connected to the reference device.
#[derive(Clone, Debug, PartialEq)]
pub struct ChainedPoses {
    /// T_device_ref per device.
    pub devices: Vec<Option<Isometry3<f64>>>,
    /// T_ref_board per board pose.
    pub boards: Vec<Option<Isometry3<f64>>>,
}

#[derive(PartialEq, Eq, PartialOrd, Ord)]
enum Node {
    Device(usize),
    Board(usize),
}

/// Chain the pair estimates from `reference` outwards, always taking the heaviest edge that
/// reaches a new node (Prim's algorithm on point counts).
pub fn chain(
    pairs: &[PairEstimate],
    devices: usize,
    boards: usize,
    reference: usize,
) -> ChainedPoses {
    let mut out = ChainedPoses {
        devices: vec![None; devices],
        boards: vec![None; boards],
    };
    if reference >= devices {
        return out;
    }
    out.devices[reference] = Some(Isometry3::identity());
    let mut heap = BinaryHeap::new();
    let push_edges = |heap: &mut BinaryHeap<(usize, usize)>, node: Node| {
        for (i, p) in pairs.iter().enumerate() {
            let touches = match node {
                Node::Device(d) => p.device == d,
                Node::Board(b) => p.pose == b,
            };
            if touches {
                heap.push((p.points, i));
            }
        }
    };
    push_edges(&mut heap, Node::Device(reference));
    while let Some((_, i)) = heap.pop() {
        let p = &pairs[i];
        match (out.devices[p.device], out.boards[p.pose]) {
            (Some(t_dev_ref), None) => {
                // T_ref_board = T_device_ref⁻¹ · T_device_board
                out.boards[p.pose] = Some(t_dev_ref.inverse() * p.device_from_board);
                push_edges(&mut heap, Node::Board(p.pose));
            }
            (None, Some(t_ref_board)) => {
                // T_device_ref = T_device_board · T_ref_board⁻¹
                out.devices[p.device] = Some(p.device_from_board * t_ref_board.inverse());
                push_edges(&mut heap, Node::Device(p.device));
            }
            _ => {}
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn iso(rx: f64, ry: f64, t: [f64; 3]) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_scaled_axis(Vector3::new(rx, ry, 0.3)),
        )
    }

    #[test]
    fn chains_exact_estimates_and_reports_unreachable() {
        let devs = [
            Isometry3::identity(),
            iso(0.1, 1.2, [500.0, 0.0, 100.0]),
            iso(-0.2, 3.0, [0.0, 50.0, 2000.0]),
        ];
        let boards = [
            iso(0.3, 0.1, [0.0, 0.0, 1500.0]),
            iso(-0.2, 1.5, [100.0, 0.0, 1400.0]),
        ];
        // Device 0 sees board 0, device 1 sees boards 0 and 1, device 2 sees board 1;
        // device 3 sees only board 2, which nobody else sees.
        let mut pairs = Vec::new();
        for (d, b) in [(0, 0), (1, 0), (1, 1), (2, 1)] {
            pairs.push(PairEstimate {
                device: d,
                pose: b,
                device_from_board: devs[d] * boards[b],
                points: 100,
            });
        }
        pairs.push(PairEstimate {
            device: 3,
            pose: 2,
            device_from_board: Isometry3::identity(),
            points: 500,
        });
        let c = chain(&pairs, 4, 3, 0);
        for (e, truth) in c.devices.iter().zip(&devs) {
            let e = e.unwrap();
            assert!((e.translation.vector - truth.translation.vector).norm() < 1e-9);
            assert!(e.rotation.angle_to(&truth.rotation) < 1e-12);
        }
        for (e, truth) in c.boards.iter().zip(&boards) {
            let e = e.unwrap();
            assert!((e.translation.vector - truth.translation.vector).norm() < 1e-9);
        }
        assert!(c.devices[3].is_none() && c.boards[2].is_none());
    }

    #[test]
    fn prefers_heavier_edges() {
        // Device 1 reaches the reference through board 0 (10 points, wrong estimate) or
        // board 1 (400 points, right estimate): the tree must use board 1.
        let dev1 = iso(0.2, 0.4, [300.0, 0.0, 0.0]);
        let (b0, b1) = (
            iso(0.1, 0.0, [0.0, 0.0, 1000.0]),
            iso(0.0, 0.2, [0.0, 0.0, 1200.0]),
        );
        let pairs = [
            PairEstimate {
                device: 0,
                pose: 0,
                device_from_board: b0,
                points: 300,
            },
            PairEstimate {
                device: 0,
                pose: 1,
                device_from_board: b1,
                points: 300,
            },
            PairEstimate {
                device: 1,
                pose: 0,
                device_from_board: iso(0.0, 0.0, [9.0; 3]),
                points: 10,
            },
            PairEstimate {
                device: 1,
                pose: 1,
                device_from_board: dev1 * b1,
                points: 400,
            },
        ];
        let c = chain(&pairs, 2, 2, 0);
        assert!((c.devices[1].unwrap().translation.vector - dev1.translation.vector).norm() < 1e-9);
    }
}
