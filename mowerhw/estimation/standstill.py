"""The start-up standstill: the gyro bias as the mean of the readings while the mower stands
(the paper calibrates it once, at rest). One rule for both phases: the standstill lasts until
the ground speed is not zero (the caller says so), the gyro turns (a reading more than
:data:`TURNING_RAD_S` from the running mean, once :data:`MIN_SAMPLES` are in) or the mower
sets off (given the accelerometer's specific force along the body's x: its departure from
the standstill's own mean — which holds the accelerometer's bias and gravity's share through
the slope — integrated over the last :data:`SETOFF_WINDOW_S`, a speed beyond
:data:`SETOFF_MPS`; a ground speed comes only every 0.1 s, and the pose was held that long
while the mower rolled: 4.9 mm behind at a σ of 1.3 mm at pixel level, stop 78). A turn begins
before a reading crosses that line, and a ground speed arrives a sample period after the
wheels began to roll: the readings of the last :data:`TAIL_S` before the end are left out
of the bias (measured at pixel level: a turn's first 50 ms left in put the bias 2·10⁻⁴ rad/s
off — 5σ of what the standstill claimed — and the heading drifted 0.01°/s on it)."""

from __future__ import annotations

import itertools
from collections import deque

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: a still gyro beyond this (rad/s) from its running mean is turning: not a standstill
TURNING_RAD_S = 0.05
#: fewest readings for a bias (and for the turning test)
MIN_SAMPLES = 20
#: the readings this close (s) to the end of the standstill are not in its bias
TAIL_S = 0.2
#: the specific force's departure from the standstill's mean is integrated over this long (s)
SETOFF_WINDOW_S = 0.1
#: ... and a speed (m/s) beyond this is setting off: a mower setting off at 0.5–1 m/s² gets
#: there in 15–30 ms. A vibration of amplitude A at f Hz integrates to at most A/(πf) over
#: any window (0.013 m/s for a 50-Hz blade shaking the IMU at 2 m/s²), an accelerometer's
#: white noise to 0.4 mm/s (VN-100: 0.14 mg/√Hz over 0.1 s). A standstill ended early by a
#: jolt costs only the bias's later readings; the ground speed still ends a late one.
SETOFF_MPS = 0.015


class StandstillCalibrator:
    """Accumulates gyro readings while the mower stands (see the module doc)."""

    def __init__(self) -> None:
        self.n = 0
        self._sum = np.zeros(3)
        self._sq = np.zeros(3)
        self._tail: deque[tuple[float, FloatArray]] = deque()
        self.still = True
        self._force_sum = 0.0
        self._forces = 0
        self._recent_forces: deque[tuple[float, float]] = deque()  # (t, force) in the window

    def add(self, t: float, gyro: FloatArray, force_x: float | None = None) -> bool:
        """One reading taken at ``t`` (``force_x``: the along-track specific force over it,
        m/s², when the IMU gives one); False (and no longer still) when it shows the mower
        turning or setting off."""
        if not self.still:
            return False
        if self.n >= MIN_SAMPLES and np.linalg.norm(gyro - self._sum / self.n) > TURNING_RAD_S:
            self.still = False
            return False
        if force_x is not None and self._sets_off(float(t), force_x):
            self.still = False
            return False
        g = np.array(gyro, dtype=np.float64).reshape(3)
        self._sum += g
        self._sq += g * g
        self.n += 1
        self._tail.append((float(t), g))
        while self._tail[0][0] < t - TAIL_S:
            self._tail.popleft()
        return True

    def _sets_off(self, t: float, force_x: float) -> bool:
        """The newest :data:`SETOFF_WINDOW_S` of forces, less the standstill's mean, times
        their intervals: a speed beyond :data:`SETOFF_MPS` (judged once :data:`MIN_SAMPLES`
        are in that mean; a reading joins it when it leaves the window, judged)."""
        window = self._recent_forces
        window.append((t, float(force_x)))
        while window[0][0] < t - SETOFF_WINDOW_S:
            self._force_sum += window.popleft()[1]
            self._forces += 1
        if self._forces < MIN_SAMPLES or len(window) < 2:
            return False
        mean = self._force_sum / self._forces
        gained = sum((f - mean) * (ti - tp) for (tp, _), (ti, f) in itertools.pairwise(window))
        return abs(gained) > SETOFF_MPS

    @property
    def tail_start(self) -> float | None:
        """The first reading's time that :meth:`bias` leaves out once the standstill is
        over (None before any)."""
        return self._tail[0][0] if self._tail else None

    def _used(self) -> tuple[int, FloatArray, FloatArray]:
        """Count, sum and sum of squares of the readings in the bias: all while still; once
        it is over, all but the last :data:`TAIL_S`."""
        if self.still or not self._tail:
            return self.n, self._sum, self._sq
        g = np.array([r for _, r in self._tail])
        return self.n - len(g), self._sum - g.sum(axis=0), self._sq - (g * g).sum(axis=0)

    def stop(self) -> None:
        """The mower moved (a ground speed that is not zero)."""
        self.still = False

    @property
    def calibrated(self) -> bool:
        """Enough readings for a bias."""
        return self._used()[0] >= MIN_SAMPLES

    @property
    def used(self) -> int:
        """The readings the bias is the mean of."""
        return self._used()[0]

    def bias(self) -> FloatArray:
        """The mean reading (zeros before the first): so far while still, then without the
        tail."""
        n, total, _ = self._used()
        return total / n if n else np.zeros(3)

    def bias_variance(self) -> float:
        """Variance of the bias estimate: the largest per-axis sample variance over ``n``."""
        n, total, sq = self._used()
        if not n:
            return float("inf")
        mean = total / n
        return float(np.max(np.maximum(sq / n - mean**2, 1e-12))) / n

    def corrected(self, gyro: FloatArray) -> FloatArray:
        """A reading with the bias so far taken out (during the standstill)."""
        return np.asarray(gyro, dtype=np.float64) - self.bias() if self.n else gyro
