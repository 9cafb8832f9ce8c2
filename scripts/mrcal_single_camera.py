#!/usr/bin/env python3
"""mrcal's optimiser on the observations of one camera, for the comparison with hexcal's
single-camera solve (issue 32 item 2; docs/design.md §8, "Observability").

Run by `cargo test --release -p hexcal-calib --lib calib::tests::opencv -- --ignored
--nocapture`, which writes the input and reads the output. By hand (Debian's python3 with
python3-mrcal and python3-opencv):

    /usr/bin/python3 scripts/mrcal_single_camera.py IN.json OUT.json

IN.json as scripts/opencv_single_camera.py reads it. mrcal's calibration object is a
rectangular grid, which a hexagonal lattice is not, so the problem is posed as mrcal's
structure-from-motion case: one camera (LENSMODEL_OPENCV5: k1, k2, p1, p2, k3, every term
estimated) at its own pose in each view, observing that view's board points as fixed
discrete points. Seeded by OpenCV's calibrateCamera; no regularisation and no outlier
rejection (Gaussian synthetic noise): mrcal's least-squares optimum on the same
observations. OUT.json: fx, fy, cx, cy, k1, k2, p1, p2, k3 and mrcal's RMS reprojection
error.
"""

import json
import sys

import cv2
import mrcal
import numpy as np


def main(src, dst):
    with open(src) as f:
        data = json.load(f)
    objects = [
        np.array([[x, y, 0.0] for x, y in v["board"]], np.float64) for v in data["views"]
    ]
    images = [np.array(v["image"], np.float64) for v in data["views"]]
    size = (data["width"], data["height"])
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    _, k, d, rvecs, tvecs = cv2.calibrateCamera(
        [o.astype(np.float32) for o in objects],
        [i.astype(np.float32) for i in images],
        size,
        None,
        None,
        criteria=criteria,
    )
    d = d.ravel()
    intrinsics = np.array(
        [[k[0, 0], k[1, 1], k[0, 2], k[1, 2], d[0], d[1], d[2], d[3], d[4]]], np.float64
    )
    # The camera's pose in view i maps that view's points (the reference frame of its own
    # fixed points) into the camera: rt_fromref = (r, t) of solvePnP.
    extrinsics = np.array(
        [np.concatenate([r.ravel(), t.ravel()]) for r, t in zip(rvecs, tvecs)], np.float64
    )
    points = np.concatenate(objects)
    observations = np.concatenate(
        [np.column_stack([i, np.ones(len(i))]) for i in images]
    ).astype(np.float64)
    first = np.cumsum([0] + [len(o) for o in objects])
    indices = np.array(
        [
            [first[v] + j, 0, v]
            for v in range(len(objects))
            for j in range(len(objects[v]))
        ],
        np.int32,
    )
    stats = mrcal.optimize(
        intrinsics,
        extrinsics,
        None,
        points,
        None,
        None,
        observations,
        indices,
        "LENSMODEL_OPENCV5",
        imagersizes=np.array([size], np.int32),
        Npoints_fixed=len(points),
        point_min_range=1.0,
        point_max_range=1e5,
        do_optimize_intrinsics_core=True,
        do_optimize_intrinsics_distortions=True,
        do_optimize_extrinsics=True,
        do_optimize_frames=False,
        do_apply_outlier_rejection=False,
        do_apply_regularization=False,
        verbose=False,
    )
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intrinsics[0]
    out = {
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        "k1": k1,
        "k2": k2,
        "p1": p1,
        "p2": p2,
        "k3": k3,
        "rms": float(stats["rms_reproj_error__pixels"]),
    }
    with open(dst, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
