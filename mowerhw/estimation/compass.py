"""The magnetometer as a coarse compass in the map's frame (issue 18: look-alike places).

A garden that looks the same turned half round (two rows of identical panels, a symmetric
bed) gives the global relocalizer two places that explain the image equally well; the
camera alone cannot choose. The VN-100's magnetometer can: the Earth's field does not turn
with the garden. It is not trusted for more than that — motors, the blade and steel nearby
bend the field by degrees to tens of degrees — so it only rules out places whose heading is
far from what it says (:class:`Compass` gives a heading and a σ; the relocalizer keeps the
hypotheses within its tolerance), never gives a pose by itself.

Angles (docs/design.md §3: map frame z up, headings CCW from the map's x axis):

- ``α`` — the direction of the field's horizontal part in the *body's* levelled frame
  (``field_in_body``): the mower's accelerometer says where up is, or the body's z when
  no accelerometer reading comes with it (a mower on its wheels).
- ``δ`` — the direction of the field's horizontal part in the *map's* frame
  (``CompassReference.north_rad``, :mod:`mowerhw.common.magnetic`), learned while teaching:
  for a body heading ψ, ``α = δ − ψ``, so ``δ = ψ + α`` averaged over the drive
  (:class:`CompassCalibration`) and, when mowing, ``ψ = δ − α`` (:class:`Compass`).

A reading whose strength or dip differs from the taught field (a steel plate, a magnet, a
car parked beside the mower) is a disturbed one and is not used.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mowerhw.common.geometry import quat_to_yaw, wrap_angle
from mowerhw.common.magnetic import CompassReference, FieldReading, field_in_body

FloatArray = NDArray[np.float64]

#: readings are kept at most this often (s; less half a 100 Hz interval, for jitter): the
#: field changes with the heading only. The runtime hands readings on at this period too.
SAMPLE_PERIOD_S = 0.1
KEEP_AFTER_S = SAMPLE_PERIOD_S - 0.005
#: a taught reference must have this many readings and at most this spread to be trusted
MIN_TEACH_SAMPLES = 50
MAX_TEACH_SPREAD_RAD = math.radians(20.0)
#: the mowing compass: readings of the last WINDOW_S, at least MIN_WINDOW_SAMPLES of them,
#: that agree within MAX_WINDOW_SPREAD_RAD (a mower turning, or a field bending, does not)
WINDOW_S = 1.0
MIN_WINDOW_SAMPLES = 5
MAX_WINDOW_SPREAD_RAD = math.radians(10.0)


def _next_reading(
    times: list[float], t: float, mag_t: ArrayLike, accel: ArrayLike | None
) -> FieldReading | None:
    """The levelled reading at ``t``, or None: too soon after the last one kept (``times``),
    not finite, or no direction (``field_in_body``)."""
    if (times and t - times[-1] < KEEP_AFTER_S) or not math.isfinite(t):
        return None
    return field_in_body(mag_t, accel)


def _circular(angles: FloatArray) -> tuple[float, float]:
    """Circular mean and spread (rad) of angles."""
    c, s = float(np.cos(angles).mean()), float(np.sin(angles).mean())
    r = min(1.0, math.hypot(c, s))
    spread = math.sqrt(-2.0 * math.log(r)) if r > 1e-12 else math.pi
    return math.atan2(s, c), spread


class CompassCalibration:
    """The teach side: readings collected while the operator drives, fitted to the drive's
    headings in the map's frame once the trajectory is final (:meth:`fit`)."""

    def __init__(self) -> None:
        self._t: list[float] = []
        self._readings: list[FieldReading] = []

    def add(self, t: float, mag_t: ArrayLike, accel: ArrayLike | None = None) -> None:
        reading = _next_reading(self._t, t, mag_t, accel)
        if reading is not None:
            self._t.append(float(t))
            self._readings.append(reading)

    def fit(self, trajectory: FloatArray) -> CompassReference | None:
        """δ from the readings and the trajectory (K, 8: t, x, y, z, qw, qx, qy, qz in the
        map's frame); None with too few readings, or when they do not agree on one field
        (a mower whose magnetometer is disturbed has no compass)."""
        if len(self._t) < MIN_TEACH_SAMPLES or trajectory.shape[0] < 2:
            return None
        t = np.asarray(self._t)
        inside = (t >= trajectory[0, 0]) & (t <= trajectory[-1, 0])
        if int(inside.sum()) < MIN_TEACH_SAMPLES:
            return None
        heading = np.interp(t[inside], trajectory[:, 0], np.unwrap(quat_to_yaw(trajectory[:, 4:8])))
        alpha = np.array([r.alpha for r, ok in zip(self._readings, inside, strict=True) if ok])
        north, spread = _circular(heading + alpha)
        if spread > MAX_TEACH_SPREAD_RAD:
            return None
        strength = float(np.median([r.strength_t for r in self._readings]))
        dip = float(np.median([r.dip_rad for r in self._readings]))
        return CompassReference(wrap_angle(north), spread, strength, dip, int(inside.sum()))


class Compass:
    """The mow side: the body's heading in the map's frame from the last second's readings
    (:meth:`heading`), or None while they are too few, disagree, or are disturbed."""

    def __init__(self, reference: CompassReference) -> None:
        self.reference = reference
        self._t: list[float] = []
        self._alpha: list[float] = []
        self.disturbed = 0  # readings refused as not the taught field

    def add(self, t: float, mag_t: ArrayLike, accel: ArrayLike | None = None) -> None:
        reading = _next_reading(self._t, t, mag_t, accel)
        if reading is None:
            return
        if self.reference.disturbed(reading):
            self.disturbed += 1
            self._t.clear()  # a disturbed stretch breaks the window
            self._alpha.clear()
            return
        self._t.append(float(t))
        self._alpha.append(reading.alpha)
        while self._t and self._t[0] < t - WINDOW_S:
            self._t.pop(0)
            self._alpha.pop(0)

    def heading(self, t: float) -> tuple[float, float] | None:
        """(ψ, σ) in the map's frame at ``t`` from the readings of the second before it."""
        if len(self._t) < MIN_WINDOW_SAMPLES or t - self._t[-1] > 2 * SAMPLE_PERIOD_S + 0.05:
            return None
        alpha, spread = _circular(np.asarray(self._alpha))
        if spread > MAX_WINDOW_SPREAD_RAD:
            return None
        sigma = math.hypot(self.reference.sigma_rad, spread)
        return wrap_angle(self.reference.north_rad - alpha), sigma
