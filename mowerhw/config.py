"""One configuration schema for the whole runtime (docs/design.md §2), validated at load.

The schema *is* the frozen dataclasses below: each section is one hardware part or one
estimator (Klipper-style: one section per module), each field carries its default, its rules
and a one-line doc. ``load_config`` walks the YAML against them and collects every problem as
``key: value … what is allowed``; a bad file raises :class:`ConfigError`, which every command
reports on one line per problem and exits with ``EX_CONFIG`` (78), the status systemd is told
not to restart on (``RestartPreventExitStatus=78``).

Relative paths in a file are resolved against the directory of that file; relative defaults
name files shipped in ``configs/``.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import reprlib
import stat
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mowerhw.common.clocksync import FRAME_CLOCKS
from mowerhw.common.supervisor_socket import supervisor_socket
from mowerhw.common.yamlfile import load_yaml

EX_CONFIG = 78  # sysexits.h: configuration error
#: the mirror-up camera of the paper: camera z along body −z, image centre at nadir
DEFAULT_Q_BC = (0.0, 1.0, 0.0, 0.0)
#: camera.q_bc and a calibration's T_cam_imu may differ by this much (deg)
EXTRINSICS_TOLERANCE_DEG = 1.0

VN100_BAUDRATES = (9600, 19200, 38400, 57600, 115200, 128000, 230400, 460800, 921600)
VN100_RATES_HZ = (1, 2, 4, 5, 8, 10, 16, 20, 25, 40, 50, 80, 100, 160, 200, 400, 800)
CAN_INTERFACES = (
    "socketcan",
    "virtual",
    "udp_multicast",
    "slcan",
    "pcan",
    "kvaser",
    "vector",
    "gs_usb",
    "socketcand",
    "serial",
    "ixxat",
    "nican",
    "neovi",
    "cantact",
    "seeedstudio",
)
CAN_BITRATES = (125000, 250000, 500000, 1000000)


class ConfigError(ValueError):
    """Invalid configuration. ``problems`` lists one message per bad key."""

    def __init__(self, problems: list[str], source: str | None = None) -> None:
        self.problems = problems
        self.source = source
        prefix = f"{source}: " if source else ""
        super().__init__("\n".join(prefix + p for p in problems))


def opt(default: Any, doc: str = "", **rules: Any) -> Any:
    """A config field: default, one-line doc, validation rules.

    Rules: ``choices`` (tuple), ``ge``/``gt``/``le``/``lt`` (numeric bounds), ``unit_norm``
    (a quaternion), ``exists`` (a path that must exist), ``nonempty`` (strings), ``octal``
    (messages show the value in octal).
    """
    meta = {"doc": doc, **rules}
    if isinstance(default, list | dict):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


def section(cls: type, doc: str = "") -> Any:
    return field(default_factory=cls, metadata={"doc": doc})


Quat = tuple[float, float, float, float]


# --------------------------------------------------------------------------- device sections


@dataclass(frozen=True)
class ImuConfig:
    """VectorNav VN-100 on a serial port (``drivers.imu.vn100``)."""

    driver: str = opt(
        "vn100",
        "vn100 (real serial device) or mock (simulated on a pty)",
        choices=("vn100", "mock"),
    )
    port: str = opt("/dev/ttyUSB0", "serial device path", nonempty=True)
    baudrate: int = opt(921600, "baud rate to switch the sensor to", choices=VN100_BAUDRATES)
    initial_baudrate: int = opt(
        115200, "baud rate the sensor is at on power-up", choices=VN100_BAUDRATES
    )
    output: str = opt("binary", "async output format", choices=("binary", "ascii"))
    rate_hz: int = opt(
        100, "IMU output rate (800 Hz divided by a whole number)", choices=VN100_RATES_HZ
    )
    grade: str = opt(
        "vn100",
        "the gyro's grade: its noise figures (below, when null) come from its datasheet; "
        "measure your own unit with `mowerhw imu characterize`",
        choices=("vn100", "bmi088", "mpu6050"),
    )
    gyro_noise_density: float | None = opt(
        None, "white noise (angle random walk), rad/s/√Hz; null: the grade's", gt=0.0, le=0.1
    )
    gyro_bias_instability: float | None = opt(
        None, "bias instability (the Allan floor), rad/s; null: the grade's", ge=0.0, le=0.1
    )
    gyro_random_walk: float | None = opt(
        None, "rate random walk, rad/s/√s; null: the grade's", ge=0.0, le=0.01
    )
    gyro_scale_error: float | None = opt(
        None,
        "1σ of the gyro's scale-factor error (fraction); the estimators estimate the yaw "
        "rate's scale with this prior; null: the grade's",
        ge=0.0,
        le=0.2,
    )
    gyro_scale_drift: float | None = opt(
        None,
        "1σ of how much the gyro's scale factor changes from the teach to a later mow "
        "(temperature, ageing; fraction): a map's taught yaw-rate scale is trusted to within "
        "this; null: the grade's",
        ge=0.0,
        le=0.2,
    )
    gyro_source: str = opt(
        "auto",
        "where the angular rate comes from: angular_rate (Common/IMU AngularRate, "
        "compensated), uncomp_gyro (IMU UncompGyro or Common Imu), delta_theta (IMU "
        "DeltaTheta or Common Deltas, Δθ/Δt); auto: the first the sensor sends, in that order",
        choices=("auto", "angular_rate", "uncomp_gyro", "delta_theta"),
    )
    configure_sensor: bool = opt(
        True,
        "write the output registers at start-up (baud, rate, binary fields for gyro_source); "
        "false: keep the sensor's own configuration and read whatever it sends",
    )
    stale_after_s: float = opt(
        0.1,
        "halt when no IMU sample for this long (the kernel's tty input delivers the samples "
        "behind other nice-0 CPU work: up to 0.12 s measured beside two CPU hogs; "
        "systemd/README.md)",
        gt=0.0,
        le=5.0,
    )
    low_latency: bool = opt(True, "request Linux serial low-latency mode (USB adapters)")
    reconnect_max_backoff_s: float = opt(5.0, "longest wait between reconnect tries", gt=0, le=60)
    q_bi: Quat = opt(
        (0.0, 1.0, 0.0, 0.0),
        "IMU frame in the body frame, (w, x, y, z); VN-100 z-down mounted: (0, 1, 0, 0)",
        unit_norm=True,
    )


@dataclass(frozen=True)
class CanConfig:
    """The CAN bus (python-can) shared by ground speed and permit/halt."""

    interface: str = opt("socketcan", "python-can interface", choices=CAN_INTERFACES)
    channel: str = opt("can0", "python-can channel (socketcan: interface name)", nonempty=True)
    bitrate: int = opt(250000, "bit rate (ISO 11783: 250000)", choices=CAN_BITRATES)
    source_address: int = opt(0x90, "this ECU's ISO 11783 source address", ge=0, le=253)
    address_claim: bool = opt(
        True,
        "claim source_address before sending, as ISO 11783-5 / J1939-81 ask (Address Claimed, "
        "PGN 60928; 250 ms of contention; requests for it answered; yielded to a lower NAME, "
        "and then no permit frame is sent: the controller sees silence); false: send without "
        "claiming",
    )
    address_claim_retry_s: float = opt(
        10.0,
        "while another ECU holds source_address: ask the bus this often whether it is free "
        "(a Request for Address Claimed) and claim it once no lower NAME answers for it",
        gt=0.0,
    )
    name_identity_number: int | None = opt(
        None,
        "this ECU's NAME: identity number, unique per unit (null: from /etc/machine-id)",
        ge=0,
        le=(1 << 21) - 1,
    )
    name_manufacturer_code: int = opt(
        0, "NAME: the SAE-assigned manufacturer code of the integrator (0: reserved)", ge=0, le=2047
    )
    name_function: int = opt(
        128, "NAME: function (128-253: specific to the industry group)", ge=0, le=255
    )
    name_function_instance: int = opt(0, "NAME: function instance", ge=0, le=31)
    name_ecu_instance: int = opt(0, "NAME: ECU instance", ge=0, le=7)
    name_device_class: int = opt(
        0, "NAME: device class (J1939: vehicle system; 0 non-specific)", ge=0, le=127
    )
    name_device_class_instance: int = opt(0, "NAME: device class instance", ge=0, le=15)
    name_industry_group: int = opt(
        2, "NAME: industry group (2: agricultural and forestry equipment)", ge=0, le=7
    )
    udp_port: int = opt(
        43113,
        "udp_multicast only: UDP port of the bus (Linux delivers every group on a port to "
        "every socket on it, so two buses on one host need two ports)",
        ge=1024,
        le=65535,
    )


@dataclass(frozen=True)
class SpeedConfig:
    """Ground speed from ISO 11783 GBSD (PGN 65097), WBSD (PGN 65096) or J1939 CCVS1 (65265)."""

    source: str = opt(
        "ground",
        "which message to use: ground (GBSD), wheel (WBSD), ccvs1 (CCVS1 wheel-based vehicle "
        "speed, what most tractor and mower controllers send), any (whichever arrives valid)",
        choices=("ground", "wheel", "ccvs1", "any"),
    )
    ccvs1_direction: str = opt(
        "etc2",
        "CCVS1 carries no direction: etc2 (reverse when the transmission's ETC2 gear is "
        "negative; no ETC2 on the bus: speed invalid) or forward (the mower never reverses)",
        choices=("etc2", "forward"),
    )
    sensor_address: int | None = opt(
        None, "accept only this source address (null: any)", ge=0, le=253
    )
    stale_after_s: float = opt(0.3, "halt when no valid speed for this long", gt=0.0, le=5.0)
    contact_point_m: tuple[float, float, float] = opt(
        (0.0, 0.0, -0.8),
        "where the ground speed is measured (the wheels' contact with the ground), body frame "
        "from the camera centre, m: (0, 0, -0.8) for a camera 0.8 m above the ground",
    )


@dataclass(frozen=True)
class CameraConfig:
    """Omnidirectional camera through V4L2 (``drivers.camera.v4l2``)."""

    driver: str = opt(
        "v4l2",
        "v4l2 (real device), stream (frames over a Unix socket: the bench's camera), "
        "or mock (synthetic frames in-process)",
        choices=("v4l2", "stream", "mock"),
    )
    device: str = opt(
        "/dev/video0", "V4L2 device path (stream: the Unix socket path)", nonempty=True
    )
    width: int = opt(1540, "frame width (px)", ge=16, le=8192)
    height: int = opt(1540, "frame height (px)", ge=16, le=8192)
    fps: float = opt(
        4.0,
        "frame rate the front end tracks (a faster camera's frames between are dropped)",
        gt=0.0,
        le=120.0,
    )
    device_fps: float | None = opt(
        None,
        "frame rate asked of the camera; null: fps. Above fps, the frames between are "
        "dropped before decoding but each tells the runtime the camera is alive, so "
        "stale_after_s may be as short as two of the camera's periods",
        gt=0.0,
        le=120.0,
    )
    pixel_format: str = opt("GREY", "V4L2 FOURCC", choices=("GREY", "YUYV", "MJPG", "BGR3"))
    calibration: Path = opt(
        Path("camera/paper-table1.yaml"), "Kalibr camchain YAML (omni + radtan)", exists=True
    )
    camchain_key: str = opt("cam0", "which camera of the camchain (cam0, cam1, …)", nonempty=True)
    extrinsics: str = opt(
        "calibration",
        "where the camera's rotation in the body frame comes from: calibration (the camchain's "
        "T_cam_imu with imu.q_bi; camera.q_bc, if also given, must agree within "
        f"{EXTRINSICS_TOLERANCE_DEG}°; a camchain without T_cam_imu uses camera.q_bc) or config "
        "(camera.q_bc, whatever the camchain says)",
        choices=("calibration", "config"),
    )
    q_bc: Quat | None = opt(
        None,
        "camera (Mei) frame in the body frame, (w, x, y, z); null: from the calibration's "
        f"T_cam_imu, else {DEFAULT_Q_BC} (mirror up, image centre at nadir)",
        unit_norm=True,
    )
    timestamps: str = opt(
        "auto",
        "where a frame's time comes from (v4l2): monotonic (the driver's buffer time, on this "
        "computer's monotonic clock as V4L2 stamps it, as it is), device (buffer times on a "
        "clock of their own, mapped onto the host's), arrival (when the frame was read: "
        "late by the transfer), or auto (monotonic when the first buffer time is, else device)",
        choices=FRAME_CLOCKS,
    )
    stale_after_s: float = opt(1.0, "halt when no frame for this long", gt=0.0, le=30.0)
    pixel_sigma: float = opt(1.0, "feature position noise (px, 1σ)", gt=0.0, le=20.0)

    def camera_fps(self) -> float:
        """The rate the camera delivers at (``device_fps``, else ``fps``): the one its
        liveness is judged at."""
        return self.fps if self.device_fps is None else self.device_fps

    def rate_key(self) -> str:
        """The key :meth:`camera_fps` comes from, for messages."""
        return "camera.fps" if self.device_fps is None else "camera.device_fps"

    def body_rotation(self) -> Quat:
        """``q_bc`` as the config loader resolved it (from the calibration or the config;
        the default when neither gives one)."""
        return self.q_bc if self.q_bc is not None else DEFAULT_Q_BC


@dataclass(frozen=True)
class PermitConfig:
    """Mowing permit / halt on CAN (ISO 11783 ISB + heartbeat + status; docs/design.md §7)."""

    period_s: float = opt(0.1, "ISB and status repeat period", ge=0.01, le=0.1)
    heartbeat_period_s: float = opt(0.1, "ISO 11783 heartbeat period", ge=0.01, le=0.1)
    status_pgn: int = opt(0xFF10, "PGN of the status frame (Proprietary B)", ge=0xFF00, le=0xFFFF)


# ------------------------------------------------------------------------ estimator sections


@dataclass(frozen=True)
class FrontendConfig:
    """Vision front end: features, KLT tracking, outlier rejection, re-identification."""

    max_features: int = opt(120, "features tracked at once", ge=8, le=2000)
    min_distance_px: float = opt(16.0, "closest two features may be", gt=0.0, le=200.0)
    quality_level: float = opt(
        0.05, "Shi–Tomasi corner strength, relative to the strongest corner", gt=0.0, lt=1.0
    )
    detector: str = opt(
        "fast",
        "fast: FAST corners scored by Shi–Tomasi on small patches (quick); shi-tomasi: "
        "cv2.goodFeaturesToTrack over the image",
        choices=("fast", "shi-tomasi"),
    )
    fast_threshold: int = opt(20, "FAST intensity threshold (grey levels)", ge=1, le=255)
    block_size: int = opt(5, "Shi–Tomasi window (px, at the detection scale)", ge=3, le=31)
    detect_level: int = opt(
        0, "pyramid level detection runs on (0 = full size: no blobs taken for corners)", ge=0, le=3
    )
    grid: int = opt(8, "detection grid (cells per side); spreads features", ge=1, le=64)
    min_elevation_deg: float = opt(
        -25.0, "detect nothing lower (grass near the deck is not a landmark)", ge=-90.0, le=90.0
    )
    max_elevation_deg: float = opt(60.0, "detect nothing higher", ge=-90.0, le=90.0)
    gyro_prediction: bool = opt(
        True,
        "start Lucas–Kanade where the gyro's rotation moves each feature, on the previous "
        "image turned by the same amount (false: from where it was; for comparison)",
    )
    klt_window_px: int = opt(21, "Lucas–Kanade window (px)", ge=5, le=101)
    klt_levels: int = opt(3, "Lucas–Kanade pyramid levels above full size", ge=0, le=6)
    klt_base_level: int = opt(
        1,
        "pyramid level Lucas–Kanade tracks on (1: half size, a quarter of the work; the "
        "sub-pixel refinement then finds each corner at full size); at most klt_levels",
        ge=0,
        le=2,
    )
    fb_max_px: float = opt(0.7, "largest forward–backward tracking error kept (px)", gt=0.0)
    subpixel: bool = opt(True, "refine tracked corners to sub-pixel (stops KLT drift)")
    max_refine_px: float = opt(1.5, "drop a track whose refinement moves it further (px)", gt=0.0)
    epipolar_threshold_deg: float = opt(
        0.35, "largest distance from its epipolar plane a track may have (deg)", gt=0.0, le=10.0
    )
    ransac_iterations: int = opt(64, "epipolar RANSAC hypotheses per frame", ge=8, le=4096)
    descriptor_refresh_frames: int = opt(
        8, "add a fresh descriptor to a track this often (frames)", ge=1
    )
    max_descriptors: int = opt(4, "descriptors kept per track / map landmark", ge=1, le=16)
    max_hamming: int = opt(50, "largest ORB distance (of 256 bits) for a re-identification", ge=1)
    association_gate: float = opt(
        0.999, "χ² probability of the predicted-bearing gate for re-identification", gt=0.5, lt=1.0
    )
    reid_angle_deg: float = opt(
        0.75, "teach: predicted-bearing gate for re-identifying a lost landmark (deg)", gt=0.0
    )
    drop_after_rejections: int = opt(
        2, "mow: drop an association the localizer rejects this many frames running", ge=1
    )


@dataclass(frozen=True)
class MotionNoiseConfig:
    """Process noise both estimators share (teach and mow sections)."""

    gyro_noise: float | None = opt(
        None, "estimator's gyro white noise, rad/s/√Hz; null: from the imu section", gt=0.0
    )
    gyro_bias_walk: float | None = opt(
        None, "estimator's gyro bias random walk, rad/s/√s; null: from the imu section", ge=0.0
    )
    gyro_scale_sigma: float | None = opt(
        None,
        "prior σ of the yaw rate's scale error the estimator estimates; null: from the imu "
        "section (imu.gyro_scale_error)",
        ge=0.0,
        le=0.2,
    )
    speed_contact_m: tuple[float, float, float] = field(
        default=(0.0, 0.0, -0.8), metadata={"internal": True}
    )  # speed.contact_point_m, copied at load
    speed_noise: float = opt(2e-3, "ground speed noise density, m/s/√Hz", gt=0.0)
    lateral_noise: float = opt(3e-3, "sideways/vertical slip density, m/s/√Hz", gt=0.0)

    def gyro(self) -> tuple[float, float, float]:
        """(white noise, bias random walk, yaw-rate scale σ) as the estimators use them: the
        section must have been through :func:`with_imu_noise`, which fills the nulls."""
        n, w, k = self.gyro_noise, self.gyro_bias_walk, self.gyro_scale_sigma
        if n is None or w is None or k is None:
            raise ValueError("gyro noise not resolved: pass the section through with_imu_noise")
        return n, w, k


@dataclass(frozen=True)
class TeachConfig(MotionNoiseConfig):
    """Teach phase: landmark observers (eqs 2–8) and robot-centric EKF (eqs 14–20)."""

    gamma1: float = opt(-2.0, "observer contraction rate for depth, γ₁ (eq. 7), 1/s", lt=0.0)
    gamma2: float = opt(-6.0, "observer contraction rate for direction, γ₂ (eq. 7), 1/s", lt=0.0)
    d_min_m: float = opt(0.5, "lower bound on landmark distance (Assumption 1)", gt=0.0)
    d_init_m: float = opt(5.0, "initial depth of a new landmark", gt=0.0)
    min_parallax_deg: float = opt(
        3.0, "skip depth pseudo-measurements below this parallax", gt=0.0, lt=90.0
    )
    min_baseline_m: float = opt(0.3, "skip depth pseudo-measurements below this baseline", gt=0.0)
    keyframe_baseline_m: float = opt(
        50.0,
        "also start a new keyframe after this distance (keyframes otherwise change "
        "when their landmarks leave the view)",
        gt=0.0,
    )
    standstill_s: float = opt(2.0, "initial standstill used to calibrate the gyro bias", ge=0.0)
    bearing_sigma_rad: float = opt(0.008, "bearing noise (1σ per axis)", gt=0.0, lt=0.5)
    boundary_simplify_m: float = opt(0.02, "Douglas–Peucker tolerance of the boundary", ge=0.0)
    min_area_m2: float = opt(4.0, "smallest lawn accepted as a boundary", gt=0.0)
    loop_closure: bool = opt(True, "close the loop at the start and distribute the error")
    ekf_measurement: str = opt(
        "epipolar",
        "EKF measurement: epipolar (depth-free part of eq. 16) or bearing (eq. 16 as printed)",
        choices=("epipolar", "bearing"),
    )
    depth_gain: str = opt(
        "weighted",
        "observer depth gain: weighted (eq. 7 capped by precision) or contraction (eq. 7 only)",
        choices=("weighted", "contraction"),
    )
    max_landmark_sigma_m: float = opt(
        0.05, "map only landmarks known better than this (largest position σ)", gt=0.0
    )
    landmark_residual_factor: float = opt(
        3.0, "drop landmarks whose bearing residual is this many times the typical one", gt=1.0
    )


@dataclass(frozen=True)
class MowConfig(MotionNoiseConfig):
    """Mow phase: world-centric EKF localizer (eqs 21–23)."""

    bearing_sigma_rad: float = opt(
        0.0035,
        "bearing noise of a frame counted alone (1σ per axis); frames from one spot or "
        "along one track share part of it and count less",
        gt=0.0,
        lt=0.5,
    )
    gate_probability: float = opt(0.999, "χ² gate of each landmark bearing", gt=0.5, lt=1.0)
    history_s: float = opt(2.0, "IMU history kept to apply late frames", gt=0.0, le=30.0)
    lockout_s: float = opt(
        3.0, "inflate, then re-initialise, after rejecting everything this long", gt=0.0
    )
    init_sigma_position_m: float = opt(0.05, "σ of the start pose's position", gt=0.0)
    init_sigma_heading_rad: float = opt(0.02, "σ of the start pose's heading", gt=0.0)
    min_landmarks: int = opt(3, "fewest accepted landmarks for a frame to count as a fix", ge=1)
    max_dead_reckoning_s: float = opt(
        3.0,
        "halt (UNCERTAIN) when the last landmark fix is older than this; at most 10 s (speed "
        "scale errors of a few per cent grow to decimetres beyond)",
        gt=0.0,
        le=10.0,
    )
    localized_after_frames: int = opt(
        3, "good frames needed after a (re)start to be localized", ge=1
    )
    gyro_scale_sigma_taught: float | None = opt(
        None,
        "prior σ of the yaw rate's scale error when the map carries the teach's estimate of "
        "it (its change since); null: from the imu section (imu.gyro_scale_drift)",
        ge=0.0,
        le=0.2,
    )
    areas: tuple[str, ...] = opt(
        (),
        "the mowing areas of the map to mow (names); empty: all of them. The others are "
        "driven with the deck off (state TRANSIT), like navigation areas",
        nonempty=True,
    )
    max_speed_mps: float = opt(
        1.0,
        "fastest the mower can go: while the ground speed is stale (and the accelerometer "
        "does not carry it, accel_bridge_s), the position is propagated at zero speed with "
        "this much uncertainty per second",
        gt=0.0,
        le=10.0,
    )
    accel_bridge_s: float = opt(
        2.0,
        "while the ground speed is stale, the IMU's along-track acceleration (gravity taken "
        "out through the filter's attitude) carries the last speed on for at most this long "
        "past the staleness limit (a mower braking for the halt the silence caused is "
        "followed, not taken to stop at once); 0: not past the limit (between two samples "
        "the acceleration still carries the newest one on); nothing without acceleration",
        ge=0.0,
        le=10.0,
    )
    accel_sigma_mps2: float = opt(
        0.1,
        "1σ of that along-track acceleration (bias, gravity through an attitude error, "
        "vibration): the position σ grows as σ·T²/2 over the T it carries the speed",
        gt=0.0,
        le=10.0,
    )
    lost_after_s: float = opt(
        6.0,
        "no landmark fix for this long: widen the pose uncertainty (0.5 m, 15°) so features "
        "can be re-identified from further off",
        gt=0.0,
        le=600.0,
    )
    frame_stamp_sigma_s: float = opt(
        0.0,
        "1σ of a frame's capture timestamp (s): a frame stamped that far off shows every "
        "bearing turned by the body rate times it, all together (0: exact stamps)",
        ge=0.0,
        le=0.1,
    )

    def taught_scale_sigma(self) -> float:
        """The prior σ of the yaw rate's scale error when the map carries the teach's
        estimate of it: :attr:`gyro_scale_sigma_taught`, never above the untaught prior
        (:meth:`gyro`). The section must have been through :func:`with_imu_noise`."""
        taught, untaught = self.gyro_scale_sigma_taught, self.gyro()[2]
        if taught is None:
            raise ValueError("gyro noise not resolved: pass the section through with_imu_noise")
        return min(taught, untaught)


@dataclass(frozen=True)
class ContainmentConfig:
    """Containment decision (docs/design.md §5 table). Each bound keeps the guarantee that a
    permit means "inside, with k σ to spare" (docs/design.md §5, "Bounds"): values outside
    them are refused, however the rest of the config is set."""

    margin_m: float = opt(
        0.4,
        "NEAR_EDGE band width (the paper's 0.4 m turn threshold); at least 0.1 m so the "
        "mower's controller is told to turn before the deck must halt",
        ge=0.1,
        le=2.0,
    )
    k_sigma: float = opt(
        3.0,
        "how many σ of position uncertainty to keep from the edge; at least 2 (below, one "
        "permit in 40 could be given outside)",
        ge=2.0,
        le=10.0,
    )
    sigma_max_m: float = opt(
        0.3,
        "above this σ the position is UNKNOWN (halt); at most 0.5 m (beyond, a lawn edge "
        "cannot be told apart from the neighbour's)",
        gt=0.0,
        le=0.5,
    )
    soft_persist: int = opt(
        3,
        "consecutive samples a soft OUTSIDE must last to halt; at most 10 (0.1 s of decisions)",
        ge=1,
        le=10,
    )
    hard_margin_m: float = opt(
        0.1,
        "beyond this far outside (minus kσ) halt at once; at most 0.3 m (the soft band is "
        "for noise at the edge, not for leaving the lawn)",
        ge=0.0,
        le=0.3,
    )


# -------------------------------------------------------------------------- runtime sections


@dataclass(frozen=True)
class MapConfig:
    """The lawn map (boundary, keep-out zones, landmarks)."""

    path: Path = opt(Path("/var/lib/mowerhw/lawn.json"), "map file written by teach, read by mow")
    max_bytes: int = opt(
        64 << 20, "a bigger map file is refused (MAP_INVALID)", ge=1 << 16, le=1 << 30
    )
    load_timeout_s: float = opt(
        10.0, "a map load (in its own process) that takes longer is refused", gt=0.0, le=120.0
    )


@dataclass(frozen=True)
class RuntimeConfig:
    """The daemon."""

    mode: str = opt("idle", "start-up mode", choices=("idle", "teach", "mow"))
    control_socket: Path = opt(Path("/run/mowerhw/control.sock"), "control socket path")
    log_level: str = opt("INFO", "log level", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    socket_mode: int = opt(
        0o660,
        "permissions of the control socket: owner and group only (at most 0770; anyone who "
        "can open it may ask for the status)",
        ge=0,
        le=0o770,
        octal=True,
    )
    control_group: str | None = opt(
        None,
        "group whose members may change the mode and write maps over the control socket "
        "(besides the service's user and root); null: nobody else",
    )
    control_max_clients: int = opt(8, "control socket connections served at once", ge=1, le=64)
    control_idle_s: float = opt(
        60.0, "a control connection without a complete request this long is closed", gt=0.0
    )
    control_requests_per_s: float = opt(
        20.0,
        "requests a control client may send per second (all together: four times this)",
        gt=0.0,
        le=1000.0,
    )
    auto_finish_teach: bool = opt(
        True, "finish teach by itself when the mower stops back at its start after a loop"
    )
    frontend_process: bool = opt(
        True,
        "track camera frames in a process of its own (off the GIL of the loop that reads the "
        "IMU and decides); false: on a thread of the estimation process",
    )
    frontend_hang_s: float = opt(
        300.0,
        "the front-end process answers no frame this long (tracking takes milliseconds, a "
        "search for the pose seconds, tens of seconds on a large map and a slow computer): "
        "it is hung; it is killed and the daemon ends with exit status 1, for systemd to "
        "restart it (without its tracks the localizer halts the deck long before). One that "
        "computes nothing for 10 s with a frame in hand (blocked, stopped, deadlocked) is "
        "hung at once",
        ge=10.0,
        le=3600.0,
    )
    map_check_period_s: float = opt(
        0.1, "how often mow mode checks the map file for changes", gt=0.0, le=10.0
    )
    pose_file: Path = opt(
        Path("/run/mowerhw/pose.json"),
        "where mow mode keeps its newest localized pose (10 Hz), so a restarted daemon "
        "resumes from it (if under 2 min old) instead of the dock",
    )
    fault_injection: bool = opt(
        False, "accept the control socket's `fault` command (test bench only)"
    )


@dataclass(frozen=True)
class SafetyConfig:
    """Lift, tilt, rollover and collision: the supervisor halts on each (docs/design.md §8).
    Tilt and rollover come from the IMU's gravity vector, lift and collision from its
    acceleration and from the mower controller's own switches (CAN, ``safety.switches_pgn``)."""

    tilt_limit_deg: float = opt(
        35.0, "halt (TILTED) when tilted more than this for tilt_debounce_s", gt=0.0, le=90.0
    )
    tilt_debounce_s: float = opt(1.0, "how long a tilt must last to halt", ge=0.0, le=10.0)
    rollover_deg: float = opt(
        60.0, "halt (TILTED) at once when tilted more than this (rolling over)", gt=0.0, le=180.0
    )
    lift_accel_mps2: float = opt(
        3.0,
        "halt (LIFTED) when the vertical specific force exceeds gravity by this for "
        "lift_debounce_s (being lifted)",
        gt=0.0,
    )
    lift_debounce_s: float = opt(0.1, "how long a lift must last to halt", ge=0.0, le=5.0)
    bump_accel_mps2: float = opt(
        25.0, "halt (COLLISION) at once on a horizontal acceleration above this", gt=0.0
    )
    clear_s: float = opt(
        2.0, "a lift, tilt or collision is latched until clear for this long", ge=0.0, le=60.0
    )
    filter_s: float = opt(
        0.05, "time constant of the low-pass on the acceleration for lift", ge=0.0, le=1.0
    )
    tilt_filter_s: float = opt(
        0.3,
        "time constant of the low-pass giving the gravity direction for tilt (a jolt must "
        "not look like rolling over)",
        ge=0.0,
        le=5.0,
    )
    switches_pgn: int = opt(
        0xFF11, "PGN of the mower controller's lift/bump/stop switch frame", ge=0xFF00, le=0xFFFF
    )
    switches_address: int | None = opt(
        None,
        "accept the switch frame only from this source address, the mower controller's "
        "(null: any; Proprietary B PGNs are each maker's own, and a tractor's bus carries "
        "several from several ECUs)",
        ge=0,
        le=253,
    )
    specific_force_stale_s: float = opt(
        0.25,
        "while mowing, halt (SENSOR_STALE) when no specific force has come from the IMU for "
        "this long: lift and tilt are judged by it (an IMU that sends no acceleration, e.g. "
        "imu.configure_sensor false with gyro-only outputs, cannot mow)",
        gt=0.0,
        le=2.0,
    )


