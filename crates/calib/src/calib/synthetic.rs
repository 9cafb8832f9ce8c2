//! A synthetic paper-like rig with exact observations, for tests and benchmarks of the
//! calibration stage: cameras and projectors around a double-sided board, some facing each
//! other across it, board poses turned so both sides are seen.

use super::bundle::{Bend, Device, Observation, Problem, Solution, Via};
use super::circle::ellipse_center;
use hexcal_core::board::{Board, BoardCircle, Hex, Side};
use hexcal_core::camera::{CameraModel, Distortion, Intrinsics, LensParams};
use hexcal_core::observations::DeviceInfo;
use hexcal_core::observations::DeviceKind;
use hexcal_core::observations::{CameraView, Frame, ProjectorPixel, ViewPoint};
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

/// A random camera model drawn from `rng`: 1920 × 1200 px, f ≈ 2400 px, barrel distortion.
fn camera_model(rng: &mut StdRng) -> CameraModel {
    CameraModel {
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
    }
}

/// A random projector model drawn from `rng`: 1920 × 1080 px, f ≈ 2200 px, lens shift.
fn projector_model(rng: &mut StdRng) -> CameraModel {
    CameraModel {
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
    }
}

/// The devices of [`SyntheticRig::build`] (cameras at (azimuth, elevation) at 1500 mm, then
/// projectors at azimuths at 1300 mm, models drawn from `rng` in that order), with poses
/// relative to device 0; and T_ref_world.
fn place_devices(
    cameras: &[(f64, f64)],
    projectors: &[f64],
    rng: &mut StdRng,
) -> (Vec<Device>, Isometry3<f64>) {
    let target = Point3::origin();
    let mut world = Vec::new();
    let mut devices = Vec::new();
    for (i, &(az, el)) in cameras.iter().enumerate() {
        world.push(look_at(around(az, el, 1500.0), target));
        devices.push((format!("cam{i}"), DeviceKind::Camera, camera_model(rng)));
    }
    for (i, &az) in projectors.iter().enumerate() {
        world.push(look_at(around(az, 5.0, 1300.0), target));
        devices.push((
            format!("proj{i}"),
            DeviceKind::Projector,
            projector_model(rng),
        ));
    }
    let ref_from_world = world[0].inverse();
    let devices = devices
        .into_iter()
        .zip(&world)
        .map(|((name, kind, model), w)| Device {
            name,
            kind,
            model,
            pose: w.inverse() * world[0],
        })
        .collect();
    (devices, ref_from_world)
}

/// `poses` board poses T_ref_board, turned in yaw over ±35° and randomly tilted, rolled and
/// shifted (from `rng`).
fn board_poses(
    poses: usize,
    ref_from_world: &Isometry3<f64>,
    rng: &mut StdRng,
) -> Vec<Isometry3<f64>> {
    (0..poses)
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
        .collect()
}

/// Whether pixel `p` lies inside the image of `m`, clear of its border.
fn inside(m: &CameraModel, p: Point2<f64>) -> bool {
    p.x > 2.0 && p.y > 2.0 && p.x < f64::from(m.width) - 3.0 && p.y < f64::from(m.height) - 3.0
}

/// One side of board pose `pose` (T_ref_board `ref_board`) facing camera `camera`.
#[derive(Clone, Copy)]
struct Shot<'a> {
    pose: usize,
    ref_board: &'a Isometry3<f64>,
    camera: usize,
    side: Side,
}

/// What the noisy observations of a synthetic rig are made from.
struct Observer<'a> {
    board: &'a Board,
    bend: &'a Bend,
    devices: &'a [Device],
    /// Observation noise per coordinate (px).
    noise: Normal<f64>,
}

