"""Triangulate the held-out board pose of a hexcal run with the hexcal Python package.

    python examples/triangulate.py hexcal-run

FOLDER is a run's folder (of `hexcal run --rig rigs/sim-paper.toml --auto`) or a calibration
folder: its `calibration/calibration.json` (or `calibration.json`) and `held-out.json`, the
held-out poses' views in the correspondences layout. For every camera pair that shares ten
circles of a pose, and every camera–projector pair, the circles are triangulated with
`hexcal.triangulate` (each point with its 1σ from the calibration's covariance and 0.1 px
of pixel noise) and the distances between them compared with the board's; `hexcal.verify`
(the `hexcal verify` command, which also removes each camera's ellipse-centre bias) is
printed below for comparison.
"""

import itertools
import json
import pathlib
import sys

import numpy as np

import hexcal


def nominal(q, r, pitch=20.0):
    """A lattice point in its side's frame (mm), hex600: d·(q + r/2, (√3/2)·r)."""
    return np.stack([pitch * (q + 0.5 * r), pitch * np.sqrt(0.75) * r], axis=1)


def length_errors(points, hexes):
    """RMS of measured − nominal over every pair of points (mm)."""
    flat = nominal(hexes[:, 0], hexes[:, 1])
    i, j = np.triu_indices(len(points), 1)
    measured = np.linalg.norm(points[i] - points[j], axis=1)
    return np.sqrt(np.mean((measured - np.linalg.norm(flat[i] - flat[j], axis=1)) ** 2))


def main(folder):
    folder = pathlib.Path(folder)
    if (folder / "calibration" / "calibration.json").exists():
        folder = folder / "calibration"
    cal = hexcal.load(folder / "calibration.json")
    held = json.loads((folder / "held-out.json").read_text())
    names = [d["name"] for d in held["devices"]]
    # (pose, side) → camera → {(q, r): pixel}; camera–projector pairs per view.
    seen, pairs = {}, []
    for v in held["views"]:
        if not isinstance(v["frame"], dict):
            continue  # unanchored: no board frame
        cam = names[v["camera"]]
        per = seen.setdefault((v["pose"], v["frame"]["anchored"]), {}).setdefault(cam, {})
        by_projector = {}
        for p in v["points"]:
            hex_ = (p["hex"]["q"], p["hex"]["r"])
            per[hex_] = p["image"]
            for pp in p["projectors"]:
                by_projector.setdefault(names[pp["projector"]], []).append(
                    (hex_, p["image"], pp["pixel"]))
        for proj, rows in by_projector.items():
            pairs.append((v["pose"], cam, proj, rows))
    for (pose, _), per in seen.items():
        for a, b in itertools.combinations(sorted(per), 2):
            common = sorted(set(per[a]) & set(per[b]))
            pairs.append((pose, a, b, [(h, per[a][h], per[b][h]) for h in common]))
    print(f"{'first':<8} {'second':<8} {'pose':>4} {'points':>6} {'length RMS mm':>14} "
          f"{'mean 1σ mm':>11}")
    for pose, a, b, rows in sorted(pairs, key=lambda p: p[:3]):
        if len(rows) < 10 or a not in cal or b not in cal:
            continue
        hexes = np.array([h for h, _, _ in rows])
        pa = np.array([x for _, x, _ in rows])
        pb = np.array([y for _, _, y in rows])
        points, cov = hexcal.triangulate(cal, a, b, pa, pb, pixel_sigma=0.1)
        sigma = np.sqrt(np.trace(cov, axis1=1, axis2=2)).mean()
        print(f"{a:<8} {b:<8} {pose:>4} {len(points):>6} {length_errors(points, hexes):>14.4f} "
              f"{sigma:>11.4f}")
    print("\nhexcal verify (ellipse-centre bias removed):")
    for k in hexcal.verify(cal, folder / "held-out.json"):
        print(f"{k['first']:<8} {k['second']:<8} {k['pose']:>4} {k['points']:>6} "
              f"{k['length_rms']:>14.4f}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
