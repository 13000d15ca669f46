"""Waiting on a few file descriptors from one ``select.poll`` kept between waits.

``multiprocessing.connection.wait`` and ``Connection.poll`` build a selector, register every
descriptor and tear it down again on each call: Python work that a process waking 50 times a
second pays every time, and from a cold wake-up about ten times what it costs warm (README,
issue 15, stop 67: ``Connection.poll(0)`` 95 µs against 29 µs for one ``poll`` system call).
Here the descriptors are registered once; a wait is one system call. Readable, hung up or in
error all count as ready, as for ``wait`` (the reader then finds out which).
"""

from __future__ import annotations

import math
import select
from collections.abc import Iterable


class FdWaiter:
    """The descriptors ``fds`` (fixed), and at most one more that may change between waits
    (a listening socket that is not always listened on), ready for reading — or, with
    ``events=select.POLLOUT``, for writing (a pipe with room)."""

    def __init__(self, fds: Iterable[int], events: int = select.POLLIN) -> None:
        self._events = events
        self._poll = select.poll()
        for fd in fds:
            self._poll.register(fd, events)
        self._extra: int | None = None

    def wait(self, timeout_s: float, extra: int | None = None) -> set[int]:
        """The ready descriptors, waiting at most ``timeout_s`` (rounded up to the
        millisecond, as ``wait`` does; 0: not at all) for one."""
        if extra != self._extra:
            if self._extra is not None:
                self._poll.unregister(self._extra)
            if extra is not None:
                self._poll.register(extra, self._events)
            self._extra = extra
        return {fd for fd, _ in self._poll.poll(math.ceil(max(0.0, timeout_s) * 1e3))}

    def ready_now(self) -> bool:
        """Whether any is ready, without waiting."""
        return bool(self._poll.poll(0))
