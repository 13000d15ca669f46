"""The estimation side's end of the pipe to the supervisor.

Decisions go up as :class:`~.lease.Lease` messages, sent from the event loop as they are
made: a changed decision at once, an unchanged one renewed at most every ``RENEW_S``. The
loop never waits on the pipe: a lease goes only while the pipe has room (a pipe the
supervisor does not empty is a supervisor that will halt on an expired lease anyway; the
lease is tried again with the next decision). Ground-speed frames the supervisor reads from
CAN come down; so do its status, a lift and the request to stop — read on the daemon's event
loop before each of its decisions (:meth:`SupervisorLink.poll`: at least every 40 ms, with
every IMU sample while they come; the loop does not wake for a message of its own — the
speed's 10 a second were a tenth of its wake-ups — and a speed sample read before a decision
is in it), else on a thread of its own. If the pipe breaks (the supervisor died) the
estimation process stops: it must never run without its supervisor.
"""

from __future__ import annotations

import asyncio
import logging
import math
import select
import threading
import time
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from mowerhw.common.samples import SpeedSample
from mowerhw.config import Config
from mowerhw.mow.gate import Decision
from mowerhw.recording.mcap import Recorder
from mowerhw.runtime.devices import CanFrames
from mowerhw.supervisor.fdwait import FdWaiter
from mowerhw.supervisor.lease import Lease

log = logging.getLogger("mowerhw.daemon")

#: an unchanged decision renews the lease at most this often (s)
RENEW_S = 0.02
#: and at the latest this long after the last lease sent or tried (the pipe full): the
#: daemon's decision timer is due then (:meth:`SupervisorLink.next_due`). While the IMU's
#: samples come (every 20 ms) a lease goes every 20–40 ms and this never fires. Without it,
#: with the samples held up, the timer was due ``DECIDE_MAX_S`` (40 ms) after the last
#: *decision*, which may have sent no lease (within ``RENEW_S`` of one): up to 60 ms between
#: leases, 20 ms short of the 80-ms lease — under two CPU hogs one ran out (README, issue 15,
#: stop 67)
RENEW_BY_S = 0.05
#: at most this many samples' forces wait for the next lease (at 50 Hz, 0.32 s of them)
MAX_UNSENT_FORCES = 16


