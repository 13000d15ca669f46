"""A permit supervisor's CAN receive thread in a test, beside another node on its bus."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import can

from drivers.can.isobus import open_bus
from mowerhw.supervisor.process import Supervisor


@contextlib.contextmanager
def receiving(sup: Supervisor, channel: str) -> Iterator[can.BusABC]:
    """The supervisor's CAN receive thread running on its bus, and another node's bus on the
    same channel to send from; stopped and shut down after."""
    assert sup.port.ensure(time.monotonic())
    rx = threading.Thread(target=sup._receive, daemon=True)
    rx.start()
    tx = open_bus("virtual", channel)
    try:
        yield tx
    finally:
        sup.stop_requested = "test"
        rx.join(2.0)
        tx.shutdown()
        if sup.port.bus is not None:
            sup.port.bus.shutdown()
