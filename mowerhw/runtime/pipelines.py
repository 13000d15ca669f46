"""Estimator chains the daemon feeds in time order: teach (Teacher + TeachVision) and mow
(Localizer + MowVision + containment).

Pure computation: samples in (host-clock seconds, body-frame gyro, signed speed, front-end
tracks), estimates out. The daemon decides when to feed them; the heavy front-end tracking
(:meth:`mowerhw.vision.VisionBase.track`) runs on its worker thread, and only
:meth:`frame_tracks` (association, estimator update) runs here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from mowerhw.camera import CameraModel
from mowerhw.common.buffer import SensorBuffer
from mowerhw.common.samples import Stream
from mowerhw.config import Config
from mowerhw.frontend.tracker import FrameTracks
from mowerhw.map import LawnMap
from mowerhw.mow import Localizer
from mowerhw.mow.containment import ContainmentResult
from mowerhw.teach import Teacher
from mowerhw.teach.teacher import TeachResult
from mowerhw.vision import MowVision, TeachVision

FloatArray = NDArray[np.float64]


#: the buffer stream of the front end's per-frame tracks (stamped with the capture time)
TRACKS = "tracks"


class StartPose(NamedTuple):
    """A pose a new localizer starts from: position, q_wb, and the gyro bias if known."""

    position: FloatArray
    quaternion: FloatArray
    gyro_bias: FloatArray | None = None


class PlanPose(NamedTuple):
    """The mower for the status page: time, position (3), q_wb (w, x, y, z), and where the
    estimator has them in the map frame the covariance (6 × 6: position, then rotation in
    world axes) and the largest σ of the horizontal position (m), as the localizer gives it."""

    t: float
    position: FloatArray
    quaternion: FloatArray
    covariance: FloatArray | None
    sigma_xy: float | None = None


@dataclass(frozen=True)
class BuildRequest:
    """An estimator chain the runtime wants built (seconds of work: off the event loop).

    ``serial`` names it: the runtime installs the chain only if no newer request came since.
    ``resumed``: a pose a previous run saved (the gyro is calibrated again, the mower stands)."""

    serial: int
    kind: str  # "teach" or "mow"
    lawn_map: LawnMap | None = None
    start_pose: StartPose | None = None
    resumed: bool = False
    mow_areas: tuple[str, ...] | None = None  # mow only these (None: the config's mow.areas)


def build_pipeline(config: Config, camera: CameraModel, req: BuildRequest) -> Pipeline:
    """The chain ``req`` asks for (pure: the same inputs give the same chain)."""
    if req.kind == "teach":
        return TeachPipeline(config, camera)
    if req.lawn_map is None:
        raise ValueError("a mow chain needs a map")
    if req.mow_areas is not None:
        config = replace(config, mow=replace(config.mow, areas=req.mow_areas))
    return MowPipeline(config, camera, req.lawn_map, start_pose=req.start_pose)


def feed_ready(pipe: Pipeline, buffer: SensorBuffer, until: float) -> None:
    """Hand the estimator every buffered sample up to ``until``, in time order (the daemon
    and a replay both feed it this way)."""
    for stream, s in buffer.pop_ready(until):
        if stream == Stream.IMU:
            pipe.imu(s.t, s.gyro, s.accel)
        elif stream == Stream.SPEED:
            pipe.speed(s.t, s.speed_mps if s.valid else float("nan"))
        elif stream == TRACKS:
            pipe.frame_tracks(s)


def yaw_of(q: FloatArray) -> float:
    """Heading (rad) of a Hamilton quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


class TeachPipeline:
    """Teach mode: standstill calibration, the drive, then :meth:`finish` → map."""

    #: frames reach the teacher in time order: the IMU is held back this long for them
    LAG_S = 0.8
    #: automatic end of the teach drive: stopped this long, back within this of the start,
    #: after driving at least this far
    AUTO_STOPPED_S = 2.0
    AUTO_CLOSE_M = 1.5
    AUTO_MIN_DISTANCE_M = 10.0

    def __init__(self, config: Config, camera: CameraModel, seed: int = 0) -> None:
        self.config = config
        self.teacher = Teacher(config.teach, camera=camera)
        self.vision = TeachVision(
            self.teacher, camera, config.camera.body_rotation(), config.frontend, seed=seed
        )
        self.lag_s = self.LAG_S
        self._stopped_since: float | None = None
        self.t_last = -math.inf

    def imu(self, t: float, gyro: FloatArray, accel: FloatArray | None = None) -> None:
        self.teacher.imu(t, gyro)
        self.t_last = t

    def magnetometer(self, t: float, mag: FloatArray, accel: FloatArray | None) -> None:
        self.teacher.magnetometer(t, mag, accel)

    def speed(self, t: float, v: float) -> None:
        self.teacher.speed(t, v)
        if v == 0.0:
            self._stopped_since = t if self._stopped_since is None else self._stopped_since
        else:
            self._stopped_since = None

    def frame_tracks(self, tracks: FrameTracks) -> None:
        self.vision.use(tracks)

    def loop_done(self) -> bool:
        """The operator has driven a loop and stopped back at the start."""
        tch = self.teacher
        if tch.phase != "driving" or tch.distance_m < self.AUTO_MIN_DISTANCE_M:
            return False
        if tch.zone_open:  # back at the dock inside a marked zone: the zone goes on
            return False
        if self._stopped_since is None or self.t_last - self._stopped_since < self.AUTO_STOPPED_S:
            return False
        pos, _ = tch.world_pose()
        return float(np.hypot(pos[0], pos[1])) < self.AUTO_CLOSE_M

    def finish(self) -> tuple[TeachResult, LawnMap]:
        """Loop closure and boundary (seconds of work: call it off the event loop)."""
        result = self.vision.annotate(self.teacher.finish())
        return result, LawnMap.from_teach_result(result)

    def plan_pose(self) -> PlanPose | None:
        """Where the teacher puts the mower now (eqs 19–20), for the status page; ``None``
        before the drive starts. Its uncertainty is robot-centric (no ellipse in the map)."""
        tch = self.teacher
        if tch.phase != "driving":
            return None
        pos, q = tch.world_pose()
        return PlanPose(self.t_last, pos, q, None)

    def landmarks_xyz(self) -> FloatArray:
        """(N, 4): id, x, y, z of every landmark located so far (the page's live map)."""
        ids, xyz, _ = self.teacher.known_landmarks()
        return np.column_stack([ids.astype(np.float64), xyz]) if ids.size else np.zeros((0, 4))

    def status(self) -> dict[str, Any]:
        tch = self.teacher
        out: dict[str, Any] = {
            "phase": tch.phase,
            "distance_m": round(tch.distance_m, 2),
            "frames": tch.counters["frames"],
            "keyframes": len(tch.keyframes),
        }
        if tch.phase == "driving":
            pos, q = tch.world_pose()
            out.update(x=round(float(pos[0]), 3), y=round(float(pos[1]), 3), yaw=yaw_of(q))
        return out