@dataclass(frozen=True)
class SupervisorConfig:
    """The permit supervisor: the process that alone writes the permit frames."""

    enabled: bool = opt(
        True,
        "run estimation in a child process and let a small supervisor process own the CAN "
        "output (false: one process, for debugging only)",
    )
    lease_s: float = opt(
        0.08,
        "a permit from the estimation side is good for this long; it is renewed with every "
        "decision (each IMU sample), so a late, stalled or dead estimator halts the deck after it",
        ge=0.05,
        le=0.1,
    )
    settle_s: float = opt(
        1.0,
        "after a lease ran out, leases must come in time this long before the deck may run "
        "again (no flicker from an estimator that keeps being late)",
        ge=0.0,
        le=30.0,
    )
    can_reopen_max_backoff_s: float = opt(
        2.0, "a failed CAN bus is reopened with backoff up to this", gt=0.0, le=60.0
    )
    can_down_restart_s: float = opt(
        30.0,
        "CAN unusable this long: stop feeding systemd's watchdog (the service is restarted)",
        gt=0.0,
        le=3600.0,
    )
    child_start_timeout_s: float = opt(
        60.0, "the estimation process must say it is running within this", gt=0.0, le=600.0
    )
    child_hang_s: float = opt(
        15.0,
        "the estimation process, once it has sent its first lease, sends nothing this long "
        "(it renews the lease at least every 0.1 s): it is hung; the supervisor kills it and "
        "ends the service with exit status 1, for systemd to restart it (the deck halted long "
        "before, when the lease ran out)",
        ge=1.0,
        le=600.0,
    )
    nice: int = opt(
        -10,
        "scheduling priority of the supervisor (lower runs first: a loaded computer must not "
        "delay a halt); needs CAP_SYS_NICE or systemd's Nice=, else it stays as started",
        ge=-20,
        le=19,
    )
    realtime_priority: int = opt(
        10,
        "SCHED_FIFO priority of the supervisor (it sleeps between frames, so it takes little; "
        "a loaded computer then cannot delay it); 0: normal scheduling. Needs "
        "CAP_SYS_NICE or systemd's CPUSchedulingPolicy=fifo; its children never inherit it",
        ge=0,
        le=50,
    )
    estimation_nice: int = opt(
        -5,
        "scheduling priority of the estimation process (behind the supervisor, ahead of "
        "ordinary work: it must renew the lease in time)",
        ge=-20,
        le=19,
    )


