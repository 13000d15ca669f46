"""The simulated mower in real time, for the hardware-in-the-loop bench (docs/design.md §9).

One yard (:func:`mowerhw.sim.make_world`) and one true mower pose on the host's monotonic
clock, stepped at 200 Hz by its own thread:

* *still* — standing (start-up, gyro calibration, waiting for the daemon);
* *teach* — the operator's drive once around the lawn edge (the simulator's teach loop);
* *mow* — driven by the mower's own controller (:class:`mowerhw.sim.controller.BangBangMower`)
  from what the daemon puts on CAN: the status frame's estimated pose and containment state.
  The controller stops when the deck is halted for an unknown state or the permit frames go
  silent, turns at NEAR_EDGE / OUTSIDE, and drives on when permitted.

The mock devices sample it: the VN-100 asks for the mean body rate since its previous packet
(+ bias, noise), the speed sensor for the ground speed, the camera renders the view at its
capture time. Every step is logged with the deck state, for scoring against the truth.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.imu.mock import MockImuState
from drivers.threaded import ThreadedDevice
from mowerhw.common.geometry import quat_to_rotmat, yaw_rotation
from mowerhw.sim.motion import Truth, camera_xy_world
from mowerhw.sim.sensors import SensorSuite, mower_magnetometer
from mowerhw.sim.world import World

FloatArray = NDArray[np.float64]
PHASES = {"still": 0, "teach": 1, "mow": 2}


class RealTimeMower(ThreadedDevice):
    STEP_HZ = 200.0
    MAX_ACCEL = 1.0  # m/s²
    MAX_YAW_ACCEL = 4.0  # rad/s²

    thread_name = "bench-world"

    def __init__(
        self,
        world: World,
        teach_truth: Truth,
        seed: int,
        q_bi: Any = (1.0, 0.0, 0.0, 0.0),
        sensors: SensorSuite | None = None,
    ) -> None:
        super().__init__()
        self.world = world
        self.truth = teach_truth
        if not world.terrain.flat:
            raise ValueError("the real-time bench drives on flat ground only")
        self.frame = teach_truth.frame  # the world frame: the body frame where teach starts
        self.sensors = sensors or world.scenario.sensors
        self.rng = np.random.default_rng([seed, 40])
        self.magnetometer = mower_magnetometer(self.sensors, seed)
        self.r_ib = quat_to_rotmat(np.asarray(q_bi, dtype=np.float64)).T  # body → IMU frame
        self.bias = self.rng.normal(0.0, self.sensors.imu.turn_on_bias, size=3)
        self.phase = "still"
        self.xy = np.zeros(2)
        self.yaw = 0.0
        self.v = 0.0
        self.w = 0.0
        self.teach_t0 = 0.0
        self.teach_done = threading.Event()
        self.controller: Callable[[float, FloatArray, float], tuple[float, float]] | None = None
        self.deck_running: Callable[[], bool] = lambda: False
        self._hist: deque[tuple[float, float, float, float, float, float]] = deque(maxlen=1000)
        self.log: list[tuple[float, float, float, float, float, int, int]] = []
        self._lock = threading.Lock()
        #: (t, yaw, speed) at the last IMU packet
        self._imu_prev: tuple[float, float, float] | None = None
        #: (from, until, specific force in the body frame): what a lift, tilt or bump makes the
        #: accelerometer read (host monotonic s)
        self.accel_events: list[tuple[float, float, FloatArray]] = []

    # ---------------------------------------------------------------------------- control

    def start(self) -> RealTimeMower:
        self._record(time.monotonic())
        self._start_thread()
        return self

    def start_teach(self) -> None:
        with self._lock:
            self.teach_t0 = time.monotonic()
            self.phase = "teach"

    def start_mow(self, controller: Callable[[float, FloatArray, float], tuple[float, float]]):
        with self._lock:
            self.controller = controller
            self.phase = "mow"

    def place_on_map(self, x: float, y: float, heading: float) -> tuple[FloatArray, float]:
        """Stand the mower at (x, y, heading) of the simulator's map frame (carried there while
        the daemon was stopped): its world pose."""
        frame = self.frame
        xy = frame.map_to_world(np.array([[x, y, 0.0]]))[0, :2]
        yaw = math.remainder(heading - frame.yaw, 2 * math.pi)
        with self._lock:
            self.phase = "still"
            self.xy, self.yaw = xy.copy(), float(yaw)
            self.v = self.w = 0.0
            self._imu_prev = None  # no turn between two IMU packets across the carry
            self._hist.clear()
            self._record(time.monotonic())
        return xy, float(yaw)

    # ------------------------------------------------------------------------------ truth

    def _run(self) -> None:
        dt = 1.0 / self.STEP_HZ
        nxt = time.monotonic()
        while not self._stop.is_set():
            nxt += dt
            wait = nxt - time.monotonic()
            if wait > 0:
                self._stop.wait(wait)
            now = time.monotonic()
            if now - nxt > 0.1:
                nxt = now  # fell far behind (a stalled host): no catch-up burst
            self._step(now)

    def _step(self, now: float) -> None:
        with self._lock:
            t_prev = self._hist[-1][0] if self._hist else now
            dt = max(0.0, now - t_prev)
            if self.phase == "teach":
                tr = self.truth
                tau = now - self.teach_t0
                if tau >= tr.t[-1]:
                    self.xy, self.yaw = tr.xy[-1].copy(), float(tr.yaw[-1])
                    self.v = self.w = 0.0
                    self.phase = "still"
                    self.teach_done.set()
                else:
                    self.xy = np.array(
                        [np.interp(tau, tr.t, tr.xy[:, 0]), np.interp(tau, tr.t, tr.xy[:, 1])]
                    )
                    yaw = float(np.interp(tau, tr.t, tr.yaw))
                    self.w = (yaw - self.yaw) / dt if dt > 0 else 0.0
                    self.yaw = yaw
                    self.v = float(np.interp(tau, tr.t, tr.speed))
            elif self.phase == "mow" and self.controller is not None:
                v_cmd, w_cmd = self.controller(now, self.xy.copy(), self.yaw)
                dv, dw = self.MAX_ACCEL * dt, self.MAX_YAW_ACCEL * dt
                v = float(np.clip(v_cmd, self.v - dv, self.v + dv))
                w = float(np.clip(w_cmd, self.w - dw, self.w + dw))
                if abs(w) > 1e-12:
                    r = v / w
                    self.xy = self.xy + r * np.array(
                        [
                            math.sin(self.yaw + w * dt) - math.sin(self.yaw),
                            -math.cos(self.yaw + w * dt) + math.cos(self.yaw),
                        ]
                    )
                else:
                    self.xy = self.xy + v * dt * np.array([math.cos(self.yaw), math.sin(self.yaw)])
                self.yaw += w * dt
                self.v, self.w = v, w
            else:
                self.v = self.w = 0.0
            self._record(now)

    def _record(self, now: float) -> None:
        self._hist.append((now, float(self.xy[0]), float(self.xy[1]), self.yaw, self.v, self.w))
        self.log.append(
            (
                now,
                float(self.xy[0]),
                float(self.xy[1]),
                self.yaw,
                self.v,
                int(self.deck_running()),
                PHASES[self.phase],
            )
        )

    def pose_at(self, t: float) -> tuple[float, float, float, float]:
        """True (x, y, ψ, v) in the world frame at host time ``t`` (interpolated; a little
        extrapolated past the newest step)."""
        with self._lock:  # queries are near the newest step: look back from the end
            h = self._hist
            k = len(h)
            while k > 0 and h[k - 1][0] >= t:
                k -= 1
            a = h[k - 1] if k > 0 else None
            b = h[k] if k < len(h) else None
            first = h[0]
        if b is None:
            t0, x, y, yaw, v, w = a  # type: ignore[misc]
            d = t - t0
            return (
                x + v * d * math.cos(yaw),
                y + v * d * math.sin(yaw),
                yaw + w * d,
                v,
            )
        if a is None:
            return first[1], first[2], first[3], first[4]
        f = (t - a[0]) / max(b[0] - a[0], 1e-12)
        return tuple(a[i] + f * (b[i] - a[i]) for i in (1, 2, 3, 4))  # type: ignore[return-value]

    def map_pose_at(self, t: float) -> tuple[float, float, float]:
        """The true pose in the simulator's map frame (the renderer's)."""
        x, y, yaw, _ = self.pose_at(t)
        f = self.frame
        c, s = math.cos(f.yaw), math.sin(f.yaw)
        return (
            float(f.origin[0] + c * x - s * y),
            float(f.origin[1] + s * x + c * y),
            float(yaw + f.yaw),
        )

    def true_outline(self, outline_map: FloatArray) -> FloatArray:
        """A map-frame ground outline in the world frame (xy)."""
        return camera_xy_world(self.world, self.frame, outline_map)

    # ------------------------------------------------------------------- sensor sources

    def imu_source(self, _t_device: float) -> MockImuState:
        """What the VN-100 measures now: mean body rate and specific force since its
        previous packet (gravity, the along-track acceleration, the centripetal one)."""
        now = time.monotonic()
        _, _, yaw, v = self.pose_at(now)
        if self._imu_prev is None or now <= self._imu_prev[0]:
            rate = along = 0.0
            dt = 0.01
        else:
            dt = now - self._imu_prev[0]
            rate = (yaw - self._imu_prev[1]) / dt
            along = (v - self._imu_prev[2]) / dt
        self._imu_prev = (now, yaw, v)
        g = self.sensors.imu
        self.bias = self.bias + self.rng.normal(0.0, g.rate_random_walk * math.sqrt(dt), 3)
        white = g.noise_density / math.sqrt(max(dt, 1e-3))
        gyro_b = np.array([0.0, 0.0, rate]) + self.bias + self.rng.normal(0.0, white, 3)
        accel_b = np.array([along, v * rate, 9.80665])  # specific force, body z up
        for t0, t1, forced in self.accel_events:
            if t0 <= now < t1:
                accel_b = forced
        return MockImuState(
            gyro=self.r_ib @ gyro_b,
            accel=self.r_ib @ accel_b,
            ypr_deg=np.array([math.degrees(yaw), 0.0, 0.0]),
            quaternion_xyzw=np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]),
            mag_gauss=self.r_ib @ self.magnetometer.measure(yaw_rotation(yaw)) * 1e4,
        )

    def speed_source(self, _t_sensor: float) -> float:
        """The ground speed the sensor reports now (noise, 0.001 m/s quantum; 0 when still)."""
        _, _, _, v = self.pose_at(time.monotonic())
        if abs(v) < 1e-9:
            return 0.0
        n = self.sensors.speed
        meas = v + float(self.rng.normal(0.0, n.white))
        return round(meas / n.quantum) * n.quantum

    def log_array(self) -> FloatArray:
        return np.array(self.log, dtype=np.float64).reshape(-1, 7)
