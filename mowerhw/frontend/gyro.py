"""Rotation between camera frames from the gyro, for KLT prediction and epipolar checks.

The front end is told the body rotation between its previous and current frame; the runtime
takes it from the raw gyro (:class:`RotationHistory`). A bias of a few mrad/s is 1 mrad over
a 4 Hz frame, far inside the tracking window and the epipolar threshold, so the raw gyro is
good enough and the front end needs no estimator state.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mowerhw.common.geometry import quat_conjugate, quat_exp, quat_multiply, quat_to_rotmat

FloatArray = NDArray[np.float64]


class RotationHistory:
    """Integrated body attitude ``q_0b(t)`` at every gyro sample, for ``history_s``.

    A sample is only kept when it comes (50–100 Hz); it is integrated when a rotation is asked
    for (once a frame) or when many wait — the same products in the same order, done back to
    back instead of one per wake-up."""

    #: integrate when this many samples wait (bounds the memory without frames)
    PENDING_MAX = 256

    def __init__(self, history_s: float = 3.0) -> None:
        self.history_s = history_s
        self._t: deque[float] = deque()
        self._q: deque[FloatArray] = deque()
        self._pending: list[tuple[float, FloatArray]] = []
        self._last_t: float | None = None

    def add(self, t: float, gyro_xyz: ArrayLike) -> None:
        """A gyro reading: the mean body rate over the interval ending at ``t``."""
        w = np.asarray(gyro_xyz, dtype=np.float64).reshape(3)
        t = float(t)
        if not math.isfinite(t + sum(w.tolist())):
            return
        if self._last_t is not None and t <= self._last_t:
            return
        self._last_t = t
        self._pending.append((t, w.copy()))
        if len(self._pending) >= self.PENDING_MAX:
            self._integrate()

    def _integrate(self) -> None:
        pending, self._pending = self._pending, []
        for t, w in pending:
            if not self._t:
                self._t.append(t)
                self._q.append(np.array([1.0, 0.0, 0.0, 0.0]))
                continue
            self._t.append(t)
            self._q.append(quat_multiply(self._q[-1], quat_exp(w * (t - self._t[-2]))))
        if pending:
            newest = self._t[-1]
            while len(self._t) > 2 and self._t[1] < newest - self.history_s:
                self._t.popleft()
                self._q.popleft()

    def _at(self, t: float) -> FloatArray | None:
        self._integrate()
        if not self._t or t < self._t[0] - 1e-6 or t > self._t[-1] + 0.05:
            return None
        ts = np.fromiter(self._t, float, len(self._t))
        k = int(np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)) if len(ts) > 1 else 0
        if len(ts) == 1 or t >= ts[-1]:
            return self._q[-1]
        t0, t1 = ts[k - 1], ts[k]
        q0, q1 = self._q[k - 1], self._q[k]
        # within one gyro interval the rate is constant: interpolate along it
        frac = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
        dq = quat_multiply(quat_conjugate(q0), q1)
        angle_axis = 2.0 * np.arctan2(np.linalg.norm(dq[1:]), dq[0])
        axis = dq[1:] / max(np.linalg.norm(dq[1:]), 1e-12)
        return quat_multiply(q0, quat_exp(axis * angle_axis * frac))

    def rotation_between(self, t0: float, t1: float) -> FloatArray | None:
        """``R_{b(t0) b(t1)}``: maps vectors of the body frame at ``t1`` into the one at
        ``t0``; None when the history does not cover both times."""
        q0, q1 = self._at(t0), self._at(t1)
        if q0 is None or q1 is None:
            return None
        return quat_to_rotmat(quat_multiply(quat_conjugate(q0), q1))
