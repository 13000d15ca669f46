"""Camera models (docs/design.md §6), in the spirit of OpenVINS' ``CamBase``.

:class:`CameraModel` is the small interface every model implements: ``project`` camera-frame
points to pixels, ``lift`` pixels to unit bearings, and the ``valid`` pixel mask. The one model
shipped is :class:`OmniRadtanCamera`: the unified (Mei) omnidirectional model with
radial–tangential distortion and skew, the model of the paper's Table I, of OpenCV's
``cv2.omnidir`` and of Kalibr's ``omni`` + ``radtan`` camchain files.

Its domain, for any ξ ≥ 0 (mirrors have ξ ≲ 1; fisheye lenses fitted with this model often
1 < ξ < 3):

* a direction at angle θ from the axis is imaged only while ``cos θ + ξ`` is clearly positive
  (``m`` finite) and, for ξ > 1, before the fold at ``cos θ = −1/ξ``, where ``ρ(θ)`` turns back
  and two directions would share a pixel;
* the distortion is used only where it is one-to-one (``det ∂distort/∂m > 0``);
* a pixel is ``valid`` where it lies in the image and the mask (mirror annulus or image
  circle), its undistortion converges, and its bearing lies in that domain — so ``lift`` of a
  valid pixel is always finite and ``project`` maps it back.

Both directions are vectorised over N points. ``lift`` removes the distortion with Newton's
method (converges to machine precision in a few steps) and lifts onto the unit sphere with the
paper's eq. (24).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: the largest ξ accepted (a calibration beyond it is certainly wrong)
XI_MAX = 10.0


class CameraCalibrationError(ValueError):
    """A camera calibration file is missing, malformed or not of a supported model."""


@dataclass(frozen=True)
class Annulus:
    """The usable image region: pixels with ``inner ≤ |p − centre| ≤ outer`` see the world
    (a mirror's annulus; a fisheye's image circle has ``inner = 0``)."""

    center_px: tuple[float, float]
    inner_radius_px: float
    outer_radius_px: float

    def contains(self, pixels: FloatArray) -> BoolArray:
        d = pixels - np.asarray(self.center_px)
        r2 = np.einsum("...i,...i->...", d, d)
        return (r2 >= self.inner_radius_px**2) & (r2 <= self.outer_radius_px**2)


class CameraModel(ABC):
    """Interface of a camera model: camera frame ``c`` ↔ pixels ``(u, v)``."""

    width: int
    height: int

    @abstractmethod
    def project(self, points_c: ArrayLike) -> FloatArray:
        """Pixels ``(N, 2)`` of camera-frame points or directions ``(N, 3)``.

        Directions the model cannot image get NaN pixels; pixels outside the image or the mask
        are returned as computed (use :meth:`valid` or :meth:`visible`).
        """

    @abstractmethod
    def lift(self, pixels: ArrayLike) -> FloatArray:
        """Unit bearings ``(N, 3)`` in the camera frame of pixels ``(N, 2)``; NaN where the
        model has no bearing."""

    @abstractmethod
    def valid(self, pixels: ArrayLike) -> BoolArray:
        """True where a pixel lies in the image and the mask, and has a bearing."""

    def visible(self, points_c: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Pixels of ``points_c`` and whether each is imaged by a valid pixel."""
        pixels = self.project(points_c)
        ok = np.all(np.isfinite(pixels), axis=-1)
        ok[ok] = self.valid(pixels[ok])
        return pixels, ok

    def mask_image(self) -> NDArray[np.uint8]:
        """``uint8`` image (255 = valid pixel centre) for feature detectors (``cv2`` ``mask=``);
        computed a band of rows at a time (a whole-image lift would need ~200 MB at once)."""
        out = np.zeros((self.height, self.width), np.uint8)
        u = np.arange(self.width, dtype=np.float64)
        rows = 64
        for v0 in range(0, self.height, rows):
            v = np.arange(v0, min(v0 + rows, self.height), dtype=np.float64)
            pix = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
            out[v0 : v0 + v.size] = self.valid(pix).reshape(v.size, self.width) * 255
        return out


