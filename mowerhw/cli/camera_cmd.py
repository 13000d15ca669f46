"""``mowerhw camera info|calibrate``: what a calibration sees; calibrating a camera."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

from mowerhw.camera import CameraCalibrationError, camera_names, load_camchain
from mowerhw.cli.common import (
    add_config_argument,
    add_plot_argument,
    load_config_or_exit,
    number,
    print_json,
)
from mowerhw.config import EX_CONFIG, camera_rotation


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("camera", help="inspect or make a camera calibration")
    csub = p.add_subparsers(dest="camera_command", metavar="ACTION", required=True)
    info = csub.add_parser(
        "info", help="field of view, valid region and model checks (incl. agreement with OpenCV)"
    )
    add_config_argument(info)
    info.add_argument(
        "--calibration",
        type=Path,
        metavar="CAMCHAIN",
        help="a Kalibr camchain YAML (default: camera.calibration of the config)",
    )
    info.add_argument(
        "--camera",
        metavar="NAME",
        help="which camera of the camchain (default: camera.camchain_key; 'all': each)",
    )
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(handler=_info)

    cal = csub.add_parser(
        "calibrate",
        help="calibrate an omnidirectional camera from checkerboard photos (Mei model)",
        description="Detect a checkerboard in every photo, fit the Mei omnidirectional model "
        "with radial-tangential distortion and skew (cv2.omnidir), drop outlier views, find "
        "the usable image region (mirror annulus or fisheye image circle) from the photos, "
        "and write a Kalibr camchain. Take 15-30 photos with the whole board in view, spread "
        "over the whole image (near the rim too) and at several distances and tilts.",
    )
    cal.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="checkerboard photos")
    cal.add_argument(
        "--pattern",
        required=True,
        metavar="COLSxROWS",
        help="inner corners of the board per row and column, e.g. 9x6",
    )
    cal.add_argument(
        "--square",
        required=True,
        type=number(float, gt=0, le=10),
        metavar="METRES",
        help="side of one square (m)",
    )
    cal.add_argument(
        "-o",
        "--out",
        type=Path,
        default=Path("camchain.yaml"),
        metavar="CAMCHAIN",
        help="the camchain to write (default: camchain.yaml)",
    )
    cal.add_argument(
        "--camera-name", default="cam0", metavar="NAME", help="its key in the camchain (cam0)"
    )
    add_plot_argument(cal, "also draw the residuals over the image (default: next to the camchain)")
    cal.add_argument("--json", action="store_true", help="print one JSON object")
    cal.set_defaults(handler=_calibrate)


# ------------------------------------------------------------------------------- info


def _info(args: argparse.Namespace) -> int:
    cfg = load_config_or_exit(args.config)
    path = args.calibration or cfg.camera.calibration
    name = args.camera or (cfg.camera.camchain_key if args.calibration is None else "cam0")
    try:
        names = camera_names(path) if name == "all" else [name]
        reports = [
            _camera_report(cfg, path, n, explicit=args.calibration is not None) for n in names
        ]
    except (CameraCalibrationError, ValueError) as exc:
        print(f"mowerhw: {exc}", file=sys.stderr)
        return EX_CONFIG
    if args.json:
        print_json(reports[0] if len(reports) == 1 else reports)
        return 0
    for k, report in enumerate(reports):
        if k:
            print()
        _print_info(report)
    return 0


def _camera_report(cfg: Any, path: Path, name: str, explicit: bool) -> dict[str, Any]:
    from mowerhw.camera.check import check_against_opencv, field_of_view

    cam = load_camchain(path, name)
    if explicit:  # the camera's own T_cam_imu (if any), with this config's IMU mount
        cfg_cam = dataclasses.replace(cfg.camera, calibration=path, camchain_key=name, q_bc=None)
        q_bc = camera_rotation(dataclasses.replace(cfg, camera=cfg_cam), cam.T_cam_imu)
    else:
        q_bc = cfg.camera.q_bc
    return {
        "calibration": str(path),
        "camera": name,
        **cam.intrinsics(),
        "q_bc": list(q_bc),
        "q_bc_from": "T_cam_imu" if cam.T_cam_imu is not None and explicit else "config",
        "field_of_view": field_of_view(cam, q_bc),
        "model_check": check_against_opencv(cam, n=20000),
    }


def _print_info(r: dict[str, Any]) -> None:
    fov, chk = r["field_of_view"], r["model_check"]
    w, h = r["resolution"]
    print(f"calibration  {r['calibration']} ({r['camera']})")
    print(
        f"model        omni (Mei) + radtan, {w}x{h} px, xi={r['xi']:.6g}, "
        f"f=({r['fu']:.2f}, {r['fv']:.2f}), c=({r['cu']:.2f}, {r['cv']:.2f}), "
        f"skew {r['skew'] * r['fu']:.3g} px"
    )
    if fov.get("valid_pixel_fraction", 0.0) == 0.0:
        print("valid region none: no pixel of this calibration has a bearing")
        return
    mask = fov["mask"]
    where = (
        f"annulus {mask['inner_radius_px']:.0f}..{mask['outer_radius_px']:.0f} px around "
        f"({mask['center_px'][0]:.1f}, {mask['center_px'][1]:.1f})"
        if mask
        else "the whole image where the model has a bearing (no mask)"
    )
    print(f"valid region {where}: {100 * fov['valid_pixel_fraction']:.0f} % of the image")
    print(
        f"sees         {fov['polar_angle_min_deg']:.1f}..{fov['polar_angle_max_deg']:.1f} deg "
        f"from the camera axis (the model stops at {fov['model_limit_deg']:.1f} deg)"
    )
    print(
        f"elevation    {fov['elevation_min_deg']:.1f}..{fov['elevation_max_deg']:.1f} deg "
        f"in the body frame (q_bc from {r['q_bc_from']})"
    )
    if r["timeshift_cam_imu_s"]:
        print(f"time shift   {1e3 * r['timeshift_cam_imu_s']:.3f} ms (t_imu = t_cam + shift)")
    print(f"round trip   project(lift(p)) - p: max {chk['roundtrip_px_max']:.2e} px")
    print(
        f"vs OpenCV    projectPoints: max {chk['project_vs_opencv_px_max']:.2e} px; "
        f"undistortPoints: max {chk['lift_vs_opencv_px_max_where_opencv_converged']:.2e} px "
        f"where OpenCV converged ({100 * chk['opencv_converged_fraction']:.1f} % of the region)"
    )
    if chk["opencv_unconverged_px_max"] > 0:
        lo, hi = chk["opencv_unconverged_radius_px_range"]
        print(
            f"             OpenCV's 20-step undistortion is off by up to "
            f"{chk['opencv_unconverged_px_max']:.2g} px at radii {lo:.0f}..{hi:.0f} px "
            "(ours converges everywhere)"
        )


# -------------------------------------------------------------------------- calibrate


def _calibrate(args: argparse.Namespace) -> int:
    from mowerhw.camera import save_camchain
    from mowerhw.camera.calibrate import CalibrationError, calibrate, parse_pattern, plot_residuals
    from mowerhw.camera.check import check_against_opencv
    from mowerhw.common.progress import Progress

    try:
        pattern = parse_pattern(args.pattern)
        with Progress(len(args.images) + 2, "calibrating") as bar:

            def step(_message: str) -> None:
                bar.advance()

            calib = calibrate(args.images, pattern, args.square, progress=step)
    except CalibrationError as exc:
        print(f"mowerhw: {exc}", file=sys.stderr)
        return 1
    used = sorted(v.rms_px or 0.0 for v in calib.used)
    comment = (
        f"mowerhw camera calibrate: {len(calib.used)} of {len(calib.views)} views, "
        f"RMS {calib.rms_px:.3f} px, board {args.pattern} x {args.square} m"
    )
    save_camchain(calib.camera, args.out, args.camera_name, comment=comment)
    written = load_camchain(args.out, args.camera_name)
    check = check_against_opencv(written, n=20000)
    plot = None
    if args.plot is not None:
        plot = args.out.with_suffix(".png") if args.plot is True else args.plot
        plot_residuals(calib, _mean_image(calib), plot)
    report = calib.as_dict()
    report["written"] = str(args.out)
    report["plot"] = None if plot is None else str(plot)
    report["model_check"] = check
    if args.json:
        print_json(report)
        return 0
    cam = calib.camera
    print(
        f"photos       {len(calib.views)}, board {args.pattern} inner corners, "
        f"{args.square} m squares, {calib.image_size[0]}x{calib.image_size[1]} px"
    )
    print(f"views        {len(calib.used)} used of {len(calib.views)}")
    for v in calib.views:
        if not v.used:
            print(f"             {Path(v.path).name}: {v.note}")
    print(
        f"rms          {calib.rms_px:.3f} px (per view {used[0]:.3f} .. {used[-1]:.3f} px)"
        if used
        else ""
    )
    per_view = "  ".join(f"{Path(v.path).name} {v.rms_px:.3f}" for v in calib.used)
    print(f"per view     {per_view}")
    print(
        f"model        xi {cam.xi:.5f}, fu {cam.fu:.2f}, fv {cam.fv:.2f}, cu {cam.cu:.2f}, "
        f"cv {cam.cv:.2f}, skew {cam.skew * cam.fu:.3f} px"
    )
    print(f"distortion   k1 {cam.k1:.5f}, k2 {cam.k2:.5f}, p1 {cam.p1:.5f}, p2 {cam.p2:.5f}")
    _print_region(report)
    cov = report["coverage"]
    print(
        f"coverage     corners in {100 * cov['grid_cells_covered']:.0f} % of the region's "
        f"grid cells; at {cov['corner_polar_deg'][0]}..{cov['corner_polar_deg'][1]} deg from "
        f"the axis (the region: {cov['region_polar_deg'][0]}..{cov['region_polar_deg'][1]})"
    )
    print(
        f"check        written camchain loads; vs cv2.omnidir: project "
        f"{check['project_vs_opencv_px_max']:.1e} px, lift "
        f"{check['lift_vs_opencv_px_max_where_opencv_converged']:.1e} px "
        f"(OpenCV converged on {100 * check['opencv_converged_fraction']:.0f} % of the region)"
    )
    print(
        f"written      {args.out} ({args.camera_name})" + (f"; residuals: {plot}" if plot else "")
    )
    return 0


def _print_region(report: dict[str, Any]) -> None:
    region = report["region"]
    ann = region["annulus"]
    if ann is None:
        print("region       no circular edge seen: the whole image where the model has bearings")
        return
    outer, inner = region["outer_edge"], region["inner_edge"]
    kind = "mirror annulus" if inner else "image circle"
    seen = []
    if outer:
        seen.append(f"outer edge r {outer['radius_px']:.1f} px on {100 * outer['support']:.0f} %")
    if inner:
        seen.append(f"inner edge r {inner['radius_px']:.1f} px on {100 * inner['support']:.0f} %")
    print(
        f"region       {kind} around ({ann['center_px'][0]:.1f}, {ann['center_px'][1]:.1f}): "
        f"{ann['inner_radius_px']:.1f}..{ann['outer_radius_px']:.1f} px"
    )
    margin = region["margin_px"]
    print(f"             {'; '.join(seen)} of the rays that see it; {margin:.1f} px kept off")


def _mean_image(calib: Any) -> Any:
    import cv2
    import numpy as np

    acc = None
    n = 0
    for v in calib.views:
        img = cv2.imread(v.path, cv2.IMREAD_GRAYSCALE)
        if img is None or (img.shape[1], img.shape[0]) != calib.image_size:
            continue
        acc = img.astype(np.float64) if acc is None else acc + img
        n += 1
    return None if acc is None else acc / n