impl Observer<'_> {
    /// T_board_side of one circle's side, moved along the board's z by the bend there.
    fn face(&self, side: Side, hex: Hex) -> Isometry3<f64> {
        let p = self.board.point(side, hex);
        Translation3::new(0.0, 0.0, self.bend.displacement(p.x, p.y))
            * self.board.side_transform(side)
    }

    /// Every camera's noisy observation of every circle of every side facing it in each of
    /// the board poses `boards`, each followed by the projectors' (noise from `rng`).
    fn observations(&self, boards: &[Isometry3<f64>], rng: &mut StdRng) -> Vec<Observation> {
        let mut observations = Vec::new();
        for (k, s_k) in boards.iter().enumerate() {
            for (c, cam) in self
                .devices
                .iter()
                .enumerate()
                .filter(|(_, d)| d.kind == DeviceKind::Camera)
            {
                for side in Side::BOTH {
                    let dev_side = cam.pose * s_k * self.board.side_transform(side);
                    // The side faces the device when the device centre lies on its +z side.
                    if (dev_side.inverse() * Point3::origin()).z <= 0.0 {
                        continue;
                    }
                    let shot = Shot {
                        pose: k,
                        ref_board: s_k,
                        camera: c,
                        side,
                    };
                    for circle in self.board.circles(shot.side) {
                        self.observe_circle(shot, &circle, rng, &mut observations);
                    }
                }
            }
        }
        observations
    }

    /// The camera's noisy observation of `circle` in `shot`, when inside its image, and the
    /// projectors' of the board point it sees there, into `out`.
    fn observe_circle(
        &self,
        shot: Shot<'_>,
        circle: &BoardCircle,
        rng: &mut StdRng,
        out: &mut Vec<Observation>,
    ) {
        let cam = &self.devices[shot.camera];
        let dev_side = cam.pose * shot.ref_board * self.face(shot.side, circle.hex);
        let Some(e) = ellipse_center(&cam.model, &dev_side, circle.center_2d, self.board.radius)
        else {
            return;
        };
        if !inside(&cam.model, e) {
            return;
        }
        let obs = e + nalgebra::Vector2::new(self.noise.sample(rng), self.noise.sample(rng));
        out.push(Observation {
            device: shot.camera,
            pose: shot.pose,
            side: shot.side,
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
        self.observe_projectors(shot, circle.hex, obs, x, rng, out);
    }

    /// Every projector's noisy pixel of the board point `x` (side frame) of circle `hex`,
    /// which the camera of `shot` observed at `ellipse_center`, when inside its raster,
    /// into `out`.
    fn observe_projectors(
        &self,
        shot: Shot<'_>,
        hex: Hex,
        ellipse_center: Point2<f64>,
        x: Point3<f64>,
        rng: &mut StdRng,
        out: &mut Vec<Observation>,
    ) {
        for (p, proj) in self
            .devices
            .iter()
            .enumerate()
            .filter(|(_, d)| d.kind == DeviceKind::Projector)
        {
            let proj_side = proj.pose * shot.ref_board * self.face(shot.side, hex);
            if (proj_side.inverse() * Point3::origin()).z <= 0.0 {
                continue;
            }
            let Some(u) = proj.model.project(&(proj_side * x)) else {
                continue;
            };
            if inside(&proj.model, u) {
                out.push(Observation {
                    device: p,
                    pose: shot.pose,
                    side: shot.side,
                    hex,
                    pixel: u + nalgebra::Vector2::new(
                        self.noise.sample(rng),
                        self.noise.sample(rng),
                    ),
                    via: Some(Via {
                        camera: shot.camera,
                        ellipse_center,
                    }),
                });
            }
        }
    }
}

impl SyntheticRig {
    /// The paper-like rig: 6 cameras (3 facing the front, 3 the back), 3 projectors
    /// (2 front, 1 back), `poses` board poses; observation noise σ px on every coordinate
    /// of cameras and projectors alike.
    pub fn paper(poses: usize, sigma: f64, seed: u64) -> SyntheticRig {
        let cameras = [0.0, -35.0, 35.0, 180.0, 150.0, 210.0]
            .into_iter()
            .enumerate()
            .map(|(i, az)| (az, 12.0 * ((i % 3) as f64 - 1.0)))
            .collect::<Vec<_>>();
        Self::build(&cameras, &[15.0, -20.0, 170.0], poses, sigma, seed, None)
    }

    /// The paper-like rig with a bent board: every circle displaced along the board's z by
    /// the bend's w at its centre (the circle itself stays planar: a bend of a few mm over
    /// 300 mm tilts a 12 mm circle by < 0.1°).
    pub fn paper_bent(poses: usize, sigma: f64, seed: u64, bend: Vector3<f64>) -> SyntheticRig {
        let cameras = [0.0, -35.0, 35.0, 180.0, 150.0, 210.0]
            .into_iter()
            .enumerate()
            .map(|(i, az)| (az, 12.0 * ((i % 3) as f64 - 1.0)))
            .collect::<Vec<_>>();
        Self::build(
            &cameras,
            &[15.0, -20.0, 170.0],
            poses,
            sigma,
            seed,
            Some(bend),
        )
    }

    /// A large rig: `cameras` on a ring around the board, half facing each side (azimuths
    /// spread over ±50° around 0° and 180°, elevations over ±15°), `projectors` likewise,
    /// `poses` board poses; noise σ px.
    pub fn ring(
        cameras: usize,
        projectors: usize,
        poses: usize,
        sigma: f64,
        seed: u64,
    ) -> SyntheticRig {
        let spread = |i: usize, n: usize| {
            let half = n.div_ceil(2);
            let (k, base) = if i < half {
                (i, 0.0)
            } else {
                (i - half, 180.0)
            };
            let m = if i < half { half } else { n - half };
            base + if m > 1 {
                -50.0 + 100.0 * k as f64 / (m - 1) as f64
            } else {
                0.0
            }
        };
        let cams: Vec<(f64, f64)> = (0..cameras)
            .map(|i| (spread(i, cameras), 15.0 * ((i % 3) as f64 - 1.0)))
            .collect();
        let projs: Vec<f64> = (0..projectors)
            .map(|i| spread(i, projectors) + 7.0)
            .collect();
        Self::build(&cams, &projs, poses, sigma, seed, None)
    }

    /// A small rig whose board poses cover every device's whole image, corners included:
    /// cameras at azimuths 0° and 25° facing the front and 180° facing the back, one
    /// projector (principal point centred) at −15°; twelve board poses, a 3 × 3 grid of
    /// shifts (±330 mm across, ±210 mm up) with alternating yaw ±20° and pitch ∓15°, and
    /// three strongly turned poses at the centre. The cameras' k3 is `k3`; noise σ px.
    pub fn covered(sigma: f64, seed: u64, k3: f64) -> SyntheticRig {
        let mut rng = StdRng::seed_from_u64(seed);
        let board = Board::hex600();
        let bend = Bend::flat(&board);
        let cameras = [(0.0, 0.0), (25.0, -10.0), (180.0, 5.0)];
        let (mut devices, ref_from_world) = place_devices(&cameras, &[-15.0], &mut rng);
        devices[3].model.intrinsics.cy = 540.0 + rng.random_range(-10.0..10.0);
        for d in &mut devices[..3] {
            d.model.distortion.k3 = k3;
        }
        let mut world = Vec::new();
        for (i, y) in [-210.0, 0.0, 210.0].into_iter().enumerate() {
            for (j, x) in [-330.0, 0.0, 330.0].into_iter().enumerate() {
                let s = if (i + j) % 2 == 0 { 1.0 } else { -1.0 };
                world.push((x, y, 20f64 * s, -15f64 * s));
            }
        }
        world.extend([
            (0.0, 0.0, 35.0, 10.0),
            (0.0, 0.0, -35.0, -10.0),
            (0.0, 0.0, 0.0, 30.0),
        ]);
        let boards = world
            .into_iter()
            .map(|(x, y, yaw, pitch)| {
                let r = UnitQuaternion::from_euler_angles(
                    f64::to_radians(pitch),
                    f64::to_radians(yaw),
                    0.0,
                );
                ref_from_world * Isometry3::from_parts(Translation3::new(x, y, 0.0), r)
            })
            .collect::<Vec<_>>();
        Self::observed(board, &bend, devices, boards, sigma, &mut rng)
    }

    /// Every device on one side: `cameras` at azimuths over ±30° (elevations over ±15°),
    /// `projectors` over ±25° (+7°), `poses` board poses as `SyntheticRig::build`'s, every
    /// odd one turned over (180° about the board's y): each pose shows every device one
    /// side, the front in the even poses, the back in the odd ones, never both (issue 32).
    pub fn one_sided(
        cameras: usize,
        projectors: usize,
        poses: usize,
        sigma: f64,
        seed: u64,
    ) -> SyntheticRig {
        let spread = |i: usize, n: usize, half: f64| {
            if n > 1 {
                -half + 2.0 * half * i as f64 / (n - 1) as f64
            } else {
                0.0
            }
        };
        let cams: Vec<(f64, f64)> = (0..cameras)
            .map(|i| (spread(i, cameras, 30.0), 15.0 * ((i % 3) as f64 - 1.0)))
            .collect();
        let projs: Vec<f64> = (0..projectors)
            .map(|i| spread(i, projectors, 25.0) + 7.0)
            .collect();
        let mut rng = StdRng::seed_from_u64(seed);
        let board = Board::hex600();
        let (devices, ref_from_world) = place_devices(&cams, &projs, &mut rng);
        let over = Isometry3::rotation(Vector3::y() * std::f64::consts::PI);
        let boards = board_poses(poses, &ref_from_world, &mut rng)
            .into_iter()
            .enumerate()
            .map(|(k, b)| if k % 2 == 1 { b * over } else { b })
            .collect();
        let bend = Bend::flat(&board);
        Self::observed(board, &bend, devices, boards, sigma, &mut rng)
    }

    /// Keeps in every board pose `k` with `which(k)` one camera's observations only (and
    /// the projectors' found through it): of the cameras that see it, the (k mod their
    /// count)-th, so the single views go round the cameras.
    pub fn keep_one_camera(&mut self, which: impl Fn(usize) -> bool) {
        let mut seen = vec![std::collections::BTreeSet::new(); self.boards.len()];
        for ob in self.observations.iter().filter(|ob| ob.via.is_none()) {
            seen[ob.pose].insert(ob.device);
        }
        let keep: Vec<Option<usize>> = seen
            .iter()
            .enumerate()
            .map(|(k, s)| {
                (which(k) && !s.is_empty()).then(|| *s.iter().nth(k % s.len()).expect("k mod len"))
            })
            .collect();
        self.observations.retain(|ob| match keep[ob.pose] {
            Some(c) => ob.via.map_or(ob.device, |v| v.camera) == c,
            None => true,
        });
    }

    /// Keeps device `device`'s observations (and those found through it) in the first
    /// `poses` board poses it sees only: a weakly seen device.
    pub fn keep_device_in(&mut self, device: usize, poses: usize) {
        let mut seen = std::collections::BTreeSet::new();
        for ob in self.observations.iter().filter(|ob| ob.device == device) {
            seen.insert(ob.pose);
        }
        let kept: Vec<usize> = seen.into_iter().take(poses).collect();
        self.observations.retain(|ob| {
            let involves = ob.device == device || ob.via.is_some_and(|v| v.camera == device);
            !involves || kept.contains(&ob.pose)
        });
    }

    /// Cameras at (azimuth, elevation) in degrees at 1500 mm, projectors at azimuths at
    /// 1300 mm and 5° elevation, all looking at the origin.
    fn build(
        cameras: &[(f64, f64)],
        projectors: &[f64],
        poses: usize,
        sigma: f64,
        seed: u64,
        bend: Option<Vector3<f64>>,
    ) -> SyntheticRig {
        let mut rng = StdRng::seed_from_u64(seed);
        let board = Board::hex600();
        let bend = Bend {
            coefficients: bend.unwrap_or_default(),
            ..Bend::flat(&board)
        };
        let (devices, ref_from_world) = place_devices(cameras, projectors, &mut rng);
        let boards = board_poses(poses, &ref_from_world, &mut rng);
        Self::observed(board, &bend, devices, boards, sigma, &mut rng)
    }

    /// The rig of `devices` seeing `board` (bent by `bend`) in `boards`, each observation
    /// with noise σ px.
    fn observed(
        board: Board,
        bend: &Bend,
        devices: Vec<Device>,
        boards: Vec<Isometry3<f64>>,
        sigma: f64,
        rng: &mut StdRng,
    ) -> SyntheticRig {
        let observer = Observer {
            board: &board,
            bend,
            devices: &devices,
            noise: Normal::new(0.0, sigma.max(1e-300)).expect("finite σ"),
        };
        let observations = observer.observations(&boards, rng);
        SyntheticRig {
            board,
            devices,
            boards,
            observations,
        }
    }

    /// The observations as anchored camera views (one per camera, pose and side) with the
    /// projector pixels decoded at each circle, as the detection stages deliver them.
    pub fn views(&self) -> Vec<CameraView> {
        let mut views: Vec<CameraView> = Vec::new();
        for ob in &self.observations {
            match ob.via {
                None => {
                    let point = ViewPoint {
                        hex: ob.hex,
                        image: ob.pixel,
                        projectors: Vec::new(),
                    };
                    match views.last_mut() {
                        Some(v)
                            if v.camera == ob.device
                                && v.pose == ob.pose
                                && v.frame == Frame::Anchored(ob.side) =>
                        {
                            v.points.push(point)
                        }
                        _ => views.push(CameraView {
                            camera: ob.device,
                            pose: ob.pose,
                            frame: Frame::Anchored(ob.side),
                            points: vec![point],
                        }),
                    }
                }
                Some(via) => {
                    // Projector observations follow their camera observation.
                    let v = views.last_mut().expect("camera observation first");
                    let p = v.points.last_mut().expect("camera observation first");
                    assert!(v.camera == via.camera && p.hex == ob.hex);
                    p.projectors.push(ProjectorPixel {
                        projector: ob.device,
                        pixel: ob.pixel,
                    });
                }
            }
        }
        views
    }

    /// The devices as [`DeviceInfo`]s.
    pub fn device_infos(&self) -> Vec<DeviceInfo> {
        self.devices.iter().map(DeviceInfo::from).collect()
    }

    /// A start for the adjustment: every focal length off by up to ±5 % (fy = fx), no
    /// distortion, every non-reference device moved by (30, −20, 40) mm and turned by 5°,
    /// every board pose turned by 5° about a random axis.
    pub fn perturbed_start(&self, seed: u64) -> Problem {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut devices = self.devices.clone();
        let turn = |rng: &mut StdRng| {
            let axis = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            UnitQuaternion::from_scaled_axis(axis * 5f64.to_radians())
        };
        for (i, d) in devices.iter_mut().enumerate() {
            d.model.intrinsics.fx *= 1.0 + rng.random_range(-0.05..0.05);
            d.model.intrinsics.fy = d.model.intrinsics.fx;
            d.model.distortion = Distortion::default();
            if i != 0 {
                d.pose = Isometry3::from_parts(
                    Translation3::from(d.pose.translation.vector + Vector3::new(30.0, -20.0, 40.0)),
                    turn(&mut rng) * d.pose.rotation,
                );
            }
        }
        let boards = self
            .boards
            .iter()
            .map(|b| Isometry3::from_parts(b.translation, turn(&mut rng) * b.rotation))
            .collect();
        Problem {
            board: self.board.clone(),
            devices,
            boards,
            observations: self.observations.clone(),
        }
    }
}

/// Where a timed or checked adjustment starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Start {
    /// [`SyntheticRig::perturbed_start`]: the truth perturbed.
    Perturbed,
    /// As `hexcal calibrate` starts: Zhang per device and the pose graph, from the views.
    Real,
}

