"""Simulated yards: a lawn, landmarks around it, and the camera that sees them.

Coordinates here are the *map* frame of the simulator (x, y on the ground, z = height above
the ground). The estimators never see this frame: :mod:`mowerhw.sim.motion` expresses the
truth in the world frame of DESIGN.md §3 (the body frame at the first sample).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from numpy.typing import NDArray

from mowerhw.camera import OmniRadtanCamera, paper_table1_camera
from mowerhw.sim.lawn import HarmonicLawn, random_lawn

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Scenario:
    """What a simulated yard looks like; a seed draws one instance."""

    name: str
    perimeter_m: float
    n_landmarks: int
    speed_mps: float
    landmark_distance_m: tuple[float, float]  # from the lawn edge (inside or outside)
    landmark_height_m: tuple[float, float]  # above the ground
    max_range_m: float  # the camera resolves a landmark up to this distance
    n_harmonics: int = 2
    amplitude: float = 0.15
    camera_height_m: float = 0.8
    standstill_s: float = 2.0


SCENARIOS: dict[str, Scenario] = {
    # The paper's §V: 15 landmarks at random in 3D, a closed teach loop of about 60 s.
    "paper": Scenario(
        name="paper",
        perimeter_m=26.0,
        n_landmarks=15,
        speed_mps=0.45,
        landmark_distance_m=(1.5, 6.0),
        landmark_height_m=(0.3, 2.5),
        max_range_m=30.0,
    ),
    # A larger, gently concave lawn for scaling: ≥ 150 m perimeter, ≥ 60 landmarks, a
    # limited camera range so landmarks come and go (keyframes change).
    "large": Scenario(
        name="large",
        perimeter_m=160.0,
        n_landmarks=80,
        speed_mps=0.6,
        landmark_distance_m=(1.5, 8.0),
        landmark_height_m=(0.3, 3.0),
        max_range_m=15.0,
        n_harmonics=3,
        amplitude=0.25,
    ),
}


@dataclass(frozen=True)
class World:
    """One yard: the lawn edge (map frame), landmarks (map frame, z above ground), camera."""

    scenario: Scenario
    lawn: HarmonicLawn
    landmark_ids: NDArray[np.int64]
    landmarks_map: FloatArray  # (N, 3)
    camera: OmniRadtanCamera = field(default_factory=paper_table1_camera)
    q_bc: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 0.0)

    @property
    def n_landmarks(self) -> int:
        return int(self.landmark_ids.size)


def place_landmarks(
    rng: np.random.Generator, lawn: HarmonicLawn, scenario: Scenario, n: int
) -> FloatArray:
    """``n`` landmarks uniformly around the lawn edge, within the scenario's distance band."""
    edge = shapely.LinearRing(lawn.outline(1440))
    lo, hi = scenario.landmark_distance_m
    region = shapely.Polygon(edge).buffer(hi)
    minx, miny, maxx, maxy = region.bounds
    points: list[FloatArray] = []
    while len(points) < n:
        cand = rng.uniform([minx, miny], [maxx, maxy], size=(4 * n, 2))
        inside = shapely.contains_xy(region, cand[:, 0], cand[:, 1])
        far = shapely.distance(edge, shapely.points(cand)) >= lo
        points.extend(cand[inside & far])
    xy = np.asarray(points[:n])
    z = rng.uniform(*scenario.landmark_height_m, size=n)
    return np.column_stack([xy, z])


def make_world(scenario: str | Scenario, seed: int, n_landmarks: int | None = None) -> World:
    """Draw a yard for ``scenario`` (a name in :data:`SCENARIOS` or a :class:`Scenario`)."""
    sc = SCENARIOS[scenario] if isinstance(scenario, str) else scenario
    rng = np.random.default_rng([seed, 1])
    lawn = random_lawn(rng, sc.perimeter_m, sc.n_harmonics, sc.amplitude)
    n = sc.n_landmarks if n_landmarks is None else n_landmarks
    landmarks = place_landmarks(rng, lawn, sc, n)
    return World(sc, lawn, np.arange(n, dtype=np.int64), landmarks)
