#!/usr/bin/env python3
"""Benchmark: camera model throughput (project and lift) against ``cv2.omnidir``, one run.

For each calibration — the paper's Table I mirror camera, the real mirror camera calibrated
from photos (``tests/data/mirror-camchain.yaml``) and a ξ = 2 fisheye (the T265's own
camchain when ``../shared/data`` is present) — times ``project`` against
``cv2.omnidir.projectPoints`` and ``lift`` against ``cv2.omnidir.undistortPoints`` (which
returns points on the plane z = 1, not bearings, after a fixed 20 fixed-point iterations), at
the batch sizes a front end uses (one frame's features) and a renderer uses (a full image),
best of several runs, one thread. Prints one JSON object: points per second and the ratio
ours / OpenCV (above 1: ours is faster).

Run: ``.venv/bin/python tools/bench_camera.py``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json
import time
from pathlib import Path

import cv2
import numpy as np

from mowerhw.camera import load_camchain, paper_table1_camera
from mowerhw.camera.check import sample_valid_pixels

ROOT = Path(__file__).resolve().parent.parent
T265 = (
    ROOT.parent
    / "shared"
    / "data"
    / "real"
    / "kalibr-t265-camchain"
    / "imu_cameras_calibration-camchain-imucam.yaml"
)


def timed(fn, repeat: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench(cam, n: int) -> dict[str, float]:
    pix = sample_valid_pixels(cam, n, seed=0)
    bearings = cam.lift(pix)
    repeat = 30 if n < 1000 else 3
    k, d, xi = cam.K, cam.D, np.array([[cam.xi]])
    zero = np.zeros(3)
    pix_cv = pix.reshape(1, -1, 2)
    bear_cv = bearings.reshape(1, -1, 3)
    t_lift = timed(lambda: cam.lift(pix), repeat)
    t_proj = timed(lambda: cam.project(bearings), repeat)
    t_cv_und = timed(lambda: cv2.omnidir.undistortPoints(pix_cv, k, d, xi, np.eye(3)), repeat)
    t_cv_proj = timed(lambda: cv2.omnidir.projectPoints(bear_cv, zero, zero, k, cam.xi, d), repeat)
    return {
        "points": n,
        "lift_points_per_s": round(n / t_lift),
        "opencv_undistort_points_per_s": round(n / t_cv_und),
        "lift_vs_opencv": round(t_cv_und / t_lift, 2),
        "project_points_per_s": round(n / t_proj),
        "opencv_project_points_per_s": round(n / t_cv_proj),
        "project_vs_opencv": round(t_cv_proj / t_proj, 2),
    }


def main() -> None:
    cv2.setNumThreads(1)
    cams = {"paper Table I (1540x1540, xi 0.92)": paper_table1_camera()}
    mirror = ROOT / "tests" / "data" / "mirror-camchain.yaml"
    if mirror.exists():
        cams["real mirror camera (1280x960, xi 0.96)"] = load_camchain(mirror)
    if T265.exists():
        cams["T265 cam0 (848x800, xi 2.0)"] = load_camchain(T265)
    out: dict[str, object] = {}
    for name, cam in cams.items():
        out[name] = {f"n{n}": bench(cam, n) for n in (200, 100_000)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