/// One synthetic rig: `cameras` / `projectors` / `poses`, noise `sigma`, `seed`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Case {
    /// Cameras.
    pub cameras: usize,
    /// Projectors.
    pub projectors: usize,
    /// Board poses.
    pub poses: usize,
    /// Observation noise per coordinate (px).
    pub sigma: f64,
    /// Seed of the rig and its noise.
    pub seed: u64,
    /// Where the adjustment starts.
    pub start: Start,
}

impl Case {
    /// The rig: the paper rig for 6 cameras and 3 projectors, else [`SyntheticRig::ring`].
    pub fn rig(&self) -> SyntheticRig {
        if self.cameras == 6 && self.projectors == 3 {
            SyntheticRig::paper(self.poses, self.sigma, self.seed)
        } else {
            SyntheticRig::ring(
                self.cameras,
                self.projectors,
                self.poses,
                self.sigma,
                self.seed,
            )
        }
    }
}

/// A rig of the observability grid (issue 32; docs/design.md §8, "Observability"): the
/// shapes whose parameters the data do not all determine.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// [`SyntheticRig::one_sided`]: every device on one side, the board turned over between
    /// poses (one camera and no projector: a single-camera calibration).
    OneSided {
        /// Cameras.
        cameras: usize,
        /// Projectors.
        projectors: usize,
        /// Board poses.
        poses: usize,
    },
    /// [`SyntheticRig::ring`] without projectors, every other pose seen by one camera only
    /// ([`SyntheticRig::keep_one_camera`]).
    SingleCameraPoses {
        /// Cameras.
        cameras: usize,
        /// Board poses.
        poses: usize,
    },
    /// [`SyntheticRig::one_sided`] with its last camera kept in 3 poses only
    /// ([`SyntheticRig::keep_device_in`]).
    FewPoses {
        /// Cameras.
        cameras: usize,
        /// Projectors.
        projectors: usize,
        /// Board poses.
        poses: usize,
    },
}

