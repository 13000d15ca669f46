"""True motion of the simulated mower, in the world frame of docs/design.md §3.

The mower is a non-holonomic vehicle on the ground of :mod:`mowerhw.sim.terrain`: its
contact point follows a horizontal path (the lawn edge when teaching), its attitude comes from
the ground's normal and its heading, and the camera (the body origin) sits
``camera_height_m`` up the body z axis. Truth is sampled on the IMU clock; the gyro reading at
sample k is the mean body rate over the interval ending at sample k (what an integrating IMU
reports), so integrating the noiseless readings reproduces the attitude exactly. The world
frame is the body frame at the first sample; on flat ground everything stays planar.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mowerhw.common.geometry import rotmat_to_quat
from mowerhw.sim.terrain import Terrain

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MapFrame:
    """The world frame in the simulator's map frame: ``p_m = R_mw p_w + origin``."""

    r_mw: FloatArray  # (3, 3)
    origin: FloatArray  # (3,) the camera centre at the first sample

    def map_to_world(self, points_map: FloatArray) -> FloatArray:
        """Map-frame points (x, y, absolute z) → world frame."""
        return (np.asarray(points_map, dtype=np.float64) - self.origin) @ self.r_mw

    def world_to_map(self, points_world: FloatArray) -> FloatArray:
        return np.asarray(points_world, dtype=np.float64) @ self.r_mw.T + self.origin

    @property
    def yaw(self) -> float:
        """Heading of the world x axis in the map (rad)."""
        return float(np.arctan2(self.r_mw[1, 0], self.r_mw[0, 0]))


def start_frame(world: Any) -> MapFrame:
    """The world frame of a yard's teach run: the body frame at the start of the lawn edge."""
    s0 = np.array([0.0])
    cam, r_mb = pose_on_ground(
        world.terrain, world.lawn.point(s0), world.lawn.heading(s0), world.scenario.camera_height_m
    )
    return MapFrame(r_mb[0].copy(), cam[0].copy())


def camera_xy_world(world: Any, frame: MapFrame, map_xy: FloatArray) -> FloatArray:
    """Where the camera is (world xy) when the mower stands at ``map_xy``: the ground's
    normal sets the mast's tilt, whatever the heading, so a lawn edge traced by the camera is
    one curve in the world plane (what the taught boundary is)."""
    n = world.terrain.normal(map_xy[:, 0], map_xy[:, 1])
    ground = np.column_stack([map_xy, world.terrain.height(map_xy[:, 0], map_xy[:, 1])])
    return frame.map_to_world(ground + world.scenario.camera_height_m * n)[:, :2]


def pose_on_ground(
    terrain: Terrain, map_xy: FloatArray, heading: FloatArray, camera_height_m: float
) -> tuple[FloatArray, FloatArray]:
    """Camera centres (K, 3) and attitudes ``R_mb`` (K, 3, 3) (map frame) of a mower whose
    contact point is at ``map_xy`` heading ``heading``."""
    x, y = map_xy[:, 0], map_xy[:, 1]
    r_mb = terrain.attitude(x, y, heading)
    ground = np.column_stack([x, y, terrain.height(x, y)])
    return ground + camera_height_m * r_mb[:, :, 2], r_mb


def surface_speed(terrain: Terrain, map_xy: FloatArray, heading: FloatArray, v_h: FloatArray):
    """Along-ground speed of the contact point from its horizontal speed (the slope along the
    heading stretches the distance a wheel rolls)."""
    if terrain.flat:
        return np.asarray(v_h, dtype=np.float64)
    gx, gy = terrain.gradient(map_xy[:, 0], map_xy[:, 1])
    along = gx * np.cos(heading) + gy * np.sin(heading)
    return np.asarray(v_h) * np.sqrt(1.0 + along * along)


@dataclass(frozen=True)
class Truth:
    """True pose at each IMU sample, world frame (= body frame at the first sample)."""

    t: FloatArray  # (K,)
    position: FloatArray  # (K, 3) the camera centre
    rot: FloatArray  # (K, 3, 3) R_wb
    speed: FloatArray  # (K,) signed along-ground speed of the contact point
    frame: MapFrame
    map_xy: FloatArray  # (K, 2) contact point in the map frame (what the renderer takes)
    map_heading: FloatArray  # (K,) horizontal heading in the map frame (unwrapped)
    camera_height_m: float

    @property
    def xy(self) -> FloatArray:
        return self.position[:, :2]

    @cached_property
    def yaw(self) -> FloatArray:
        """(K,) heading of the body x axis in the world xy plane, unwrapped."""
        return np.unwrap(np.arctan2(self.rot[:, 1, 0], self.rot[:, 0, 0]))

    @cached_property
    def quat(self) -> FloatArray:
        """(K, 4) ``q_wb``."""
        return rotmat_to_quat(self.rot)

    @cached_property
    def body_rate(self) -> FloatArray:
        """(K, 3) mean body rate over the interval ending at each sample (0 at the first)."""
        rate = np.zeros((self.t.size, 3))
        rel = np.einsum("kji,kjl->kil", self.rot[:-1], self.rot[1:])  # R_{k-1}ᵀ R_k
        rate[1:] = Rotation.from_matrix(rel).as_rotvec() / np.diff(self.t)[:, None]
        return rate

    def map_to_world(self, points_map: FloatArray) -> FloatArray:
        return self.frame.map_to_world(points_map)

    def index_at(self, t: float) -> int:
        return int(np.clip(np.searchsorted(self.t, t - 1e-9), 0, self.t.size - 1))


def truth_from_path(
    t: FloatArray,
    map_xy: FloatArray,
    heading: FloatArray,
    v_h: FloatArray,
    terrain: Terrain,
    camera_height_m: float,
) -> Truth:
    """The full truth of a contact-point path (map frame) on ``terrain``."""
    cam_m, r_mb = pose_on_ground(terrain, map_xy, heading, camera_height_m)
    frame = MapFrame(r_mb[0].copy(), cam_m[0].copy())
    position = frame.map_to_world(cam_m)
    rot = np.einsum("ji,kjl->kil", frame.r_mw, r_mb)  # R_wb = R_mwᵀ R_mb
    speed = surface_speed(terrain, map_xy, heading, v_h)
    return Truth(t, position, rot, speed, frame, map_xy, heading, camera_height_m)


def cosine_ramp_profile(
    total_distance: float, cruise: float, ramp_s: float, standstill_s: float, end_still_s: float
) -> tuple[float, Any, Any]:
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
    lawn: Any,
    speed_mps: float,
    camera_height_m: float,
    imu_hz: float = 100.0,
    standstill_s: float = 2.0,
    ramp_s: float = 1.5,
    end_still_s: float = 1.0,
    terrain: Terrain | None = None,
) -> Truth:
    """Drive once around the lawn edge, counter-clockwise, back to the start, and stop."""
    duration, s_of_t, v_of_t = cosine_ramp_profile(
        lawn.perimeter, speed_mps, ramp_s, standstill_s, end_still_s
    )
    t = np.arange(0.0, duration + 1e-9, 1.0 / imu_hz)
    s = s_of_t(t)
    map_xy = lawn.point(s)
    heading = np.unwrap(lawn.heading(s))
    return truth_from_path(t, map_xy, heading, v_of_t(t), terrain or Terrain(), camera_height_m)