@dataclass(frozen=True)
class OmniRadtanCamera(CameraModel):
    """Unified omnidirectional (Mei) model with radial–tangential distortion (docs/design.md §6).

    ``xs = X/‖X‖``, ``m = xs_xy / (xs_z + ξ)``, ``md = distort(m)``,
    ``u = fu (md_x + s md_y) + cu``, ``v = fv md_y + cv`` (``s`` = ``skew``, dimensionless:
    OpenCV's ``K[0, 1]`` is ``s · fu``).
    """

    xi: float
    fu: float
    fv: float
    cu: float
    cv: float
    k1: float
    k2: float
    p1: float
    p2: float
    width: int
    height: int
    skew: float = 0.0
    mask: Annulus | None = None
    T_cam_imu: FloatArray | None = field(default=None, compare=False)
    timeshift_cam_imu: float = 0.0  # Kalibr: t_imu = t_cam + timeshift (s)
    # A direction is imaged only if xs_z + ξ exceeds this: keeps m finite and the
    # distortion polynomial in its calibrated range.
    min_denominator: float = 0.05
    # ... and, for ξ > 1, only if 1 + ξ xs_z exceeds this: short of the fold, where the
    # model's angle per pixel grows without bound.
    min_fold_margin: float = 0.02

    def __post_init__(self) -> None:
        for name in ("xi", "fu", "fv", "cu", "cv", "k1", "k2", "p1", "p2", "skew"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise CameraCalibrationError(f"camera {name} must be a finite number, got {value}")
        if self.fu <= 0 or self.fv <= 0:
            raise CameraCalibrationError(
                f"camera focal lengths must be positive, got fu={self.fu}, fv={self.fv}"
            )
        if not 0.0 <= self.xi <= XI_MAX:
            raise CameraCalibrationError(f"camera xi must be in [0, {XI_MAX:g}], got {self.xi}")
        if self.width <= 0 or self.height <= 0:
            raise CameraCalibrationError(
                f"camera resolution must be positive, got {self.width}x{self.height}"
            )
        if not math.isfinite(self.timeshift_cam_imu) or abs(self.timeshift_cam_imu) > 1.0:
            raise CameraCalibrationError(
                f"camera timeshift_cam_imu must be a finite time under 1 s, "
                f"got {self.timeshift_cam_imu}"
            )

    # -- the model, in its steps -------------------------------------------------------------

    @property
    def K(self) -> FloatArray:
        """3×3 projection matrix (OpenCV layout)."""
        return np.array([[self.fu, self.skew * self.fu, self.cu], [0, self.fv, self.cv], [0, 0, 1]])

    @property
    def D(self) -> FloatArray:
        """Distortion ``(k1, k2, p1, p2)`` (OpenCV and Kalibr order)."""
        return np.array([self.k1, self.k2, self.p1, self.p2])

    @property
    def fold_angle(self) -> float:
        """Angle (rad) from the axis beyond which no direction is imaged (the fold for ξ > 1,
        where ``xs_z + ξ`` reaches ``min_denominator`` otherwise)."""
        cos_limit = max(
            self.min_denominator - self.xi,
            (self.min_fold_margin - 1.0) / self.xi if self.xi > 1.0 else -1.0,
        )
        return float(math.acos(max(-1.0, min(1.0, cos_limit))))

    def distort(self, m: ArrayLike) -> FloatArray:
        """Radial–tangential distortion of normalised points ``m`` (N, 2)."""
        m = np.asarray(m, dtype=np.float64)
        x, y = m[..., 0], m[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([x * radial + dx, y * radial + dy], axis=-1)

    def _distort_jacobian(self, m: FloatArray) -> tuple[FloatArray, ...]:
        """∂distort/∂m as its four entries (j00, j01, j10, j11), each shaped like ``m[..., 0]``."""
        x, y = m[..., 0], m[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        dradial = 2.0 * self.k1 + 4.0 * self.k2 * r2  # ∂radial/∂(x or y) = dradial · (x or y)
        off = dradial * x * y + 2 * self.p1 * x + 2 * self.p2 * y
        j00 = radial + dradial * x * x + 2 * self.p1 * y + 6 * self.p2 * x
        j11 = radial + dradial * y * y + 6 * self.p1 * y + 2 * self.p2 * x
        return j00, off, off, j11

    def one_to_one(self, m: FloatArray) -> BoolArray:
        """Where the distortion is locally one-to-one and orientation-preserving."""
        j00, j01, j10, j11 = self._distort_jacobian(m)
        return (j00 * j11 - j01 * j10) > 0.0

    def undistort(self, md: ArrayLike, iterations: int = 12) -> FloatArray:
        """Invert :meth:`distort` by Newton's method (vectorised; quadratic convergence).
        NaN where it does not converge, or converges onto the distortion's folded branch."""
        md = np.asarray(md, dtype=np.float64)
        x, y = self._undistort_xy(md[..., 0], md[..., 1], iterations)
        return np.stack([x, y], axis=-1)

    def _undistort_xy(
        self, xd: FloatArray, yd: FloatArray, iterations: int = 12
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`undistort` on coordinate arrays (fewer temporaries: this is ``lift``'s
        inner loop, and a frame's few hundred features make it overhead-bound)."""
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        r2 = xd * xd + yd * yd
        scale = 1.0 / (1.0 + k1 * r2 + k2 * r2 * r2)  # one radial step: Newton's start
        x, y = xd * scale, yd * scale
        tol = 1e-14  # ≈ 5e-12 px
        for _ in range(iterations + 1):
            xx, yy, xy = x * x, y * y, x * y
            r2 = xx + yy
            radial = 1.0 + r2 * (k1 + k2 * r2)
            ex = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) - xd
            ey = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy - yd
            if not (np.abs(ex).max(initial=0.0) > tol or np.abs(ey).max(initial=0.0) > tol):
                break
            dradial = 2.0 * k1 + 4.0 * k2 * r2
            off = dradial * xy + 2.0 * (p1 * x + p2 * y)
            j00 = radial + dradial * xx + 2.0 * p1 * y + 6.0 * p2 * x
            j11 = radial + dradial * yy + 6.0 * p1 * y + 2.0 * p2 * x
            inv_det = 1.0 / (j00 * j11 - off * off)
            # Newton step J⁻¹ e with the explicit 2×2 inverse (J is symmetric here)
            x = x - (j11 * ex - off * ey) * inv_det
            y = y - (j00 * ey - off * ex) * inv_det
        # converged (the loop's last residual), on the unfolded branch (det J > 0)
        bound = 1e-9 * np.maximum(1.0, np.maximum(np.abs(xd), np.abs(yd)))
        dradial = 2.0 * k1 + 4.0 * k2 * r2
        j00 = radial + dradial * xx + 2.0 * p1 * y + 6.0 * p2 * x
        j11 = radial + dradial * yy + 6.0 * p1 * y + 2.0 * p2 * x
        off = dradial * xy + 2.0 * (p1 * x + p2 * y)
        ok = (np.abs(ex) <= bound) & (np.abs(ey) <= bound) & (j00 * j11 - off * off > 0.0)
        return np.where(ok, x, np.nan), np.where(ok, y, np.nan)

    def normalized_to_pixels(self, md: FloatArray) -> FloatArray:
        u = self.fu * (md[..., 0] + self.skew * md[..., 1]) + self.cu
        v = self.fv * md[..., 1] + self.cv
        return np.stack([u, v], axis=-1)

    def pixels_to_normalized(self, pixels: FloatArray) -> FloatArray:
        my = (pixels[..., 1] - self.cv) / self.fv
        mx = (pixels[..., 0] - self.cu) / self.fu - self.skew * my
        return np.stack([mx, my], axis=-1)

    def imaged(self, xs: FloatArray) -> BoolArray:
        """Which unit directions lie in the model's domain (see the module doc)."""
        z = xs[..., 2]
        ok = z + self.xi > self.min_denominator
        if self.xi > 1.0:
            ok &= 1.0 + self.xi * z > self.min_fold_margin
        return ok

    def sphere_to_normalized(self, xs: FloatArray) -> FloatArray:
        """``m = xs_xy / (xs_z + ξ)`` for unit vectors; NaN where not imaged."""
        den = np.where(self.imaged(xs), xs[..., 2] + self.xi, np.nan)
        return xs[..., :2] / den[..., None]

    def normalized_to_sphere(self, p: FloatArray) -> FloatArray:
        """Paper eq. (24): lift undistorted normalised points onto the unit sphere; NaN past
        the fold (``1 + (1 − ξ²) ρ² < 0`` for ξ > 1)."""
        rho2 = p[..., 0] ** 2 + p[..., 1] ** 2
        disc = 1.0 + (1.0 - self.xi**2) * rho2
        f = (self.xi + np.sqrt(np.where(disc >= 0.0, disc, np.nan))) / (rho2 + 1.0)
        return np.stack([f * p[..., 0], f * p[..., 1], f - self.xi], axis=-1)

    # -- CameraModel interface ---------------------------------------------------------------

    def project(self, points_c: ArrayLike) -> FloatArray:
        pts = np.asarray(points_c, dtype=np.float64)
        px, py, pz = pts[..., 0], pts[..., 1], pts[..., 2]
        norm = np.sqrt(px * px + py * py + pz * pz)
        z = pz / norm  # NaN for a zero vector
        xi = self.xi
        ok = z + xi > self.min_denominator
        if xi > 1.0:
            ok &= 1.0 + xi * z > self.min_fold_margin
        inv = np.where(ok, 1.0 / (norm * (z + xi)), np.nan)
        x, y = px * inv, py * inv
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        xx, yy, xy = x * x, y * y, x * y
        r2 = xx + yy
        radial = 1.0 + r2 * (k1 + k2 * r2)
        xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
        yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
        # only where the distortion is one-to-one (det ∂distort/∂m > 0)
        dradial = 2.0 * k1 + 4.0 * k2 * r2
        off = dradial * xy + 2.0 * (p1 * x + p2 * y)
        j00 = radial + dradial * xx + 2.0 * p1 * y + 6.0 * p2 * x
        j11 = radial + dradial * yy + 6.0 * p1 * y + 2.0 * p2 * x
        keep = j00 * j11 - off * off > 0.0
        u = np.where(keep, self.fu * (xd + self.skew * yd) + self.cu, np.nan)
        v = np.where(keep, self.fv * yd + self.cv, np.nan)
        return np.stack([u, v], axis=-1)

    def lift(self, pixels: ArrayLike) -> FloatArray:
        pix = np.asarray(pixels, dtype=np.float64)
        yd = (pix[..., 1] - self.cv) * (1.0 / self.fv)
        xd = (pix[..., 0] - self.cu) * (1.0 / self.fu) - self.skew * yd
        x, y = self._undistort_xy(xd, yd)
        # paper eq. (24), NaN past the fold (1 + (1 − ξ²) ρ² < 0 for ξ > 1)
        rho2 = x * x + y * y
        xi = self.xi
        disc = 1.0 + (1.0 - xi * xi) * rho2
        f = (xi + np.sqrt(np.where(disc >= 0.0, disc, np.nan))) / (rho2 + 1.0)
        z = f - xi
        ok = z + xi > self.min_denominator
        if xi > 1.0:
            ok &= 1.0 + xi * z > self.min_fold_margin
        f = np.where(ok, f, np.nan)
        return np.stack([f * x, f * y, np.where(ok, z, np.nan)], axis=-1)

    def in_image(self, pixels: FloatArray) -> BoolArray:
        """Inside the image and the mask (no model check)."""
        ok = (
            (pixels[..., 0] >= 0)
            & (pixels[..., 0] <= self.width - 1)
            & (pixels[..., 1] >= 0)
            & (pixels[..., 1] <= self.height - 1)
        )
        if self.mask is not None:
            ok &= self.mask.contains(pixels)
        return ok

    def valid(self, pixels: ArrayLike) -> BoolArray:
        pix = np.asarray(pixels, dtype=np.float64)
        ok = self.in_image(pix)
        if np.any(ok):
            ok[ok] = np.all(np.isfinite(self.lift(pix[ok])), axis=-1)
        return ok

    @cached_property
    def _mask_image(self) -> NDArray[np.uint8]:
        return super().mask_image()

    def mask_image(self) -> NDArray[np.uint8]:
        """As :meth:`CameraModel.mask_image`, computed once per camera (a full-image lift)."""
        return self._mask_image.copy()

    def bearing_sigma(self, pixels: ArrayLike, sigma_px: float) -> FloatArray:
        """Angular standard deviation (rad) of the bearing of each pixel under isotropic pixel
        noise ``sigma_px``: ``sigma_px`` × the local angle per pixel (numerical, per point)."""
        pix = np.asarray(pixels, dtype=np.float64)
        h = 0.5
        b0 = self.lift(pix)
        du = self.lift(pix + [h, 0.0])
        dv = self.lift(pix + [0.0, h])
        ang_u = np.arccos(np.clip(np.einsum("...i,...i->...", b0, du), -1, 1)) / h
        ang_v = np.arccos(np.clip(np.einsum("...i,...i->...", b0, dv), -1, 1)) / h
        return sigma_px * np.sqrt(0.5 * (ang_u**2 + ang_v**2))

    def intrinsics(self) -> dict[str, object]:
        """The calibration's numbers, for reports (skew also in pixels, as OpenCV's K[0,1])."""
        return {
            "model": "omni (Mei) + radtan",
            "resolution": [self.width, self.height],
            "xi": self.xi,
            "fu": self.fu,
            "fv": self.fv,
            "cu": self.cu,
            "cv": self.cv,
            "skew": self.skew,
            "skew_px": self.skew * self.fu,
            "distortion": [self.k1, self.k2, self.p1, self.p2],
            "timeshift_cam_imu_s": self.timeshift_cam_imu,
        }

    def with_mask(self, mask: Annulus | None) -> OmniRadtanCamera:
        return replace(self, mask=mask)

    # -- Kalibr camchain (mowerhw.camera.kalibr) ------------------------------------------

    def to_kalibr(self) -> dict:
        from mowerhw.camera.kalibr import camera_to_entry

        return camera_to_entry(self)

    @classmethod
    def from_kalibr(cls, entry: dict, where: str = "cam0") -> OmniRadtanCamera:
        from mowerhw.camera.kalibr import camera_from_entry

        return camera_from_entry(entry, where)


def paper_table1_camera(mask: Annulus | None = None) -> OmniRadtanCamera:
    """The paper's Table I calibration (1540×1540), as a built-in for tests and simulation."""
    return OmniRadtanCamera(
        xi=0.92036,
        fu=476.60667,
        fv=476.74991,
        cu=775.11715,
        cv=778.91684,
        k1=-0.17357,
        k2=0.02025,
        p1=-0.00209,
        p2=0.00091,
        width=1540,
        height=1540,
        mask=mask if mask is not None else Annulus((775.11715, 778.91684), 180.0, 760.0),
    )
