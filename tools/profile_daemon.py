"""Where the daemon's CPU goes: a bench run, and py-spy sampling the daemon's processes (the
permit supervisor, the estimation process and its front-end worker, every thread) while it
mows; each sample is put in the part of the runtime it belongs to. Prints one JSON object:
per process, the share of one core per part (samples / (rate × seconds)) and per thread
(/proc: user and system time, so what py-spy cannot see — system calls, native waits — is
counted too); and for the estimation process's event loop, each handler's own CPU clock
over the same window (``handler_cpu`` of the daemon's status: exact, where sampling misses
most of the short callbacks the loop runs 50 times a second).

    .venv/bin/python tools/profile_daemon.py --map MAP --duration 60 --spy 30

Needs ``py-spy`` (pip) and permission to read the processes (ptrace).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

#: the first matching frame (innermost last) names the part a sample belongs to
PARTS = (
    ("front end: ORB descriptors", "OrbDescriber.describe"),
    ("front end: KLT tracking", "FrontEnd._track"),
    ("front end: detection", "FrontEnd._detect"),
    ("front end: other", "FrontEnd.process"),
    ("vision: association + localizer update", "MowVision.use"),
    ("localizer: IMU propagation", "Localizer.imu"),
    ("core: decisions", "RuntimeCore._decide"),
    ("core: other", "RuntimeCore."),
    ("VN-100 reading and parsing", "Vn100._readable"),
    ("VN-100 reading and parsing", "Vn100._run"),
    ("camera stream", "StreamCamera"),
    ("supervisor: leases and frames", "Supervisor._decide"),
    ("supervisor: lease messages", "Supervisor._drain"),
    ("supervisor: CAN receive", "Supervisor._receive"),
    ("link to the supervisor", "SupervisorLink."),
    ("recording", "Recorder."),
    ("event loop, other", "BaseEventLoop"),
)


#: a sample whose innermost frame is one of these is a thread waiting, not working (py-spy
#: without --native cannot always tell)
IDLE_LEAVES = (
    "EpollSelector.select",
    "Condition.wait",
    "Event.wait",
    "_worker (concurrent/futures/thread.py:81)",
    "Connection.recv",
    "Connection._recv",
    "_poll",
    "wait (multiprocessing/connection.py",
    "select (selectors.py",
    "Vn100._read_available",  # select() on the serial port, natively
)


def part_of(stack: str) -> str:
    for name, marker in PARTS:
        if marker in stack:
            return name
    return "other"


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return out


def thread_times(pid: int) -> dict[int, tuple[float, float, float]]:
    """User and system CPU seconds and the times it went to sleep (voluntary context
    switches: each is a wake-up later) of every thread of ``pid`` (/proc/PID/task/TID)."""
    tick = float(os.sysconf("SC_CLK_TCK"))
    out = {}
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            fields = (task / "stat").read_text().rpartition(")")[2].split()
        except OSError:
            continue
        try:
            status = (task / "status").read_text()
            wakes = float(status.split("voluntary_ctxt_switches:")[1].split()[0])
        except (OSError, IndexError, ValueError):
            wakes = 0.0
        out[int(task.name)] = (int(fields[11]) / tick, int(fields[12]) / tick, wakes)
    return out


def thread_names(pid: int) -> dict[int, str]:
    """Native thread id → Python thread name (``py-spy dump --json``)."""
    try:
        raw = subprocess.run(
            ["py-spy", "dump", "--json", "--nonblocking", "-p", str(pid)],
            capture_output=True,
            timeout=20,
            check=True,
        ).stdout
        return {int(t["os_thread_id"]): str(t["thread_name"]) for t in json.loads(raw)}
    except (subprocess.SubprocessError, ValueError, KeyError, TypeError):
        return {}


def per_thread(
    before: dict[int, tuple[float, float, float]],
    after: dict[int, tuple[float, float, float]],
    names: dict[int, str],
    seconds: float,
) -> dict[str, dict[str, float]]:
    """Share of one core per thread over the window, user and system apart, and its
    wake-ups a second (on a machine whose caches go cold between wake-ups, each costs
    far more than the work it does: measured here, 41 µs of VN-100 parsing back to back
    took 370 µs 10 ms after the last)."""
    out: dict[str, dict[str, float]] = {}
    for tid, (user, system, wakes) in after.items():
        u0, s0, w0 = before.get(tid, (0.0, 0.0, 0.0))
        user_pct, sys_pct = 100 * (user - u0) / seconds, 100 * (system - s0) / seconds
        if user_pct + sys_pct < 0.05:
            continue
        out[f"{names.get(tid, 'thread')} ({tid})"] = {
            "user": round(user_pct, 1),
            "system": round(sys_pct, 1),
            "wakeups_per_s": round((wakes - w0) / seconds, 1),
        }
    return dict(sorted(out.items(), key=lambda kv: -(kv[1]["user"] + kv[1]["system"])))


def spy(pid: int, seconds: float, rate: int, path: Path) -> subprocess.Popen[bytes]:
    cmd = ["py-spy", "record", "--format", "raw", "-o", str(path), "-d", str(int(seconds))]
    cmd += ["-r", str(rate), "-p", str(pid), "--nonblocking"]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def summarise(path: Path, seconds: float, rate: int) -> dict[str, Any]:
    parts: Counter[str] = Counter()
    total = 0
    for line in path.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        if not n.isdigit():
            continue
        leaf = stack.rsplit(";", 1)[-1]
        if any(marker in leaf for marker in IDLE_LEAVES):
            continue
        parts[part_of(stack)] += int(n)
        total += int(n)
    scale = 100.0 / (rate * seconds)
    return {
        "cpu_percent_of_one_core": round(total * scale, 1),
        "by_part_percent_of_one_core": {k: round(v * scale, 1) for k, v in parts.most_common()},
    }


def handler_shares(before: dict[str, Any], after: dict[str, Any], seconds: float) -> dict[str, Any]:
    """The estimation loop's handlers between two snapshots of the daemon's status
    (``handler_cpu``, and the VN-100 driver's ``loop_read_cpu_s``): per handler, its share of
    one core, calls a second and CPU per call; the VN-100's reading and parsing around its
    sample handler; the loop thread's own share, and what of it neither holds (the loop,
    its tasks, the control socket)."""
    c0, c1 = before.get("handler_cpu", {}), after.get("handler_cpu", {})
    h0, h1 = c0.get("handlers", {}), c1.get("handlers", {})
    out: dict[str, dict[str, float]] = {}
    cpu_of: dict[str, float] = {}
    for name, now in h1.items():
        was = h0.get(name, {"calls": 0, "cpu_s": 0.0})
        calls, cpu = now["calls"] - was["calls"], now["cpu_s"] - was["cpu_s"]
        if calls <= 0:
            continue
        cpu_of[name] = cpu
        out[name] = {
            "percent_of_one_core": round(100 * cpu / seconds, 2),
            "calls_per_s": round(calls / seconds, 1),
            "us_per_call": round(1e6 * cpu / calls, 1),
        }
    loop_cpu = c1.get("loop_thread_cpu_s", 0.0) - c0.get("loop_thread_cpu_s", 0.0)
    d0, d1 = before.get("imu_driver", {}), after.get("imu_driver", {})
    reads = d1.get("loop_read_cpu_s", 0.0) - d0.get("loop_read_cpu_s", 0.0)
    # the sample handler runs inside the read
    parsing = max(0.0, reads - cpu_of.get("IMU sample", 0.0))
    return {
        "loop_thread_percent_of_one_core": round(100 * loop_cpu / seconds, 2),
        "vn100_reading_and_parsing_percent": round(100 * parsing / seconds, 2),
        "outside_the_handlers_percent": round(
            100 * (loop_cpu - sum(cpu_of.values()) - parsing) / seconds, 2
        ),
        "handlers": dict(sorted(out.items(), key=lambda kv: -kv[1]["percent_of_one_core"])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--map", type=Path, required=True, help="a map of the yard (sim teach)")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of mowing")
    ap.add_argument("--spy", type=float, default=30.0, help="seconds of sampling while mowing")
    ap.add_argument("--rate", type=int, default=100, help="samples per second")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    if shutil.which("py-spy") is None:
        raise SystemExit("profile_daemon: needs py-spy (pip install py-spy)")
    from mowerhw.bench import Bench
    from mowerhw.runtime.control_protocol import request

    out = Path(tempfile.mkdtemp(prefix="mowerhw-profile-"))
    bench = Bench(duration_s=args.duration, seed=args.seed, out_dir=out, map_path=args.map)
    found: dict[str, Path] = {}
    threads: dict[str, dict[str, dict[str, float]]] = {}
    handlers: dict[str, Any] = {}

    def sample() -> None:
        while bench.proc is None:
            time.sleep(0.2)
        time.sleep(15.0)  # start-up, localization, the first permit
        sup = bench.proc.pid
        procs = {"supervisor": sup}
        for kid in children(sup):  # not the multiprocessing resource tracker
            if b"spawn_main" in Path(f"/proc/{kid}/cmdline").read_bytes():
                procs["estimation"] = kid
                for grandkid in children(kid):  # the front end's process, if it has one
                    if b"frontend_worker" in Path(f"/proc/{grandkid}/cmdline").read_bytes():
                        procs["frontend"] = grandkid
        names = {pid: thread_names(pid) for pid in procs.values()}
        cpu0 = request(bench.sock, "status", timeout=5.0)
        before = {pid: thread_times(pid) for pid in procs.values()}
        t0 = time.monotonic()
        spies = []
        for name, pid in procs.items():
            found[name] = out / f"{name}.txt"
            spies.append(spy(pid, args.spy, args.rate, found[name]))
        for s in spies:
            s.wait()
        seconds = time.monotonic() - t0
        for name, pid in procs.items():
            threads[name] = per_thread(before[pid], thread_times(pid), names[pid], seconds)
        cpu1 = request(bench.sock, "status", timeout=5.0)
        handlers.update(handler_shares(cpu0, cpu1, time.monotonic() - t0))

    t = threading.Thread(target=sample, daemon=True)
    t.start()
    r = bench.run()
    t.join(timeout=5.0)
    result: dict[str, Any] = {
        "bench_cpu_percent_all_processes": r["cpu_percent"],
        "peak_rss_mb_all_processes": r["peak_rss_mb"],
        "sampled_s": args.spy,
    }
    for name, path in found.items():
        if path.exists():
            result[name] = summarise(path, args.spy, args.rate)
            result[name]["threads_percent_of_one_core"] = threads.get(name, {})
    if handlers:
        result["estimation_loop_handlers"] = handlers
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
