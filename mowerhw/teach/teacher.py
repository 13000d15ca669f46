"""The teach phase as one pure object (the API of the teach issue).

    teacher = Teacher(config)
    teacher.imu(t, gyro_xyz); teacher.speed(t, v); teacher.bearings(t, ids, unit_xyz)
    result = teacher.finish()

It wires the pieces of paper §II–III together:

1. **Standstill** (from the first sample until the ground speed leaves 0): the gyro is
   averaged into its bias; bearings are averaged into keyframe 0's anchor bearings. The
   world frame is the body frame at the first sample (docs/design.md §3).
2. **Driving**: at IMU rate the body motion moves the EKF (eq. 14) and every landmark
   observer (eq. 2/4). At camera rate each seen landmark gets a direction update and, when
   the geometry allows, a depth pseudo-measurement (eqs 3, 5, 7); then the robot-centric
   EKF is updated with the landmarks anchored in the current keyframe (eqs 16–18).
3. **Keyframes**: when too few landmarks anchored in the current keyframe remain in view
   (or after ``keyframe_baseline_m``), the current pose becomes a new keyframe (eq. 19).
4. **Outputs**: the world pose at every IMU sample and every landmark's world position
   (eq. 20); at ``finish`` the loop is closed (the pose at the end measured against the
   landmarks mapped from the first keyframe) and the error spread over the trajectory and
   the landmarks; the ground track becomes the boundary.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mowerhw.camera import CameraModel
from mowerhw.common.geometry import (
    IDENTITY_QUAT,
    quat_conjugate,
    quat_exp,
    quat_multiply,
    quat_rotate,
    quat_to_rotmat,
    quat_to_yaw,
    rotmat_log,
)
from mowerhw.common.magnetic import CompassReference
from mowerhw.config import Config, TeachConfig, with_imu_noise
from mowerhw.estimation.compass import CompassCalibration
from mowerhw.estimation.odometry import BodyMotion, SpeedTrack, camera_velocity
from mowerhw.estimation.standstill import StandstillCalibrator
from mowerhw.teach.boundary import BoundaryError, boundary_from_path
from mowerhw.teach.depth import depth_pseudo_measurement
from mowerhw.teach.ekf import EkfNoise, RobotCentricEKF
from mowerhw.teach.keyframes import (
    Keyframe,
    compose,
    landmark_world_covariance,
    landmarks_in_world,
    world_pose_covariance,
)
from mowerhw.teach.marks import (
    MARK_KINDS,
    TaughtZone,
    TeachMark,
    check_mark,
    dock_index,
    zones_from_marks,
)
from mowerhw.teach.observer import LandmarkObservers
from mowerhw.teach.smoother import SmootherProblem, preintegrate_segments, smooth

log = logging.getLogger(__name__)
EPI_MIN_ANGLE_DEG = 10.0
FloatArray = NDArray[np.float64]


def _anchor_pose_variance(anchor_cov: FloatArray, depth: FloatArray) -> FloatArray:
    """Bearing variance (rad²) an anchor pose's uncertainty adds: rotation, and position over
    the landmark's distance."""
    rot = np.trace(anchor_cov[:, 3:, 3:], axis1=1, axis2=2) / 3.0
    pos = np.trace(anchor_cov[:, :3, :3], axis1=1, axis2=2) / 3.0
    var: FloatArray = rot + pos / np.maximum(depth, 0.1) ** 2
    return var


