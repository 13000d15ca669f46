"""Camera models (DESIGN.md §6), in the spirit of OpenVINS' ``CamBase``.

:class:`CameraModel` is the small interface every model implements: ``project`` camera-frame
points to pixels, ``lift`` pixels to unit bearings, and the ``valid`` pixel mask. The one model
shipped is :class:`OmniRadtanCamera`: the unified (Mei) omnidirectional model with
radial–tangential distortion, the model of the paper's Table I, of OpenCV's ``cv2.omnidir``
and of Kalibr's ``omni`` + ``radtan`` camchain files.

Both directions are vectorised over N points. ``lift`` removes the distortion with Newton's
method (converges to machine precision in a few steps over the whole valid annulus) and then
lifts onto the unit sphere with the paper's eq. (24).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class CameraCalibrationError(ValueError):
    """A camera calibration file is missing, malformed or not of a supported model."""


@dataclass(frozen=True)
class Annulus:
    """The mirror annulus: pixels with ``inner ≤ |p − centre| ≤ outer`` see the world."""

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

        Points the model cannot image get NaN pixels; pixels outside the mask are returned as
        computed (use :meth:`valid` or :meth:`visible`).
        """

    @abstractmethod
    def lift(self, pixels: ArrayLike) -> FloatArray:
        """Unit bearings ``(N, 3)`` in the camera frame of pixels ``(N, 2)``."""

    @abstractmethod
    def valid(self, pixels: ArrayLike) -> BoolArray:
        """True where a pixel lies in the image and in the mask (sees the world)."""

    def visible(self, points_c: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Pixels of ``points_c`` and whether each is imaged by a valid pixel."""
        pixels = self.project(points_c)
        ok = np.all(np.isfinite(pixels), axis=-1)
        ok[ok] = self.valid(pixels[ok])
        return pixels, ok

    def mask_image(self) -> NDArray[np.uint8]:
        """``uint8`` image (255 = valid) for feature detectors (``cv2`` ``mask=``)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        pix = np.stack([u, v], axis=-1).reshape(-1, 2).astype(np.float64)
        return (self.valid(pix).reshape(self.height, self.width) * 255).astype(np.uint8)


@dataclass(frozen=True)
class OmniRadtanCamera(CameraModel):
    """Unified omnidirectional (Mei) model with radial–tangential distortion (DESIGN.md §6).

    ``xs = X/‖X‖``, ``m = xs_xy / (xs_z + ξ)``, ``md = distort(m)``,
    ``u = fu (md_x + s md_y) + cu``, ``v = fv md_y + cv``.
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
    # A direction is imaged only if xs_z + ξ exceeds this: keeps m finite and the
    # distortion polynomial in its calibrated range.
    min_denominator: float = 0.05

    def __post_init__(self) -> None:
        for name in ("xi", "fu", "fv", "cu", "cv", "k1", "k2", "p1", "p2", "skew"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise CameraCalibrationError(f"camera {name} must be a finite number, got {value}")
        if self.fu <= 0 or self.fv <= 0:
            raise CameraCalibrationError(
                f"camera focal lengths must be positive, got fu={self.fu}, fv={self.fv}"
            )
        if not 0.0 <= self.xi <= 2.0:
            raise CameraCalibrationError(f"camera xi must be in [0, 2], got {self.xi}")
        if self.width <= 0 or self.height <= 0:
            raise CameraCalibrationError(
                f"camera resolution must be positive, got {self.width}x{self.height}"
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

    def distort(self, m: ArrayLike) -> FloatArray:
        """Radial–tangential distortion of normalised points ``m`` (N, 2)."""
        m = np.asarray(m, dtype=np.float64)
        x, y = m[..., 0], m[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([x * radial + dx, y * radial + dy], axis=-1)

    def _distort_jacobian(self, m: FloatArray) -> FloatArray:
        """∂distort/∂m, shape (N, 2, 2)."""
        x, y = m[..., 0], m[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        dradial = 2.0 * self.k1 + 4.0 * self.k2 * r2  # ∂radial/∂(x or y) = dradial · (x or y)
        j = np.empty((*m.shape[:-1], 2, 2))
        j[..., 0, 0] = radial + dradial * x * x + 2 * self.p1 * y + 6 * self.p2 * x
        j[..., 0, 1] = dradial * x * y + 2 * self.p1 * x + 2 * self.p2 * y
        j[..., 1, 0] = dradial * x * y + 2 * self.p1 * x + 2 * self.p2 * y
        j[..., 1, 1] = radial + dradial * y * y + 6 * self.p1 * y + 2 * self.p2 * x
        return j

    def undistort(self, md: ArrayLike, iterations: int = 12) -> FloatArray:
        """Invert :meth:`distort` by Newton's method (vectorised; quadratic convergence)."""
        md = np.asarray(md, dtype=np.float64)
        r2 = np.sum(md * md, axis=-1, keepdims=True)
        m = md / (1.0 + self.k1 * r2 + self.k2 * r2 * r2)  # one radial step: Newton's start
        for _ in range(iterations):
            residual = self.distort(m) - md
            if not np.any(np.abs(residual) > 1e-14):  # ≈ 5e-12 px
                break
            j = self._distort_jacobian(m)
            det = j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]
            # Newton step J⁻¹ r with the explicit 2×2 inverse (J is near identity here).
            step_x = (j[..., 1, 1] * residual[..., 0] - j[..., 0, 1] * residual[..., 1]) / det
            step_y = (j[..., 0, 0] * residual[..., 1] - j[..., 1, 0] * residual[..., 0]) / det
            m = m - np.stack([step_x, step_y], axis=-1)
        return m

    def normalized_to_pixels(self, md: FloatArray) -> FloatArray:
        u = self.fu * (md[..., 0] + self.skew * md[..., 1]) + self.cu
        v = self.fv * md[..., 1] + self.cv
        return np.stack([u, v], axis=-1)

    def pixels_to_normalized(self, pixels: FloatArray) -> FloatArray:
        my = (pixels[..., 1] - self.cv) / self.fv
        mx = (pixels[..., 0] - self.cu) / self.fu - self.skew * my
        return np.stack([mx, my], axis=-1)

    def sphere_to_normalized(self, xs: FloatArray) -> FloatArray:
        """``m = xs_xy / (xs_z + ξ)`` for unit vectors; NaN where not imaged."""
        den = xs[..., 2] + self.xi
        den = np.where(den > self.min_denominator, den, np.nan)
        return xs[..., :2] / den[..., None]

    def normalized_to_sphere(self, p: FloatArray) -> FloatArray:
        """Paper eq. (24): lift undistorted normalised points onto the unit sphere."""
        rho2 = p[..., 0] ** 2 + p[..., 1] ** 2
        f = (self.xi + np.sqrt(1.0 + (1.0 - self.xi**2) * rho2)) / (rho2 + 1.0)
        return np.stack([f * p[..., 0], f * p[..., 1], f - self.xi], axis=-1)

    # -- CameraModel interface ---------------------------------------------------------------

    def project(self, points_c: ArrayLike) -> FloatArray:
        pts = np.asarray(points_c, dtype=np.float64)
        norm = np.linalg.norm(pts, axis=-1, keepdims=True)
        xs = pts / np.where(norm > 0, norm, np.nan)
        return self.normalized_to_pixels(self.distort(self.sphere_to_normalized(xs)))

    def lift(self, pixels: ArrayLike) -> FloatArray:
        pix = np.asarray(pixels, dtype=np.float64)
        return self.normalized_to_sphere(self.undistort(self.pixels_to_normalized(pix)))

    def valid(self, pixels: ArrayLike) -> BoolArray:
        pix = np.asarray(pixels, dtype=np.float64)
        ok = (
            (pix[..., 0] >= 0)
            & (pix[..., 0] <= self.width - 1)
            & (pix[..., 1] >= 0)
            & (pix[..., 1] <= self.height - 1)
        )
        if self.mask is not None:
            ok &= self.mask.contains(pix)
        return ok

    def polar_angle_of_radius(self, radius_px: float) -> float:
        """Angle (rad) from the camera z axis imaged at ``radius_px`` from the principal point
        along +u (used to report the field of view an annulus gives)."""
        bearing = self.lift(np.array([[self.cu + radius_px, self.cv]]))[0]
        return float(np.arccos(np.clip(bearing[2], -1.0, 1.0)))

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

    def with_mask(self, mask: Annulus | None) -> OmniRadtanCamera:
        return replace(self, mask=mask)

    # -- Kalibr camchain ---------------------------------------------------------------------

    def to_kalibr(self) -> dict[str, Any]:
        """This calibration as a Kalibr camchain camera entry (plus our ``mask`` extension)."""
        entry: dict[str, Any] = {
            "camera_model": "omni",
            "intrinsics": [self.xi, self.fu, self.fv, self.cu, self.cv],
            "distortion_model": "radtan",
            "distortion_coeffs": [self.k1, self.k2, self.p1, self.p2],
            "resolution": [self.width, self.height],
        }
        if self.T_cam_imu is not None:
            entry["T_cam_imu"] = np.asarray(self.T_cam_imu).tolist()
        if self.mask is not None:
            entry["mask"] = {
                "center": list(self.mask.center_px),
                "inner_radius": self.mask.inner_radius_px,
                "outer_radius": self.mask.outer_radius_px,
            }
        return entry

    @classmethod
    def from_kalibr(cls, entry: dict[str, Any], where: str = "cam0") -> OmniRadtanCamera:
        """Build from one camchain camera entry; errors name the key and what is allowed."""
        if not isinstance(entry, dict):
            raise CameraCalibrationError(f"{where}: expected a mapping, got {type(entry).__name__}")
        model = entry.get("camera_model")
        if model != "omni":
            raise CameraCalibrationError(
                f"{where}.camera_model: {model!r} is not supported; allowed: 'omni'"
            )
        dmodel = entry.get("distortion_model")
        if dmodel != "radtan":
            raise CameraCalibrationError(
                f"{where}.distortion_model: {dmodel!r} is not supported; allowed: 'radtan'"
            )
        intr = _numbers(entry, "intrinsics", 5, where, "[xi, fu, fv, pu, pv]")
        dist = _numbers(entry, "distortion_coeffs", 4, where, "[k1, k2, r1, r2]")
        res = _numbers(entry, "resolution", 2, where, "[width, height]")
        if any(r != int(r) or r <= 0 for r in res):
            raise CameraCalibrationError(
                f"{where}.resolution: {res} must be two positive whole numbers [width, height]"
            )
        xi, fu, fv, cu, cv = intr
        t_cam_imu = None
        if "T_cam_imu" in entry:
            t_cam_imu = np.asarray(entry["T_cam_imu"], dtype=np.float64)
            if t_cam_imu.shape != (4, 4) or not np.all(np.isfinite(t_cam_imu)):
                raise CameraCalibrationError(f"{where}.T_cam_imu: must be a finite 4x4 matrix")
            rot = t_cam_imu[:3, :3]
            if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
                raise CameraCalibrationError(
                    f"{where}.T_cam_imu: its upper-left 3x3 block is not a rotation matrix"
                )
        mask = None
        if "mask" in entry:
            mask = _annulus(entry["mask"], (cu, cv), f"{where}.mask")
        return cls(
            xi=xi,
            fu=fu,
            fv=fv,
            cu=cu,
            cv=cv,
            k1=dist[0],
            k2=dist[1],
            p1=dist[2],
            p2=dist[3],
            width=int(res[0]),
            height=int(res[1]),
            mask=mask,
            T_cam_imu=t_cam_imu,
        )