class SupervisorLink:
    """A :class:`mowerhw.runtime.devices.DecisionOutput` over the supervisor's pipe."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.open_failures = 0
        self.supervisor_status: dict[str, Any] = {}
        self.leases_sent = 0
        self.leases_deferred = 0  # the pipe was full: tried again with the next decision
        #: forces of decisions that renewed no lease, for the next one (bounded: a pipe the
        #: supervisor does not empty ends in an expired lease anyway)
        self._unsent_forces: deque[tuple[float, float, float, float]] = deque(
            maxlen=MAX_UNSENT_FORCES
        )
        self._last_force: tuple[float, float, float] | None = None
        self._sent_key: tuple[bool, str] | None = None
        self._sent_at = -math.inf
        self._tried_at = -math.inf  # the last lease sent, or tried with the pipe full
        self._permit = False
        self._room = FdWaiter([conn.fileno()], select.POLLOUT)
        self._news = FdWaiter([conn.fileno()])  # before every decision: one system call
        self._send_lock = threading.Lock()
        self._closed = False
        self._frames: CanFrames | None = None
        self._on_lost: Callable[[str], None] | None = None
        self._on_lifted: Callable[[bool], None] | None = None
        self._polled = False  # read by :meth:`poll` (on an event loop), not by a thread

    def output(
        self,
        cfg: Config,
        on_speed: Callable[[SpeedSample], None],
        on_lost: Callable[[str], None],
        recorder: Recorder | None,
        on_lifted: Callable[[bool], None] | None = None,
    ) -> SupervisorLink:
        """Bind the daemon's callbacks (thread-safe ones: they run on this link's threads).
        The supervisor forwards every CAN frame it receives; they are recorded and their
        ground speed decoded here, as a one-process daemon does. ``on_lifted``: the
        supervisor's safety functions say the mower is lifted (True) or not any more."""
        self._frames = CanFrames(cfg, on_speed, recorder)
        self._on_lost = on_lost
        self._on_lifted = on_lifted
        return self

    # ------------------------------------------------------------------ DecisionOutput

    def open(self) -> bool:
        """Start; without a running event loop a thread reads the supervisor's messages,
        with one the loop's owner calls :meth:`poll` before each decision."""
        try:
            asyncio.get_running_loop()
        except RuntimeError:
            threading.Thread(target=self._read, name="supervisor-rx", daemon=True).start()
        else:
            self._polled = True
        self.send(("ready", None))
        return True

    def poll(self) -> None:
        """Every whole message the supervisor has sent, handled now (on the loop's thread;
        its callbacks run before this returns)."""
        if not self._polled or self._closed:
            return
        try:
            while self._news.ready_now():
                if not self._receive():
                    return
        except (OSError, EOFError, ValueError) as exc:
            self._lost(f"the supervisor's pipe closed ({type(exc).__name__})")

    def retry(self, now: float) -> None:
        return None

    def send_decision(
        self,
        d: Decision,
        pose_xyh: tuple[float, float, float],
        now: float,
        accel: tuple[float, float, float] | None = None,
    ) -> bool:
        key = (bool(d.permit), d.reason)
        due = key != self._sent_key or time.monotonic() - self._sent_at >= RENEW_S
        sent = False
        if due and not self._closed:
            self._tried_at = time.monotonic()
            lease = Lease.of(
                d,
                pose_xyh,
                now,
                accel or (math.nan, math.nan, math.nan),
                tuple(self._unsent_forces),
            )
            sent = self._send_if_room(("lease", lease.wire()))
            if sent:
                self._sent_key, self._sent_at = key, time.monotonic()
                self.leases_sent += 1
                self._unsent_forces.clear()
        # a new sample's force (a timer's decision repeats the last one), if it has one
        if (
            not sent
            and accel is not None
            and accel != self._last_force
            and all(map(math.isfinite, accel))
        ):
            self._unsent_forces.append((now, *accel))
        self._last_force = accel
        was, self._permit = self._permit, bool(d.permit)
        return was and not d.permit

    def tick(self, now: float) -> None:
        return None  # every decision renews the lease; the supervisor sends the frames

    def next_due(self) -> float:
        """When a decision must renew the lease (:data:`RENEW_BY_S` after the last lease
        sent or tried)."""
        if self._closed or self._tried_at == -math.inf:
            return math.inf  # the daemon's own timer until the first lease
        return self._tried_at + RENEW_BY_S  # (a full pipe: tried again then, no sooner)

    def shutdown(self, now: float) -> None:
        self._closed = True

    def close(self) -> None:
        self.shutdown(0.0)

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "supervisor": dict(self.supervisor_status),
            "leases_sent": self.leases_sent,
            "leases_deferred": self.leases_deferred,
        }
        if self._frames is not None:
            out["speed_reader"] = vars(self._frames.speed_reader.stats)
        return out

    # ------------------------------------------------------------------------ threads

    def send(self, msg: tuple[str, Any]) -> None:
        try:
            with self._send_lock:
                self.conn.send(msg)
        except (OSError, EOFError, ValueError) as exc:
            self._lost(f"cannot write to the supervisor ({exc})")

    def _send_if_room(self, msg: tuple[str, Any]) -> bool:
        """Send ``msg`` if the pipe has room for it now (never blocks: a Unix socket is
        reported writable while at most a quarter of its send buffer is in use, and a lease
        is a few hundred bytes)."""
        try:
            if not self._room.ready_now():
                self.leases_deferred += 1
                return False
        except OSError as exc:
            self._lost(f"cannot write to the supervisor ({exc})")
            return False
        self.send(msg)
        return not self._closed

    def _read(self) -> None:
        while self._receive():
            pass

    def _receive(self) -> bool:
        """One message from the supervisor, handled; False once the pipe is done with."""
        try:
            kind, body = self.conn.recv()
        except (OSError, EOFError, ValueError) as exc:
            self._lost(f"the supervisor's pipe closed ({type(exc).__name__})")
            return False
        if kind == "can" and self._frames is not None:
            self._frames.handle(*body)
        elif kind == "status":
            self.supervisor_status = body
        elif kind == "lifted" and self._on_lifted is not None:
            self._on_lifted(bool(body))
        elif kind == "stop":
            self._lost("the supervisor asked to stop")
            return False
        return True

    def _lost(self, why: str) -> None:
        if not self._closed and self._on_lost is not None:
            self._closed = True
            self._on_lost(why)
