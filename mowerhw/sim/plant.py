"""The simulated mower for closed-loop mowing: true motion from commands, and its sensors.

The mower is driven by commanded forward speed and turn rate (the mower's own controller
decides them, from the *estimate*). The true pose is integrated exactly at the IMU rate; the
sensors are those of :mod:`mowerhw.sim.sensors` (gyro with bias and noise at 100 Hz, ground
speed at 10 Hz quantised to 0.001 m/s, bearings at 4 Hz with pixel noise through the omni
camera). Camera frames are *late*: a frame taken at ``t`` is delivered at
``t + frame_latency_s`` (exposure and processing), stamped with ``t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mowerhw.samples import BearingObservation
from mowerhw.sim.lawn import HarmonicLawn
from mowerhw.sim.sensors import Rates, SensorNoise, observe_at
from mowerhw.sim.world import World

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class WorldFrame:
    """The world frame of a teach run: the body frame at the start of the lawn-edge drive."""

    origin_xy: FloatArray
    origin_yaw: float
    camera_height_m: float

    @classmethod
    def of(cls, lawn: HarmonicLawn, camera_height_m: float) -> WorldFrame:
        return cls(
            lawn.point(np.array([0.0]))[0], float(lawn.heading(np.array([0.0]))[0]), camera_height_m
        )

    def map_to_world(self, points_map: FloatArray) -> FloatArray:
        """Map-frame points (x, y, height above ground) → world frame."""
        c, s = np.cos(self.origin_yaw), np.sin(self.origin_yaw)
        d = points_map[:, :2] - self.origin_xy
        z = points_map[:, 2] - self.camera_height_m if points_map.shape[1] > 2 else 0.0 * d[:, 0]
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], z])

    def outline_world(self, lawn: HarmonicLawn, n: int = 1440) -> FloatArray:
        pts = lawn.outline(n)
        return self.map_to_world(np.column_stack([pts, np.zeros(len(pts))]))[:, :2]


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


class MowerPlant:
    """True planar pose + sensors, stepped at the IMU rate by (v, ω) commands."""

    def __init__(
        self,
        world: World,
        seed: int,
        noise: SensorNoise | None = None,
        rates: Rates | None = None,
        frame_latency_s: float = 0.15,
        start_xy: tuple[float, float] = (0.0, 0.0),
        start_yaw: float = 0.0,
        vision_dropout: tuple[float, float] | None = None,
        max_accel: float = 1.0,
        max_yaw_accel: float = 4.0,
        renderer: Any = None,
    ) -> None:
        """With a ``renderer`` (:class:`mowerhw.sim.render.OmniRenderer`) the camera delivers
        rendered images (:class:`PixelFrame`, pixel level); without, noisy bearings of known
        landmark ids (bearing level)."""
        self.world = world
        self.renderer = renderer
        self.max_accel = max_accel  # m/s²: a mower cannot stop or start in no time
        self.max_yaw_accel = max_yaw_accel  # rad/s²
        self.w = 0.0
        self.noise = noise or SensorNoise()
        self.rates = rates or Rates()
        self.frame_latency_s = frame_latency_s
        self.frame = WorldFrame.of(world.lawn, world.scenario.camera_height_m)
        self.landmarks_w = self.frame.map_to_world(world.landmarks_map)
        self.rng = np.random.default_rng([seed, 20])
        self.cam_rng = np.random.default_rng([seed, 21])
        self.dt = 1.0 / self.rates.imu_hz
        self.t = 0.0
        self.k = 0
        self.xy = np.array(start_xy, dtype=np.float64)
        self.yaw = float(start_yaw)
        self.v = 0.0
        self.bias = self.rng.normal(0.0, self.noise.gyro_bias, size=3)
        self.vision_dropout = vision_dropout
        self._pending: list[Any] = []  # taken, not yet delivered
        self._speed_every = round(self.rates.imu_hz / self.rates.speed_hz)
        self._frame_every = round(self.rates.imu_hz / self.rates.camera_hz)

    def first_output(self) -> PlantOutput:
        """The readings at t = 0, before any motion."""
        gyro = self.bias + self.rng.normal(0.0, self.noise.gyro_white, size=3)
        out = PlantOutput((0.0, gyro), (0.0, 0.0))
        self._take_frame()
        return out

    def step(self, v_cmd: float, w_cmd: float) -> PlantOutput:
        """Advance one IMU interval towards the commanded (v, ω) within the acceleration limits;
        return what the sensors reported."""
        dt = self.dt
        dv, dw = self.max_accel * dt, self.max_yaw_accel * dt
        v_cmd = float(np.clip(v_cmd, self.v - dv, self.v + dv))
        w_cmd = float(np.clip(w_cmd, self.w - dw, self.w + dw))
        self.w = w_cmd
        if abs(w_cmd) > 1e-12:  # exact arc
            r = v_cmd / w_cmd
            self.xy = self.xy + r * np.array(
                [
                    np.sin(self.yaw + w_cmd * dt) - np.sin(self.yaw),
                    -np.cos(self.yaw + w_cmd * dt) + np.cos(self.yaw),
                ]
            )
        else:
            self.xy = self.xy + v_cmd * dt * np.array([np.cos(self.yaw), np.sin(self.yaw)])
        self.yaw += w_cmd * dt
        self.v = v_cmd
        self.t = round(self.t + dt, 9)
        self.k += 1
        n = self.noise
        self.bias = self.bias + self.rng.normal(0.0, n.gyro_bias_walk * np.sqrt(dt), size=3)
        gyro = np.array([0.0, 0.0, w_cmd]) + self.bias + self.rng.normal(0.0, n.gyro_white, 3)
        out = PlantOutput((self.t, gyro))
        if self.k % self._speed_every == 0:
            meas = 0.0 if abs(v_cmd) < 1e-9 else v_cmd + self.rng.normal(0.0, n.speed_white)
            out.speed = (self.t, round(meas / n.speed_quantum) * n.speed_quantum)
        if self.k % self._frame_every == 0:
            self._take_frame()
        due = [f for f in self._pending if f.t + self.frame_latency_s <= self.t + 1e-9]
        if due:
            self._pending = self._pending[len(due) :]  # taken in time order
            out.frames = due
        return out

    def map_pose(self) -> tuple[float, float, float]:
        """The true pose in the simulator's map frame (what the renderer takes)."""
        f = self.frame
        c, s = np.cos(f.origin_yaw), np.sin(f.origin_yaw)
        x = f.origin_xy[0] + c * self.xy[0] - s * self.xy[1]
        y = f.origin_xy[1] + s * self.xy[0] + c * self.xy[1]
        return float(x), float(y), float(self.yaw + f.origin_yaw)

    def _take_frame(self) -> None:
        d = self.vision_dropout
        dark = d is not None and d[0] <= self.t < d[0] + d[1]
        if self.renderer is not None:
            pose = self.map_pose()
            image = self.renderer.render(*pose)
            if dark:  # the lens is covered: the camera still delivers, but sees nothing
                image = np.zeros_like(image)
            self._pending.append(PixelFrame(self.t, image, pose))
            return
        obs, _ = observe_at(
            self.world, self.t, self.xy, self.yaw, self.landmarks_w, self.cam_rng, self.noise.pixel
        )
        if dark:  # the camera sees nothing it knows
            obs = BearingObservation(t=obs.t, ids=np.zeros(0, np.int64), bearings=np.zeros((0, 3)))
        self._pending.append(obs)
