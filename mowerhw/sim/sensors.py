"""Sensor models of the bearing-level bench (DESIGN.md §9, level 1).

* gyro at 100 Hz: true body rate + a constant per-run bias + a slow bias random walk + white
  noise (VN-100-like figures);
* signed ground speed at 10 Hz: true speed + white noise, quantised to 0.001 m/s as on CAN;
* camera at 4 Hz: every landmark inside the camera's range is projected through the omni
  camera model (DESIGN.md §6), kept if its pixel is inside the mirror annulus, perturbed with
  Gaussian pixel noise, kept if the noisy pixel is still valid, and lifted back to a unit
  bearing in the body frame: the estimators get ids and unit vectors, as from a front end.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mowerhw.geometry import quat_to_rotmat
from mowerhw.samples import BearingObservation
from mowerhw.sim.motion import PlanarTruth
from mowerhw.sim.world import World

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SensorNoise:
    """Noise of the simulated sensors (1σ)."""

    gyro_white: float = 6e-4  # rad/s per 100 Hz sample (VN-100: 0.0035 °/s/√Hz)
    gyro_bias: float = 2e-3  # rad/s, constant per run and axis (removed by the standstill)
    gyro_bias_walk: float = 2e-6  # rad/s/√s (≈ 10 °/h after 10 min, the VN-100's stability)
    speed_white: float = 0.005  # m/s per 10 Hz sample
    speed_quantum: float = 0.001  # m/s, the GBSD resolution
    pixel: float = 3.0  # px (the paper's §V)


@dataclass(frozen=True)
class Rates:
    imu_hz: float = 100.0
    speed_hz: float = 10.0
    camera_hz: float = 4.0


@dataclass
class SensorStreams:
    """Everything the estimators may see, on one clock (seconds from the first sample)."""

    imu_t: FloatArray  # (K,)
    gyro: FloatArray  # (K, 3) rad/s, body frame
    speed_t: FloatArray  # (M,)
    speed: FloatArray  # (M,) m/s, signed
    frames: list[BearingObservation]
    gyro_bias: FloatArray  # (K, 3) the true bias at each IMU sample (for evaluation)
    frame_pixels: list[FloatArray] = field(default_factory=list)  # true pixels per frame

    def events(self):
        """(kind, sample) in time order; at equal times imu, then speed, then bearings."""
        items: list[tuple[float, int, str, object]] = []
        items += [(t, 0, "imu", (t, g)) for t, g in zip(self.imu_t, self.gyro, strict=True)]
        items += [(t, 1, "speed", (t, v)) for t, v in zip(self.speed_t, self.speed, strict=True)]
        items += [(f.t, 2, "bearings", f) for f in self.frames]
        items.sort(key=lambda e: (e[0], e[1]))
        for _, _, kind, payload in items:
            yield kind, payload


def body_points(truth: PlanarTruth, idx: int, points_world: FloatArray) -> FloatArray:
    """World points in the body frame of truth sample ``idx``: ``R_wbᵀ (p − x_b)``."""
    return points_in_body(truth.xy[idx], float(truth.yaw[idx]), points_world)


def points_in_body(xy: FloatArray, yaw: float, points_world: FloatArray) -> FloatArray:
    """World points in the body frame of a planar pose (camera at z = 0)."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = points_world - np.array([xy[0], xy[1], 0.0])
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])


def observe_at(
    world: World,
    t: float,
    xy: FloatArray,
    yaw: float,
    landmarks_w: FloatArray,
    rng: np.random.Generator,
    pixel_sigma: float,
) -> tuple[BearingObservation, FloatArray]:
    """The landmarks the camera sees from a planar pose: noisy bearings + true pixels."""
    pb = points_in_body(xy, yaw, landmarks_w)
    rng_ok = np.linalg.norm(pb, axis=-1) <= world.scenario.max_range_m
    r_bc = quat_to_rotmat(world.q_bc)
    pix, vis = world.camera.visible(pb @ r_bc)  # R_bcᵀ p (row vectors)
    vis &= rng_ok
    noisy = pix[vis] + rng.normal(0.0, pixel_sigma, size=(int(vis.sum()), 2))
    still_ok = world.camera.valid(noisy)
    ids = world.landmark_ids[vis][still_ok]
    bearings = world.camera.lift(noisy[still_ok]) @ r_bc.T
    obs = BearingObservation(t=float(t), ids=ids, bearings=bearings)
    return obs, pix[vis][still_ok]


def observe(
    world: World,
    truth: PlanarTruth,
    idx: int,
    landmarks_w: FloatArray,
    rng: np.random.Generator,
    pixel_sigma: float,
) -> tuple[BearingObservation, FloatArray]:
    """The landmarks the camera sees at truth sample ``idx``."""
    return observe_at(
        world,
        float(truth.t[idx]),
        truth.xy[idx],
        float(truth.yaw[idx]),
        landmarks_w,
        rng,
        pixel_sigma,
    )


def simulate_sensors(
    world: World,
    truth: PlanarTruth,
    landmarks_w: FloatArray,
    seed: int,
    noise: SensorNoise | None = None,
    rates: Rates | None = None,
) -> SensorStreams:
    """Sensor streams for a truth trajectory (bearing level)."""
    noise = noise or SensorNoise()
    rates = rates or Rates()
    rng = np.random.default_rng([seed, 2])
    k = truth.t.size
    dt = 1.0 / rates.imu_hz
    bias0 = rng.normal(0.0, noise.gyro_bias, size=3)
    walk = np.cumsum(rng.normal(0.0, noise.gyro_bias_walk * np.sqrt(dt), size=(k, 3)), axis=0)
    bias = bias0 + walk
    gyro = truth.body_rate + bias + rng.normal(0.0, noise.gyro_white, size=(k, 3))

    step = round(rates.imu_hz / rates.speed_hz)
    sidx = np.arange(0, k, step)
    v = truth.speed[sidx] + rng.normal(0.0, noise.speed_white, size=sidx.size)
    v = np.where(truth.speed[sidx] == 0.0, 0.0, v)  # a standing mower reads exactly 0
    v = np.round(v / noise.speed_quantum) * noise.speed_quantum

    cam_rng = np.random.default_rng([seed, 3])
    cstep = round(rates.imu_hz / rates.camera_hz)
    frames, pixels = [], []
    for idx in range(0, k, cstep):
        obs, pix = observe(world, truth, idx, landmarks_w, cam_rng, noise.pixel)
        frames.append(obs)
        pixels.append(pix)
    return SensorStreams(truth.t.copy(), gyro, truth.t[sidx].copy(), v, frames, bias, pixels)
