"""Per-landmark nonlinear observers (paper §II, eqs 2–8; docs/design.md §4), vectorised.

Each landmark i has the state ``z = (d, y)``: its distance and unit direction in the current
body frame. All landmarks live in arrays (N,) and (N, 3) and are propagated and updated
together; landmarks are added and removed with array operations, never a Python loop per
landmark per sample.

* Propagation (eq. 2/4) at IMU rate. Eq. (2) is eq. (1), ``ẋ = −[ω]× x − v``, written for
  ``x = d y``; over one IMU interval with constant ω and v that flow is the rigid motion
  ``x⁺ = exp(ω Δt)ᵀ (x − Δ)``, which we apply exactly instead of an Euler step of (4).
* Update (eq. 5) at camera rate: ``d⁺ = d⁻ + l₁ (d_k − d⁻)``, ``y⁺ = y⁻ + l₂ (y_k − y⁻)``,
  then ``‖y‖ = 1`` and ``d ≥ d_min`` (Assumption 1). The gains come from eq. (7),
  ``l_m = 1 − exp(½ (γ_m − λ) Δt_k)``, with ``λ = λ_max(Fᵀ + F)`` of the Jacobian F of eq. (8)
  at each landmark's state: hybrid contraction at rate γ (eq. 11).

Beside the paper's state each landmark carries bookkeeping variances of d and of the
direction (what the EKF needs to weigh it and the map stores as its covariance). They follow
the same gains: ``σ²⁺ = (1 − l)² σ²⁻ + l² σ²_meas``.

Beyond the paper (``weighted_depth``, on by default): the depth gain is
``min(l₁, σ_d² / (σ_d² + σ²_{d_k}))`` — eq. (7)'s gain as an upper bound, lowered when a
pseudo-measurement is less precise than the estimate. Eq. (3) degrades badly as the baseline
shrinks (the mower coming back towards an anchor); a fixed gain would chase those
triangulations, the weighted gain holds the estimate made with good geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def contraction_rate(d: FloatArray, y: FloatArray, v: FloatArray, w: FloatArray) -> FloatArray:
    """λ = λ_max(Fᵀ + F) with F of eq. (8), per landmark: (N,).

    F = [[0, −vᵀ], [(I − yyᵀ) v / d², −[ω]× + (y vᵀ + (vᵀy) I) / d]]. The skew part −[ω]×
    cancels in Fᵀ + F, so ω does not enter.
    """
    del w  # documented: it cancels
    n = d.shape[0]
    vy = y @ v  # (N,)
    top = -v[None, :] + ((v[None, :] - vy[:, None] * y) / d[:, None] ** 2)  # row 0, cols 1..3
    block = (np.einsum("ni,j->nij", y, v) + vy[:, None, None] * np.eye(3)) / d[:, None, None]
    s = np.zeros((n, 4, 4))
    s[:, 0, 1:] = top
    s[:, 1:, 0] = top
    s[:, 1:, 1:] = block + np.swapaxes(block, 1, 2)
    return np.asarray(np.linalg.eigvalsh(s)[:, -1], dtype=np.float64)


def observer_gain(gamma: float, lam: FloatArray, dt_k: float) -> FloatArray:
    """Eq. (7): ``l = 1 − exp(½ (γ − λ) Δt_k)``, kept in [0, 1]."""
    return np.clip(1.0 - np.exp(0.5 * (gamma - lam) * dt_k), 0.0, 1.0)


@dataclass
class ObserverUpdateStats:
    direction_updates: int = 0
    depth_updates: int = 0
    depth_clamped: int = 0  # hit d_min (Assumption 1)


class LandmarkObservers:
    """The observers of every landmark currently tracked, as arrays."""

    def __init__(
        self, gamma1: float, gamma2: float, d_min: float, weighted_depth: bool = True
    ) -> None:
        if gamma1 >= 0 or gamma2 >= 0:
            raise ValueError("observer rates γ₁, γ₂ must be negative (eq. 7)")
        self.gamma1 = gamma1
        self.gamma2 = gamma2
        self.d_min = d_min
        self.weighted_depth = weighted_depth
        self.ids: IntArray = np.zeros(0, dtype=np.int64)
        self.d: FloatArray = np.zeros(0)
        self.y: FloatArray = np.zeros((0, 3))
        self.var_d: FloatArray = np.zeros(0)
        self.var_y: FloatArray = np.zeros(0)  # rad², isotropic about y
        self.depth_updates: IntArray = np.zeros(0, dtype=np.int64)
        self._row: dict[int, int] = {}
        self.stats = ObserverUpdateStats()

    def __len__(self) -> int:
        return int(self.ids.size)

    # -- bookkeeping --------------------------------------------------------------------------

    def rows(self, ids: IntArray) -> IntArray:
        """Row of each id (−1 if not tracked)."""
        get = self._row.get
        return np.fromiter((get(int(i), -1) for i in ids), dtype=np.int64, count=len(ids))

    def add(self, ids: IntArray, y: FloatArray, d0: float, var_d0: float, var_y0: float) -> None:
        """Start observers for new landmarks at direction ``y`` and depth ``d0``."""
        if ids.size == 0:
            return
        self.ids = np.concatenate([self.ids, ids])
        self.d = np.concatenate([self.d, np.full(ids.size, d0)])
        self.y = np.concatenate([self.y, y / np.linalg.norm(y, axis=-1, keepdims=True)])
        self.var_d = np.concatenate([self.var_d, np.full(ids.size, var_d0)])
        self.var_y = np.concatenate([self.var_y, np.full(ids.size, var_y0)])
        self.depth_updates = np.concatenate([self.depth_updates, np.zeros(ids.size, np.int64)])
        self._reindex()

    def remove(self, keep: NDArray[np.bool_]) -> None:
        """Keep only the rows where ``keep`` is True."""
        for name in ("ids", "d", "y", "var_d", "var_y", "depth_updates"):
            setattr(self, name, getattr(self, name)[keep])
        self._reindex()

    def _reindex(self) -> None:
        self._row = {int(i): r for r, i in enumerate(self.ids)}

    def positions(self) -> FloatArray:
        """Landmarks in the current body frame, ``x = d y`` (N, 3)."""
        return self.d[:, None] * self.y

    def covariances(self) -> FloatArray:
        """Approximate covariance of ``x = d y`` (N, 3, 3): σ_d² yyᵀ + d² σ_y² (I − yyᵀ)."""
        yy = np.einsum("ni,nj->nij", self.y, self.y)
        perp = np.eye(3)[None] - yy
        cov: FloatArray = self.var_d[:, None, None] * yy
        cov += (self.d**2 * self.var_y)[:, None, None] * perp
        return cov

    # -- eq. (2)/(4): propagation ---------------------------------------------------------------

    def propagate(self, c_old_new: FloatArray, displacement: FloatArray) -> None:
        """Move every landmark by one IMU interval of body motion (exact flow of eq. 1/2).

        ``c_old_new`` = exp(ω Δt) (3, 3), the new body axes in the old body frame;
        ``displacement`` Δ (3,), the new body origin in the old body frame.
        """
        if self.ids.size == 0:
            return
        x = (self.d[:, None] * self.y - displacement) @ c_old_new  # Cᵀ (x − Δ), row form
        self.d = np.linalg.norm(x, axis=-1)
        self.y = x / self.d[:, None]

    # -- eq. (5), (7): update -----------------------------------------------------------------

    def update(
        self,
        rows: IntArray,
        y_meas: FloatArray,
        var_y_meas: float,
        d_meas: FloatArray,
        var_d_meas: FloatArray,
        dt_k: float,
        v: FloatArray,
        w: FloatArray,
    ) -> None:
        """Update the landmarks at ``rows`` with measured bearings and depth pseudo-measurements
        (NaN depth: no pseudo-measurement this frame, direction only)."""
        if rows.size == 0:
            return
        d = self.d[rows]
        y = self.y[rows]
        lam = contraction_rate(d, y, v, w)
        l1 = observer_gain(self.gamma1, lam, dt_k)
        l2 = observer_gain(self.gamma2, lam, dt_k)
        # eq. (5): direction, then back onto the unit sphere
        y_new = y + l2[:, None] * (y_meas - y)
        y_new /= np.linalg.norm(y_new, axis=-1, keepdims=True)
        self.y[rows] = y_new
        self.var_y[rows] = (1 - l2) ** 2 * self.var_y[rows] + l2**2 * var_y_meas
        # eq. (5): depth where a pseudo-measurement exists, then Assumption 1
        has = np.isfinite(d_meas)
        r = rows[has]
        g = l1[has]
        if self.weighted_depth:
            # Never more than eq. (7)'s gain; less when the pseudo-measurement is poorer
            # than the estimate (a 1-D Kalman gain): noisy triangulations are not chased.
            prior = self.var_d[r]
            g = np.minimum(g, prior / (prior + var_d_meas[has]))
        d_new = d[has] + g * (d_meas[has] - d[has])
        clamped = d_new < self.d_min
        self.d[r] = np.maximum(d_new, self.d_min)
        self.var_d[r] = (1 - g) ** 2 * self.var_d[r] + g**2 * var_d_meas[has]
        self.depth_updates[r] += 1
        self.stats.direction_updates += int(rows.size)
        self.stats.depth_updates += int(r.size)
        self.stats.depth_clamped += int(clamped.sum())
