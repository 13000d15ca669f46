"""The Earth's magnetic field as the mower reads it, and as a map keeps it (issue 18).

Plain records and geometry shared by the map file (:mod:`mowerhw.map`: ``compass``) and the
compass estimators (:mod:`mowerhw.estimation.compass`, whose doc explains the angles): a
levelled reading's direction ``α`` in the body frame, and the taught field's direction ``δ``
in the map's frame with its strength and dip."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from mowerhw.common.geometry import cross_rows, wrap_angle

#: a reading's strength may differ from the taught field's by this share, its dip by this
STRENGTH_TOLERANCE = 0.15
DIP_TOLERANCE_RAD = math.radians(8.0)


@dataclass(frozen=True)
class FieldReading:
    """One levelled reading: ``alpha`` (rad, body frame), strength (T), dip (rad, + down)."""

    alpha: float
    strength_t: float
    dip_rad: float


def field_in_body(mag_t: ArrayLike, accel: ArrayLike | None = None) -> FieldReading | None:
    """The field's horizontal direction in the body's levelled frame (module doc), from a
    body-frame magnetometer reading (T) and, when there is one, the accelerometer's
    specific force (m/s², body frame: up when at rest). None for a reading that is not
    finite, zero, or (nearly) vertical, and for a body standing on its end."""
    m = np.asarray(mag_t, dtype=np.float64).reshape(3)
    up = np.array([0.0, 0.0, 1.0])
    if accel is not None:
        f = np.asarray(accel, dtype=np.float64).reshape(3)
        norm_f = float(np.linalg.norm(f))
        if math.isfinite(norm_f) and 5.0 < norm_f < 15.0:  # roughly 1 g: gravity, not a jolt
            up = f / norm_f
    strength = float(np.linalg.norm(m))
    if not math.isfinite(strength) or strength <= 0.0:
        return None
    m_h = m - float(m @ up) * up
    if float(np.linalg.norm(m_h)) < 0.05 * strength:
        return None
    x_h = np.array([1.0, 0.0, 0.0]) - up[0] * up
    if float(np.linalg.norm(x_h)) < 0.1:  # the body's x axis points (nearly) up: on its end
        return None
    x_h /= np.linalg.norm(x_h)
    y_h = cross_rows(up[None, :], x_h[None, :])[0]  # up × x_h: np.cross's values
    alpha = math.atan2(float(m_h @ y_h), float(m_h @ x_h))
    dip = math.asin(max(-1.0, min(1.0, -float(m @ up) / strength)))
    return FieldReading(alpha, strength, dip)


@dataclass(frozen=True)
class CompassReference:
    """The taught field in the map's frame: ``north_rad`` = δ (module doc), the spread of
    the teach drive's readings about it, the field's strength and dip, how many readings."""

    north_rad: float
    sigma_rad: float
    strength_t: float
    dip_rad: float
    samples: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "north_rad": self.north_rad,
            "sigma_rad": self.sigma_rad,
            "strength_t": self.strength_t,
            "dip_rad": self.dip_rad,
            "samples": self.samples,
        }

    @classmethod
    def from_dict(cls, d: Any) -> CompassReference:
        """From a map file's ``compass``; ValueError naming what is wrong."""
        if not isinstance(d, dict):
            raise ValueError("compass: expected an object")
        fields = ("north_rad", "sigma_rad", "strength_t", "dip_rad", "samples")
        missing = [k for k in fields if k not in d]
        if missing:
            raise ValueError(f"compass: missing {', '.join(missing)}")
        vals = []
        for k in fields:
            v = d[k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"compass.{k}: expected a finite number, got {v!r}")
            vals.append(float(v))
        north, sigma, strength, dip, samples = vals
        if not 0.0 <= sigma <= math.pi:
            raise ValueError(f"compass.sigma_rad: {sigma} is not within 0 … π")
        if not 0.0 < strength < 1e-3:
            raise ValueError(f"compass.strength_t: {strength} T is not a geomagnetic field")
        if abs(dip) > math.pi / 2:
            raise ValueError(f"compass.dip_rad: {dip} is not within −π/2 … π/2")
        if samples < 1 or samples != int(samples):
            raise ValueError(f"compass.samples: {samples} is not a positive whole number")
        return cls(wrap_angle(north), sigma, strength, dip, int(samples))

    def disturbed(self, reading: FieldReading) -> bool:
        """A reading whose strength or dip is not the taught field's (module doc)."""
        off = abs(reading.strength_t - self.strength_t) > STRENGTH_TOLERANCE * self.strength_t
        return off or abs(reading.dip_rad - self.dip_rad) > DIP_TOLERANCE_RAD
