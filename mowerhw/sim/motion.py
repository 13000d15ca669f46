"""True motion of the simulated mower, in the world frame of DESIGN.md §3.

The mower is a planar non-holonomic vehicle: body x forward, z up, the camera (body origin)
``camera_height_m`` above flat ground. Truth is sampled on the IMU clock; the gyro reading at
sample k is the mean body rate over the interval ending at sample k (what an integrating IMU
reports), so integrating the noiseless readings reproduces the truth exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.geometry import yaw_to_quat
from mowerhw.sim.lawn import HarmonicLawn

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PlanarTruth:
    """True pose at each IMU sample, world frame (= body frame at the first sample)."""

    t: FloatArray  # (K,)
    xy: FloatArray  # (K, 2)
    yaw: FloatArray  # (K,) continuous (unwrapped)
    speed: FloatArray  # (K,) signed forward speed at each sample
    origin_xy: FloatArray  # map-frame position of the world origin
    origin_yaw: float  # map-frame heading of the world x axis
    camera_height_m: float

    @property
    def position(self) -> FloatArray:
        """(K, 3): the camera centre; z = 0 on flat ground (the world origin is a camera pose)."""
        return np.column_stack([self.xy, np.zeros_like(self.yaw)])

    @property
    def quat(self) -> FloatArray:
        """(K, 4) ``q_wb``."""
        return yaw_to_quat(self.yaw)

    @property
    def body_rate(self) -> FloatArray:
        """(K, 3) mean body rate over the interval ending at each sample (0 at the first)."""
        rate = np.zeros((self.t.size, 3))
        rate[1:, 2] = np.diff(self.yaw) / np.diff(self.t)
        return rate

    def map_to_world(self, points_map: FloatArray) -> FloatArray:
        """Map-frame points (x, y, height above ground) → world frame."""
        c, s = np.cos(self.origin_yaw), np.sin(self.origin_yaw)
        d = points_map[:, :2] - self.origin_xy
        x = c * d[:, 0] + s * d[:, 1]
        y = -s * d[:, 0] + c * d[:, 1]
        return np.column_stack([x, y, points_map[:, 2] - self.camera_height_m])

    def index_at(self, t: float) -> int:
        return int(np.clip(np.searchsorted(self.t, t - 1e-9), 0, self.t.size - 1))


def cosine_ramp_profile(
    total_distance: float, cruise: float, ramp_s: float, standstill_s: float, end_still_s: float
) -> tuple[float, callable, callable]:
    """Speed profile: still, cosine ramp up, cruise, cosine ramp down, still.

    Returns (duration, s(t), v(t)) with exactly ``total_distance`` covered.
    """
    ramp_dist = cruise * ramp_s / 2.0
    cruise_s = (total_distance - 2 * ramp_dist) / cruise
    if cruise_s < 0:
        raise ValueError("loop too short for the ramps at this speed")
    t1 = standstill_s
    t2 = t1 + ramp_s
    t3 = t2 + cruise_s
    t4 = t3 + ramp_s
    duration = t4 + end_still_s

    def v(t: FloatArray) -> FloatArray:
        t = np.asarray(t, dtype=np.float64)
        up = 0.5 * cruise * (1 - np.cos(np.pi * (t - t1) / ramp_s))
        down = 0.5 * cruise * (1 + np.cos(np.pi * (t - t3) / ramp_s))
        return np.select([t < t1, t < t2, t < t3, t < t4], [0.0, up, cruise, down], 0.0)

    def s(t: FloatArray) -> FloatArray:
        t = np.asarray(t, dtype=np.float64)
        a = t - t1
        up = 0.5 * cruise * (a - ramp_s / np.pi * np.sin(np.pi * a / ramp_s))
        mid = ramp_dist + cruise * (t - t2)
        b = t - t3
        down = (
            ramp_dist
            + cruise * cruise_s
            + 0.5 * cruise * (b + ramp_s / np.pi * np.sin(np.pi * b / ramp_s))
        )
        return np.select([t < t1, t < t2, t < t3, t < t4], [0.0, up, mid, down], total_distance)

    return duration, s, v


def teach_loop(
    lawn: HarmonicLawn,
    speed_mps: float,
    camera_height_m: float,
    imu_hz: float = 100.0,
    standstill_s: float = 2.0,
    ramp_s: float = 1.5,
    end_still_s: float = 1.0,
) -> PlanarTruth:
    """Drive once around the lawn edge, counter-clockwise, back to the start, and stop."""
    duration, s_of_t, v_of_t = cosine_ramp_profile(
        lawn.perimeter, speed_mps, ramp_s, standstill_s, end_still_s
    )
    t = np.arange(0.0, duration + 1e-9, 1.0 / imu_hz)
    s = s_of_t(t)
    xy_map = lawn.point(s)
    yaw_map = np.unwrap(lawn.heading(s))
    origin_xy, origin_yaw = xy_map[0].copy(), float(yaw_map[0])
    c, si = np.cos(origin_yaw), np.sin(origin_yaw)
    d = xy_map - origin_xy
    xy = np.column_stack([c * d[:, 0] + si * d[:, 1], -si * d[:, 0] + c * d[:, 1]])
    return PlanarTruth(
        t, xy, yaw_map - origin_yaw, v_of_t(t), origin_xy, origin_yaw, camera_height_m
    )
