"""Load hexcal's exports in the neighbouring tools' own readers (or, where the tool is not
on this machine, in a reader written here from the format's documentation) and compare
their projections with hexcal's.

Usage: check_exports.py FORMAT CALIBRATION_DIR REFERENCE.json
FORMAT is mrcal, colmap, ros, stereo or kalibr. REFERENCE.json (written by
tests/exports.rs) holds, per device, points in the reference device's frame, the same
points in the device's frame, and hexcal's projections of them (pixel (0, 0) at the centre
of the top-left pixel). Prints one line of figures per device; exits non-zero (assertion)
when a bound is broken.
"""

import json
import re
import sys

import numpy as np


def devices(ref):
    return ref["devices"]


def check_mrcal(out, ref):
    import mrcal

    for d in devices(ref):
        model = mrcal.cameramodel(f"{out}/mrcal/{d['name']}.cameramodel")
        lensmodel, intrinsics = model.intrinsics()
        assert tuple(model.imagersize()) == (d["width"], d["height"]), model.imagersize()
        rt = model.extrinsics_rt_fromref()
        p_cam = mrcal.transform_point_rt(rt, np.array(d["points_ref"]))
        q = mrcal.project(p_cam, lensmodel, intrinsics)
        err = np.abs(q - np.array(d["pixels"])).max()
        # mrcal projects OpenCV models with OpenCV's equations in double precision: the
        # two agree to rounding (pixels ~1e3, so ~1e-12); 1e-6 px is the bound.
        assert err < 1e-6, (d["name"], err)
        region = model.valid_intrinsics_region()
        # On this rig every device's centre is well determined, so every model has one.
        assert region is not None, d["name"]
        if region is not None:
            # A closed polygon around the principal point (ray casting: odd crossings).
            assert region.ndim == 2 and region.shape[1] == 2 and (region[0] == region[-1]).all()
            cx, cy = intrinsics[2], intrinsics[3]
            a, b = region[:-1], region[1:]
            straddle = (a[:, 1] > cy) != (b[:, 1] > cy)
            with np.errstate(divide="ignore", invalid="ignore"):
                x = a[:, 0] + (cy - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
            assert (straddle & (x > cx)).sum() % 2 == 1, (d["name"], region)
        regions = "none" if region is None else f"{len(region) - 1} vertices"
        text = open(f"{out}/mrcal/{d['name']}.cameramodel").read()
        if d["kind"] == "projector":
            assert "projector" in text, d["name"]
        print(f"mrcal {d['name']} {lensmodel} max projection difference {err:.3e} px, valid region {regions}")


def colmap_rows(path):
    rows = []
    with open(path) as f:
        lines = f.read().split("\n")
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        rows.append((line.split(), lines[i] if i < len(lines) else ""))
        i += 1
    return rows


def colmap_project(model, params, x):
    """COLMAP's OPENCV / FULL_OPENCV projection (colmap/sensor/models.h) of camera-frame x."""
    u, v = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2 = params[:8]
    k3 = k4 = k5 = k6 = 0.0
    if model == "FULL_OPENCV":
        k3, k4, k5, k6 = params[8:12]
    else:
        assert model == "OPENCV", model
    r2 = u * u + v * v
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    du = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    dv = v * radial + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
    return np.stack([fx * du + cx, fy * dv + cy], axis=1)


def quat_to_r(qw, qx, qy, qz):
    return np.array(
        [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
            [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
            [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)],
        ]
    )


def check_colmap(out, ref):
    cameras = {}
    with open(f"{out}/colmap/cameras.txt") as f:
        for line in f:
            if line.strip() and not line.startswith("#"):
                fields = line.split()
                cameras[int(fields[0])] = (
                    fields[1],
                    int(fields[2]),
                    int(fields[3]),
                    [float(x) for x in fields[4:]],
                )
    images = {}
    for fields, points in colmap_rows(f"{out}/colmap/images.txt"):
        assert points.strip() == "", points
        q = [float(x) for x in fields[1:5]]
        t = np.array([float(x) for x in fields[5:8]])
        images[fields[9]] = (quat_to_r(*q), t, int(fields[8]))
    header = open(f"{out}/colmap/images.txt").read()
    for d in devices(ref):
        r, t, cam = images[d["name"]]
        model, w, h, params = cameras[cam]
        assert (w, h) == (d["width"], d["height"])
        x = np.array(d["points_ref"]) @ r.T + t
        # COLMAP's pixel (0, 0) is the top-left pixel's corner: hexcal's pixel + 0.5.
        q = colmap_project(model, params, x) - 0.5
        err = np.abs(q - np.array(d["pixels"])).max()
        assert err < 1e-6, (d["name"], err)
        if d["kind"] == "projector":
            assert f"# {d['name']} is a projector" in header, d["name"]
        print(f"colmap {d['name']} {model} max projection difference {err:.3e} px")


def check_ros(out, ref):
    import cv2
    import yaml

    for d in devices(ref):
        info = yaml.safe_load(open(f"{out}/ros/{d['name']}.yaml"))
        assert info["camera_name"] == d["name"]
        assert (info["image_width"], info["image_height"]) == (d["width"], d["height"])
        k = np.array(info["camera_matrix"]["data"]).reshape(3, 3)
        assert (info["camera_matrix"]["rows"], info["camera_matrix"]["cols"]) == (3, 3)
        dist = np.array(info["distortion_coefficients"]["data"])
        expected = {5: "plumb_bob", 8: "rational_polynomial"}[len(dist)]
        assert info["distortion_model"] == expected, info["distortion_model"]
        r = np.array(info["rectification_matrix"]["data"]).reshape(3, 3)
        assert np.array_equal(r, np.eye(3)), r
        p = np.array(info["projection_matrix"]["data"]).reshape(3, 4)
        assert np.array_equal(p[:, :3], k) and np.array_equal(p[:, 3], np.zeros(3)), p
        x = np.array(d["points_dev"])
        q, _ = cv2.projectPoints(x, np.zeros(3), np.zeros(3), k, dist)
        err = np.abs(q.reshape(-1, 2) - np.array(d["pixels"])).max()
        assert err < 1e-6, (d["name"], err)
        print(f"ros {d['name']} {expected} max projection difference {err:.3e} px")


def check_stereo(out, ref, pair):
    import cv2

    first, second = pair.split(",")
    fs = cv2.FileStorage(f"{out}/stereo/{first}-{second}.yml", cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    node = lambda n: fs.getNode(n).mat()  # noqa: E731
    size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    k1, d1, k2, d2 = node("K1"), node("D1"), node("K2"), node("D2")
    r, t = node("R"), node("T")
    # R, T against the devices' poses in the reference file: X2 = R·X1 + T.
    by_name = {d["name"]: d for d in devices(ref)}
    a, b = by_name[first], by_name[second]
    ra, _ = cv2.Rodrigues(np.array(a["rvec"]))
    rb, _ = cv2.Rodrigues(np.array(b["rvec"]))
    r_true = rb @ ra.T
    t_true = np.array(b["tvec"]) - r_true @ np.array(a["tvec"])
    assert np.abs(r - r_true).max() < 1e-12, r - r_true
    assert np.abs(t.ravel() - t_true).max() < 1e-9, t.ravel() - t_true
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(k1, d1, k2, d2, size, r, t)
    for name, mine, cv in [("R1", node("R1"), r1), ("R2", node("R2"), r2)]:
        assert np.abs(mine - cv).max() < 1e-12, (name, mine - cv)
    # The principal points come from the image corners' rays: OpenCV undistorts them in
    # float32 with 5 fixed-point iterations, hexcal to convergence. Bound: the focal length
    # times the largest difference between OpenCV's corner undistortion and a converged one,
    # plus float32 rounding of normalised coordinates (|n| < 1: 6e-8 · f · 8).
    corners = np.array([[0, 0], [size[0] - 1, 0], [0, size[1] - 1], [size[0] - 1, size[1] - 1]], np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    gap = 0.0
    for k, dist in [(k1, d1), (k2, d2)]:
        c = corners.reshape(-1, 1, 2).astype(np.float64)
        five = cv2.undistortPoints(corners.reshape(-1, 1, 2), k, dist)
        full = cv2.undistortPointsIter(c, k, dist, None, None, crit)
        gap = max(gap, np.abs(five - full).max())
    fc = p1[0, 0]
    tol = fc * (gap + 8 * 6e-8)
    mine_p1, mine_p2, mine_q = node("P1"), node("P2"), node("Q")
    assert abs(mine_p1[0, 0] - fc) < 1e-9 * fc and abs(mine_p2[1, 1] - p2[1, 1]) < 1e-9 * fc
    for name, mine, cv in [("P1", mine_p1, p1), ("P2", mine_p2, p2)]:
        assert np.abs(mine[:, :2] - cv[:, :2]).max() < 1e-9 * fc, (name, mine - cv)
        assert np.abs(mine[:, 2] - cv[:, 2]).max() < tol, (name, mine - cv, tol)
        assert np.abs(mine[:, 3] - cv[:, 3]).max() <= 1e-9 * abs(cv[:, 3]).max(), (name, mine - cv)
    assert np.abs(mine_q[:, 3] - q[:, 3]).max() < tol, (mine_q - q, tol)
    assert np.abs(mine_q[:, :3] - q[:, :3]).max() < 1e-12, mine_q - q
    cc = max(np.abs(mine_p1[:, 2] - p1[:, 2]).max(), np.abs(mine_p2[:, 2] - p2[:, 2]).max())
    print(f"stereo {pair}: R1, R2 equal; principal points differ by {cc:.2e} px (bound {tol:.2e})")


def check_kalibr(out, ref):
    import cv2
    import yaml

    text = open(f"{out}/camchain.yaml").read()
    chain = yaml.safe_load(text)
    recorded = {
        m.group(1): float(m.group(2))
        for m in re.finditer(r"radtan refit of (\S+) .*largest deviation ([0-9.]+) px", text)
    }
    n = len(devices(ref))
    assert sorted(chain) == sorted(f"cam{i}" for i in range(n)), list(chain)
    t_prev = None
    for i, d in enumerate(devices(ref)):
        cam = chain[f"cam{i}"]
        # What Kalibr's CameraChainParameters reads for a pinhole-radtan camera.
        assert cam["camera_model"] == "pinhole" and len(cam["intrinsics"]) == 4
        assert cam["distortion_model"] == "radtan" and len(cam["distortion_coeffs"]) == 4
        assert cam["resolution"] == [d["width"], d["height"]]
        overlaps = cam["cam_overlaps"]
        assert all(isinstance(j, int) and 0 <= j < n and j != i for j in overlaps), overlaps
        assert all(i in chain[f"cam{j}"]["cam_overlaps"] for j in overlaps), (i, overlaps)
        rd, _ = cv2.Rodrigues(np.array(d["rvec"]))
        t_dev = np.eye(4)
        t_dev[:3, :3], t_dev[:3, 3] = rd, np.array(d["tvec"]) * 1e-3
        if i > 0:
            t = np.array(cam["T_cn_cnm1"])
            assert np.abs(t @ t_prev - t_dev).max() < 1e-9, (i, t @ t_prev - t_dev)
        t_prev = t_dev
        fx, fy, cx, cy = cam["intrinsics"]
        k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        x = np.array(d["points_dev"])
        q, _ = cv2.projectPoints(x, np.zeros(3), np.zeros(3), k, np.array(cam["distortion_coeffs"]))
        err = np.linalg.norm(q.reshape(-1, 2) - np.array(d["pixels"]), axis=1).max()
        bound = recorded.get(d["name"], 0.0)
        # The test's points are nodes of the refit's grid (corners included), where the
        # recorded figure is the largest deviation; the rest is rounding.
        assert err <= bound + 1e-4, (d["name"], err, bound)
        print(f"kalibr {d['name']} overlaps {overlaps} radtan deviation {err:.4f} px (recorded {bound:.4f})")


def main():
    fmt, out, ref_path = sys.argv[1:4]
    ref = json.load(open(ref_path))
    if fmt == "stereo":
        check_stereo(out, ref, sys.argv[4])
    else:
        {"mrcal": check_mrcal, "colmap": check_colmap, "ros": check_ros, "kalibr": check_kalibr}[fmt](out, ref)


main()
