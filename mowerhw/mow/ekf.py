"""World-centric error-state EKF of the mow phase (paper §IV, eqs 21–23; docs/design.md §5).

State: the body's world position ``x = x_b^w``, orientation ``q = q_wb``, the gyro bias and
the yaw rate's scale error ``k`` (beyond the paper: a MEMS gyro that reads 3 % high turns
every 180° edge turn into 185°). Error state (10), in the teach filter's order (position,
rotation, bias, then the scale): ``δx``, ``δθ`` (world frame, ``R_wb = exp([δθ]×) R̂_wb``),
``δb``, ``δk``. Only this module indexes it (:data:`X`, :data:`TH`, :data:`BG`, :data:`SC`).

Propagation (eq. 21): ``ẋ = R(q) v``, ``q̇ = ½ q ⊗ (0, ω)`` with ``ω = (ω_m − b)`` and its z
component times ``1 − k``, ``v = (speed, 0, 0)``; the mean moves by the exact rigid motion of
one IMU interval (:class:`mowerhw.estimation.odometry.BodyMotion`), the error by

    δθ' = δθ − R̂' Δt (δb + ω_z ẑ δk + n_g)
    δx' = δx − [R̂ Δ]× δθ + R̂ Δt n_v
    δb' = δb + n_b,  δk' = δk + n_k

Update (eqs 22–23): a map landmark at ``L_i`` (world) is seen along
``h = normalize(R(q)ᵀ (L_i − x))``; the residual lives in the tangent plane of the measured
bearing. Each landmark is χ²-gated on its own 2×2 innovation covariance.

The map's landmark positions are themselves estimates, and the same map errors are met in
every frame: they are Schmidt *consider* parameters (cross-covariance ``P_xL`` with the state,
propagated with Φ, never estimated away), so the pose covariance never shrinks below what
the map can support.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from mowerhw.common.geometry import (
    IDENTITY_QUAT,
    quat_exp,
    quat_multiply_unit,
    quat_normalize,
    quat_to_rotmat,
    skew,
    tangent_basis,
)
from mowerhw.estimation.odometry import BodyMotion

FloatArray = NDArray[np.float64]

X, TH, BG, SC = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 10)
K_ = 9  # the scale error's index
YAW = 5  # the world-z component of δθ
N_ERR = 10  # error-state size
#: the yaw-rate scale error drifts this much per √s (temperature): a little, so it can follow
SCALE_WALK = 2e-5


@dataclass
class LocalizerNoise:
    gyro: float = 1e-4  # rad/s/√Hz
    gyro_bias_walk: float = 2e-6  # rad/s²/√Hz
    speed: float = 2e-3  # m/s/√Hz
    lateral: float = 3e-3  # m/s/√Hz
    scale_sigma: float = 0.005  # prior σ of the yaw rate's scale error


#: a bearing the update leaves this far off its own σ (χ²₂ at 99.9 %) is no pairing of
#: that landmark (:meth:`WorldPoseEKF._fit`) — when it is one of a few
POSTERIOR_GATE = float(chi2.ppf(0.999, df=2))
FAR_OFF_SHARE = 0.25
#: an update's correction, gain, innovation covariance, H_x and H_L P_LL
_Gain = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]


@dataclass(frozen=True)
class _Linearised:
    """A frame's bearings linearised for eq. (23): map rows, residuals (N, 2), ``H_x``,
    ``H_L``, the bearing σ, and the stamp error's shared term (with its σ)."""

    rows: NDArray[np.int64]
    res: FloatArray
    hx: FloatArray
    hl: FloatArray
    sigma: float
    shared: FloatArray | None
    stamp_sigma: float


@dataclass
class UpdateOutcome:
    accepted: NDArray[np.bool_]
    nis: FloatArray
    used: int = 0
    rejected: int = 0


