#!/usr/bin/env python3
"""Check: the camera model on real third-party calibrations and photos.

* ``kalibr-t265-camchain``: a real Kalibr camchain of an Intel RealSense T265 (two fisheye
  cameras fitted with the Mei model, ξ ≈ 2.0 and 2.07, ``T_cam_imu``, time shifts) and the
  factory Kannala–Brandt (KB4) intrinsics of the same unit. Each camera is loaded; rays from
  0 to 55° off the axis, all around, are projected with the Mei model (ours) and with the
  factory model (``cv2.fisheye.projectPoints``): two calibrations of one lens, made by two
  parties with two models, should agree to a few pixels.
* ``omni-mirror-checkerboard``: ``mowerhw camera calibrate`` on the 18 real mirror photos
  (9x6 inner corners); its report and the written camchain's agreement with ``cv2.omnidir``.

Prints one JSON object per check. Run: ``.venv/bin/python tools/check_real_cameras.py``.
"""

from __future__ import annotations

import json
import re
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from mowerhw.camera import load_camchain, save_camchain
from mowerhw.camera.check import check_against_opencv, field_of_view

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
T265 = DATA / "kalibr-t265-camchain"
MIRROR = DATA / "omni-mirror-checkerboard"


def factory_kb4(camera_index: int) -> tuple[np.ndarray, np.ndarray]:
    """K and D of the factory KB4 model of T265 fisheye ``camera_index`` (1 or 2)."""
    text = (T265 / "factory_kannala_brandt_intrinsics.txt").read_text()
    block = text.split(f"Fisheye {camera_index} ")[1]
    num = r"(-?[0-9.eE+-]+)"
    fx, fy, ppx, ppy = (
        float(re.search(rf"{key} {num}", block).group(1)) for key in ("Fx", "Fy", "PPX", "PPY")
    )
    coeffs = [float(v) for v in re.search(r"KB4 coeffs: ([^F]+)", block).group(1).split()[:4]]
    return np.array([[fx, 0.0, ppx], [0.0, fy, ppy], [0.0, 0.0, 1.0]]), np.array(coeffs)


def mei_vs_factory(max_deg: float = 55.0, step_deg: float = 5.0) -> list[dict[str, object]]:
    """Per T265 camera: the largest pixel difference between the two models, by angle."""
    path = T265 / "imu_cameras_calibration-camchain-imucam.yaml"
    out = []
    for index, name in ((1, "cam0"), (2, "cam1")):
        cam = load_camchain(path, name)
        k, d = factory_kb4(index)
        by_angle = {}
        for deg in np.arange(0.0, max_deg + 1e-9, step_deg):
            az = np.radians(np.arange(0.0, 360.0, 2.0))
            th = np.radians(deg)
            rays = np.stack(
                [np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), np.full_like(az, np.cos(th))], 1
            )
            ours = cam.project(rays)
            kb, _ = cv2.fisheye.projectPoints(
                rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k, d
            )
            diff = np.linalg.norm(ours - kb.reshape(-1, 2), axis=1)
            by_angle[f"{deg:.0f}"] = round(float(diff.max()), 2)
        fov = field_of_view(cam)
        out.append(
            {
                "camera": name,
                "xi": cam.xi,
                "loads": True,
                "polar_deg_range": [
                    round(fov["polar_angle_min_deg"], 1),
                    round(fov["polar_angle_max_deg"], 1),
                ],
                "max_px_diff_by_angle_deg": by_angle,
                "max_px_diff_to_55deg": max(by_angle.values()),
            }
        )
    return out


def calibrate_mirror(out_dir: Path) -> dict[str, object]:
    from mowerhw.camera.calibrate import calibrate

    images = sorted((MIRROR / "images").glob("*.jpg"), key=lambda p: int(p.stem))
    calib = calibrate(images, (9, 6), 0.03)
    path = out_dir / "mirror.yaml"
    save_camchain(calib.camera, path)
    written = load_camchain(path)
    report = calib.as_dict()
    report["model_check"] = check_against_opencv(written, n=50000)
    return report


def main() -> None:
    if not DATA.exists():
        sys.exit(f"no real data at {DATA}")
    print(json.dumps({"t265_mei_vs_factory_kb4": mei_vs_factory()}))
    with tempfile.TemporaryDirectory() as tmp:
        report = calibrate_mirror(Path(tmp))
    report["views"] = [v for v in report["views"] if not v["used"]]  # the per-view list is long
    print(json.dumps({"mirror_calibration": report}))


if __name__ == "__main__":
    main()
