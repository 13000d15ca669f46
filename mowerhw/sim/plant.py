"""The simulated mower for closed-loop mowing: true motion from commands, and its sensors.

The mower is driven by commanded along-ground speed and heading rate (the mower's own
controller decides them, from the *estimate*). Its contact point moves on the ground of
:mod:`mowerhw.sim.terrain` (exact arcs in the horizontal plane, at the IMU rate); attitude and
camera position follow from the ground (:func:`mowerhw.sim.motion.pose_on_ground`). The sensors
are those of :mod:`mowerhw.sim.sensors` (the scenario's gyro grade at 100 Hz, its ground-speed
sensor at 10 Hz, bearings at 4 Hz through the omni camera). A ground-speed reading is the speed
of the IMU interval just moved, stamped at that interval's middle (where it is true: the
estimators take a reading to be the speed at its stamp). Camera frames are *late*: a frame
taken at ``t`` is delivered after the scenario's latency (or ``frame_latency_s``), stamped with
``t`` (plus the stamp jitter); frames and single bearings are lost as the scenario says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mowerhw.common.samples import BearingObservation
from mowerhw.common.units import GRAVITY_MPS2
from mowerhw.sim.motion import MapFrame, camera_xy_world, pose_on_ground, start_frame
from mowerhw.sim.sensors import (
    CameraTiming,
    Gyro,
    SensorSuite,
    Speedometer,
    mower_magnetometer,
    observe_at,
)
from mowerhw.sim.world import World

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PixelFrame:
    """A rendered camera frame (pixel level), taken at ``t`` from ``map_pose``."""

    t: float
    image: NDArray[np.uint8]
    map_pose: tuple[float, float, float]  # x, y, ψ in the simulator's map frame (truth)


@dataclass
class PlantOutput:
    """What the sensors produced during one step (arrival order within the step)."""

    imu: tuple[float, FloatArray]
    speed: tuple[float, float] | None = None
    frames: list[Any] = field(default_factory=list)  # BearingObservation or PixelFrame
    mag: tuple[float, FloatArray] | None = None  # a magnetometer reading (T, body frame)


class MowerPlant:
    """The true mower + sensors, stepped at the IMU rate by (v, ω) commands."""

    def __init__(
        self,
        world: World,
        seed: int,
        sensors: SensorSuite | None = None,
        frame_latency_s: float | None = None,
        start_xy: tuple[float, float] = (0.0, 0.0),
        start_yaw: float = 0.0,
        vision_dropout: tuple[float, float] | None = None,
        max_accel: float = 1.0,
        max_yaw_accel: float = 4.0,
        renderer: Any = None,
        speed_scale: float | None = None,
        gyro_scale: FloatArray | None = None,
    ) -> None:
        """With a ``renderer`` (:class:`mowerhw.sim.render.OmniRenderer`) the camera delivers
        rendered images (:class:`PixelFrame`, pixel level); without, noisy bearings of known
        landmark ids (bearing level). ``start_xy``/``start_yaw``: the start pose in the world
        frame (the dock is the origin); ``frame_latency_s`` overrides the scenario's;
        ``speed_scale``: the scale of this mower's ground-speed sensor (its teach run's),
        changed by the model's day-to-day σ (default: drawn for this run); ``gyro_scale``
        the same for the gyro's scale per axis (its teach run's, changed by the grade's
        ``scale_drift``)."""
        self.world = world
        self.renderer = renderer
        self.max_accel = max_accel  # m/s²: a mower cannot stop or start in no time
        self.max_yaw_accel = max_yaw_accel  # rad/s²
        self.sensors = sensors or world.scenario.sensors
        cam = self.sensors.camera
        if frame_latency_s is not None:
            cam = CameraTiming(
                (frame_latency_s, frame_latency_s),
                cam.stamp_jitter_s,
                cam.frame_drop,
                cam.bearing_drop,
                cam.pixel_sigma,
            )
        self.camera_timing = cam
        self.rates = self.sensors.rates
        self.frame: MapFrame = start_frame(world)
        self.landmarks_w = self.frame.map_to_world(world.landmarks_map)
        self.rng = np.random.default_rng([seed, 20])
        self.cam_rng = np.random.default_rng([seed, 21])
        self.timing_rng = np.random.default_rng([seed, 22])
        if gyro_scale is not None and self.sensors.imu.scale_drift:
            drift = np.random.default_rng([seed, 25]).normal(0.0, self.sensors.imu.scale_drift, 3)
            gyro_scale = np.asarray(gyro_scale, dtype=np.float64) * (1.0 + drift)
        self.gyro = Gyro(
            self.sensors.imu, np.random.default_rng([seed, 23]), self.rates.imu_hz, gyro_scale
        )
        speed_rng = np.random.default_rng([seed, 24])
        if speed_scale is not None and self.sensors.speed.day_sigma:
            speed_scale *= 1.0 + speed_rng.normal(0.0, self.sensors.speed.day_sigma)
        self.speedometer = Speedometer(self.sensors.speed, speed_rng, speed_scale)
        self.magnetometer = mower_magnetometer(self.sensors, seed)
        self._mag_every = max(1, round(self.rates.imu_hz / self.sensors.mag.rate_hz))
        self.dt = 1.0 / self.rates.imu_hz
        self.t = 0.0
        self.k = 0
        start_map = self.frame.world_to_map(np.array([[start_xy[0], start_xy[1], 0.0]]))[0]
        self.map_xy = start_map[:2].copy()
        self.map_heading = float(start_yaw) + self.frame.yaw
        self.v = self._v_prev = 0.0
        self.w = 0.0
        self.vision_dropout = vision_dropout
        self._pending: list[tuple[float, Any]] = []  # (delivery time, frame), taken in order
        self._speed_every = round(self.rates.imu_hz / self.rates.speed_hz)
        self._frame_every = round(self.rates.imu_hz / self.rates.camera_hz)
        self._carry: tuple[float, float, FloatArray, FloatArray, float, float] | None = None
        self._update_pose()

    def place(self, map_xy: tuple[float, float], heading: float) -> None:
        """Stand the mower at ``map_xy`` (simulator map frame) facing ``heading`` (before the
        first output: a start away from the dock)."""
        self.map_xy = np.asarray(map_xy, dtype=np.float64).reshape(2).copy()
        self.map_heading = float(heading)
        self._update_pose()

    def carry(self, to_map_xy: tuple[float, float], to_heading: float, duration_s: float) -> None:
        """Someone picks the mower up now and puts it down at ``to_map_xy`` (map frame) facing
        ``to_heading`` after ``duration_s`` (a kidnap, issue 18): the pose moves there evenly,
        the gyro sees the turn, the wheels stop (ground speed 0), the commands are ignored."""
        t0 = self.t
        turn = math.remainder(to_heading - self.map_heading, 2 * math.pi)
        xy1 = np.asarray(to_map_xy, dtype=np.float64).reshape(2)
        self._carry = (t0, t0 + duration_s, self.map_xy.copy(), xy1, self.map_heading, turn)
        self.v = 0.0  # lifted: the wheels stop (no jolt: the lift's own force is the event's)

    @property
    def carried(self) -> bool:
        return self._carry is not None

    # -- truth --------------------------------------------------------------------------------

    def _update_pose(self) -> None:
        h = self.world.scenario.camera_height_m
        cam, r_mb = pose_on_ground(
            self.world.terrain, self.map_xy[None], np.array([self.map_heading]), h
        )
        self.position = self.frame.map_to_world(cam)[0]
        self.rot = self.frame.r_mw.T @ r_mb[0]  # R_wb

    @property
    def xy(self) -> FloatArray:
        """World xy of the camera (the body origin)."""
        return self.position[:2]

    @property
    def yaw(self) -> float:
        return float(math.atan2(self.rot[1, 0], self.rot[0, 0]))

    def outline_world(self, outline_map: FloatArray) -> FloatArray:
        """A map-frame ground outline as the camera traces it, world xy."""
        return camera_xy_world(self.world, self.frame, outline_map)

    def first_output(self) -> PlantOutput:
        """The readings at t = 0, before any motion."""
        gyro, _ = self.gyro.measure(np.zeros(3))
        out = PlantOutput((0.0, gyro), (0.0, 0.0))
        self._take_frame()
        return out

    def step(self, v_cmd: float, w_cmd: float) -> PlantOutput:
        """Advance one IMU interval towards the commanded (v, ω) within the acceleration limits;
        return what the sensors reported."""
        dt = self.dt
        if self._carry is not None:
            return self._carried_step()
        dv, dw = self.max_accel * dt, self.max_yaw_accel * dt
        v_cmd = float(np.clip(v_cmd, self.v - dv, self.v + dv))
        w_cmd = float(np.clip(w_cmd, self.w - dw, self.w + dw))
        self.w = w_cmd
        # the contact point rolls v dt along the ground: its horizontal run is shorter on a slope
        terrain = self.world.terrain
        stretch = 1.0
        if not terrain.flat:
            gx, gy = terrain.gradient(self.map_xy[:1], self.map_xy[1:])
            along = float(gx[0] * math.cos(self.map_heading) + gy[0] * math.sin(self.map_heading))
            stretch = math.sqrt(1.0 + along * along)
        vh = v_cmd / stretch
        psi = self.map_heading
        if abs(w_cmd) > 1e-12:  # exact arc
            r = vh / w_cmd
            self.map_xy = self.map_xy + r * np.array(
                [
                    math.sin(psi + w_cmd * dt) - math.sin(psi),
                    -math.cos(psi + w_cmd * dt) + math.cos(psi),
                ]
            )
        else:
            self.map_xy = self.map_xy + vh * dt * np.array([math.cos(psi), math.sin(psi)])
        self.map_heading = psi + w_cmd * dt
        return self._sense(v_cmd)

    def _carried_step(self) -> PlantOutput:
        assert self._carry is not None
        t0, t1, xy0, xy1, h0, turn = self._carry
        a = min(1.0, (self.t + self.dt - t0) / (t1 - t0))
        self.map_xy = xy0 + a * (xy1 - xy0)
        self.map_heading = h0 + a * turn
        self.w = turn / (t1 - t0) if a < 1.0 else 0.0
        if a >= 1.0:
            self._carry = None
        return self._sense(0.0)

    def _sense(self, v_cmd: float) -> PlantOutput:
        """The new pose's truth and the sensors' readings for the interval just moved."""
        dt = self.dt
        rot_prev = self.rot
        self._update_pose()
        self._v_prev, self.v = self.v, v_cmd
        self.t = round(self.t + dt, 9)
        self.k += 1
        rate = Rotation.from_matrix(rot_prev.T @ self.rot).as_rotvec() / dt
        gyro, _ = self.gyro.measure(rate)
        out = PlantOutput((self.t, gyro))
        if self.k % self._speed_every == 0:
            meas = self.speedometer.measure(self.t, v_cmd, self._speed_every * dt)
            # the speed of the interval just moved: true at its middle
            out.speed = (round(self.t - 0.5 * dt, 9), meas)
        if self.k % self._mag_every == 0:
            out.mag = (self.t, self.magnetometer.measure(self.rot))
        if self.k % self._frame_every == 0:
            self._take_frame()
        due = [f for when, f in self._pending if when <= self.t + 1e-9]
        if due:
            self._pending = [(when, f) for when, f in self._pending if when > self.t + 1e-9]
            out.frames = sorted(due, key=lambda f: f.t)
        return out

    def specific_force(self) -> tuple[float, float, float]:
        """What the accelerometer reads now (body frame, z up, m/s²): gravity through the
        attitude on the ground, the along-track acceleration and the centripetal one."""
        g_body = self.rot.T @ np.array([0.0, 0.0, GRAVITY_MPS2])
        along = (self.v - self._v_prev) / self.dt
        return (
            float(g_body[0] + along),
            float(g_body[1] + self.v * self.w),
            float(g_body[2]),
        )

    def in_flight(self) -> list[Any]:
        """Frames taken but not delivered yet, in time order."""
        return sorted((f for _, f in self._pending), key=lambda f: f.t)

    def map_pose(self) -> tuple[float, float, float]:
        """The true planar pose in the simulator's map frame (what the renderer takes)."""
        return float(self.map_xy[0]), float(self.map_xy[1]), float(self.map_heading)

    def _take_frame(self) -> None:
        timing = self.camera_timing
        d = self.vision_dropout
        dark = d is not None and d[0] <= self.t < d[0] + d[1]
        lo, hi = timing.latency_s
        deliver = self.t + (self.timing_rng.uniform(lo, hi) if hi > lo else lo)
        lost = bool(timing.frame_drop) and self.timing_rng.random() < timing.frame_drop
        dark = dark or lost  # a frame that recognises nothing (blur, glare) still arrives
        stamp = self.t + (
            self.timing_rng.normal(0.0, timing.stamp_jitter_s) if timing.stamp_jitter_s else 0.0
        )
        if self.renderer is not None:
            pose = self.map_pose()
            image = self.renderer.render(*pose)
            if dark:  # the lens is covered: the camera still delivers, but sees nothing
                image = np.zeros_like(image)
            self._pending.append((deliver, PixelFrame(stamp, image, pose)))
            return
        obs, _ = observe_at(
            self.world,
            stamp,
            self.position,
            self.rot,
            self.landmarks_w,
            self.cam_rng,
            timing.pixel_sigma,
            timing.bearing_drop,
        )
        if dark:  # the camera sees nothing it knows
            obs = BearingObservation(t=obs.t, ids=np.zeros(0, np.int64), bearings=np.zeros((0, 3)))
        self._pending.append((deliver, obs))
