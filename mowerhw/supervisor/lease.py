"""The permit lease and the supervisor's own decision (pure: no I/O, no clock of its own).

The estimation side sends a :class:`Lease` with every decision; it is good for
``supervisor.lease_s`` after the supervisor received it. :class:`SupervisorGate` permits only
while the newest lease is fresh and permits, and the supervisor's own checks hold (the ground
speed it sees itself is fresh, CAN is up); otherwise it halts with the first reason that
applies, logged once per change.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from mowerhw.common.reasons import Reason, State
from mowerhw.mow.gate import Decision

log = logging.getLogger("mowerhw.supervisor")


@dataclass(frozen=True, slots=True)
class Lease:
    """One decision of the estimation side, with the pose for the status frame."""

    permit: bool
    state: str
    reason: str
    detail: str
    signed_distance_m: float
    x: float
    y: float
    heading: float
    decided_at: float  # host monotonic s (CLOCK_MONOTONIC is one clock for all processes)
    #: the newest IMU sample's specific force, body frame (m/s²; NaN if the IMU has none)
    accel: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    #: the samples' specific forces since the previous lease that went without one of their
    #: own, oldest first, (t, fx, fy, fz): an unchanged decision renews the lease at most
    #: every ``link.RENEW_S``, and the safety checks must see every sample (a collision is
    #: one sample over its limit)
    earlier_forces: tuple[tuple[float, float, float, float], ...] = ()

    @classmethod
    def of(
        cls,
        d: Decision,
        pose_xyh: tuple[float, float, float],
        now: float,
        accel: tuple[float, float, float] = (math.nan, math.nan, math.nan),
        earlier_forces: tuple[tuple[float, float, float, float], ...] = (),
    ) -> Lease:
        return cls(
            bool(d.permit),
            str(d.state),
            d.reason,
            d.detail,
            float(d.signed_distance_m),
            *pose_xyh,
            now,
            accel,
            earlier_forces,
        )

    def wire(self) -> tuple[Any, ...]:
        """The lease as plain values for the pipe (:meth:`from_wire` makes it again): a
        tuple of numbers and strings pickles in a fraction of the time a dataclass with
        enum members does, and a lease goes up 50 times a second."""
        return (
            self.permit,
            str(self.state),
            str(self.reason),
            self.detail,
            self.signed_distance_m,
            self.x,
            self.y,
            self.heading,
            self.decided_at,
            self.accel,
            self.earlier_forces,
        )

    @classmethod
    def from_wire(cls, values: tuple[Any, ...]) -> Lease:
        return cls(*values)


#: what the supervisor decides before the first lease
NO_LEASE = Lease(
    False, State.UNKNOWN, Reason.NOT_MOWING, "starting", math.nan, math.nan, math.nan, math.nan, 0.0
)


class SupervisorGate:
    """The newest lease while it is fresh, and the supervisor's own checks. After a lease ran
    out, leases must come in time for ``settle_s`` before a permit again: an estimator that
    is late again and again must not make the deck flicker."""

    def __init__(self, lease_s: float, settle_s: float = 1.0) -> None:
        self.lease_s = lease_s
        self.settle_s = settle_s
        self.lease = NO_LEASE
        self.received_at: float | None = None
        self.current = NO_LEASE
        self.changes = 0
        self.expired = 0  # how many times the lease ran out
        self._on_time_since: float | None = None  # leases in time since
        self._was_late = False
        self._expired_now = False

    def _ran_out(self, now: float) -> bool:
        return self.received_at is not None and now - self.received_at > self.lease_s

    def renew(self, lease: Lease, now: float) -> None:
        if self.received_at is None or self._ran_out(now):
            self._on_time_since = now  # the first lease, or the first in time after a gap
            self._was_late = self._was_late or self.received_at is not None
        self.lease, self.received_at = lease, now

    def lease_expires(self) -> float:
        """When the newest lease runs out (``-inf`` before the first)."""
        return -math.inf if self.received_at is None else self.received_at + self.lease_s

    def decide(self, now: float, own_halt: tuple[str, str] | None = None) -> Lease:
        """The decision for ``now``. ``own_halt``: the supervisor's own reason to halt (a
        stale speed it sees, lifted or tilted, shutting down), which comes first."""
        lease = self.lease
        late = Reason.ESTIMATOR_LATE
        ran_out = self._ran_out(now)
        if ran_out and not self._expired_now:
            self.expired += 1
        self._expired_now = ran_out
        if own_halt is not None:
            d = _halt(lease, own_halt[0], own_halt[1], now)
        elif self.received_at is None:
            d = _halt(lease, late, "no permit lease yet: estimation starting", now)
        elif ran_out:
            self._was_late = True
            d = _halt(
                lease,
                late,
                f"no permit lease for {now - self.received_at:.3f} s (limit {self.lease_s} s): "
                "the estimator is late, stalled or dead",
                now,
            )
        elif lease.permit and self._was_late and now - (self._on_time_since or now) < self.settle_s:
            on_time = now - (self._on_time_since or now)
            d = _halt(
                lease,
                late,
                f"leases in time again for {on_time:.2f} of {self.settle_s} s after the "
                "estimator was late",
                now,
            )
        else:
            d = lease
        if d.permit != self.current.permit or d.reason != self.current.reason:
            self.changes += 1
            if d.permit:
                log.info("supervisor: PERMIT (%s)", d.state)
            elif d.reason != self.current.reason:
                log.warning("supervisor: HALT %s: %s", d.reason, d.detail)
        self.current = d
        return d


def _halt(lease: Lease, reason: str, detail: str, now: float) -> Lease:
    return Lease(
        False,
        State.UNKNOWN,
        str(reason),
        detail,
        math.nan,
        lease.x,
        lease.y,
        lease.heading,
        now,
    )