@dataclass(frozen=True)
class WebConfig:
    """The status page (``mowerhw.web``, issue 19): a process of its own that reads the
    daemon through its control socket, so a slow or absent browser never slows the runtime."""

    enabled: bool = opt(False, "serve the status page (the supervisor starts its process)")
    host: str = opt(
        "127.0.0.1",
        "address the page binds to (localhost by default; 0.0.0.0 serves every interface: "
        "the status is then readable by anyone who reaches it, controls still need the token)",
        nonempty=True,
    )
    port: int = opt(8080, "TCP port of the page (0: any free port, logged)", ge=0, le=65535)
    token_file: Path = opt(
        Path("/var/lib/mowerhw/web-token"),
        "the controls' token: created (mode 0600) with a random token if missing; a systemd "
        "credential named web-token ($CREDENTIALS_DIRECTORY) is used instead when present",
    )
    rate_hz: float = opt(
        10.0, "how often the page is updated while a browser is connected", ge=1.0, le=20.0
    )
    max_clients: int = opt(16, "browsers served at once", ge=1, le=256)
    trajectory_points: int = opt(
        36000, "trajectory points the page keeps (5 a second: 2 h by default)", ge=100, le=10**6
    )
    foxglove: bool = opt(
        False,
        "also serve the pose and state topics of the recordings live with the Foxglove SDK's "
        "WebSocket server (for Foxglove's app, with the layout used for recordings)",
    )
    foxglove_host: str = opt("127.0.0.1", "address of the Foxglove live server", nonempty=True)
    foxglove_port: int = opt(8765, "port of the Foxglove live server (0: any)", ge=0, le=65535)
    nice: int = opt(
        10,
        "scheduling priority of the page's process (after everything that mows)",
        ge=-20,
        le=19,
    )


