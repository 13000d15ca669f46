#!/usr/bin/env python3
"""Benchmark: the runtime core's handlers on a recorded run, warm, and the decisions kept.

A bench or field recording made with ``--record`` carries the runtime core's journal: every
input in the order the daemon applied it (IMU samples, the front end's tracks, speed, …).
Replayed (:func:`mowerhw.recording.replay.replay_decisions`), the core makes the daemon's
decisions again; here each IMU sample's and each frame's tracks' handler is timed on the
thread's CPU clock, back to back (caches warm, unlike the daemon's paced wake-ups: the
live figures are in ``handler_cpu`` of ``mowerhw ctl status`` and ``tools/profile_daemon.py``).
The best of ``--repeat`` replays is reported, with the replayed decision sequence's sha256
and whether it matches the live one — so a change meant to compute the same thing faster
shows both its time and that the decisions did not move (issue 15, stop 68). Prints one
JSON object.

    .venv/bin/python -m mowerhw bench --duration 40 --record /tmp/b.mcap
    .venv/bin/python tools/bench_core_replay.py /tmp/b.mcap
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mowerhw.recording.replay import replay_decisions
from mowerhw.runtime.core import RuntimeCore

HANDLERS = ("imu", "tracks")


def timed(name: str, fn: Callable[..., Any], spent: dict[str, list[float]]) -> Callable[..., Any]:
    """``fn`` with its thread CPU time added to ``spent[name]`` (seconds, calls)."""

    def call(*args: Any, **kwargs: Any) -> Any:
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            cell = spent[name]
            cell[0] += time.thread_time() - t0
            cell[1] += 1

    return call


def measure(recording: Path, repeat: int = 3) -> dict[str, Any]:
    """The handlers' best time per call over ``repeat`` replays of ``recording``, and the
    replayed decisions (the core's handlers are restored afterwards)."""
    originals = {name: getattr(RuntimeCore, name) for name in HANDLERS}
    best: dict[str, float] = {}
    calls: dict[str, int] = {}
    result: dict[str, Any] = {}
    try:
        for _ in range(max(1, repeat)):
            spent: dict[str, list[float]] = {name: [0.0, 0] for name in HANDLERS}
            for name, fn in originals.items():
                setattr(RuntimeCore, name, timed(name, fn, spent))
            result = replay_decisions(recording)
            for name, (seconds, n) in spent.items():
                calls[name] = int(n)
                if n:
                    us = seconds / n * 1e6
                    best[name] = min(best.get(name, us), us)
    finally:
        for name, fn in originals.items():
            setattr(RuntimeCore, name, fn)
    return {
        "recording": str(recording),
        "repeats": max(1, repeat),
        "handlers_us_per_call_best": {k: round(v, 1) for k, v in best.items()},
        "calls": calls,
        "decisions": result.get("decisions"),
        "same_as_live": result.get("same_as_live"),
        "replay_sha256": result.get("replay_sha256"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path, help="an MCAP recording with the runtime journal")
    ap.add_argument("--repeat", type=int, default=3, help="replays; the best time is kept")
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # the replayed gate's halts are in the summary
    print(json.dumps(measure(args.recording, args.repeat), indent=1))


if __name__ == "__main__":
    main()