@dataclass
class EkfState:
    """Everything needed to restart the filter from a point in time (late frames)."""

    x: FloatArray
    q: FloatArray
    bg: FloatArray
    P: FloatArray
    pxl: FloatArray = field(repr=False)
    k: float = 0.0  # yaw-rate scale error

    def set_bias(self, bias: FloatArray, var: float) -> None:
        """The gyro bias known out of band (a standstill calibration), with variance ``var``
        and no correlation with the rest."""
        _set_bias(self, bias, var)

    def copy(self) -> EkfState:
        return EkfState(
            self.x.copy(), self.q.copy(), self.bg.copy(), self.P.copy(), self.pxl.copy(), self.k
        )

    def finite(self) -> bool:
        """Every number of the state and its covariance is finite (:func:`_state_finite`)."""
        return _state_finite(self)


def _state_finite(s: EkfState | WorldPoseEKF) -> bool:
    """The one finite check of a filter state: one sum per array — a NaN or an infinity
    anywhere makes it non-finite (a sum that overflows from finite entries is as unusable).
    Checked twice an IMU sample: the small vectors summed as Python floats, the covariance
    by the ufunc's own reduce (without ``ndarray.sum``'s wrapper)."""
    total = float(np.add.reduce(s.P, None)) + sum(s.x.tolist()) + sum(s.q.tolist())
    return math.isfinite(total + sum(s.bg.tolist()) + s.k)


def _set_bias(s: EkfState | WorldPoseEKF, bias: FloatArray, var: float) -> None:
    s.bg = np.asarray(bias, dtype=np.float64).copy()
    s.P[BG, :] = 0.0
    s.P[:, BG] = 0.0
    s.P[BG, BG] = np.eye(3) * var
    s.pxl[BG, :] = 0.0


