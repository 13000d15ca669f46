"""How much a frame's bearings are worth when their errors are partly the frames' before.

Frames from one place see the same corners from the same place: part of each bearing's error
(a rendered or detected corner's bias, the map's own error of it) is the same each time, and
it changes only slowly as the mower drives on. The model (issue 18, the localizer's frame σ):
a frame's error is ``c + n`` in units of a lone frame's variance — a common part ``c`` (the
share ``f`` of the variance) that moves on between frames as an AR(1) with correlation ``ρ``
(1 standing, ``exp(−distance/length)`` driving), and the frame's own ``n`` (``1 − f``). The
information a new frame adds about the pose — a scalar stand-in ``x`` that every frame
measures, ``z = x + c + n`` — is found exactly by a two-state Kalman filter over ``(x, c)``,
and the frame's bearings are weighed by it: their σ is a lone frame's over its square root.

Standing, ``k`` frames are worth ``k / ((1 − f) + k f)`` lone ones (never more than ``1/f``).
The rule this replaces (stop 63) carried a count ``k ← 1 + ρ k``, exact standing but not once
the mower moves: after ten standing frames the first frame 0.125 m on (ρ 0.53) added 0.04 of
a lone frame's information where the model gives 0.31, so a relocalized mower driving off
was under-confident for seconds (NEES bins under their bound, README issue 18).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class SharedFrameError:
    """The frames' shared error so far (module doc); :meth:`move_on`, then :meth:`frame`."""

    def __init__(self, share: float) -> None:
        if not 0.0 <= share < 1.0:
            raise ValueError(f"the shared part of a frame's variance is in [0, 1), not {share}")
        self.share = share
        #: covariance of the errors of (x's estimate, c's estimate); None before any frame
        self._p: FloatArray | None = None

    def move_on(self, rho: float) -> None:
        """Between two frames the common error keeps ``rho`` of itself (1: the same spot,
        0: a fresh one): ``c ← ρ c + √(1 − ρ²) w`` (the AR(1)'s prediction step)."""
        if self._p is None:
            return
        r = min(max(rho, 0.0), 1.0)
        p = self._p
        p[0, 1] *= r
        p[1, 0] *= r
        p[1, 1] = r * r * p[1, 1] + (1.0 - r * r) * self.share

    def frame(self) -> float:
        """A frame now: its σ over a lone frame's, ``1/√(information it adds)`` (≥ 1)."""
        f = self.share
        if self._p is None:  # the first: x unknown, so it is worth a lone frame; after it
            # x's error is c + n (variance 1), c's estimate is 0 (error −c: variance f)
            self._p = np.array([[1.0, -f], [-f, f]])
            return 1.0
        p = self._p
        before = 1.0 / p[0, 0]
        ph = p[:, 0] + p[:, 1]  # P Hᵀ with H = [1, 1]
        s = ph[0] + ph[1] + (1.0 - f)
        self._p = p - np.outer(ph, ph) / s
        gained = 1.0 / self._p[0, 0] - before
        return 1.0 / math.sqrt(max(gained, 1e-12))