def _numbers(entry: dict[str, Any], key: str, n: int, where: str, shape: str) -> list[float]:
    value = entry.get(key)
    if not isinstance(value, list | tuple) or len(value) != n:
        raise CameraCalibrationError(f"{where}.{key}: {value!r} must be a list of {n}: {shape}")
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise CameraCalibrationError(
            f"{where}.{key}: {value!r} must hold {n} numbers: {shape}"
        ) from None
    if not all(math.isfinite(v) for v in out):
        raise CameraCalibrationError(f"{where}.{key}: {value!r} must hold finite numbers")
    return out


def _annulus(raw: Any, default_center: tuple[float, float], where: str) -> Annulus:
    if not isinstance(raw, dict):
        raise CameraCalibrationError(f"{where}: expected a mapping with inner_radius, outer_radius")
    try:
        center = tuple(float(c) for c in raw.get("center", default_center))
        inner = float(raw.get("inner_radius", 0.0))
        outer = float(raw["outer_radius"])
    except KeyError:
        raise CameraCalibrationError(f"{where}.outer_radius: missing (pixels)") from None
    except (TypeError, ValueError):
        raise CameraCalibrationError(f"{where}: center/radii must be numbers (pixels)") from None
    if len(center) != 2 or not (0.0 <= inner < outer):
        raise CameraCalibrationError(
            f"{where}: need 0 <= inner_radius < outer_radius and a 2-element center, "
            f"got inner={inner}, outer={outer}, center={center}"
        )
    return Annulus((center[0], center[1]), inner, outer)


def load_camchain(path: str | Path, camera: str = "cam0") -> OmniRadtanCamera:
    """Load one camera of a Kalibr camchain YAML file."""
    path = Path(path)
    try:
        with path.open("r", encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except FileNotFoundError:
        raise CameraCalibrationError(f"camera calibration {path}: file not found") from None
    except yaml.YAMLError as exc:
        raise CameraCalibrationError(f"camera calibration {path}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or camera not in doc:
        found = ", ".join(doc) if isinstance(doc, dict) else "nothing"
        raise CameraCalibrationError(
            f"camera calibration {path}: no '{camera}' entry (found: {found})"
        )
    try:
        return OmniRadtanCamera.from_kalibr(doc[camera], where=camera)
    except CameraCalibrationError as exc:
        raise CameraCalibrationError(f"camera calibration {path}: {exc}") from None


def save_camchain(cam: OmniRadtanCamera, path: str | Path, camera: str = "cam0") -> None:
    """Write a camchain YAML file with this camera as ``camera``."""
    Path(path).write_text(yaml.safe_dump({camera: cam.to_kalibr()}, sort_keys=False))


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
