"""Exact views of one real photo under known pure rotations of the camera.

A central camera that only rotates sees the same rays, so a photo taken at one orientation
gives the image at any other with no depth at all: the pixel ``p`` of the rotated view sees
the ray ``R lift(p)`` of the photo's camera, which the photo shows at ``project(R lift(p))``.
Each view is resampled once from the original photo (bilinear), the first one included, so
every view has the same texture and the same interpolation; pixels whose ray the photo does
not hold (outside its valid region) are black.

This puts real texture — real corners, blur, noise, repetitive structure — in front of the
tracker, with the truth of every pixel known: a point seen at ``p`` in view ``j`` is at
``project(R_kᵀ R_j lift(p))`` in view ``k`` (``R_k`` maps view-k camera coordinates into the
photo's).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from mowerhw.camera.model import OmniRadtanCamera
from mowerhw.common.geometry import rotmat_exp

FloatArray = NDArray[np.float64]


class RotatedViews:
    """Views of ``photo`` (grey, the calibration's size) through ``camera`` rotated by ``R``."""

    def __init__(self, camera: OmniRadtanCamera, photo: NDArray[np.uint8]) -> None:
        if photo.ndim == 3:
            photo = cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY)
        if photo.shape != (camera.height, camera.width):
            raise ValueError(
                f"photo of {photo.shape[1]}x{photo.shape[0]} px for a "
                f"{camera.width}x{camera.height} calibration"
            )
        self.camera = camera
        self.photo = photo
        v, u = np.mgrid[0 : camera.height, 0 : camera.width]
        pix = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        self._valid = camera.valid(pix)
        self._rays = camera.lift(pix[self._valid])

    def view(self, r: FloatArray) -> NDArray[np.uint8]:
        """The image of the camera rotated by ``r`` (view → photo camera coordinates)."""
        cam = self.camera
        src = np.full((cam.height * cam.width, 2), -1.0, dtype=np.float32)
        pix = cam.project(self._rays @ np.asarray(r, dtype=np.float64).T)
        held = np.all(np.isfinite(pix), axis=1)
        held[held] = cam.valid(pix[held])
        idx = np.flatnonzero(self._valid)[held]
        src[idx] = pix[held]
        maps = src.reshape(cam.height, cam.width, 2)
        return cv2.remap(self.photo, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderValue=0)

    def truth(self, pixels_j: FloatArray, r_j: FloatArray, r_k: FloatArray) -> FloatArray:
        """Where points seen at ``pixels_j`` in the view rotated by ``r_j`` are in view ``r_k``."""
        rays = self.camera.lift(np.asarray(pixels_j, dtype=np.float64))
        return self.camera.project(rays @ (np.asarray(r_k).T @ np.asarray(r_j)).T)


def mower_rotations(
    n: int,
    dt: float,
    yaw_rate_dps: float,
    wobble_deg: float,
    seed: int = 0,
    axis_c: Sequence[float] = (0.0, 0.0, 1.0),
) -> list[FloatArray]:
    """Camera rotations of a turning mower on rough grass: a yaw at ``yaw_rate_dps`` about the
    camera axis ``axis_c`` (the mirror's axis is the mower's vertical) that reverses now and
    then, and a slow tilt wobble of ``wobble_deg`` about the other two axes."""
    rng = np.random.default_rng(seed)
    axis = np.asarray(axis_c, dtype=np.float64)
    axis /= np.linalg.norm(axis)
    yaw = 0.0
    direction = 1.0
    out = []
    phase = rng.uniform(0, 2 * np.pi, 2)
    for k in range(n):
        if k and rng.random() < 0.15:
            direction = -direction
        yaw += direction * np.radians(yaw_rate_dps) * dt * rng.uniform(0.5, 1.0)
        t = k * dt
        tilt = np.radians(wobble_deg) * np.array(
            [np.sin(1.3 * t + phase[0]), np.sin(0.9 * t + phase[1]), 0.0]
        )
        out.append(rotmat_exp(axis * yaw) @ rotmat_exp(tilt))
    return out
