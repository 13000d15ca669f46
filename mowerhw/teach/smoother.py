"""Loop closure as a batch smoother over the whole teach drive (beyond the paper).

The paper leaves loop closure to future work. When the mower is back at its start it sees
the first landmarks again; the filter's end pose then disagrees with what those landmarks
say. Distributing that disagreement well over the drive is a least-squares problem over

* the body pose at every camera frame (``R_wb,k``, ``t_wb,k``; the first one is the world
  frame and stays fixed),
* every landmark's world position, and
* the gyro bias, one value per segment of the drive (``bias_segment``), tied by
  random-walk factors, with the standstill calibration as the prior of the first,
* the gyro's yaw-rate scale error ``s`` (one value: ``ω_z = (1 − s)(ω_m − b)_z``; MEMS gyros
  are off by up to a few per cent, which turns a 360° loop into 370°), with a prior,

with two kinds of factors:

* **odometry** between consecutive frames: the gyro and ground speed preintegrated into a
  relative rotation ``ΔR`` and translation ``Δp`` (body frame of the earlier frame), with
  their covariance and first-order bias and scale Jacobians (``ΔR(b, s) ≈ ΔR Exp(J_R δb +
  J_Rs s)``, ``Δp(b, s) ≈ Δp + J_p δb + J_ps s``), under a Cauchy loss: a wheel that slips
  for a second makes a few odometry factors wrong by many σ, and they must not bend the drive
  (measured on the scenario matrix: Cauchy 2.2 cm, Huber 2.4 cm boundary on the bumpy strip
  with slip, the same elsewhere);
* **bearings**: ``u_ki ≈ normalize(R_kᵀ (L_i − t_k))``, residual in the tangent plane of the
  measured bearing, Huber-weighted against outliers.

Levenberg–Marquardt on the sparse normal equations (scipy.sparse), started from the filter.
Pose updates are right perturbations ``R ← R Exp(φ)`` and ``t ← t + δt`` (world).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import NDArray

from mowerhw.common.geometry import frame_jacobian, rotmat_exp, rotmat_log, skew, tangent_basis

FloatArray = NDArray[np.float64]


def right_jacobian(phi: FloatArray) -> FloatArray:
    """SO(3) right Jacobian ``Jr(φ)`` for (N, 3) rotation vectors: (N, 3, 3)."""
    phi = np.atleast_2d(phi)
    a = np.linalg.norm(phi, axis=-1)[:, None, None]
    k = skew(phi)
    small = a < 1e-6
    a_s = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5, (1 - np.cos(a_s)) / a_s**2)
    c2 = np.where(small, 1.0 / 6.0, (a_s - np.sin(a_s)) / a_s**3)
    return np.eye(3)[None] - c1 * k + c2 * (k @ k)


def right_jacobian_inv(phi: FloatArray) -> FloatArray:
    """``Jr(φ)⁻¹`` for (N, 3) rotation vectors: (N, 3, 3)."""
    phi = np.atleast_2d(phi)
    a = np.linalg.norm(phi, axis=-1)[:, None, None]
    k = skew(phi)
    small = a < 1e-6
    a_s = np.where(small, 1.0, a)
    c = np.where(small, 1.0 / 12.0, 1 / a_s**2 - (1 + np.cos(a_s)) / (2 * a_s * np.sin(a_s)))
    return np.eye(3)[None] + 0.5 * k + c * (k @ k)


@dataclass
class Preintegrated:
    """Gyro + ground speed between two frames, in the body frame of the first."""

    dR: FloatArray  # (3, 3)
    dp: FloatArray  # (3,)
    cov: FloatArray  # (6, 6) of (δθ, δp)
    j_rb: FloatArray  # ∂(ΔR)/∂b as right-perturbation Jacobian (3, 3)
    j_pb: FloatArray  # ∂(Δp)/∂b (3, 3)
    dt: float
    j_rs: FloatArray  # ∂(ΔR)/∂s (3,): the yaw-rate scale error
    j_ps: FloatArray  # ∂(Δp)/∂s (3,)


def preintegrate_segments(
    log: FloatArray,
    bounds: NDArray[np.int64],
    bias: FloatArray,
    gyro_density: float,
    speed_density: float,
    lateral_density: float,
    contact: FloatArray | None = None,
) -> list[Preintegrated]:
    """Preintegrate consecutive IMU segments ``log[bounds[k]:bounds[k+1]]`` at once.

    ``log`` rows are IMU intervals (Δt, gyro x, y, z, forward speed at the wheels'
    ``contact`` point, body frame from the camera); with bias ``bias``
    each segment gives ``ΔR = Π Exp((ω_j − b) Δt_j)``, ``Δp = Σ ΔR_j v_j Δt_j``, the
    covariance of (δθ, δp) from gyro and speed/slip noise densities, and the bias Jacobians.
    All segments advance together, one IMU step at a time (padded with Δt = 0).
    """
    starts, ends = bounds[:-1], bounds[1:]
    lengths = ends - starts
    nseg, width = starts.size, max(int(lengths.max(initial=0)), 1)
    idx = starts[:, None] + np.arange(width)[None, :]
    valid = np.arange(width)[None, :] < lengths[:, None]
    rows = np.where(valid, idx, 0)
    dt = np.where(valid, log[rows, 0] if log.size else 0.0, 0.0)
    w = (log[rows, 1:4] - bias) if log.size else np.zeros((nseg, width, 3))
    w = np.where(valid[..., None], w, 0.0)
    sp_ = np.where(valid, log[rows, 4] if log.size else 0.0, 0.0)
    phi = w * dt[..., None]
    steps = rotmat_exp(phi.reshape(-1, 3)).reshape(nseg, width, 3, 3)
    jrs = right_jacobian(phi.reshape(-1, 3)).reshape(nseg, width, 3, 3)
    qv = np.array([speed_density, lateral_density, lateral_density]) ** 2
    dR = np.broadcast_to(np.eye(3), (nseg, 3, 3)).copy()
    dp = np.zeros((nseg, 3))
    cov = np.zeros((nseg, 6, 6))
    j_rb = np.zeros((nseg, 3, 3))
    j_pb = np.zeros((nseg, 3, 3))
    j_rs = np.zeros((nseg, 3))
    j_ps = np.zeros((nseg, 3))
    for j in range(width):
        d = dt[:, j]
        live = d > 0
        inv_dt = np.where(live, 1.0 / np.where(live, d, 1.0), 0.0)
        v = np.zeros((nseg, 3))
        v[:, 0] = sp_[:, j]
        if contact is not None:  # the camera's own motion on its mast (odometry.camera_velocity)
            v -= np.cross(w[:, j], contact)
        step, jr = steps[:, j], jrs[:, j]
        # the displacement over the step, J_l(ω Δt) v Δt, exactly like the filter's BodyMotion
        disp = np.einsum("nij,nj->ni", right_jacobian(-phi[:, j]), v * d[:, None])
        dr_sd = dR @ skew(disp)
        # covariance of (δθ, δp): δθ' = stepᵀ δθ − Jr Δt n_g ; δp' = δp − ΔR [disp]× δθ + ΔR n_v Δt
        a = np.broadcast_to(np.eye(6), (nseg, 6, 6)).copy()
        a[:, :3, :3] = np.swapaxes(step, 1, 2)
        a[:, 3:, :3] = -dr_sd
        b_g = -jr * d[:, None, None]
        b_v = dR * d[:, None, None]
        cov = a @ cov @ np.swapaxes(a, 1, 2)
        cov[:, :3, :3] += b_g @ np.swapaxes(b_g, 1, 2) * (gyro_density**2 * inv_dt)[:, None, None]
        cov[:, 3:, 3:] += (b_v * qv[None, None, :]) @ np.swapaxes(b_v, 1, 2) * inv_dt[:, None, None]
        # ∂Δp/∂b: the rotation so far turns this step's displacement, and the step's own arc
        # bends with the rate (first order: ½ [v]× Δt²)
        j_pb = j_pb - dr_sd @ j_rb + dR @ skew(v) * (0.5 * d * d)[:, None, None]
        j_rb = np.swapaxes(step, 1, 2) @ j_rb - jr * d[:, None, None]
        # a scale error s changes this step's rate by −s (ω − b)_z ẑ: the bias's effect
        # through the column (ω − b)_z ẑ
        wz = np.zeros((nseg, 3))
        wz[:, 2] = w[:, j, 2]
        arc = np.einsum("nij,nj->ni", dR @ skew(v), wz) * (0.5 * d * d)[:, None]
        j_ps = j_ps - np.einsum("nij,nj->ni", dr_sd, j_rs) + arc
        j_rs = np.einsum("nji,nj->ni", step, j_rs) - np.einsum("nij,nj->ni", jr, wz) * d[:, None]
        dp = dp + np.einsum("nij,nj->ni", dR, disp)
        dR = dR @ step
    cov = cov + np.eye(6)[None] * 1e-12
    total = dt.sum(axis=1)
    return [
        Preintegrated(dR[k], dp[k], cov[k], j_rb[k], j_pb[k], float(total[k]), j_rs[k], j_ps[k])
        for k in range(nseg)
    ]


@dataclass
class SmootherProblem:
    r_wb: FloatArray  # (K, 3, 3) initial poses; pose 0 is fixed
    t_wb: FloatArray  # (K, 3)
    odometry: list[Preintegrated]  # K − 1 factors, between k and k + 1
    obs_frame: NDArray[np.int64]  # (M,)
    obs_landmark: NDArray[np.int64]  # (M,) index into landmarks
    obs_bearing: FloatArray  # (M, 3) body frame
    obs_sigma: FloatArray  # (M,) rad
    landmarks: FloatArray  # (N, 3) initial
    bias0: FloatArray  # (3,) the bias the odometry was preintegrated with
    bias_prior: FloatArray  # (3,)
    bias_prior_cov: FloatArray  # (3, 3)
    bias_segment: NDArray[np.int64] | None = None  # (K − 1,) bias segment of each factor
    bias_walk_cov: FloatArray | None = None  # (S − 1, 3, 3) between consecutive segments
    scale_prior_sigma: float = 0.0  # σ of the yaw-rate scale error (0: not estimated)
    odometry_huber: float = 3.0  # whitened odometry residual at which factors weigh half


@dataclass
class SmootherResult:
    r_wb: FloatArray
    t_wb: FloatArray
    landmarks: FloatArray
    landmark_cov: FloatArray  # (N, 3, 3) marginal covariances, bearings at their long-run σ
    bias: FloatArray  # (S, 3) per bias segment
    scale: float  # the yaw-rate scale error s
    cost_initial: float
    cost_final: float
    iterations: int
    outliers: int
    bearing_rms_rad: float
    #: the bearings' long-run variance over their configured σ² (:func:`bearing_variance_factor`),
    #: at which ``landmark_cov`` is taken
    bearing_variance_factor: float = 1.0
    #: (N, 3, 3) the marginal covariances with the bearings at their configured σ: how well
    #: the drive's geometry locates each landmark, whatever the camera's precision
    landmark_cov_configured: FloatArray | None = None
    #: (N, 3, 3) each landmark's own error, once the map's frame is taken out: ``landmark_cov``
    #: less what all landmarks share, the frame's error (:func:`frame_jacobian`) fitted over
    #: them in least squares. The landmarks' errors are correlated through the drive (a
    #: speed noise that makes the drive 0.1 % long makes every landmark 0.1 % far); the map
    #: keeps them as independent, which holds for these, not for the marginals.
    landmark_cov_own: FloatArray | None = None
    #: (4, 4) the map frame's error (shift x, y; turn; scale) against the world (the ground);
    #: None when it could not be told apart (fewer than 3 landmarks, a singular system)
    frame_cov: FloatArray | None = None


#: how many times :func:`smooth` solves again with the bearings at the long-run σ their
#: residuals show (:func:`bearing_variance_factor`); it stops sooner once that σ is the one
#: it weighed them at, within :data:`REWEIGHT_TOLERANCE` (a factor of the variance)
BEARING_REWEIGHT_ROUNDS = 1
REWEIGHT_TOLERANCE = 0.1


def _huber_weights(norm_res: FloatArray, k: float = 2.5) -> FloatArray:
    return np.where(norm_res <= k, 1.0, k / np.maximum(norm_res, 1e-12))


class _Layout:
    def __init__(self, k: int, n: int, nseg: int) -> None:
        self.k, self.n, self.nseg = k, n, nseg
        self.pose0 = 0  # poses 1..K-1: 6 each
        self.lm0 = 6 * (k - 1)
        self.bias0 = self.lm0 + 3 * n
        self.scale = self.bias0 + 3 * nseg
        self.size = self.scale + 1

    def bias(self, s: NDArray[np.int64]) -> NDArray[np.int64]:
        return self.bias0 + 3 * s

    def pose(self, k: NDArray[np.int64]) -> NDArray[np.int64]:
        """Column of φ_k (then δt_k at +3); −1 for the fixed pose 0."""
        return np.where(k > 0, 6 * (k - 1), -1)

    def lm(self, i: NDArray[np.int64]) -> NDArray[np.int64]:
        return self.lm0 + 3 * i


def _scatter(
    rows_list: list[NDArray[np.int64]],
    cols_list: list[NDArray[np.int64]],
    vals_list: list[FloatArray],
    row0: NDArray[np.int64],
    col0: NDArray[np.int64],
    block: FloatArray,
) -> None:
    """Queue a dense (B, r, c) block per item at rows row0[b] + i, cols col0[b] + j."""
    _, r, c = block.shape
    keep = col0 >= 0
    if not keep.any():
        return
    ii = (row0[keep][:, None, None] + np.arange(r)[None, :, None]).repeat(c, axis=2)
    jj = (col0[keep][:, None, None] + np.arange(c)[None, None, :]).repeat(r, axis=1)
    rows_list.append(ii.ravel())
    cols_list.append(jj.ravel())
    vals_list.append(block[keep].ravel())


def _whiten(cov: FloatArray) -> FloatArray:
    """``W`` with ``Wᵀ W = cov⁻¹`` for (B, d, d) covariances."""
    return np.linalg.cholesky(np.linalg.inv(cov)).swapaxes(-1, -2)


def smooth(
    problem: SmootherProblem,
    iterations: int = 15,
    reweight_rounds: int = BEARING_REWEIGHT_ROUNDS,
) -> SmootherResult:
    """Levenberg–Marquardt over poses, landmarks and gyro biases (see the module doc), solved
    again with the bearings at their measured long-run σ (:func:`bearing_variance_factor`)
    up to ``reweight_rounds`` times, until the σ they are weighted at is the σ their
    residuals show."""
    r_wb = problem.r_wb.copy()
    t_wb = problem.t_wb.copy()
    lms = problem.landmarks.copy()
    k, n = r_wb.shape[0], lms.shape[0]
    seg = (
        problem.bias_segment
        if problem.bias_segment is not None
        else np.zeros(max(k - 1, 0), dtype=np.int64)
    )
    nseg = int(seg.max(initial=0)) + 1
    bias = np.tile(problem.bias0, (nseg, 1))
    scale = 0.0
    lay = _Layout(k, n, nseg)
    scale_w = 1.0 / problem.scale_prior_sigma if problem.scale_prior_sigma > 0 else 1e9
    odo = problem.odometry
    m_odo = len(odo)
    if m_odo:
        o_w = _whiten(np.stack([f.cov for f in odo]))
        dR = np.stack([f.dR for f in odo])
        dp = np.stack([f.dp for f in odo])
        j_rb = np.stack([f.j_rb for f in odo])
        j_pb = np.stack([f.j_pb for f in odo])
        j_rs = np.stack([f.j_rs for f in odo])
        j_ps = np.stack([f.j_ps for f in odo])
    b_w = _whiten(problem.bias_prior_cov[None])[0]
    walk_cov = problem.bias_walk_cov
    walk_w = _whiten(walk_cov) if nseg > 1 and walk_cov is not None else np.zeros((0, 3, 3))
    basis = np.swapaxes(tangent_basis(problem.obs_bearing), 1, 2)  # (M, 2, 3)
    # the bearings' σ the solve weighs them at: the configured one, then their long-run one
    variance_scale = 1.0
    sigma = problem.obs_sigma
    fi, li = problem.obs_frame, problem.obs_landmark
    i0 = np.arange(m_odo)

    def residuals(
        r_wb: FloatArray, t_wb: FloatArray, lms: FloatArray, bias: FloatArray, scale: float
    ) -> dict[str, FloatArray]:
        out: dict[str, FloatArray] = {}
        if m_odo:
            db = bias[seg] - problem.bias0  # (K−1, 3)
            pred_r = dR @ rotmat_exp(np.einsum("nij,nj->ni", j_rb, db) + j_rs * scale)
            rk, rk1 = r_wb[i0], r_wb[i0 + 1]
            r_th = rotmat_log(np.swapaxes(pred_r, 1, 2) @ np.swapaxes(rk, 1, 2) @ rk1)
            r_th = np.atleast_2d(r_th)
            r_p = np.einsum("nji,nj->ni", rk, t_wb[i0 + 1] - t_wb[i0]) - (
                dp + np.einsum("nij,nj->ni", j_pb, db) + j_ps * scale
            )
            out["th"] = r_th
            out["odo"] = np.einsum("nij,nj->ni", o_w, np.concatenate([r_th, r_p], axis=1))
        else:
            out["th"] = np.zeros((0, 3))
            out["odo"] = np.zeros((0, 6))
        ell = np.einsum("nji,nj->ni", r_wb[fi], lms[li] - t_wb[fi])
        h = ell / np.linalg.norm(ell, axis=-1, keepdims=True)
        out["ell"], out["h"] = ell, h
        out["b"] = np.einsum("nij,nj->ni", basis, problem.obs_bearing - h) / sigma[:, None]
        out["prior"] = b_w @ (bias[0] - problem.bias_prior)
        out["walk"] = np.einsum("nij,nj->ni", walk_w, bias[1:] - bias[:-1])
        out["scale"] = np.array([scale_w * scale])
        return out

    def huber(norm: FloatArray, k: float) -> FloatArray:
        return np.where(norm <= k, 0.5 * norm**2, k * norm - 0.5 * k**2)

    def cost_of(parts: dict[str, FloatArray]) -> float:
        nb = np.linalg.norm(parts["b"], axis=1)
        no = np.linalg.norm(parts["odo"], axis=1)
        quad = np.sum(parts["prior"] ** 2) + np.sum(parts["walk"] ** 2) + parts["scale"][0] ** 2
        c2 = problem.odometry_huber**2
        robust = np.sum(huber(nb, 2.5)) + np.sum(0.5 * c2 * np.log1p(no**2 / c2))  # Cauchy
        return float(0.5 * quad + robust)

    parts = residuals(r_wb, t_wb, lms, bias, scale)
    cost0 = cost = cost_of(parts)
    lam = 1e-4
    it = 0
    a = None
    jac = sp.csr_matrix((0, lay.size))
    bearing_rows = slice(0, 0)
    total_iterations = 0
    for rnd in range(reweight_rounds + 1):
        for it in range(1, iterations + 1):  # noqa: B007
            rows: list[NDArray[np.int64]] = []
            cols: list[NDArray[np.int64]] = []
            vals: list[FloatArray] = []
            res_all: list[FloatArray] = []
            row = 0
            if m_odo:  # odometry blocks, 6 rows each
                r_th = parts["th"]
                jinv = right_jacobian_inv(r_th)
                rk, rk1 = r_wb[i0], r_wb[i0 + 1]
                blk_k = np.zeros((m_odo, 6, 6))
                blk_k[:, :3, :3] = -jinv @ np.swapaxes(rk1, 1, 2) @ rk
                blk_k[:, 3:, :3] = skew(np.einsum("nji,nj->ni", rk, t_wb[i0 + 1] - t_wb[i0]))
                blk_k[:, 3:, 3:] = -np.swapaxes(rk, 1, 2)
                blk_k1 = np.zeros((m_odo, 6, 6))
                blk_k1[:, :3, :3] = jinv
                blk_k1[:, 3:, 3:] = np.swapaxes(rk, 1, 2)
                blk_b = np.zeros((m_odo, 6, 3))
                rot_back = -jinv @ np.swapaxes(rotmat_exp(r_th), 1, 2)
                blk_b[:, :3] = rot_back @ j_rb
                blk_b[:, 3:] = -j_pb
                blk_s = np.zeros((m_odo, 6, 1))
                blk_s[:, :3, 0] = np.einsum("nij,nj->ni", rot_back, j_rs)
                blk_s[:, 3:, 0] = -j_ps
                # Huber on whole factors through IRLS weights (a slipping wheel)
                ow = np.sqrt(
                    1.0
                    / (1.0 + (np.linalg.norm(parts["odo"], axis=1) / problem.odometry_huber) ** 2)
                )[:, None, None]
                r0 = row + 6 * i0
                _scatter(rows, cols, vals, r0, lay.pose(i0), ow * (o_w @ blk_k))
                _scatter(rows, cols, vals, r0, lay.pose(i0 + 1), ow * (o_w @ blk_k1))
                _scatter(rows, cols, vals, r0, lay.bias(seg), ow * (o_w @ blk_b))
                _scatter(rows, cols, vals, r0, np.full(m_odo, lay.scale), ow * (o_w @ blk_s))
                res_all.append((parts["odo"] * ow[:, :, 0]).ravel())
                row += 6 * m_odo
            # bearing blocks, 2 rows each, Huber through IRLS weights
            m = fi.size
            ell, h = parts["ell"], parts["h"]
            wts = np.sqrt(_huber_weights(np.linalg.norm(parts["b"], axis=1)))
            norm = np.linalg.norm(ell, axis=-1)
            dh = (np.eye(3)[None] - np.einsum("ni,nj->nij", h, h)) / norm[:, None, None]
            g = -np.einsum("nij,njk->nik", basis, dh) / sigma[:, None, None]
            g = g * wts[:, None, None]
            rt = np.swapaxes(r_wb[fi], 1, 2)
            blk_pose = np.concatenate([g @ skew(ell), -g @ rt], axis=2)
            r0 = row + 2 * np.arange(m)
            bearing_rows = slice(row, row + 2 * m)
            _scatter(rows, cols, vals, r0, lay.pose(fi), blk_pose)
            _scatter(rows, cols, vals, r0, lay.lm(li), g @ rt)
            res_all.append((parts["b"] * wts[:, None]).ravel())
            row += 2 * m
            # bias prior and random walk
            _scatter(rows, cols, vals, np.array([row]), lay.bias(np.array([0])), b_w[None])
            res_all.append(parts["prior"])
            row += 3
            if nseg > 1:
                sidx = np.arange(nseg - 1)
                r0 = row + 3 * sidx
                _scatter(rows, cols, vals, r0, lay.bias(sidx), -walk_w)
                _scatter(rows, cols, vals, r0, lay.bias(sidx + 1), walk_w)
                res_all.append(parts["walk"].ravel())
                row += 3 * (nseg - 1)
            _scatter(
                rows, cols, vals, np.array([row]), np.array([lay.scale]), np.array([[[scale_w]]])
            )
            res_all.append(parts["scale"])
            row += 1
            jac = sp.csr_matrix(
                (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                shape=(row, lay.size),
            )
            res = np.concatenate(res_all)
            a = (jac.T @ jac).tocsc()
            grad = jac.T @ res
            diag = a.diagonal()
            improved, rel_drop = False, 0.0
            for _ in range(8):
                try:
                    step = -_LandmarkSchur(a, lay, lam * np.maximum(diag, 1e-9)).solve(grad)
                except (np.linalg.LinAlgError, ValueError):
                    lam *= 10
                    continue
                if not np.all(np.isfinite(step)):
                    lam *= 10
                    continue
                cand = _apply(step, r_wb, t_wb, lms, bias, scale, lay)
                cparts = residuals(*cand)
                ccost = cost_of(cparts)
                if ccost < cost:
                    r_wb, t_wb, lms, bias, scale = cand
                    parts, improved = cparts, True
                    rel_drop = (cost - ccost) / max(cost, 1e-12)
                    cost = ccost
                    lam = max(lam / 3, 1e-9)
                    break
                lam *= 10
            if not improved or rel_drop < 1e-7:
                break
        total_iterations += it
        nb = np.linalg.norm(parts["b"], axis=1)
        inlier = nb <= 2.5
        factor = bearing_variance_factor(parts["b"][inlier], fi[inlier], li[inlier])
        if rnd == reweight_rounds or abs(factor - 1.0) <= REWEIGHT_TOLERANCE:
            break
        # weighed at the configured σ, the bearings count for less than they are worth
        # against the odometry, and the drive's odometry errors (a gyro's turn) stay in the
        # map, where the covariance, taken at the long-run σ, says they are not
        variance_scale *= factor
        sigma = problem.obs_sigma * math.sqrt(variance_scale)
        parts = residuals(r_wb, t_wb, lms, bias, scale)
        cost = cost_of(parts)
        lam = 1e-4
    lm_cov = lm_cov_configured = lm_own = np.zeros((n, 3, 3))
    frame_cov: FloatArray | None = None  # too few landmarks: the marginals hold the frame
    if n and a is not None:
        # the information again, the bearings' rows at their configured σ, then at their
        # long-run one
        row_scale = np.ones(jac.shape[0])
        row_scale[bearing_rows] = math.sqrt(variance_scale)
        configured = sp.diags(row_scale) @ jac
        lm_cov_configured = _landmark_covariances((configured.T @ configured).tocsc(), lay, n)
        row_scale[bearing_rows] = 1.0 / math.sqrt(factor)
        scaled = sp.diags(row_scale) @ jac
        if n >= 3:
            lm_cov, lm_own, split = _split_covariances((scaled.T @ scaled).tocsc(), lay, lms[:, :2])
            if np.all(np.isfinite(split)):
                frame_cov = split
            else:  # singular: the marginals (NaN too) say so, the frame stays unknown
                lm_own = lm_cov
        else:
            lm_cov = lm_own = _landmark_covariances((scaled.T @ scaled).tocsc(), lay, n)
    ang_rms = float(np.sqrt(np.mean((nb * sigma) ** 2 / 2))) if nb.size else 0.0
    return SmootherResult(
        r_wb,
        t_wb,
        lms,
        lm_cov,
        bias,
        float(scale),
        cost0,
        cost,
        total_iterations,
        int((nb > 5.0).sum()),
        ang_rms,
        factor * variance_scale,
        lm_cov_configured,
        lm_own,
        frame_cov,
    )


def bearing_variance_factor(
    whitened: FloatArray, frame: NDArray[np.int64], landmark: NDArray[np.int64]
) -> float:
    """The bearings' long-run variance, in units of their configured σ² (1: as configured).

    A landmark's position is the average of its track, so what sets its covariance is the
    variance of a track's *mean* error, and KLT errors are correlated along a track (the
    tracked point drifts for several frames: lag-one autocorrelation 0.6 on rendered
    drives). The per-bearing residual variance alone then makes the map several times too
    sure of itself; the configured σ makes it several times too unsure. This is the
    Newey–West (1987) estimate: the residuals' autocovariance ``γ(ℓ)`` between bearings of
    the same landmark ``ℓ`` frames apart, summed with Bartlett weights up to the bandwidth
    ``L = ⌊4 (T/100)^(2/9)⌋`` (Newey & West 1994; ``T`` the median track length), per
    tangent axis. 1.0 when there is too little to tell (fewer than 100 pairs at lag 0)."""
    if landmark.size < 100:
        return 1.0
    lengths = np.bincount(landmark)
    track = float(np.median(lengths[lengths > 0]))
    bandwidth = max(1, math.floor(4.0 * (track / 100.0) ** (2.0 / 9.0)))
    order = np.lexsort((frame, landmark))
    # one key per bearing, landmarks far enough apart that ``lag`` never reaches the next
    key = landmark[order].astype(np.int64) * (int(frame.max()) + bandwidth + 1) + frame[order]
    res = whitened[order]
    gamma0 = float(np.mean(np.sum(res * res, axis=1)) / 2)
    total = gamma0
    for lag in range(1, bandwidth + 1):
        at = np.searchsorted(key, key + lag)
        hit = at < key.size
        hit[hit] = key[at[hit]] == key[hit] + lag  # the same landmark, ``lag`` frames on
        if not hit.any():
            continue
        gamma = float(np.mean(np.sum(res[hit] * res[at[hit]], axis=1)) / 2)
        total += 2.0 * (1.0 - lag / (bandwidth + 1)) * gamma
    return total if total > 0 else gamma0


def _apply(
    step: FloatArray,
    r_wb: FloatArray,
    t_wb: FloatArray,
    lms: FloatArray,
    bias: FloatArray,
    scale: float,
    lay: _Layout,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]:
    r_new = r_wb.copy()
    t_new = t_wb.copy()
    if lay.k > 1:
        s = step[: lay.lm0].reshape(-1, 6)
        r_new[1:] = r_wb[1:] @ rotmat_exp(s[:, :3])
        t_new[1:] = t_wb[1:] + s[:, 3:]
    l_new = lms + step[lay.lm0 : lay.bias0].reshape(-1, 3)
    b_new = bias + step[lay.bias0 : lay.scale].reshape(-1, 3)
    return r_new, t_new, l_new, b_new, scale + float(step[lay.scale])


class _LandmarkSchur:
    """The (damped) normal equations ``(a + diag(damp)) x = b`` solved by eliminating the
    landmarks: no factor ties two landmarks, so their part of ``a`` is 3×3 block-diagonal and
    inverts block by block; what remains (poses, gyro biases, scale) is one dense Cholesky.
    A sparse LU of the whole system fills in almost densely (a landmark is seen from hundreds
    of frames) and took minutes on a garden-sized drive; this takes a second or less.
    ``LinAlgError`` when the system is not positive definite."""

    def __init__(self, a: sp.spmatrix, lay: _Layout, damp: FloatArray) -> None:
        a = sp.csr_matrix(a)
        n = lay.n
        self.lm = np.arange(lay.lm0, lay.bias0)
        self.rest = np.r_[np.arange(0, lay.lm0), np.arange(lay.bias0, lay.size)]
        base = lay.lm0 + 3 * np.arange(n)
        rr = (base[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
        cc = (base[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
        blocks = np.asarray(a[rr.ravel(), cc.ravel()]).reshape(n, 3, 3)
        blocks = blocks + np.einsum("ij,nj->nij", np.eye(3), damp[base[:, None] + np.arange(3)])
        self.ll_inv = np.linalg.inv(blocks)  # LinAlgError if a landmark is not constrained
        self.d_inv = sp.bsr_matrix(
            (self.ll_inv, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)
        ).tocsr()
        rows = a[self.rest]
        self.a_rl = rows[:, self.lm]
        self.m = self.a_rl @ self.d_inv  # A_rl A_ll⁻¹
        s = rows[:, self.rest].toarray()  # dense: the reduced system fills in anyway
        s -= self._m_a_lr()
        s[np.diag_indices_from(s)] += damp[self.rest]
        self.chol = sla.cho_factor(s, lower=True, overwrite_a=True, check_finite=False)
        if not np.all(np.isfinite(self.chol[0])):
            raise np.linalg.LinAlgError("reduced system not finite")

    #: dense BLAS against scipy's sparse product, multiply-adds per second (about)
    DENSE_SPEEDUP = 8.0

    def _m_a_lr(self) -> FloatArray:
        """``A_rl A_ll⁻¹ A_lr`` (dense): a sparse product when few poses see each landmark,
        a dense one (BLAS) when many do, whichever costs fewer operations."""
        per_col = np.diff(self.a_rl.tocsc().indptr).astype(np.float64)
        sparse_ops = float(np.sum(per_col**2))
        r, c = self.a_rl.shape
        if r * r * c / self.DENSE_SPEEDUP < sparse_ops:
            return np.asarray(self.m.toarray() @ self.a_rl.T.toarray())
        return np.asarray((self.m @ self.a_rl.T).toarray())

    def solve(self, b: FloatArray) -> FloatArray:
        b_l = b[self.lm]
        x_r = sla.cho_solve(self.chol, b[self.rest] - self.m @ b_l, check_finite=False)
        x = np.empty_like(b)
        x[self.rest] = x_r
        x[self.lm] = self.d_inv @ (b_l - self.a_rl.T @ x_r)
        return x

    def _joint_factor(self) -> FloatArray:
        """``X`` (R, N, 3) with the landmarks' joint covariance ``blockdiag(A_ll⁻¹) + XᵀX``
        (``X = L⁻¹ A_rl A_ll⁻¹``, ``L`` the reduced system's Cholesky factor)."""
        x = sla.solve_triangular(self.chol[0], self.m.toarray(), lower=True, check_finite=False)
        out: FloatArray = x.reshape(x.shape[0], self.ll_inv.shape[0], 3)
        return out

    def landmark_covariances(self) -> FloatArray:
        """The 3×3 diagonal blocks of the inverse for every landmark:
        ``A_ll⁻¹ + (A_ll⁻¹ A_lr) S⁻¹ (A_rl A_ll⁻¹)`` with ``S`` the reduced system."""
        x3 = self._joint_factor()
        cov: FloatArray = self.ll_inv + np.einsum("rni,rnj->nij", x3, x3)
        return cov

    def frame_split(self, xy: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The landmarks' marginal covariances (N, 3, 3), split into each landmark's own
        error in the map's frame (N, 3, 3) and the frame's (4, 4), for landmarks at ``xy``
        (N, 2): see :func:`frame_jacobian` and :class:`SmootherResult`."""
        x3 = self._joint_factor()
        n = xy.shape[0]
        a = frame_jacobian(np.column_stack([xy, np.zeros(n)]))  # (N, 3, 4)
        # the least-squares frame over the landmarks, δ = (AᵀA)⁻¹ Aᵀ e = Σ G_i e_i
        g = np.linalg.solve(np.einsum("nki,nkj->ij", a, a), np.einsum("nkc->cnk", a).reshape(4, -1))
        g = g.reshape(4, n, 3).transpose(1, 0, 2)  # G_i (4, 3)
        xg = np.einsum("rnk,nck->rc", x3, g)  # X Gᵀ (R, 4)
        # S_i = cov(e_i, δ) = A_ll⁻¹_i G_iᵀ + X_iᵀ (X Gᵀ)
        s = np.einsum("nkl,ncl->nkc", self.ll_inv, g) + np.einsum("rnk,rc->nkc", x3, xg)
        frame = np.einsum("nck,nkl,ndl->cd", g, self.ll_inv, g) + xg.T @ xg
        marginal = self.ll_inv + np.einsum("rni,rnj->nij", x3, x3)
        sa = np.einsum("nkc,nlc->nkl", s, a)  # S_i A_iᵀ
        own = marginal - sa - np.swapaxes(sa, 1, 2) + np.einsum("nkc,cd,nld->nkl", a, frame, a)
        return marginal, own, frame


def _landmark_covariances(a: sp.csc_matrix, lay: _Layout, n: int) -> FloatArray:
    """Diagonal 3×3 blocks of the inverse information for every landmark (one factorisation)."""
    try:
        out = _LandmarkSchur(a, lay, np.zeros(lay.size)).landmark_covariances()
    except (np.linalg.LinAlgError, ValueError):
        return np.full((n, 3, 3), np.nan)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _split_covariances(
    a: sp.csc_matrix, lay: _Layout, xy: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:meth:`_LandmarkSchur.frame_split` of the information ``a`` (one factorisation),
    symmetric; NaN when it is singular."""
    n = xy.shape[0]
    try:
        parts = _LandmarkSchur(a, lay, np.zeros(lay.size)).frame_split(xy)
    except (np.linalg.LinAlgError, ValueError):
        return np.full((n, 3, 3), np.nan), np.full((n, 3, 3), np.nan), np.full((4, 4), np.nan)
    marginal, own, frame = (0.5 * (c + np.swapaxes(c, -1, -2)) for c in parts)
    return marginal, own, frame
