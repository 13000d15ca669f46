#!/usr/bin/env python3
"""Benchmark: real-time factor of the mow-phase Localizer with 15 and 200 landmarks.

A map is taught on the simulator (``paper``: 15 landmarks; ``large`` with 200 landmarks),
then the same drive's sensor streams are fed to a :class:`mowerhw.mow.Localizer` against that
map, with a containment decision after every IMU sample (as the daemon does). Simulation and
teaching are excluded from the timing. Best of ``--repeat``. Prints one JSON object.

    .venv/bin/python tools/bench_localizer.py
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import time

from mowerhw.evaluation.teach import run_teach
from mowerhw.map import LawnMap
from mowerhw.mow import Localizer
from mowerhw.sim import simulate_teach


def bench(scenario: str, seed: int, n_landmarks: int | None, repeat: int) -> dict:
    run = simulate_teach(scenario, seed, n_landmarks=n_landmarks)
    taught = run_teach(run=run)
    lawn_map = LawnMap.from_teach_result(taught.result)
    events = list(run.streams.events())
    best = float("inf")
    best_c = float("inf")
    loc = None
    for _ in range(repeat):
        loc = Localizer(lawn_map)
        imu, speed, bearings, containment = loc.imu, loc.speed, loc.bearings, loc.containment
        t_cont = 0.0
        t0 = time.perf_counter()
        for kind, p in events:
            if kind == "imu":
                imu(*p)
                c0 = time.perf_counter()
                containment()
                t_cont += time.perf_counter() - c0
            elif kind == "speed":
                speed(*p)
            else:
                bearings(p.t, p.ids, p.bearings)
        wall = time.perf_counter() - t0
        best = min(best, wall)
        best_c = min(best_c, t_cont)
    n_imu = run.streams.imu_t.size
    return {
        "landmarks_in_map": len(lawn_map.landmarks),
        "landmarks_per_frame_mean": round(
            sum(len(f) for f in run.streams.frames) / len(run.streams.frames), 1
        ),
        "sim_s": round(run.duration_s, 1),
        "wall_s": round(best, 3),
        "real_time_factor": round(run.duration_s / best, 1),
        "us_per_imu_sample": round(1e6 * best / n_imu, 1),
        "containment_us_per_call": round(1e6 * best_c / n_imu, 1),
        "frames_with_fix": loc.counters.frames_with_fix if loc else 0,
        "frames": loc.counters.frames if loc else 0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    out = {
        "paper_15_landmarks": bench("paper", args.seed, None, args.repeat),
        "large_200_landmarks": bench("large", args.seed, 200, max(1, args.repeat - 1)),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