class MowPipeline:
    """Mow mode: localize against the map, decide containment."""

    LAG_S = 0.0  # the localizer takes late frames itself (state history, docs/design.md §5)

    def __init__(
        self,
        config: Config,
        camera: CameraModel,
        lawn_map: LawnMap,
        start_pose: StartPose | None = None,
        seed: int = 0,
    ) -> None:
        self.config = config
        self.map = lawn_map
        start = None if start_pose is None else (start_pose.position, start_pose.quaternion)
        self.localizer = Localizer(lawn_map, config, start_pose=start)
        self.vision = MowVision(
            self.localizer,
            camera,
            config.camera.body_rotation(),
            config.frontend,
            seed=seed,
            pixel_sigma=config.camera.pixel_sigma,
        )
        self.lag_s = self.LAG_S
        self._cont: ContainmentResult | None = None
        self._cont_key: tuple[Any, ...] | None = None
        self._finite = True
        self._finite_key: tuple[Any, ...] | None = None
        self._news = (0, 0, 0)  # searches, relocalizations, failed checks already told

    def news(self) -> list[str]:
        """What the operator should read in the log since the last call: the pose given up
        (and why), the pose found again (and where) — issue 18. Each once."""
        loc = self.localizer
        c = loc.counters
        out: list[str] = []
        if c.searches != self._news[0] and loc.search is not None:
            out.append(loc.search.describe())
        if c.relocalizations != self._news[1]:
            _, x, y, heading, sigma = self.pose()
            out.append(
                f"pose found: x {x:.2f} m, y {y:.2f} m, heading {math.degrees(heading):.1f}° "
                f"(σ {sigma:.3f} m); checking it before the deck may run"
            )
        if c.checks_failed != self._news[2]:
            out.append("a re-localization did not check out: searching again")
        self._news = (c.searches, c.relocalizations, c.checks_failed)
        return out

    def imu(self, t: float, gyro: FloatArray, accel: FloatArray | None = None) -> None:
        self.localizer.imu(t, gyro, accel)

    def magnetometer(self, t: float, mag: FloatArray, accel: FloatArray | None) -> None:
        self.localizer.magnetometer(t, mag, accel)

    def speed(self, t: float, v: float) -> None:
        self.localizer.speed(t, v)

    def frame_tracks(self, tracks: FrameTracks) -> None:
        self.vision.use(tracks)

    def containment(self) -> ContainmentResult:
        """The decision for the newest state. Evaluated again only when the estimator has
        changed (a new sample); between samples the gate's staleness check on the host clock
        is what can change the decision."""
        key = self.localizer.version
        if key != self._cont_key or self._cont is None:
            self._cont = self.localizer.containment()
            self._cont_key = key
        return self._cont

    def mow_only(self, areas: tuple[str, ...]) -> None:
        """Mow only these areas from now on, the localizer running on (ValueError naming
        the areas there are for an unknown one)."""
        self.localizer.mow_only(areas)

    def finite(self) -> bool:
        key = self.localizer.version
        if key != self._finite_key:
            self._finite = self.localizer.is_finite()
            self._finite_key = key
        return self._finite

    def pose(self) -> tuple[float, float, float, float, float]:
        """t, x, y, heading, σ_xy."""
        p = self.localizer.pose()
        x, y = float(p.position[0]), float(p.position[1])
        return p.t, x, y, yaw_of(p.quaternion), self.localizer.sigma_xy()

    def plan_pose(self) -> PlanPose | None:
        """The newest estimate with its covariance (the page's ellipse)."""
        if not self.finite():
            return None
        p = self.localizer.pose()
        return PlanPose(p.t, p.position, p.quaternion, p.covariance, self.localizer.sigma_xy())

    def last_good_pose(self) -> StartPose | None:
        """Position, q_wb and the calibrated gyro bias (for a rebuilt estimator)."""
        if not self.finite():
            return None
        p = self.localizer.pose()
        return StartPose(p.position, p.quaternion, self.localizer.gyro_bias)

    def status(self) -> dict[str, Any]:
        st = self.localizer.status()
        st.pop("gyro_bias", None)
        vs = self.vision.stats
        st["vision"] = {
            "tracks": vs.tracks_per_frame[-1] if vs.tracks_per_frame else 0,
            "associated": len(self.vision.landmark_of),
            "reidentified": vs.reidentified,
            "dropped_associations": vs.dropped_associations,
        }
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in st.items()}


Pipeline = TeachPipeline | MowPipeline
