#!/usr/bin/env python3
"""Benchmark: what one IMU sample's localizer step costs back to back and at the daemon's pace.

The daemon's estimation loop wakes for each 50-Hz IMU sample and does a little work; in
between, the CPU idles. Measured here (issue 15): the same step — the mow ``Localizer``'s
IMU propagation and a containment decision, on a map taught on the simulator — timed
back to back (as replays and ``tools/bench_localizer.py`` time it), then with a sleep between
samples (the daemon's pace), then in batches (``--batch``: that many samples per wake-up,
the same sleep per sample). Each case reports the per-sample thread CPU (µs, median and
mean) and, for batches, by the sample's place in its batch. Prints one JSON object.

    .venv/bin/python tools/bench_wakeup_cost.py --samples 1500
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import statistics
import time
from typing import Any

from mowerhw.evaluation.teach import run_teach
from mowerhw.map import LawnMap
from mowerhw.mow import Localizer
from mowerhw.sim import simulate_teach

#: the first samples of a case are left out (the filter settling, the caches filling)
WARM_UP = 200


def run_case(
    lawn_map: LawnMap, events: list[Any], samples: int, sleep_s: float, batch: int
) -> dict[str, Any]:
    """Feed the drive's events to a new localizer; after every ``batch`` IMU samples sleep
    ``sleep_s`` per sample of the batch (0: back to back). Each IMU sample's step (its
    propagation and a containment decision) is timed on the thread's CPU clock."""
    loc = Localizer(lawn_map)
    by_place: list[list[float]] = [[] for _ in range(batch)]
    n = 0
    for kind, p in events:
        if kind == "imu":
            started = time.thread_time()
            loc.imu(*p)
            loc.containment()
            by_place[n % batch].append(time.thread_time() - started)
            n += 1
            if sleep_s > 0.0 and n % batch == 0:
                time.sleep(sleep_s * batch)
            if n >= samples + WARM_UP:
                break
        elif kind == "speed":
            loc.speed(*p)
        else:
            loc.bearings(p.t, p.ids, p.bearings)
    kept = [c[WARM_UP // batch :] for c in by_place]
    every = [x for c in kept for x in c]
    out: dict[str, Any] = {
        "us_per_sample_median": round(1e6 * statistics.median(every), 1),
        "us_per_sample_mean": round(1e6 * statistics.fmean(every), 1),
    }
    if batch > 1:
        out["us_median_by_place_in_batch"] = [round(1e6 * statistics.median(c), 1) for c in kept]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--samples", type=int, default=1500, help="IMU samples timed per case")
    ap.add_argument("--period-ms", type=float, default=20.0, help="the IMU's period (50 Hz)")
    ap.add_argument("--batch", type=int, nargs="*", default=[2, 5], help="batch sizes")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    run = simulate_teach("paper", args.seed)
    lawn_map = LawnMap.from_teach_result(run_teach(run=run).result)
    events = list(run.streams.events())
    period = args.period_ms / 1e3
    cases: dict[str, Any] = {
        "back_to_back": run_case(lawn_map, events, args.samples, 0.0, 1),
        f"one_per_wake_up_every_{args.period_ms:g}_ms": run_case(
            lawn_map, events, args.samples, period, 1
        ),
    }
    for b in args.batch:
        cases[f"{b}_per_wake_up"] = run_case(lawn_map, events, args.samples, period, b)
    warm = cases["back_to_back"]["us_per_sample_mean"]
    paced = cases[f"one_per_wake_up_every_{args.period_ms:g}_ms"]["us_per_sample_mean"]
    print(
        json.dumps(
            {
                "samples_per_case": args.samples,
                "cases": cases,
                "paced_over_back_to_back": round(paced / warm, 2),
            }
        )
    )


if __name__ == "__main__":
    main()
