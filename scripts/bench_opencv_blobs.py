#!/usr/bin/env python3
"""OpenCV's SimpleBlobDetector (the blob finder behind findCirclesGrid) on the images of
`hexcal bench detect-grid --out DIR`, side by side with hexcal's detect + grid figures.

`hexcal bench detect-grid` runs it itself (embedded) after its own timings when
/usr/bin/python3 has cv2 (Debian: apt-get install python3-opencv). By hand:

    cargo run --release -- bench detect-grid --out /tmp/bench
    /usr/bin/python3 scripts/bench_opencv_blobs.py /tmp/bench [--runs 7]

Per image: median time of SimpleBlobDetector.detect (OpenCV's own threads, as many as it
uses by default), recall of whole circles (a keypoint within a third of the circle's radius
of the truth's outline-ellipse centre) and the RMS centre error of the matched keypoints,
next to hexcal's figures read from DIR/hexcal_bench.json (same matching rule).
"""

import argparse
import json
import math
import os
import statistics
import time

import cv2
import numpy as np


def blob_detector(radius_min, radius_max):
    """White blobs between the given radii; shape filters loose enough for tilted circles
    (inertia ratio down to 0.2, i.e. about 78 degrees of tilt) and for marker rings."""
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor = True
    p.blobColor = 255
    p.minThreshold = 30
    p.maxThreshold = 220
    p.thresholdStep = 10
    p.minRepeatability = 2
    p.minDistBetweenBlobs = 2.0
    p.filterByArea = True
    p.minArea = math.pi * radius_min**2 * 0.2
    p.maxArea = math.pi * radius_max**2 * 1.5
    p.filterByCircularity = False
    p.filterByConvexity = True
    p.minConvexity = 0.8
    p.filterByInertia = True
    p.minInertiaRatio = 0.2
    return cv2.SimpleBlobDetector_create(p)


def whole_circles(truth):
    """(x, y, radius) of every whole circle with an outline ellipse."""
    return [
        (c["ellipse"][0], c["ellipse"][1], c["radius"])
        for c in truth["circles"]
        if c["whole"] and c.get("ellipse") is not None
    ]


def score(centres, circles):
    """Matched count and RMS error: each whole circle's nearest centre within r/3."""
    if len(centres) == 0:
        return 0, float("nan")
    pts = np.asarray(centres, dtype=float)
    sq = []
    for x, y, r in circles:
        d2 = (pts[:, 0] - x) ** 2 + (pts[:, 1] - y) ** 2
        i = int(np.argmin(d2))
        if d2[i] < (r / 3.0) ** 2:
            sq.append(d2[i])
    rms = math.sqrt(sum(sq) / len(sq)) if sq else float("nan")
    return len(sq), rms


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dir", help="output directory of `hexcal bench detect-grid --out`")
    ap.add_argument("--runs", type=int, default=7, help="timed runs per image")
    args = ap.parse_args()
    with open(os.path.join(args.dir, "hexcal_bench.json")) as f:
        hexcal = json.load(f)
    print(
        f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; "
        f"hexcal {hexcal['threads']} threads; load average now: "
        f"{open('/proc/loadavg').read().strip()}"
    )
    header = (
        f"{'image':<18} {'whole':>6} | {'hexcal ms':>9} {'recall':>7} {'rms px':>8} | "
        f"{'opencv ms':>9} {'recall':>7} {'rms px':>8}"
    )
    print(header)
    print("-" * len(header))
    for row in hexcal["rows"]:
        name = row["image"]
        with open(os.path.join(args.dir, os.path.splitext(name)[0] + ".json")) as f:
            truth = json.load(f)
        img = cv2.imread(os.path.join(args.dir, name), cv2.IMREAD_UNCHANGED)
        if img.dtype != np.uint8:
            img = cv2.convertScaleAbs(img, alpha=255.0 / float(img.max()))
        circles = whole_circles(truth)
        radii = [r for _, _, r in circles]
        det = blob_detector(min(radii), max(radii))
        det.detect(img)  # warm-up
        times = []
        for _ in range(max(1, args.runs)):
            t0 = time.perf_counter()
            kps = det.detect(img)
            times.append((time.perf_counter() - t0) * 1e3)
        # Keypoint coordinates: OpenCV's pixel (0, 0) is the centre of the top-left pixel,
        # as hexcal's.
        matched, rms = score([kp.pt for kp in kps], circles)
        whole = len(circles)
        print(
            f"{name:<18} {whole:>6} | {row['total_ms']:>9.1f} "
            f"{row['matched'] / whole:>7.4f} {row['centre_rms']:>8.4f} | "
            f"{statistics.median(times):>9.1f} {matched / whole:>7.4f} {rms:>8.4f}"
        )


if __name__ == "__main__":
    main()
