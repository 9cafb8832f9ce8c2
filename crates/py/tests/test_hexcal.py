"""The hexcal Python package against OpenCV, the simulated rig's truth, the repository's
sample images and a simulated phase-shift stack (crates/py/tests/conftest.py)."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

import hexcal
from conftest import REPO, SAMPLES


def test_calibrate_recovers_the_rig(rig, calibrated):
    assert calibrated.names == ["cam0", "cam1", "proj0"]
    assert calibrated.reference == "cam0"
    for truth in rig.devices:
        d = calibrated[truth["name"]]
        assert d.kind == truth["kind"]
        assert abs(d.intrinsics["fx"] / truth["K"][0][0] - 1) < 1e-3
        assert np.allclose(d.tvec, truth["pose"][1], atol=1.0)
        assert d.pose.shape == (4, 4)
        assert np.allclose(d.pose[:3, 3], d.tvec)
        assert np.allclose(d.pose[:3, :3], cv2.Rodrigues(d.rvec)[0])
        cov = d.lens_covariance
        assert cov.shape == (len(d.lens_params),) * 2
        assert np.allclose(np.sqrt(np.diag(cov)), d.lens_std)


def test_load_gives_what_was_saved(calibrated, tmp_path):
    path = tmp_path / "again.json"
    calibrated.save(path)
    again = hexcal.load(str(path))
    assert again.to_json() == calibrated.to_json()
    assert "cam1" in again and "nope" not in again and len(again) == 3


def test_project_equals_opencv_through_the_export(rig, calibrated, tmp_path):
    pts = rig.truth_points(5)
    for d in calibrated.devices:
        path = tmp_path / f"{d.name}.yml"
        path.write_text(d.opencv_yaml())
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        k, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
        r, t = fs.getNode("R").mat(), fs.getNode("T").mat()
        want, _ = cv2.projectPoints(pts, cv2.Rodrigues(r)[0], t, k, dist)
        got = d.project(pts)
        assert got.shape == (len(pts), 2)
        assert np.max(np.abs(got - want.reshape(-1, 2))) < 1e-9


def test_project_device_frame_and_unproject_round_trip(calibrated):
    for d in calibrated.devices:
        xs, ys = np.meshgrid(np.linspace(0, d.width - 1, 9), np.linspace(0, d.height - 1, 7))
        pixels = np.stack([xs.ravel(), ys.ravel()], axis=1)
        rays = d.unproject(pixels)
        assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
        again = d.project(rays * 1000.0, frame="device")
        assert np.max(np.abs(again - pixels)) < 1e-6
        origins, directions = d.rays(pixels)
        r, t = d.pose[:3, :3], d.pose[:3, 3]
        assert np.allclose(origins, -r.T @ t)
        assert np.allclose(directions, rays @ r)


def test_project_behind_the_device_is_nan(calibrated):
    got = calibrated["cam0"].project([[0.0, 0.0, -100.0], [0.0, 0.0, 100.0]])
    assert np.isnan(got[0]).all() and np.isfinite(got[1]).all()


def test_projection_uncertainty_grows_towards_the_corners(calibrated):
    d = calibrated["cam0"]
    u = d.projection_uncertainty([[d.intrinsics["cx"], d.intrinsics["cy"]], [0.0, 0.0]])
    assert np.all(u > 0) and u[1] > u[0]


def pairs(rig, calibrated, first, second, pose=5):
    a, b = rig.pixels[first][pose], rig.pixels[second][pose]
    ok = ~np.isnan(a[:, 0]) & ~np.isnan(b[:, 0])
    return a[ok], b[ok], rig.truth_points(pose)[ok]


@pytest.mark.parametrize("first,second", [(0, 1), (0, 2), (1, 2)])
def test_triangulate_the_held_out_pose(rig, calibrated, first, second):
    a, b, truth = pairs(rig, calibrated, first, second)
    names = calibrated.names
    points = hexcal.triangulate(calibrated, names[first], names[second], a, b)
    assert len(points) > 300
    assert np.sqrt(np.mean(np.sum((points - truth) ** 2, axis=1))) < 0.5
    # The midpoint of the two rays, computed here from the rays hexcal gives.
    (oa, da), (ob, db) = calibrated[names[first]].rays(a), calibrated[names[second]].rays(b)
    w = oa - ob
    p, q, r = np.sum(da * db, 1), np.sum(da * w, 1), np.sum(db * w, 1)
    s, t = (p * r - q) / (1 - p * p), (r - p * q) / (1 - p * p)
    mid = (oa + da * s[:, None] + ob + db * t[:, None]) / 2
    assert np.max(np.abs(points - mid)) < 1e-6


def test_triangulation_covariance_matches_monte_carlo(rig, calibrated):
    a, b, _ = pairs(rig, calibrated, 0, 1)
    a, b = a[:5], b[:5]
    sigma = 0.3
    _, c0 = hexcal.triangulate(calibrated, "cam0", "cam1", a, b, pixel_sigma=0.0)
    points, c1 = hexcal.triangulate(calibrated, "cam0", "cam1", a, b, pixel_sigma=sigma)
    assert c1.shape == (5, 3, 3)
    assert np.allclose(c1, np.transpose(c1, (0, 2, 1)))
    assert np.all(np.linalg.eigvalsh(c0) > -1e-12)
    # The pixel-noise part against sampled noise on the first point.
    rng = np.random.default_rng(1)
    n = 2000
    na = a[:1] + rng.normal(0, sigma, (n, 2))
    nb = b[:1] + rng.normal(0, sigma, (n, 2))
    sampled = np.cov(hexcal.triangulate(calibrated, "cam0", "cam1", na, nb).T)
    predicted = c1[0] - c0[0]
    assert np.allclose(np.diag(sampled), np.diag(predicted), rtol=0.15)


def test_verify_is_hexcal_verify_on_the_held_out_pose(rig, calibrated, tmp_path):
    held = rig.correspondences([5])
    checks = hexcal.verify(calibrated, held)
    found = {(c["first"], c["second"]) for c in checks}
    assert {("cam0", "cam1"), ("cam0", "proj0"), ("cam1", "proj0")} <= found
    for c in checks:
        assert c["points"] > 300 and c["length_rms"] < 0.2 and c["flatness_rms"] < 0.2
    path = tmp_path / "held-out.json"
    path.write_text(json.dumps(held))
    assert hexcal.verify(calibrated, path) == checks


@pytest.mark.parametrize("name", ["g1_frontal_00", "g2_tilted_02", "g5_back_05"])
def test_detect_labels_the_sample_images(name):
    truth = json.loads((SAMPLES / f"{name}.json").read_text())
    image = cv2.imread(str(SAMPLES / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
    found = hexcal.detect(image)
    assert found["circles"].shape[1] == 4
    assert found["points"].shape == (len(found["hex"]), 2)
    side = {"front": 0, "back": 1}[truth["side"]]
    labelled = {
        (int(q), int(r)): xy
        for (q, r), xy, s, a in zip(found["hex"], found["points"], found["side"], found["anchored"])
        if a and s == side
    }
    hits = 0
    for c in truth["circles"]:
        xy = labelled.get((c["q"], c["r"]))
        if xy is not None:
            hits += 1
            assert np.hypot(*(xy - np.array(c["ellipse"]))) < 0.5
    assert hits >= 0.9 * len(truth["circles"])
    # The labelled points are rows of the circles.
    assert np.allclose(found["circles"][found["circle"], :2], found["points"])


def sequence():
    return {
        "steps": 3,
        "projectors": [{"width": 1280, "height": 800, "frequency": 1,
                        "response": {"kind": "linear"}}],
        "column_counts": [20, 21, 25],
        "row_counts": [20, 21, 25],
    }


def stack(width=160, height=120):
    """A camera seeing the projector's pixels u = 300 + 2.5x, v = 200 + 2.5y, with the
    patterns of docs/design.md §6 on an ambient of 20 DN, 8 bit."""
    seq = sequence()
    y, x = np.mgrid[0:height, 0:width].astype(float)
    u, v = 300 + 2.5 * x, 200 + 2.5 * y
    frames = []
    n = seq["steps"]
    for direction, counts in (("c", seq["column_counts"]), ("r", seq["row_counts"])):
        for count in counts:
            pos, size = (u, 1280) if direction == "c" else (v, 800)
            for s in range(n):
                phi = 2 * np.pi * count * (pos + 0.5) / size - 2 * np.pi * s / n
                frames.append(np.round(20 + 200 * 0.5 * (1 + np.cos(phi))).astype(np.uint8))
    return np.stack(frames), u, v


def test_decode_a_simulated_stack():
    frames, u, v = stack()
    out = hexcal.decode(frames, sequence())
    assert len(out["projectors"]) == 1
    p = out["projectors"][0]
    valid = p["valid"]
    assert valid.shape == u.shape and valid.dtype == bool
    assert valid.mean() > 0.95
    assert np.max(np.abs(p["u"][valid] - u[valid])) < 0.2
    assert np.max(np.abs(p["v"][valid] - v[valid])) < 0.2
    assert np.allclose(out["ambient"], 20, atol=2)
    # A list of frames decodes the same.
    again = hexcal.decode(list(frames), sequence())
    assert np.array_equal(again["projectors"][0]["u"], p["u"], equal_nan=True)


def test_bad_input_raises():
    frames, _, _ = stack(32, 24)
    with pytest.raises(hexcal.Error, match="stack ends after 17 frames"):
        hexcal.decode(frames[:-1], sequence())
    with pytest.raises(hexcal.Error, match="full_scale"):
        hexcal.decode(frames.astype(np.float32), sequence())
    bad = sequence()
    bad["steps"] = 2
    with pytest.raises(hexcal.Error, match="sequence"):
        hexcal.decode(frames, bad)
    with pytest.raises(hexcal.Error, match="2-D numpy array"):
        hexcal.detect(np.zeros(10))
    with pytest.raises(hexcal.Error, match="board"):
        hexcal.detect(np.zeros((20, 20), np.uint8), board="no-such-board")
    with pytest.raises(hexcal.Error, match="not a correspondences file"):
        hexcal.calibrate({"board": "hex600"})
    with pytest.raises(hexcal.Error, match=r"views\[0\]"):
        hexcal.calibrate({"board": "hex600", "poses": 1, "devices": [
            {"name": "cam0", "kind": "camera", "width": 640, "height": 480}], "views": [
            {"camera": 3, "pose": 0, "frame": "unanchored", "points": []}]})
    assert issubclass(hexcal.Error, ValueError)


def test_bad_calibration_input_raises(calibrated, tmp_path):
    d = calibrated["cam0"]
    with pytest.raises(hexcal.Error, match=r"N×3 array, got shape \(2, 2\)"):
        d.project(np.zeros((2, 2)))
    with pytest.raises(hexcal.Error, match="not an array of numbers"):
        d.unproject([["a", "b"]])
    with pytest.raises(hexcal.Error, match="frame"):
        d.project(np.zeros((1, 3)), frame="world")
    with pytest.raises(KeyError, match="cam9"):
        calibrated["cam9"]
    with pytest.raises(hexcal.Error, match="one pixel pair per row"):
        hexcal.triangulate(calibrated, "cam0", "cam1", np.zeros((2, 2)), np.zeros((3, 2)))
    path = tmp_path / "calibration.json"
    text = json.loads(calibrated.to_json())
    text["devices"][1]["intrinsics"]["fx"] = -1.0
    path.write_text(json.dumps(text))
    with pytest.raises(hexcal.Error, match=r"devices\[1\]\.intrinsics\.fx"):
        hexcal.load(path)
    path.write_text("{")
    with pytest.raises(hexcal.Error, match="calibration.json"):
        hexcal.load(path)


def test_the_example_triangulates_a_calibration_folder(rig, calibrated, tmp_path):
    calibrated.save(tmp_path / "calibration.json")
    (tmp_path / "held-out.json").write_text(json.dumps(rig.correspondences([5])))
    script = REPO / "examples" / "triangulate.py"
    run = subprocess.run([sys.executable, str(script), str(tmp_path)],
                         capture_output=True, text=True, check=True)
    rows = [line.split() for line in run.stdout.splitlines()[1:4]]
    assert [r[:2] for r in rows] == [["cam0", "cam1"], ["cam0", "proj0"], ["cam1", "proj0"]]
    assert all(float(r[4]) < 0.2 for r in rows)
    assert "hexcal verify" in run.stdout


def test_the_stubs_name_what_the_module_has():
    import ast

    stub = ast.parse((REPO / "crates/py/python/hexcal/_hexcal.pyi").read_text())
    top = {n.name: n for n in stub.body if isinstance(n, (ast.ClassDef, ast.FunctionDef))}
    assert set(top) == set(hexcal.__all__)
    for cls in ("Device", "Calibration"):
        stubbed = {n.name for n in top[cls].body if isinstance(n, ast.FunctionDef)}
        public = {m for m in dir(getattr(hexcal, cls)) if not m.startswith("_")}
        assert public <= stubbed, public - stubbed
