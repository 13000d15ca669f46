"""Numerical checks of a camera model: self-consistency and agreement with ``cv2.omnidir``.

Used by ``mowerhw camera info`` and by the tests, so the figures a user sees are the figures
the suite asserts on.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mowerhw.camera.model import OmniRadtanCamera
from mowerhw.common.geometry import FloatArray, quat_to_rotmat


def sample_valid_pixels(cam: OmniRadtanCamera, n: int, seed: int = 0) -> FloatArray:
    """``n`` pixels drawn uniformly over the valid region (fewer if it is tiny or empty)."""
    rng = np.random.default_rng(seed)
    out = np.empty((0, 2))
    for _ in range(50):
        if out.shape[0] >= n:
            break
        pix = rng.uniform([0.0, 0.0], [cam.width - 1.0, cam.height - 1.0], size=(2 * n, 2))
        out = np.concatenate([out, pix[cam.valid(pix)]])
    return out[:n]


def angle_between(a: FloatArray, b: FloatArray) -> FloatArray:
    """Angle (rad) between unit vectors, accurate near 0 (atan2 of |a×b| and a·b)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...i,...i->...", a, b))


def field_of_view(cam: OmniRadtanCamera, q_bc: Any = (1.0, 0.0, 0.0, 0.0)) -> dict[str, Any]:
    """What the valid region sees: the polar-angle range of its bearings (from the camera
    axis), the elevation range they give in the body frame, its radii around the principal
    point and its share of the image. Measured on valid pixels, so always finite."""
    pix = sample_valid_pixels(cam, 20000, seed=1)
    if pix.shape[0] == 0:
        return {"valid_pixel_fraction": 0.0}
    rays = cam.lift(pix)
    bearings_b = rays @ quat_to_rotmat(q_bc).T
    elevation = np.degrees(np.arcsin(np.clip(bearings_b[:, 2], -1.0, 1.0)))
    polar = np.degrees(np.arccos(np.clip(rays[:, 2], -1.0, 1.0)))
    radius = np.hypot(pix[:, 0] - cam.cu, pix[:, 1] - cam.cv)
    return {
        "mask": None
        if cam.mask is None
        else {
            "center_px": list(cam.mask.center_px),
            "inner_radius_px": cam.mask.inner_radius_px,
            "outer_radius_px": cam.mask.outer_radius_px,
        },
        "radius_px_range": [float(radius.min()), float(radius.max())],
        "polar_angle_min_deg": float(polar.min()),
        "polar_angle_max_deg": float(polar.max()),
        "model_limit_deg": float(np.degrees(cam.fold_angle)),
        "elevation_min_deg": float(elevation.min()),
        "elevation_max_deg": float(elevation.max()),
        "valid_pixel_fraction": float(cam.valid(_all_pixels(cam, step=8)).mean()),
    }


def _all_pixels(cam: OmniRadtanCamera, step: int) -> FloatArray:
    v, u = np.mgrid[0 : cam.height : step, 0 : cam.width : step]
    return np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)


def check_against_opencv(
    cam: OmniRadtanCamera, n: int = 20000, seed: int = 0, converged_px: float = 1e-7
) -> dict[str, Any]:
    """Compare ``project``/``lift`` with ``cv2.omnidir.projectPoints``/``undistortPoints``.

    * ``roundtrip_px_max``: ``project(lift(p)) − p`` over random valid pixels (ours alone).
    * ``project_vs_opencv_px_max``: our ``project`` vs ``cv2.omnidir.projectPoints`` on the
      bearings of those pixels (the whole valid field of view).
    * ``lift_vs_opencv_*``: our ``lift`` vs ``cv2.omnidir.undistortPoints``. OpenCV returns the
      undistorted point reprojected on the plane z = 1 (a line through the origin), after a
      fixed 20 fixed-point iterations of the distortion inverse. Where those iterations have
      converged (OpenCV's own ``projectPoints`` of its result lands within ``converged_px`` of
      the input) the two must agree; the fraction of the annulus where OpenCV converges and
      OpenCV's own error elsewhere are reported, not hidden.
    """
    import cv2  # OpenCV is only needed for this check

    pix = sample_valid_pixels(cam, n, seed)
    ours = cam.lift(pix)
    roundtrip = np.linalg.norm(cam.project(ours) - pix, axis=-1)

    rvec = tvec = np.zeros(3)
    cv_pix, _ = cv2.omnidir.projectPoints(ours.reshape(1, -1, 3), rvec, tvec, cam.K, cam.xi, cam.D)
    project_err = np.linalg.norm(cv_pix.reshape(-1, 2) - cam.project(ours), axis=-1)

    und = cv2.omnidir.undistortPoints(
        pix.reshape(1, -1, 2), cam.K, cam.D, np.array([[cam.xi]]), np.eye(3)
    ).reshape(-1, 2)
    line = np.concatenate([und, np.ones((und.shape[0], 1))], axis=-1)
    line /= np.linalg.norm(line, axis=-1, keepdims=True)
    # OpenCV gives a line; its direction is the one OpenCV's own projection maps back nearest
    # to the input pixel (beyond 90° from the axis the point lies at z < 0).
    candidates = []
    for sign in (1.0, -1.0):
        back, _ = cv2.omnidir.projectPoints(
            (sign * line).reshape(1, -1, 3), rvec, tvec, cam.K, cam.xi, cam.D
        )
        err = np.linalg.norm(back.reshape(-1, 2) - pix, axis=-1)
        candidates.append(np.where(np.isfinite(err), err, np.inf))
    use_neg = candidates[1] < candidates[0]
    cv_bearing = np.where(use_neg[:, None], -line, line)
    cv_self_err = np.minimum(candidates[0], candidates[1])
    converged = cv_self_err <= converged_px
    lift_px = np.linalg.norm(cam.project(cv_bearing) - cam.project(ours), axis=-1)
    lift_ang = angle_between(cv_bearing, ours)
    radius = np.linalg.norm(pix - [cam.cu, cam.cv], axis=-1)

    def worst(values: FloatArray) -> float:
        return float(values.max()) if values.size else 0.0

    return {
        "points": int(pix.shape[0]),
        "roundtrip_px_max": float(roundtrip.max()),
        "roundtrip_bearing_rad_max": float(angle_between(cam.lift(cam.project(ours)), ours).max()),
        "project_vs_opencv_px_max": float(project_err.max()),
        "lift_vs_opencv_px_max_where_opencv_converged": worst(lift_px[converged]),
        "lift_vs_opencv_rad_max_where_opencv_converged": worst(lift_ang[converged]),
        "opencv_converged_fraction": float(converged.mean()),
        "opencv_unconverged_px_max": float(cv_self_err[~converged].max())
        if (~converged).any()
        else 0.0,
        "opencv_unconverged_radius_px_range": [
            float(radius[~converged].min()),
            float(radius[~converged].max()),
        ]
        if (~converged).any()
        else [],
    }
