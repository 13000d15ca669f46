"""The simulated bench: worlds, true motion, sensor streams (DESIGN.md §9).

Pure computation (numpy, shapely): used by the tests, the ``mowerhw sim`` commands, the
tools and, through drivers/mock, by the mock hardware.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.sim.motion import PlanarTruth, teach_loop
from mowerhw.sim.sensors import Rates, SensorNoise, SensorStreams, simulate_sensors
from mowerhw.sim.world import SCENARIOS, Scenario, World, make_world

__all__ = [
    "SCENARIOS",
    "PlanarTruth",
    "Rates",
    "Scenario",
    "SensorNoise",
    "SensorStreams",
    "TeachRun",
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
    truth: PlanarTruth
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
    noise: SensorNoise | None = None,
    rates: Rates | None = None,
) -> TeachRun:
    """One teach drive around a random lawn of ``scenario``; ``seed`` makes it repeatable."""
    world = make_world(scenario, seed, n_landmarks)
    sc = world.scenario
    rates = rates or Rates()
    truth = teach_loop(
        world.lawn, sc.speed_mps, sc.camera_height_m, rates.imu_hz, standstill_s=sc.standstill_s
    )
    landmarks_w = truth.map_to_world(world.landmarks_map)
    streams = simulate_sensors(world, truth, landmarks_w, seed, noise, rates)
    return TeachRun(sc.name, seed, world, truth, landmarks_w, streams)
