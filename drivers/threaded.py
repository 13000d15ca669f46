"""The one start/stop-a-thread shape every device and mock shares."""

from __future__ import annotations

import threading


class ThreadedDevice:
    """A device whose loop (:meth:`_run`) runs on its own daemon thread until :meth:`stop`.
    ``_run`` polls ``self._stop`` (an Event: ``self._stop.wait(dt)`` sleeps interruptibly)."""

    thread_name = "device"
    join_timeout_s = 2.0

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _start_thread(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.join_timeout_s)

    def _run(self) -> None:
        raise NotImplementedError
