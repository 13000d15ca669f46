"""Gyro grades: the error budgets of the IMUs a mower may carry, from their datasheets.

One table for both sides: the simulator draws its gyros from it (:mod:`mowerhw.sim.sensors`)
and the configuration's ``imu.grade`` takes its noise figures from it (the estimators' process
noise), until ``mowerhw imu characterize`` measures a user's own unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

DPS = math.pi / 180.0  # rad/s per °/s
DPH = DPS / 3600.0  # rad/s per °/h
#: bias instability (flicker noise) is simulated as Gauss–Markov processes with these
#: correlation times, each of standard deviation B / FLICKER_ALLAN: together their Allan
#: deviation is flat at ≈ B from about 10 s to 1000 s (measured with allantools)
FLICKER_TIMES_S = (3.0, 30.0, 300.0, 3000.0)
FLICKER_ALLAN = 0.8


@dataclass(frozen=True)
class ImuGrade:
    """A gyro's error budget (1σ unless said otherwise), SI units.

    ``noise_density`` rad/s/√Hz (angle random walk); ``bias_instability`` rad/s, the flat
    floor of the Allan deviation (as datasheets quote in-run bias stability), simulated as
    flicker noise (:data:`FLICKER_TIMES_S`); ``rate_random_walk`` rad/s/√s; ``turn_on_bias``
    rad/s, constant per run and axis; ``scale_factor`` fraction, per unit and axis (the
    spread from one unit to another); ``scale_drift`` fraction, how much one unit's scale
    changes from one run to a later one (temperature, ageing) — what a scale a teach run
    learnt is still off when the same mower mows days later.
    """

    name: str
    noise_density: float
    bias_instability: float
    rate_random_walk: float
    turn_on_bias: float
    scale_factor: float
    scale_drift: float
    source: str = ""


#: Gyro grades. Figures from the datasheets where they give them; ``source`` says which.
IMU_GRADES: dict[str, ImuGrade] = {
    "vn100": ImuGrade(
        "vn100",
        noise_density=0.0035 * DPS,  # VN-100 datasheet: 0.0035 °/s/√Hz
        bias_instability=0.0,  # (within the random walk below, as the bench has always had)
        rate_random_walk=2e-6,  # ≈ 25 °/h/√h: the 10 °/h in-run stability over ~10 min
        turn_on_bias=2e-3,  # removed by the start-up standstill
        scale_factor=0.0,  # factory-calibrated
        scale_drift=0.001,  # assumed: the factory calibration spans the temperature range
        source="VN-100 datasheet: noise 0.0035 °/s/√Hz, in-run bias stability < 10 °/h",
    ),
    "bmi088": ImuGrade(
        "bmi088",
        noise_density=0.014 * DPS,  # BMI088 datasheet: output noise 0.014 °/s/√Hz
        bias_instability=2.0 * DPH,  # Bosch: bias stability 2 °/h
        rate_random_walk=4e-7,  # ≈ 5 °/h/√h, assumed (not in the datasheet)
        turn_on_bias=1.0 * DPS,  # zero-rate offset ±1 °/s
        scale_factor=0.01,  # sensitivity tolerance ±1 %
        scale_drift=0.005,  # assumed: sensitivity drift ±0.03 %/K over ~15 K between runs
        source="BMI088 datasheet (BST-BMI088-DS001): noise 0.014 °/s/√Hz, ZRO ±1 °/s, "
        "sensitivity ±1 %; bias stability 2 °/h (Bosch); random walk assumed",
    ),
    "mpu6050": ImuGrade(
        "mpu6050",
        noise_density=0.005 * DPS,  # MPU-6000/6050 PS: rate noise spectral density
        bias_instability=20.0 * DPH,  # not in the datasheet: Allan studies give 10–30 °/h
        rate_random_walk=2e-6,  # ≈ 25 °/h/√h, assumed
        turn_on_bias=20.0 * DPS,  # initial ZRO tolerance ±20 °/s
        scale_factor=0.03,  # sensitivity scale factor tolerance ±3 %
        scale_drift=0.003,  # sensitivity change ±2 % over −40…85 °C: ~0.3 % over ~20 K
        source="MPU-6000/6050 product specification rev 3.4: noise 0.005 °/s/√Hz, initial "
        "ZRO ±20 °/s, sensitivity ±3 %; bias instability 20 °/h and random walk assumed",
    ),
}


#: how much the estimators' white gyro noise exceeds the sensor's (timing, discretisation)
PROCESS_NOISE_MARGIN = 1.64
#: the bias instability enters the estimators as a random walk over this time (s)
BIAS_INSTABILITY_TIME_S = 100.0


def gyro_process_noise(
    noise_density: float,
    bias_instability: float,
    rate_random_walk: float,
    margin: float = PROCESS_NOISE_MARGIN,
) -> tuple[float, float]:
    """The estimators' gyro process noise from a gyro's Allan figures: white noise density
    (rad/s/√Hz, times ``margin``) and bias random-walk density (rad/s/√s: the rate random
    walk plus the bias instability spread over :data:`BIAS_INSTABILITY_TIME_S`). For the
    VN-100 grade: 1e-4 and 2e-6, the figures the estimators were first tuned with."""
    white = margin * noise_density
    walk = math.sqrt(rate_random_walk**2 + bias_instability**2 / BIAS_INSTABILITY_TIME_S)
    return white, walk