@dataclass(frozen=True)
class Config:
    """The whole runtime configuration."""

    imu: ImuConfig = section(ImuConfig, "VN-100 IMU")
    can: CanConfig = section(CanConfig, "CAN bus")
    speed: SpeedConfig = section(SpeedConfig, "ground speed")
    camera: CameraConfig = section(CameraConfig, "omnidirectional camera")
    frontend: FrontendConfig = section(FrontendConfig, "vision front end")
    permit: PermitConfig = section(PermitConfig, "permit / halt output")
    teach: TeachConfig = section(TeachConfig, "teach-phase estimators")
    mow: MowConfig = section(MowConfig, "mow-phase localizer")
    containment: ContainmentConfig = section(ContainmentConfig, "containment decision")
    map: MapConfig = section(MapConfig, "lawn map")
    runtime: RuntimeConfig = section(RuntimeConfig, "daemon")
    supervisor: SupervisorConfig = section(SupervisorConfig, "permit supervisor")
    safety: SafetyConfig = section(SafetyConfig, "lift, tilt, rollover, collision")
    web: WebConfig = section(WebConfig, "status page")
    source: Path | None = field(default=None, compare=False, metadata={"internal": True})


# ------------------------------------------------------------------------------ validation


def _fmt(value: Any) -> str:
    """A value as a message shows it (at most 80 characters)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 10**18:
        return "a number too large"
    if isinstance(value, str):
        text = repr(value)
    elif isinstance(value, float) and value.is_integer():
        text = str(int(value)) if abs(value) < 1e15 else repr(value)
    elif isinstance(value, list | dict):
        text = reprlib.repr(value)
    else:
        text = str(value)
    return text if len(text) <= 80 else text[:77] + "..."


_INT_TEXT = re.compile(r"[+-]?(0[oO][0-7]+|0[xX][0-9a-fA-F]+|[0-9]{1,18})")
_FLOAT_TEXT = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?")


def _check_scalar(tp: Any, value: Any, key: str, meta: dict, base: Path | None) -> Any:
    """Convert and check one scalar; raise ValueError(message) on a bad value."""
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{key}: {_fmt(value)} is not true or false")
        return value
    if tp is int:
        if isinstance(value, str) and _INT_TEXT.match(value.strip()):
            value = int(value.strip(), 0)  # "0o660", "0x90" (YAML 1.2 spellings)
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer() and abs(value) < 2**63:
                value = int(value)
            else:
                raise ValueError(f"{key}: {_fmt(value)} is not a whole number")
    elif tp is float:
        if isinstance(value, str) and _FLOAT_TEXT.match(value.strip()):
            value = float(value)  # "1e-3": YAML 1.1 reads it as a string
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{key}: {_fmt(value)} is not a number")
        try:
            value = float(value)
        except OverflowError:
            raise ValueError(f"{key}: {_fmt(value)} is not a finite number") from None
        if not math.isfinite(value):
            raise ValueError(f"{key}: {_fmt(value)} is not a finite number")
    elif tp is str:
        if not isinstance(value, str):
            raise ValueError(f"{key}: {_fmt(value)} is not a string")
        if meta.get("nonempty") and not value.strip():
            raise ValueError(f"{key}: must not be empty")
    elif tp is Path:
        if not isinstance(value, str | Path) or not str(value).strip():
            raise ValueError(f"{key}: {_fmt(value)} is not a path")
        text = str(value)
        if "\0" in text or len(text) > 4095 or any(len(part) > 255 for part in text.split("/")):
            raise ValueError(
                f"{key}: {_fmt(value)} is not a usable path (a NUL byte, or longer than the "
                "system allows: 4095 in all, 255 per name)"
            )
        value = Path(value).expanduser()
        if base is not None and not value.is_absolute():
            value = base / value
        if meta.get("exists") and not value.exists():
            raise ValueError(f"{key}: {str(value)!r} does not exist")
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        allowed = ", ".join(str(c) for c in choices)
        raise ValueError(f"{key}: {_fmt(value)} is not one of {allowed}")
    for rule, ok, words in (
        ("ge", lambda v, b: v >= b, "at least"),
        ("gt", lambda v, b: v > b, "greater than"),
        ("le", lambda v, b: v <= b, "at most"),
        ("lt", lambda v, b: v < b, "less than"),
    ):
        if rule in meta and not ok(value, meta[rule]):
            shown = (lambda v: f"{v:#o}") if meta.get("octal") else _fmt
            raise ValueError(
                f"{key}: {shown(value)} is out of range: must be {words} {shown(meta[rule])}"
            )
    return value


def _check_value(tp: Any, value: Any, key: str, meta: dict, base: Path | None) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _check_value(args[0], value, key, meta, base)
    if origin is tuple and typing.get_args(tp)[1:] == (Ellipsis,):  # a list of names
        item = typing.get_args(tp)[0]
        if not isinstance(value, list | tuple) or len(value) > 64:
            raise ValueError(f"{key}: {_fmt(value)} must be a list (at most 64 entries)")
        names = tuple(
            _check_scalar(item, v, f"{key}[{i}]", meta, base) for i, v in enumerate(value)
        )
        if len(set(names)) != len(names):
            raise ValueError(f"{key}: {list(names)} names an entry twice")
        return names
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list | tuple) or len(value) != len(args):
            raise ValueError(f"{key}: {_fmt(value)} must be a list of {len(args)} numbers")
        items = tuple(
            _check_scalar(a, v, f"{key}[{i}]", {}, base)
            for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
        if meta.get("unit_norm"):
            norm = math.sqrt(sum(v * v for v in items))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(
                    f"{key}: {list(items)} is not a unit quaternion (w, x, y, z): norm {norm:.4f}"
                )
            items = tuple(v / norm for v in items)
        return items
    return _check_scalar(tp, value, key, meta, base)


def _build(cls: type, raw: Any, prefix: str, base: Path | None, problems: list[str]) -> Any:
    where = prefix or "top level"
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        problems.append(f"{where}: expected a mapping of keys, got {_fmt(raw)}")
        return cls()
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    values: dict[str, Any] = {}
    for key, value in raw.items():
        name = str(key)
        full = f"{prefix}.{name}" if prefix else name
        if name not in fields:
            close = difflib.get_close_matches(name, list(fields), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            allowed = ", ".join(fields)
            problems.append(f"{full}: unknown key{hint}; allowed keys: {allowed}")
            continue
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            values[name] = _build(tp, value, full, base, problems)
            continue
        try:
            values[name] = _check_value(tp, value, full, dict(fields[name].metadata), base)
        except ValueError as exc:
            problems.append(str(exc))
    for name, f in fields.items():
        if name in values:
            continue
        if dataclasses.is_dataclass(hints[name]):  # an absent section: all its defaults
            values[name] = _build(
                hints[name], {}, f"{prefix}.{name}" if prefix else name, base, problems
            )
            continue
        # A relative default names a file shipped in configs/ (e.g. the Table I camera).
        default = f.default
        if hints[name] is Path and isinstance(default, Path) and not default.is_absolute():
            try:
                values[name] = _check_value(
                    Path, str(default), f"{prefix}.{name}", dict(f.metadata), shipped_configs_dir()
                )
            except ValueError as exc:
                problems.append(str(exc))
    return cls(**values)


def config_from_dict(raw: Any, base_dir: Path | None = None, source: str | None = None) -> Config:
    """Validate a parsed YAML document; raise :class:`ConfigError` naming every bad key."""
    problems: list[str] = []
    cfg = _build(Config, raw, "", base_dir, problems)
    if not problems:
        problems.extend(_cross_checks(cfg))
    if problems:
        raise ConfigError(problems, source)
    cfg = _resolve_camera_rotation(cfg)
    cfg = _resolve_imu_noise(cfg)
    return dataclasses.replace(cfg, source=Path(source) if source else None)


def gyro_scale_sigma(imu: ImuConfig) -> float:
    """The prior σ of the gyro's yaw-rate scale error: the config's, else its grade's (never
    below 0.5 %: no unit is calibrated better in the field)."""
    from mowerhw.imu.grades import IMU_GRADES

    given = imu.gyro_scale_error
    return max(IMU_GRADES[imu.grade].scale_factor if given is None else given, 0.005)


#: the teach's own estimate of the yaw-rate scale is off by about this much (0.025 % rms
#: over 200 pixel-level teaches of a gyro with no scale error, stop 65)
TAUGHT_SCALE_MIN_SIGMA = 0.0005


def gyro_scale_drift(imu: ImuConfig) -> float:
    """The prior σ of the yaw-rate scale error when a map carries the scale its teach learnt:
    how much the unit's scale changes from one run to another (the config's, else its
    grade's), at least :data:`TAUGHT_SCALE_MIN_SIGMA` (what the teach's estimate misses)."""
    from mowerhw.imu.grades import IMU_GRADES

    given = imu.gyro_scale_drift
    drift = IMU_GRADES[imu.grade].scale_drift if given is None else given
    return max(drift, TAUGHT_SCALE_MIN_SIGMA)


def imu_noise(imu: ImuConfig) -> tuple[float, float, float]:
    """The gyro's Allan figures (noise density, bias instability, random walk): the config's
    own where given, else its grade's (:data:`mowerhw.imu.grades.IMU_GRADES`)."""
    from mowerhw.imu.grades import IMU_GRADES

    g = IMU_GRADES[imu.grade]
    return (
        g.noise_density if imu.gyro_noise_density is None else imu.gyro_noise_density,
        g.bias_instability if imu.gyro_bias_instability is None else imu.gyro_bias_instability,
        g.rate_random_walk if imu.gyro_random_walk is None else imu.gyro_random_walk,
    )


