"""Rotation conventions of docs/design.md §3, in one place.

* Quaternions are Hamilton, scalar first: ``q = (w, x, y, z)``.
* ``q_ab`` maps b-coordinates into a: ``v_a = R(q_ab) v_b``; composition ``q_ac = q_ab ⊗ q_bc``.
* ``[a]×`` is the skew matrix with ``[a]× b = a × b``.
* The exponential map takes a rotation vector ``φ`` (axis · angle, rad) to the quaternion
  ``(cos ½|φ|, sin ½|φ| φ/|φ|)``; the logarithm is its inverse on the short arc (|φ| ≤ π).

Every function broadcasts over leading dimensions (``(..., 4)`` quaternions, ``(..., 3)``
vectors), so estimators can apply them to arrays of landmarks without a Python loop.
``scipy.spatial.transform.Rotation`` (scalar-last!) is used where a conversion is involved
(matrices, Euler angles); the small, hot formulas (products, R(q), exp/log) are written out
because they run at IMU rate on single quaternions, where scipy's object overhead dominates.
"""

from __future__ import annotations

import math
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]

IDENTITY_QUAT: FloatArray = np.array([1.0, 0.0, 0.0, 0.0])

# Below this angle (rad) exp/log use Taylor series: sin(x)/x loses no digits there.
_SMALL_ANGLE = 1e-6


def as_quat(q: ArrayLike) -> FloatArray:
    """``q`` as a float array with a last axis of 4 (no normalisation)."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"a quaternion has 4 components (w, x, y, z), got shape {q.shape}")
    return q


def quat_normalize(q: ArrayLike) -> FloatArray:
    """Unit quaternion with a non-negative scalar part (the canonical sign)."""
    q = as_quat(q)
    if q.ndim == 1:
        return _unit(*q.tolist())
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_conjugate(q: ArrayLike) -> FloatArray:
    """``q*``: the inverse rotation of a unit quaternion (``q_ba = q_ab*``)."""
    q = as_quat(q)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _unit(w: float, x: float, y: float, z: float) -> FloatArray:
    """A single quaternion's components scaled to unit length, scalar part ≥ 0."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    n = -n if w < 0.0 else n
    return np.array([w / n, x / n, y / n, z / n])


def _hamilton(
    pw: Any, px: Any, py: Any, pz: Any, qw: Any, qx: Any, qy: Any, qz: Any
) -> tuple[Any, Any, Any, Any]:
    """The components of ``p ⊗ q`` from theirs (floats, or arrays broadcasting alike)."""
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def quat_multiply(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """Hamilton product ``p ⊗ q`` (so ``R(p ⊗ q) = R(p) R(q)``)."""
    p, q = as_quat(p), as_quat(q)
    if p.ndim == 1 and q.ndim == 1:  # the hot single-quaternion case, without broadcasting
        return np.array(_hamilton(*p.tolist(), *q.tolist()))
    return np.stack(_hamilton(*np.moveaxis(p, -1, 0), *np.moveaxis(q, -1, 0)), axis=-1)


def quat_multiply_unit(p: FloatArray, q: FloatArray) -> FloatArray:
    """``quat_normalize(quat_multiply(p, q))`` for two single quaternions, without the
    arrays between: the same numbers (the filters' attitude steps, each IMU sample's)."""
    return _unit(*_hamilton(*p.tolist(), *q.tolist()))


def quat_to_rotmat(q: ArrayLike) -> FloatArray:
    """``R(q)`` for a unit quaternion, shape ``(..., 3, 3)``."""
    q = as_quat(q)
    if q.ndim == 1:
        w, x, y, z = q.tolist()
    else:
        w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]
    if q.ndim == 1:
        return np.array(rows)
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def quat_rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """``R(q) v`` (broadcasting ``q`` (..., 4) against ``v`` (..., 3))."""
    q = as_quat(q)
    v = np.asarray(v, dtype=np.float64)
    if q.ndim == 1 and v.ndim == 1:
        return quat_to_rotmat(q) @ v
    return np.einsum("...ij,...j->...i", quat_to_rotmat(q), np.asarray(v, dtype=np.float64))


def rotmat_to_quat(r: ArrayLike) -> FloatArray:
    """Unit quaternion (w ≥ 0) of a rotation matrix (via scipy, converted to scalar first)."""
    xyzw = Rotation.from_matrix(np.asarray(r, dtype=np.float64)).as_quat()
    return quat_normalize(xyzw[..., [3, 0, 1, 2]])


