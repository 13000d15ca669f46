#!/usr/bin/env python3
"""Benchmark: real-time factor of the teach estimators (simulated seconds per wall second).

Runs the Teacher on pre-generated streams (simulation time excluded) and reports, best of
``--repeat`` runs per case, the on-line estimator (IMU/speed/camera inputs) and ``finish``
(loop closure + boundary) separately and together. Cases: the paper scenario (15 landmarks)
and the large lawn with 200 landmarks; the inverse-depth EKF baseline on the same streams for
comparison (on the large lawn only the first ``--idp-seconds`` of the drive: its cost grows
with the square of the landmarks). Prints one JSON object.

    .venv/bin/python tools/bench_teach.py
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import resource
import time

from mowerhw.baselines.inverse_depth import InverseDepthEkfMapper
from mowerhw.sim import simulate_teach
from mowerhw.teach import Teacher


def _events(run, until: float | None = None):
    evs = list(run.streams.events())
    if until is None:
        return evs
    return [e for e in evs if (e[1].t if e[0] == "bearings" else e[1][0]) <= until]


def _drive(est, events) -> float:
    imu, speed, bearings = est.imu, est.speed, est.bearings
    t0 = time.perf_counter()
    for kind, p in events:
        if kind == "imu":
            imu(*p)
        elif kind == "speed":
            speed(*p)
        else:
            bearings(p.t, p.ids, p.bearings)
    return time.perf_counter() - t0


def bench_teacher(run, repeat: int) -> dict:
    events = _events(run)
    best_online = best_finish = float("inf")
    for _ in range(repeat):
        t = Teacher()
        best_online = min(best_online, _drive(t, events))
        t0 = time.perf_counter()
        t.finish()
        best_finish = min(best_finish, time.perf_counter() - t0)
    dur = run.duration_s
    return {
        "sim_s": round(dur, 1),
        "landmarks": run.world.n_landmarks,
        "imu_samples": int(run.streams.imu_t.size),
        "online_wall_s": round(best_online, 3),
        "finish_wall_s": round(best_finish, 3),
        "rtf_online": round(dur / best_online, 1),
        "rtf_total": round(dur / (best_online + best_finish), 1),
        "us_per_imu_sample": round(1e6 * best_online / run.streams.imu_t.size, 1),
    }


def bench_idp(run, until: float | None) -> dict:
    events = _events(run, until)
    m = InverseDepthEkfMapper()
    wall = _drive(m, events)
    dur = min(run.duration_s, until) if until else run.duration_s
    return {
        "sim_s": round(dur, 1),
        "wall_s": round(wall, 3),
        "rtf": round(dur / wall, 1),
        "state_size": int(m.P.shape[0]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--idp-seconds", type=float, default=40.0)
    args = ap.parse_args()
    paper = simulate_teach("paper", args.seed)
    large = simulate_teach("large", args.seed, n_landmarks=200)
    out = {
        "goal": "rtf >= 100 with 15 landmarks, >= 20 with 200",
        "paper_15_landmarks": bench_teacher(paper, args.repeat),
        "large_200_landmarks": bench_teacher(large, max(1, args.repeat - 1)),
        "inverse_depth_ekf": {
            "paper_15_landmarks": bench_idp(paper, None),
            "large_200_landmarks_first_part": bench_idp(large, args.idp_seconds),
        },
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