impl Shape {
    /// The rig of this shape with noise `sigma` from `seed`.
    pub fn rig(&self, sigma: f64, seed: u64) -> SyntheticRig {
        match *self {
            Shape::OneSided {
                cameras,
                projectors,
                poses,
            } => SyntheticRig::one_sided(cameras, projectors, poses, sigma, seed),
            Shape::SingleCameraPoses { cameras, poses } => {
                let mut rig = SyntheticRig::ring(cameras, 0, poses, sigma, seed);
                rig.keep_one_camera(|k| k % 2 == 1);
                rig
            }
            Shape::FewPoses {
                cameras,
                projectors,
                poses,
            } => {
                let mut rig = SyntheticRig::one_sided(cameras, projectors, poses, sigma, seed);
                rig.keep_device_in(cameras - 1, 3);
                rig
            }
        }
    }
}

/// Figures of one adjustment of a synthetic rig against its truth (`hexcal bench calib`,
/// the convergence grid).
#[derive(Clone, Debug)]
pub struct CaseResult {
    /// Devices in the rig.
    pub devices: usize,
    /// Devices left out by the real start (too few views, not linked).
    pub excluded: usize,
    /// Observations (camera and projector).
    pub observations: usize,
    /// Scalar residuals n and free parameters p of the final solve.
    pub dof: (usize, usize),
    /// LM iterations over every observation, all phases.
    pub iterations: usize,
    /// LM iterations of the coarse descent before them.
    pub coarse_iterations: usize,
    /// Whether both phases stopped at their minimum.
    pub converged: bool,
    /// Wall time of the adjustment (the real start: of the whole calibration) (s).
    pub seconds: f64,
    /// Posterior σ per coordinate (px); the simulated noise was the case's `sigma`.
    pub posterior_sigma: f64,
    /// Largest relative focal-length error over all devices.
    pub worst_focal_error: f64,
    /// Largest |error| / standard deviation over every free parameter, and its name.
    pub worst_z: (f64, String),
    /// The bound on |error|/σ for this many parameters: Bonferroni at 10⁻³ (4.6 for 200).
    pub z_bound: f64,
    /// What the data could not determine, held at its prior and not compared
    /// ([`Solution::held`]).
    pub held: Vec<super::observability::Unobserved>,
}

