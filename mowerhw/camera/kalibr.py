"""Kalibr camchain files (``omni`` + ``radtan``), read and written (docs/design.md §6).

A camchain holds one entry per camera (``cam0``, ``cam1``, …). Per entry mowerhw reads
``camera_model``, ``intrinsics`` ``[ξ, fu, fv, cu, cv]``, ``distortion_model``,
``distortion_coeffs`` ``[k1, k2, p1, p2]``, ``resolution``, ``T_cam_imu`` (the IMU-to-camera
transform: ``p_cam = T_cam_imu p_imu``) and ``timeshift_cam_imu`` (``t_imu = t_cam + shift``),
and two extensions Kalibr ignores: ``skew`` (dimensionless, ``u = fu (x + skew y) + cu``;
written only when it moves a pixel by more than :data:`SKEW_NEGLIGIBLE_PX`) and ``mask`` (the
usable image region: ``center``, ``inner_radius``, ``outer_radius`` in pixels). What else
Kalibr writes (``cam_overlaps``, ``T_cn_cnm1``, ``rostopic``) is accepted and checked for
shape where it has one, not used.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mowerhw.camera.model import Annulus, CameraCalibrationError, OmniRadtanCamera
from mowerhw.common.fileio import write_atomic
from mowerhw.common.yamlfile import load_yaml

#: skew whose largest effect over the image is below this is not written (px)
SKEW_NEGLIGIBLE_PX = 0.01


def camera_to_entry(cam: OmniRadtanCamera) -> dict[str, Any]:
    """A camchain camera entry (plus our ``skew`` and ``mask`` extensions)."""
    entry: dict[str, Any] = {
        "camera_model": "omni",
        "intrinsics": [float(cam.xi), float(cam.fu), float(cam.fv), float(cam.cu), float(cam.cv)],
        "distortion_model": "radtan",
        "distortion_coeffs": [float(cam.k1), float(cam.k2), float(cam.p1), float(cam.p2)],
        "resolution": [int(cam.width), int(cam.height)],
    }
    if abs(cam.skew) * cam.fu * (cam.height / 2.0) / cam.fv > SKEW_NEGLIGIBLE_PX:
        entry["skew"] = float(cam.skew)
    if cam.T_cam_imu is not None:
        entry["T_cam_imu"] = np.asarray(cam.T_cam_imu, dtype=float).tolist()
    if cam.timeshift_cam_imu:
        entry["timeshift_cam_imu"] = float(cam.timeshift_cam_imu)
    if cam.mask is not None:
        entry["mask"] = {
            "center": [float(c) for c in cam.mask.center_px],
            "inner_radius": float(cam.mask.inner_radius_px),
            "outer_radius": float(cam.mask.outer_radius_px),
        }
    return entry


def camera_from_entry(entry: Any, where: str = "cam0") -> OmniRadtanCamera:
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
    skew = _scalar(entry, "skew", 0.0, where, "a number (dimensionless: OpenCV K[0,1] / fu)")
    shift = _scalar(entry, "timeshift_cam_imu", 0.0, where, "seconds (t_imu = t_cam + shift)")
    t_cam_imu = _transform(entry, "T_cam_imu", where) if "T_cam_imu" in entry else None
    if "T_cn_cnm1" in entry:
        _transform(entry, "T_cn_cnm1", where)
    overlaps = entry.get("cam_overlaps", [])
    if not isinstance(overlaps, list) or not all(isinstance(o, int) for o in overlaps):
        raise CameraCalibrationError(f"{where}.cam_overlaps: {overlaps!r} must be camera indices")
    mask = _annulus(entry["mask"], (cu, cv), f"{where}.mask") if "mask" in entry else None
    try:
        return OmniRadtanCamera(
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
            skew=skew,
            mask=mask,
            T_cam_imu=t_cam_imu,
            timeshift_cam_imu=shift,
        )
    except CameraCalibrationError as exc:
        raise CameraCalibrationError(f"{where}: {exc}") from None


def _scalar(entry: dict[str, Any], key: str, default: float, where: str, what: str) -> float:
    value = entry.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CameraCalibrationError(f"{where}.{key}: {value!r} must be {what}")
    return float(value)


def _transform(entry: dict[str, Any], key: str, where: str) -> np.ndarray:
    try:
        t = np.asarray(entry[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraCalibrationError(f"{where}.{key}: must be a 4x4 matrix of numbers") from None
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise CameraCalibrationError(f"{where}.{key}: must be a finite 4x4 matrix")
    rot = t[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise CameraCalibrationError(f"{where}.{key}: its upper-left 3x3 block is not a rotation")
    return t


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
    if len(center) != 2 or not all(math.isfinite(v) for v in (*center, inner, outer)):
        raise CameraCalibrationError(f"{where}: center must be 2 finite numbers, radii finite")
    if not 0.0 <= inner < outer:
        raise CameraCalibrationError(
            f"{where}: need 0 <= inner_radius < outer_radius, got inner={inner}, outer={outer}"
        )
    return Annulus((center[0], center[1]), inner, outer)


def read_camchain(path: str | Path) -> dict[str, Any]:
    """The camchain document (a mapping of camera names to entries)."""
    path = Path(path)
    try:
        with path.open("r", encoding="utf-8") as fh:
            doc = load_yaml(fh.read())  # no key twice, no aliases (docs/design.md §8)
    except FileNotFoundError:
        raise CameraCalibrationError(f"camera calibration {path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CameraCalibrationError(f"camera calibration {path}: cannot read it ({exc})") from None
    except yaml.YAMLError as exc:
        raise CameraCalibrationError(f"camera calibration {path}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or not doc:
        raise CameraCalibrationError(
            f"camera calibration {path}: expected camera entries (cam0: …), found nothing"
        )
    return doc


def camera_names(path: str | Path) -> list[str]:
    return [str(k) for k in read_camchain(path)]


def load_camchain(path: str | Path, camera: str = "cam0") -> OmniRadtanCamera:
    """Load one camera of a Kalibr camchain YAML file."""
    doc = read_camchain(path)
    if camera not in doc:
        raise CameraCalibrationError(
            f"camera calibration {path}: no '{camera}' entry "
            f"(found: {', '.join(str(k) for k in doc)}; choose with camera.camchain_key)"
        )
    try:
        return camera_from_entry(doc[camera], where=camera)
    except CameraCalibrationError as exc:
        raise CameraCalibrationError(f"camera calibration {path}: {exc}") from None


def save_camchain(
    cam: OmniRadtanCamera | dict[str, OmniRadtanCamera],
    path: str | Path,
    camera: str = "cam0",
    comment: str = "",
) -> None:
    """Write a camchain YAML file (atomically) with ``cam`` as ``camera``, or several."""
    cams = cam if isinstance(cam, dict) else {camera: cam}
    text = yaml.safe_dump({k: camera_to_entry(c) for k, c in cams.items()}, sort_keys=False)
    if comment:
        text = "".join(f"# {line}\n" for line in comment.splitlines()) + text
    write_atomic(Path(path), text.encode())
