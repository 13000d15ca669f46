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


@dataclass(frozen=True)
class _Piece:
    """A straight segment (``kappa`` 0) or a circular arc of a :class:`PathLawn`."""

    s0: float
    length: float
    start: tuple[float, float]
    heading0: float  # unwrapped
    kappa: float


class PathLawn:
    """A polygonal lawn (counter-clockwise corners) whose corners are rounded to arcs of
    ``fillet_m``: the path a mower traces along an L, a U, a strip. Same interface as
    :class:`HarmonicLawn` (arc length → point, heading, curvature); concave corners turn
    right (negative curvature)."""

    def __init__(self, corners: FloatArray | list[tuple[float, float]], fillet_m: float = 1.0):
        pts = np.asarray(corners, dtype=np.float64)
        if pts.shape[0] < 3 or pts.shape[1] != 2:
            raise ValueError("a lawn needs at least 3 corners (x, y)")
        area = 0.5 * np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1])
        if area < 0:
            pts = pts[::-1]
        self.corners = pts
        self.fillet_m = fillet_m
        n = len(pts)
        d = np.roll(pts, -1, axis=0) - pts  # edge i: corner i → i+1
        length = np.linalg.norm(d, axis=1)
        u = d / length[:, None]
        # turn at corner i (between edge i-1 and edge i), left positive
        u_in = np.roll(u, 1, axis=0)
        turn = np.arctan2(u_in[:, 0] * u[:, 1] - u_in[:, 1] * u[:, 0], np.sum(u_in * u, axis=1))
        cut = fillet_m * np.tan(np.abs(turn) / 2.0)
        if np.any(length < cut + np.roll(cut, -1) + 1e-9):
            raise ValueError(f"edges too short for {fillet_m} m rounded corners")
        pieces: list[_Piece] = []
        s = 0.0
        heading = float(np.arctan2(u[0, 1], u[0, 0]))
        for i in range(n):  # edge i (after corner i's arc), then corner i+1's arc
            start = pts[i] + u[i] * cut[i]
            seg = length[i] - cut[i] - cut[(i + 1) % n]
            pieces.append(_Piece(s, float(seg), (float(start[0]), float(start[1])), heading, 0.0))
            s += seg
            j = (i + 1) % n
            arc_start = pts[j] - u[i] * cut[j]
            k = float(np.sign(turn[j]) / fillet_m)
            arc_len = float(abs(turn[j]) * fillet_m)
            pieces.append(
                _Piece(s, arc_len, (float(arc_start[0]), float(arc_start[1])), heading, k)
            )
            s += arc_len
            heading += float(turn[j])
        self._pieces = pieces
        self._s0 = np.array([p.s0 for p in pieces])
        self.perimeter = float(s)

    def _locate(self, s: FloatArray) -> tuple[NDArray[np.int64], FloatArray]:
        s = np.mod(np.asarray(s, dtype=np.float64), self.perimeter)
        idx = np.clip(np.searchsorted(self._s0, s, side="right") - 1, 0, len(self._pieces) - 1)
        return idx, s - self._s0[idx]

    def point(self, s: FloatArray) -> FloatArray:
        idx, ds = self._locate(s)
        out = np.empty((*ds.shape, 2))
        for i in np.unique(idx):
            p = self._pieces[int(i)]
            m = idx == i
            a = ds[m]
            if p.kappa == 0.0:
                out[m, 0] = p.start[0] + a * np.cos(p.heading0)
                out[m, 1] = p.start[1] + a * np.sin(p.heading0)
            else:
                h = p.heading0 + p.kappa * a
                out[m, 0] = p.start[0] + (np.sin(h) - np.sin(p.heading0)) / p.kappa
                out[m, 1] = p.start[1] - (np.cos(h) - np.cos(p.heading0)) / p.kappa
        return out

    def heading(self, s: FloatArray) -> FloatArray:
        """Direction of travel (rad), unwrapped along the first lap; later laps add 2π."""
        s = np.asarray(s, dtype=np.float64)
        laps = np.floor(s / self.perimeter)
        idx, ds = self._locate(s)
        h0 = np.array([self._pieces[int(i)].heading0 for i in idx.ravel()]).reshape(idx.shape)
        k = np.array([self._pieces[int(i)].kappa for i in idx.ravel()]).reshape(idx.shape)
        return h0 + k * ds + 2.0 * np.pi * laps

    def curvature(self, s: FloatArray) -> FloatArray:
        idx, _ = self._locate(s)
        return np.array([self._pieces[int(i)].kappa for i in idx.ravel()]).reshape(idx.shape)

    def outline(self, n: int = 720) -> FloatArray:
        return self.point(np.linspace(0.0, self.perimeter, n, endpoint=False))


#: lawn shapes by name: corners (m, counter-clockwise) and corner radius
SHAPES: dict[str, tuple[list[tuple[float, float]], float]] = {
    "L": ([(0, 0), (14, 0), (14, 6), (6, 6), (6, 12), (0, 12)], 1.0),
    "U": (
        [(0, 0), (15, 0), (15, 11), (10.5, 11), (10.5, 4.5), (4.5, 4.5), (4.5, 11), (0, 11)],
        1.0,
    ),
    "strip": ([(0, 0), (32, 0), (32, 4), (0, 4)], 1.2),
    "rectangle": ([(0, 0), (12, 0), (12, 8), (0, 8)], 1.5),
    # two lawns joined by a path (mowerhw.sim.garden)
    "garden": (
        [(0, 0), (8, 0), (8, 2), (12, 2), (12, 0), (20, 0), (20, 6), (12, 6), (12, 4), (8, 4)]
        + [(8, 6), (0, 6)],
        0.5,
    ),
}


def shaped_lawn(name: str) -> PathLawn:
    corners, fillet = SHAPES[name]
    return PathLawn(corners, fillet)