def stale_limits_s(cfg: Config | None = None) -> dict[str, float]:
    """Per sensor stream, how long without usable data makes it stale: the sensor sections'
    ``stale_after_s`` (defaults without a config). Only the permit gate judges staleness;
    the localizer reads the same limits to know when to stop trusting a held speed."""
    imu, speed, camera = (
        (ImuConfig(), SpeedConfig(), CameraConfig())
        if cfg is None
        else (cfg.imu, cfg.speed, cfg.camera)
    )
    return {
        "imu": imu.stale_after_s,
        "speed": speed.stale_after_s,
        "camera": camera.stale_after_s,
    }


def with_imu_noise(section: Any, imu: ImuConfig | None = None) -> Any:
    """A teach or mow section with its null gyro process noise filled in from ``imu`` (the
    defaults' VN-100 when not given): the one place the estimators' gyro noise is decided."""
    taught_missing = isinstance(section, MowConfig) and section.gyro_scale_sigma_taught is None
    resolved = None not in (section.gyro_noise, section.gyro_bias_walk, section.gyro_scale_sigma)
    if resolved and not taught_missing:
        return section
    from mowerhw.imu.grades import gyro_process_noise

    imu = imu or ImuConfig()
    white, walk = gyro_process_noise(*imu_noise(imu))
    out = dataclasses.replace(
        section,
        gyro_noise=white if section.gyro_noise is None else section.gyro_noise,
        gyro_bias_walk=walk if section.gyro_bias_walk is None else section.gyro_bias_walk,
        gyro_scale_sigma=gyro_scale_sigma(imu)
        if section.gyro_scale_sigma is None
        else section.gyro_scale_sigma,
    )
    if taught_missing:
        out = dataclasses.replace(out, gyro_scale_sigma_taught=gyro_scale_drift(imu))
    return out


