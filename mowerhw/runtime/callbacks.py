"""How device callbacks reach the daemon's event loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

log = logging.getLogger("mowerhw.daemon")


def threadsafe(loop: asyncio.AbstractEventLoop, fn: Callable[[Any], None]) -> Callable[[Any], None]:
    """``fn`` called on ``loop``, from a device thread."""

    def call(arg: Any) -> None:
        with contextlib.suppress(RuntimeError):  # the loop is closing
            loop.call_soon_threadsafe(fn, arg)

    return call


def crash_only(
    fn: Callable[[Any], None], name: str, failed: Callable[[str], None]
) -> Callable[[Any], None]:
    """``fn`` as a loop callback that, if it raises, logs it and calls ``failed`` with why
    (the daemon halts and ends the process, as for a task that dies: asyncio would only log
    an exception in a callback and go on)."""

    def call(arg: Any) -> None:
        try:
            fn(arg)
        except Exception as exc:
            log.exception("the %s handler failed: halting and ending the process", name)
            failed(f"the {name} handler failed ({exc!r})")

    return call
