"""``mowerhw demo``: a short, self-checking tour of what this build can do.

It exercises the real modules on synthetic data and prints what they measured; every figure
is computed, none is canned. It grows with the product (the mock-bench teach + mow run).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from mowerhw.cli.common import add_config_argument, load_config_or_exit, print_json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="a short tour: config, camera model, clock sync, buffer")
    add_config_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(handler=_demo)


def _camera_section(cfg: Any) -> dict[str, Any]:
    from mowerhw.camera import load_camchain
    from mowerhw.camera.check import angle_between, check_against_opencv, field_of_view
    from mowerhw.common.geometry import quat_to_rotmat

    cam = load_camchain(cfg.camera.calibration, cfg.camera.camchain_key)
    # Landmarks around the mower: a ring of window corners 8 m away, 1 m above the camera.
    az = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
    pts_b = np.stack([8 * np.cos(az), 8 * np.sin(az), np.ones_like(az)], axis=-1)
    r_bc = quat_to_rotmat(cfg.camera.q_bc)
    pix, visible = cam.visible(pts_b @ r_bc)  # body → camera: R_bcᵀ p (row form: p @ R_bc)
    back_b = cam.lift(pix[visible]) @ r_bc.T
    truth_b = pts_b[visible] / np.linalg.norm(pts_b[visible], axis=-1, keepdims=True)
    err = np.degrees(angle_between(back_b, truth_b))
    return {
        "calibration": str(cfg.camera.calibration),
        "landmarks_visible": f"{int(visible.sum())}/{len(az)}",
        "landmark_pixels": np.round(pix[visible][:3], 1).tolist(),
        "bearing_roundtrip_deg_max": float(err.max()),
        "field_of_view": field_of_view(cam, cfg.camera.q_bc),
        "model_check": check_against_opencv(cam, n=5000),
    }


def _clocksync_section() -> dict[str, Any]:
    """VN-100-like stream: 100 Hz device ns clock, 60 ppm fast, USB jitter and stalls."""
    from mowerhw.common.clocksync import ClockSync

    rng = np.random.default_rng(3)
    n = 6000
    true_host = 1000.0 + np.arange(n) * 0.01
    device_ns = np.round((true_host - 1000.0) * (1 + 60e-6) * 1e9 + 5e9)
    delay = 0.0008 + rng.exponential(0.0015, n)
    stalls = rng.random(n) < 0.01
    delay[stalls] += rng.uniform(0.02, 0.08, int(stalls.sum()))
    arrival = true_host + delay
    sync = ClockSync(device_unit_s=1e-9)
    mapped = np.array([sync.update(d, a) for d, a in zip(device_ns, arrival, strict=True)])
    settled = slice(1000, None)
    err = mapped[settled] - (true_host[settled] + 0.0008)
    raw = arrival[settled] - true_host[settled]
    return {
        "samples": n,
        "drift_ppm_true": 60.0,
        "drift_ppm_estimated": round(sync.drift_ppm, 2),
        "arrival_jitter_ms_p99": float(np.percentile(raw, 99) * 1e3),
        "mapped_error_ms_p99": float(np.percentile(np.abs(err), 99) * 1e3),
        "resets": sync.stats.resets,
    }


def _buffer_section() -> dict[str, Any]:
    from mowerhw.common.buffer import SensorBuffer
    from mowerhw.common.samples import ImuSample, SpeedSample, Stream
    from mowerhw.estimation.odometry import SpeedTrack

    buf = SensorBuffer()
    for k in range(21):  # 2 s of 10 Hz speed, ramping 0 → 0.5 m/s
        buf.push(Stream.SPEED, SpeedSample(t=0.1 * k, speed_mps=round(0.025 * k, 3)))
    for k in range(200):
        buf.push(Stream.IMU, ImuSample(t=0.01 * k + 0.005, gyro=[0.0, 0.0, 0.1]))
    late = ImuSample(t=0.5, gyro=[0, 0, 0.1])
    buf.push(Stream.IMU, late)  # arrives late: counted, still delivered in order
    ordered = buf.pop_ready()
    track = SpeedTrack()  # the estimators' speed model, fed in time order
    for stream, s in ordered:
        if stream == Stream.SPEED:
            track.add(s.t, s.speed_mps)
    imu_t = np.array([s.t for stream, s in ordered if stream == Stream.IMU and s.t <= 2.0])
    speed = track.interpolate(imu_t)
    times = [s.t for _, s in ordered]
    return {
        "delivered": len(ordered),
        "time_ordered": bool(np.all(np.diff(times) >= 0)),
        "speed_at_imu_times_max_err": float(np.max(np.abs(speed - 0.25 * imu_t))),
        "stats": buf.stats(),
    }


def _demo(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    cfg = load_config_or_exit(args.config)
    report = {
        "config": str(cfg.source) if cfg.source else "built-in defaults",
        "camera": _camera_section(cfg),
        "clocksync": _clocksync_section(),
        "buffer": _buffer_section(),
    }
    report["wall_s"] = round(time.perf_counter() - started, 3)
    if args.json:
        print_json(report)
        return 0
    cam, cs, bf = report["camera"], report["clocksync"], report["buffer"]
    fov = cam["field_of_view"]
    print(f"config       {report['config']}: valid")
    print(f"camera       {cam['calibration']}")
    print(
        f"             annulus sees {fov['elevation_min_deg']:.0f}..{fov['elevation_max_deg']:.0f}"
        f" deg elevation; {cam['landmarks_visible']} ring landmarks visible, first at "
        f"{cam['landmark_pixels'][0]} px; bearing round trip {cam['bearing_roundtrip_deg_max']:.1e}"
        " deg"
    )
    chk = cam["model_check"]
    print(
        f"             vs cv2.omnidir: projectPoints {chk['project_vs_opencv_px_max']:.1e} px, "
        f"undistortPoints {chk['lift_vs_opencv_px_max_where_opencv_converged']:.1e} px "
        "(where OpenCV converges)"
    )
    print(
        f"clock sync   VN-100-like 100 Hz, 60 ppm drift: estimated {cs['drift_ppm_estimated']} ppm;"
        f" arrival jitter p99 {cs['arrival_jitter_ms_p99']:.2f} ms -> mapped error p99 "
        f"{cs['mapped_error_ms_p99']:.3f} ms"
    )
    print(
        f"buffer       {bf['delivered']} samples delivered in time order: {bf['time_ordered']}; "
        f"speed at IMU times max error {bf['speed_at_imu_times_max_err']:.1e} m/s; "
        f"out-of-order imu: {bf['stats']['imu']['out_of_order']}"
    )
    print(f"done in {report['wall_s']} s. Next: `mowerhw --help`.")
    return 0
