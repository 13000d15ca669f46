#!/usr/bin/env python3
"""Benchmark: the vision front end on 1540×1540 omni frames, on one core.

Renders the frames of a simulated teach drive (paper scenario, 4 Hz; rendering is not
timed), then runs :class:`mowerhw.frontend.FrontEnd` over them with OpenCV limited to one
thread and prints one JSON object: time per frame (mean and percentiles, wall and CPU),
frames per second, the share of one core the front end needs at the camera's 4 Hz, tracks
per frame and features detected. Also the renderer's own time per frame (the bench's cost).

Run: ``.venv/bin/python tools/bench_frontend.py`` (``--frames 120 --max-features 200``).
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np

from mowerhw.config import FrontendConfig
from mowerhw.frontend import FrontEnd, RotationHistory
from mowerhw.sim import simulate_teach
from mowerhw.sim.render import OmniRenderer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-features", type=int, default=FrontendConfig().max_features)
    ap.add_argument("--camera-hz", type=float, default=4.0)
    args = ap.parse_args()
    cv2.setNumThreads(1)  # one core, as the issue asks
    run = simulate_teach("paper", args.seed)
    tr, st = run.truth, run.streams
    renderer = OmniRenderer(run.world, args.seed)
    frames, render_ms = [], []
    for f in st.frames[: args.frames]:
        k = tr.index_at(f.t)
        x, y = tr.map_xy[k]
        t0 = time.perf_counter()
        frames.append((f.t, renderer.render(float(x), float(y), float(tr.map_heading[k]))))
        render_ms.append((time.perf_counter() - t0) * 1e3)
    cfg = FrontendConfig(max_features=args.max_features)
    fe = FrontEnd(run.world.camera, run.world.q_bc, cfg)
    rot = RotationHistory()
    wall, cpu, tracks = [], [], []
    ki, t_prev = 0, None
    for t, img in frames:
        while ki < st.imu_t.size and st.imu_t[ki] <= t + 1e-9:
            rot.add(st.imu_t[ki], st.gyro[ki])
            ki += 1
        r = rot.rotation_between(t_prev, t) if t_prev is not None else None
        w0, c0 = time.perf_counter(), time.process_time()
        out = fe.process(t, img, r)
        wall.append((time.perf_counter() - w0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
        tracks.append(out.ids.size)
        t_prev = t
    w, c = np.array(wall[1:]), np.array(cpu[1:])  # the first frame only detects

    def pct(a: np.ndarray) -> dict[str, float]:
        return {f"p{q}": round(float(np.percentile(a, q)), 2) for q in (50, 90, 99)}

    print(
        json.dumps(
            {
                "frames": len(w),
                "image": "1540x1540 8-bit",
                "opencv_threads": cv2.getNumThreads(),
                "max_features": args.max_features,
                "ms_per_frame_wall": {"mean": round(float(w.mean()), 2), **pct(w)},
                "ms_per_frame_cpu": {"mean": round(float(c.mean()), 2), **pct(c)},
                "frames_per_s": round(1000.0 / float(w.mean()), 1),
                "core_share_at_camera_rate": round(float(c.mean()) * args.camera_hz / 1000.0, 4),
                "camera_hz": args.camera_hz,
                "tracks_per_frame_median": float(np.median(tracks)),
                "features_detected": fe.stats.detected,
                "render_ms_per_frame": round(float(np.mean(render_ms)), 1),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
