#!/usr/bin/env python3
"""Attack the control socket of a mowing bench (issue 16) and measure what it costs the
control loop. Prints one JSON object.

Starts ``mowerhw bench --map MAP`` with a ground-speed gap every ``--halt-every`` s (so the
deck must halt, and the halt latency can be measured while the socket is under attack),
waits until it mows, then runs one phase after another, ``--phase-s`` each:

* ``baseline``: nothing but the well-behaved client;
* ``pipelining``: 4 clients writing thousands of requests per write (``status``, empty
  lines, unknown words), two of which never read a reply;
* ``idle``: 1,100 connections opened and held open;
* ``nested``: clients sending deeply nested and oversized JSON, over and over;
* ``all``: the three at once;
* ``supervisor``: the permit supervisor's status socket (``control.sock.supervisor``, served
  by its own loop at real-time priority) flooded: 4 clients connecting as fast as they can,
  two of which never read.

A well-behaved client asks for the status every 0.25 s throughout: its answer times, and
the halt latencies and event-loop lags the daemon reports, are sorted into the phases. The
bench's own JSON (deck stops, missed halts, the watchdog pings as systemd would see them,
the supervisor's figures) is included.

    .venv/bin/python tools/attack_control.py --map MAP [--phase-s 20]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import resource
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

PHASES = ("baseline", "pipelining", "idle", "nested", "all", "supervisor")


def _percentiles(values: list[float]) -> dict[str, float | int | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    a = np.asarray(values)
    return {
        "p50": round(float(np.percentile(a, 50)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
        "n": int(a.size),
    }


def _connect(path: Path, timeout: float = 5.0) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    s.connect(str(path))
    return s


class Attack:
    """The attackers of one phase: threads that run until :meth:`stop`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.connections = 0
        self.stop_event = threading.Event()
        self.threads: list[threading.Thread] = []
        self.held: list[socket.socket] = []
        self.sent_bytes = 0
        self.errors = 0

    def start(self, kind: str) -> None:
        if kind in ("pipelining", "all"):
            for k in range(4):
                self._thread(self._pipeline, reads=k < 2)
        if kind in ("idle", "all"):
            self._thread(self._idle)
        if kind in ("nested", "all"):
            for _ in range(2):
                self._thread(self._nested)
        if kind == "supervisor":
            for k in range(4):
                self._thread(self._flood_supervisor, reads=k < 2)

    def _thread(self, fn: Any, **kw: Any) -> None:
        t = threading.Thread(target=fn, kwargs=kw, daemon=True)
        t.start()
        self.threads.append(t)

    def _pipeline(self, reads: bool) -> None:
        burst = (b"status\n" * 3000) + (b"\n" * 3000) + (b"explode now\n" * 1000)
        while not self.stop_event.is_set():
            try:
                s = _connect(self.path, timeout=1.0)
            except OSError:
                self.errors += 1
                time.sleep(0.05)
                continue
            if reads:  # drain the replies so the socket keeps flowing
                threading.Thread(target=_drain, args=(s, self.stop_event), daemon=True).start()
            try:
                while not self.stop_event.is_set():
                    s.sendall(burst)
                    self.sent_bytes += len(burst)
            except OSError:  # the daemon closed it (a reply timed out, the line limit)
                self.errors += 1
            finally:
                s.close()

    def _idle(self) -> None:
        for _ in range(1100):
            if self.stop_event.is_set():
                break
            try:
                self.held.append(_connect(self.path, timeout=1.0))
            except OSError:
                self.errors += 1
        self.stop_event.wait()

    def _nested(self) -> None:
        attacks = [
            b'{"cmd": "status", "x": ' + b"[" * 4000 + b"]" * 4000 + b"}\n",
            b"[" * 3000 + b"\n",
            b'{"cmd":"status","cmd":"mow"}\n',
            b"x" * 70_000,
        ]
        while not self.stop_event.is_set():
            try:
                s = _connect(self.path, timeout=1.0)
                threading.Thread(target=_drain, args=(s, self.stop_event), daemon=True).start()
                for a in attacks * 20:
                    s.sendall(a)
                    self.sent_bytes += len(a)
                s.close()
            except OSError:
                self.errors += 1
                time.sleep(0.01)

    def _flood_supervisor(self, reads: bool) -> None:
        from mowerhw.common.supervisor_socket import supervisor_socket

        path = supervisor_socket(self.path)
        while not self.stop_event.is_set():
            try:
                with _connect(path, timeout=1.0) as s:
                    self.connections += 1
                    s.sendall(b"status\n" * 100)  # it reads nothing: ignored
                    if reads:
                        s.recv(65536)
            except OSError:
                self.errors += 1

    def stop(self) -> dict[str, int]:
        self.stop_event.set()
        for t in self.threads:
            t.join(5.0)
        for s in self.held:
            with contextlib.suppress(OSError):
                s.close()
        return {
            "sent_bytes": self.sent_bytes,
            "held_connections": len(self.held),
            "connections": self.connections,
            "errors": self.errors,
        }


