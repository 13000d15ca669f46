"""Odometry building blocks shared by every estimator: body motion and ground speed.

* :class:`BodyMotion` — one IMU interval of rigid motion for a constant body rate and velocity
  (exact: rotation ``exp(ω Δt)``, displacement ``J_l(ω Δt) v Δt``).
* :class:`SpeedTrack` — the 10 Hz ground speed turned into a speed for each 100 Hz IMU
  interval: on-line, the newest sample extrapolated along the slope of the last two (a
  first-order hold: holding the value alone lags every acceleration by half a speed period,
  ≈ 2 cm per start or stop); after the fact, interpolation.
* :func:`accel_shaped_speeds` — after the fact, between two samples, the speed the
  accelerometer's along-track acceleration shows, made to agree with both samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import quat_exp, quat_to_rotmat

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BodyMotion:
    """One IMU interval of rigid body motion for constant body rate ω and velocity v.

    ``dq = exp(ω Δt)`` and ``c = R(dq)``: the new body axes in the old body frame;
    ``disp = ∫₀^Δt exp([ω]× τ) v dτ = J_l(ω Δt) v Δt``: the new origin in the old frame, with
    the SO(3) left Jacobian ``J_l(φ) = I + (1 − cos θ)/θ² [φ]× + (θ − sin θ)/θ³ [φ]×²``.
    Exact for constant ω and v.
    """

    dq: FloatArray
    disp: FloatArray
    w: FloatArray
    dt: float

    @classmethod
    def of(cls, w: FloatArray, v: FloatArray, dt: float) -> BodyMotion:
        phi = w * dt
        return cls(quat_exp(phi), left_jacobian_times(phi, v * dt), w, dt)

    @cached_property
    def c(self) -> FloatArray:
        """``R(dq)``, computed once when first asked (the teach filter and its landmark
        observers both read it; the world-centric filter does not need it)."""
        return quat_to_rotmat(self.dq)


def camera_velocity(
    speed: float, w: FloatArray, contact_b: FloatArray | tuple[float, float, float]
) -> FloatArray:
    """Velocity of the body origin (the camera centre) from the ground speed measured at
    ``contact_b`` (the wheels' contact point, body frame) and the body rate: ``v = s x̂ −
    ω × p``. On bumps a camera on a 0.8 m mast swings sideways by ``0.8 m × ω`` — the wheels
    do not see that."""
    px, py, pz = float(contact_b[0]), float(contact_b[1]), float(contact_b[2])
    wx, wy, wz = float(w[0]), float(w[1]), float(w[2])
    return np.array([speed - (wy * pz - wz * py), -(wz * px - wx * pz), -(wx * py - wy * px)])


def left_jacobian_times(phi: FloatArray, u: FloatArray) -> FloatArray:
    """``J_l(φ) u`` for single 3-vectors (closed form, no matrices)."""
    (px, py, pz), (ux, uy, uz) = phi.tolist(), u.tolist()
    t2 = px * px + py * py + pz * pz
    if t2 < 1e-12:
        a, b = 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        t = math.sqrt(t2)
        a, b = (1.0 - math.cos(t)) / t2, (t - math.sin(t)) / (t2 * t)
    cx, cy, cz = py * uz - pz * uy, pz * ux - px * uz, px * uy - py * ux  # φ × u
    ccx, ccy, ccz = py * cz - pz * cy, pz * cx - px * cz, px * cy - py * cx  # φ × (φ × u)
    return np.array([ux + a * cx + b * ccx, uy + a * cy + b * ccy, uz + a * cz + b * ccz])


class SpeedTrack:
    """The ground-speed samples seen so far, and the speed to use for an IMU interval."""

    #: extrapolate at most this far past the newest sample
    EXTRAPOLATE_S = 0.15

    def __init__(self) -> None:
        self.samples: list[tuple[float, float]] = []
        self.latest = 0.0

    def add(self, t: float, v: float) -> None:
        self.samples.append((float(t), float(v)))
        self.latest = float(v)
        if len(self.samples) > 4096:  # keep memory bounded on long runs
            del self.samples[:2048]

    @property
    def last_time(self) -> float | None:
        return self.samples[-1][0] if self.samples else None

    def at(self, t_mid: float) -> float:
        """Speed for an IMU interval centred at ``t_mid`` (on-line: first-order hold)."""
        s = self.samples
        if len(s) < 2:
            return self.latest
        (t1, v1), (t2, v2) = s[-2], s[-1]
        ahead = t_mid - t2
        if t2 - t1 <= 0 or not 0.0 <= ahead <= self.EXTRAPOLATE_S:
            return v2
        v = v2 + (v2 - v1) / (t2 - t1) * ahead
        return v if v * v2 > 0 else 0.0  # never extrapolate through a stop

    def known(self, t_mid: float) -> float:
        """Speed for an interval centred at ``t_mid`` with what is known now: linear
        interpolation between the samples around it; past the newest, :meth:`at`."""
        s = self.samples
        if len(s) < 2 or t_mid >= s[-1][0]:
            return self.at(t_mid)
        k = len(s) - 1
        while k > 1 and s[k - 1][0] > t_mid:
            k -= 1
        (ta, va), (tb, vb) = s[k - 1], s[k]
        if t_mid <= ta or tb <= ta:
            return va
        return va + (vb - va) * (t_mid - ta) / (tb - ta)

    def distance(self, t0: float, t1: float) -> float:
        """Distance (m, unsigned) driven from ``t0`` to ``t1`` by the samples taken up to
        ``t1`` — each the speed of the interval before it, the newest held after it — so the
        answer does not depend on samples that came later; 0 without samples."""
        s = self.samples
        k = len(s)
        while k > 0 and s[k - 1][0] > t1:
            k -= 1
        if k == 0:
            return 0.0
        total = abs(s[k - 1][1]) * max(0.0, t1 - max(t0, s[k - 1][0]))  # after the newest
        end = s[k - 1][0]
        for j in range(k - 1, 0, -1):
            start = s[j - 1][0]
            if end <= t0:
                break
            total += abs(s[j][1]) * max(0.0, min(end, t1) - max(start, t0))
            end = start
        return total

    def interpolate(self, t: FloatArray) -> FloatArray:
        """After the fact: linear interpolation at times ``t``."""
        if len(self.samples) < 2:
            return np.full(np.shape(t), self.latest)
        arr = np.asarray(self.samples)
        return np.interp(t, arr[:, 0], arr[:, 1])


def accel_shaped_speeds(
    a: tuple[float, float],
    b: tuple[float, float],
    steps: FloatArray,
    at: FloatArray,
    max_miss: float,
) -> FloatArray | None:
    """The ground speed at times ``at`` (after ``a``'s time) between two speed samples ``a``
    and ``b`` (time, m/s) and just past ``b``, from IMU steps ``steps`` (rows ``t0, t1,
    along``: each interval's along-track acceleration, m/s², in time order): the speed the
    acceleration integrates to from ``a``, plus its miss at ``b`` spread in proportion to
    the time since ``a`` (a constant acceleration error, the accelerometer's bias or a
    slope's share, is taken out exactly), the miss held past ``b``. With no acceleration
    the straight line between the samples, as :meth:`SpeedTrack.known` interpolates; a
    set-off between two samples is a bend in it, which the line cut (1 mm ahead for good at
    every set-off 30 ms after a sample at 1 m/s²). None when the steps do not cover ``a``
    to ``b`` without a gap, or when the miss is beyond ``max_miss`` (m/s): then the
    acceleration was not the wheels' (a bump's spike, a skid) and the line is the better
    guess."""
    (ta, va), (tb, vb) = a, b
    if tb <= ta or steps.size == 0:
        return None
    t0, t1, along = steps[:, 0], steps[:, 1], steps[:, 2]
    if t0[0] > ta + 1e-9 or t1[-1] < tb - 1e-9 or np.any(np.abs(t0[1:] - t1[:-1]) > 1e-9):
        return None
    start = np.maximum(t0, ta)  # each step's part after ``a``
    gained = np.concatenate([[0.0], np.cumsum(along * np.maximum(t1 - start, 0.0))])

    def integrated(t: FloatArray) -> FloatArray:
        j = np.clip(np.searchsorted(t1, t, side="left"), 0, len(t1) - 1)
        return va + gained[j] + along[j] * np.maximum(t - start[j], 0.0)

    miss = vb - float(integrated(np.array([tb]))[0])
    if abs(miss) > max_miss:
        return None
    t = np.asarray(at, dtype=np.float64)
    return integrated(t) + miss * np.minimum((t - ta) / (tb - ta), 1.0)
