"""The simulated bench: worlds, true motion, sensor streams (docs/design.md §9).

Pure computation (numpy, shapely): used by the tests, the ``mowerhw sim`` commands, the
tools and, through drivers/mock, by the mock hardware.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.sim.motion import Truth, teach_loop
from mowerhw.sim.scenarios import MATRIX, SCENARIOS, Scenario
from mowerhw.sim.sensors import (
    IMU_GRADES,
    PAPER_SENSORS,
    Rates,
    SensorStreams,
    SensorSuite,
    simulate_sensors,
)
from mowerhw.sim.world import World, make_world

__all__ = [
    "IMU_GRADES",
    "MATRIX",
    "PAPER_SENSORS",
    "SCENARIOS",
    "Rates",
    "Scenario",
    "SensorStreams",
    "SensorSuite",
    "TeachRun",
    "Truth",
    "World",
    "make_world",
    "simulate_teach",
]


@dataclass
class TeachRun:
    """A simulated teach drive: the world, the truth, and what the sensors reported."""

    scenario: str
    seed: int
    world: World
    truth: Truth
    landmarks_w: NDArray[np.float64]  # (N, 3) true landmark positions, world frame
    streams: SensorStreams

    @property
    def duration_s(self) -> float:
        return float(self.truth.t[-1])

    def true_boundary(self) -> NDArray[np.float64]:
        """The true path on the ground (world xy), the boundary the teach run should find."""
        return self.truth.xy


def simulate_teach(
    scenario: str | Scenario = "paper",
    seed: int = 0,
    n_landmarks: int | None = None,
    sensors: SensorSuite | None = None,
) -> TeachRun:
    """One teach drive around a random lawn of ``scenario``; ``seed`` makes it repeatable.
    ``sensors`` replaces the scenario's own."""
    world = make_world(scenario, seed, n_landmarks)
    sc = world.scenario
    sensors = sensors or sc.sensors
    truth = teach_loop(
        world.lawn,
        sc.speed_mps,
        sc.camera_height_m,
        sensors.rates.imu_hz,
        standstill_s=sc.standstill_s,
        terrain=world.terrain,
    )
    landmarks_w = truth.map_to_world(world.landmarks_map)
    streams = simulate_sensors(world, truth, landmarks_w, seed, sensors)
    return TeachRun(sc.name, seed, world, truth, landmarks_w, streams)
