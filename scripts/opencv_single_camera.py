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


def main(src, dst):
    with open(src) as f:
        data = json.load(f)
    objects = [
        np.array([[x, y, 0.0] for x, y in v["board"]], np.float32) for v in data["views"]
    ]
    images = [np.array(v["image"], np.float32) for v in data["views"]]
    size = (data["width"], data["height"])
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, k, d, _, _ = cv2.calibrateCamera(objects, images, size, None, None, criteria=criteria)
    d = d.ravel()
    out = {
        "fx": k[0, 0],
        "fy": k[1, 1],
        "cx": k[0, 2],
        "cy": k[1, 2],
        "k1": d[0],
        "k2": d[1],
        "p1": d[2],
        "p2": d[3],
        "k3": d[4],
        "rms": rms,
    }
    with open(dst, "w") as f:
        json.dump({key: float(v) for key, v in out.items()}, f)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
