"""A simulated ground-speed sensor: GBSD (PGN 65097) every 100 ms on a python-can bus."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can

from drivers.can.isobus import PGN_GBSD
from drivers.can.speed import encode_speed
from drivers.threaded import ThreadedDevice


class MockSpeedSensor(ThreadedDevice):
    """Sends the speed ``speed_at(t)`` (t: seconds since start) every ``period_s``."""

    thread_name = "mock-speed"

    def __init__(
        self,
        bus: can.BusABC,
        speed_at: Callable[[float], float],
        period_s: float = 0.1,
        source_address: int = 0x80,
        pgn: int = PGN_GBSD,
    ) -> None:
        super().__init__()
        self.bus = bus
        self.speed_at = speed_at
        self.period_s = period_s
        self.sa = source_address
        self.pgn = pgn
        self.sent = 0
        self.distance_m = 0.0
        self.paused = threading.Event()  # set: the sensor goes quiet (unplugged)
        self._t0 = 0.0

    def start(self) -> MockSpeedSensor:
        self._t0 = time.monotonic()
        self._start_thread()
        return self

    def _run(self) -> None:
        import can

        nxt = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= nxt:
                v = self.speed_at(now - self._t0)
                self.distance_m += abs(v) * self.period_s
                if not self.paused.is_set():
                    ident, data = encode_speed(v, self.distance_m, self.sa, self.pgn)
                    self.bus.send(can.Message(arbitration_id=ident, data=data, is_extended_id=True))
                    self.sent += 1
                nxt += self.period_s
            self._stop.wait(max(0.0, min(nxt - time.monotonic(), 0.05)))
