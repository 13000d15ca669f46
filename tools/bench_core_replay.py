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
shows both its time and that the decisions did not move (issue 15, stop 68). With
``--pause-ms``, one more replay pauses that long before each handler call (a sleep, or a
busy wait with ``--pause-kind spin``), as the daemon's paced wake-ups do: the difference
from the back-to-back figure is what the pause alone costs the next call (issue 15, stop
73: caches gone cold on this machine, whatever the thread did meanwhile). Prints one JSON
object.

    .venv/bin/python -m mowerhw bench --duration 40 --record /tmp/b.mcap
    .venv/bin/python tools/bench_core_replay.py /tmp/b.mcap --pause-ms 5
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


def pause(seconds: float, kind: str) -> None:
    """Wait ``seconds``: asleep (``sleep``) or busy on this thread (``spin``)."""
    if kind == "spin":
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            pass
    else:
        time.sleep(seconds)


def timed(
    name: str,
    fn: Callable[..., Any],
    spent: dict[str, list[float]],
    before: Callable[[], None] | None = None,
) -> Callable[..., Any]:
    """``fn`` with its thread CPU time added to ``spent[name]`` (seconds, calls); ``before``
    runs ahead of each call, outside the time."""

    def call(*args: Any, **kwargs: Any) -> Any:
        if before is not None:
            before()
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            cell = spent[name]
            cell[0] += time.thread_time() - t0
            cell[1] += 1

    return call


def _replay_timed(
    recording: Path, before: Callable[[], None] | None = None
) -> tuple[dict[str, list[float]], dict[str, Any]]:
    """One replay of ``recording`` with the handlers timed: (seconds, calls) per handler and
    the replay's summary (the core's handlers are restored afterwards)."""
    originals = {name: getattr(RuntimeCore, name) for name in HANDLERS}
    spent: dict[str, list[float]] = {name: [0.0, 0] for name in HANDLERS}
    try:
        for name, fn in originals.items():
            setattr(RuntimeCore, name, timed(name, fn, spent, before))
        return spent, replay_decisions(recording)
    finally:
        for name, fn in originals.items():
            setattr(RuntimeCore, name, fn)


def _per_call_us(spent: dict[str, list[float]]) -> dict[str, float]:
    return {name: round(s / n * 1e6, 1) for name, (s, n) in spent.items() if n}


def measure(
    recording: Path, repeat: int = 3, pause_ms: float = 0.0, pause_kind: str = "sleep"
) -> dict[str, Any]:
    """The handlers' best time per call over ``repeat`` back-to-back replays of
    ``recording`` and the replayed decisions; with ``pause_ms``, also their time per call in
    one replay that pauses before each call."""
    best: dict[str, float] = {}
    calls: dict[str, int] = {}
    result: dict[str, Any] = {}
    for _ in range(max(1, repeat)):
        spent, result = _replay_timed(recording)
        for name, us in _per_call_us(spent).items():
            calls[name] = int(spent[name][1])
            best[name] = min(best.get(name, us), us)
    out: dict[str, Any] = {
        "recording": str(recording),
        "repeats": max(1, repeat),
        "handlers_us_per_call_best": best,
        "calls": calls,
        "decisions": result.get("decisions"),
        "same_as_live": result.get("same_as_live"),
        "replay_sha256": result.get("replay_sha256"),
    }
    if pause_ms > 0:
        spent, paused = _replay_timed(recording, lambda: pause(pause_ms / 1e3, pause_kind))
        out["after_pause"] = {
            "pause_ms": pause_ms,
            "pause_kind": pause_kind,
            "handlers_us_per_call": _per_call_us(spent),
            "same_as_live": paused.get("same_as_live"),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path, help="an MCAP recording with the runtime journal")
    ap.add_argument("--repeat", type=int, default=3, help="replays; the best time is kept")
    ap.add_argument(
        "--pause-ms", type=float, default=0.0, help="one more replay, pausing before each call"
    )
    ap.add_argument("--pause-kind", choices=("sleep", "spin"), default="sleep")
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # the replayed gate's halts are in the summary
    report = measure(args.recording, args.repeat, args.pause_ms, args.pause_kind)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
