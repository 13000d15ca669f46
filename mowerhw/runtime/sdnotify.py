"""systemd's notify protocol (sd_notify(3)) without a dependency: datagrams to $NOTIFY_SOCKET.

``READY=1`` once the devices are open, ``STATUS=…`` with mode and containment state,
``WATCHDOG=1`` from the estimator loop (so a hung estimator is restarted: ``WatchdogSec=``),
``STOPPING=1`` on shutdown. Outside systemd (no $NOTIFY_SOCKET) every call does nothing.
"""

from __future__ import annotations

import os
import socket


class Notifier:
    def __init__(self) -> None:
        addr = os.environ.get("NOTIFY_SOCKET", "")
        if addr.startswith("@"):  # abstract namespace
            addr = "\0" + addr[1:]
        self.address = addr
        self._sock: socket.socket | None = None
        self._next_watchdog = 0.0
        self._last_status = ""
        if addr:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        usec = os.environ.get("WATCHDOG_USEC", "")
        pid = os.environ.get("WATCHDOG_PID", "")
        ours = not pid or pid == str(os.getpid())
        #: how often to ping (a quarter of systemd's WatchdogSec: a late ping still has most
        #: of the time left), or None when there is no watchdog
        self.watchdog_period_s = int(usec) / 4e6 if usec.isdigit() and ours else None

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, *lines: str) -> bool:
        if self._sock is None:
            return False
        try:
            self._sock.sendto("\n".join(lines).encode(), self.address)
            return True
        except OSError:
            return False

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1", *((f"STATUS={status}",) if status else ()))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def tick(self, now: float, status: str) -> None:
        """From the event loop's ticker: the watchdog ping when due, STATUS when it changed
        (a hung loop stops the pings and systemd restarts the service)."""
        period = self.watchdog_period_s
        if period is not None and now >= self._next_watchdog:
            self._next_watchdog = now + period
            self.watchdog()
        if status != self._last_status:
            self._last_status = status
            self.status(status)