impl CaseResult {
    /// σ̂ within 2 % of the simulated σ and every parameter within `z_bound` of the truth.
    pub fn passes(&self, sigma: f64) -> bool {
        (self.posterior_sigma / sigma - 1.0).abs() <= 0.02 && self.worst_z.0 <= self.z_bound
    }
}

/// The smallest k (to 0.01) with m·P(|z| > k) ≤ 10⁻³ for standard normal z, by the Mills
/// bound P(|z| > k) ≤ 2φ(k)/k: 4.6 for m = 200, 5.0 for m = 1600.
pub fn bonferroni_bound(m: usize) -> f64 {
    let tail = |k: f64| 2.0 * (-k * k / 2.0).exp() / (k * (2.0 * std::f64::consts::PI).sqrt());
    let mut k = 3.0;
    while m as f64 * tail(k) > 1e-3 {
        k += 0.01;
    }
    k
}

/// Left increment (ω, τ) taking `b` to `a`: a = (exp ω, τ)·b, the solver's own pose
/// parameterisation.
fn increment(a: &Isometry3<f64>, b: &Isometry3<f64>) -> [f64; 6] {
    let delta = a * b.inverse();
    let (w, t) = (delta.rotation.scaled_axis(), delta.translation.vector);
    [w.x, w.y, w.z, t.x, t.y, t.z]
}

