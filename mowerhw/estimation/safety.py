"""Lift, tilt, rollover and collision (IEC 60335-2-107: the blade stops when the mower is
lifted or tilted). Pure: samples and switch states in, a halt reason out.

* **tilt**: the angle between the low-passed specific force and the body's up axis (the
  gravity vector, body frame z up) above ``safety.tilt_limit_deg`` for
  ``tilt_debounce_s``, or above ``rollover_deg`` at once;
* **lift**: the low-passed vertical specific force above gravity by ``lift_accel_mps2`` for
  ``lift_debounce_s`` (the mower accelerating upwards), or the controller's lift switch;
* **collision**: a horizontal specific force above ``bump_accel_mps2`` (one sample), or
  the controller's bumper;
* the controller's stop button halts like a collision.

Each is latched until it has been clear for ``clear_s``; the halt names what and since when.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mowerhw.common.reasons import Reason
from mowerhw.common.units import GRAVITY_MPS2
from mowerhw.config import SafetyConfig

G = GRAVITY_MPS2


@dataclass
class _Latch:
    reason: str
    active_since: float | None = None  # the raw condition holds since
    latched_at: float | None = None  # halting since
    clear_since: float | None = None  # the raw condition has been clear since
    detail: str = ""

    def update(
        self, now: float, active: bool, debounce: float, detail: str, clear_s: float
    ) -> None:
        if active:
            self.clear_since = None
            if self.active_since is None:
                self.active_since = now
            if self.latched_at is None and now - self.active_since >= debounce:
                self.latched_at, self.detail = now, detail
        else:
            self.active_since = None
            if self.latched_at is not None:
                if self.clear_since is None:
                    self.clear_since = now
                if now - self.clear_since >= clear_s:
                    self.latched_at = self.clear_since = None


def _low_pass(
    prev: tuple[float, float, float] | None,
    x: tuple[float, float, float],
    dt: float,
    tau: float,
) -> tuple[float, float, float]:
    if prev is None or tau <= 0.0:
        return x
    k = min(1.0, dt / tau)
    return (
        prev[0] + k * (x[0] - prev[0]),
        prev[1] + k * (x[1] - prev[1]),
        prev[2] + k * (x[2] - prev[2]),
    )


class SafetyMonitor:
    """Feed :meth:`imu` (body-frame specific force) and :meth:`switches`; ask :meth:`halt`."""

    def __init__(self, cfg: SafetyConfig) -> None:
        self.cfg = cfg
        self._f: tuple[float, float, float] | None = None  # low-passed specific force
        self._g: tuple[float, float, float] | None = None  # slower: the gravity direction
        self._t: float | None = None
        self.tilt = _Latch(Reason.TILTED)
        self.lift = _Latch(Reason.LIFTED)
        self.bump = _Latch(Reason.COLLISION)
        self.lift_switch = _Latch(Reason.LIFTED)
        self.bump_switch = _Latch(Reason.COLLISION)
        self.stop_switch = _Latch(Reason.COLLISION)
        self.tilt_deg = 0.0

    def imu(self, t: float, accel_body: tuple[float, float, float]) -> None:
        """One IMU sample's specific force (m/s², body frame, z up)."""
        ax, ay, az = accel_body
        if not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az)):
            return
        c = self.cfg
        dt = 0.0 if self._t is None else max(0.0, t - self._t)
        self._t = t
        self._f = _low_pass(self._f, (ax, ay, az), dt, c.filter_s)
        fz = self._f[2]
        # tilt from a slower filter: a jolt must not look like the mower rolling over
        gx, gy, gz = self._g = _low_pass(self._g, (ax, ay, az), dt, c.tilt_filter_s)
        norm = math.sqrt(gx * gx + gy * gy + gz * gz)
        self.tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, gz / norm)))) if norm else 0.0
        rolled = self.tilt_deg > c.rollover_deg
        tilted = self.tilt_deg > c.tilt_limit_deg
        debounce = 0.0 if rolled else c.tilt_debounce_s
        what = "rolled over" if rolled else "tilted"
        self.tilt.update(
            t,
            tilted,
            debounce,
            f"{what} {self.tilt_deg:.0f}° (limit {c.tilt_limit_deg:.0f}°)",
            c.clear_s,
        )
        up = fz - G
        self.lift.update(
            t,
            up > c.lift_accel_mps2,
            c.lift_debounce_s,
            f"accelerating upwards at {up:.1f} m/s² (lifted?)",
            c.clear_s,
        )
        horizontal = math.hypot(ax, ay)
        self.bump.update(
            t,
            horizontal > c.bump_accel_mps2,
            0.0,
            f"a {horizontal:.0f} m/s² jolt (collision?)",
            c.clear_s,
        )

    def switches(self, t: float, lifted: bool, bumped: bool, stop: bool) -> None:
        """The mower controller's switch frame."""
        c = self.cfg
        self.lift_switch.update(t, lifted, 0.0, "the mower's lift switch", c.clear_s)
        self.bump_switch.update(t, bumped, 0.0, "the mower's bumper", c.clear_s)
        self.stop_switch.update(t, stop, 0.0, "the mower's stop button", c.clear_s)

    def halt(self, now: float) -> tuple[str, str] | None:
        """The first latched condition: (reason, detail), else None."""
        for latch in (
            self.lift_switch,
            self.lift,
            self.tilt,
            self.stop_switch,
            self.bump_switch,
            self.bump,
        ):
            if latch.latched_at is not None:
                since = now - latch.latched_at
                clear = (
                    f"; clear for {now - latch.clear_since:.1f} of {self.cfg.clear_s} s"
                    if latch.clear_since is not None
                    else ""
                )
                return latch.reason, f"{latch.detail}, {since:.1f} s ago{clear}"
        return None
