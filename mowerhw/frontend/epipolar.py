"""Two-view outlier rejection on the sphere with a known rotation (gyro).

For bearings ``y1`` (previous frame) and ``y2`` (current frame, both body frames) of a static
point, with ``R21`` taking previous-frame vectors into the current frame and ``t`` the
translation direction, the epipolar constraint is ``y2 · (t × R21 y1) = 0``, i.e.
``t · n = 0`` with ``n = R21 y1 × y2``. Two tracks fix ``t`` (``n_a × n_b``): a 2-point RANSAC,
vectorised over all hypotheses at once. The residual of a track is its angular distance
from the epipolar plane, ``|y2 · m| `` with ``m`` the unit normal of the plane through ``t``
and ``R21 y1``. With (almost) no translation every track must simply be rotated by ``R21``.
Bearing vectors work for the whole omni field of view (rays behind the image plane too),
which ``cv2.findEssentialMat`` on normalized pinhole points cannot.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def _plane_residuals(t: FloatArray, ry1: FloatArray, y2: FloatArray) -> FloatArray:
    """(H, N) angular distance of each y2 from the plane spanned by t_h and R21 y1."""
    m = np.cross(t[:, None, :], ry1[None, :, :])  # (H, N, 3)
    norm = np.linalg.norm(m, axis=-1)
    res = np.abs(np.einsum("hnk,nk->hn", m, y2)) / np.maximum(norm, 1e-9)
    # a point at the epipole (t ∥ R21 y1): the plane is undefined; judge it by its rotation
    near_epipole = norm < 1e-3
    if near_epipole.any():
        rot = np.linalg.norm(y2 - ry1, axis=-1)
        res = np.where(near_epipole, rot[None, :], res)
    return res


def epipolar_inliers(
    y1: FloatArray,
    y2: FloatArray,
    r21: FloatArray,
    threshold_rad: float,
    iterations: int = 64,
    rng: np.random.Generator | None = None,
) -> tuple[NDArray[np.bool_], FloatArray | None]:
    """Inliers of the tracks ``y1 → y2`` under rotation ``r21`` and the best translation
    direction (None when the motion is a pure rotation or there are too few tracks)."""
    n = y1.shape[0]
    ry1 = y1 @ r21.T
    derot = np.linalg.norm(y2 - ry1, axis=1)
    if n == 0:
        return np.zeros(0, bool), None
    # Pure rotation (standing still, turning on the spot): every track must follow R21.
    if n < 5 or np.median(derot) < threshold_rad:
        return derot < 3.0 * threshold_rad, None
    rng = rng or np.random.default_rng(0)
    nvec = np.cross(ry1, y2)
    a = rng.integers(0, n, size=iterations)
    b = (a + rng.integers(1, n, size=iterations)) % n
    t = np.cross(nvec[a], nvec[b])
    norm = np.linalg.norm(t, axis=1)
    good = norm > 1e-12
    if not good.any():
        return derot < 3.0 * threshold_rad, None
    t = t[good] / norm[good, None]
    # the sign of t: most points move away from it (forward motion: the flow leaves the
    # epipole), which the residual does not see; keep both signs equivalent here
    res = _plane_residuals(t, ry1, y2)
    inl = res < threshold_rad
    best = int(np.argmax(inl.sum(axis=1)))
    mask = inl[best]
    # refine t on the inliers: the null vector of their n's, then re-score once
    if mask.sum() >= 3:
        _, _, vt = np.linalg.svd(nvec[mask])
        t_ref = vt[-1]
        mask = _plane_residuals(t_ref[None], ry1, y2)[0] < threshold_rad
        return mask, t_ref
    return mask, t[best]
