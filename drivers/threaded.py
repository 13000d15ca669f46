"""The one start/stop-a-thread shape every device and mock shares."""

from __future__ import annotations

import os
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

    def set_nice(self, nice: int) -> None:
        """The device thread's niceness (Linux: per thread); OSError without the right."""
        if self._thread is None or self._thread.native_id is None:
            raise RuntimeError("the device is not running")
        os.setpriority(os.PRIO_PROCESS, self._thread.native_id, nice)

    def _run(self) -> None:
        raise NotImplementedError
