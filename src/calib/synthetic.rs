//! A synthetic paper-like rig with exact observations, for tests and benchmarks of the
//! calibration stage: cameras and projectors around a double-sided board, some facing each
//! other across it, board poses turned so both sides are seen.

use super::bundle::{Device, DeviceKind, Observation, Via};
use crate::board::{Board, Side};
use crate::camera::{CameraModel, Distortion, Intrinsics};
use nalgebra::{
    Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use rand::{rngs::StdRng, Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

/// A rig with ground truth and noisy observations.
#[derive(Clone, Debug)]
pub struct SyntheticRig {
    /// The board.
    pub board: Board,
    /// True devices (device 0 is the reference, T_device_ref).
    pub devices: Vec<Device>,
    /// True board poses T_ref_board.
    pub boards: Vec<Isometry3<f64>>,
    /// Noisy observations.
    pub observations: Vec<Observation>,
}

/// T_world_device of a device at `eye` looking at `target`, y down, world y up.
pub fn look_at(eye: Point3<f64>, target: Point3<f64>) -> Isometry3<f64> {
    let z = (target - eye).normalize();
    let up = Vector3::y();
    let y = -(up - z * up.dot(&z)).normalize();
    let x = y.cross(&z);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(
        Translation3::from(eye.coords),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

fn around(azimuth_deg: f64, elevation_deg: f64, distance: f64) -> Point3<f64> {
    let (a, e) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    Point3::new(
        distance * e.cos() * a.sin(),
        distance * e.sin(),
        distance * e.cos() * a.cos(),
    )
}

/// Exact image-ellipse centre of a board circle: the centre of the conic fitted to densely
/// projected rim points (independent of the solver's closed-form bias model).
pub fn ellipse_center(
    model: &CameraModel,
    device_from_side: &Isometry3<f64>,
    center: Point2<f64>,
    radius: f64,
) -> Option<Point2<f64>> {
    let n = 64;
    let mut ata = nalgebra::Matrix5::<f64>::zeros();
    let mut atb = nalgebra::Vector5::<f64>::zeros();
    let c0 = model.project(&(device_from_side * Point3::new(center.x, center.y, 0.0)))?;
    for i in 0..n {
        let t = std::f64::consts::TAU * i as f64 / n as f64;
        let p = device_from_side
            * Point3::new(
                center.x + radius * t.cos(),
                center.y + radius * t.sin(),
                0.0,
            );
        let q = model.project(&p)? - c0;
        // x² + B xy + C y² + D x + E y + F = 0 with the x² coefficient fixed to 1.
        let row = nalgebra::Vector5::new(q.x * q.y, q.y * q.y, q.x, q.y, 1.0);
        ata += row * row.transpose();
        atb += row * (-q.x * q.x);
    }
    let s = ata.lu().solve(&atb)?;
    let (b, c, d, e) = (s[0], s[1], s[2], s[3]);
    let m = nalgebra::Matrix2::new(1.0, b / 2.0, b / 2.0, c);
    let off = -m.try_inverse()? * nalgebra::Vector2::new(d / 2.0, e / 2.0);
    Some(c0 + off)
}

impl SyntheticRig {
    /// The paper-like rig: 6 cameras (3 facing the front, 3 the back), 3 projectors
    /// (2 front, 1 back), `poses` board poses; observation noise σ px on every coordinate
    /// of cameras and projectors alike.
    pub fn paper(poses: usize, sigma: f64, seed: u64) -> SyntheticRig {
        let mut rng = StdRng::seed_from_u64(seed);
        let board = Board::hex600();
        let cam_model = |rng: &mut StdRng| CameraModel {
            width: 1920,
            height: 1200,
            intrinsics: Intrinsics {
                fx: 2400.0 * rng.random_range(0.97..1.03),
                fy: 2400.0 * rng.random_range(0.97..1.03),
                cx: 960.0 + rng.random_range(-20.0..20.0),
                cy: 600.0 + rng.random_range(-20.0..20.0),
            },
            distortion: Distortion {
                k1: rng.random_range(-0.2..-0.05),
                k2: rng.random_range(0.0..0.1),
                p1: rng.random_range(-1e-3..1e-3),
                p2: rng.random_range(-1e-3..1e-3),
                ..Default::default()
            },
        };
        let proj_model = |rng: &mut StdRng| CameraModel {
            width: 1920,
            height: 1080,
            intrinsics: Intrinsics {
                fx: 2200.0 * rng.random_range(0.98..1.02),
                fy: 2200.0 * rng.random_range(0.98..1.02),
                cx: 960.0 + rng.random_range(-10.0..10.0),
                // Lens shift: principal point near the bottom edge.
                cy: 1000.0 + rng.random_range(-20.0..20.0),
            },
            distortion: Distortion {
                k1: rng.random_range(-0.05..0.05),
                ..Default::default()
            },
        };
        let target = Point3::origin();
        let mut world = Vec::new();
        let mut devices = Vec::new();
        for (i, az) in [0.0, -35.0, 35.0, 180.0, 150.0, 210.0]
            .into_iter()
            .enumerate()
        {
            world.push(look_at(
                around(az, 12.0 * ((i % 3) as f64 - 1.0), 1500.0),
                target,
            ));
            devices.push((format!("cam{i}"), DeviceKind::Camera, cam_model(&mut rng)));
        }
        for (i, az) in [15.0, -20.0, 170.0].into_iter().enumerate() {
            world.push(look_at(around(az, 5.0, 1300.0), target));
            devices.push((
                format!("proj{i}"),
                DeviceKind::Projector,
                proj_model(&mut rng),
            ));
        }
        let ref_from_world = world[0].inverse();
        let devices: Vec<Device> = devices
            .into_iter()
            .zip(&world)
            .map(|((name, kind, model), w)| Device {
                name,
                kind,
                model,
                pose: w.inverse() * world[0],
            })
            .collect();
        let boards: Vec<Isometry3<f64>> = (0..poses)
            .map(|k| {
                let yaw = (-35.0 + 70.0 * k as f64 / (poses.max(2) - 1) as f64).to_radians();
                let tilt = rng.random_range(-25f64..25.0).to_radians();
                let roll = rng.random_range(-20f64..20.0).to_radians();
                let r = UnitQuaternion::from_euler_angles(tilt, yaw, roll);
                let t = Translation3::new(
                    rng.random_range(-60.0..60.0),
                    rng.random_range(-60.0..60.0),
                    rng.random_range(-80.0..80.0),
                );
                ref_from_world * Isometry3::from_parts(t, r)
            })
            .collect();
        let noise = Normal::new(0.0, sigma.max(1e-300)).expect("finite σ");
        let mut observations = Vec::new();
        let inside = |m: &CameraModel, p: Point2<f64>| {
            p.x > 2.0
                && p.y > 2.0
                && p.x < f64::from(m.width) - 3.0
                && p.y < f64::from(m.height) - 3.0
        };
        for (k, s_k) in boards.iter().enumerate() {
            for (c, cam) in devices
                .iter()
                .enumerate()
                .filter(|(_, d)| d.kind == DeviceKind::Camera)
            {
                for side in Side::BOTH {
                    let dev_side = cam.pose * s_k * board.side_transform(side);
                    // The side faces the device when the device centre lies on its +z side.
                    if (dev_side.inverse() * Point3::origin()).z <= 0.0 {
                        continue;
                    }
                    for circle in board.circles(side) {
                        let Some(e) =
                            ellipse_center(&cam.model, &dev_side, circle.center_2d, board.radius)
                        else {
                            continue;
                        };
                        if !inside(&cam.model, e) {
                            continue;
                        }
                        let obs = e + nalgebra::Vector2::new(
                            noise.sample(&mut rng),
                            noise.sample(&mut rng),
                        );
                        observations.push(Observation {
                            device: c,
                            pose: k,
                            side,
                            hex: circle.hex,
                            pixel: obs,
                            via: None,
                        });
                        // Projector observations: the projector pixel of the board point this
                        // camera sees at its observed ellipse centre.
                        let ray = cam.model.ray(obs).expect("inside the image");
                        let t = dev_side.inverse();
                        let (o, d) = (t * Point3::origin(), t * ray);
                        let x = o + d * (-o.z / d.z);
                        for (p, proj) in devices
                            .iter()
                            .enumerate()
                            .filter(|(_, d)| d.kind == DeviceKind::Projector)
                        {
                            let proj_side = proj.pose * s_k * board.side_transform(side);
                            if (proj_side.inverse() * Point3::origin()).z <= 0.0 {
                                continue;
                            }
                            let Some(u) = proj.model.project(&(proj_side * x)) else {
                                continue;
                            };
                            if inside(&proj.model, u) {
                                observations.push(Observation {
                                    device: p,
                                    pose: k,
                                    side,
                                    hex: circle.hex,
                                    pixel: u + nalgebra::Vector2::new(
                                        noise.sample(&mut rng),
                                        noise.sample(&mut rng),
                                    ),
                                    via: Some(Via {
                                        camera: c,
                                        ellipse_center: obs,
                                    }),
                                });
                            }
                        }
                    }
                }
            }
        }
        SyntheticRig {
            board,
            devices,
            boards,
            observations,
        }
    }
}
