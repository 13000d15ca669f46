#!/usr/bin/env python3
"""Global relocalization at pixel level: random starts with no prior (issue 18).

For one taught map (the pixel-level teach of ``--scenario``/``--seed``: rendered drive, front
end, Teacher, loop closure), ``--starts`` random poses inside the lawn (uniform position at
least 0.3 m inside the edge, uniform heading): the mower stands there; each 0.25 s frame (the
bench camera's 4 Hz) is rendered with fresh pixel noise, goes through a fresh front end, and
:class:`mowerhw.mow.relocalize.GlobalRelocalizer` answers from it. A pose is *accepted* when
two consecutive frames agree within 0.10 m and 3°; the run gives up after ``--seconds``.

Prints one JSON object: success rate (accepted, error < 0.10 m and < 3°), time to accept
(median, p95), accepted-but-wrong (error > 0.15 m: the dangerous case), single-frame
answers and their errors, per-frame cost (ms), the map's descriptor bytes per 100 landmarks.

    .venv/bin/python tools/relocalize_pixel.py --scenario paper --seed 1 --starts 100
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import shapely

from mowerhw.evaluation.campaign import scenario_config
from mowerhw.evaluation.pixel import run_teach_pixel, yard_arguments
from mowerhw.evaluation.recovery import random_pose
from mowerhw.frontend.tracker import FrontEnd
from mowerhw.map import LawnMap
from mowerhw.mow.relocalize import GlobalRelocalizer
from mowerhw.sim.motion import pose_on_ground
from mowerhw.sim.render import OmniRenderer

FRAME_S = 0.25
AGREE_M, AGREE_RAD = 0.10, math.radians(3.0)
WRONG_M = 0.15


def _pct(a: list[float], q: float) -> float | None:
    return round(float(np.percentile(a, q)), 3) if a else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    yard_arguments(ap, with_map=False)
    ap.add_argument("--starts", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()
    cfg = scenario_config(args.scenario)  # the yard mower's own IMU grade
    t0 = time.perf_counter()
    taught = run_teach_pixel(args.scenario, args.seed, cfg)
    if taught.result is None:
        raise SystemExit(f"teach failed: {taught.error}")
    teach_s = time.perf_counter() - t0
    lawn_map = LawnMap.from_teach_result(taught.result)
    world, truth = taught.run.world, taught.run.truth
    frame = truth.frame
    renderer = OmniRenderer(world, args.seed + 1000)
    reloc = GlobalRelocalizer(lawn_map)
    lawn = shapely.Polygon(world.lawn.outline(720)).buffer(-0.3)
    rng = np.random.default_rng([args.seed, 18])
    frames = max(2, round(args.seconds / FRAME_S))
    runs, single_err, frame_ms, single_ok, single_n = [], [], [], 0, 0
    for i in range(args.starts):
        x, y, psi = random_pose(lawn, rng)
        cam_m, r_mb = pose_on_ground(
            world.terrain, np.array([[x, y]]), np.array([psi]), world.scenario.camera_height_m
        )
        p_true = frame.map_to_world(cam_m)[0]
        r_true = frame.r_mw.T @ r_mb[0]
        yaw_true = math.atan2(r_true[1, 0], r_true[0, 0])
        fe = FrontEnd(world.camera, world.q_bc, cfg.frontend, seed=args.seed * 1000 + i)
        prev = None
        outcome: dict[str, object] = {"accepted": False}
        for k in range(frames):
            tracks = fe.process(k * FRAME_S, renderer.render(float(x), float(y), psi))
            res = reloc.locate(tracks.bearings)
            frame_ms.append(res.ms)
            single_n += 1
            if not res.ok:
                prev = None
                continue
            single_ok += 1
            err = float(np.linalg.norm(res.p_wb[:2] - p_true[:2]))
            single_err.append(err)
            if prev is not None:
                d = float(np.linalg.norm(res.p_wb[:2] - prev.p_wb[:2]))
                dy = abs((res.yaw - prev.yaw + math.pi) % (2 * math.pi) - math.pi)
                if d < AGREE_M and dy < AGREE_RAD:
                    yaw_err = abs((res.yaw - yaw_true + math.pi) % (2 * math.pi) - math.pi)
                    outcome = {
                        "accepted": True,
                        "t_s": round((k + 1) * FRAME_S, 2),
                        "error_m": round(err, 4),
                        "yaw_error_deg": round(math.degrees(yaw_err), 3),
                        "inliers": len(res.inliers),
                    }
                    break
            prev = res
        runs.append(outcome)
    acc = [r for r in runs if r["accepted"]]
    good = [
        r
        for r in acc
        if float(r["error_m"]) < 0.10 and float(r["yaw_error_deg"]) < 3.0  # type: ignore[arg-type]
    ]
    wrong = [r for r in acc if float(r["error_m"]) > WRONG_M]  # type: ignore[arg-type]
    times = [float(r["t_s"]) for r in acc]  # type: ignore[arg-type]
    desc_bytes = sum(len(lm.descriptor or b"") for lm in lawn_map.landmarks)
    print(
        json.dumps(
            {
                "scenario": args.scenario,
                "seed": args.seed,
                "starts": args.starts,
                "map_landmarks": len(lawn_map.landmarks),
                "success_rate": round(len(good) / max(1, len(runs)), 3),
                "accepted": len(acc),
                "accepted_wrong_over_0.15m": len(wrong),
                "time_to_accept_s": {"median": _pct(times, 50), "p95": _pct(times, 95)},
                "accepted_error_m": {
                    "median": _pct([float(r["error_m"]) for r in acc], 50),  # type: ignore[arg-type]
                    "max": round(max(float(r["error_m"]) for r in acc), 4) if acc else None,  # type: ignore[arg-type]
                },
                "single_frame": {
                    "frames": single_n,
                    "answered": single_ok,
                    "error_m_median": _pct(single_err, 50),
                    "error_m_p95": _pct(single_err, 95),
                    "over_0.15m": int(np.sum(np.array(single_err) > WRONG_M)),
                },
                "ms_per_frame": {"median": _pct(frame_ms, 50), "p95": _pct(frame_ms, 95)},
                "descriptor_bytes_per_100_landmarks": round(
                    100 * desc_bytes / max(1, len(lawn_map.landmarks))
                ),
                "teach_s": round(teach_s, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