/// Largest |error|/σ over every free parameter of `sol` against the truth (`devices`,
/// `boards` indexed like the solution's), with its name, and the parameters compared.
pub fn worst_deviation(
    sol: &Solution,
    devices: &[&Device],
    boards: &[&Isometry3<f64>],
    front_back: &Isometry3<f64>,
) -> ((f64, String), usize) {
    let mut worst = (0.0f64, String::new());
    let mut count = 0;
    let mut check = |name: String, at: usize, value: f64| {
        let z = value.abs() / sol.covariance.variance(at).sqrt();
        count += 1;
        if z.is_nan() || z > worst.0 {
            worst = (z, name);
        }
    };
    let pose = |check: &mut dyn FnMut(String, usize, f64), name: &str, at, inc: [f64; 6]| {
        for (j, v) in inc.into_iter().enumerate() {
            check(format!("{name} pose[{j}]"), at + j, v);
        }
    };
    for (d, (est, truth)) in sol.devices.iter().zip(devices).enumerate() {
        let (lens_at, pose_at) = sol.index[d];
        let (a, b) = (est.model.lens_vector(), truth.model.lens_vector());
        for (j, q) in LensParams::for_model(&est.model).iter().enumerate() {
            check(
                format!("{} {q}", est.name),
                lens_at + j,
                a[q.index()] - b[q.index()],
            );
        }
        if let Some(at) = pose_at {
            pose(&mut check, &est.name, at, increment(&est.pose, &truth.pose));
        }
    }
    for (k, (est, truth)) in sol.boards.iter().zip(boards).enumerate() {
        let name = format!("board {k}");
        pose(&mut check, &name, sol.board_index[k], increment(est, truth));
    }
    if let (Some(at), Some(est)) = (sol.side_index, &sol.front_back) {
        let inc = increment(est, front_back);
        pose(&mut check, "front→back", at, inc);
    }
    (worst, count)
}

