"""The standard the paper argues against: inverse-depth EKF-SLAM (Civera et al., 2008).

One world-centric EKF over the robot pose, the gyro bias and every landmark, each landmark
parametrised by the position ``a`` of the camera where it was first seen, the azimuth θ and
elevation φ of its first bearing (world frame), and its inverse depth ρ:

    x_i^w = a + m(θ, φ) / ρ,          m = (cos φ cos θ, cos φ sin θ, sin φ)

and measured through the ρ-scaled bearing ``h ∝ R_wbᵀ (ρ (a − x_b) + m)`` (no division by
ρ, so a landmark at infinity is fine; a ρ that goes negative is the known failure mode).

Same inputs, same standstill bias calibration, same noise settings as the
:class:`mowerhw.teach.Teacher`, so the Monte-Carlo comparison (``tools/montecarlo_teach.py``)
is like for like. It is a baseline for evaluation, not part of the product runtime.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from mowerhw.common.geometry import (
    IDENTITY_QUAT,
    quat_exp,
    quat_multiply_unit,
    quat_to_rotmat,
    skew,
    tangent_basis,
)
from mowerhw.config import TeachConfig, with_imu_noise
from mowerhw.estimation.odometry import BodyMotion, SpeedTrack, camera_velocity
from mowerhw.teach.smoother import right_jacobian

FloatArray = NDArray[np.float64]

TH, X, BG = slice(0, 3), slice(3, 6), slice(6, 9)  # robot error state: δθ (world), δx, δb
ROBOT = 9
LM = 6  # per landmark: a (3), θ, φ, ρ


@dataclass
class InverseDepthResult:
    trajectory: FloatArray  # (K, 8) t, x, y, z, qw, qx, qy, qz
    landmarks: dict[int, FloatArray]
    negative_depths: int
    diagnostics: dict[str, Any] = field(default_factory=dict)


class InverseDepthEkfMapper:
    """Inverse-depth EKF-SLAM with the Teacher's input API."""

    RHO0 = 0.1  # initial inverse depth (1/m): 10 m
    SIGMA_RHO = 0.5  # its σ: from "right here" to "at infinity"

    def __init__(self, config: TeachConfig | None = None) -> None:
        self.cfg = with_imu_noise(config or TeachConfig())
        c = self.cfg
        self.sigma = c.bearing_sigma_rad
        self.x = np.zeros(3)
        self.q = IDENTITY_QUAT.copy()  # q_wb
        self.bg = np.zeros(3)
        self.lm = np.zeros((0, LM))
        self.ids: list[int] = []
        self.index: dict[int, int] = {}
        self.P = np.zeros((ROBOT, ROBOT))
        self.gate = float(chi2.ppf(0.999, df=2))
        self.phase = "standstill"
        self.t_imu: float | None = None
        self.speed_mps = 0.0
        self._speeds = SpeedTrack()
        self._gyro: list[FloatArray] = []
        self._traj: list[FloatArray] = []
        self.w_last = np.zeros(3)
        self.negative_depths = 0
        self.gated = 0
        self._q_noise = np.diag(
            [c.gyro_noise**2] * 3 + [c.speed_noise**2, c.lateral_noise**2, c.lateral_noise**2]
        )

    # -- inputs ---------------------------------------------------------------------------------

    def imu(self, t: float, gyro_xyz: ArrayLike) -> None:
        gyro = np.asarray(gyro_xyz, dtype=np.float64).reshape(3)
        if self.phase == "standstill":
            self._gyro.append(gyro)
            self.t_imu = float(t)
            self._record()
            return
        if self.t_imu is None or t <= self.t_imu:
            return
        self.w_last = gyro - self.bg
        self._propagate(float(t) - self.t_imu, self.w_last)
        self.t_imu = float(t)
        self._record()

    def speed(self, t: float, v: float) -> None:
        if not (math.isfinite(t) and math.isfinite(v)):
            return
        self.speed_mps = float(v)
        self._speeds.add(t, v)
        if self.phase == "standstill" and v != 0.0:
            g = np.array(self._gyro) if self._gyro else np.zeros((1, 3))
            self.bg = g.mean(axis=0)
            var = float(np.max(g.var(axis=0))) / max(len(g), 1) + 1e-10
            self.P[BG, BG] = np.eye(3) * (var if len(self._gyro) >= 10 else 0.005**2)
            self.phase = "driving"

    def bearings(self, t: float, ids: ArrayLike, unit_xyz: ArrayLike) -> None:
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        u = np.asarray(unit_xyz, dtype=np.float64).reshape(-1, 3)
        if self.t_imu is not None and t > self.t_imu and self.phase == "driving":
            self._propagate(float(t) - self.t_imu, self.w_last)
            self.t_imu = float(t)
        known = np.array([i in self.index for i in ids.tolist()], dtype=bool)
        if known.any():
            self._update(ids[known], u[known])
        for i, b in zip(ids[~known].tolist(), u[~known], strict=True):
            self._add(i, b)

    # -- estimation -----------------------------------------------------------------------------

    def _propagate(self, dt: float, w: FloatArray) -> None:
        speed = self._speeds.at(self.t_imu + 0.5 * dt)  # type: ignore[operator]
        v = camera_velocity(speed, w, self.cfg.speed_contact_m)
        m = BodyMotion.of(w, v, dt)
        r = quat_to_rotmat(self.q)
        disp_w = r @ m.disp
        self.x = self.x + disp_w
        self.q = quat_multiply_unit(self.q, m.dq)
        r_new = quat_to_rotmat(self.q)
        jr = right_jacobian(w * dt)[0]
        phi = np.eye(ROBOT)
        phi[TH, BG] = -r_new @ jr * dt
        phi[X, TH] = -skew(disp_w)
        g = np.zeros((ROBOT, 6))
        g[TH, 0:3] = -r_new @ jr
        g[X, 3:6] = r
        q = g @ self._q_noise @ g.T * dt
        q[BG, BG] += np.eye(3) * self.cfg.gyro_bias_walk**2 * dt
        P = self.P
        P[:ROBOT, :ROBOT] = phi @ P[:ROBOT, :ROBOT] @ phi.T + q
        if P.shape[0] > ROBOT:
            P[:ROBOT, ROBOT:] = phi @ P[:ROBOT, ROBOT:]
            P[ROBOT:, :ROBOT] = P[:ROBOT, ROBOT:].T

    def _add(self, lid: int, u: FloatArray) -> None:
        """Initialise a landmark from its first bearing (Civera's inverse-depth init)."""
        r = quat_to_rotmat(self.q)
        m = r @ u
        rxy = math.hypot(m[0], m[1])
        theta, phi_ = math.atan2(m[1], m[0]), math.atan2(m[2], rxy)
        d_ang = np.array(
            [[-m[1] / rxy**2, m[0] / rxy**2, 0.0], [-m[0] * m[2] / rxy, -m[1] * m[2] / rxy, rxy]]
        )
        j_r = np.zeros((LM, ROBOT))
        j_r[0:3, X] = np.eye(3)
        j_r[3:5, TH] = d_ang @ (-skew(m))
        basis = tangent_basis(u[None])[0]
        j_u = np.zeros((LM, 2))
        j_u[3:5] = d_ang @ r @ basis
        n = self.P.shape[0]
        p_new = np.zeros((n + LM, n + LM))
        p_new[:n, :n] = self.P
        cross = j_r @ self.P[:ROBOT, :]
        p_new[n:, :n] = cross
        p_new[:n, n:] = cross.T
        p_new[n:, n:] = (
            j_r @ self.P[:ROBOT, :ROBOT] @ j_r.T
            + j_u @ j_u.T * self.sigma**2
            + np.diag([0, 0, 0, 0, 0, self.SIGMA_RHO**2])
        )
        self.P = p_new
        self.lm = np.vstack([self.lm, [*self.x, theta, phi_, self.RHO0]])
        self.index[lid] = len(self.ids)
        self.ids.append(lid)

    def _update(self, ids: NDArray[np.int64], u: FloatArray) -> None:
        k = np.array([self.index[i] for i in ids.tolist()])
        lm = self.lm[k]
        r = quat_to_rotmat(self.q)
        th, ph, rho = lm[:, 3], lm[:, 4], lm[:, 5]
        m = np.column_stack([np.cos(ph) * np.cos(th), np.cos(ph) * np.sin(th), np.sin(ph)])
        g = rho[:, None] * (lm[:, 0:3] - self.x) + m
        ell = g @ r  # R_wbᵀ g
        nrm = np.linalg.norm(ell, axis=1)
        h = ell / nrm[:, None]
        dh = (np.eye(3)[None] - np.einsum("ni,nj->nij", h, h)) / nrm[:, None, None]
        bt = np.swapaxes(tangent_basis(u), 1, 2)
        a = np.einsum("nij,njk->nik", bt, dh)  # (N, 2, 3): ∂r/∂ℓ (with r = u − h → negate)
        n_state = self.P.shape[0]
        H = np.zeros((k.size, 2, n_state))
        rt = r.T
        H[:, :, TH] = a @ (rt @ skew_rows(g))
        H[:, :, X] = -rho[:, None, None] * (a @ rt)
        dm_dth = np.column_stack([-np.cos(ph) * np.sin(th), np.cos(ph) * np.cos(th), 0 * th])
        dm_dph = np.column_stack([-np.sin(ph) * np.cos(th), -np.sin(ph) * np.sin(th), np.cos(ph)])
        cols = ROBOT + LM * k
        blk = np.zeros((k.size, 2, LM))
        blk[:, :, 0:3] = rho[:, None, None] * (a @ rt)
        blk[:, :, 3] = np.einsum("nij,nj->ni", a @ rt, dm_dth)
        blk[:, :, 4] = np.einsum("nij,nj->ni", a @ rt, dm_dph)
        blk[:, :, 5] = np.einsum("nij,nj->ni", a @ rt, lm[:, 0:3] - self.x)
        for j in range(k.size):
            H[j, :, cols[j] : cols[j] + LM] = blk[j]
        res = np.einsum("nij,nj->ni", bt, u - h)
        R2 = np.eye(2) * self.sigma**2
        S = np.einsum("nij,jk,nlk->nil", H, self.P, H) + R2
        nis = np.einsum("ni,nij,nj->n", res, np.linalg.inv(S), res)
        ok = nis <= self.gate
        self.gated += int((~ok).sum())
        if not ok.any():
            return
        Hs = H[ok].reshape(-1, n_state)
        rs = res[ok].reshape(-1)
        Rs = np.eye(Hs.shape[0]) * self.sigma**2
        S_all = Hs @ self.P @ Hs.T + Rs
        K = np.linalg.solve(S_all, Hs @ self.P).T
        dx = K @ rs
        ikh = np.eye(n_state) - K @ Hs
        self.P = ikh @ self.P @ ikh.T + K @ Rs @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        self.q = quat_multiply_unit(quat_exp(dx[TH]), self.q)
        self.x = self.x + dx[X]
        self.bg = self.bg + dx[BG]
        self.lm = self.lm + dx[ROBOT:].reshape(-1, LM)
        self.negative_depths += int(np.sum(self.lm[:, 5] <= 0))

    def _record(self) -> None:
        self._traj.append(np.concatenate([[self.t_imu], self.x, self.q]))

    def finish(self) -> InverseDepthResult:
        landmarks = {}
        for i, row in zip(self.ids, self.lm, strict=True):
            th, ph, rho = row[3], row[4], row[5]
            m = np.array([np.cos(ph) * np.cos(th), np.cos(ph) * np.sin(th), np.sin(ph)])
            landmarks[i] = row[0:3] + m / rho if rho > 1e-6 else np.full(3, np.nan)
        return InverseDepthResult(
            trajectory=np.array(self._traj),
            landmarks=landmarks,
            negative_depths=self.negative_depths,
            diagnostics={"gated": self.gated, "state_size": int(self.P.shape[0])},
        )


def skew_rows(g: FloatArray) -> FloatArray:
    """(N, 3, 3) skew matrices of the rows of ``g``."""
    return skew(g)
