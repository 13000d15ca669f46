"""The bench's stand-in for systemd's notify socket: the daemon is started with
``NOTIFY_SOCKET`` and ``WATCHDOG_USEC`` as systemd would, and every ``WATCHDOG=1`` it sends is
timed, so a bench run shows the gaps systemd would have seen (``WatchdogSec=``)."""

from __future__ import annotations

import contextlib
import itertools
import socket
import threading
import time
from pathlib import Path


class NotifyListener:
    """A datagram socket at ``path`` collecting the daemon's notify messages."""

    def __init__(self, path: Path, watchdog_s: float = 2.0) -> None:
        self.path = Path(path)
        self.watchdog_s = watchdog_s
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(self.path))
        self._sock.settimeout(0.2)
        self.pings: list[float] = []  # time.monotonic() of each WATCHDOG=1
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-notify", daemon=True)
        self._thread.start()

    def env(self) -> dict[str, str]:
        """What systemd puts in the service's environment."""
        return {"NOTIFY_SOCKET": str(self.path), "WATCHDOG_USEC": str(int(self.watchdog_s * 1e6))}

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if b"WATCHDOG=1" in data.split(b"\n"):
                self.pings.append(time.monotonic())

    def gaps(self, since: float, until: float) -> dict[str, float | int | None]:
        """Pings between ``since`` and ``until`` and the longest time without one."""
        t = [since, *[p for p in self.pings if since <= p <= until], until]
        longest = max(b - a for a, b in itertools.pairwise(t))
        return {
            "pings": len(t) - 2,
            "max_gap_s": round(longest, 3) if longest is not None else None,
            "watchdog_s": self.watchdog_s,
        }

    def close(self) -> None:
        self._stop.set()
        self._sock.close()
        self._thread.join(1.0)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