def _resolve_imu_noise(cfg: Config) -> Config:
    """The config with the imu figures and the estimators' gyro noise all numbers."""
    n, b, k = imu_noise(cfg.imu)
    imu = dataclasses.replace(
        cfg.imu,
        gyro_noise_density=n,
        gyro_bias_instability=b,
        gyro_random_walk=k,
        gyro_scale_error=gyro_scale_sigma(cfg.imu),
        gyro_scale_drift=gyro_scale_drift(cfg.imu),
    )
    contact = tuple(float(v) for v in cfg.speed.contact_point_m)
    teach = dataclasses.replace(with_imu_noise(cfg.teach, imu), speed_contact_m=contact)
    mow = dataclasses.replace(with_imu_noise(cfg.mow, imu), speed_contact_m=contact)
    return dataclasses.replace(cfg, imu=imu, teach=teach, mow=mow)


def _resolve_camera_rotation(cfg: Config) -> Config:
    """The config with ``camera.q_bc`` set from its source (see :func:`camera_rotation`), so
    everything downstream reads one value."""
    t_cam_imu = None
    if cfg.camera.extrinsics == "calibration" and cfg.camera.calibration.exists():
        from mowerhw.camera import load_camchain

        t_cam_imu = load_camchain(cfg.camera.calibration, cfg.camera.camchain_key).T_cam_imu
    q_bc = camera_rotation(cfg, t_cam_imu)
    return dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, q_bc=q_bc))


