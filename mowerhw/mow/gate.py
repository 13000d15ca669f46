"""The fail-safe permit decision (docs/design.md §5, §8): halt unless every condition holds.

:class:`PermitGate` is asked after every IMU sample and on a short timer. It permits only in
mow mode, with a valid map, every sensor fresh on the host clock (IMU 100 ms, speed 300 ms,
camera: ``camera.stale_after_s``), no estimator fault, and containment saying INSIDE or
NEAR_EDGE. The first failing condition is the reason (precedence: shutting down, not mowing,
map invalid, sensor stale, fault, then containment's own). A change of decision is logged once
with its reason; :meth:`decide` is pure apart from that log line.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from mowerhw.common.reasons import Reason, State
from mowerhw.config import Config, stale_limits_s

if TYPE_CHECKING:
    from mowerhw.mow.containment import ContainmentResult

log = logging.getLogger("mowerhw.permit")


@dataclass(frozen=True)
class Decision:
    permit: bool
    state: str  # containment state (UNKNOWN when the runtime halts before containment)
    reason: str  # "" while permitted
    detail: str = ""
    signed_distance_m: float = float("nan")


class PermitGate:
    """Every condition for mowing, checked in order; logs each change of decision once."""

    @classmethod
    def from_config(cls, cfg: Config | None, log_changes: bool = True) -> PermitGate:
        """Staleness limits from the config's sensor sections (defaults without one)."""
        return cls(stale_limits_s(cfg), log_changes)

    def __init__(self, limits_s: dict[str, float], log_changes: bool = True) -> None:
        self.stale_limits_s = dict(limits_s)
        self.log_changes = log_changes
        self.current = Decision(False, State.UNKNOWN, Reason.NOT_MOWING, "starting")
        self.changes = 0

    def stale(
        self,
        now: float,
        last_arrival: dict[str, float | None],
        notes: dict[str, tuple[float, str]] | None = None,
    ) -> tuple[str, str] | None:
        """The first stream with no good data for longer than its limit: (stream, detail).

        ``notes``: per stream, the arrival time and the device's own word for why its newest
        data is not usable (``speed sensor reports not available (GBSD from 0x47)``); while it
        is recent, it is the detail instead of "silent"."""
        for name, limit in self.stale_limits_s.items():
            last = last_arrival.get(name)
            if not self.late(name, now, last):
                continue
            note = (notes or {}).get(name)
            if note is not None and last is not None and note[0] < last:
                note = None  # good data came after it
            if note is not None and now - note[0] <= limit:
                return name, note[1]
            said = f"; last heard {now - note[0]:.1f} s ago: {note[1]}" if note else ""
            if last is None:
                return name, f"no {name} data yet{said}"
            return name, f"{name} silent for {now - last:.3f} s (limit {limit} s){said}"
        return None

    def late(self, name: str, now: float, last: float | None) -> bool:
        """Whether stream ``name``, last heard at ``last``, is older than its limit (the one
        rule of staleness: the decision and the status page both ask it)."""
        limit = self.stale_limits_s.get(name)
        return limit is not None and (last is None or now - last > limit)

    def next_stale_deadline(self, now: float, last_arrival: dict[str, float | None]) -> float:
        """When the next stream's limit runs out (a shell wakes then, so a silent sensor
        halts within a millisecond or two of its limit), or ``inf``."""
        due = math.inf
        for name, limit in self.stale_limits_s.items():
            last = last_arrival.get(name)
            if last is not None and last + limit > now:
                due = min(due, last + limit)
        return due

    def revealed_at(
        self,
        now: float,
        stale: tuple[str, str] | None,
        last_arrival: dict[str, float | None],
        revealed_at: float | None,
    ) -> float:
        """When a halt's cause became known: a silent sensor when its limit ran out, else
        ``revealed_at`` (the arrival of the input that showed it), else ``now``."""
        if stale is not None:
            last = last_arrival.get(stale[0])
            return last + self.stale_limits_s[stale[0]] if last is not None else now
        return revealed_at if revealed_at is not None else now

    def decide(
        self,
        now: float,
        mode: str,
        last_arrival: dict[str, float | None],
        containment: ContainmentResult | None = None,
        map_problem: str = "",
        fault: str = "",
        shutting_down: bool = False,
        stale: tuple[str, str] | Literal[False] | None = False,
    ) -> Decision:
        """``stale``: the caller's own :meth:`stale` result for this ``now``, if it has one
        (False: work it out here)."""

        def halt(reason: Reason, detail: str) -> Decision:
            return Decision(False, State.UNKNOWN, reason.value, detail)

        if shutting_down:
            d = halt(Reason.SHUTTING_DOWN, "the daemon is stopping")
        elif mode != "mow":
            d = halt(Reason.NOT_MOWING, f"mode is {mode}")
        elif map_problem:
            d = halt(Reason.MAP_INVALID, map_problem)
        elif (st := self.stale(now, last_arrival) if stale is False else stale) is not None:
            d = halt(Reason.SENSOR_STALE, st[1])
        elif fault:
            d = halt(Reason.FAULT, fault)
        elif containment is None:
            d = halt(Reason.NOT_LOCALIZED, "no estimate yet")
        else:
            c = containment
            ok = c.permit and math.isfinite(c.signed_distance_m)
            d = Decision(
                ok,
                c.state,
                "" if ok else (c.reason or Reason.FAULT.value),
                c.detail if not ok else "",
                c.signed_distance_m,
            )
        self._log_change(d)
        self.current = d
        return d

    def _log_change(self, d: Decision) -> None:
        prev = self.current
        if d.permit == prev.permit and d.reason == prev.reason:
            return
        if not self.log_changes:
            self.changes += 1
            return
        self.changes += 1
        if d.permit:
            log.info("PERMIT: mowing permitted (%s, %.2f m inside)", d.state, d.signed_distance_m)
        else:
            log.warning("HALT %s: %s", d.reason, d.detail or d.state)
