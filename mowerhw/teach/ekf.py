"""Robot-centric EKF of the teach phase (paper §III, eqs 14–18; docs/design.md §4).

State: the pose of the current keyframe frame ``bj`` in the current body frame —
``p = x^{bj}`` and ``q = q^{bj} = q_{b←bj}`` — plus the gyro bias ``b_g`` (the paper
calibrates it once; we keep estimating the residual). The quaternion is handled as an error
state (multiplicative): ``R(q) = exp([δθ]×) R(q̂)``, ``p = p̂ + δp``, ``b_g = b̂ + δb``; the
9-vector ``(δp, δθ, δb)`` carries the covariance.

Propagation (eq. 14): ``ẋ^{bj} = −[ω]× x^{bj} − v``, ``q̇^{bj} = ½ Ω(ω) q^{bj}`` with
``ω = ω_m − b_g`` and ``v = (s, 0, 0)``; the mean is moved by the exact rigid motion of one
IMU interval, the error by

    δṗ = −[ω̂]× δp − [p̂]× (δb + n_g) + n_v
    δθ̇ = −[ω̂]× δθ + δb + n_g
    δḃ = n_b

Update (eqs 16–18): for a landmark anchored at frame ``a`` (fixed pose in ``bj``), the
predicted anchor bearing is ``h = ℓ/‖ℓ‖``, ``ℓ = R_jaᵀ (R(q)ᵀ (x_i − x^{bj}) − t_ja)``, with
``x_i = d_i y_i`` from the observers; the measurement is the bearing taken at the anchor
(eq. 16 with anchor = keyframe: ``R_ja = I``, ``t_ja = 0``). Residuals live in the tangent
plane of the measured bearing; each landmark is χ²-gated before the batch update.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from mowerhw.common.geometry import (
    IDENTITY_QUAT,
    quat_conjugate,
    quat_exp,
    quat_multiply_unit,
    quat_to_rotmat,
    skew,
    tangent_basis,
)
from mowerhw.estimation.odometry import BodyMotion

FloatArray = NDArray[np.float64]

P_, TH, BG = slice(0, 3), slice(3, 6), slice(6, 9)  # error-state blocks
_I3 = np.eye(3)


@dataclass
class EkfNoise:
    """Continuous noise densities of the EKF's process model."""

    gyro: float = 1e-4  # rad/s/√Hz
    gyro_bias_walk: float = 2e-5  # rad/s²/√Hz
    speed: float = 2e-3  # m/s/√Hz along x
    lateral: float = 5e-3  # m/s/√Hz across (non-holonomic slip)


@dataclass
class UpdateStats:
    frames: int = 0
    used: int = 0
    gated: int = 0
    last_nis: FloatArray = field(default_factory=lambda: np.zeros(0))


