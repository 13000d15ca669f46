"""The start-up standstill: the gyro bias as the mean of the readings while the mower stands
(the paper calibrates it once, at rest). One rule for both phases: the standstill lasts until
the ground speed is not zero (the caller says so) or the gyro turns (a reading more than
:data:`TURNING_RAD_S` from the running mean, once :data:`MIN_SAMPLES` are in)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: a still gyro beyond this (rad/s) from its running mean is turning: not a standstill
TURNING_RAD_S = 0.05
#: fewest readings for a bias (and for the turning test)
MIN_SAMPLES = 20


class StandstillCalibrator:
    """Accumulates gyro readings while the mower stands (see the module doc)."""

    def __init__(self) -> None:
        self.n = 0
        self._sum = np.zeros(3)
        self._sq = np.zeros(3)
        self.still = True

    def add(self, gyro: FloatArray) -> bool:
        """One reading; False (and no longer still) when it shows the mower turning."""
        if not self.still:
            return False
        if self.n >= MIN_SAMPLES and np.linalg.norm(gyro - self._sum / self.n) > TURNING_RAD_S:
            self.still = False
            return False
        self._sum += gyro
        self._sq += gyro * gyro
        self.n += 1
        return True

    def stop(self) -> None:
        """The mower moved (a ground speed that is not zero)."""
        self.still = False

    @property
    def calibrated(self) -> bool:
        """Enough readings for a bias."""
        return self.n >= MIN_SAMPLES

    def bias(self) -> FloatArray:
        """The mean reading so far (zeros before the first)."""
        return self._sum / self.n if self.n else np.zeros(3)

    def bias_variance(self) -> float:
        """Variance of the bias estimate: the largest per-axis sample variance over ``n``."""
        if not self.n:
            return float("inf")
        mean = self._sum / self.n
        return float(np.max(np.maximum(self._sq / self.n - mean**2, 1e-12))) / self.n

    def corrected(self, gyro: FloatArray) -> FloatArray:
        """A reading with the bias so far taken out (during the standstill)."""
        return np.asarray(gyro, dtype=np.float64) - self.bias() if self.n else gyro