def quat_to_scipy(q: ArrayLike) -> Rotation:
    """A scipy ``Rotation`` from our scalar-first quaternion(s)."""
    return Rotation.from_quat(as_quat(q)[..., [1, 2, 3, 0]])


def quat_from_scipy(rot: Rotation) -> FloatArray:
    """Scalar-first quaternion(s) of a scipy ``Rotation``."""
    return quat_normalize(rot.as_quat()[..., [3, 0, 1, 2]])


def skew(a: ArrayLike) -> FloatArray:
    """``[a]×`` with ``[a]× b = a × b``, shape ``(..., 3, 3)``."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 1:
        x, y, z = a.tolist()
        return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    x, y, z = np.moveaxis(a, -1, 0)
    o = np.zeros_like(x)
    return np.stack(
        [np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], axis=-2
    )


def quat_exp(phi: ArrayLike) -> FloatArray:
    """Exponential map: rotation vector ``φ`` (rad) → unit quaternion."""
    phi = np.asarray(phi, dtype=np.float64)
    if phi.ndim == 1:
        x, y, z = phi.tolist()
        angle = math.sqrt(x * x + y * y + z * z)
        k = 0.5 - angle * angle / 48.0 if angle < _SMALL_ANGLE else math.sin(0.5 * angle) / angle
        return np.array([math.cos(0.5 * angle), k * x, k * y, k * z])
    angle = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * angle
    small = angle < _SMALL_ANGLE
    # sin(|φ|/2)/|φ| with its Taylor series ½ − |φ|²/48 near zero.
    safe = np.where(small, 1.0, angle)
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([np.cos(half), k * phi], axis=-1)


def quat_log(q: ArrayLike) -> FloatArray:
    """Logarithm: unit quaternion → rotation vector on the short arc (|φ| ≤ π)."""
    q = quat_normalize(q)  # w ≥ 0 picks the short arc
    w = np.clip(q[..., :1], -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    small = s < _SMALL_ANGLE
    angle = 2.0 * np.arctan2(s, w)
    # φ = angle · v/|v|; near zero angle/|v| → 2/w (series 2/w · (1 − s²/(3w²)) ≈ 2/w).
    w_safe = np.where(small, w, 1.0)  # w ≈ 1 whenever |v| is small
    k = np.where(
        small, 2.0 / w_safe * (1.0 - s**2 / (3.0 * w_safe**2)), angle / np.where(small, 1.0, s)
    )
    return k * v


def rotmat_exp(phi: ArrayLike) -> FloatArray:
    """Rodrigues: rotation vector → rotation matrix (``R(quat_exp(φ))``)."""
    return quat_to_rotmat(quat_exp(phi))


def rotmat_log(r: ArrayLike) -> FloatArray:
    """Rotation matrix → rotation vector (via scipy, which is stable near π)."""
    return Rotation.from_matrix(np.asarray(r, dtype=np.float64)).as_rotvec()


def omega_matrix(w: ArrayLike) -> FloatArray:
    """``Ω(ω)`` of docs/design.md §4 / paper eq. (15): ``[[0, ωᵀ], [−ω, −[ω]×]]``.

    With it, ``q̇ = ½ Ω(ω) q`` is the kinematics of ``q_{b←x}`` for any frame x fixed in the
    world while the body turns at ``ω`` (body frame): the robot-centric keyframe orientation
    ``q^{bj}`` of eq. (14). It equals left multiplication by the pure quaternion ``(0, −ω)``.
    """
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros((*w.shape[:-1], 4, 4))
    out[..., 0, 1:] = w
    out[..., 1:, 0] = -w
    out[..., 1:, 1:] = -skew(w)
    return out


def quat_derivative_body_to_fixed(q_bx: ArrayLike, w_body: ArrayLike) -> FloatArray:
    """``q̇_{b←x} = ½ Ω(ω) q_{b←x}`` (eq. 14): a fixed frame seen from the turning body."""
    return 0.5 * np.einsum("...ij,...j->...i", omega_matrix(w_body), as_quat(q_bx))


def quat_derivative_world_to_body(q_wb: ArrayLike, w_body: ArrayLike) -> FloatArray:
    """``q̇_wb = ½ q_wb ⊗ (0, ω)`` (docs/design.md §5, eq. 21 written for Hamilton ``q_wb``)."""
    w_body = np.asarray(w_body, dtype=np.float64)
    pure = np.concatenate([np.zeros((*w_body.shape[:-1], 1)), w_body], axis=-1)
    return 0.5 * quat_multiply(q_wb, pure)


def integrate_body_rate(q_wb: ArrayLike, w_body: ArrayLike, dt: float) -> FloatArray:
    """Exact update of ``q_wb`` for a constant body rate over ``dt``: ``q ⊗ exp(ω dt)``."""
    return quat_multiply(q_wb, quat_exp(np.asarray(w_body, dtype=np.float64) * dt))


def ypr_deg_to_quat(yaw: float, pitch: float, roll: float) -> FloatArray:
    """VN-100 yaw/pitch/roll (deg; intrinsic z-y'-x'', the 3-2-1 sequence) → ``q_ned←body``."""
    return quat_from_scipy(Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True))


