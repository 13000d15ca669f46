"""Lawn outlines for the simulator: smooth closed curves, parametrised by arc length.

A lawn edge is the polar curve ``r(θ) = R₀ (1 + Σ a_k cos(kθ + φ_k))`` (a few harmonics give
round, oval, kidney or gently concave lawns). It is sampled densely once; position, heading
and curvature at any arc length come from analytic derivatives at the interpolated θ, so the
mower's true motion is smooth and exactly consistent with its gyro and speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class HarmonicLawn:
    """Closed curve ``r(θ) = R₀ (1 + Σ a_k cos(k θ + φ_k))``, traversed counter-clockwise."""

    r0: float
    harmonics: tuple[tuple[int, float, float], ...]  # (k, a_k, φ_k)
    samples: int = 8192

    def __post_init__(self) -> None:
        theta = np.linspace(0.0, 2.0 * np.pi, self.samples + 1)
        dx, dy = self._d1(theta)
        speed = np.hypot(dx, dy)
        s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(theta))])
        object.__setattr__(self, "_theta", theta)
        object.__setattr__(self, "_s", s)

    # r(θ) and its derivatives --------------------------------------------------------------
    def _r(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        r = np.ones_like(t)
        dr = np.zeros_like(t)
        ddr = np.zeros_like(t)
        for k, a, phi in self.harmonics:
            r = r + a * np.cos(k * t + phi)
            dr = dr - a * k * np.sin(k * t + phi)
            ddr = ddr - a * k * k * np.cos(k * t + phi)
        return self.r0 * r, self.r0 * dr, self.r0 * ddr

    def _d1(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        r, dr, _ = self._r(t)
        return dr * np.cos(t) - r * np.sin(t), dr * np.sin(t) + r * np.cos(t)

    @property
    def perimeter(self) -> float:
        return float(self._s[-1])  # type: ignore[attr-defined]

    def theta_at(self, s: FloatArray) -> FloatArray:
        s = np.mod(np.asarray(s, dtype=np.float64), self.perimeter)
        return np.interp(s, self._s, self._theta)  # type: ignore[attr-defined]

    def point(self, s: FloatArray) -> FloatArray:
        """(x, y) at arc length ``s`` (map frame)."""
        t = self.theta_at(s)
        r, _, _ = self._r(t)
        return np.stack([r * np.cos(t), r * np.sin(t)], axis=-1)

    def heading(self, s: FloatArray) -> FloatArray:
        """Direction of travel (rad) at arc length ``s``, continuous (unwrapped along s)."""
        t = self.theta_at(s)
        dx, dy = self._d1(t)
        return np.arctan2(dy, dx)

    def curvature(self, s: FloatArray) -> FloatArray:
        """Signed curvature (1/m; positive = turning left) at arc length ``s``."""
        t = self.theta_at(s)
        r, dr, ddr = self._r(t)
        num = r * r + 2 * dr * dr - r * ddr
        return num / (r * r + dr * dr) ** 1.5

    def outline(self, n: int = 720) -> FloatArray:
        """``n`` points of the closed outline (not repeating the first)."""
        return self.point(np.linspace(0.0, self.perimeter, n, endpoint=False))


def random_lawn(
    rng: np.random.Generator,
    perimeter_m: float,
    n_harmonics: int = 2,
    amplitude: float = 0.15,
    max_curvature: float = 1.2,
) -> HarmonicLawn:
    """A random smooth lawn with about the requested perimeter and bounded curvature."""
    for _ in range(200):
        harmonics = tuple(
            (
                k,
                float(rng.uniform(0.3, 1.0) * amplitude / (k - 1)),
                float(rng.uniform(0, 2 * np.pi)),
            )
            for k in range(2, 2 + n_harmonics)
        )
        unit = HarmonicLawn(1.0, harmonics, samples=2048)
        lawn = HarmonicLawn(perimeter_m / unit.perimeter, harmonics)
        kappa = lawn.curvature(np.linspace(0.0, lawn.perimeter, 2000))
        if np.abs(kappa).max() <= max_curvature:
            return lawn
    raise RuntimeError("could not draw a lawn with bounded curvature; lower the amplitude")
