#!/usr/bin/env python3
"""OpenCV's calibrateCamera on the observations of one camera, for the comparison with
hexcal's single-camera solve (issue 32 item 2; docs/design.md §8, "Observability").

Run by `cargo test --release -p hexcal-calib --lib calib::tests::opencv -- --ignored
--nocapture`, which writes the input and reads the output. By hand:

    /usr/bin/python3 scripts/opencv_single_camera.py IN.json OUT.json

IN.json: {"width": W, "height": H, "views": [{"board": [[x, y], ...], "image": [[u, v],
...]}, ...]}, board points in each view's own side plane (mm, z = 0), image points the
observed pixels (ellipse centres), in OpenCV's pixel convention (hexcal's). OUT.json: the
camera matrix's fx, fy, cx, cy and the distortion k1, k2, p1, p2, k3 (OpenCV's default
five-term model, every term estimated), and OpenCV's RMS reprojection error.
"""

import json
import sys

import cv2
import numpy as np


def calibrate(src):
    """OpenCV's calibrateCamera on IN.json `src` (in float32, as OpenCV takes them): each
    view's board points (z = 0) and image points as read (float64), the image size, and
    OpenCV's (rms, camera matrix, distortion, rvecs, tvecs)."""
    with open(src) as f:
        data = json.load(f)
    objects = [
        np.array([[x, y, 0.0] for x, y in v["board"]], np.float64) for v in data["views"]
    ]
    images = [np.array(v["image"], np.float64) for v in data["views"]]
    size = (data["width"], data["height"])
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    found = cv2.calibrateCamera(
        [o.astype(np.float32) for o in objects],
        [i.astype(np.float32) for i in images],
        size,
        None,
        None,
        criteria=criteria,
    )
    return objects, images, size, found


def write(dst, values, rms):
    """OUT.json: the nine model values (fx, fy, cx, cy, k1, k2, p1, p2, k3) and the RMS."""
    keys = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
    out = {key: float(v) for key, v in zip(keys, values)}
    out["rms"] = float(rms)
    with open(dst, "w") as f:
        json.dump(out, f)


def main(src, dst):
    _, _, _, (rms, k, d, _, _) = calibrate(src)
    d = d.ravel()
    write(dst, [k[0, 0], k[1, 1], k[0, 2], k[1, 2], *d[:5]], rms)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
