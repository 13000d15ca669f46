"""The mower's own controller on the bench: random coverage with bang-bang edge turns.

As in the paper's §V mowing simulation: the mower drives straight; when containment says it
is near the edge (NEAR_EDGE, within the 0.4 m band) or past it, it turns on the spot to a random
heading pointing into the lawn and drives on. It steers by the *estimate* (position, heading,
containment) — never the truth — so an estimation error can carry it across the edge, which
is exactly what the containment output must catch. When containment is UNKNOWN it stops and
waits.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import wrap_angle

FloatArray = NDArray[np.float64]


class BangBangMower:
    """(v, ω) commands from the estimated pose and the containment state."""

    def __init__(
        self,
        inward: Callable[[float, float], FloatArray],
        rng: np.random.Generator,
        speed_mps: float = 0.45,
        turn_rate: float = 0.8,
        spread_deg: float = 60.0,
        start_after_s: float = 2.0,
    ) -> None:
        self.inward = inward  # (x, y) → unit vector into the mowable area (from the map)
        self.rng = rng
        self.speed = speed_mps
        self.turn_rate = turn_rate
        self.spread = math.radians(spread_deg)
        self.start_after_s = start_after_s
        self.mode = "wait"
        self.target = 0.0
        self.turns = 0

    def command(self, t: float, x: float, y: float, yaw: float, state: str) -> tuple[float, float]:
        if t < self.start_after_s:
            return 0.0, 0.0  # the standstill the localizer calibrates its gyro on
        if state == "UNKNOWN":
            self.mode = "wait"
            return 0.0, 0.0
        if self.mode == "wait":
            self.mode = "drive"
        if self.mode == "drive" and state in ("NEAR_EDGE", "OUTSIDE"):
            n = self.inward(x, y)
            heading = np.array([math.cos(yaw), math.sin(yaw)])
            if heading @ n < math.cos(math.radians(75.0)):  # heading for the edge: turn
                self.target = math.atan2(n[1], n[0]) + self.rng.uniform(-self.spread, self.spread)
                self.mode = "turn"
                self.turns += 1
        if self.mode == "turn":
            err = wrap_angle(self.target - yaw)
            if abs(err) < math.radians(3.0):
                self.mode = "drive"
            else:
                return 0.0, math.copysign(min(self.turn_rate, 4.0 * abs(err)), err)
        return self.speed, 0.0
