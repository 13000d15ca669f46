"""A scripted estimation process for testing the supervisor (as the mock devices test the
drivers): it renews permit leases on a schedule, goes quiet when told, and exits."""

from __future__ import annotations

import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from mowerhw.common.units import GRAVITY_MPS2
from mowerhw.supervisor.lease import Lease

#: (seconds, what): "permit" (leases that permit, every 10 ms), "quiet" (no lease), "exit"
DEFAULT_SCRIPT: tuple[tuple[float, str], ...] = (
    (1.0, "permit"),
    (0.5, "quiet"),
    (1.6, "permit"),  # longer than supervisor.settle_s (1 s): permitted again
    (0.0, "exit"),
)


def scripted_estimator(
    config: Any,
    mode: str | None,
    record: Path | None,
    conn: Connection,
    log_level: int,
    script: tuple[tuple[float, str], ...] = DEFAULT_SCRIPT,
) -> None:
    """Entry point of the spawned mock (the signature of ``estimator_main``)."""
    conn.send(("ready", None))
    for seconds, what in script:
        if what == "exit":
            conn.close()
            raise SystemExit(3)
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            while conn.poll():
                conn.recv()  # CAN frames and status from the supervisor
            if what == "permit":
                now = time.monotonic()
                # an upright mower's IMU: gravity on body z (the supervisor's lift/tilt input)
                level = (0.0, 0.0, GRAVITY_MPS2)
                lease = Lease(True, "INSIDE", "", "", 1.0, 0.0, 0.0, 0.0, now, level)
                conn.send(("lease", lease.wire()))
            time.sleep(0.01)
    raise SystemExit(0)
