"""Daemon benchmarks on the hardware-in-the-loop bench (prints one JSON object).

* halt latency under load: while the front end tracks every frame, the ground-speed sensor
  goes quiet for 0.6 s every ``--halt-every`` seconds (each time the daemon must halt); and
  every mow-phase halt (OUTSIDE at the edge, …) counts too. Latency = arrival of the
  revealing sample (or the staleness deadline) → the ISB stop frame sent, from the daemon;
* the permit supervisor: lease → frame latency, loop stalls over 20 ms, leases that ran out
  (spurious ESTIMATOR_LATE halts when the machine is loaded: ``--load N`` CPU hogs; those
  while mowing, from its log: ``supervisor_lease_halts``);
* CPU share of the daemon's processes at real-time rates (50 Hz Δθ/Δv IMU, 10 Hz speed, 4 Hz
  1540×1540 frames), from /proc;
* memory: the daemon's RSS every 10 s (a soak: ``--duration 3600``).

    .venv/bin/python tools/bench_daemon.py --duration 600 --halt-every 20

A trade-off is measured with ``--config``: e.g. the VN-100 at 25 Hz (``imu.rate_hz``), what
a slower computer could run (README, issue 15, stop 67).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from mowerhw.bench import Bench, FaultSpec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=300.0, help="seconds of mowing")
    ap.add_argument("--halt-every", type=float, default=20.0, help="seconds between speed gaps")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--map", type=Path, help="a map of the yard (default: pixel-level sim teach)")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--load", type=int, default=0, help="CPU hogs beside the daemon")
    ap.add_argument(
        "--config",
        type=Path,
        help="run the daemon with this config's rates, limits and thresholds (default: "
        "configs/bench.yaml); the bench's mock devices, bus and files replace its own",
    )
    args = ap.parse_args()
    map_path = args.map
    if map_path is None:
        from mowerhw.evaluation.pixel import run_teach_pixel
        from mowerhw.map import LawnMap

        res = run_teach_pixel("paper", args.seed)
        map_path = Path(tempfile.mkdtemp(prefix="mowerhw-map-")) / "lawn.json"
        LawnMap.from_teach_result(res.result).save(map_path)
    n = int(args.duration // args.halt_every)
    faults = [FaultSpec("speed-stop", args.halt_every * (k + 0.5), 0.6) for k in range(n)]
    bench = Bench(
        duration_s=args.duration,
        seed=args.seed,
        out_dir=args.out,
        faults=faults,
        map_path=map_path,
        load=args.load,
        config_path=args.config,
    )
    r = bench.run()
    mowing_log = _lines_between(bench.daemon_log, bench.mow_start[1], bench.mow_end[1])
    stops = [f["stop_after_ms"] for f in r.get("faults", []) if f["stop_after_ms"] is not None]
    out = {
        "mow_s": r["mow_s"],
        "halt_latency_ms": r["halt_latency_ms"],
        "halts_by_reason": r["halts_by_reason"],
        "speed_gaps": len(faults),
        "speed_gap_stop_seen_ms": {
            "min": min(stops) if stops else None,
            "max": max(stops) if stops else None,
            "n": len(stops),
        },
        "cpu_percent_of_one_core": r["cpu_percent"],
        "peak_rss_mb": r["peak_rss_mb"],
        "rss_mb_over_time": bench.rss_samples,
        "missed_halts": r["missed_halts"],
        "false_halt_fraction": r["false_halt_fraction"],
        "supervisor": r.get("supervisor"),
        "watchdog": r.get("watchdog"),
        "mock_imu": r.get("mock_imu"),
        "daemon_imu_silent_halts": _imu_silent_halts(mowing_log),
        # the "spurious halts" while mowing, of each kind: the estimation side's
        # (false_halt_fraction, "imu silent") and the supervisor's own (a lease ran out)
        "supervisor_lease_halts": _lease_halts(mowing_log),
        "daemon_imu_gaps": _imu_gaps(mowing_log),
        "load_processes": args.load,
        "position_rmse_m": r["position_rmse_m"],
    }
    print(json.dumps(out, indent=1))


def _lines_between(log_path: Path, from_wall: float, until_wall: float) -> list[str] | None:
    """The daemon log's lines stamped from ``from_wall`` to ``until_wall`` (time.time(), to
    the log's millisecond: its ``asctime`` is local time); None if the log cannot be read.
    The mowing's lines: not the start-up's (a supervisor waiting for its first lease says
    so), not the scoring's after it."""
    try:
        lines = log_path.read_text(errors="replace").splitlines()
    except OSError:
        return None
    out = []
    for line in lines:
        try:
            stamp = time.mktime(time.strptime(line[:19], "%Y-%m-%d %H:%M:%S"))
            stamp += float(line[20:23]) / 1e3
        except ValueError:
            continue
        if from_wall - 1e-3 <= stamp <= until_wall:
            out.append(line)
    return out


def _lines_saying(lines: list[str] | None, text: str) -> int:
    """How many of the log's ``lines`` contain ``text`` (-1: no log to read)."""
    if lines is None:
        return -1
    return sum(1 for line in lines if text in line)


def _imu_silent_halts(lines: list[str] | None) -> int:
    """Halts the estimation side gave while mowing because no IMU sample had arrived for its
    limit (-1: no log to read)."""
    return _lines_saying(lines, "mowerhw.permit: HALT SENSOR_STALE: imu silent")


def _lease_halts(lines: list[str] | None) -> int:
    """Halts the permit supervisor gave while mowing because the estimation side's lease ran
    out (the estimator late: under ``--load``, spurious; -1: no log to read)."""
    return _lines_saying(lines, "supervisor: HALT ESTIMATOR_LATE: no permit lease")


def _imu_gaps(lines: list[str] | None) -> dict[str, int]:
    """The daemon's IMU silences past its limit while mowing, by where the sensor's own clock
    puts them: ``sensor`` (it was silent: the mock VN-100 sent late), ``host`` (it sent on
    time and the samples were held up on the way: the mock's own write, the kernel, the
    daemon's computer — ``mock_imu.late_writes_over_50ms_while_mowing`` says how many of
    them the mock wrote late; ``host_in_the_daemon``: those of them where the daemon itself
    went without a decision for half the gap or more), empty without a log."""
    if lines is None:
        return {}
    gaps = [line for line in lines if "imu: a sample again" in line]
    return {
        "sensor": sum("the sensor itself was silent" in line for line in gaps),
        "host": sum("held up on this computer" in line for line in gaps),
        "host_in_the_daemon": sum("in this daemon" in line for line in gaps),
        "unknown": sum("the sensor sends no time" in line for line in gaps),
    }


if __name__ == "__main__":
    main()