#: CAN interfaces with no mower on them: the only ones ``runtime.fault_injection`` may use
BENCH_CAN_INTERFACES = ("virtual", "udp_multicast")


def _runtime_checks(cfg: Config) -> list[str]:
    """The daemon's files and sockets: no two the same, nothing world-writable, no test
    hooks on a real mower."""
    problems = []
    rt = cfg.runtime
    if rt.socket_mode & 0o007:
        problems.append(
            f"runtime.socket_mode: {rt.socket_mode:#o} lets every user on the computer send "
            "commands; at most 0770 (owner and group)"
        )
    if rt.fault_injection and cfg.can.interface not in BENCH_CAN_INTERFACES:
        problems.append(
            f"runtime.fault_injection: only for the test bench (can.interface "
            f"{' or '.join(BENCH_CAN_INTERFACES)}), not with can.interface "
            f"{cfg.can.interface!r}: a real mower must not take injected faults"
        )
    paths = {
        "map.path": cfg.map.path,
        "map picture (map.path with .png)": cfg.map.path.with_suffix(".png"),
        "map backup (map.path + .bak)": cfg.map.path.with_name(cfg.map.path.name + ".bak"),
        "runtime.control_socket": rt.control_socket,
        "control socket lock (runtime.control_socket + .lock)": Path(
            str(rt.control_socket) + ".lock"
        ),
        "runtime.pose_file": rt.pose_file,
        "the permit supervisor's status socket (runtime.control_socket + .supervisor)": (
            supervisor_socket(rt.control_socket)
        ),
    }
    seen: dict[Path, str] = {}
    for name, path in paths.items():
        key = Path(os.path.realpath(path))
        if key in seen:
            problems.append(f"{name}: {path} is also {seen[key]}; each needs its own file")
        seen.setdefault(key, name)
    sock = rt.control_socket
    mode = _file_mode(sock)
    if mode is not None and not stat.S_ISSOCK(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "a file that is not a socket"
        problems.append(
            f"runtime.control_socket: {sock} is {kind}; the daemon would have to delete it"
        )
    for name, path in (("map.path", cfg.map.path), ("runtime.pose_file", rt.pose_file)):
        mode = _file_mode(path)
        if mode is not None and stat.S_ISDIR(mode):
            problems.append(f"{name}: {path} is a directory, not a file")
    return problems


def _file_mode(path: Path) -> int | None:
    """``st_mode`` of ``path``, None if there is nothing there (or it cannot be seen)."""
    try:
        return os.stat(path).st_mode
    except (OSError, ValueError):
        return None


def _cross_checks(cfg: Config) -> list[str]:
    """Rules between keys, and files the config points at."""
    problems = _runtime_checks(cfg)
    if (
        cfg.imu.driver == "vn100"
        and cfg.imu.output == "ascii"
        and cfg.imu.rate_hz >= 100
        and cfg.imu.baudrate <= 115200
    ):
        problems.append(
            f"imu.baudrate: {cfg.imu.baudrate} is too slow for {cfg.imu.rate_hz} Hz ASCII output "
            "(docs/design.md §7); use 230400 or more, or imu.output: binary"
        )
    own = cfg.can.source_address
    for key, other in (
        ("speed.sensor_address", cfg.speed.sensor_address),
        ("safety.switches_address", cfg.safety.switches_address),
    ):
        if other == own:
            problems.append(
                f"{key}: 0x{other:02X} is can.source_address, this ECU's own: its frames would "
                "be taken for our own and dropped (each ECU on the bus needs its own address)"
            )
    for name, limit, key, rate in (
        ("imu", cfg.imu.stale_after_s, "imu.rate_hz", float(cfg.imu.rate_hz)),
        ("camera", cfg.camera.stale_after_s, cfg.camera.rate_key(), cfg.camera.camera_fps()),
    ):
        if limit < 2.0 / rate:  # one late or lost sample must not halt the deck
            problems.append(
                f"{name}.stale_after_s: {limit:g} s is under two sample periods at {key} "
                f"{rate:g} ({2.0 / rate:g} s): every late sample would halt; raise it to at "
                f"least {2.0 / rate:g} s, or the rate"
            )
    cam = cfg.camera
    if cam.device_fps is not None and cam.device_fps < cam.fps:
        problems.append(
            f"camera.device_fps: {cam.device_fps:g} is under camera.fps {cam.fps:g}: the front "
            "end cannot track more frames than the camera delivers; set device_fps at or "
            "above fps, or null (the camera at fps)"
        )
    fe = cfg.frontend
    if fe.klt_base_level > fe.klt_levels:
        problems.append(
            f"frontend.klt_base_level: {fe.klt_base_level} is above frontend.klt_levels "
            f"({fe.klt_levels}); Lucas–Kanade tracks from a level of its own pyramid, 0 to "
            f"{fe.klt_levels}"
        )
    if fe.klt_base_level > 0 and not fe.subpixel:
        problems.append(
            f"frontend.klt_base_level: {fe.klt_base_level} needs frontend.subpixel: true "
            "(tracks from a smaller image are found again at full size by the refinement); "
            "set klt_base_level: 0 to track at full size without it"
        )
    cal = cfg.camera.calibration
    if cal.exists():
        from mowerhw.camera import CameraCalibrationError, load_camchain

        try:
            cam = load_camchain(cal, cfg.camera.camchain_key)
        except CameraCalibrationError as exc:
            problems.append(f"camera.calibration: {exc}")
        else:
            if (cam.width, cam.height) != (cfg.camera.width, cfg.camera.height):
                problems.append(
                    f"camera.width/height: {cfg.camera.width}x{cfg.camera.height} does not match "
                    f"the calibration's resolution {cam.width}x{cam.height} ({cal})"
                )
            try:
                camera_rotation(cfg, cam.T_cam_imu)
            except ValueError as exc:
                problems.append(str(exc))
    return problems


def camera_rotation(cfg: Config, t_cam_imu: Any = None) -> Quat:
    """The camera's rotation in the body frame, ``q_bc`` (w, x, y, z), from its one source
    (``camera.extrinsics``): the calibration's ``T_cam_imu`` (p_cam = T p_imu) composed with
    ``imu.q_bi``, or ``camera.q_bc``. Raises ValueError naming both on a conflict."""
    import numpy as np

    from mowerhw.common.geometry import quat_multiply, quat_to_rotmat, rotmat_to_quat

    c = cfg.camera
    given = c.q_bc
    if c.extrinsics == "config" or t_cam_imu is None:
        return given if given is not None else DEFAULT_Q_BC
    r_ci = np.asarray(t_cam_imu, dtype=np.float64)[:3, :3]
    q_ic = rotmat_to_quat(r_ci.T)
    q = quat_multiply(np.asarray(cfg.imu.q_bi, dtype=np.float64), q_ic)
    q = q if q[0] >= 0 else -q
    derived: Quat = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    if given is not None:
        r_diff = quat_to_rotmat(np.asarray(given)).T @ quat_to_rotmat(q)
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r_diff) - 1.0) / 2.0))))
        if angle > EXTRINSICS_TOLERANCE_DEG:
            shown = ", ".join(f"{v:.4f}" for v in derived)
            raise ValueError(
                f"camera.q_bc: {list(given)} differs by {angle:.1f}° from the camera rotation "
                f"the calibration gives ({shown}: T_cam_imu of {c.camchain_key} in "
                f"{c.calibration} with imu.q_bi); remove camera.q_bc to use the calibration, "
                "or set camera.extrinsics: config to use camera.q_bc"
            )
    return derived


