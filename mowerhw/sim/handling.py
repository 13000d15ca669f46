"""People handling the mower (the events of ``mowerhw sim mow --fault``): lifted, tilted,
bumped. What the IMU's accelerometer and the mower's own switches would report while it
happens, so the safety functions (:mod:`mowerhw.estimation.safety`) are judged in the
simulator as on the bench (issue 15)."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: how each kind shows, and its default length (s)
KINDS = {"lift": 2.0, "tilt": 3.0, "bump": 0.2}
#: the upward acceleration of a mower being lifted (m/s²), for this long (s) at the start
LIFT_ACCEL_MPS2, LIFT_ACCEL_S = 6.0, 0.3
#: the angle a tilted mower is held at (deg)
TILT_DEG = 45.0
#: a collision's horizontal jolt (m/s²), for this long (s)
BUMP_ACCEL_MPS2, BUMP_JOLT_S = 40.0, 0.02


@dataclass(frozen=True)
class HandlingEvent:
    """One event: ``kind`` at ``at_s`` of simulated time, for ``duration_s``."""

    kind: str
    at_s: float
    duration_s: float

    @classmethod
    def parse(cls, text: str) -> HandlingEvent:
        """``KIND@T[:D]``, e.g. ``lift@60:2``; ValueError naming what is allowed."""
        try:
            kind, _, when = text.partition("@")
            at, _, dur = when.partition(":")
            if kind not in KINDS:
                raise ValueError
            event = cls(kind, float(at), float(dur) if dur else KINDS[kind])
        except ValueError:
            raise ValueError(
                f"{text!r}: expected KIND@T[:D] with KIND one of {', '.join(KINDS)} "
                "(e.g. lift@60:2)"
            ) from None
        if not (math.isfinite(event.at_s) and event.at_s >= 0 and 0 < event.duration_s <= 600):
            raise ValueError(f"{text!r}: T must be ≥ 0 and D between 0 and 600 s")
        return event

    def active(self, t: float) -> bool:
        return self.at_s <= t < self.at_s + self.duration_s


def handled(
    events: list[HandlingEvent], t: float, force: tuple[float, float, float]
) -> tuple[tuple[float, float, float], tuple[bool, bool, bool]]:
    """The specific force (body frame, z up) and the switches (lifted, bumped, stop) while
    the events at ``t`` happen to a mower that would otherwise read ``force``."""
    fx, fy, fz = force
    lifted = bumped = False
    for e in events:
        if not e.active(t):
            continue
        since = t - e.at_s
        if e.kind == "lift":
            lifted = True
            if since < LIFT_ACCEL_S:
                fz += LIFT_ACCEL_MPS2
        elif e.kind == "tilt":  # held up on one side: gravity turns about the body's x axis
            a = math.radians(TILT_DEG)
            fy, fz = fy * math.cos(a) + fz * math.sin(a), -fy * math.sin(a) + fz * math.cos(a)
        elif e.kind == "bump":
            bumped = True
            if since < BUMP_JOLT_S:
                fx -= BUMP_ACCEL_MPS2
    return (fx, fy, fz), (lifted, bumped, False)


@dataclass(frozen=True)
class Kidnap:
    """The mower picked up at ``at_s`` (the first moment from then on that the deck runs),
    carried for ``carry_s`` and put down at ``to_map_xy``
    (simulator map frame) facing ``to_heading`` (issue 18). ``lifted``: the lift shows on the
    accelerometer and the lift switch (a lift event for the carry); without, only the camera
    can tell (a mower pushed along, or a lift its sensors missed)."""

    at_s: float
    carry_s: float
    to_map_xy: tuple[float, float]
    to_heading: float
    lifted: bool = True
    #: other places to put it down, (x, y, heading): the first at least
    #: ``min_displacement_m`` from where it was picked up is taken (else the farthest)
    alternatives: tuple[tuple[float, float, float], ...] = ()
    min_displacement_m: float = 0.0

    def destination(self, from_map_xy: tuple[float, float]) -> tuple[float, float, float]:
        """Where it is put down, picked up at ``from_map_xy``."""
        options = [(*self.to_map_xy, self.to_heading), *self.alternatives]
        away = [math.dist(o[:2], from_map_xy) for o in options]
        for o, d in zip(options, away, strict=True):
            if d >= self.min_displacement_m:
                return o
        return options[max(range(len(options)), key=away.__getitem__)]

    def lift(self) -> HandlingEvent | None:
        return HandlingEvent("lift", self.at_s, self.carry_s) if self.lifted else None
