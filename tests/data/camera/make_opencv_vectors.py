#!/usr/bin/env python3
"""Reference vectors for hexcal's camera model, computed by OpenCV.

    pip install opencv-python-headless numpy
    python3 tests/data/camera/make_opencv_vectors.py

Writes opencv_vectors.json beside this script (read by crates/core/src/camera/tests.rs, which needs no
Python). For each camera (5-coefficient, 8-coefficient rational, strong barrel k1 = -0.3,
projector-like with the principal point below the image):
  - "views": object points with rvec/tvec and the pixels cv2.projectPoints gives, ~20 per
    view spread over the whole image up to a few pixels from the corners; for the first
    points of each view also projectPoints' Jacobian with respect to tvec, (fx, fy, cx, cy)
    and the distortion coefficients;
  - "undistort": pixels on a grid through the image corners and the normalised points
    cv2.undistortPoints gives with tight termination criteria, checked here by
    re-projection.
Numbers are written with repr (shortest round-trip), i.e. full double precision.
"""

import json
import pathlib

import cv2
import numpy as np

SEED = 20240611
POINTS_PER_VIEW = 20
JACOBIAN_POINTS_PER_VIEW = 5
# cv2.undistortPoints: fixed-point iteration until the re-projection error (px) is below EPS.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10000, 1e-14)

CAMERAS = [
    {
        "name": "standard5",
        "width": 1920,
        "height": 1200,
        "f": (1500.0, 1502.5),
        "c": (955.3, 604.7),
        "dist": [-0.12, 0.05, 0.0008, -0.0005, -0.01],
    },
    {
        "name": "rational8",
        "width": 2448,
        "height": 2048,
        "f": (2400.0, 2395.0),
        "c": (1230.4, 1019.8),
        "dist": [0.8, -0.2, 0.0004, -0.0006, 0.05, 0.95, 0.1, 0.02],
    },
    {
        "name": "strong_barrel",
        "width": 1280,
        "height": 1024,
        "f": (900.0, 899.0),
        "c": (641.2, 509.6),
        "dist": [-0.3, 0.1, 0.001, -0.002, -0.01],
    },
    {
        "name": "projector_shifted",
        "width": 1920,
        "height": 1080,
        "f": (2200.0, 2210.0),
        "c": (962.0, 1150.0),
        "dist": [0.03, -0.06, -0.0004, 0.0003, 0.02],
    },
]


def camera_matrix(cam):
    (fx, fy), (cx, cy) = cam["f"], cam["c"]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def undistort(cam, pixels):
    """Normalised undistorted points of pixels (N×2) by cv2.undistortPoints."""
    src = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    out = cv2.undistortPoints(
        src, camera_matrix(cam), np.array(cam["dist"]), criteria=UNDISTORT_CRITERIA
    )
    return out.reshape(-1, 2)


def project(cam, points, rvec, tvec):
    """Pixels (N×2) and the 2N×(10+ndist) Jacobian from cv2.projectPoints."""
    px, jac = cv2.projectPoints(
        np.asarray(points, dtype=np.float64).reshape(-1, 1, 3),
        np.asarray(rvec, dtype=np.float64),
        np.asarray(tvec, dtype=np.float64),
        camera_matrix(cam),
        np.array(cam["dist"]),
    )
    return px.reshape(-1, 2), jac


def reprojection_error(cam, pixels, normalised):
    """Largest pixel distance between pixels and the re-projected normalised points."""
    rays = np.hstack([normalised, np.ones((len(normalised), 1))])
    back, _ = project(cam, rays, np.zeros(3), np.zeros(3))
    return float(np.max(np.linalg.norm(back - np.asarray(pixels), axis=1)))


def target_pixels(cam, rng):
    """~20 pixels spread over the image: a 5×4 grid reaching 2–4 px from the borders."""
    w, h = cam["width"], cam["height"]
    us = np.linspace(0.0, w - 1.0, 5)
    vs = np.linspace(0.0, h - 1.0, 4)
    grid = np.array([(u, v) for v in vs for u in us])
    inward = np.sign(np.array([w - 1.0, h - 1.0]) / 2.0 - grid)
    return grid + inward * rng.uniform(2.0, 4.0, grid.shape)


def make_view(cam, rng):
    angle = rng.uniform(0.2, 1.2)
    axis = rng.normal(size=3)
    rvec = axis / np.linalg.norm(axis) * angle
    tvec = np.array([rng.uniform(-150, 150), rng.uniform(-150, 150), rng.uniform(800, 2000)])
    pixels = target_pixels(cam, rng)
    n = undistort(cam, pixels)
    depth = rng.uniform(400.0, 3000.0, len(n))
    x_cam = np.hstack([n, np.ones((len(n), 1))]) * depth[:, None]
    r, _ = cv2.Rodrigues(rvec)
    x_obj = (x_cam - tvec) @ r  # Rᵀ (X_cam − t), row-wise
    projected, jac = project(cam, x_obj, rvec, tvec)
    nd = len(cam["dist"])
    # projectPoints' Jacobian columns: rvec (3), tvec (3), fx, fy, cx, cy (4), dist (nd).
    jacobians = []
    for i in range(JACOBIAN_POINTS_PER_VIEW):
        rows = jac[2 * i : 2 * i + 2]
        jacobians.append(
            {
                "d_tvec": rows[:, 3:6].tolist(),
                "d_intrinsics": rows[:, 6:10].tolist(),
                "d_dist": rows[:, 10 : 10 + nd].tolist(),
            }
        )
    return {
        "rvec": rvec.tolist(),
        "tvec": tvec.tolist(),
        "points": x_obj.tolist(),
        "pixels": projected.tolist(),
        "jacobians": jacobians,
    }


def make_undistort(cam):
    w, h = cam["width"], cam["height"]
    pixels = np.array(
        [(u, v) for v in np.linspace(0.0, h - 1.0, 5) for u in np.linspace(0.0, w - 1.0, 6)]
    )
    n = undistort(cam, pixels)
    err = reprojection_error(cam, pixels, n)
    assert err < 1e-9, f"{cam['name']}: cv2.undistortPoints did not converge ({err} px)"
    return {"pixels": pixels.tolist(), "normalised": n.tolist(), "reprojection_error_px": err}


def main():
    rng = np.random.default_rng(SEED)
    cameras = []
    for cam in CAMERAS:
        cameras.append(
            {
                "name": cam["name"],
                "width": cam["width"],
                "height": cam["height"],
                "K": camera_matrix(cam).tolist(),
                "dist": cam["dist"],
                "views": [make_view(cam, rng) for _ in range(3)],
                "undistort": make_undistort(cam),
            }
        )
    out = {
        "generator": "make_opencv_vectors.py",
        "opencv_version": cv2.__version__,
        "numpy_version": np.__version__,
        "seed": SEED,
        "cameras": cameras,
    }
    path = pathlib.Path(__file__).with_name("opencv_vectors.json")
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path} ({path.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
