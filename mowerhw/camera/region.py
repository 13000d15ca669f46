"""The usable image region of an omnidirectional camera, found from its own photos.

A mirror camera sees the world in an annulus: outside it the mirror's rim, the mount and the
black corners of the sensor; inside it the camera's own reflection. A fisheye lens sees it in
an image circle. Both are circles (the optics are round), so both are found the same way:

1. over all photos, per pixel, the mean and the standard deviation of the brightness (each
   photo scaled to the same mean first, so auto-exposure does not count as change): the
   world changes from photo to photo and is textured, the rim, the mount and the black
   corners do not, so the region's edges are where either of the two steps;
2. both images resampled on rays from the principal point (``cv2.warpPolar``); on each ray,
   the strongest radial steps are candidate edge points — outside every checkerboard corner
   for the outer edge (the corners were seen, so they are inside), inside every corner for
   the inner one;
3. a circle fitted to the candidates by RANSAC (one point per ray), then by least squares on
   its inliers; it is accepted only if most rays on which it lies inside the image support it.

The annulus is then shrunk by a margin (the rim is blurred over a few pixels). A fisheye with
no inner edge gets ``inner = 0``; an image with no visible outer edge (the circle is larger
than the sensor) is limited by the image and the model's domain alone.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mowerhw.camera.model import Annulus

FloatArray = NDArray[np.float64]

#: rays around the principal point
RAYS = 720
#: a circle is accepted when at least this share of the rays that can see it support it
MIN_SUPPORT = 0.5
#: candidate edge points on a ray (the strongest steps, at least 4 px apart)
CANDIDATES_PER_RAY = 3
#: a candidate within this distance of the circle supports it (px)
INLIER_PX = 2.0


@dataclass(frozen=True)
class Circle:
    """A fitted edge: centre and radius (px), and the share of rays that support it."""

    center: tuple[float, float]
    radius: float
    support: float
    rays: int  # rays on which it lies inside the image


@dataclass(frozen=True)
class Region:
    """What was found: the outer and inner edges (None if not seen) and the annulus."""

    annulus: Annulus | None
    outer: Circle | None
    inner: Circle | None
    margin_px: float

    def as_dict(self) -> dict[str, object]:
        def circle(c: Circle | None) -> dict[str, object] | None:
            if c is None:
                return None
            return {
                "center_px": [round(c.center[0], 2), round(c.center[1], 2)],
                "radius_px": round(c.radius, 2),
                "support": round(c.support, 3),
                "rays": c.rays,
            }

        ann = self.annulus
        return {
            "outer_edge": circle(self.outer),
            "inner_edge": circle(self.inner),
            "margin_px": self.margin_px,
            "annulus": None
            if ann is None
            else {
                "center_px": [round(ann.center_px[0], 2), round(ann.center_px[1], 2)],
                "inner_radius_px": round(ann.inner_radius_px, 2),
                "outer_radius_px": round(ann.outer_radius_px, 2),
            },
        }


class BrightnessStats:
    """Per-pixel mean and standard deviation over photos (Welford), exposure-normalised."""

    def __init__(self) -> None:
        self.n = 0
        self._mean: FloatArray | None = None
        self._m2: FloatArray | None = None
        self._level = 0.0

    def add(self, grey: NDArray[np.uint8]) -> None:
        img = grey.astype(np.float64)
        level = float(img.mean())
        if self.n == 0:
            self._level = level
            self._mean = np.zeros_like(img)
            self._m2 = np.zeros_like(img)
        elif img.shape != self._mean.shape:  # type: ignore[union-attr]
            raise ValueError(f"photo of {img.shape[::-1]} px among photos of another size")
        img *= self._level / max(level, 1e-6)
        self.n += 1
        delta = img - self._mean
        self._mean += delta / self.n  # type: ignore[operator]
        self._m2 += delta * (img - self._mean)  # type: ignore[operator]

    @property
    def mean(self) -> FloatArray:
        assert self._mean is not None, "no photos"
        return self._mean

    @property
    def std(self) -> FloatArray:
        assert self._m2 is not None, "no photos"
        return np.sqrt(self._m2 / max(self.n - 1, 1))


def find_region(
    stats: BrightnessStats,
    center: tuple[float, float],
    corner_radii: Iterable[float],
    margin_px: float | None = None,
    seed: int = 0,
) -> Region:
    """The annulus (or image circle) of photos summarised by ``stats``; ``center``: the
    principal point; ``corner_radii``: distances of the detected checkerboard corners from it
    (the region's edges lie outside / inside all of them)."""
    radii = np.asarray(list(corner_radii), dtype=np.float64)
    if radii.size == 0:
        raise ValueError("no checkerboard corners to tell the inside of the region from outside")
    mean, std = stats.mean, stats.std
    h, w = mean.shape
    cx, cy = center
    r_max = int(np.ceil(np.hypot(max(cx, w - cx), max(cy, h - cy)))) + 2
    edge, seen = _edge_strength(mean, std, (cx, cy), r_max)
    r_corner_lo, r_corner_hi = float(radii.min()), float(radii.max())
    outer = _fit(edge, seen, (cx, cy), int(r_corner_hi) + 3, r_max, seed)
    inner = _fit(edge, seen, (cx, cy), 3, int(r_corner_lo) - 3, seed + 1)
    if outer is not None and outer.radius <= r_corner_hi:
        outer = None
    if inner is not None and (inner.radius >= r_corner_lo or inner.radius < 5):
        inner = None
    if margin_px is None:
        margin_px = max(3.0, 0.01 * (outer.radius if outer else r_corner_hi))
    if outer is None and inner is None:
        return Region(None, None, None, margin_px)
    c = outer.center if outer is not None else inner.center  # type: ignore[union-attr]
    outer_r = outer.radius - margin_px if outer is not None else float(r_max) + np.hypot(w, h)
    inner_r = 0.0
    if inner is not None:  # from the outer centre, the whole inner disc plus the margin
        offset = float(np.hypot(inner.center[0] - c[0], inner.center[1] - c[1]))
        inner_r = inner.radius + offset + margin_px
    annulus = Annulus((float(c[0]), float(c[1])), float(inner_r), float(outer_r))
    return Region(annulus, outer, inner, float(margin_px))


def _edge_strength(
    mean: FloatArray, std: FloatArray, center: tuple[float, float], r_max: int
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Radial step strength on RAYS × r_max polar samples, and where a sample is in the image
    (away from its border, whose own step is not an edge of the optics)."""
    flags = cv2.WARP_POLAR_LINEAR + cv2.INTER_LINEAR + cv2.WARP_FILL_OUTLIERS

    def polar(img: FloatArray) -> FloatArray:
        out = cv2.warpPolar(img.astype(np.float32), (r_max, RAYS), center, r_max, flags)
        return np.asarray(out, dtype=np.float64)

    inside = polar(np.ones_like(mean)) > 0.999
    seen = cv2.erode(inside.astype(np.uint8), np.ones((1, 11), np.uint8)).astype(bool)
    strength = np.zeros((RAYS, r_max))
    for img in (mean, std):
        p = cv2.GaussianBlur(polar(img), (0, 0), sigmaX=1.5, sigmaY=2.0)
        step = np.abs(np.gradient(p, axis=1))
        scale = np.median(step[seen]) if np.any(seen) else 1.0
        strength += step / max(float(scale), 1e-9)
    strength[~seen] = 0.0
    return strength, seen


def _candidates(edge: FloatArray, lo: int, hi: int, center: tuple[float, float]) -> FloatArray:
    """(ray, x, y) of the strongest steps on each ray between radii ``lo`` and ``hi``."""
    lo, hi = max(lo, 1), min(hi, edge.shape[1])
    if hi - lo < 3:
        return np.zeros((0, 3))
    band = edge[:, lo:hi]
    order = np.argsort(band, axis=1)[:, ::-1][:, : 4 * CANDIDATES_PER_RAY]
    rows = []
    for ray in range(RAYS):
        chosen: list[int] = []
        for i in order[ray]:
            if band[ray, i] <= 0.0:
                break
            if all(abs(int(i) - c) > 4 for c in chosen):
                chosen.append(int(i))
            if len(chosen) == CANDIDATES_PER_RAY:
                break
        theta = 2.0 * np.pi * ray / RAYS
        for i in chosen:
            r = lo + i
            rows.append((ray, center[0] + r * np.cos(theta), center[1] + r * np.sin(theta)))
    return np.array(rows) if rows else np.zeros((0, 3))


def _circle_through(p: FloatArray) -> tuple[float, float, float] | None:
    """Least-squares circle (algebraic fit) through points ``p`` (N ≥ 3, 2)."""
    a = np.c_[2.0 * p[:, 0], 2.0 * p[:, 1], np.ones(len(p))]
    b = p[:, 0] ** 2 + p[:, 1] ** 2
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    x0, y0, c = sol
    r2 = c + x0 * x0 + y0 * y0
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return float(x0), float(y0), float(np.sqrt(r2))


def _rays_seeing(
    seen: NDArray[np.bool_], circle: tuple[float, float, float], center: tuple[float, float]
) -> NDArray[np.bool_]:
    """Rays (from ``center``) on which ``circle`` lies inside the image."""
    x0, y0, r = circle
    theta = 2.0 * np.pi * np.arange(RAYS) / RAYS
    # where the ray from center meets the circle (the far intersection)
    dx, dy = np.cos(theta), np.sin(theta)
    ox, oy = center[0] - x0, center[1] - y0
    b = ox * dx + oy * dy
    disc = b * b - (ox * ox + oy * oy - r * r)
    t = -b + np.sqrt(np.maximum(disc, 0.0))
    radius = np.clip(np.round(t).astype(int), 0, seen.shape[1] - 1)
    return (disc > 0) & seen[np.arange(RAYS), radius]


def _fit(
    edge: FloatArray,
    seen: NDArray[np.bool_],
    center: tuple[float, float],
    lo: int,
    hi: int,
    seed: int,
    iterations: int = 1500,
) -> Circle | None:
    pts = _candidates(edge, lo, hi, center)
    if pts.shape[0] < 3:
        return None
    rng = np.random.default_rng(seed)
    rays = pts[:, 0].astype(int)
    best_score, best = 0, None
    for _ in range(iterations):
        idx = rng.choice(pts.shape[0], 3, replace=False)
        if len(set(rays[idx])) < 3:
            continue
        circle = _circle_through(pts[idx, 1:])
        if circle is None:
            continue
        x0, y0, r = circle
        dist = np.abs(np.hypot(pts[:, 1] - x0, pts[:, 2] - y0) - r)
        score = len(set(rays[dist < INLIER_PX]))
        if score > best_score:
            best_score, best = score, circle
    if best is None:
        return None
    for _ in range(3):  # refine on the inliers (one per ray: the nearest)
        x0, y0, r = best
        dist = np.abs(np.hypot(pts[:, 1] - x0, pts[:, 2] - y0) - r)
        keep = dist < INLIER_PX
        refined = _circle_through(pts[keep, 1:]) if keep.sum() >= 3 else None
        if refined is None:
            break
        best = refined
    x0, y0, r = best
    dist = np.abs(np.hypot(pts[:, 1] - x0, pts[:, 2] - y0) - r)
    supporting = len(set(rays[dist < INLIER_PX]))
    visible = int(_rays_seeing(seen, best, center).sum())
    support = supporting / max(visible, 1)
    if visible < RAYS // 10 or support < MIN_SUPPORT:
        return None
    return Circle((x0, y0), r, min(support, 1.0), visible)
