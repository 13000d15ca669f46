#!/usr/bin/env python3
"""Benchmark: the vision front end on real mirror-camera photos.

1. **Detection on real images**: the front end (:class:`mowerhw.frontend.FrontEnd`) detects
   features in each of the 18 real catadioptric photos of ``omni-mirror-checkerboard`` with
   the camera calibrated from them (``tests/data/mirror-camchain.yaml``, written by
   ``mowerhw camera calibrate``); every feature must lie in the valid region (the mirror
   annulus), none on the rim, the camera's own reflection or the black corners.
2. **Real texture, known motion**: from one real photo, exact views under known pure rotations
   of the camera (:mod:`mowerhw.sim.rotated_views`: a central camera needs no depth for
   that) — a mower turning at up to ``--yaw-rate`` deg/s with a tilt wobble, at 4 Hz — go
   through the front end with and without the gyro's prediction (``frontend.gyro_prediction``);
   every track is scored against where its birth pixel truly is in each later view.

Prints one JSON object. Run: ``.venv/bin/python tools/bench_klt_real.py`` (``--frames 40``).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from mowerhw.camera import load_camchain
from mowerhw.common.geometry import quat_to_rotmat
from mowerhw.config import DEFAULT_Q_BC, FrontendConfig
from mowerhw.frontend import FrontEnd
from mowerhw.sim.rotated_views import RotatedViews, mower_rotations

ROOT = Path(__file__).resolve().parent.parent
PHOTOS = ROOT.parent / "shared" / "data" / "real" / "omni-mirror-checkerboard" / "images"
CAMCHAIN = ROOT / "tests" / "data" / "mirror-camchain.yaml"


def photos() -> list[Path]:
    return sorted(PHOTOS.glob("*.jpg"), key=lambda p: int(p.stem))


def detection_on_photos(paths: list[Path]) -> dict[str, object]:
    """Features the front end detects in each photo: how many, and how many outside the
    valid region or within a KLT half-window of its edge."""
    cam = load_camchain(CAMCHAIN)
    ann = cam.mask
    assert ann is not None
    total = outside = 0
    margins = []
    for path in paths:
        fe = FrontEnd(cam, DEFAULT_Q_BC, FrontendConfig())  # the camera's mask is computed once
        tracks = fe.process(0.0, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
        px = tracks.pixels
        total += px.shape[0]
        outside += int((~cam.valid(px)).sum())
        r = np.hypot(px[:, 0] - ann.center_px[0], px[:, 1] - ann.center_px[1])
        margins.append(np.minimum(r - ann.inner_radius_px, ann.outer_radius_px - r).min())
    return {
        "photos": len(paths),
        "features": total,
        "outside_valid_region": outside,
        "outside_share": outside / max(total, 1),
        "closest_to_region_edge_px": round(float(min(margins)), 1),
    }


def track_sequence(
    views: RotatedViews,
    rotations: list[np.ndarray],
    gyro_prediction: bool,
    dt: float = 0.25,
) -> dict[str, object]:
    """The front end over the rotated views; every track scored against the truth."""
    cam = views.camera
    r_bc = quat_to_rotmat(np.asarray(DEFAULT_Q_BC))
    cfg = dataclasses.replace(FrontendConfig(), gyro_prediction=gyro_prediction)
    fe = FrontEnd(cam, DEFAULT_Q_BC, cfg)
    birth: dict[int, tuple[int, np.ndarray]] = {}
    errors: list[float] = []
    ages: list[int] = []
    tracked = []
    t0 = time.perf_counter()
    for k, r_k in enumerate(rotations):
        image = views.view(r_k)
        r_prev_cur = None
        if k:
            r_cam = rotations[k - 1].T @ r_k  # current camera → previous camera
            r_prev_cur = r_bc @ r_cam @ r_bc.T  # … in the body frame, as the gyro gives it
        tracks = fe.process(k * dt, image, r_prev_cur)
        tracked.append(int(tracks.ids.size))
        for tid, px, age in zip(tracks.ids, tracks.pixels, tracks.ages, strict=True):
            if age == 0 or int(tid) not in birth:
                birth[int(tid)] = (k, px.copy())
                continue
            j, px0 = birth[int(tid)]
            truth = views.truth(px0[None], rotations[j], r_k)[0]
            errors.append(float(np.linalg.norm(px - truth)))
            ages.append(k - j)
    err = np.array(errors)
    s = fe.stats
    return {
        "gyro_prediction": gyro_prediction,
        "frames": len(rotations),
        "track_scores": int(err.size),
        "error_px_median": round(float(np.median(err)), 3) if err.size else None,
        "error_px_p95": round(float(np.percentile(err, 95)), 3) if err.size else None,
        "error_px_max": round(float(err.max()), 2) if err.size else None,
        "share_over_1px": round(float((err > 1.0).mean()), 4) if err.size else None,
        "tracks_per_frame_median": float(np.median(tracked[1:])) if len(tracked) > 1 else 0.0,
        "scored_track_age_frames_median": float(np.median(ages)) if ages else None,
        "scored_track_age_frames_max": int(max(ages)) if ages else None,
        "lost_klt": s.lost_klt,
        "lost_forward_backward": s.lost_forward_backward,
        "lost_epipolar": s.lost_epipolar,
        "s_per_frame": round((time.perf_counter() - t0) / len(rotations), 3),
    }


def run(frames: int, yaw_rate: float, wobble: float, photo: Path, seed: int) -> dict[str, object]:
    cam = load_camchain(CAMCHAIN)
    views = RotatedViews(cam, cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE))
    rotations = mower_rotations(frames, 0.25, yaw_rate, wobble, seed=seed)
    steps = [
        np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))
        for a, b in itertools.pairwise(rotations)
    ]
    return {
        "photo": photo.name,
        "rotation_per_frame_deg": {
            "median": round(float(np.median(steps)), 2),
            "max": round(float(np.max(steps)), 2),
        },
        "with_gyro": track_sequence(views, rotations, True),
        "without_gyro": track_sequence(views, rotations, False),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--yaw-rate", type=float, default=45.0, help="deg/s (a mower turns 30-90)")
    ap.add_argument("--wobble", type=float, default=3.0, help="tilt amplitude (deg)")
    ap.add_argument("--photo", default="1.jpg")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if not PHOTOS.exists():
        sys.exit(f"no real photos at {PHOTOS}")
    out = {
        "detection": detection_on_photos(photos()),
        "sequence": run(args.frames, args.yaw_rate, args.wobble, PHOTOS / args.photo, args.seed),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
