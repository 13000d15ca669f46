"""Process settings for the daemon: what keeps a Python process's pauses short."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import signal
import sys
import time
from pathlib import Path

from mowerhw.config import Config

log = logging.getLogger("mowerhw.daemon")


_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 0.01


def cpu_seconds(pid: int) -> float | None:
    """CPU time (user + system) process ``pid`` has used, from ``/proc`` (None where it
    cannot be read, or it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) * _TICK_S  # utime, stime (fields 14, 15)
    except (OSError, IndexError, ValueError):
        return None


def die_with_parent() -> None:
    """Linux: kill this process when its parent dies (even by SIGKILL): the estimation
    process without its supervisor can permit nothing, the front-end worker without the
    estimation process serves no one."""
    with contextlib.suppress(Exception):
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def tune_process() -> None:
    """Short GIL switches, one OpenCV thread, start-up objects out of the collector's way,
    and a warning for every garbage collection long enough to stall the event loop."""
    import cv2

    # a front end on a thread (runtime.frontend_process false) must not hold the GIL for
    # 5 ms; with it in its own process this costs nothing measurable (stop 41, side by side)
    sys.setswitchinterval(0.001)
    cv2.setNumThreads(1)  # one frame at a time on one worker; OpenCV's pool would spin
    gc.collect()
    gc.freeze()  # the start-up objects (modules, config) are never scanned by a full collection
    started = [0.0]

    def gc_watch(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            started[0] = time.perf_counter()
        elif (ms := (time.perf_counter() - started[0]) * 1e3) > 20.0:
            log.warning("garbage collection (generation %d) took %.0f ms", info["generation"], ms)

    gc.callbacks.append(gc_watch)


class LoopLag:
    """How late the event loop's ticker woke (the loop was busy): kept for the status,
    logged when it is long enough to matter."""

    def __init__(self, keep: int = 200) -> None:
        self.keep = keep
        self.lags_ms: list[float] = []
        self.lag_times: list[float] = []  # time.monotonic() of each

    def woke(self, due: float, now: float) -> None:
        lag = (now - due) * 1e3
        if lag > 5.0:
            self.lags_ms.append(round(lag, 1))
            self.lag_times.append(round(now, 3))
            del self.lags_ms[: -self.keep]
            del self.lag_times[: -self.keep]
            if lag > 50.0:
                log.warning("event loop was blocked for %.0f ms", lag)


def run_daemon(
    config: Config,
    mode: str | None = None,
    record: str | Path | None = None,
    duration_s: float | None = None,
) -> int:
    """Run until stopped; the exit status (0 after a clean stop)."""
    from mowerhw.runtime.daemon import Daemon

    tune_process()
    daemon = Daemon(config, mode, record)

    async def main() -> int:
        if duration_s is not None:
            asyncio.get_running_loop().call_later(duration_s, daemon.request_stop, "duration")
        return await daemon.run()

    return asyncio.run(main())