def quat_to_ypr_deg(q: ArrayLike) -> FloatArray:
    """Inverse of :func:`ypr_deg_to_quat`: (yaw, pitch, roll) in degrees."""
    return quat_to_scipy(q).as_euler("ZYX", degrees=True)


def quat_angle(q: ArrayLike) -> FloatArray:
    """Rotation angle (rad, in [0, π]) of a unit quaternion."""
    return np.linalg.norm(quat_log(q), axis=-1)


def quat_distance(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """Angle (rad) of the rotation between ``p`` and ``q`` (sign-invariant)."""
    return quat_angle(quat_multiply(quat_conjugate(p), q))


def tuple3(v: ArrayLike) -> tuple[float, float, float]:
    """A 3-vector as a tuple of Python floats (for messages between processes)."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3).tolist()
    return x, y, z


@overload
def wrap_angle(a: float) -> float: ...
@overload
def wrap_angle(a: FloatArray) -> FloatArray: ...
def wrap_angle(a: float | FloatArray) -> float | FloatArray:
    """An angle (rad), or each of an array, wrapped into [−π, π)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def yaw_rotation(yaw: float) -> FloatArray:
    """``R_z(ψ)``: the rotation by heading ψ about the vertical (a planar pose's ``R_wb``;
    its transpose takes world vectors into such a body)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_to_quat(yaw: ArrayLike) -> FloatArray:
    """Rotation about +z by ``yaw`` rad (the planar mower's heading)."""
    yaw = np.asarray(yaw, dtype=np.float64)[..., None]
    zeros = np.zeros_like(yaw)
    return np.concatenate([np.cos(yaw / 2), zeros, zeros, np.sin(yaw / 2)], axis=-1)


def quat_to_yaw(q: ArrayLike) -> FloatArray:
    """Heading (rad) of the body x axis projected on the world xy plane."""
    r = quat_to_rotmat(q)
    return np.arctan2(r[..., 1, 0], r[..., 0, 0])


def tangent_basis(u: ArrayLike) -> FloatArray:
    """(N, 3, 2): two orthonormal vectors ⊥ each unit vector of ``u`` (N, 3), right-handed
    with it (``e1 × e2 = u``): the 2D residual space of a bearing."""
    u = np.asarray(u, dtype=np.float64)
    ux, uy, uz = u[:, 0], u[:, 1], u[:, 2]
    # e1 = helper × u, helper x̂ (|u_x| < 0.9) or ŷ: (0, −u_z, u_y) or (u_z, 0, −u_x); written
    # out, as np.cross computes it (the same values), without its generality's cost (a
    # quarter of a frame update's bearing model)
    use_x = np.abs(ux) < 0.9
    zero = np.zeros_like(ux)
    e1 = np.empty_like(u)
    e1[:, 0] = np.where(use_x, zero, uz)
    e1[:, 1] = np.where(use_x, -uz, zero)
    e1[:, 2] = np.where(use_x, uy, -ux)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    out = np.empty((u.shape[0], 3, 2))
    out[:, :, 0] = e1
    out[:, :, 1] = cross_rows(u, e1)
    return out


def cross_rows(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row by row ``a × b`` of two (n, 3) arrays: np.cross's arithmetic (the same values)
    without its generic axis handling, which costs more than the products for small n."""
    out = np.empty_like(b)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def frame_jacobian(points: FloatArray) -> FloatArray:
    """(N, 3, 4): how an error ``δ = (t_x, t_y, θ, s)`` of a whole map's frame against the
    ground (a shift, a turn about the vertical and a scale, about the frame's origin) moves
    points at ``points`` (N, 3): ``δp_xy = t + θ ẑ × p + s p_xy``; heights stay."""
    n = points.shape[0]
    a = np.zeros((n, 3, 4))
    a[:, 0, 0] = a[:, 1, 1] = 1.0
    a[:, 0, 2], a[:, 1, 2] = -points[:, 1], points[:, 0]
    a[:, 0, 3], a[:, 1, 3] = points[:, 0], points[:, 1]
    return a
