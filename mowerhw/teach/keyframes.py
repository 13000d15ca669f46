"""Keyframes and the world pose (paper eqs 19–20; docs/design.md §4).

The robot-centric EKF estimates the current keyframe ``bj`` in the current body frame. A
keyframe stores the world frame in its own frame, ``(x_w^{bj}, q_w^{bj})``, and the
covariance of its world pose. Composition (eq. 19):

    x_w = x^{bj} + R(q^{bj}) x_w^{bj}          q_w = q^{bj} ⊗ q_w^{bj}

gives the world frame in the current body frame, and the outputs (eq. 20):

    x_b^w = −R(q_w)ᵀ x_w                        x_i^w = R(q_w)ᵀ (x_i − x_w)

World-pose covariances use the left error ``R_wb = exp([δθ]×) R̂_wb``, ``t = t̂ + δt`` in world
axes, ordered ``(δθ, δt)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import quat_conjugate, quat_multiply, quat_rotate, quat_to_rotmat, skew

FloatArray = NDArray[np.float64]


@dataclass
class Keyframe:
    index: int
    t: float
    x_w_in_kf: FloatArray  # x_w^{bj}: world origin in the keyframe frame
    q_w_in_kf: FloatArray  # q_w^{bj} = q_{bj←w}
    cov_w: FloatArray  # (6, 6) covariance of the keyframe's world pose, (δθ, δt)
    distance_m: float = 0.0  # distance driven when it was made


def compose(p: FloatArray, q: FloatArray, kf: Keyframe) -> tuple[FloatArray, FloatArray]:
    """Eq. (19): the world frame in the current body frame, ``(x_w, q_w)``."""
    x_w = p + quat_rotate(q, kf.x_w_in_kf)
    q_w = quat_multiply(q, kf.q_w_in_kf)
    return x_w, q_w


def body_in_world(x_w: FloatArray, q_w: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eq. (20), first row: the body's world position ``x_b^w`` and ``q_wb = q_w*``."""
    return -quat_rotate(quat_conjugate(q_w), x_w), quat_conjugate(q_w)


def landmarks_in_world(x_b: FloatArray, x_w: FloatArray, q_w: FloatArray) -> FloatArray:
    """Eq. (20), second row: ``x_i^w = R(q_w)ᵀ (x_i − x_w)`` for (N, 3) body-frame landmarks."""
    return (x_b - x_w) @ quat_to_rotmat(q_w)


def world_pose_covariance(
    kf: Keyframe, p: FloatArray, q: FloatArray, p_rel: FloatArray
) -> FloatArray:
    """Covariance (6, 6) of the body's world pose, (δθ, δt) in world axes.

    ``T_wb = T_w,bj ∘ (T_b,bj)⁻¹``. With the keyframe's world error (δθ_j, δt_j) and the EKF's
    (δp, δθ) (body frame, ``R(q^{bj}) = exp([δθ]×) R̂``):
    ``δθ_w = δθ_j − R_wb δθ``,  ``δt_w = δt_j + [v]× δθ_j − R_wb δp − R_wb [p]× δθ``
    with ``v = R_wb p`` (the keyframe origin relative to the body, world axes).
    """
    _, q_w = compose(p, q, kf)
    r_wb = quat_to_rotmat(quat_conjugate(q_w))
    v = r_wb @ p
    j_kf = np.eye(6)
    j_kf[3:, :3] = skew(v)
    j_rel = np.zeros((6, 6))  # columns: (δp, δθ) of the EKF
    j_rel[:3, 3:] = -r_wb
    j_rel[3:, :3] = -r_wb
    j_rel[3:, 3:] = -r_wb @ skew(p)
    return j_kf @ kf.cov_w @ j_kf.T + j_rel @ p_rel @ j_rel.T


def landmark_world_covariance(
    x_b: FloatArray, cov_b: FloatArray, q_w: FloatArray, cov_pose: FloatArray
) -> FloatArray:
    """Covariance (N, 3, 3) of ``x_i^w = R_wb x_i + t_wb``: pose (δθ, δt) and landmark terms."""
    r_wb = quat_to_rotmat(quat_conjugate(q_w))
    xw_rel = x_b @ r_wb.T  # R_wb x_i
    j = np.zeros((x_b.shape[0], 3, 6))
    j[:, :, :3] = -skew(xw_rel)
    j[:, :, 3:] = np.eye(3)
    pose = np.einsum("nij,jk,nlk->nil", j, cov_pose, j)
    cov: FloatArray = pose + np.einsum("ij,njk,lk->nil", r_wb, cov_b, r_wb)
    return cov
