#!/usr/bin/env python3
"""Benchmark: camera model throughput (project and lift) on the Table I calibration.

Prints one JSON object: points per second for ``project`` and ``lift`` at batch sizes a front
end uses (one frame's features) and a renderer uses (a full image), and the per-frame cost of
lifting 200 features. Run: ``.venv/bin/python tools/bench_camera.py``.
"""

from __future__ import annotations

import json
import time

from mowerhw.camera import paper_table1_camera
from mowerhw.camera.check import sample_valid_pixels


def timed(fn, repeat: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    cam = paper_table1_camera()
    out: dict[str, object] = {"camera": "paper Table I, 1540x1540"}
    for n in (200, 100_000):
        pix = sample_valid_pixels(cam, n, seed=0)
        bearings = cam.lift(pix)
        t_lift = timed(lambda p=pix: cam.lift(p), 20 if n < 1000 else 3)
        t_proj = timed(lambda b=bearings: cam.project(b), 20 if n < 1000 else 3)
        out[f"n{n}"] = {
            "lift_us": round(t_lift * 1e6, 1),
            "project_us": round(t_proj * 1e6, 1),
            "lift_points_per_s": round(n / t_lift),
            "project_points_per_s": round(n / t_proj),
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
