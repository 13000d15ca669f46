"""How device callbacks reach the daemon's event loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger("mowerhw.daemon")


class HandlerCosts:
    """The CPU time each of the event loop's handlers used, by name: what an IMU sample, a
    frame's estimation or a decision costs on this computer (``mowerhw ctl status`` →
    ``handler_cpu``). Counted with ``time.thread_time`` around each call — the loop
    thread's own CPU, not what it waited for — which a sampling profiler cannot give:
    sampling misses most of the short callbacks the loop runs at 50 Hz (on the bench,
    py-spy saw 1.6 % of a core on the IMU path, the clocks of its reads and handler 4.0 %).
    Two snapshots a known time apart give each handler's share of a core in between."""

    def __init__(self) -> None:
        self._calls: dict[str, int] = {}
        self._cpu_s: dict[str, float] = {}

    def add(self, name: str, cpu_s: float) -> None:
        self._calls[name] = self._calls.get(name, 0) + 1
        self._cpu_s[name] = self._cpu_s.get(name, 0.0) + cpu_s

    def status(self) -> dict[str, Any]:
        """Per handler: calls and CPU seconds so far, and the mean per call (µs); and the
        loop thread's own CPU seconds so far (call it on the loop thread): what is not in a
        handler is the loop itself, its tasks and the control socket."""
        out: dict[str, Any] = {
            name: {
                "calls": n,
                "cpu_s": round(self._cpu_s[name], 6),
                "us_per_call": round(1e6 * self._cpu_s[name] / n, 1),
            }
            for name, n in sorted(self._calls.items())
        }
        return {"loop_thread_cpu_s": round(time.thread_time(), 6), "handlers": out}


def threadsafe(loop: asyncio.AbstractEventLoop, fn: Callable[[Any], None]) -> Callable[[Any], None]:
    """``fn`` called on ``loop``: from a device thread through ``call_soon_threadsafe``, at
    once when called on the loop itself (a reader the loop polls before a decision: what it
    read is in that decision)."""

    def call(arg: Any) -> None:
        try:
            on_the_loop = asyncio.get_running_loop() is loop
        except RuntimeError:  # a device thread: no loop of its own
            on_the_loop = False
        if on_the_loop:
            fn(arg)
            return
        with contextlib.suppress(RuntimeError):  # the loop is closing
            loop.call_soon_threadsafe(fn, arg)

    return call


def crash_only(
    fn: Callable[[Any], None],
    name: str,
    failed: Callable[[str], None],
    costs: HandlerCosts | None = None,
) -> Callable[[Any], None]:
    """``fn`` as a loop callback that, if it raises, logs it and calls ``failed`` with why
    (the daemon halts and ends the process, as for a task that dies: asyncio would only log
    an exception in a callback and go on); with ``costs``, its CPU time is counted there
    under ``name``."""

    def call(arg: Any) -> None:
        started = time.thread_time() if costs is not None else 0.0
        try:
            fn(arg)
        except Exception as exc:
            log.exception("the %s handler failed: halting and ending the process", name)
            failed(f"the {name} handler failed ({exc!r})")
        finally:
            if costs is not None:
                costs.add(name, time.thread_time() - started)

    return call
