"""Sensor models of the simulated bench (docs/design.md §9): gyro grades, ground speed, camera.

* **gyro** (:class:`Gyro`): true body rate × (1 + scale-factor error) + turn-on bias + bias
  instability (a first-order Gauss–Markov process) + rate random walk + white noise, per
  :class:`~mowerhw.imu.grades.ImuGrade`; three grades from their datasheets
  (:data:`~mowerhw.imu.grades.IMU_GRADES`);
* **ground speed** (:class:`Speedometer`): signed along-ground speed × (1 + scale error) +
  white noise, wheel-slip events (the wheels turn faster than the mower moves), quantised as
  on CAN; a standing mower reads exactly 0;
* **magnetometer** (:class:`Magnetometer`): the Earth's field (:class:`MagnetometerModel`:
  strength, dip, its direction in the simulator's world frame) turned into the body frame,
  plus the mower's own field that calibration left (a constant body-frame offset per mower:
  it turns with the mower, so the heading it gives is off by a few degrees, differently at
  each heading) and white noise; read at 10 Hz;
* **camera** (:class:`CameraTiming`, :func:`observe_at`): every landmark inside the camera's
  range is projected through the omni camera model (docs/design.md §6), kept if its pixel is valid,
  perturbed with Gaussian pixel noise, kept if the noisy pixel is still valid, and lifted back
  to a unit bearing in the body frame; some frames recognise nothing (blur, glare: the frame
  arrives empty), single bearings are missed, frames are delivered late by a jittered latency
  and stamped with a little jitter.

The paper scenario uses :data:`PAPER_SENSORS` (a VN-100, 3 px, 0.15 s latency as before).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import yaw_rotation
from mowerhw.common.samples import BearingObservation
from mowerhw.imu.grades import FLICKER_ALLAN, FLICKER_TIMES_S, IMU_GRADES, ImuGrade
from mowerhw.sim.motion import Truth
from mowerhw.sim.world import World

FloatArray = NDArray[np.float64]


class Gyro:
    """A gyro of one grade, sampled at ``rate_hz``; ``measure`` gives the reading and the true
    bias (everything but the white noise and the scale error) for the evaluation."""

    def __init__(
        self,
        grade: ImuGrade,
        rng: np.random.Generator,
        rate_hz: float,
        scale: FloatArray | None = None,
    ) -> None:
        """``scale``: this unit's scale per axis (another run of it: :func:`mower_gyro_scale`);
        default: one drawn for this unit from the grade's tolerance."""
        self.grade = grade
        self.rng = rng
        self.dt = 1.0 / rate_hz
        self.turn_on = rng.normal(0.0, grade.turn_on_bias, 3) if grade.turn_on_bias else np.zeros(3)
        # drawn even when given: the draws after it (the flicker) stay the same either way
        drawn = 1.0 + (rng.normal(0.0, grade.scale_factor, 3) if grade.scale_factor else 0.0)
        self.scale = drawn if scale is None else np.asarray(scale, dtype=np.float64)
        self._flicker_sigma = grade.bias_instability / FLICKER_ALLAN
        self._phi = np.exp(-self.dt / np.asarray(FLICKER_TIMES_S))[:, None]  # (M, 1)
        self.flicker = (
            rng.normal(0.0, self._flicker_sigma, (len(FLICKER_TIMES_S), 3))
            if self._flicker_sigma
            else np.zeros((len(FLICKER_TIMES_S), 3))
        )
        self.walk = np.zeros(3)

    @property
    def bias(self) -> FloatArray:
        return self.turn_on + self.flicker.sum(axis=0) + self.walk

    def measure(self, true_rate: FloatArray) -> tuple[FloatArray, FloatArray]:
        g, rng, dt = self.grade, self.rng, self.dt
        if self._flicker_sigma:
            drive = self._flicker_sigma * np.sqrt(1.0 - self._phi**2)
            self.flicker = self._phi * self.flicker + drive * rng.normal(size=self.flicker.shape)
        if g.rate_random_walk:
            self.walk = self.walk + rng.normal(0.0, g.rate_random_walk * math.sqrt(dt), 3)
        white = rng.normal(0.0, g.noise_density / math.sqrt(dt), 3)
        bias = self.bias
        return self.scale * np.asarray(true_rate) + bias + white, bias

    def measure_all(self, true_rates: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Readings and biases (K, 3) for a whole sequence of true rates: the same processes as
        :meth:`measure`, run as filters over the whole sequence at once."""
        from scipy.signal import lfilter

        g, rng, dt = self.grade, self.rng, self.dt
        k = true_rates.shape[0]
        bias = np.tile(self.turn_on, (k, 1))
        if self._flicker_sigma:
            for m, phi in enumerate(self._phi[:, 0]):
                drive = rng.normal(0.0, self._flicker_sigma * math.sqrt(1.0 - phi**2), (k, 3))
                drive[0] += phi * self.flicker[m]
                state = lfilter([1.0], [1.0, -phi], drive, axis=0)
                self.flicker[m] = state[-1]
                bias += state
        if g.rate_random_walk:
            steps = rng.normal(0.0, g.rate_random_walk * math.sqrt(dt), (k, 3))
            walk = self.walk + np.cumsum(steps, axis=0)
            self.walk = walk[-1].copy()
            bias += walk
        white = rng.normal(0.0, g.noise_density / math.sqrt(dt), (k, 3))
        return self.scale * np.asarray(true_rates) + bias + white, bias


@dataclass(frozen=True)
class SpeedModel:
    """Ground-speed sensor: white noise (m/s per sample), scale error (its size uniform in
    ``scale_error`` (lo, hi), its sign random; per mower: a tyre's circumference), its
    day-to-day change (1σ), slip events (per minute of driving; each ``slip_s`` long, the
    wheels turning ``slip_fraction`` faster than the mower moves), quantum (m/s)."""

    white: float = 0.005
    scale_error: tuple[float, float] = (0.0, 0.0)
    day_sigma: float = 0.0  # the scale's change from one day to another (grass, tyre wear)
    slip_per_min: float = 0.0
    slip_s: float = 1.0
    slip_fraction: float = 0.15
    quantum: float = 0.001


class Speedometer:
    """:class:`SpeedModel` applied to true speeds, one reading at a time."""

    def __init__(
        self, model: SpeedModel, rng: np.random.Generator, scale: float | None = None
    ) -> None:
        self.model = model
        self.rng = rng
        lo, hi = model.scale_error
        drawn = 1.0 + (rng.uniform(lo, hi) * rng.choice([-1.0, 1.0]) if hi > 0 else 0.0)
        self.scale = drawn if scale is None else scale
        self._slip_until = -1.0
        self.slipping = False

    def measure(self, t: float, true_speed: float, dt: float) -> float:
        m, rng = self.model, self.rng
        if true_speed == 0.0:
            self.slipping = False
            return 0.0  # a standing mower reads exactly 0
        if m.slip_per_min and t >= self._slip_until and rng.random() < m.slip_per_min * dt / 60:
            self._slip_until = t + m.slip_s
        self.slipping = t < self._slip_until
        v = true_speed * self.scale * (1.0 + (m.slip_fraction if self.slipping else 0.0))
        v += rng.normal(0.0, m.white)
        return round(v / m.quantum) * m.quantum


@dataclass(frozen=True)
class MagnetometerModel:
    """The Earth's field where the garden is, and what the mower's magnetometer adds to it."""

    strength_t: float = 50e-6
    dip_rad: float = math.radians(65.0)
    #: the field's horizontal direction in the simulator's world frame (an arbitrary frame)
    declination_rad: float = 1.0
    #: the mower's own field left after calibration (per axis, body frame, one draw per mower)
    residual_t: float = 1.0e-6
    noise_t: float = 0.4e-6
    rate_hz: float = 10.0

    @property
    def field_w(self) -> FloatArray:
        """The field in the world frame (T; x, y, z up: it points down in the north)."""
        h = self.strength_t * math.cos(self.dip_rad)
        return np.array(
            [
                h * math.cos(self.declination_rad),
                h * math.sin(self.declination_rad),
                -self.strength_t * math.sin(self.dip_rad),
            ]
        )


class Magnetometer:
    """:class:`MagnetometerModel` read at body attitudes: ``R_wbᵀ B_w`` + residual + noise."""

    def __init__(self, model: MagnetometerModel, rng: np.random.Generator) -> None:
        self.model = model
        self.rng = rng
        self.residual = rng.normal(0.0, model.residual_t, 3)

    def measure_all(self, r_wb: FloatArray) -> FloatArray:
        """Readings (K, 3) in T for attitudes (K, 3, 3)."""
        rot = np.asarray(r_wb, dtype=np.float64).reshape(-1, 3, 3)
        body = np.einsum("kji,j->ki", rot, self.model.field_w)
        out: FloatArray = (
            body + self.residual + self.rng.normal(0.0, self.model.noise_t, body.shape)
        )
        return out

    def measure(self, r_wb: FloatArray) -> FloatArray:
        out: FloatArray = self.measure_all(r_wb)[0]
        return out


def mower_magnetometer(sensors: SensorSuite, seed: int) -> Magnetometer:
    """The magnetometer of yard ``seed``'s mower (its residual is the same when it mows)."""
    return Magnetometer(sensors.mag, np.random.default_rng([seed, 7]))


@dataclass(frozen=True)
class CameraTiming:
    """Camera delivery: latency ``latency_s`` (lo, hi) uniform per frame, capture-stamp
    jitter (1σ, s), frames lost (probability), single bearings missed (probability), pixel
    noise (1σ px)."""

    latency_s: tuple[float, float] = (0.15, 0.15)
    stamp_jitter_s: float = 0.0
    frame_drop: float = 0.0
    bearing_drop: float = 0.0
    pixel_sigma: float = 3.0


@dataclass(frozen=True)
class Rates:
    imu_hz: float = 100.0
    speed_hz: float = 10.0
    camera_hz: float = 4.0


@dataclass(frozen=True)
class SensorSuite:
    """Everything about the sensors of a scenario."""

    imu: ImuGrade = field(default_factory=lambda: IMU_GRADES["vn100"])
    speed: SpeedModel = field(default_factory=SpeedModel)
    camera: CameraTiming = field(default_factory=CameraTiming)
    mag: MagnetometerModel = field(default_factory=MagnetometerModel)
    rates: Rates = field(default_factory=Rates)


PAPER_SENSORS = SensorSuite()


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
    slipping: NDArray[np.bool_] | None = None  # (M,) wheel slip at each speed reading
    speed_scale: float = 1.0  # the speed sensor's true scale (1 + its scale error)
    gyro_scale: FloatArray | None = None  # (3,) the gyro's true scale per axis
    mag_t: FloatArray | None = None  # (L,) magnetometer reading times
    mag: FloatArray | None = None  # (L, 3) T, body frame

    def events(self, magnetometer: bool = False):
        """(kind, sample) in time order; at equal times imu, (mag,) then speed, then
        bearings. ``magnetometer``: the magnetometer's readings too, as ("mag", (t, m))."""
        items: list[tuple[float, float, str, object]] = []
        items += [(t, 0, "imu", (t, g)) for t, g in zip(self.imu_t, self.gyro, strict=True)]
        if magnetometer and self.mag_t is not None and self.mag is not None:
            items += [(t, 0.5, "mag", (t, m)) for t, m in zip(self.mag_t, self.mag, strict=True)]
        items += [(t, 1, "speed", (t, v)) for t, v in zip(self.speed_t, self.speed, strict=True)]
        items += [(f.t, 2, "bearings", f) for f in self.frames]
        items.sort(key=lambda e: (e[0], e[1]))
        for _, _, kind, payload in items:
            yield kind, payload


def points_in_body(position: FloatArray, r_wb: FloatArray, points_world: FloatArray) -> FloatArray:
    """World points in the body frame of a pose: ``R_wbᵀ (p − x_b)`` (row vectors)."""
    return (points_world - np.asarray(position)) @ np.asarray(r_wb)


def body_points(truth: Truth, idx: int, points_world: FloatArray) -> FloatArray:
    """World points in the body frame of truth sample ``idx``."""
    return points_in_body(truth.position[idx], truth.rot[idx], points_world)


def planar_pose(xy: FloatArray, yaw: float) -> tuple[FloatArray, FloatArray]:
    """Position (camera at z = 0) and ``R_wb`` of a planar pose."""
    return np.array([xy[0], xy[1], 0.0]), yaw_rotation(yaw)


def observe_at(
    world: World,
    t: float,
    position: FloatArray,
    r_wb: FloatArray,
    landmarks_w: FloatArray,
    rng: np.random.Generator,
    pixel_sigma: float,
    bearing_drop: float = 0.0,
) -> tuple[BearingObservation, FloatArray]:
    """The landmarks the camera sees from a pose: noisy bearings + true pixels."""
    from mowerhw.common.geometry import quat_to_rotmat

    pb = points_in_body(position, r_wb, landmarks_w)
    rng_ok = np.linalg.norm(pb, axis=-1) <= world.scenario.max_range_m
    r_bc = quat_to_rotmat(world.q_bc)
    pix, vis = world.camera.visible(pb @ r_bc)  # R_bcᵀ p (row vectors)
    vis &= rng_ok
    noisy = pix[vis] + rng.normal(0.0, pixel_sigma, size=(int(vis.sum()), 2))
    still_ok = world.camera.valid(noisy)
    if bearing_drop:
        still_ok &= rng.random(still_ok.size) >= bearing_drop
    ids = world.landmark_ids[vis][still_ok]
    bearings = world.camera.lift(noisy[still_ok]) @ r_bc.T
    obs = BearingObservation(t=float(t), ids=ids, bearings=bearings)
    return obs, pix[vis][still_ok]


def mower_speed_scale(sensors: SensorSuite, seed: int) -> float:
    """The scale of the ground-speed sensor of yard ``seed``'s mower, as its teach run has
    it (the same tyres mow the lawn later)."""
    return Speedometer(sensors.speed, np.random.default_rng([seed, 4])).scale


def mower_gyro_scale(sensors: SensorSuite, seed: int) -> FloatArray:
    """The scale per axis of the gyro of yard ``seed``'s mower, as its teach run has it (the
    same unit mows the lawn later)."""
    unit = Gyro(sensors.imu, np.random.default_rng([seed, 2]), sensors.rates.imu_hz)
    return np.broadcast_to(unit.scale, (3,)).copy()


def simulate_sensors(
    world: World,
    truth: Truth,
    landmarks_w: FloatArray,
    seed: int,
    sensors: SensorSuite | None = None,
) -> SensorStreams:
    """Sensor streams for a truth trajectory (bearing level)."""
    sensors = sensors or PAPER_SENSORS
    rates = sensors.rates
    gyro_sim = Gyro(sensors.imu, np.random.default_rng([seed, 2]), rates.imu_hz)
    gyro, bias = gyro_sim.measure_all(truth.body_rate)

    k = truth.t.size
    step = round(rates.imu_hz / rates.speed_hz)
    sidx = np.arange(0, k, step)
    meter = Speedometer(sensors.speed, np.random.default_rng([seed, 4]))
    dt_speed = 1.0 / rates.speed_hz
    v = np.empty(sidx.size)
    slipping = np.zeros(sidx.size, dtype=bool)
    for j, i in enumerate(sidx):
        v[j] = meter.measure(float(truth.t[i]), float(truth.speed[i]), dt_speed)
        slipping[j] = meter.slipping

    mstep = max(1, round(rates.imu_hz / sensors.mag.rate_hz))
    midx = np.arange(0, k, mstep)
    mag = mower_magnetometer(sensors, seed).measure_all(truth.rot[midx])

    cam = sensors.camera
    cam_rng = np.random.default_rng([seed, 3])
    timing_rng = np.random.default_rng([seed, 5])
    cstep = round(rates.imu_hz / rates.camera_hz)
    frames, pixels = [], []
    for idx in range(0, k, cstep):
        obs, pix = observe_at(
            world,
            float(truth.t[idx]),
            truth.position[idx],
            truth.rot[idx],
            landmarks_w,
            cam_rng,
            cam.pixel_sigma,
            cam.bearing_drop,
        )
        if cam.frame_drop and timing_rng.random() < cam.frame_drop:  # seen, nothing recognised
            obs = BearingObservation(t=obs.t, ids=np.zeros(0, np.int64), bearings=np.zeros((0, 3)))
            pix = np.zeros((0, 2))
        if cam.stamp_jitter_s:
            stamp = obs.t + timing_rng.normal(0.0, cam.stamp_jitter_s)
            obs = BearingObservation(t=stamp, ids=obs.ids, bearings=obs.bearings)
        frames.append(obs)
        pixels.append(pix)
    return SensorStreams(
        truth.t.copy(),
        gyro,
        truth.t[sidx].copy(),
        v,
        frames,
        bias,
        pixels,
        slipping,
        float(meter.scale),
        np.broadcast_to(gyro_sim.scale, (3,)).copy(),
        truth.t[midx].copy(),
        mag,
    )