def _landmark_rms(problem: Any, r_wb: FloatArray, t_wb: FloatArray, lms: FloatArray) -> FloatArray:
    """RMS angle (rad) between each landmark's observed bearings and where the final poses
    and position put it (NaN for a landmark without observations)."""
    fi, li = problem.obs_frame, problem.obs_landmark
    ell = np.einsum("nji,nj->ni", r_wb[fi], lms[li] - t_wb[fi])  # R_wbᵀ (L − t)
    ell /= np.linalg.norm(ell, axis=1, keepdims=True)
    ang = np.arccos(np.clip(np.einsum("ni,ni->n", ell, problem.obs_bearing), -1.0, 1.0))
    n = lms.shape[0]
    sq = np.bincount(li, weights=ang**2, minlength=n)
    cnt = np.bincount(li, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(sq / cnt)


def _outliers(rms: FloatArray, factor: float) -> NDArray[np.bool_]:
    """Which residuals exceed ``factor`` times the median (with at least 8 to judge by)."""
    fin = np.isfinite(rms)
    if fin.sum() < 8:
        return np.zeros(rms.shape, bool)
    return fin & (rms > factor * float(np.median(rms[fin])))


def _inconsistent(landmarks: dict[int, dict[str, Any]], factor: float) -> list[int]:
    """Landmarks whose bearings disagree with their own position ``factor`` times more than
    the typical landmark's do: not a fixed point (a corner formed by one thing passing in
    front of another) or two points taken for one (a wrong re-identification)."""
    ids = [i for i, r in landmarks.items() if not np.isnan(r.get("rms", np.nan))]
    rms = np.array([landmarks[i]["rms"] for i in ids])
    fin = np.isfinite(rms)
    if fin.sum() < 8:
        return [i for i, v in zip(ids, rms, strict=True) if not np.isfinite(v)]
    typical = float(np.median(rms[fin]))
    return [i for i, v in zip(ids, rms, strict=True) if not v <= factor * typical]


def _well_located(cov: FloatArray, sigma_max: float) -> bool:
    """True if a landmark's largest position σ is finite and at most ``sigma_max``."""
    if not np.all(np.isfinite(cov)):
        return False
    eig = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    # a covariance that is not positive semi-definite is numerically unknown, not small
    return bool(eig[0] >= -1e-9 and eig[-1] <= sigma_max**2)


class TeachError(RuntimeError):
    """The teach run cannot produce a map (the message says why and what to do)."""


@dataclass
class LoopClosure:
    """What closing the loop measured and did."""

    applied: bool
    reason: str
    translation_m: float = 0.0
    rotation_rad: float = 0.0
    landmarks_used: int = 0
    residual_rms_rad: float = float("nan")
    #: the bearings' σ the landmark covariances are taken at: their long-run σ along a track
    #: (:func:`mowerhw.teach.smoother.bearing_variance_factor`), not the configured one
    bearing_sigma_long_run_rad: float = float("nan")


@dataclass
class TeachResult:
    """Everything the teach run produced (world frame = body frame at the first sample)."""

    boundary: FloatArray  # (M, 2) world xy, counter-clockwise, not repeating the first point
    landmarks: dict[int, FloatArray]  # id → xyz
    landmark_covariances: dict[int, FloatArray]  # id → (3, 3)
    trajectory: FloatArray  # (K, 8): t, x, y, z, qw, qx, qy, qz (after loop closure)
    trajectory_no_closure: FloatArray  # (K, 8) before loop closure
    closure: LoopClosure
    keyframes: list[Keyframe]
    diagnostics: dict[str, Any] = field(default_factory=dict)
    descriptors: dict[int, bytes] = field(default_factory=dict)  # id → ORB descriptor(s)
    landmark_keyframes: dict[int, int] = field(default_factory=dict)  # id → keyframe first seen
    camera: Any = None  # the calibration the map was made with (OmniRadtanCamera)
    zones: list[TaughtZone] = field(default_factory=list)  # marked stretches (teach/marks.py)
    dock_index: int | None = None  # the trajectory sample the operator marked as the dock
    compass: CompassReference | None = None  # the field in the map's frame, when it was read
    #: (4, 4) the error the map's frame shares at every landmark and edge point, against the
    #: ground: shift x, y; turn; scale about the start (``geometry.frame_jacobian``). None
    #: without a loop closure (the landmark covariances then hold it)
    frame_covariance: FloatArray | None = None

    @property
    def start_pose(self) -> tuple[FloatArray, FloatArray]:
        """Position and q_wb of the dock: where the teach drive started, or where the
        operator marked it."""
        k = 0 if self.dock_index is None else self.dock_index
        return self.trajectory[k, 1:4].copy(), self.trajectory[k, 4:8].copy()

    def save(self, path: Any) -> Any:
        """Write the map file atomically (see :mod:`mowerhw.map`); returns the saved map."""
        from mowerhw.map import LawnMap

        lawn_map = LawnMap.from_teach_result(self)
        lawn_map.save(path)
        return lawn_map


class _Growable:
    """An (n, width) float array that grows by doubling (trajectory recording)."""

    def __init__(self, width: int) -> None:
        self._a = np.zeros((1024, width))
        self.n = 0

    def append(self, row: FloatArray) -> None:
        if self.n == self._a.shape[0]:
            self._a = np.concatenate([self._a, np.zeros_like(self._a)])
        self._a[self.n] = row
        self.n += 1

    def array(self) -> FloatArray:
        return self._a[: self.n].copy()


def _teach_config(config: Config | TeachConfig | None) -> TeachConfig:
    section: TeachConfig
    if config is None:
        section = with_imu_noise(TeachConfig())
    elif isinstance(config, Config):
        section = with_imu_noise(config.teach, config.imu)
    else:
        section = with_imu_noise(config)
    return section


class Teacher:
    """Teach-phase estimator: landmark observers + robot-centric EKF + keyframes."""

    #: landmarks unseen for this long are retired (their last world position is kept)
    LOST_AFTER_S = 3.0
    #: fewer than this many landmarks of the current keyframe in view → new keyframe
    MIN_KEYFRAME_LANDMARKS = 6
    #: a landmark counts as mapped once its depth has this relative σ or better
    CONVERGED_REL_SIGMA = 0.15
    #: the loop-closure smoother keeps one gyro bias per this much driving
    BIAS_SEGMENT_S = 10.0
    #: landmarks the smoother refines: seen in at least this many frames, σ below this
    SMOOTHER_MIN_FRAMES = 5
    SMOOTHER_MAX_SIGMA_M = 1.0
    #: the smoother keeps a camera frame once the mower has moved or turned this much since
    #: the last one it kept (the odometry between is preintegrated): its sparse solve grows
    #: much faster than the number of poses, and frames 5 cm apart add little but cost
    SMOOTHER_FRAME_STEP_M = 0.2
    SMOOTHER_FRAME_TURN_RAD = 0.12

    def __init__(
        self,
        config: Config | TeachConfig | None = None,
        camera: CameraModel | None = None,
        on_frame: Callable[[Teacher, float, Any], None] | None = None,
    ) -> None:
        """``camera`` (optional) is stored in the map; ``on_frame(teacher, t, depth)`` is called
        after every camera frame while driving (plots and diagnostics use it)."""
        self.cfg = _teach_config(config)
        self.camera = camera
        self.on_frame = on_frame
        c = self.cfg
        self.sigma = c.bearing_sigma_rad
        self.obs = LandmarkObservers(
            c.gamma1, c.gamma2, c.d_min_m, weighted_depth=c.depth_gain == "weighted"
        )
        self.ekf = RobotCentricEKF(
            EkfNoise(
                gyro=c.gyro()[0],
                gyro_bias_walk=c.gyro()[1],
                speed=c.speed_noise,
                lateral=c.lateral_noise,
            )
        )
        self.phase = "waiting"  # waiting → standstill → driving → finished
        self.marks: list[TeachMark] = []  # what the operator marked while driving
        self.t0: float | None = None
        self.t_imu: float | None = None
        self.t_frame: float | None = None
        self.speed_mps = 0.0
        self.w_last = np.zeros(3)
        self.distance_m = 0.0
        self.frame_covariance: FloatArray | None = None  # the loop closure's (TeachResult)
        self.keyframes: list[Keyframe] = []
        self._standstill = StandstillCalibrator()
        self._compass = CompassCalibration()
        self._still_bearings: dict[int, list[FloatArray]] = {}
        self._traj = _Growable(10)  # t, x^{bj} (3), q^{bj} (4), distance, keyframe index
        self._row = np.zeros(10)
        # Per-landmark columns aligned with the observer rows.
        self._cols: dict[str, Any] = {}
        self._archive: dict[int, dict[str, Any]] = {}  # retired landmarks
        # What the loop closure (batch smoother) needs: raw IMU intervals while driving
        # (Δt, gyro xyz, speed), and every frame with the filter's pose at it.
        self._imu_log: list[tuple[float, ...]] = []  # Δt, gyro xyz, speed, interval end
        self._speeds = SpeedTrack()
        # (t, ids, bearings, t_wb, q_wb, imu_log_index)
        self._frames: list[tuple[float, NDArray[np.int64], FloatArray, FloatArray, FloatArray, int]]
        self._frames = []
        self._still_obs: dict[int, tuple[FloatArray, float]] = {}  # averaged standstill bearings
        self._still_t = 0.0
        self._bias_at_start = np.zeros(3)
        self._bias_var = 0.005**2
        self.counters = {
            "frames": 0,
            "keyframes": 0,
            "depth_low_parallax": 0,
            "depth_inconsistent": 0,
            "reanchored": 0,
            "retired": 0,
            "revived": 0,
            "nonfinite_inputs": 0,
        }

    # ------------------------------------------------------------------------------ inputs

    def imu(self, t: float, gyro_xyz: ArrayLike) -> None:
        """A gyro reading (rad/s, body frame): the mean rate over the interval ending at t."""
        gyro = np.asarray(gyro_xyz, dtype=np.float64).reshape(3)
        gx, gy, gz = gyro.tolist()
        if not (math.isfinite(t) and math.isfinite(gx + gy + gz)):
            self.counters["nonfinite_inputs"] += 1
            return
        if self.phase == "waiting":
            self.phase = "standstill"
            self.t0 = self.t_imu = float(t)
            self._record()
            return
        if self.phase == "standstill":
            self.t_imu = float(t)
            self._record()
            if not self._standstill.add(float(t), gyro):  # it turned: the standstill is over
                self._start_driving()
            return
        if self.phase != "driving" or t <= self.t_imu:  # type: ignore[operator]
            return
        self.w_last = gyro - self.ekf.bg
        self._propagate(float(t) - self.t_imu, self.w_last, gyro)  # type: ignore[operator]
        self.t_imu = float(t)
        self._record()

    def magnetometer(self, t: float, mag_t: ArrayLike, accel: ArrayLike | None = None) -> None:
        """A magnetometer reading (T, body frame; with the accelerometer's, m/s², when there
        is one): the map learns the field's direction (:mod:`mowerhw.estimation.compass`)."""
        self._compass.add(t, mag_t, accel)

    def speed(self, t: float, v: float) -> None:
        """Signed ground speed (m/s); NaN or invalid readings are ignored (held speed)."""
        if not (np.isfinite(t) and np.isfinite(v)):
            self.counters["nonfinite_inputs"] += 1
            return
        self.speed_mps = float(v)
        self._speeds.add(t, v)
        if self.phase in ("waiting", "standstill") and v != 0.0:
            if self.phase == "waiting":
                self.t0 = self.t_imu = float(t)
                self._record()
            self._start_driving()

    def bearings(self, t: float, landmark_ids: ArrayLike, unit_xyz: ArrayLike) -> None:
        """Unit bearings (body frame) of the landmarks seen in one frame."""
        ids: NDArray[np.int64] = np.asarray(landmark_ids, dtype=np.int64).reshape(-1)
        u = np.asarray(unit_xyz, dtype=np.float64).reshape(-1, 3)
        if ids.size != u.shape[0]:
            raise ValueError(f"{ids.size} ids but {u.shape[0]} bearings")
        good = np.all(np.isfinite(u), axis=1) & (np.linalg.norm(u, axis=1) > 0.5)
        if not good.all():
            self.counters["nonfinite_inputs"] += int((~good).sum())
        ids, u = ids[good], u[good] / np.linalg.norm(u[good], axis=1, keepdims=True)
        _, first = np.unique(ids, return_index=True)  # one bearing per id
        ids, u = ids[np.sort(first)], u[np.sort(first)]
        self.counters["frames"] += 1
        if self.phase in ("waiting", "standstill"):
            for i, b in zip(ids.tolist(), u, strict=True):
                self._still_bearings.setdefault(i, []).append(b)
            self.t_frame = float(t)
            return
        if self.phase != "driving":
            return
        if self.t_imu is not None and t > self.t_imu:
            self._propagate(float(t) - self.t_imu, self.w_last, self.w_last + self.ekf.bg)
            self.t_imu = float(t)
        self._frame(float(t), ids, u)
        pos, q_wb = self.world_pose()
        self._frames.append((float(t), ids, u, pos, q_wb, len(self._imu_log)))

    # ------------------------------------------------------------------------- internals

    def _record(self) -> None:
        """Log the EKF state at this IMU sample; world poses are composed at ``finish``."""
        kf = self.keyframes[-1].index if self.keyframes else -1
        row = self._row
        row[0] = self.t_imu
        row[1:4] = self.ekf.p
        row[4:8] = self.ekf.q
        row[8] = self.distance_m
        row[9] = kf
        self._traj.append(row)

    def known_landmarks(self) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """Ids, world positions and covariances of every landmark located so far, tracked
        or retired (what re-identification can match a new feature against)."""
        recs = self._all_landmarks()
        ids = np.array(sorted(recs), dtype=np.int64)
        if ids.size == 0:
            return ids, np.zeros((0, 3)), np.zeros((0, 3, 3))
        xyz = np.stack([recs[i]["xyz"] for i in ids.tolist()])
        cov = np.stack([recs[i]["cov"] for i in ids.tolist()])
        return ids, xyz, cov

    def landmark_snapshot(self) -> tuple[NDArray[np.int64], FloatArray]:
        """Ids and current world positions (eq. 20) of the tracked landmarks seen so far."""
        ok = np.isfinite(self._cols["snap_t"]) if self._cols else np.zeros(0, bool)
        if not self._cols:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        return self.obs.ids[ok].copy(), self._cols["snap_xyz"][ok].copy()

    def _world_trajectory(self) -> FloatArray:
        """(K, 9): t, x_b^w (3), q_wb (4), distance — eqs (19)–(20) for every logged sample."""
        log_ = self._traj.array()
        out = np.zeros((log_.shape[0], 9))
        out[:, 0] = log_[:, 0]
        out[:, 4] = 1.0
        out[:, 8] = log_[:, 8]
        kf_idx = log_[:, 9].astype(np.int64)
        for kf in self.keyframes:
            sel = kf_idx == kf.index
            if not sel.any():
                continue
            p, q = log_[sel, 1:4], log_[sel, 4:8]
            x_w = p + quat_rotate(q, kf.x_w_in_kf)  # eq. (19)
            q_wb = quat_conjugate(quat_multiply(q, kf.q_w_in_kf))
            out[sel, 1:4] = -quat_rotate(q_wb, x_w)  # eq. (20)
            out[sel, 4:8] = q_wb
        return out

    def corrected_rate(self, gyro: FloatArray) -> FloatArray:
        """A gyro reading's body rate with the current bias estimate taken out (during the
        start-up standstill: the mean so far)."""
        if self.phase in ("waiting", "standstill"):
            return self._standstill.corrected(gyro)
        return np.asarray(gyro, dtype=np.float64) - self.ekf.bg

    def world_pose(self) -> tuple[FloatArray, FloatArray]:
        """Current body pose in the world: ``x_b^w``, ``q_wb`` (eqs 19–20)."""
        x_w, q_w = compose(self.ekf.p, self.ekf.q, self.keyframes[-1])
        q_wb = quat_conjugate(q_w)
        return -(quat_to_rotmat(q_wb) @ x_w), q_wb

    def _propagate(self, dt: float, w: FloatArray, gyro_raw: FloatArray) -> None:
        t_end = self.t_imu + dt  # type: ignore[operator]
        speed = self._speeds.at(t_end - 0.5 * dt)
        self._imu_log.append((dt, gyro_raw[0], gyro_raw[1], gyro_raw[2], speed, t_end))
        v = camera_velocity(speed, w, self.cfg.speed_contact_m)
        m = BodyMotion.of(w, v, dt)
        self.ekf.propagate(m)
        self.obs.propagate(m.c, m.disp)
        self.distance_m += abs(speed) * dt

    def _start_driving(self) -> None:
        """End of the standstill: gyro bias, keyframe 0, observers from averaged bearings."""
        assert self.t_imu is not None  # driving starts on an IMU sample
        t_start = float(self.t_imu)
        c = self.cfg
        still = self._standstill
        still.stop()
        if still.calibrated:
            mean = still.bias()
            self._bias_var = still.bias_variance() + 1e-10
            self.ekf.set_bias(mean, self._bias_var)
        else:
            log.warning("teach: no standstill before driving; gyro bias not calibrated")
            self.ekf.set_bias(np.zeros(3), self._bias_var)
        self.standstill_samples = still.used
        self._bias_at_start = self.ekf.bg.copy()
        self._still_t = t_start
        self.keyframes.append(
            Keyframe(0, t_start, np.zeros(3), IDENTITY_QUAT.copy(), np.zeros((6, 6)), 0.0)
        )
        self.phase = "driving"
        if self._still_bearings:
            ids = np.array(sorted(self._still_bearings), dtype=np.int64)
            means = np.array([np.mean(self._still_bearings[i], axis=0) for i in ids.tolist()])
            means /= np.linalg.norm(means, axis=1, keepdims=True)
            # a standstill is one view of a still scene: its frames' bearings share their
            # tracking errors (a corner's pixel found the same way in the same image), so
            # their mean is as sure as one bearing, not n times surer — counted n times
            # surer it pinned the map's frame to the dock too tightly (README, issue 18,
            # stop 71: the maps' frame covariance against the truth)
            var = np.full(ids.size, self.sigma**2)
            self._add_landmarks(ids, means, var, t_start)
            self._set_consider_anchors(self.obs.rows(ids))
            self._still_obs = {
                int(i): (m, float(v)) for i, m, v in zip(ids, means, var, strict=True)
            }
        self._still_bearings.clear()
        self.t_frame = self.t_imu
        del c

    def _anchor_here(self, n: int) -> dict[str, FloatArray]:
        """Anchor columns for n landmarks anchored at the current body frame."""
        r = quat_to_rotmat(self.ekf.q)  # R_{b←bj}
        r_ja = np.broadcast_to(r.T, (n, 3, 3)).copy()  # anchor (= now) axes in bj
        t_ja = np.broadcast_to(-r.T @ self.ekf.p, (n, 3)).copy()  # anchor origin in bj
        return {
            "anchor_kf": np.full(n, self.keyframes[-1].index, dtype=np.int64),
            "anchor_r": r_ja,
            "anchor_t": t_ja,
            "anchor_p": np.broadcast_to(self.ekf.p, (n, 3)).copy(),
            "anchor_cov": np.broadcast_to(self.ekf.P[:6, :6], (n, 6, 6)).copy(),
        }

    def _add_landmarks(
        self, ids: NDArray[np.int64], u: FloatArray, u_var: FloatArray, t: float
    ) -> None:
        """New observers (or revived retired ones) for ``ids`` seen along ``u`` now."""
        c = self.cfg
        n = ids.size
        d0 = np.full(n, c.d_init_m)
        var_d0 = np.full(n, c.d_init_m**2)
        y0 = u.copy()
        revived = np.array([i in self._archive for i in ids.tolist()], dtype=bool)
        if revived.any():  # a landmark seen before: start from its mapped position
            x_w, q_w = compose(self.ekf.p, self.ekf.q, self.keyframes[-1])
            for k in np.flatnonzero(revived):
                rec = self._archive.pop(int(ids[k]))
                xb = quat_to_rotmat(q_w) @ rec["xyz"] + x_w  # eq. 20 inverted
                dist = float(np.linalg.norm(xb))
                if dist > c.d_min_m:
                    d0[k] = dist
                    var_d0[k] = float(np.trace(rec["cov"])) / 3.0 + 0.01
            self.counters["revived"] += int(revived.sum())
        self.obs.add(ids, y0, c.d_init_m, c.d_init_m**2, self.sigma**2)
        rows = self.obs.rows(ids)
        self.obs.d[rows] = d0
        self.obs.var_d[rows] = var_d0
        new_cols = self._anchor_here(n)
        new_cols["anchor_y"] = u.copy()
        new_cols["anchor_var"] = np.asarray(u_var, dtype=np.float64).reshape(n).copy()
        new_cols["last_seen"] = np.full(n, t)
        new_cols["anchor_slot"] = np.full(n, -1, dtype=np.int64)
        new_cols["snap_xyz"] = np.full((n, 3), np.nan)
        new_cols["snap_cov"] = np.full((n, 3, 3), np.nan)
        new_cols["snap_t"] = np.full(n, np.nan)
        new_cols["snap_dist"] = np.full(n, np.nan)
        for key, val in new_cols.items():
            self._cols[key] = (
                val if key not in self._cols else np.concatenate([self._cols[key], val])
            )

    def _retire(self, keep: NDArray[np.bool_]) -> None:
        gone = np.flatnonzero(~keep)
        for k in gone:
            if np.isfinite(self._cols["snap_t"][k]):
                self._archive[int(self.obs.ids[k])] = {
                    "xyz": self._cols["snap_xyz"][k].copy(),
                    "cov": self._cols["snap_cov"][k].copy(),
                    "t": float(self._cols["snap_t"][k]),
                    "dist": float(self._cols["snap_dist"][k]),
                }
        self.counters["retired"] += int(gone.size)
        self.obs.remove(keep)
        for key in self._cols:
            self._cols[key] = self._cols[key][keep]

    def _frame(self, t: float, ids: NDArray[np.int64], u: FloatArray) -> None:
        c = self.cfg
        cols = self._cols
        rows = self.obs.rows(ids)
        new = rows < 0
        if new.any():
            self._add_landmarks(ids[new], u[new], np.full(int(new.sum()), self.sigma**2), t)
        old_ids = ids[~new]
        old_u = u[~new]
        rows = self.obs.rows(old_ids)
        kf = self.keyframes[-1]
        # Landmarks anchored in an older keyframe that come back into view: anchor them here.
        stale = cols["anchor_kf"][rows] != kf.index
        if stale.any():
            self._reanchor(rows[stale], old_u[stale])
        dt_k = max(t - (self.t_frame if self.t_frame is not None else t), 1e-3)
        self.t_frame = t
        v = np.array([self.speed_mps, 0.0, 0.0])
        if rows.size:
            # eq. (3): depth pseudo-measurements from each landmark's anchor
            dm, var_d = self._depths(rows, old_u)
            self.counters["depth_low_parallax"] += int(dm.low_parallax.sum())
            self.counters["depth_inconsistent"] += int(dm.inconsistent.sum())
            # eqs (5), (7): observer updates
            self.obs.update(rows, old_u, self.sigma**2, dm.depth, var_d, dt_k, v, self.w_last)
            self._last_depth = (self.obs.ids[rows].copy(), dm.depth.copy())
            # eqs (16)–(18): EKF update with the landmarks anchored in this keyframe
            anchor_var = cols["anchor_var"][rows] + _anchor_pose_variance(
                cols["anchor_cov"][rows], self.obs.d[rows]
            )
            if c.ekf_measurement == "epipolar":
                # Only anchors taken at the keyframe itself: an anchor taken between keyframes
                # is one raw bearing at an estimated pose, and its error would be reused by
                # every later update as if it were fresh (see the module doc).
                exact = ~np.any(cols["anchor_cov"][rows] != 0.0, axis=(1, 2))
                sel = rows[exact]
                self.ekf.update_epipolar(
                    old_u[exact],
                    self.sigma**2,
                    cols["anchor_y"][sel],
                    anchor_var[exact],
                    cols["anchor_r"][sel],
                    cols["anchor_t"][sel],
                    c.min_baseline_m,
                    np.radians(EPI_MIN_ANGLE_DEG),
                    anchor_slot=cols["anchor_slot"][sel],
                )
            else:
                self.ekf.update(
                    self.obs.positions()[rows],
                    self.obs.covariances()[rows],
                    cols["anchor_y"][rows],
                    cols["anchor_var"][rows],
                    cols["anchor_r"][rows],
                    cols["anchor_t"][rows],
                    cols["anchor_cov"][rows],
                    cols["anchor_p"][rows],
                )
        cols["last_seen"][self.obs.rows(ids)] = t
        self._snapshot(self.obs.rows(ids), t)
        if self.on_frame is not None:
            self.on_frame(self, t, getattr(self, "_last_depth", None))
        self._maybe_new_keyframe(t, self.obs.rows(ids))
        lost = t - cols["last_seen"] > self.LOST_AFTER_S
        if lost.any():
            self._retire(~lost)

    def _depths(self, rows: NDArray[np.int64], u: FloatArray) -> tuple[Any, FloatArray]:
        """Eq. (3) for ``rows``, with the variance of each pseudo-measurement.

        Besides both rays' noise, the relative pose between anchor and now is uncertain:
        the EKF's pose covariance and, for anchors taken between keyframes, the anchor's.
        A rotation error acts on eq. (3) like more ray noise, a translation error like
        baseline noise, so they enter the same first-order formula
        (:func:`mowerhw.teach.depth.depth_pseudo_measurement`).
        """
        c, cols = self.cfg, self._cols
        r = quat_to_rotmat(self.ekf.q)
        r_ba = np.einsum("ij,njk->nik", r, cols["anchor_r"][rows])
        origin_b = self.ekf.p + cols["anchor_t"][rows] @ r.T
        p_rel = self.ekf.P[:6, :6] + cols["anchor_cov"][rows]
        rot_var = np.trace(p_rel[:, 3:, 3:], axis1=1, axis2=2) / 3.0
        pos_var = np.trace(p_rel[:, :3, :3], axis1=1, axis2=2)
        dm = depth_pseudo_measurement(
            origin_b,
            r_ba,
            cols["anchor_y"][rows],
            u,
            np.sqrt(self.sigma**2 + rot_var),
            np.radians(c.min_parallax_deg),
            c.min_baseline_m,
            baseline_variance=pos_var,
        )
        return dm, dm.variance

    def _reanchor(self, rows: NDArray[np.int64], u: FloatArray | None) -> None:
        """Anchor ``rows`` at the current body frame (bearing ``u``, or the observer's)."""
        fresh = self._anchor_here(rows.size)
        for key, val in fresh.items():
            self._cols[key][rows] = val
        self._cols["anchor_slot"][rows] = -1
        if u is None:
            self._cols["anchor_y"][rows] = self.obs.y[rows]
            self._cols["anchor_var"][rows] = self.obs.var_y[rows]
        else:
            self._cols["anchor_y"][rows] = u
            self._cols["anchor_var"][rows] = self.sigma**2
        self.counters["reanchored"] += int(rows.size)

    def _set_consider_anchors(self, rows: NDArray[np.int64]) -> None:
        """The anchors just taken at the keyframe become the EKF's consider parameters."""
        self._cols["anchor_slot"][:] = -1
        self._cols["anchor_slot"][rows] = np.arange(rows.size)
        self.ekf.set_anchors(self._cols["anchor_var"][rows])

    def _snapshot(self, rows: NDArray[np.int64], t: float) -> None:
        """World position (eq. 20) and covariance of the landmarks just observed."""
        if rows.size == 0:
            return
        kf = self.keyframes[-1]
        x_w, q_w = compose(self.ekf.p, self.ekf.q, kf)
        cov_pose = world_pose_covariance(kf, self.ekf.p, self.ekf.q, self.ekf.P[:6, :6])
        xb = self.obs.positions()[rows]
        xyz = landmarks_in_world(xb, x_w, q_w)
        cov = landmark_world_covariance(xb, self.obs.covariances()[rows], q_w, cov_pose)
        cols = self._cols
        cols["snap_xyz"][rows] = xyz
        cols["snap_cov"][rows] = cov
        cols["snap_t"][rows] = t
        cols["snap_dist"][rows] = self.distance_m

    def _maybe_new_keyframe(self, t: float, seen_rows: NDArray[np.int64]) -> None:
        kf = self.keyframes[-1]
        anchored_here = (self._cols["anchor_kf"][seen_rows] == kf.index) & ~np.any(
            self._cols["anchor_cov"][seen_rows] != 0.0, axis=(1, 2)
        )
        converged = (
            np.sqrt(self.obs.var_d[seen_rows]) / self.obs.d[seen_rows] < self.CONVERGED_REL_SIGMA
        )
        good_here = int(np.sum(anchored_here & converged))
        few = good_here < self.MIN_KEYFRAME_LANDMARKS and np.sum(converged) > good_here
        far = self.distance_m - kf.distance_m > self.cfg.keyframe_baseline_m
        if not (few or far):
            return
        x_w, q_w = compose(self.ekf.p, self.ekf.q, kf)
        cov_w = world_pose_covariance(kf, self.ekf.p, self.ekf.q, self.ekf.P[:6, :6])
        self.keyframes.append(Keyframe(len(self.keyframes), t, x_w, q_w, cov_w, self.distance_m))
        self.ekf.reset_keyframe()
        self._reanchor(seen_rows, None)  # anchors at the new keyframe: the filtered bearings
        self._set_consider_anchors(seen_rows)
        self.counters["keyframes"] += 1

    # ----------------------------------------------------------------------------- finish

    def _all_landmarks(self) -> dict[int, dict[str, Any]]:
        out = dict(self._archive)
        cols = self._cols
        for k, lid in enumerate(self.obs.ids.tolist()):
            if np.isfinite(cols["snap_t"][k]):
                out[lid] = {
                    "xyz": cols["snap_xyz"][k].copy(),
                    "cov": cols["snap_cov"][k].copy(),
                    "t": float(cols["snap_t"][k]),
                    "dist": float(cols["snap_dist"][k]),
                }
        return out

    def _close_loop(self, traj: FloatArray, landmarks: dict[int, dict[str, Any]]) -> LoopClosure:
        """Smooth the whole drive (:mod:`mowerhw.teach.smoother`) and apply it (in place)."""
        if not self.cfg.loop_closure:
            return LoopClosure(False, "disabled in the configuration")
        frames = self._smoother_frames()
        if len(frames) < 3:
            return LoopClosure(False, "too few camera frames while driving")
        problem, lm_ids, reobserved = self._smoother_problem(landmarks, frames)
        if problem is None:
            return LoopClosure(False, "no landmark was mapped")
        try:
            out = smooth(problem)
            # A landmark that is not one fixed point (an occlusion corner sliding along an
            # edge, two features taken for one) drags the poses towards its own error:
            # smooth again without the ones that fit badly.
            rms = _landmark_rms(problem, out.r_wb, out.t_wb, out.landmarks)
            bad = _outliers(rms, self.cfg.landmark_residual_factor)
            if bad.any():
                for b in np.flatnonzero(bad).tolist():
                    landmarks[lm_ids[b]]["rms"] = float("inf")
                keep = {lid: landmarks[lid] for j, lid in enumerate(lm_ids) if not bad[j]}
                problem2, lm_ids2, reobserved2 = self._smoother_problem(keep, frames)
                if problem2 is not None:
                    out = smooth(problem2)
                    problem, lm_ids, reobserved = problem2, lm_ids2, reobserved2
        except (np.linalg.LinAlgError, ValueError, RuntimeError) as exc:
            log.warning("teach: loop closure failed (%s); keeping the filter's estimate", exc)
            return LoopClosure(False, f"smoother failed: {exc}")
        # left (world) correction at every frame, spread over the IMU-rate trajectory
        corr_r = out.r_wb @ np.swapaxes(problem.r_wb, 1, 2)
        corr_t = out.t_wb - np.einsum("nij,nj->ni", corr_r, problem.t_wb)
        frame_t = np.array([self._still_t] + [f[0] for f in frames])
        phi = rotmat_log(corr_r)
        ts = traj[:, 0]
        phi_i = np.stack([np.interp(ts, frame_t, phi[:, a]) for a in range(3)], axis=1)
        t_i = np.stack([np.interp(ts, frame_t, corr_t[:, a]) for a in range(3)], axis=1)
        r_i = quat_to_rotmat(quat_exp(phi_i))
        traj[:, 1:4] = np.einsum("nij,nj->ni", r_i, traj[:, 1:4]) + t_i
        traj[:, 4:8] = quat_multiply(quat_exp(phi_i), traj[:, 4:8])
        # each landmark's own error; what all share, the map frame's, is kept apart
        own = out.landmark_cov if out.landmark_cov_own is None else out.landmark_cov_own
        for j, lid in enumerate(lm_ids):
            landmarks[lid]["xyz"] = out.landmarks[j].copy()
            landmarks[lid]["cov"] = own[j].copy()
            if out.landmark_cov_configured is not None:
                landmarks[lid]["cov_geometry"] = out.landmark_cov_configured[j].copy()
        rms = _landmark_rms(problem, out.r_wb, out.t_wb, out.landmarks)
        for j, lid in enumerate(lm_ids):
            landmarks[lid]["rms"] = float(rms[j])
        self.frame_covariance = out.frame_cov
        self.ekf_bias_smoothed = out.bias[-1]
        self.gyro_scale_error = out.scale
        closed = reobserved >= 4
        return LoopClosure(
            applied=True,
            reason="loop closed: start landmarks seen again at the end"
            if closed
            else f"refined only: {reobserved} start landmarks seen again at the end",
            translation_m=float(
                np.linalg.norm(corr_t[-1] + (corr_r[-1] - np.eye(3)) @ problem.t_wb[-1])
            ),
            rotation_rad=float(np.linalg.norm(phi[-1])),
            landmarks_used=reobserved,
            residual_rms_rad=out.bearing_rms_rad,
            bearing_sigma_long_run_rad=self.sigma * math.sqrt(out.bearing_variance_factor),
        )

    def _bias_segments(self, frames: list[tuple[Any, ...]]) -> dict[str, Any]:
        """One gyro bias per ``BIAS_SEGMENT_S`` of driving, tied by the bias random walk."""
        t = np.array([self._still_t] + [f[0] for f in frames])
        seg = np.floor((t[:-1] - t[0]) / self.BIAS_SEGMENT_S).astype(np.int64)
        nseg = int(seg.max(initial=0)) + 1
        walk_var = max(self.cfg.gyro()[1], 1e-9) ** 2 * self.BIAS_SEGMENT_S
        return {
            "bias_segment": seg,
            "bias_walk_cov": np.tile(np.eye(3) * walk_var, (nseg - 1, 1, 1)),
        }

    def _smoother_frames(self) -> list[tuple[Any, ...]]:
        """The camera frames the smoother keeps: the first, then one each time the mower has
        moved :data:`SMOOTHER_FRAME_STEP_M` or turned :data:`SMOOTHER_FRAME_TURN_RAD` since
        the last one kept, and the last."""
        frames = self._frames
        if len(frames) < 3:
            return list(frames)
        pos = np.array([f[3] for f in frames])
        yaw = np.unwrap(quat_to_yaw(np.array([f[4] for f in frames])))
        kept = [0]
        for k in range(1, len(frames) - 1):
            j = kept[-1]
            moved = float(np.linalg.norm(pos[k] - pos[j]))
            if moved >= self.SMOOTHER_FRAME_STEP_M or abs(yaw[k] - yaw[j]) >= (
                self.SMOOTHER_FRAME_TURN_RAD
            ):
                kept.append(k)
        kept.append(len(frames) - 1)
        return [frames[k] for k in kept]

    def _smoother_problem(
        self, landmarks: dict[int, dict[str, Any]], frames: list[tuple[Any, ...]]
    ) -> tuple[SmootherProblem | None, list[int], int]:
        """Poses at ``frames`` (the filter's), odometry between them, bearings, initial
        map."""
        c = self.cfg
        # Only landmarks the smoother can locate: seen often enough, and already roughly
        # known. A landmark seen twice makes the normal equations (nearly) singular, and
        # its marginal covariance numerically meaningless; it is not mapped anyway.
        seen: dict[int, int] = {}
        for _, ids, *_rest in frames:
            for lid in ids.tolist():
                seen[lid] = seen.get(lid, 0) + 1
        lm_ids = sorted(
            lid
            for lid, rec in landmarks.items()
            if seen.get(lid, 0) >= self.SMOOTHER_MIN_FRAMES
            and _well_located(rec["cov"], self.SMOOTHER_MAX_SIGMA_M)
        )
        if not lm_ids:
            return None, [], 0
        index = {lid: j for j, lid in enumerate(lm_ids)}
        r_wb = [np.eye(3)] + [quat_to_rotmat(f[4]) for f in frames]
        t_wb = [np.zeros(3)] + [f[3] for f in frames]
        log_arr = np.asarray(self._imu_log, dtype=np.float64).reshape(-1, 6)
        # after the fact: the speed interpolated mid-interval
        log_arr[:, 4] = self._speeds.interpolate(log_arr[:, 5] - 0.5 * log_arr[:, 0])
        bounds = np.array([0] + [f[5] for f in frames])
        bias0 = self._bias_at_start
        odometry = preintegrate_segments(
            log_arr,
            bounds,
            bias0,
            c.gyro()[0],
            c.speed_noise,
            c.lateral_noise,
            contact=np.asarray(c.speed_contact_m, dtype=np.float64),
        )
        of, ol, ob, osg = [], [], [], []
        for lid, (u, var) in self._still_obs.items():
            if lid in index:
                of.append(0)
                ol.append(index[lid])
                ob.append(u)
                osg.append(np.sqrt(var))
        for k, (_, ids, u, *_rest) in enumerate(frames, start=1):
            for lid, b in zip(ids.tolist(), u, strict=True):
                if lid in index:
                    of.append(k)
                    ol.append(index[lid])
                    ob.append(b)
                    osg.append(self.sigma)
        n_frames = len(frames)
        early = {lid for _, ids, *_r in frames[: max(1, n_frames // 10)] for lid in ids.tolist()}
        early |= set(self._still_obs)
        late = {lid for _, ids, *_r in frames[-max(1, n_frames // 10) :] for lid in ids.tolist()}
        problem = SmootherProblem(
            r_wb=np.stack(r_wb),
            t_wb=np.stack(t_wb),
            odometry=odometry,
            obs_frame=np.asarray(of, dtype=np.int64),
            obs_landmark=np.asarray(ol, dtype=np.int64),
            obs_bearing=np.asarray(ob),
            obs_sigma=np.asarray(osg),
            landmarks=np.stack([landmarks[lid]["xyz"] for lid in lm_ids]),
            bias0=bias0,
            bias_prior=bias0,
            bias_prior_cov=np.eye(3) * self._bias_var,
            scale_prior_sigma=float(c.gyro_scale_sigma or 0.0),
            **self._bias_segments(frames),
        )
        return problem, lm_ids, len(early & late)

    def finish(self) -> TeachResult:
        """Close the loop, build the boundary, and return the map content."""
        if self.phase != "driving":
            raise TeachError("the mower never drove: teach needs a drive around the lawn edge")
        self.phase = "finished"
        traj9 = self._world_trajectory()
        landmarks = self._all_landmarks()
        raw = traj9[:, :8].copy()
        closure = self._close_loop(traj9, landmarks)
        # The map keeps only landmarks located well enough to localize against (a feature
        # tracked briefly, or seen with too little parallax, has a poorly known depth): judged
        # by the drive's geometry, with the bearings at their configured σ, not by how
        # precise the camera turned out to be (the loop closure's long-run σ; a map denser
        # in poorly placed landmarks is harder to relocalize in).
        limit = self.cfg.max_landmark_sigma_m
        loose = [
            i
            for i, r in landmarks.items()
            if not _well_located(r.get("cov_geometry", r["cov"]), limit)
        ]
        for i in loose:
            del landmarks[i]
        # ... and only fixed points: bearings that fit one position
        inconsistent = _inconsistent(landmarks, self.cfg.landmark_residual_factor)
        for i in inconsistent:
            del landmarks[i]
        c = self.cfg
        zones = zones_from_marks(
            traj9[:, 0],
            traj9[:, 1:3],
            traj9[:, 8],
            self.marks,
            c.boundary_simplify_m,
            c.min_area_m2,
        )
        mowing = [z for z in zones if z.kind == "mow"]
        if zones and not mowing:
            raise BoundaryError(
                "zones were marked but no mowing area: mark each lawn too (ctl teach area NAME)"
            )
        boundary = (
            mowing[0].polygon
            if mowing
            else boundary_from_path(
                traj9[:, 1:3], c.boundary_simplify_m, c.min_area_m2, distance=traj9[:, 8]
            )
        )
        diagnostics = {
            "standstill_samples": getattr(self, "standstill_samples", 0),
            "gyro_bias": self.ekf.bg.tolist(),
            "gyro_yaw_scale_error": getattr(self, "gyro_scale_error", 0.0),
            "distance_m": self.distance_m,
            "keyframes": len(self.keyframes),
            "ekf_updates": self.ekf.stats.used,
            "ekf_gated": self.ekf.stats.gated,
            **self.counters,
            "landmarks_too_uncertain": len(loose),
            "landmarks_inconsistent": len(inconsistent),
            **{f"observer_{k}": v for k, v in vars(self.obs.stats).items()},
        }
        return TeachResult(
            boundary=boundary,
            landmarks={i: r["xyz"] for i, r in landmarks.items()},
            landmark_covariances={i: r["cov"] for i, r in landmarks.items()},
            trajectory=traj9[:, :8],
            trajectory_no_closure=raw,
            closure=closure,
            keyframes=list(self.keyframes),
            diagnostics=diagnostics,
            camera=self.camera,
            zones=zones,
            dock_index=dock_index(traj9[:, 0], self.marks),
            compass=self._compass.fit(traj9[:, :8]),
            frame_covariance=self.frame_covariance,
        )

    def mark(self, t: float, kind: str, name: str = "") -> str:
        """The operator marks, at sensor time ``t``, what is driven from now on (see
        :mod:`mowerhw.teach.marks`); why not, or ""."""
        if self.phase == "finished":
            return "teach is finished"
        problem = check_mark(kind, name, self.marks)
        if not problem:
            self.marks.append(TeachMark(t, kind, name))
        return problem

    @property
    def zone_open(self) -> bool:
        """A marked zone is being driven (no end of the drive yet)."""
        return bool(self.marks) and MARK_KINDS[self.marks[-1].kind] is not None