class WorldPoseEKF:
    """Pose of the body in the map's world frame, plus gyro bias."""

    def __init__(
        self,
        noise: LocalizerNoise,
        landmark_cov: FloatArray,
        gate_probability: float = 0.999,
    ) -> None:
        self.noise = noise
        self.x = np.zeros(3)
        self.q = IDENTITY_QUAT.copy()
        self.bg = np.zeros(3)
        self.k = 0.0
        self.P = np.zeros((N_ERR, N_ERR))
        self.P[SC, SC] = noise.scale_sigma**2
        self.landmark_cov = np.asarray(landmark_cov, dtype=np.float64).reshape(-1, 3, 3)
        self.pxl = np.zeros((N_ERR, 3 * self.landmark_cov.shape[0]))  # P_xL (consider)
        self.gate = float(chi2.ppf(gate_probability, df=2))
        self._qv = np.array([noise.speed**2, noise.lateral**2, noise.lateral**2])
        self._eye = np.eye(N_ERR)
        self._q_per_s = np.zeros((N_ERR, N_ERR))
        self._q_per_s[TH, TH] = np.eye(3) * noise.gyro**2
        self._q_per_s[BG, BG] = np.eye(3) * noise.gyro_bias_walk**2
        self._q_per_s[K_, K_] = SCALE_WALK**2

    # -- state handling -----------------------------------------------------------------------

    def snapshot(self) -> EkfState:
        return EkfState(
            self.x.copy(), self.q.copy(), self.bg.copy(), self.P.copy(), self.pxl.copy(), self.k
        )

    def snapshot_view(self) -> EkfState:
        """The current state without copying (read only)."""
        return EkfState(self.x, self.q, self.bg, self.P, self.pxl, self.k)

    def corrected_rate(self, gyro: FloatArray) -> FloatArray:
        """The body rate from a gyro reading: bias out, the yaw rate's scale error out."""
        w = np.asarray(gyro, dtype=np.float64) - self.bg
        w[2] *= 1.0 - self.k
        return w

    def predict_bearings(
        self,
        rows: NDArray[np.int64],
        landmarks_w: FloatArray,
        sigma: float,
        state: EkfState | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Where map landmarks ``rows`` should be seen from ``state`` (default: now): unit
        bearings (N, 3) and the covariance (N, 2, 2) of a measurement about them, in the
        tangent basis of each predicted bearing (eq. 22 linearised, map and pose
        uncertainty and bearing noise ``sigma``); for gating re-identification."""
        st = state if state is not None else self.snapshot_view()
        if rows.size == 0:
            return np.zeros((0, 3)), np.zeros((0, 2, 2))
        h, _, _, _, s_each = _bearing_model(st, self.landmark_cov, rows, landmarks_w, None, sigma)
        return h, s_each

    def restore(self, s: EkfState) -> None:
        self.x, self.q, self.bg = s.x.copy(), s.q.copy(), s.bg.copy()
        self.P, self.pxl = s.P.copy(), s.pxl.copy()
        self.k = s.k

    def reset(
        self,
        x: FloatArray,
        q: FloatArray,
        sigma_pos: float,
        sigma_rot: FloatArray,
        bias: FloatArray | None = None,
        bias_var: float | None = None,
        planar_cov: FloatArray | None = None,
    ) -> None:
        """Start over at pose (x, q) with the given σ (rotation σ per world axis), or, for
        (x, y, heading), ``planar_cov`` (3, 3) — an answer fitted in the plane."""
        self.x = np.asarray(x, dtype=np.float64).copy()
        self.q = quat_normalize(q)
        if bias is not None:
            self.bg = np.asarray(bias, dtype=np.float64).copy()
        p = np.zeros((N_ERR, N_ERR))
        p[TH, TH] = np.diag(np.asarray(sigma_rot, dtype=np.float64) ** 2)
        p[X, X] = np.eye(3) * sigma_pos**2
        old_bias = self.P[BG, BG].copy()
        p[BG, BG] = np.eye(3) * bias_var if bias_var is not None else old_bias
        p[SC, SC] = self.P[SC, SC]  # what is known of the gyro's scale survives a restart
        if planar_cov is not None:
            planar = np.array([0, 1, YAW])
            p[np.ix_(planar, planar)] = planar_cov
        self.P = p
        self.pxl[:] = 0.0

    def set_landmark_cross(self, rows: NDArray[np.int64], cross: FloatArray) -> None:
        """After :meth:`reset` at a fitted pose: the (x, y, heading) error's cross-covariance
        (3, 3·len(rows)) with map landmarks ``rows`` — a pose fitted to landmarks shares
        their errors, and the same landmarks seen again must not count as news. The pose's
        covariance is raised, where it is less than the part of it those errors explain
        (``C P_L⁻¹ Cᵀ``), to that part: the joint covariance stays positive semi-definite
        and the pose is never surer than the map allows."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        c = np.asarray(cross, dtype=np.float64).reshape(3, 3 * rows.size)
        if rows.size == 0 or not np.all(np.isfinite(c)):
            return
        pose = np.array([0, 1, YAW])
        blocks = c.reshape(3, rows.size, 3).transpose(1, 0, 2)  # (k, 3 pose, 3 axis)
        explained = np.einsum(
            "kia,kab,kjb->ij", blocks, np.linalg.pinv(self.landmark_cov[rows]), blocks
        )
        short, basis = np.linalg.eigh(1.001 * explained - self.P[np.ix_(pose, pose)])
        self.P[np.ix_(pose, pose)] += (basis * np.maximum(short, 0.0)) @ basis.T
        cols = (3 * rows[:, None] + np.arange(3)[None, :]).reshape(-1)
        self.pxl[np.ix_(pose, cols)] = c

    def set_scale(self, k: float, sigma: float) -> None:
        """The yaw rate's scale error known out of band (what the teach learnt), with σ
        ``sigma`` (its change since) and no correlation with the rest."""
        self.k = float(k)
        self.P[SC, :] = 0.0
        self.P[:, SC] = 0.0
        self.P[K_, K_] = sigma**2
        self.pxl[SC, :] = 0.0

    def reopen_scale(self, sigma: float) -> None:
        """Make the yaw rate's scale error at least ``sigma`` uncertain again (a larger
        variance on the diagonal: the covariance stays positive semi-definite)."""
        self.P[K_, K_] = max(float(self.P[K_, K_]), sigma**2)

    def set_bias(self, bias: FloatArray, var: float) -> None:
        """As :meth:`EkfState.set_bias`."""
        _set_bias(self, bias, var)

    def inflate(self, sigma_pos: float, sigma_yaw: float) -> None:
        """Widen the pose uncertainty (recovery from a lock-out)."""
        self.widen(sigma_pos**2, sigma_yaw**2)

    def widen(self, xy_var: float, yaw_var: float) -> None:
        """Add horizontal position and yaw variance the motion model does not know about."""
        if xy_var > 0.0:
            self.P[0:2, 0:2] += np.eye(2) * xy_var
        if yaw_var > 0.0:
            self.P[YAW, YAW] += yaw_var

    def pose_covariance(self) -> FloatArray:
        """(6, 6): position, then rotation (world axes)."""
        return self.P[:6, :6].copy()

    def sigma_xy(self) -> float:
        """Largest standard deviation of the horizontal position (m)."""
        return largest_sigma_xy(self.P)

    @property
    def R(self) -> FloatArray:
        return quat_to_rotmat(self.q)

    def finite(self) -> bool:
        """Every number of the state and its covariance is finite (:func:`_state_finite`)."""
        return _state_finite(self)

    # -- eq. (21): propagation ------------------------------------------------------------------

    def propagate(self, m: BodyMotion, wheels_still: bool = False) -> None:
        """Carry the state over one IMU interval (eq. 21); ``wheels_still``: the ground
        speed read exactly 0 over it (0.001 m/s a bit on the wire, docs/design.md §7)."""
        r = quat_to_rotmat(self.q)
        disp_w = r @ m.disp
        self.x = self.x + disp_w
        self.q = quat_multiply_unit(self.q, m.dq)
        r_new = quat_to_rotmat(self.q)
        dt = m.dt
        phi = self._eye.copy()
        phi[TH, BG] = r_new * -dt
        phi[TH, K_] = r_new[:, 2] * -(float(m.w[2]) * dt)  # the yaw rate's scale error
        dx, dy, dz = disp_w.tolist()
        phi[X, TH] = ((0.0, dz, -dy), (-dz, 0.0, dx), (dy, -dx, 0.0))  # −[disp_w]×
        q = self._q_per_s * dt  # attitude, bias and scale random walks (diagonal)
        if not wheels_still:
            # the speed and slip densities are the noise of a mower that moves; a standing
            # one does not slide (a lifted or carried one is the lift's and the localizer's
            # to see; a stale speed widens the pose in the localizer)
            q[X, X] = (r * self._qv) @ r.T * dt
        self.P = phi @ self.P @ phi.T + q
        if self.pxl.shape[1]:
            self.pxl = phi @ self.pxl

    # -- eqs (22)–(23): update ------------------------------------------------------------------

    def update(
        self,
        rows: NDArray[np.int64],
        landmarks_w: FloatArray,
        bearings: FloatArray,
        sigma: float,
        rate: FloatArray | None = None,
        stamp_sigma: float = 0.0,
        own_sigma: float | None = None,
    ) -> UpdateOutcome:
        """Update with bearings (body frame) of map landmarks ``rows`` at ``landmarks_w``.
        ``stamp_sigma``: the frame's timestamp 1σ (s); with the body ``rate`` (rad/s) it
        turns every bearing alike, ``∂z/∂t = −ω × h`` — one error the frame's bearings share,
        not one each. ``own_sigma``: a bearing's own σ in this frame (``sigma`` less what it
        shares with other frames); with it, a few bearings the update would leave far off it
        are refused and the update made without them (:meth:`_fit`)."""
        n = rows.size
        if n == 0:
            return UpdateOutcome(np.zeros(0, bool), np.zeros(0))
        h, bt, hx, hl, s_each = _bearing_model(
            self.snapshot_view(), self.landmark_cov, rows, landmarks_w, bearings, sigma
        )
        shared = None  # (N, 2): each residual's change per second of stamp error
        if stamp_sigma > 0.0 and rate is not None:
            shared = np.einsum("nij,nj->ni", bt, -np.cross(np.asarray(rate, np.float64), h))
            s_each = s_each + stamp_sigma**2 * np.einsum("ni,nj->nij", shared, shared)
        res = np.einsum("nij,nj->ni", bt, bearings - h)
        nis = np.einsum("ni,nij,nj->n", res, np.linalg.inv(s_each), res)
        ok = np.isfinite(nis) & (nis <= self.gate)
        if not ok.any():
            return UpdateOutcome(ok, nis, 0, n)
        frame = _Linearised(rows, res, hx, hl, sigma, shared, stamp_sigma)
        ok, (dx, K, S, Hx, pll_hl) = self._fit(frame, ok, nis, own_sigma)
        out = UpdateOutcome(ok, nis, int(ok.sum()), int((~ok).sum()))
        self.P = self.P - K @ S @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        if self.pxl.shape[1]:
            self.pxl = self.pxl - K @ (Hx @ self.pxl + pll_hl)
        self.q = quat_multiply_unit(quat_exp(dx[TH]), self.q)
        self.x = self.x + dx[X]
        self.bg = self.bg + dx[BG]
        self.k = self.k + float(dx[K_])
        return out

    def _fit(
        self,
        frame: _Linearised,
        ok: NDArray[np.bool_],
        nis: FloatArray,
        own_sigma: float | None,
    ) -> tuple[NDArray[np.bool_], _Gain]:
        """The bearings to update with and their :meth:`_gain`: every gated one, unless the
        update leaves some beyond :data:`POSTERIOR_GATE` of their own σ (``own_sigma``) —
        then without at most :data:`FAR_OFF_SHARE` of them: those the update leaves far off
        when they are a few, else (the update was dragged, the many left off) the most
        surprising one before it, the largest NIS, one at a time, until none is left far off.
        One wrong pairing of a near landmark, let through the χ² gate by a loose pose, pulls
        the pose far more than many far landmarks hold it (measured on the bench: a mower
        standing with its speed silent, σ 6 cm, one corner 3 m away paired 3° off moved the
        pose 9 cm, and the standing frames after could not move it back). With no such
        subset, every gated bearing (the pose itself is off: the localizer's agreement
        rules judge that)."""
        first = self._gain(frame, ok)
        if own_sigma is None:
            return ok, first
        keep, fit = ok.copy(), first
        budget = int(FAR_OFF_SHARE * ok.sum())
        limit = POSTERIOR_GATE * own_sigma**2
        while True:
            dx, Hx = fit[0], fit[3]
            post = frame.res[keep] - (Hx @ dx).reshape(-1, 2)  # each residual after it
            far = np.einsum("ni,ni->n", post, post) > limit
            if not far.any():
                return keep, fit
            idx = np.flatnonzero(keep)
            room = budget - int((ok & ~keep).sum())
            out = idx[far] if far.sum() <= room else idx[[int(np.argmax(nis[idx]))]]
            if out.size > room:
                return ok, first
            keep[out] = False
            fit = self._gain(frame, keep)

    def _gain(self, frame: _Linearised, ok: NDArray[np.bool_]) -> _Gain:
        """Eq. (23) for the bearings ``ok``: the correction, the gain, the innovation
        covariance, ``H_x`` and ``H_L P_LL`` (for the cross-covariance)."""
        rows, res, hx, hl, sigma = frame.rows, frame.res, frame.hx, frame.hl, frame.sigma
        shared, stamp_sigma = frame.shared, frame.stamp_sigma
        k = int(ok.sum())
        Hx = hx[ok].reshape(2 * k, N_ERR)
        # H_L as a dense (2k, 3·len(map)) matrix over the observed landmarks' columns only
        sel = rows[ok]
        r_idx = (2 * np.arange(k)[:, None, None] + np.arange(2)[None, :, None]).repeat(3, 2)
        c_idx = (3 * sel[:, None, None] + np.arange(3)[None, None, :]).repeat(2, 1)
        hl_full = np.zeros((2 * k, self.pxl.shape[1]))
        hl_full[r_idx, c_idx] = hl[ok]
        pll_hl = np.zeros_like(hl_full)  # H_L P_LL (P_LL is block diagonal)
        pll_hl[r_idx, c_idx] = hl[ok] @ self.landmark_cov[sel]
        ph = self.P @ Hx.T + self.pxl @ hl_full.T  # (10, 2k)
        S = Hx @ ph + hl_full @ (self.pxl.T @ Hx.T) + pll_hl @ hl_full.T
        S += sigma**2 * np.eye(2 * k)
        if shared is not None:
            g = shared[ok].reshape(-1)
            S += stamp_sigma**2 * np.outer(g, g)
        K = np.asarray(np.linalg.solve(S, ph.T).T, dtype=np.float64)
        dx: FloatArray = K @ res[ok].reshape(-1)
        return dx, K, S, Hx, pll_hl


def _bearing_model(
    st: EkfState,
    landmark_cov: FloatArray,
    rows: NDArray[np.int64],
    landmarks_w: FloatArray,
    bearings: FloatArray | None,
    sigma: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Eq. (22) linearised at ``st``: predicted bearings ``h``, the residual basis (that of
    the measured bearings, or of ``h`` for a prediction), ``H_x`` (N, 2, 10), ``H_L`` (N, 2, 3)
    and each landmark's innovation covariance with its consider terms (N, 2, 2)."""
    n = rows.size
    r = quat_to_rotmat(st.q)
    d = landmarks_w - st.x
    ell = d @ r  # R(q)ᵀ (L − x)
    norm = np.linalg.norm(ell, axis=1)
    h = ell / norm[:, None]
    dh = (np.eye(3)[None] - np.einsum("ni,nj->nij", h, h)) / norm[:, None, None]
    bt = np.swapaxes(tangent_basis(h if bearings is None else bearings), 1, 2)
    a = np.einsum("nij,njk->nik", bt, dh) @ r.T  # (N, 2, 3): ∂r/∂(world vector)
    hx = np.zeros((n, 2, N_ERR))
    hx[:, :, TH] = np.einsum("nij,njk->nik", a, skew(d))  # ∂ℓ/∂δθ = Rᵀ [d]×
    hx[:, :, X] = -a
    hl = a  # ∂/∂L
    # per-landmark innovation covariance, with the consider terms of that landmark
    cols = 3 * rows[:, None] + np.arange(3)[None, :]  # (N, 3) columns in P_xL
    pxl_i = st.pxl[:, cols]  # (10, N, 3)
    cov_l = landmark_cov[rows]
    s_each = (
        np.einsum("nij,jk,nlk->nil", hx, st.P, hx)
        + np.einsum("nij,jnk,nlk->nil", hx, pxl_i, hl)
        + np.einsum("nij,knj,nlk->nil", hl, pxl_i, hx)
        + np.einsum("nij,njk,nlk->nil", hl, cov_l, hl)
        + sigma**2 * np.eye(2)[None]
    )
    return h, bt, hx, hl, s_each


def largest_sigma_xy(cov: FloatArray) -> float:
    """Largest standard deviation (m) of the horizontal position whose covariance is
    ``cov[:2, :2]``: the larger eigenvalue of the symmetric 2×2 block in closed form (per IMU
    sample); NaN stays NaN."""
    a, b, c = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    largest = 0.5 * (a + c) + math.hypot(0.5 * (a - c), b)
    return math.sqrt(largest) if largest > 0.0 else (largest if math.isnan(largest) else 0.0)