class RobotCentricEKF:
    """The keyframe's pose in the current body frame, plus the gyro bias (error-state EKF)."""

    def __init__(self, noise: EkfNoise, gate_probability: float = 0.999) -> None:
        self.noise = noise
        self.p = np.zeros(3)  # x^{bj}
        self.q = IDENTITY_QUAT.copy()  # q^{bj} = q_{b←bj}
        self.bg = np.zeros(3)
        self.P = np.zeros((9, 9))
        # Schmidt consider parameters: the 2-D errors of the anchors taken at the keyframe
        self.pxa = np.zeros((9, 0))  # cross-covariance state ↔ anchor errors
        self.pa_var = np.zeros(0)  # each anchor error's variance (per column)
        self._qv_diag = (noise.speed**2, noise.lateral**2, noise.lateral**2)
        self.gate = float(chi2.ppf(gate_probability, df=2))
        self.gate_1d = float(chi2.ppf(gate_probability, df=1))
        self.stats = UpdateStats()

    @property
    def R(self) -> FloatArray:
        """``R(q^{bj}) = R_{b←bj}``."""
        return quat_to_rotmat(self.q)

    def set_bias(self, bias: FloatArray, variance: float) -> None:
        self.bg = np.asarray(bias, dtype=np.float64).copy()
        self.P[BG, BG] = np.eye(3) * variance
        self.P[BG, :6] = 0.0
        self.P[:6, BG] = 0.0

    def reset_keyframe(self) -> None:
        """A new keyframe at the current body pose: ``x^{bj} = 0``, ``q^{bj} = 1``, exactly.
        The old keyframe's anchors go with it (:meth:`set_anchors` gives the new ones)."""
        self.p = np.zeros(3)
        self.q = IDENTITY_QUAT.copy()
        self.P[:6, :] = 0.0
        self.P[:, :6] = 0.0
        self.set_anchors(np.zeros(0))

    def set_anchors(self, variances: FloatArray) -> None:
        """Consider slots 0..n−1 for the anchors taken at this keyframe (bearing variances)."""
        v = np.asarray(variances, dtype=np.float64)
        self.pxa = np.zeros((9, 2 * v.size))
        self.pa_var = np.repeat(v, 2)

    # -- eq. (14): propagation ------------------------------------------------------------------

    def propagate(self, m: BodyMotion) -> None:
        """Move the mean by one IMU interval of body motion (exact: ``x⁺ = Cᵀ (x − Δ)``,
        ``q⁺ = exp(ω Δt)* ⊗ q``) and the covariance by the linearised error dynamics.

        With ``W = [ω̂]×`` and ``S = [p̂]×``: ``F = [[−W, 0, −S], [0, −W, I], [0, 0, 0]]``,
        ``F² = [[W², 0, W S], [0, W², −W], 0]``, ``Φ = I + F Δt + ½ F² Δt²``; the noise
        ``G = [[I, −S, 0], [0, I, 0], [0, 0, I]]`` on (n_v, n_g, n_b) gives ``Q = G Q_c Gᵀ Δt``.
        """
        p_hat = self.p
        dt = m.dt
        self.p = m.c.T @ (p_hat - m.disp)
        self.q = quat_multiply_unit(quat_conjugate(m.dq), self.q)
        phi, q = _transition(m.w.tolist(), p_hat.tolist(), dt, self.noise, self._qv_diag)
        self.P = phi @ self.P @ phi.T + q  # symmetrised at every update
        if self.pxa.shape[1]:
            self.pxa = phi @ self.pxa

    # -- eqs (16)–(18): update --------------------------------------------------------------------

    def predict_anchor_bearings(
        self, x_b: FloatArray, r_ja: FloatArray, t_ja: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Predicted anchor bearings h (N, 3), their Jacobians wrt the error state (N, 3, 9)
        and wrt the landmark position in the body frame (N, 3, 3)."""
        r = self.R
        rel = x_b - self.p  # x_i − x^{bj}
        ell_j = rel @ r  # R(q)ᵀ (x_i − x^{bj}), row form
        ell = np.einsum("nji,nj->ni", r_ja, ell_j - t_ja)  # R_jaᵀ (ℓ_j − t_ja)
        norm = np.linalg.norm(ell, axis=-1)
        h = ell / norm[:, None]
        dh_dell = (np.eye(3)[None] - np.einsum("ni,nj->nij", h, h)) / norm[:, None, None]
        a = np.einsum("nji,jk->nik", r_ja, r.T)  # R_jaᵀ R(q)ᵀ
        dell = np.zeros((x_b.shape[0], 3, 9))
        dell[:, :, P_] = -a
        dell[:, :, TH] = np.einsum("nij,njk->nik", a, skew(rel))
        return h, np.einsum("nij,njk->nik", dh_dell, dell), np.einsum("nij,njk->nik", dh_dell, a)

    def update(
        self,
        x_b: FloatArray,
        cov_x: FloatArray,
        anchor_bearing: FloatArray,
        anchor_var: FloatArray,
        r_ja: FloatArray,
        t_ja: FloatArray,
        anchor_cov: FloatArray | None = None,
        anchor_p: FloatArray | None = None,
    ) -> NDArray[np.bool_]:
        """One batch update with N landmarks; returns which passed the χ² gate.

        ``anchor_cov`` (N, 6, 6) is the EKF covariance of (δp, δθ) when an anchor was taken
        between keyframes (zero for anchors at the keyframe itself), ``anchor_p`` the EKF's
        ``x^{bj}`` then; their uncertainty enters the measurement noise.
        """
        n = x_b.shape[0]
        self.stats.frames += 1
        if n == 0:
            return np.zeros(0, dtype=bool)
        h, hx, hl = self.predict_anchor_bearings(x_b, r_ja, t_ja)
        basis = tangent_basis(anchor_bearing)  # (N, 3, 2)
        bt = np.swapaxes(basis, 1, 2)  # (N, 2, 3)
        res = np.einsum("nij,nj->ni", bt, anchor_bearing - h)  # (N, 2)
        H = np.einsum("nij,njk->nik", bt, hx)  # (N, 2, 9)
        L = np.einsum("nij,njk->nik", bt, hl)  # (N, 2, 3)
        # measurement noise: anchor bearing + the observer's landmark uncertainty
        R = anchor_var[:, None, None] * np.eye(2)[None] + np.einsum("nij,njk,nlk->nil", L, cov_x, L)
        if anchor_cov is not None and anchor_p is not None:
            R = R + self._anchor_noise(x_b, r_ja, t_ja, basis, anchor_cov, anchor_p)
        S = np.einsum("nij,jk,nlk->nil", H, self.P, H) + R
        nis = np.einsum("ni,nij,nj->n", res, np.linalg.inv(S), res)
        ok: NDArray[np.bool_] = nis <= self.gate
        self.stats.last_nis = nis
        self.stats.gated += int((~ok).sum())
        self.stats.used += int(ok.sum())
        if not ok.any():
            return ok
        Hs = H[ok].reshape(-1, 9)
        rs = res[ok].reshape(-1)
        Rs = _block_diag(R[ok])
        S_all = Hs @ self.P @ Hs.T + Rs
        K = np.linalg.solve(S_all, Hs @ self.P).T  # P Hᵀ S⁻¹ (eq. 18)
        dx = K @ rs
        ikh = np.eye(9) - K @ Hs
        self.P = ikh @ self.P @ ikh.T + K @ Rs @ K.T  # Joseph form
        self.P = 0.5 * (self.P + self.P.T)
        self.p = self.p + dx[P_]
        self.q = quat_multiply_unit(quat_exp(dx[TH]), self.q)
        self.bg = self.bg + dx[BG]
        return ok

    def _anchor_noise(
        self,
        x_b: FloatArray,
        r_ja: FloatArray,
        t_ja: FloatArray,
        basis: FloatArray,
        anchor_cov: FloatArray,
        anchor_p: FloatArray,
    ) -> FloatArray:
        """Noise from the anchor pose's own uncertainty (anchors taken between keyframes).

        With the anchor's EKF error (δp_a, δθ_a): ``ℓ ≈ ℓ̂ + δp_a − [ℓ̂ − p̂_a]× δθ_a``.
        """
        ell_j = (x_b - self.p) @ self.R
        ell = np.einsum("nji,nj->ni", r_ja, ell_j - t_ja)
        norm = np.linalg.norm(ell, axis=-1)
        h = ell / norm[:, None]
        dh = (np.eye(3)[None] - np.einsum("ni,nj->nij", h, h)) / norm[:, None, None]
        ja = np.zeros((x_b.shape[0], 3, 6))
        ja[:, :, :3] = np.eye(3)
        ja[:, :, 3:] = -skew(ell - anchor_p)
        m = np.einsum("nji,njk,nkl->nil", basis, dh, ja)  # (N, 2, 6)
        cov: FloatArray = np.einsum("nij,njk,nlk->nil", m, anchor_cov, m)
        return cov

    def update_epipolar(
        self,
        y_now: FloatArray,
        y_var: float,
        anchor_bearing: FloatArray,
        anchor_var: FloatArray,
        r_ja: FloatArray,
        t_ja: FloatArray,
        min_baseline_m: float,
        min_angle_rad: float,
        anchor_slot: NDArray[np.int64] | None = None,
    ) -> NDArray[np.bool_]:
        """Batch update with the depth-free part of eq. (16): the epipolar constraint.

        Eq. (16) predicts the anchor bearing ``h ∝ ℓ = b + d v`` with ``b`` the current body
        origin and ``v`` the current bearing, both in the anchor frame. Whatever the depth d,
        h lies in the plane of b and v; the residual's component along that plane's normal
        ``n̂ = (b × v)/‖b × v‖`` is ``r = n̂ · u_a``, free of the landmark depth. Because the
        observer's depth is itself triangulated from this EKF's pose (eq. 3), the in-plane
        component would feed the EKF's own errors back to it; the normal one does not.

        An anchor bearing is measured once and used in every later update, so its error is
        not white noise. Anchors with a ``anchor_slot`` ≥ 0 (those taken at the keyframe) are
        Schmidt *consider* parameters: their 2-D errors keep a cross-covariance with the state
        (``P_xa``, propagated with Φ), enter every innovation covariance, and are never
        "estimated away". Others count as white noise of variance ``anchor_var``.
        """
        n = y_now.shape[0]
        self.stats.frames += 1
        if n == 0:
            return np.zeros(0, dtype=bool)
        r = self.R
        a = np.einsum("nji,kj->nik", r_ja, r)  # R_jaᵀ R(q)ᵀ  (N, 3, 3)
        c_j = -r.T @ self.p  # current body origin in the keyframe frame
        b = np.einsum("nji,nj->ni", r_ja, c_j[None] - t_ja)
        v = np.einsum("nij,nj->ni", a, y_now)
        m = np.cross(b, v)
        m_norm = np.linalg.norm(m, axis=-1)
        base = np.linalg.norm(b, axis=-1)
        sin_bv = m_norm / np.maximum(base, 1e-12)
        usable = (base >= min_baseline_m) & (sin_bv >= np.sin(min_angle_rad))
        sin_bu = np.linalg.norm(np.cross(b, anchor_bearing), axis=-1) / np.maximum(base, 1e-12)
        usable &= sin_bu >= np.sin(min_angle_rad)
        ok = np.zeros(n, dtype=bool)
        if not usable.any():
            return ok
        idx = np.flatnonzero(usable)
        m_hat = m[idx] / m_norm[idx, None]
        u = anchor_bearing[idx]
        res = np.einsum("ni,ni->n", m_hat, u)
        g = (u - res[:, None] * m_hat) / m_norm[idx, None]  # ∂r/∂m
        ai = a[idx]
        db = np.zeros((idx.size, 3, 9))  # ∂b/∂δx
        db[:, :, P_] = -ai
        db[:, :, TH] = -np.einsum("nij,jk->nik", ai, skew(self.p))
        dv = np.zeros((idx.size, 3, 9))  # ∂v/∂δx
        dv[:, :, TH] = np.einsum("nij,njk->nik", ai, skew(y_now[idx]))
        dm = -np.einsum("nij,njk->nik", skew(v[idx]), db) + np.einsum(
            "nij,njk->nik", skew(b[idx]), dv
        )
        H = np.einsum("ni,nij->nj", g, dm)  # (K, 9)
        # noise: the current bearing (σ_y) through the plane tilt ...
        dr_dy = np.einsum("ni,nij,njk->nk", g, skew(b[idx]), ai)
        dr_dy -= np.einsum("nk,nk->n", dr_dy, y_now[idx])[:, None] * y_now[idx]  # tangent part
        rvar = y_var * np.einsum("nk,nk->n", dr_dy, dr_dy)
        # ... and the anchor bearing: ∂r/∂u_a = m̂ in the anchor's tangent plane
        slot = np.full(idx.size, -1) if anchor_slot is None else anchor_slot[idx]
        consider = (slot >= 0) & (2 * slot + 1 < self.pxa.shape[1])
        rvar = rvar + np.where(consider, 0.0, anchor_var[idx])
        h_a = np.einsum("ni,nij->nj", m_hat, tangent_basis(u))  # (K, 2)
        cols = np.stack([2 * slot, 2 * slot + 1], axis=1)  # (K, 2), valid where consider
        ha_full = np.zeros((idx.size, self.pxa.shape[1]))
        rows_c = np.flatnonzero(consider)
        ha_full[rows_c[:, None], cols[rows_c]] = h_a[rows_c]
        ph = self.P @ H.T + self.pxa @ ha_full.T  # (9, K): P_xx Hᵀ + P_xa H_aᵀ
        s_mat = H @ ph + ha_full @ (self.pxa.T @ H.T) + (ha_full * self.pa_var) @ ha_full.T
        s_mat += np.diag(rvar)
        nis = res**2 / np.diag(s_mat)
        passed = nis <= self.gate_1d
        ok[idx[passed]] = True
        self.stats.last_nis = nis
        self.stats.gated += int((~passed).sum())
        self.stats.used += int(passed.sum())
        if not passed.any():
            return ok
        # the constraint's measurement is 0: innovation = 0 − r(x̂); Schmidt gain on x only
        sel = np.flatnonzero(passed)
        S = s_mat[np.ix_(sel, sel)]
        K = np.linalg.solve(S, ph[:, sel].T).T  # (9, k)
        dx = K @ (-res[sel])
        self.P = self.P - K @ S @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        self.pxa = self.pxa - K @ (H[sel] @ self.pxa + ha_full[sel] * self.pa_var)
        self.p = self.p + dx[P_]
        self.q = quat_multiply_unit(quat_exp(dx[TH]), self.q)
        self.bg = self.bg + dx[BG]
        return ok


def _transition(
    w: list[float], p: list[float], dt: float, noise: EkfNoise, qv: tuple[float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """Φ and Q Δt of :meth:`RobotCentricEKF.propagate`, written out in scalars.

    With ``W = [ω̂]× Δt``, ``S = [p̂]×``: ``Φ_pp = Φ_θθ = I − W + ½ W²``,
    ``Φ_pb = (−S + ½ W S) Δt``, ``Φ_θb = (I − ½ W) Δt``; ``Q_pp = Q_v + q_g S Sᵀ``,
    ``Q_pθ = −q_g S``, ``Q_θθ = q_g I``, ``Q_bb = q_b I`` (all times Δt). One ``np.array``
    call instead of a dozen small-matrix operations: this runs at IMU rate.
    """
    wx, wy, wz = w[0] * dt, w[1] * dt, w[2] * dt
    px, py, pz = p
    # D = I − W + ½ W²  (W = [w dt]×,  W² = w wᵀ dt² − |w dt|² I)
    n2 = wx * wx + wy * wy + wz * wz
    d00, d11, d22 = 1 + 0.5 * (wx * wx - n2), 1 + 0.5 * (wy * wy - n2), 1 + 0.5 * (wz * wz - n2)
    d01, d02, d12 = 0.5 * wx * wy + wz, 0.5 * wx * wz - wy, 0.5 * wy * wz + wx
    d10, d20, d21 = 0.5 * wx * wy - wz, 0.5 * wx * wz + wy, 0.5 * wy * wz - wx
    # WS = W S with S = [p]×: (W S)_ij = (w·p) δ... computed explicitly
    s = ((0.0, -pz, py), (pz, 0.0, -px), (-py, px, 0.0))
    wm = ((0.0, -wz, wy), (wz, 0.0, -wx), (-wy, wx, 0.0))
    ws = [[sum(wm[i][k] * s[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
    pb = [[(-s[i][j] + 0.5 * ws[i][j]) * dt for j in range(3)] for i in range(3)]
    tb = [[((1.0 if i == j else 0.0) - 0.5 * wm[i][j]) * dt for j in range(3)] for i in range(3)]
    phi = np.array(
        [
            [d00, d01, d02, 0, 0, 0, pb[0][0], pb[0][1], pb[0][2]],
            [d10, d11, d12, 0, 0, 0, pb[1][0], pb[1][1], pb[1][2]],
            [d20, d21, d22, 0, 0, 0, pb[2][0], pb[2][1], pb[2][2]],
            [0, 0, 0, d00, d01, d02, tb[0][0], tb[0][1], tb[0][2]],
            [0, 0, 0, d10, d11, d12, tb[1][0], tb[1][1], tb[1][2]],
            [0, 0, 0, d20, d21, d22, tb[2][0], tb[2][1], tb[2][2]],
            [0, 0, 0, 0, 0, 0, 1, 0, 0],
            [0, 0, 0, 0, 0, 0, 0, 1, 0],
            [0, 0, 0, 0, 0, 0, 0, 0, 1],
        ],
        dtype=np.float64,
    )
    g = noise.gyro**2 * dt
    b = noise.gyro_bias_walk**2 * dt
    # S Sᵀ = |p|² I − p pᵀ
    pp = px * px + py * py + pz * pz
    sst = (
        (pp - px * px, -px * py, -px * pz),
        (-px * py, pp - py * py, -py * pz),
        (-px * pz, -py * pz, pp - pz * pz),
    )
    q = np.array(
        [
            [qv[0] * dt + g * sst[0][0], g * sst[0][1], g * sst[0][2], 0, g * pz, -g * py, 0, 0, 0],
            [g * sst[1][0], qv[1] * dt + g * sst[1][1], g * sst[1][2], -g * pz, 0, g * px, 0, 0, 0],
            [g * sst[2][0], g * sst[2][1], qv[2] * dt + g * sst[2][2], g * py, -g * px, 0, 0, 0, 0],
            [0, -g * pz, g * py, g, 0, 0, 0, 0, 0],
            [g * pz, 0, -g * px, 0, g, 0, 0, 0, 0],
            [-g * py, g * px, 0, 0, 0, g, 0, 0, 0],
            [0, 0, 0, 0, 0, 0, b, 0, 0],
            [0, 0, 0, 0, 0, 0, 0, b, 0],
            [0, 0, 0, 0, 0, 0, 0, 0, b],
        ],
        dtype=np.float64,
    )
    return phi, q


def _block_diag(blocks: FloatArray) -> FloatArray:
    """(N, 2, 2) → (2N, 2N) block diagonal."""
    n = blocks.shape[0]
    out = np.zeros((2 * n, 2 * n))
    idx = np.arange(n) * 2
    for i in range(2):
        for j in range(2):
            out[idx + i, idx + j] = blocks[:, i, j]
    return out