def _drain(s: socket.socket, stop: threading.Event) -> None:
    try:
        s.settimeout(0.5)
    except OSError:  # closed already
        return
    while not stop.is_set():
        try:
            if not s.recv(65536):
                return
        except TimeoutError:
            continue
        except OSError:
            return


class GoodClient(threading.Thread):
    """Asks for the status every 0.25 s; keeps every answer and how long it took."""

    def __init__(self, path: Path) -> None:
        super().__init__(daemon=True)
        self.path = path
        self.answers: list[tuple[float, float, dict[str, Any] | None]] = []
        self.stop_event = threading.Event()

    def run(self) -> None:
        while not self.stop_event.wait(0.25):
            t0 = time.monotonic()
            try:
                with _connect(self.path, timeout=5.0) as s:
                    s.sendall(b'{"cmd": "status"}\n')
                    buf = b""
                    while not buf.endswith(b"\n"):
                        chunk = s.recv(1 << 20)
                        if not chunk:
                            break
                        buf += chunk
                reply = json.loads(buf) if buf else None
            except (OSError, ValueError):
                reply = None
            self.answers.append((t0, (time.monotonic() - t0) * 1e3, reply))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", type=Path, required=True, help="a map of the bench's yard")
    ap.add_argument("--phase-s", type=float, default=20.0)
    ap.add_argument("--halt-every", type=float, default=5.0)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    with contextlib.suppress(ValueError, OSError):  # 1,100 connections need the descriptors
        resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, 4096)), hard))
    out = args.out or Path(tempfile.mkdtemp(prefix="attack-"))
    mow_s = args.phase_s * len(PHASES) + 15.0
    cmd = [sys.executable, "-m", "mowerhw", "bench", "--map", str(args.map), "--json"]
    cmd += ["--duration", str(mow_s), "--out", str(out)]
    t = args.halt_every
    while t < mow_s - 2:
        cmd += ["--fault", f"speed-stop@{t:.1f}:1"]
        t += args.halt_every
    bench = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    sock = out / "control.sock"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        with contextlib.suppress(Exception):
            from mowerhw.runtime.control_protocol import request

            if request(sock, "status", timeout=2.0).get("mode") == "mow":
                break
        time.sleep(0.5)
    else:
        bench.kill()
        raise SystemExit("attack_control: the bench did not start mowing")
    time.sleep(5.0)  # localized and permitted
    good = GoodClient(sock)
    good.start()
    spans: dict[str, tuple[float, float]] = {}
    attackers: dict[str, dict[str, int]] = {}
    for phase in PHASES:
        attack = Attack(sock)
        t0 = time.monotonic()
        if phase != "baseline":
            attack.start(phase)
        time.sleep(args.phase_s)
        attackers[phase] = attack.stop()
        spans[phase] = (t0, time.monotonic())
        time.sleep(1.0)
    good.stop_event.set()
    good.join(10.0)
    stdout, _ = bench.communicate(timeout=600)
    try:
        bench_json = json.loads(stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        bench_json = {"error": "no JSON from the bench", "tail": stdout[-500:]}
    halts: dict[tuple[str, float], float] = {}
    lags: list[tuple[float, float]] = []
    for _, _, reply in good.answers:
        if reply and reply.get("ok"):
            for h in reply.get("halt_latencies", []):
                halts[(h["reason"], h["t"])] = h["latency_ms"]
            lags += list(
                zip(
                    reply.get("loop_lag_times", []),
                    reply.get("loop_lag_ms_over_5", []),
                    strict=False,
                )
            )
    result: dict[str, Any] = {"phase_s": args.phase_s, "phases": {}}
    for phase, (a, b) in spans.items():
        answers = [(ms, r) for t0, ms, r in good.answers if a <= t0 <= b]
        in_phase = [ms for (_, t), ms in halts.items() if a <= t <= b]
        # the supervisor's own figures (counted since it started) at the phase's end
        sup = next(
            (r.get("supervisor") or {} for _, r in reversed(answers) if r and r.get("ok")), {}
        )
        result["phases"][phase] = {
            "halt_latency_ms": _percentiles(in_phase),
            "supervisor_at_end": {
                k: sup.get(k)
                for k in (
                    "max_loop_lag_ms",
                    "loop_stalls_over_20ms",
                    "lease_expired",
                    "status_socket",
                )
            },
            "status_answer_ms": _percentiles([ms for ms, r in answers if r and r.get("ok")]),
            "status_refused_or_failed": sum(1 for _, r in answers if not (r and r.get("ok"))),
            "daemon_loop_lag_over_5ms_max": max(
                (lag for t, lag in lags if a <= t <= b), default=0.0
            ),
            "attackers": attackers[phase],
        }
    last = next((r for _, _, r in reversed(good.answers) if r and r.get("ok")), {})
    result["control_status"] = last.get("control", {})
    result["bench"] = {
        k: bench_json.get(k)
        for k in (
            "missed_halts",
            "false_halt_fraction",
            "halt_latency_ms",
            "halts_by_reason",
            "permit_gaps",
            "watchdog",
            "supervisor",
            "cpu_percent",
            "daemon_restarts",
            "mow_s",
            "error",
        )
        if k in bench_json
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
