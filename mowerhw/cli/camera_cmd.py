"""``mowerhw camera info``: what a calibration sees, and how well the model holds."""

from __future__ import annotations

import argparse
from pathlib import Path

from mowerhw.camera import CameraCalibrationError, load_camchain
from mowerhw.cli.common import add_config_argument, load_config_or_exit, print_json
from mowerhw.config import EX_CONFIG


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("camera", help="inspect a camera calibration")
    csub = p.add_subparsers(dest="camera_command", metavar="ACTION", required=True)
    info = csub.add_parser(
        "info", help="field of view, mask and model checks (incl. agreement with cv2.omnidir)"
    )
    add_config_argument(info)
    info.add_argument(
        "--calibration",
        type=Path,
        metavar="CAMCHAIN",
        help="a Kalibr camchain YAML (default: camera.calibration of the config)",
    )
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(handler=_info)


def _info(args: argparse.Namespace) -> int:
    from mowerhw.camera_check import check_against_opencv, field_of_view

    cfg = load_config_or_exit(args.config)
    path = args.calibration or cfg.camera.calibration
    try:
        cam = load_camchain(path)
    except CameraCalibrationError as exc:
        print(f"mowerhw: {exc}")
        return EX_CONFIG
    report = {
        "calibration": str(path),
        "model": "omni (Mei) + radtan",
        "resolution": [cam.width, cam.height],
        "xi": cam.xi,
        "fu": cam.fu,
        "fv": cam.fv,
        "cu": cam.cu,
        "cv": cam.cv,
        "distortion": [cam.k1, cam.k2, cam.p1, cam.p2],
        "field_of_view": field_of_view(cam, cfg.camera.q_bc),
        "model_check": check_against_opencv(cam, n=20000),
    }
    if args.json:
        print_json(report)
        return 0
    fov, chk = report["field_of_view"], report["model_check"]
    print(f"calibration  {path}")
    print(f"model        omni (Mei) + radtan, {cam.width}x{cam.height} px, xi={cam.xi}")
    print(
        f"mask         annulus {fov['inner_radius_px']:.0f}..{fov['outer_radius_px']:.0f} px "
        f"= {fov['polar_angle_min_deg']:.1f}..{fov['polar_angle_max_deg']:.1f} deg from the "
        f"camera axis ({100 * fov['valid_pixel_fraction']:.0f} % of the image)"
    )
    print(
        f"elevation    {fov['elevation_min_deg']:.1f}..{fov['elevation_max_deg']:.1f} deg "
        "in the body frame (camera.q_bc)"
    )
    print(f"round trip   project(lift(p)) - p: max {chk['roundtrip_px_max']:.2e} px")
    print(
        f"vs OpenCV    projectPoints: max {chk['project_vs_opencv_px_max']:.2e} px; "
        f"undistortPoints: max {chk['lift_vs_opencv_px_max_where_opencv_converged']:.2e} px "
        f"where OpenCV converged ({100 * chk['opencv_converged_fraction']:.1f} % of the mask)"
    )
    if chk["opencv_unconverged_px_max"] > 0:
        lo, hi = chk["opencv_unconverged_radius_px_range"]
        print(
            f"             OpenCV's 20-step undistortion is off by up to "
            f"{chk['opencv_unconverged_px_max']:.2g} px at radii {lo:.0f}..{hi:.0f} px "
            "(ours converges everywhere)"
        )
    return 0
