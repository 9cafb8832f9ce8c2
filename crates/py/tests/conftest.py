"""A simulated rig for the tests, projected with OpenCV (independent of hexcal's camera
model): two cameras and a projector, six poses of the built-in board hex600 (front side),
the last held out. Correspondences in the layout of the correspondences file."""

import pathlib

import cv2
import numpy as np
import pytest

import hexcal

REPO = pathlib.Path(__file__).resolve().parents[3]
SAMPLES = REPO / "tests" / "data" / "samples"


def lattice():
    """hex600's front circles: (q, r) and (x, y) in mm (docs/design.md §3)."""
    out = []
    for r in range(-14, 15):
        for q in range(-40, 41):
            x, y = 20.0 * (q + 0.5 * r), 20.0 * np.sqrt(0.75) * r
            if abs(x) <= 290 + 1e-9 and abs(y) <= 230 + 1e-9:
                out.append((q, r, x, y))
    return out


def look_at(centre, target):
    """T_device_ref (rvec, tvec) of a device at `centre` looking at `target` (y down)."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    return cv2.Rodrigues(r)[0].ravel(), -r @ centre


class Rig:
    def __init__(self, seed=7, noise=0.05):
        rng = np.random.default_rng(seed)
        target = [0.0, 0.0, 1200.0]
        self.devices = [
            dict(name="cam0", kind="camera", width=1280, height=1024,
                 K=[[1100.0, 0, 641.5], [0, 1102.0, 509.0], [0, 0, 1]],
                 D=[-0.12, 0.06, 0.0004, -0.0003, 0.0],
                 pose=(np.zeros(3), np.zeros(3))),
            dict(name="cam1", kind="camera", width=1280, height=1024,
                 K=[[1150.0, 0, 635.0], [0, 1149.0, 515.5], [0, 0, 1]],
                 D=[-0.09, 0.03, -0.0002, 0.0005, 0.0],
                 pose=look_at(np.array([420.0, -30.0, 60.0]), target)),
            dict(name="proj0", kind="projector", width=1280, height=800,
                 K=[[1500.0, 0, 640.0], [0, 1500.0, 700.0], [0, 0, 1]],
                 D=[0.0, 0.0, 0.0, 0.0, 0.0],
                 pose=look_at(np.array([-350.0, -120.0, 30.0]), target)),
        ]
        self.points = lattice()
        board = np.array([[x, y, 0.0] for _, _, x, y in self.points])
        self.poses = []
        flip = cv2.Rodrigues(np.array([np.pi, 0.0, 0.0]))[0]  # front faces the rig
        for k in range(6):
            tilt = cv2.Rodrigues(rng.uniform(-0.45, 0.45, 3) * [1, 1, 0.3])[0]
            r = tilt @ flip
            t = np.array([rng.uniform(-60, 60), rng.uniform(-60, 60), 1200 + rng.uniform(-150, 150)])
            self.poses.append((r, t))
        # Each device's pixels of every board point in every pose (NaN outside its image).
        self.pixels = []
        for d in self.devices:
            per = []
            rvec, tvec = d["pose"]
            for r, t in self.poses:
                ref = board @ r.T + t
                px, _ = cv2.projectPoints(ref, rvec, tvec, np.array(d["K"]), np.array(d["D"]))
                px = px.reshape(-1, 2) + rng.normal(0, noise, (len(board), 2))
                dev = ref @ cv2.Rodrigues(rvec)[0].T + tvec
                inside = (px[:, 0] > 5) & (px[:, 1] > 5) & (px[:, 0] < d["width"] - 6) & (
                    px[:, 1] < d["height"] - 6) & (dev[:, 2] > 0)
                px[~inside] = np.nan
                per.append(px)
            self.pixels.append(per)
        self.board = board

    def truth_points(self, pose):
        """The board points of a pose in the reference (cam0) frame (mm)."""
        r, t = self.poses[pose]
        return self.board @ r.T + t

    def correspondences(self, poses):
        views = []
        for new, k in enumerate(poses):
            for c in (0, 1):
                pts = []
                for i, (q, r, _, _) in enumerate(self.points):
                    px = self.pixels[c][k][i]
                    if np.isnan(px[0]):
                        continue
                    pp = self.pixels[2][k][i]
                    projectors = [] if np.isnan(pp[0]) else [
                        {"projector": 2, "pixel": [float(pp[0]), float(pp[1])]}]
                    pts.append({"hex": {"q": q, "r": r}, "image": [float(px[0]), float(px[1])],
                                "projectors": projectors})
                views.append({"camera": c, "pose": new, "frame": {"anchored": "front"},
                              "points": pts})
        return {
            "board": "hex600",
            "devices": [{k: d[k] for k in ("name", "kind", "width", "height")}
                        for d in self.devices],
            "poses": len(poses),
            "views": views,
        }


@pytest.fixture(scope="session")
def rig():
    return Rig()


@pytest.fixture(scope="session")
def calibrated(rig, tmp_path_factory):
    """The rig calibrated from poses 0–4 (pose 5 held out), saved and loaded back."""
    cal = hexcal.calibrate(rig.correspondences(range(5)))
    path = tmp_path_factory.mktemp("cal") / "calibration.json"
    cal.save(path)
    return hexcal.load(path)