/// Build the case's rig, adjust it from the case's start and compare with the truth.
pub fn run_case(case: &Case) -> Result<CaseResult, super::CalibError> {
    run_rig(case.rig(), case.start, case.seed)
}

/// Adjust `rig` from `start` (the perturbed truth from `seed` + 1) and compare with the
/// truth: every estimated parameter, none held (docs/design.md §8, "Observability").
pub fn run_rig(
    mut rig: SyntheticRig,
    start: Start,
    seed: u64,
) -> Result<CaseResult, super::CalibError> {
    let observations = rig.observations.len();
    let t = std::time::Instant::now();
    let (sol, device_index, pose_index, excluded) = match start {
        Start::Perturbed => {
            // The start takes the observations over (millions on the largest rigs: never
            // two copies at once).
            let observations = std::mem::take(&mut rig.observations);
            let start = Problem {
                observations,
                ..rig.perturbed_start(seed + 1)
            };
            let sol = super::bundle::adjust(&start, &super::bundle::Options::default())?;
            let n = (rig.devices.len(), rig.boards.len());
            (sol, (0..n.0).collect(), (0..n.1).collect(), 0)
        }
        Start::Real => {
            // The views replace the observations: never both beside the solver's own.
            let views = rig.views();
            rig.observations = Vec::new();
            let cal = super::solve::calibrate(
                &rig.board,
                &rig.device_infos(),
                rig.boards.len(),
                &views,
                // The solver against the truth: the true model's every term estimated.
                &super::solve::CalibrateOptions {
                    select_lens: false,
                    ..Default::default()
                },
            )?;
            let excluded = cal.excluded.len();
            (cal.solution, cal.device_index, cal.pose_index, excluded)
        }
    };
    let seconds = t.elapsed().as_secs_f64();
    let devices: Vec<&Device> = device_index.iter().map(|&d| &rig.devices[d]).collect();
    let boards: Vec<&Isometry3<f64>> = pose_index.iter().map(|&k| &rig.boards[k]).collect();
    let (worst_z, m) = worst_deviation(
        &sol,
        &devices,
        &boards,
        &rig.board.side_transform(Side::Back),
    );
    let worst_focal_error = sol
        .devices
        .iter()
        .zip(&devices)
        .map(|(e, t)| (e.model.intrinsics.fx / t.model.intrinsics.fx - 1.0).abs())
        .fold(0.0, f64::max);
    Ok(CaseResult {
        devices: rig.devices.len(),
        excluded,
        observations,
        dof: sol.dof,
        iterations: sol.iterations,
        coarse_iterations: sol.coarse_iterations,
        converged: sol.converged,
        seconds,
        posterior_sigma: sol.sigma,
        worst_focal_error,
        worst_z,
        z_bound: bonferroni_bound(m),
        held: sol.held,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use hexcal_sim::truth::{fit_ellipse, outline, RIM_POINTS};

    /// Largest distance between the solver's ellipse centre (8 rim points, [`ellipse_center`])
    /// and an independent conic fitted to 256 rim points by the simulator's ground truth,
    /// over every `stride`-th camera observation of `rig` (at the true poses).
    fn worst_bias_model_error(rig: &SyntheticRig, stride: usize) -> f64 {
        let mut worst = 0.0f64;
        for ob in rig
            .observations
            .iter()
            .filter(|o| o.via.is_none())
            .step_by(stride)
        {
            let cam = &rig.devices[ob.device];
            let face = cam.pose * rig.boards[ob.pose] * rig.board.side_transform(ob.side);
            let c = rig.board.position(ob.hex);
            let solver = ellipse_center(&cam.model, &face, c, rig.board.radius).unwrap();
            let rim = outline(&cam.model, &face, c, rig.board.radius, RIM_POINTS).unwrap();
            let truth = fit_ellipse(&rim).unwrap().center;
            worst = worst.max((solver - truth).norm());
        }
        worst
    }

    #[test]
    fn the_bias_model_matches_an_independent_conic_on_every_test_geometry() {
        // The synthetic observations are made with the solver's own `ellipse_center`, so a
        // wrong bias model could not fail the calibration tests: check it against the
        // simulator's dense rim fit on the geometries those tests use (every paper and ring
        // rig the unit and integration tests build), far below the 0.1 px noise.
        // (poses, seed) of every paper rig a test builds (the bent board's devices and poses
        // are those of its seed), the NEES draws' seeds 100–129 included.
        let mut paper: Vec<(usize, u64)> = vec![
            (10, 7),
            (8, 21),
            (10, 51),
            (10, 61),
            (10, 41),
            (10, 2),
            (5, 3),
            (4, 9),
            (3, 5),
            (10, 3),
            (10, 71),
            (9, 41),
            (8, 17),
            (10, 11),
        ];
        paper.extend((31..36).map(|s| (10, s)));
        paper.extend((100..130).map(|s| (10, s)));
        let mut rigs: Vec<(String, SyntheticRig, usize)> = paper
            .into_iter()
            .map(|(poses, seed)| {
                let name = format!("paper {poses} poses, seed {seed}");
                (name, SyntheticRig::paper(poses, 0.0, seed), 13)
            })
            .collect();
        let mut rings = vec![
            (20, 4, 20, 1),
            (8, 4, 40, 1),
            (20, 4, 40, 1),
            (12, 0, 10, 3),
            (12, 0, 10, 1),
            (20, 4, 4, 1),
            (4, 0, 6, 7),
            (2, 2, 5, 11),
        ];
        rings.extend((50..53).map(|s| (8, 0, 10, s)));
        for (c, p, k, seed) in rings {
            let rig = SyntheticRig::ring(c, p, k, 0.0, seed);
            rigs.push((format!("ring {c}/{p}/{k} seed {seed}"), rig, 29));
        }
        for (name, rig, stride) in &rigs {
            let worst = worst_bias_model_error(rig, *stride);
            eprintln!("{name}: largest difference {worst:.2e} px");
            assert!(worst < 1e-3, "{name}: {worst} px");
        }
    }
}
