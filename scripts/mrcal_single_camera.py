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

import os
import sys

import mrcal
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from opencv_single_camera import calibrate, write  # noqa: E402


def main(src, dst):
    objects, images, size, (_, k, d, rvecs, tvecs) = calibrate(src)
    d = d.ravel()
    intrinsics = np.array(
        [[k[0, 0], k[1, 1], k[0, 2], k[1, 2], d[0], d[1], d[2], d[3], d[4]]], np.float64
    )
    # The camera's pose in view i maps that view's points (the reference frame of its own
    # fixed points) into the camera: rt_fromref = (r, t) of calibrateCamera's view i.
    extrinsics = np.array(
        [np.concatenate([r.ravel(), t.ravel()]) for r, t in zip(rvecs, tvecs)], np.float64
    )
    points = np.concatenate(objects)
    observations = np.concatenate([np.column_stack([i, np.ones(len(i))]) for i in images])
    first = np.cumsum([0] + [len(o) for o in objects])
    indices = np.array(
        [[first[v] + j, 0, v] for v in range(len(objects)) for j in range(len(objects[v]))],
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
    write(dst, intrinsics[0], stats["rms_reproj_error__pixels"])


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
