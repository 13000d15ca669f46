"""Fit a body pose to bearings of known points (Gauss–Newton on SE(3), tangent residuals).

Used to measure the teach loop-closure error (the pose at the end of the loop against
landmarks mapped at its start) and to (re)initialise the mow-phase localizer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import rotmat_exp, skew, tangent_basis

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PoseFit:
    r_wb: FloatArray  # (3, 3)
    t_wb: FloatArray  # (3,)
    rms_rad: float  # RMS angular residual
    iterations: int
    covariance: FloatArray  # (6, 6) of the left error (δθ, δt), world axes


def fit_pose_to_bearings(
    points_w: FloatArray,
    bearings_b: FloatArray,
    r_wb: FloatArray,
    t_wb: FloatArray,
    sigma_rad: float,
    iterations: int = 15,
    fix_roll_pitch: bool = False,
) -> PoseFit:
    """Refine ``(R_wb, t_wb)`` so that ``normalize(R_wbᵀ (P_i − t)) ≈ u_i``.

    Residuals are the angle components of ``u_i − h_i`` in the tangent plane of ``u_i``;
    the update is a left perturbation ``R ← exp([δθ]×) R``, ``t ← t + δt``.
    """
    r, t = r_wb.copy(), t_wb.copy()
    basis = tangent_basis(bearings_b)
    bt = np.swapaxes(basis, 1, 2)
    info = np.zeros((6, 6))
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        rel = points_w - t  # (N, 3) world
        ell = rel @ r  # Rᵀ (P − t)
        norm = np.linalg.norm(ell, axis=-1)
        h = ell / norm[:, None]
        dh = (np.eye(3)[None] - np.einsum("ni,nj->nij", h, h)) / norm[:, None, None]
        # ℓ = Rᵀ exp(−[δθ]×)(P − t − δt) ≈ ℓ̂ + Rᵀ [P − t]× δθ − Rᵀ δt
        j = np.zeros((points_w.shape[0], 3, 6))
        j[:, :, :3] = np.einsum("ji,njk->nik", r, skew(rel))
        j[:, :, 3:] = -r.T[None]
        jj = np.einsum("nij,njk,nkl->nil", bt, dh, j).reshape(-1, 6)
        res = np.einsum("nij,nj->ni", bt, bearings_b - h).reshape(-1)
        if fix_roll_pitch:
            jj[:, :2] = 0.0
        info = jj.T @ jj / sigma_rad**2
        reg = np.diag([1e-9] * 6) + (np.diag([1e6, 1e6, 0, 0, 0, 0]) if fix_roll_pitch else 0.0)
        step = np.linalg.solve(jj.T @ jj + reg * sigma_rad**2, jj.T @ res)
        r = rotmat_exp(step[:3]) @ r
        t = t + step[3:]
        if np.linalg.norm(step) < 1e-10:
            break
    rel = points_w - t
    ell = rel @ r
    h = ell / np.linalg.norm(ell, axis=-1, keepdims=True)
    ang = np.arctan2(np.linalg.norm(np.cross(h, bearings_b), axis=-1), np.sum(h * bearings_b, -1))
    cov = np.linalg.pinv(info) if np.all(np.isfinite(info)) else np.full((6, 6), np.inf)
    return PoseFit(r, t, float(np.sqrt(np.mean(ang**2))), it, cov)
