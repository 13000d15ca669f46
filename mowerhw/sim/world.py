"""Simulated yards: a lawn, the ground, landmarks around it, beds inside, and the camera.

Coordinates here are the *map* frame of the simulator (x, y on the ground plane, z up; the
ground is at ``terrain.height(x, y)``). The estimators never see this frame:
:mod:`mowerhw.sim.motion` expresses the truth in the world frame of docs/design.md §3 (the body
frame at the first sample). Scenario presets: :mod:`mowerhw.sim.scenarios`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray

from mowerhw.camera import OmniRadtanCamera, paper_table1_camera
from mowerhw.sim.lawn import random_lawn, shaped_lawn
from mowerhw.sim.terrain import Terrain, random_bumps

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class World:
    """One yard: the lawn edge, the ground, landmarks (map frame, absolute z), flower beds
    (keep-out polygons, map frame), the camera."""

    scenario: Any  # mowerhw.sim.scenarios.Scenario
    lawn: Any  # HarmonicLawn or PathLawn: arc length → point, heading
    landmark_ids: NDArray[np.int64]
    landmarks_map: FloatArray  # (N, 3)
    camera: OmniRadtanCamera = field(default_factory=paper_table1_camera)
    q_bc: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 0.0)
    terrain: Terrain = field(default_factory=Terrain)
    beds: tuple[FloatArray, ...] = ()  # (M, 2) outlines, map frame
    #: per landmark, the index of the landmark it is the look-alike twin of (the same
    #: panel, turned half round the lawn's centre), or −1 (scenario ``twins``)
    twin_of: NDArray[np.int64] | None = None

    @property
    def n_landmarks(self) -> int:
        return int(self.landmark_ids.size)


def place_landmarks(
    rng: np.random.Generator, outline: FloatArray, distance_m: tuple[float, float], n: int
) -> FloatArray:
    """``n`` points (x, y) uniformly around a lawn edge, within a distance band of it."""
    edge = shapely.LinearRing(outline)
    lo, hi = distance_m
    region = shapely.Polygon(edge).buffer(hi)
    minx, miny, maxx, maxy = region.bounds
    points: list[FloatArray] = []
    while len(points) < n:
        cand = rng.uniform([minx, miny], [maxx, maxy], size=(4 * n, 2))
        inside = shapely.contains_xy(region, cand[:, 0], cand[:, 1])
        far = shapely.distance(edge, shapely.points(cand)) >= lo
        points.extend(cand[inside & far])
    return np.asarray(points[:n])


def place_beds(
    rng: np.random.Generator,
    outline: FloatArray,
    n: int,
    radius_m: tuple[float, float] = (0.7, 1.1),
) -> list[tuple[FloatArray, float]]:
    """``n`` round beds inside the lawn, at least 1.5 m from its edge and from each other:
    (centre, radius)."""
    lawn = shapely.Polygon(outline)
    minx, miny, maxx, maxy = lawn.bounds
    beds: list[tuple[FloatArray, float]] = []
    for _ in range(2000):
        if len(beds) == n:
            break
        c = rng.uniform([minx, miny], [maxx, maxy])
        r = float(rng.uniform(*radius_m))
        disc = shapely.Point(c).buffer(r + 1.5)
        if not lawn.contains(disc):
            continue
        if any(np.linalg.norm(c - c2) < r + r2 + 1.5 for c2, r2 in beds):
            continue
        beds.append((c, r))
    return beds


def make_world(scenario: Any, seed: int, n_landmarks: int | None = None) -> World:
    """Draw a yard for ``scenario`` (a preset name of :mod:`mowerhw.sim.scenarios` or a
    :class:`~mowerhw.sim.scenarios.Scenario`)."""
    from mowerhw.sim.scenarios import SCENARIOS

    sc = SCENARIOS[scenario] if isinstance(scenario, str) else scenario
    rng = np.random.default_rng([seed, 1])
    if sc.shape:
        lawn: Any = shaped_lawn(sc.shape)
    else:
        lawn = random_lawn(rng, sc.perimeter_m, sc.n_harmonics, sc.amplitude)
    outline = lawn.outline(1440)
    n = sc.n_landmarks if n_landmarks is None else n_landmarks
    pairs = round(sc.twins * n / 2)
    xy = place_landmarks(rng, outline, sc.landmark_distance_m, n - pairs)
    height = rng.uniform(*sc.landmark_height_m, size=n - pairs)
    twin_of = np.full(n, -1, dtype=np.int64)
    if pairs:  # the first ``pairs`` landmarks get a twin half round the lawn's centre
        centre = 0.5 * (outline.min(axis=0) + outline.max(axis=0))
        xy = np.vstack([xy, 2 * centre - xy[:pairs]])
        height = np.concatenate([height, height[:pairs]])
        twin_of[n - pairs :] = np.arange(pairs)
    beds = place_beds(rng, outline, sc.beds) if sc.beds else []
    terrain = Terrain()
    if sc.slope_deg or sc.bumps_per_m2:
        bumps: tuple = ()
        if sc.bumps_per_m2:
            lx0, ly0 = outline.min(axis=0) - 2.0
            lx1, ly1 = outline.max(axis=0) + 2.0
            bumps = random_bumps(
                rng, (lx0, ly0, lx1, ly1), sc.bumps_per_m2, (0.03, 0.08), (0.3, 0.6)
            )
        centre = outline.mean(axis=0) + rng.uniform(-2.0, 2.0, size=2)
        terrain = Terrain(
            sc.slope_deg,
            float(rng.uniform(0, 360)),
            bumps,
            slope_origin=(float(centre[0]), float(centre[1])),
        )
    trees = np.array([[c[0], c[1]] for c, _ in beds]).reshape(-1, 2)
    tree_h = rng.uniform(1.5, 3.0, size=len(beds))
    xy = np.vstack([xy, trees])
    height = np.concatenate([height, tree_h])
    twin_of = np.concatenate([twin_of, np.full(len(beds), -1, dtype=np.int64)])
    z = terrain.height(xy[:, 0], xy[:, 1]) + height
    landmarks = np.column_stack([xy, z])
    bed_outlines = tuple(
        np.asarray(shapely.Point(c).buffer(r, quad_segs=8).exterior.coords)[:-1] for c, r in beds
    )
    return World(
        sc,
        lawn,
        np.arange(landmarks.shape[0], dtype=np.int64),
        landmarks,
        terrain=terrain,
        beds=bed_outlines,
        twin_of=twin_of if pairs else None,
    )