#: a config file is at most this big (bytes)
MAX_CONFIG_BYTES = 1 << 20


def load_config(path: str | Path) -> Config:
    """Load and validate a YAML config file (at most :data:`MAX_CONFIG_BYTES`)."""
    path = Path(path)
    try:
        if path.exists() and not path.is_file():
            raise ConfigError(["not a regular file"], str(path))
        with path.open("rb") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
        if len(data) > MAX_CONFIG_BYTES:
            raise ConfigError([f"larger than {MAX_CONFIG_BYTES} bytes"], str(path))
        text = data.decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(["file not found"], str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError([f"cannot read the file: {exc}"], str(path)) from None
    raw = parse_config_yaml(text, str(path))
    return config_from_dict(raw, base_dir=path.resolve().parent, source=str(path))


def parse_config_yaml(text: str, source: str) -> Any:
    """The YAML document of a config, read with limits (no aliases, bounded depth, no key
    twice: :mod:`mowerhw.common.yamlfile`); :class:`ConfigError` naming the problem."""
    try:
        return load_yaml(text)
    except RecursionError:
        raise ConfigError(["nested too deeply"], source) from None
    except (ValueError, OverflowError) as exc:  # e.g. a number of thousands of digits
        raise ConfigError([f"not a usable YAML value: {str(exc)[:120]}"], source) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError([f"not valid YAML{where}: {problem}"], source) from None


def default_config() -> Config:
    """All defaults (relative default paths name files shipped in ``configs/``)."""
    return config_from_dict({})


def shipped_configs_dir() -> Path:
    """The ``configs/`` folder of the source tree (or of an installed share location)."""
    here = Path(__file__).resolve().parent.parent / "configs"
    return here


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Plain data (for YAML/JSON dumps and recordings)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        if f.metadata.get("internal"):
            continue
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = config_to_dict(value)
        elif isinstance(value, Path):
            out[f.name] = str(value)
        elif isinstance(value, tuple):
            out[f.name] = list(value)
        else:
            out[f.name] = value
    return out


def describe_schema(cls: type = Config, prefix: str = "") -> list[str]:
    """Human-readable list of every key with its default and doc (``mowerhw config schema``)."""
    lines = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.metadata.get("internal"):
            continue
        key = f"{prefix}.{f.name}" if prefix else f.name
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            lines.append(f"{key}:  # {f.metadata.get('doc', '')}")
            lines.extend(describe_schema(tp, key))
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        rules = {k: v for k, v in f.metadata.items() if k != "doc"}
        extra = ""
        if "choices" in rules:
            extra = " [one of " + ", ".join(str(c) for c in rules["choices"]) + "]"
        lines.append(
            f"  {key} = {_fmt(default) if default is not None else 'null'}  "
            f"# {f.metadata.get('doc', '')}{extra}"
        )
    return lines
