"""The mow phase as one pure object: localize against the map, decide containment.

    loc = Localizer(map_, config=None, start_pose=None)
    loc.imu(t, gyro_xyz, accel_xyz=None); loc.speed(t, v)
    loc.bearings(t, ids, unit_xyz)     # ids = map landmark ids
    loc.pose()          # -> Pose(t, position (3,), quaternion (4,) wxyz, covariance (6, 6))
    loc.containment()   # -> .state, .permit, .signed_distance_m, .sigma_m, .reason

Around the world-centric EKF (:mod:`mowerhw.mow.ekf`):

* **Start**: at the map's dock pose (the teach start) or a given pose, with the configured σ.
  While the mower stands still at the start, the gyro is averaged into its bias and the
  pose is held (no integration of a still gyro); vision updates already run.
* **Late frames**: the filter keeps ``history_s`` of IMU inputs and states; a frame stamped
  before the newest IMU sample is applied at its own time and the IMU samples since are
  re-propagated, so the newest state stays at IMU rate and is exact.
* **Gating and lock-out**: every bearing is χ²-gated; if frames that see enough landmarks are
  all rejected for ``lockout_s``, the pose uncertainty is widened; if that does not help
  within another ``lockout_s``, the pose is re-fitted from the bearings of one frame (known
  ids) and the filter restarts there. A frame naming an id the map does not have is counted
  and ignored.
* **Faults**: a non-finite state restarts the filter at its last good pose with a wide
  uncertainty; containment reports FAULT until it is localized again.
* **Losing the pose and finding it again** (issue 18, with a relocalizer: pixel level, where
  :class:`mowerhw.vision.MowVision` calls :meth:`Localizer.use_relocalizer`): every pose the
  filter starts from (the dock, a given or resumed pose) is first *checked* by the
  relocalizer near it; the pose is *given up* (:meth:`Localizer.lose`: halt at once) when the
  mower is lifted (:meth:`Localizer.lifted`), when most matched landmarks jump away from
  their predictions (carried or pushed), after a lock-out of ``SEARCH_AFTER_S`` or no fix for
  ``lost_after_s``; a search near the prior becomes global after 3 s. An answer is accepted
  when two frames agree through the odometry between them
  (:class:`mowerhw.mow.recovery.RelocalizationSearch`).
* **Consistency check**: after every re-localization (accepted search, resume, refit,
  lock-out, fault restart) the filter is on probation until enough consecutive frames are
  consistent (:class:`mowerhw.mow.recovery.Probation`); one that cannot show it in 10 s is
  given up and searched for.
* **Between speed samples, and a silent ground speed**: past the newest sample the IMU's
  along-track acceleration carries its speed on (:meth:`Localizer._carry_speed`; the next
  sample drives those steps again), past the speed's staleness limit for at most
  ``mow.accel_bridge_s`` (:meth:`Localizer._carried_variance`); without acceleration, or after
  that, the position is propagated at zero speed with the mower's top speed as its
  uncertainty.
* **Containment**: UNKNOWN unless localized, all sensors fresh, the last landmark fix no older
  than ``mow.max_dead_reckoning_s``, and σ ≤ ``containment.sigma_max_m``; otherwise the table
  of :mod:`mowerhw.mow.containment`. The dead-reckoning limit is what halts first when the
  camera recognises nothing: with these sensors the odometry σ grows by only millimetres in a
  few seconds, but wet grass, a bump or a lifted mower are not in that noise model.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mowerhw.common.geometry import (
    quat_multiply,
    quat_multiply_unit,
    quat_to_rotmat,
    quat_to_yaw,
    rotmat_to_quat,
    yaw_rotation,
    yaw_to_quat,
)
from mowerhw.common.relocalization import Relocalization
from mowerhw.common.units import GRAVITY_MPS2
from mowerhw.config import Config, ContainmentConfig, MowConfig, stale_limits_s, with_imu_noise
from mowerhw.estimation.compass import Compass
from mowerhw.estimation.odometry import (
    BodyMotion,
    SpeedTrack,
    accel_shaped_speeds,
    camera_velocity,
    left_jacobian_times,
)
from mowerhw.estimation.posefit import fit_pose_to_bearings
from mowerhw.estimation.standstill import StandstillCalibrator
from mowerhw.map import LawnMap, frame_pose_covariance
from mowerhw.map import load as load_map
from mowerhw.mow.containment import (
    Containment,
    ContainmentResult,
    LawnGeometry,
    Reason,
)
from mowerhw.mow.ekf import EkfState, LocalizerNoise, WorldPoseEKF, largest_sigma_xy
from mowerhw.mow.recovery import (
    Pose2D,
    Probation,
    RelocalizationSearch,
    accepted_covariance,
)
from mowerhw.mow.spot import SharedFrameError

FloatArray = NDArray[np.float64]


class Pose(NamedTuple):
    """The localizer's newest estimate: ``t, position, quaternion, covariance = loc.pose()``,
    ``loc.pose()[1]``, ``loc.pose().position``."""

    t: float
    position: FloatArray  # (3,) x_b^w
    quaternion: FloatArray  # (4,) q_wb, w first
    covariance: FloatArray  # (6, 6): position (3), then rotation (3, world axes)


@dataclass
class LocalizerCounters:
    imu_samples: int = 0
    frames: int = 0
    frames_with_fix: int = 0
    bearings_used: int = 0
    bearings_rejected: int = 0
    unknown_ids: int = 0
    late_frames: int = 0
    late_frames_dropped: int = 0
    lockouts: int = 0
    inflations: int = 0
    reinitialisations: int = 0
    faults: int = 0
    nonfinite_inputs: int = 0
    speed_stale_steps: int = 0  # IMU steps propagated without a fresh ground speed
    speed_carried_steps: int = 0  # … of them at the speed the accelerometer carried on
    frames_without_imu: int = 0  # frames refused: no IMU sample near their time
    imu_gaps: int = 0  # IMU intervals past the IMU's staleness limit (see Localizer._step)
    searches: int = 0  # times the pose was given up and searched for (no prior, kidnap, …)
    relocalizations: int = 0  # searches that ended in an accepted pose (near a prior or global)
    checks_passed: int = 0  # re-localizations that passed the consistency check
    checks_failed: int = 0  # … that did not (the pose was searched for again)


@dataclass
class _Step:
    """One propagated IMU interval: its inputs and the state after it (for late frames)."""

    t0: float
    t1: float
    gyro: FloatArray
    speed: float
    state: EkfState = field(repr=False)
    held: bool = False  # a start-up calibration step: the pose was held, not propagated
    widen: tuple[float, float] = (0.0, 0.0)  # (xy variance, yaw variance) added after it
    speed_known: bool = True  # False: no fresh ground speed then (driven at 0, widened)
    wheels_still: bool = False  # the wheels stood (no speed or slip noise added over it)
    along: float | None = None  # the along-track acceleration over it (m/s²), if known

    def drive_at(self, speed: float) -> None:
        """The step driven again at a ground speed known now: the wheels stood over it
        when that speed reads exactly 0."""
        self.speed, self.wheels_still = speed, speed == 0.0


def _configs(config: Any) -> tuple[MowConfig, ContainmentConfig, dict[str, float]]:
    if config is None:
        return with_imu_noise(MowConfig()), ContainmentConfig(), stale_limits_s()
    if isinstance(config, Config):
        mow = with_imu_noise(config.mow, config.imu)
        return mow, config.containment, stale_limits_s(config)
    if isinstance(config, MowConfig):
        return with_imu_noise(config), ContainmentConfig(), stale_limits_s()
    raise TypeError(f"config must be a Config or MowConfig, not {type(config).__name__}")


def _within(value: float, bound: float) -> float:
    """``value`` clipped to ± ``bound``."""
    return min(max(value, -bound), bound)


class Localizer:
    """World-centric localization against a lawn map, and the containment decision."""

    #: below this position σ (m) the filter trusts many agreeing landmarks over a majority
    CONFIDENT_SIGMA_M = 0.1

    def __init__(
        self,
        map_: LawnMap | str | Path,
        config: Config | MowConfig | None = None,
        start_pose: tuple[ArrayLike, ArrayLike] | None = None,
    ) -> None:
        self.map = load_map(map_) if isinstance(map_, str | Path) else map_
        self.cfg, ccfg, self.stale_s = _configs(config)
        c = self.cfg
        self.ids = self.map.landmark_ids()
        self._row = {int(i): r for r, i in enumerate(self.ids.tolist())}
        self.landmarks = self.map.landmark_positions()
        self._containment_cfg = ccfg
        self.geometry = LawnGeometry.of_map(self.map, c.areas)
        self._containment = Containment(self.geometry, ccfg)
        g_noise, g_walk, g_scale = c.gyro()
        noise = LocalizerNoise(g_noise, g_walk, c.speed_noise, c.lateral_noise, g_scale)
        self.ekf = WorldPoseEKF(noise, self.map.landmark_covariances(), c.gate_probability)
        # the gyro's yaw-rate scale error as teaching found it (the same unit, most likely):
        # known to within what a unit's scale changes from one run to another
        taught_k = self.map.teach.get("gyro_yaw_scale_error") if self.map.teach else None
        if isinstance(taught_k, int | float) and math.isfinite(taught_k) and abs(taught_k) < 0.2:
            self.ekf.set_scale(float(taught_k), c.taught_scale_sigma())
        self.counters = LocalizerCounters()
        self._speeds = SpeedTrack()
        self._history: deque[_Step] = deque()
        self.t_imu: float | None = None
        self.t_speed: float | None = None
        self.t_camera: float | None = None  # arrival (capture stamp) of the newest frame
        self.t_fix: float | None = None  # newest frame that gave a landmark fix
        self._good_frames = 0
        self._fault = ""
        self._area_changes = 0  # mow_only calls (part of :attr:`version`)
        self._lockout_since: float | None = None
        self._inflated = False
        self._lost_inflated = False
        self._frames_needed = 0  # more than localized_after_frames after an IMU gap
        self._w_last = np.zeros(3)
        #: the newest IMU sample's mean specific force along the body's x (m/s²), if it has
        #: one, and the speed carried on from the newest ground-speed sample by integrating
        #: the along-track acceleration since (:meth:`_carry_speed`)
        self._force_x: float | None = None
        self._carried_v: float | None = None
        self._t_last_frame: float | None = None  # time of the last frame's update
        self._shared_error = SharedFrameError(self.SPOT_SHARED)  # the frames' common error
        self._standstill = StandstillCalibrator()
        self._resets = 0
        self._injected = 0
        self._since = "since start"
        self.calibrating = True
        self.last_rejected = np.zeros(0, np.int64)  # map ids the last frame's χ² gate refused
        self.search: RelocalizationSearch | None = None  # no trustworthy pose: searching
        #: calls of :meth:`lifted` so far: a front end that sees it grow since its previous
        #: frame forgets its tracks (:attr:`~mowerhw.common.relocalization.SearchRequest.carried`)
        self.lifted_calls = 0
        self.relocalizes = False  # a relocalizer answers searches (use_relocalizer)
        self.probation: Probation | None = None  # a re-localization being checked
        # the magnetometer as a coarse compass, when the map has the taught field
        self.compass = Compass(self.map.compass) if self.map.compass is not None else None
        if start_pose is None:
            start_pose = (self.map.dock_position, self.map.dock_quaternion)
        self.reinitialise(start_pose)

    # ---------------------------------------------------------------------------- control

    def reinitialise(
        self,
        pose: tuple[ArrayLike, ArrayLike] | None = None,
        sigma_position_m: float | None = None,
        sigma_heading_rad: float | None = None,
        planar_cov: FloatArray | None = None,
    ) -> None:
        """Restart the filter at ``pose`` (position, q_wb), or at its current pose;
        ``planar_cov``: the (x, y, heading) covariance, when known in full."""
        c = self.cfg
        if pose is None:
            pos, quat = self.ekf.x.copy(), self.ekf.q.copy()
        else:
            pos = np.asarray(pose[0], dtype=np.float64).reshape(3)
            quat = np.asarray(pose[1], dtype=np.float64).reshape(4)
        s_pos = sigma_position_m if sigma_position_m is not None else c.init_sigma_position_m
        s_yaw = sigma_heading_rad if sigma_heading_rad is not None else c.init_sigma_heading_rad
        bias_var = None if self.counters.imu_samples else 0.005**2
        self.ekf.reset(
            pos,
            quat,
            s_pos,
            np.array([0.01, 0.01, s_yaw]),
            bias_var=bias_var,
            planar_cov=planar_cov,
        )
        self._good_frames = 0
        self._lockout_since = None
        self._inflated = False
        self._history.clear()
        self._resets += 1
        self._since = "since start" if self._resets == 1 else "since the filter restarted"

    def resume(
        self,
        position: ArrayLike,
        quaternion: ArrayLike,
        sigma_position_m: float,
        sigma_heading_rad: float,
        *,
        gyro_bias: ArrayLike | None = None,
        calibrate: bool = False,
        frames_needed: int = 1,
    ) -> None:
        """Restart from a pose this mower had (an estimator rebuilt in this run, or a
        restart): the pose widened by the σ given, the gyro bias kept (``gyro_bias``) or
        learnt again while the mower stands (``calibrate``), and not localized before
        ``frames_needed`` good frames."""
        self.reinitialise((position, quaternion), sigma_position_m, sigma_heading_rad)
        if gyro_bias is not None:
            self.ekf.bg = np.asarray(gyro_bias, dtype=np.float64).reshape(3).copy()
        self.calibrating = calibrate
        if calibrate:
            self._standstill = StandstillCalibrator()
        self.require_frames(frames_needed)
        if self.relocalizes:
            self.lose("to check the resumed pose against the landmarks", near=True, prior=True)
        else:
            self._on_probation("resume")

    # --------------------------------------------------------------- losing the pose (§18)

    #: good frames a global relocalization needs before the deck may run (4 Hz: 2.5 s)
    AFTER_RELOCALIZATION_FRAMES = 10

    def use_relocalizer(self) -> None:
        """A relocalizer will answer :meth:`search_near` (pixel level: the vision asks it):
        from now on every pose this filter starts from — the dock or the start pose, a
        resumed pose, the pose of a lock-out — is checked by it before the filter trusts
        it (:meth:`lose` with ``near``), and a lock-out searches instead of refitting."""
        self.relocalizes = True
        if self.search is None:
            self.lose("to check the start pose against the landmarks", near=True, prior=True)

    LIFTED = "since it was lifted"

    def lifted(self) -> None:
        """The safety functions say the mower is lifted (call it while they do): it may be
        put down anywhere. With a relocalizer its pose is given up and searched for, no
        answer accepted before it stands again; without (bearing level: every bearing names
        its landmark), the lock-out path recovers."""
        if not self.relocalizes:
            return
        self.lifted_calls += 1
        if self.search is not None and self.search.why == self.LIFTED:
            self.search.hold()
            return
        self.lose(self.LIFTED)

    def lose(self, why: str, near: bool = False, prior: bool = False) -> None:
        """Give the pose up (no prior at start, lifted, carried, a re-localization that did
        not check out): halt at once, and search for the pose with the global relocalizer's
        answers (:meth:`relocalization`). ``why`` completes "searching for the pose …";
        ``near``: first around the filter's own pose; ``prior``: that pose is a start pose
        being checked (no sign of trouble: it needs only the frames a start needs — after a
        kidnap or a lock-out, an answer needs the frames of a global relocalization)."""
        self.search = RelocalizationSearch(why, self.t_imu, near, prior)
        self.probation = None
        self._good_frames = 0
        self._lockout_since = None
        self.counters.searches += 1

    @property
    def searching(self) -> bool:
        """The pose is given up: frames are for :meth:`relocalization`, not updates."""
        return self.search is not None

    def compass_heading(self) -> tuple[float, float] | None:
        """What the compass says the heading is now (ψ, σ in the map's frame), or None: no
        taught field, or no steady, undisturbed reading."""
        if self.compass is None or self.t_imu is None:
            return None
        return self.compass.heading(self.t_imu)

    def search_heading(self) -> tuple[float, float] | None:
        """:meth:`compass_heading` while the search is global; otherwise None."""
        if self.search is None or self.search.near:
            return None
        return self.compass_heading()

    def search_near(self) -> tuple[float, float, float] | None:
        """Where the search looks: the filter's (x, y, heading) while it checks a prior,
        None while it searches everywhere (only while :attr:`searching`)."""
        if self.search is None or not self.search.near:
            return None
        p = self._pose2d(self.ekf.snapshot_view())
        return p.x, p.y, p.yaw

    def relocalization(self, t: float, answer: Relocalization) -> bool:
        """A global relocalizer's answer from the frame taken at ``t``; True when it is
        accepted (it agrees with the previous answer through the odometry between them,
        :class:`mowerhw.mow.recovery.RelocalizationSearch`): the filter restarts there,
        on probation."""
        if self.search is None:
            return False
        odometry_then = self._pose2d(self._state_at(t))
        search = self.search
        accepted = search.offer(t, answer, odometry_then)
        if accepted is None:
            search.widen(t)
            return False
        odometry_now = self._pose2d(self.ekf.snapshot_view())
        now = accepted.compose(odometry_then.between(odometry_now))
        z = float(answer.p_wb[2])
        self.search = None
        self.t_fix = t  # the answer is a landmark fix
        self.counters.relocalizations += 1
        planar = accepted_covariance(answer.covariance)
        self.reinitialise(
            (np.array([now.x, now.y, z]), yaw_to_quat(now.yaw)),
            math.sqrt(max(planar[0, 0], planar[1, 1])),  # the height's; x, y, heading: planar
            planar_cov=planar,
        )
        self._answer_frame_shared(
            odometry_then.distance(odometry_now), odometry_then.turn(odometry_now)
        )
        if answer.landmark_cross is not None:
            rows = self._rows_of([i for _, i in answer.inliers])
            if np.all(rows >= 0):
                self.ekf.set_landmark_cross(rows, answer.landmark_cross)
        if search.near and search.checks_prior:  # a start pose confirmed: as it would be
            self.require_frames(self._frames_needed, "since the prior pose was confirmed")
        else:  # a kidnap, a lock-out, an IMU gap: the frames of a relocalization
            where = "near the filter's pose" if search.near else "global"
            self.require_frames(self.AFTER_RELOCALIZATION_FRAMES, f"since a {where} relocalization")
        self._on_probation("local" if search.near else "global")
        return True

    def _on_probation(self, kind: str) -> None:
        """Check the pose before trusting it; a check already running goes on with its own
        deadline (a lock-out inside a check must not give it more time)."""
        need = max(self.cfg.localized_after_frames, self._frames_needed)
        if self.probation is not None:
            self.probation.consistent = 0
            self.probation.frames_needed = need
            return
        self.probation = Probation(kind, None, need)

    def _rows_of(self, ids: Sequence[int]) -> NDArray[np.int64]:
        """The filter's rows of map landmark ``ids`` (−1: not in the map)."""
        return np.array([self._row.get(int(i), -1) for i in ids], dtype=np.int64)

    @staticmethod
    def _pose2d(state: EkfState) -> Pose2D:
        return Pose2D(float(state.x[0]), float(state.x[1]), float(quat_to_yaw(state.q)))

    def _state_at(self, t: float) -> EkfState:
        """The filter's state at ``t``, as the frame update there will start from: the
        history's state at the IMU sample before ``t`` propagated over the rest of its
        interval, or the newest state extrapolated with the last rate for a frame slightly
        ahead of the IMU (:meth:`bearings`). Not the state at the sample before: a frame
        falls anywhere inside an IMU interval, and a mower turning at 1 rad/s turns 1.1° in
        the 20 ms between two 50 Hz samples — far more than a bearing's σ."""
        if self.t_imu is None:
            return self.ekf.snapshot_view()
        if t < self.t_imu:
            k = self._step_before(t)
            return self.ekf.snapshot_view() if k is None else self._state_in_history(k, t)
        if t > self.t_imu and t - self.t_imu <= self.stale_s["imu"] and self._w_last is not None:
            # without the carry the speed past a 0 reading is 0 (it is never extrapolated
            # through a stop): the wheels stand there, as :meth:`_step_one` decides
            speed, _ = self._speed_at(0.5 * (self.t_imu + t))
            return self._propagated(
                self.ekf.snapshot_view(), t - self.t_imu, self._w_last, speed, speed == 0.0
            )
        return self.ekf.snapshot_view()

    def _step_before(self, t: float) -> int | None:
        """The newest history step that ends at or before ``t`` (None: ``t`` is older than
        the history)."""
        hist = self._history
        return next((i for i in range(len(hist) - 1, -1, -1) if hist[i].t1 <= t), None)

    def _state_in_history(self, k: int, t: float) -> EkfState:
        """The state at ``t`` from history step ``k`` (the newest ending by ``t``): its state,
        carried over the rest of the next interval up to ``t`` unless that one was held."""
        hist = self._history
        nxt = hist[k + 1] if k + 1 < len(hist) else None
        if nxt is None or nxt.held or t <= hist[k].t1:
            return hist[k].state
        return self._propagated(
            hist[k].state, t - hist[k].t1, nxt.gyro, nxt.speed, nxt.wheels_still
        )

    def _propagated(
        self,
        state: EkfState,
        dt: float,
        gyro: FloatArray,
        speed: float,
        still: bool,
    ) -> EkfState:
        """``state`` (a copy or a view: it is copied, not changed) carried ``dt`` further at
        ``gyro`` and ``speed`` (``still``: :meth:`_advance`); the filter is left as it was."""
        now = self.ekf.snapshot()
        self.ekf.restore(state)
        self._advance(gyro, speed, dt, still)
        out = self.ekf.snapshot()
        self.ekf.restore(now)
        return out

    def inject_fault(self) -> None:
        """Fault injection (``runtime.fault_injection`` only): the filter's state becomes
        NaN, as a diverged estimator's would."""
        self.ekf.x[:] = np.nan
        self._injected += 1

    def is_finite(self) -> bool:
        """Every number of the state and its covariance is finite: the filter's own check,
        the one each step's fault check makes (:meth:`WorldPoseEKF.finite`)."""
        return self.ekf.finite()

    @property
    def version(self) -> tuple[Any, ...]:
        """Changes whenever the estimate may have changed (a new input, a restart)."""
        c = self.counters
        return (
            self.t_imu,
            self.t_speed,
            self.t_camera,
            self.t_fix,
            c.frames,
            c.faults,
            self._resets,
            c.searches,
            self._injected,
            self._area_changes,
        )

    @property
    def gyro_bias(self) -> FloatArray:
        """The filter's gyro bias estimate (rad/s, body frame)."""
        return self.ekf.bg.copy()

    # ------------------------------------------------------------------------------ inputs

    def imu(self, t: float, gyro_xyz: ArrayLike, accel_xyz: ArrayLike | None = None) -> None:
        """Gyro (rad/s, body frame): the mean rate over the interval ending at ``t``;
        ``accel_xyz``: the mean specific force over it (m/s², body frame, +g up at rest),
        if the IMU gives one (it carries a stale ground speed on: :meth:`_carry_speed`)."""
        gyro = np.asarray(gyro_xyz, dtype=np.float64).reshape(3)
        gx, gy, gz = gyro.tolist()
        if not (math.isfinite(t) and math.isfinite(gx + gy + gz)):
            self.counters.nonfinite_inputs += 1
            return
        force_x = None if accel_xyz is None else float(np.asarray(accel_xyz).reshape(-1)[0])
        self._force_x = force_x if force_x is not None and math.isfinite(force_x) else None
        self.counters.imu_samples += 1
        if self.t_imu is None:
            self.t_imu = float(t)
            self._remember(float(t), float(t), gyro, 0.0, held=True)
            return
        if t <= self.t_imu:
            return
        if self.calibrating and not self._standstill.add(float(t), gyro, self._force_x):
            self._end_calibration()  # turning or setting off: not a standstill any more
        if self.calibrating:  # standing still at the start: hold the pose, learn the bias
            self._remember(self.t_imu, float(t), gyro, 0.0, held=True, along=self._along_track())
            self.t_imu = float(t)
            return
        self._step(self.t_imu, float(t), gyro)
        self.t_imu = float(t)

    def magnetometer(self, t: float, mag_t: ArrayLike, accel: ArrayLike | None = None) -> None:
        """A magnetometer reading (T, body frame; the accelerometer's, m/s², when there is
        one): the compass a global search may use (:meth:`search_heading`)."""
        if self.compass is not None:
            self.compass.add(t, mag_t, accel)

    def speed(self, t: float, v: float) -> None:
        """Signed ground speed (m/s); NaN (invalid / not available) is ignored."""
        if not (math.isfinite(t) and math.isfinite(v)):
            self.counters.nonfinite_inputs += 1
            return
        previous = self._speeds.last_time
        self._speeds.add(t, v)
        if self.t_speed is None or t >= self.t_speed:
            self._carried_v = float(v)  # the newest: carried on from here if it goes silent
        self.t_speed = float(t) if self.t_speed is None else max(self.t_speed, float(t))
        if self.calibrating and v != 0.0:
            self._end_calibration()
        if previous is not None and 0.0 < t - previous <= self.stale_s["speed"]:
            self._respeed(previous)

    def bearings(self, t: float, ids: ArrayLike, unit_xyz: ArrayLike, refused: int = 0) -> None:
        """Unit bearings (body frame) of map landmarks ``ids`` seen in the frame taken at ``t``;
        ``refused``: landmarks the vision had matched but found in this frame far from where
        this filter predicts them (they count as disagreeing with the pose)."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        u = np.asarray(unit_xyz, dtype=np.float64).reshape(-1, 3)
        if ids.size != u.shape[0]:
            raise ValueError(f"{ids.size} ids but {u.shape[0]} bearings")
        if not math.isfinite(t):
            self.counters.nonfinite_inputs += 1
            return
        norms = np.linalg.norm(u, axis=1)
        good = np.all(np.isfinite(u), axis=1) & (norms > 0.5)
        self.counters.nonfinite_inputs += int((~good).sum())
        rows = self._rows_of(ids.tolist())
        self.counters.unknown_ids += int(np.sum(good & (rows < 0)))
        keep = good & (rows >= 0)
        rows, u = rows[keep], u[keep] / norms[keep, None]
        self.counters.frames += 1
        self.t_camera = float(t) if self.t_camera is None else max(self.t_camera, float(t))
        if self.t_imu is None or self.search is not None:
            return
        if t > self.t_imu + self.stale_s["imu"]:
            # the IMU is silent (unplugged): extrapolating to the frame would dead-reckon at
            # the held speed without any gyro; the frame is not used
            self.counters.frames_without_imu += 1
            return
        if t < self.t_imu - 1e-9:
            self._late_frame(float(t), rows, u, refused)
        else:
            if t > self.t_imu:  # a frame slightly ahead of the IMU: extrapolate to it
                self._step(self.t_imu, float(t), self._w_last)
                self.t_imu = float(t)
            self._frame_update(float(t), rows, u, refused)
        self._check_fault()

    # ------------------------------------------------------------------------- internals

    def _end_calibration(self) -> None:
        if not self.calibrating:
            return
        self.calibrating = False
        self._standstill.stop()
        if not self._standstill.calibrated:
            return
        bias = self._standstill.bias()
        var = self.cfg.gyro()[0] ** 2 * 100 / self._standstill.used
        # The bias is set out of band: every stored state gets it too, or a late frame from
        # before this moment would restore the uncalibrated bias.
        self.ekf.set_bias(bias, var)
        for st in self._history:
            st.state.set_bias(bias, var)
        self._drive_held(self._standstill.tail_start)

    def _drive_held(self, since: float | None) -> None:
        """The standstill is over: the steps held since ``since`` (the calibrator's tail,
        left out of the bias — a turn or a roll that had already begun) are driven now, at
        the bias just learnt and the ground speed now known. The pose, and every stored state
        after, moves by that motion (composed in the body frame where the tail began; held
        steps kept the covariance as it was, and so do these)."""
        if since is None:
            return
        hist = self._history
        k = len(hist)
        while k > 0 and hist[k - 1].t1 >= since:
            k -= 1
        dq, dp = np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3)  # the tail's motion so far
        for j in range(k, len(hist)):
            st = hist[j]
            if st.held:
                w = self.ekf.corrected_rate(st.gyro)
                # past the newest ground speed (the accelerometer ended the standstill):
                # carried on from it as a propagated step's is
                carried = self._carry_speed(st.t0, st.t1, st.along)
                speed, _ = self._speed_at(0.5 * (st.t0 + st.t1), carried)
                v = camera_velocity(speed, w, self.cfg.speed_contact_m)
                m = BodyMotion.of(w, v, st.t1 - st.t0)
                dp = dp + quat_to_rotmat(dq) @ m.disp
                dq = quat_multiply(dq, m.dq)
                st.drive_at(speed)
                st.held = False
            _move(st.state, dq, dp)
        _move(self.ekf, dq, dp)

    def _remember(
        self,
        t0: float,
        t1: float,
        gyro: FloatArray,
        speed: float,
        held: bool = False,
        widen: tuple[float, float] = (0.0, 0.0),
        speed_known: bool = True,
        wheels_still: bool = False,
        along: float | None = None,
    ) -> None:
        self._history.append(
            _Step(
                t0,
                t1,
                gyro.copy(),
                speed,
                self.ekf.snapshot(),
                held,
                widen,
                speed_known,
                wheels_still,
                along,
            )
        )
        horizon = t1 - self.cfg.history_s
        while len(self._history) > 2 and self._history[1].t1 < horizon:
            self._history.popleft()

    def _propagate(self, t0: float, t1: float, gyro: FloatArray, speed: float, still: bool) -> None:
        self._w_last = gyro.copy()
        self._advance(gyro, speed, t1 - t0, still)

    def _advance(self, gyro: FloatArray, speed: float, dt: float, still: bool) -> None:
        """The filter carried ``dt`` at a gyro reading and a ground speed: the body motion
        they make; ``still``: the wheels stood (no speed or slip noise, :meth:`_step_one`)."""
        w = self.ekf.corrected_rate(gyro)
        motion = BodyMotion.of(w, camera_velocity(speed, w, self.cfg.speed_contact_m), dt)
        self.ekf.propagate(motion, wheels_still=still)

    #: an IMU interval longer than the IMU's staleness limit (``imu.stale_after_s``: the
    #: runtime halted for it) is a gap — the IMU was unplugged or silent, the motion in it
    #: unknown: it is propagated in sub-steps with the ground speed measured meanwhile, and
    #: widened. A shorter one (a late or lost packet: the deck ran on through it) is only
    #: propagated in sub-steps (past :data:`SUBSTEPS_ABOVE_S`). (The gap was 50 ms: at 50 Hz
    #: a packet 30 ms late — 12 in 10 minutes on the bench under two CPU hogs — cost 2.5 s
    #: of mowing each.)
    SUBSTEPS_ABOVE_S = 0.05
    GAP_SUBSTEP_S = 0.01
    #: unknown motion during an IMU gap: position and heading σ grow this much per second
    GAP_POS_RATE = 0.1  # m/s
    GAP_YAW_RATE = 0.2  # rad/s
    #: good frames needed to be localized again after an IMU gap (4 Hz: 2.5 s)
    AFTER_GAP_FRAMES = 10
    AFTER_GAP = "since an IMU gap"

    def _step(self, t0: float, t1: float, gyro: FloatArray) -> None:
        if t1 - t0 <= self.SUBSTEPS_ABOVE_S:
            self._step_one(t0, t1, gyro)
            return
        gap = t1 - t0 > self.stale_s["imu"]
        n = math.ceil((t1 - t0) / self.GAP_SUBSTEP_S)
        edges = np.linspace(t0, t1, n + 1)
        for a, b in itertools.pairwise(edges):
            self._step_one(float(a), float(b), gyro, gap=gap)
        if gap:
            self.counters.imu_gaps += 1
            if self.relocalizes and self.search is None:
                # the motion in the gap is unknown, the widened pose's first associations
                # may pair wrong corners (measured on the bench: 13 cm off at σ 1.5 cm, and
                # permitted, after ten frames): the relocalizer checks it as it checks a
                # resumed pose, near where the filter thinks it is
                self.lose(self.AFTER_GAP, near=True)
            else:
                # trust the pose again only after a run of good frames
                self.require_frames(self.AFTER_GAP_FRAMES, self.AFTER_GAP)

    def _step_one(self, t0: float, t1: float, gyro: FloatArray, gap: bool = False) -> None:
        along = self._along_track()
        carried = self._carry_speed(t0, t1, along)
        speed, speed_stale = self._speed_at(0.5 * (t0 + t1), carried)
        pos_var = yaw_var = 0.0
        if speed_stale:
            self.counters.speed_stale_steps += 1
            bridged = self._carried_variance(t0, t1)
            if carried is not None and bridged is not None:
                self.counters.speed_carried_steps += 1
                speed, pos_var = carried, bridged
            else:
                # no ground speed: holding the last value would drive on while the mower
                # may have stopped; propagate at zero, the speed unknown up to max_speed_mps
                pos_var = (self.cfg.max_speed_mps * (t1 - t0)) ** 2
        if gap:
            pos_var += (self.GAP_POS_RATE * (t1 - t0)) ** 2
            yaw_var += (self.GAP_YAW_RATE * (t1 - t0)) ** 2
        lost = self.t_fix is not None and t1 - self.t_fix > self.cfg.lost_after_s
        if lost and self.relocalizes and self.search is None and not self._lost_inflated:
            # nothing recognised for long: a wider prior would let re-identification pair
            # features with the wrong landmarks; the relocalizer searches instead
            self._lost_inflated = True  # once per episode without a fix
            self.lose(f"since no landmark fix for {t1 - (self.t_fix or t1):.1f} s", near=True)
        elif lost and not self._lost_inflated:  # let re-identification look wider
            pos_var += 0.5**2
            yaw_var += math.radians(15.0) ** 2
            self._lost_inflated = True
            self.counters.inflations += 1
        # the wheels stand while the newest ground speed reads exactly 0 (the speed carried
        # on past it by the accelerometer is a guess at a mower setting off, and the next
        # sample drives those steps again, :meth:`_respeed`; counting it as speed noise grew
        # a standing mower's σ 0.8 → 2.5 mm in 2.5 s while its error stayed under 1 mm)
        still = speed == 0.0 or (not speed_stale and self._speeds.latest == 0.0)
        self._propagate(t0, t1, gyro, speed, still)
        self._widen((pos_var, yaw_var))
        self._remember(
            t0,
            t1,
            gyro,
            speed,
            widen=(pos_var, yaw_var),
            speed_known=not speed_stale,
            wheels_still=still,
            along=along,
        )
        self._check_fault()

    #: the along-track acceleration that carries the speed on is taken within ± this (m/s²)
    MAX_ALONG_MPS2 = 3.0

    def _along_track(self) -> float | None:
        """The IMU's along-track acceleration now: the specific force along the body's x
        less gravity's share through the filter's attitude, ``f_x − g·R[2,0]``
        (docs/design.md §3: body x forward, z up; ``R`` world ← body), within ±
        :data:`MAX_ALONG_MPS2`; None without an accelerometer."""
        f_x = self._force_x
        if f_x is None:
            return None
        w, x, y, z = self.ekf.q.tolist()
        # a mower's own drive and brakes stay well inside the bound; a bump's spike (3 g for
        # 60 ms on the bench) is not the wheels' speed, and the next sample tells what it was
        return _within(float(f_x - GRAVITY_MPS2 * 2.0 * (x * z - w * y)), self.MAX_ALONG_MPS2)

    def _carry_speed(self, t0: float, t1: float, along: float | None) -> float | None:
        """Carry the newest ground speed on over the step ``t0``–``t1`` (the part after
        that sample) at the along-track acceleration ``along`` (:meth:`_along_track`).
        Returns the carried speed at the step's middle (within ± ``max_speed_mps``), or
        None without a speed or an acceleration."""
        v0, t_s = self._carried_v, self.t_speed
        if v0 is None or t_s is None or along is None:
            return None
        dt = t1 - max(t0, t_s)
        if dt <= 0.0:
            return _within(v0, self.cfg.max_speed_mps)
        self._carried_v = v0 + along * dt
        return _within(v0 + 0.5 * along * dt, self.cfg.max_speed_mps)

    def _carried_variance(self, t0: float, t1: float) -> float | None:
        """While the ground speed is stale (``mow.accel_bridge_s`` past its limit at
        most), the position variance a step at the carried speed adds — an acceleration
        error ``δa`` makes the speed ``δa (t − t_s)`` off since the newest speed at
        ``t_s``, and the position ``δa (t − t_s)² / 2`` off: that σ at ``t1`` squared less
        the same at ``t0``, the first stale step taking all of it (the steps before the
        limit, driven at the same carried speed, added none: a sample then would have
        corrected them, `_respeed`). None: past that, propagated at zero speed."""
        t_s, c = self.t_speed, self.cfg
        limit = self.stale_s["speed"]
        if t_s is None or not 0.0 < c.accel_bridge_s >= t1 - t_s - limit:
            return None
        before = 0.5 * c.accel_sigma_mps2 * (t0 - t_s) ** 2 if t0 - t_s > limit else 0.0
        after = 0.5 * c.accel_sigma_mps2 * (t1 - t_s) ** 2
        return after**2 - before**2

    def _speed_at(self, t: float, carried: float | None = None) -> tuple[float, bool]:
        """The ground speed to propagate with at ``t``, and whether it is stale (then 0).
        Past the newest sample: the speed the accelerometer ``carried`` on from it, or
        without one its slope extrapolated; the next sample drives those steps again
        (:meth:`_respeed`). Before it (IMU samples held up on this computer while the
        speed came on time): interpolated between the samples around ``t``."""
        if self.t_speed is None or t - self.t_speed > self.stale_s["speed"]:
            return 0.0, True
        if carried is not None and t > self.t_speed:
            return carried, False
        return self._speeds.known(t), False

    def _respeed(self, since: float) -> None:
        """A ground-speed sample has come: the IMU intervals after the one before it (at
        ``since``) were driven at a speed extrapolated from older samples — at a start, at 0
        for a whole sample period while the mower already rolled. Now the speed then is
        known (:meth:`_shaped_speeds`: the accelerometer's between the two samples, or
        :meth:`SpeedTrack.known`'s line; steps held for the start-up calibration are
        :meth:`_drive_held`'s): the pose, and every stored state after, moves by
        the distance missed. Position is linear in the speed (``v = s x̂ − ω × p``), so an
        interval's share is ``R J_l(ω dt) x̂ δs dt`` (the propagation's own increment,
        :class:`BodyMotion`); the covariance is unchanged to first order."""
        hist = self._history
        k = len(hist)
        while k > 0 and 0.5 * (hist[k - 1].t0 + hist[k - 1].t1) > since:
            k -= 1
        if k == 0 or k == len(hist):
            return
        shaped = self._shaped_speeds(k)
        if shaped is not None:
            self._carried_v = float(shaped[-1])  # carried on from the newest step's end
        shift = np.zeros(3)
        for j in range(k, len(hist)):
            st = hist[j]
            if not st.held and st.speed_known:
                dt = st.t1 - st.t0
                mid = 0.5 * (st.t0 + st.t1)
                known = self._speeds.known(mid) if shaped is None else float(shaped[j - k])
                ds = known - st.speed
                if ds != 0.0:
                    before = hist[j - 1].state
                    w = st.gyro - before.bg
                    w[2] *= 1.0 - before.k
                    step = left_jacobian_times(w * dt, np.array([ds * dt, 0.0, 0.0]))
                    shift = shift + quat_to_rotmat(before.q) @ step
                    st.drive_at(known)
            if shift.any():
                st.state.x = st.state.x + shift
        if shift.any():
            self.ekf.x = self.ekf.x + shift

    def _shaped_speeds(self, first: int) -> FloatArray | None:
        """The ground speed at the middle of each stored step from ``first`` on, and at the
        newest step's end, between the two newest speed samples (and past the newest) as the
        steps' along-track accelerations shape it (:func:`accel_shaped_speeds`, their miss
        within 3 ``accel_sigma_mps2`` over the samples' interval); None without two samples,
        without an acceleration for every step since the older or steps up to the newer, or
        with a larger miss (the caller interpolates then)."""
        samples = self._speeds.samples
        if len(samples) < 2:
            return None
        a, b = samples[-2], samples[-1]
        hist = self._history
        k = first
        while k > 0 and hist[k - 1].t1 > a[0]:  # from the step the older sample falls in
            k -= 1
        steps = list(itertools.islice(hist, k, None))
        if any(st.along is None for st in steps):
            return None
        rows = np.array([(st.t0, st.t1, st.along) for st in steps], dtype=np.float64)
        at = np.append(0.5 * (rows[first - k :, 0] + rows[first - k :, 1]), rows[-1, 1])
        max_miss = 3.0 * self.cfg.accel_sigma_mps2 * (b[0] - a[0])
        return accel_shaped_speeds(a, b, rows, at, max_miss)

    def _widen(self, widen: tuple[float, float]) -> None:
        """Add uncertainty the motion model does not know about (kept in the history, so a
        late frame's re-propagation applies it again)."""
        self.ekf.widen(*widen)

    def _late_frame(
        self, t: float, rows: NDArray[np.int64], u: FloatArray, refused: int = 0
    ) -> None:
        """Apply a frame at its own time and re-propagate the IMU samples since (exact)."""
        hist = self._history
        k = self._step_before(t)
        if k is None:
            self.counters.late_frames_dropped += 1
            return
        self.counters.late_frames += 1
        self.ekf.restore(self._state_in_history(k, t))  # with the next interval up to t
        after = list(hist)[k + 1 :]
        resets = self._resets
        self._frame_update(t, rows, u, refused, after[0].gyro if after else None)
        if self._resets != resets:  # the update re-initialised the filter at t: replay since
            for j, st in enumerate(after):
                t0 = t if j == 0 and t > st.t0 else st.t0
                if st.t1 > t0:
                    self._propagate(t0, st.t1, st.gyro, st.speed, st.wheels_still)
                self._widen(st.widen)
                self._remember(
                    t0,
                    st.t1,
                    st.gyro,
                    st.speed,
                    widen=st.widen,
                    speed_known=st.speed_known,
                    wheels_still=st.wheels_still,
                    along=st.along,
                )
            return
        # re-propagate: the rest of that interval, then every later one, as they were
        for j, st in enumerate(after):
            t0 = t if j == 0 and t > st.t0 else st.t0
            if not st.held and st.t1 > t0:
                self._propagate(t0, st.t1, st.gyro, st.speed, st.wheels_still)
            self._widen(st.widen)
            hist[k + 1 + j] = replace(st, state=self.ekf.snapshot())

    def _frame_update(
        self,
        t: float,
        rows: NDArray[np.int64],
        u: FloatArray,
        refused: int = 0,
        gyro: FloatArray | None = None,
    ) -> None:
        """One frame's update at its time ``t`` (``gyro``: the reading then, for what a
        stamp error turns; default the latest)."""
        c = self.cfg
        rate = None  # only a stamp error needs the body rate
        if c.frame_stamp_sigma_s > 0.0:
            rate = self.ekf.corrected_rate(self._w_last if gyro is None else gyro)
        out = self.ekf.update(
            rows,
            self.landmarks[rows],
            u,
            self._bearing_sigma(t),
            rate=rate,
            stamp_sigma=c.frame_stamp_sigma_s,
            own_sigma=c.bearing_sigma_rad,
        )
        self.last_rejected = self.ids[rows[~out.accepted]]
        self.counters.bearings_used += out.used
        self.counters.bearings_rejected += out.rejected
        # a fix: enough landmarks, and most of those in view agree with the estimate — or,
        # while the filter is sure of itself, many do (the others are then mistaken
        # associations, not a wrong pose: measured on the bench, a well-tracking filter locked
        # out at 3 mm error when re-identification offered more wrong pairs than right ones)
        # (``refused``: matched landmarks the vision found far from their prediction — tracks
        # that were right and moved, as when the mower is carried: never outvoted)
        agree = out.used >= 0.5 * (rows.size + refused) or (
            out.used >= 2 * c.min_landmarks
            and self.sigma_xy() < self.CONFIDENT_SIGMA_M
            and refused < out.used
        )
        fix = out.used >= c.min_landmarks and agree
        if self.probation is not None:
            accepted = np.concatenate([out.accepted, np.zeros(refused, bool)])
            self._check(t, out.nis, accepted, fix)
        if fix:
            self.counters.frames_with_fix += 1
            self._good_frames += 1
            self.t_fix = t if self.t_fix is None else max(self.t_fix, t)
            self._lockout_since = None
            self._inflated = False
            self._lost_inflated = False
            if self._fault and self._good_frames >= c.localized_after_frames:
                self._fault = ""
            return
        if rows.size + refused >= c.min_landmarks:  # it sees landmarks, believes too few
            self._lockout(t, rows, u)
        if not self.relocalizes or self.search is not None:
            return
        # with a relocalizer: the pose is given up at once when most of the landmarks the
        # vision had matched jumped away from it (carried or pushed: a kidnap the lift switch
        # missed), or when the landmarks have disagreed with it for SEARCH_AFTER_S; the
        # relocalizer checks the pose where it is first, then everywhere
        if refused >= c.min_landmarks and refused >= 0.5 * (rows.size + refused):
            self.lose(
                f"since {refused} of {rows.size + refused} landmarks in view jumped away from "
                f"where the pose puts them (carried or pushed?)",
                near=True,
            )
        elif self._lockout_since is not None and t - self._lockout_since >= self.SEARCH_AFTER_S:
            self.lose(
                f"since the landmarks in view disagreed with the pose for "
                f"{t - self._lockout_since:.1f} s",
                near=True,
            )

    #: between two frames the mower moved less than this: it stands (the same view again)
    STILL_M, STILL_RAD = 0.01, math.radians(0.5)
    #: once it moves, the common part of a frame's error keeps exp(−away) of itself, ``away``
    #: the distance driven over this (or the angle turned over that): the next frames still
    #: see the same corners from nearly the same place. 0.35 m: what is left of a corner's
    #: rendered error beyond its landmark's own bias and the frame's shared part keeps
    #: 0.56–0.76 of itself from one frame to the next, 0.11 m on (measured, pixel level,
    #: tools/bearing_errors_pixel.py), and exp(−0.11/0.35) = 0.73; the whole error keeps far
    #: more (0.94 at 0.1–0.15 m, 0.80 at 1 m: README, issue 18, stop 64). With the exact model of
    #: :class:`~mowerhw.mow.spot.SharedFrameError` (stop 63) the pixel start pools' NEES bins
    #: inside their bounds: paper 18/20, look-alike 13/20 (its six misses the standing
    #: answer's own σ); 0.2 m (fitted in stops 54–61 to the count rule before) 17 and 10/20,
    #: the last driving bins over (3.6–4.0) (README, issue 18)
    SPOT_M, SPOT_RAD = 0.35, math.radians(10.0)
    #: the share of a standing frame's bearing variance that every frame from that spot has
    #: too (a corner's detection bias, the same pixels rendered again); the rest is its own.
    #: Chosen, then measured against σ·√k on the same maps and runs (tools/recovery_pixel.py,
    #: seed 1, paper and look-alike, 100 starts and 20 kidnaps each): NEES bins inside the 95 %
    #: bounds 71 of 80 against 68, over-confident bins 5 against 7 (README). 0.75 left a mower
    #: standing after a 0.3 m wrong answer 6.6 cm off after 12 s of right bearings
    #: (tests/test_recovery.py), its check less sharp
    SPOT_SHARED = 0.5

    def _bearing_sigma(self, t: float) -> float:
        """The bearing σ of this frame's update. Frames from a mower standing still see the
        same corners from the same place: their errors (a corner's detection bias, the
        map's) are partly the same each time, not independent. A share ``f``
        (:data:`SPOT_SHARED`) of each frame's variance is common to nearby frames, an AR(1)
        along the track: standing it stays, driving it keeps ``ρ = exp(−away)`` of itself
        for the distance driven and the angle turned since the last frame (:data:`SPOT_M`,
        :data:`SPOT_RAD`; :meth:`shared_from_last`). The frame's σ is a lone frame's over the
        square root of the information it adds (:class:`mowerhw.mow.spot.SharedFrameError`,
        exact for that model): standing, ``k`` frames are worth ``k / ((1 − f) + k f)``
        (at most ``1/f``, however long the mower stands), so a minute at the dock does not
        make the filter surer than a few frames can (measured: NEES 7–11 for the 3 s a
        relocalized mower stands with every frame counted in full). A mower that keeps
        moving gets ``(1 − ρ)``-ish of a frame each time, not a lone frame's worth: a
        rendered corner's error changes slowly along a track (measured, pixel level:
        next-frame correlation 0.56–0.76 of the part that stays neither with a landmark nor
        with the frame)."""
        t_from, self._t_last_frame = self._t_last_frame, t
        moved, turned = self._motion_between(t_from, t)
        self._shared_error.move_on(self.shared_from_last(moved, turned))
        return self.cfg.bearing_sigma_rad * self._shared_error.frame()

    def _answer_frame_shared(self, moved: float, turned: float) -> None:
        """An accepted answer is the first frame from its spot (:meth:`_bearing_sigma`): the
        filter restarts with that frame's covariance, so the frames after it share its
        error as they would a frame's (counted afresh, they counted the standing mower's
        spot once more than it is worth). ``moved``, ``turned``: the odometry from the
        answer's frame to now, where the filter restarts (its history begins here)."""
        self._shared_error = SharedFrameError(self.SPOT_SHARED)
        self._shared_error.frame()
        self._shared_error.move_on(self.shared_from_last(moved, turned))
        self._t_last_frame = self.t_imu

    @classmethod
    def shared_from_last(cls, moved: float, turned: float) -> float:
        """The share ρ of the last frame's common error the next one still has, when the
        mower moved ``moved`` m and turned ``turned`` rad in between: 1 standing still,
        ``exp(−(moved/SPOT_M + turned/SPOT_RAD))`` moving (0 for an unknown motion)."""
        if moved < cls.STILL_M and turned < cls.STILL_RAD:
            return 1.0
        return math.exp(-(moved / cls.SPOT_M + turned / cls.SPOT_RAD))

    def _motion_between(self, t_from: float | None, t: float) -> tuple[float, float]:
        """Distance driven (m) and angle turned (rad) from ``t_from`` (the last frame's time)
        to ``t``, from the ground-speed samples taken up to ``t`` and the IMU intervals kept —
        the same for a frame on time and one applied late; unknown (infinite) without a last
        frame or when the IMU history does not reach back that far."""
        hist = self._history
        if t_from is None or not hist or hist[0].t0 > t_from or t <= t_from:
            return math.inf, math.inf
        turned = 0.0
        for st in reversed(hist):
            if st.t1 <= t_from:
                break
            dt = min(st.t1, t) - max(st.t0, t_from)
            if dt > 0.0:
                g, bg = st.gyro, st.state.bg
                turned += math.hypot(g[0] - bg[0], g[1] - bg[1], g[2] - bg[2]) * dt
        return self._speeds.distance(t_from, t), turned

    def _check(self, t: float, nis: FloatArray, accepted: NDArray[np.bool_], fix: bool) -> None:
        """One frame of the consistency check after a re-localization."""
        assert self.probation is not None
        verdict = self.probation.frame(t, nis, accepted, fix)
        if verdict == "passed":
            self.counters.checks_passed += 1
            self.probation = None
        elif verdict == "failed":
            self.counters.checks_failed += 1
            p = self.probation
            self.lose(f"since the {p.kind} re-localization did not check out ({p.last})")

    def _lockout(self, t: float, rows: NDArray[np.int64], u: FloatArray) -> None:
        c = self.cfg
        if self._lockout_since is None:
            self._lockout_since = t
            self.counters.lockouts += 1
            # the bearings disagree: the gyro's scale may not be the one the map taught (a
            # unit changed since): known again only to the untaught prior (measured: a unit
            # 5–6 % off its taught scale, trusted to 0.3 %, was never learnt — halted for good)
            self.ekf.reopen_scale(c.gyro()[2])
            return
        waited = t - self._lockout_since
        if waited >= c.lockout_s and not self._inflated:
            self.ekf.inflate(0.5, math.radians(15.0))
            self._inflated = True
            self._good_frames = 0
            self._since = (
                f"since a lock-out (fewer than half of the landmarks in view agreed with the "
                f"estimate for {waited:.1f} s)"
            )
            self.counters.inflations += 1
            self._on_probation("lock-out")
        elif waited >= 2 * c.lockout_s:
            self._refit(rows, u)

    #: with a relocalizer, a lock-out this long (s) gives the pose up at once (kidnap)
    SEARCH_AFTER_S = 1.0

    def _refit(self, rows: NDArray[np.int64], u: FloatArray) -> None:
        """Re-initialise from one frame: fit the pose to the bearings of known landmarks,
        starting from the current position at several headings, keeping the best fit."""
        sigma = self.cfg.bearing_sigma_rad
        best = None
        r0 = self.ekf.R
        for yaw in np.radians([0, 45, -45, 90, -90, 135, -135, 180]):
            fit = fit_pose_to_bearings(
                self.landmarks[rows],
                u,
                yaw_rotation(float(yaw)) @ r0,
                self.ekf.x,
                sigma,
                iterations=25,
            )
            if np.all(np.isfinite(fit.t_wb)) and (best is None or fit.rms_rad < best.rms_rad):
                best = fit
        if best is None or best.rms_rad > 3 * sigma:
            return  # no credible fit either: stay halted, try again next frame
        self.counters.reinitialisations += 1
        self.reinitialise((best.t_wb, rotmat_to_quat(best.r_wb)), 0.2, math.radians(5.0))
        self._on_probation("refit")

    def _check_fault(self) -> None:
        if self.ekf.finite():
            return
        self.counters.faults += 1
        self._fault = "the estimator produced non-finite values and was restarted"
        good = next((s.state for s in reversed(self._history) if s.state.finite()), None)
        if good is not None:
            self.ekf.restore(good)
        if not self.ekf.finite():
            self.ekf.bg = np.zeros(3)
            self.ekf.x = self.map.dock_position.copy()
            self.ekf.q = self.map.dock_quaternion.copy()
        self.reinitialise(None, 1.0, math.radians(30.0))
        self._on_probation("fault restart")

    # ----------------------------------------------------------------------------- outputs

    def predict_bearings(
        self, t: float | None = None
    ) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """Every map landmark as the filter expects to see it in a frame taken at ``t``
        (default: now): map ids, unit bearings (body frame) and the covariance of a measured
        bearing about each (tangent basis of the prediction). For re-identification."""
        state = None if t is None else self._state_at(t)
        rows = np.arange(self.ids.size)
        h, cov = self.ekf.predict_bearings(
            rows, self.landmarks, self.cfg.bearing_sigma_rad, state=state
        )
        return self.ids.copy(), h, cov

    def corrected_rate(self, gyro: FloatArray) -> FloatArray:
        """A gyro reading's body rate with the filter's bias and yaw-rate scale taken out
        (during the start-up calibration: the mean so far)."""
        if self.calibrating:
            return self._standstill.corrected(gyro)
        return self.ekf.corrected_rate(gyro)

    def pose(self) -> Pose:
        """The newest estimate: t, position, q_wb, covariance (position then rotation)."""
        t = self.t_imu if self.t_imu is not None else float("nan")
        return Pose(t, self.ekf.x.copy(), self.ekf.q.copy(), self.ekf.pose_covariance())

    def ground_covariance(self) -> FloatArray:
        """(3, 3) the (x, y, heading) covariance against the ground itself: :meth:`pose`'s,
        which is against the map (what containment needs: the taught edge shares the map's
        frame), plus the map frame's own error where the mower is
        (:func:`mowerhw.map.frame_pose_covariance`; nothing more for a map without it).
        What the teach could not see is not in it: the ground-speed sensor's own scale error
        (a tyre's circumference) makes the whole map that much larger or smaller, and
        bearings cannot tell (design.md §4)."""
        cov: FloatArray = self.ekf.pose_covariance()[np.ix_([0, 1, 5], [0, 1, 5])]
        if self.map.frame_covariance is not None:
            cov = cov + frame_pose_covariance(self.map.frame_covariance, self.ekf.x[:2])
        return cov

    def require_frames(self, n: int, why: str = "since a restart") -> None:
        """Not localized again until ``n`` good frames from now (after a discontinuity: an
        IMU gap, a rebuilt or resumed estimator); ``why`` ends the halt message."""
        self._good_frames = 0
        self._since = why
        self._frames_needed = max(int(n), self.cfg.localized_after_frames)

    @property
    def localized(self) -> bool:
        need = max(self.cfg.localized_after_frames, self._frames_needed)
        return (
            self._good_frames >= need
            and not self._fault
            and self.search is None
            and self.probation is None
        )

    def sigma_xy(self) -> float:
        """Largest standard deviation of the horizontal position (m)."""
        return self.ekf.sigma_xy()

    def mow_only(self, areas: Sequence[str]) -> None:
        """Mow only these mowing areas of the map from now on (empty: all), the others
        becoming transit; the pose and its filter go on untouched. ValueError naming the
        areas there are for a name the map does not have."""
        geometry = LawnGeometry.of_map(self.map, tuple(areas))
        self.geometry = geometry
        self._containment = Containment(geometry, self._containment_cfg)
        self._area_changes += 1

    def containment(self) -> ContainmentResult:
        """The containment decision for the newest estimate. Whether the sensors are fresh is
        the permit gate's to judge (:class:`mowerhw.mow.gate.PermitGate`), not the filter's."""
        t = self.t_imu if self.t_imu is not None else float("nan")
        halt = self._halt_reason()
        x, y = float(self.ekf.x[0]), float(self.ekf.x[1])
        return self._containment.evaluate(t, x, y, self.sigma_xy(), halt)

    def _halt_reason(self) -> tuple[Reason, str] | None:
        if self.t_imu is None:
            return Reason.NOT_LOCALIZED, "no IMU sample yet"
        if self._fault:
            return Reason.FAULT, self._fault
        if self.search is not None:
            return Reason.NOT_LOCALIZED, self.search.describe()
        if self._lockout_since is not None:
            # bearings of several landmarks disagree with the pose: carried elsewhere, or the
            # pose is wrong — halt at once, not only when the last fix is too old
            return Reason.UNCERTAIN, (
                f"the landmarks in view disagree with the pose (since "
                f"{self.t_imu - self._lockout_since:.1f} s)"
            )
        if self.probation is not None and self._good_frames >= max(
            self.cfg.localized_after_frames, self._frames_needed
        ):
            return Reason.NOT_LOCALIZED, self.probation.describe()
        if not self.localized:
            need = max(self.cfg.localized_after_frames, self._frames_needed)
            return Reason.NOT_LOCALIZED, f"{self._good_frames}/{need} landmark fixes {self._since}"
        limit = self.cfg.max_dead_reckoning_s
        if self.t_fix is not None and self.t_imu - self.t_fix > limit:
            return Reason.UNCERTAIN, (
                f"no landmark fix for {self.t_imu - self.t_fix:.1f} s (limit {limit} s); "
                f"odometry σ {self.sigma_xy():.3f} m"
            )
        return None

    def status(self) -> dict[str, Any]:
        """Counters and state for logs, the control socket and recordings."""
        p = self.pose()
        return {
            "t": p.t,
            "localized": self.localized,
            "calibrating": self.calibrating,
            "searching": self.search.describe() if self.search is not None else "",
            "checking": self.probation.describe() if self.probation is not None else "",
            "position": p.position.tolist(),
            "sigma_xy_m": self.sigma_xy(),
            # against the ground (the map frame's own error too: ground_covariance)
            "sigma_xy_ground_m": largest_sigma_xy(self.ground_covariance()),
            "gyro_bias": self.ekf.bg.tolist(),
            "compass": self._compass_status(),
            **vars(self.counters),
        }

    def _compass_status(self) -> dict[str, Any] | None:
        """The compass: None when the map has no taught field; else the heading it gives now
        (degrees in the map's frame, None while it has no steady reading) and how many
        readings it refused as not the taught field."""
        if self.compass is None:
            return None
        found = self.compass_heading()
        return {
            "heading_deg": None if found is None else round(math.degrees(found[0]), 1),
            "sigma_deg": None if found is None else round(math.degrees(found[1]), 1),
            "disturbed_readings": self.compass.disturbed,
        }


def _move(s: EkfState | WorldPoseEKF, dq: FloatArray, dp: FloatArray) -> None:
    """Move a pose by a motion ``(dq, dp)`` given in its own body frame."""
    s.x = s.x + quat_to_rotmat(s.q) @ dp
    s.q = quat_multiply_unit(s.q, dq)
