"""The ground the simulated mower drives on: flat, a plane slope, bumps, or both.

The ground is a height field ``z = h(x, y)`` in the simulator's map frame (z up). The mower
is a rigid body resting on it: its body z axis is the ground's normal (averaged over the
mower's footprint, so bumps shorter than the mower tilt it less), its x axis the horizontal
heading projected onto the ground plane, and the camera sits ``camera_height_m`` up its z
axis from the ground contact point. On a bump or a slope the camera therefore moves sideways
relative to the wheels when the mower tilts — what a real mast does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Bump:
    """A smooth round bump (or dip, negative height): ``height · exp(−d² / 2σ²)``."""

    x: float
    y: float
    height_m: float
    sigma_m: float


@dataclass(frozen=True)
class Terrain:
    """A hillside and bumps. The hillside is flat on one side of a line through
    ``slope_origin`` and rises towards ``slope_dir_deg`` on the other, its slope growing
    smoothly to ``slope_deg`` over ``slope_width_m`` (``h = tan α · L · softplus(u / L)``): a
    uniform slope would be no test at all, since the world frame tilts with the mower's start
    and the lawn would be a plane in it."""

    slope_deg: float = 0.0
    slope_dir_deg: float = 0.0
    bumps: tuple[Bump, ...] = field(default_factory=tuple)
    footprint_m: float = 0.25  # the normal is averaged over ± this (the mower's half length)
    slope_origin: tuple[float, float] = (0.0, 0.0)
    slope_width_m: float = 3.0

    @property
    def flat(self) -> bool:
        return self.slope_deg == 0.0 and not self.bumps

    def _ramp(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Height of the hillside and its direction (cos, sin) times the local slope."""
        g = math.tan(math.radians(self.slope_deg))
        a = math.radians(self.slope_dir_deg)
        ca, sa = math.cos(a), math.sin(a)
        w = self.slope_width_m
        u = ((x - self.slope_origin[0]) * ca + (y - self.slope_origin[1]) * sa) / w
        h = g * w * np.logaddexp(0.0, u)  # softplus, no overflow
        local = g / (1.0 + np.exp(-u))
        return h, local * ca, local * sa

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        h = self._ramp(x, y)[0] if self.slope_deg else np.zeros_like(x)
        for b in self.bumps:
            h = h + b.height_m * np.exp(-((x - b.x) ** 2 + (y - b.y) ** 2) / (2 * b.sigma_m**2))
        return h

    def gradient(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """∂h/∂x, ∂h/∂y, averaged over the footprint (a 5-point stencil) for the bumps."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.slope_deg:
            _, dx, dy = self._ramp(x, y)
        else:
            dx, dy = np.zeros_like(x), np.zeros_like(y)
        if self.bumps:
            f = self.footprint_m
            dx = dx + (self._bumps(x + f, y) - self._bumps(x - f, y)) / (2 * f)
            dy = dy + (self._bumps(x, y + f) - self._bumps(x, y - f)) / (2 * f)
        return dx, dy

    def _bumps(self, x: FloatArray, y: FloatArray) -> FloatArray:
        h = np.zeros_like(x)
        for b in self.bumps:
            h = h + b.height_m * np.exp(-((x - b.x) ** 2 + (y - b.y) ** 2) / (2 * b.sigma_m**2))
        return h

    def normal(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Unit ground normals (N, 3) (up)."""
        dx, dy = self.gradient(x, y)
        n = np.stack([-dx, -dy, np.ones_like(dx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def attitude(self, x: FloatArray, y: FloatArray, heading: FloatArray) -> FloatArray:
        """``R_mb`` (N, 3, 3) of a mower at (x, y) heading ``heading`` (horizontal, rad)."""
        n = self.normal(x, y)
        h = np.asarray(heading, dtype=np.float64)
        d = np.stack([np.cos(h), np.sin(h), np.zeros_like(h)], axis=-1)
        xb = d - np.sum(d * n, axis=-1, keepdims=True) * n
        xb /= np.linalg.norm(xb, axis=-1, keepdims=True)
        yb = np.cross(n, xb)
        return np.stack([xb, yb, n], axis=-1)  # columns: body axes in the map frame


def random_bumps(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    density_per_m2: float,
    height_m: tuple[float, float],
    sigma_m: tuple[float, float],
) -> tuple[Bump, ...]:
    """Bumps and dips scattered over ``bounds`` (xmin, ymin, xmax, ymax)."""
    x0, y0, x1, y1 = bounds
    n = max(1, round(density_per_m2 * (x1 - x0) * (y1 - y0)))
    out = []
    for _ in range(n):
        h = rng.uniform(*height_m) * rng.choice([-1.0, 1.0])
        out.append(
            Bump(
                float(rng.uniform(x0, x1)),
                float(rng.uniform(y0, y1)),
                float(h),
                float(rng.uniform(*sigma_m)),
            )
        )
    return tuple(out)
