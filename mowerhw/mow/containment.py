"""Containment: may the deck run here? (docs/design.md §5 table; paper §IV).

``s`` is the signed distance from the estimated position to the lawn's edge — positive
inside, keep-out zones being holes — and ``σ`` the largest standard deviation of the
estimated horizontal position. With ``m = s − k σ``:

| state     | when                                   | permit |
|-----------|----------------------------------------|--------|
| INSIDE    | ``m ≥ margin``                         | yes    |
| NEAR_EDGE | ``0 ≤ m < margin``                     | yes (the mower's controller turns) |
| OUTSIDE   | ``m < 0``                              | no     |
| UNKNOWN   | not localized, σ too large, a sensor stale, an estimator fault, no map | no |

So that estimation noise does not chatter the deck at the edge, a *soft* violation
(``−hard_margin ≤ m < 0``) must last ``soft_persist`` consecutive samples before it halts,
and once halted for OUTSIDE, ``m ≥ 0`` must last as long before the permit returns; a *hard*
violation (``m < −hard_margin``) halts at once. Every halt carries a reason.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
import shapely.ops
from numpy.typing import NDArray
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from mowerhw.common.reasons import Reason as Reason
from mowerhw.common.reasons import State as State
from mowerhw.config import ContainmentConfig
from mowerhw.map import LawnMap

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ContainmentResult:
    state: str
    permit: bool
    signed_distance_m: float
    sigma_m: float
    reason: str  # "" while permitted
    detail: str = ""
    t: float = float("nan")


def unknown(
    reason: Reason, detail: str = "", t: float = float("nan"), sigma: float = float("nan")
) -> ContainmentResult:
    """A halt without a usable position."""
    return ContainmentResult(State.UNKNOWN, False, float("nan"), sigma, reason.value, detail, t)


class LawnGeometry:
    """The mowable area (outline minus keep-outs) as prepared shapely geometry."""

    #: the band along the edges where "inward" points at the area shrunk by it (m)
    INWARD_BAND_M = 0.5

    def __init__(
        self,
        outline: FloatArray,
        keepouts: Sequence[tuple[str, FloatArray]] = (),
        more_areas: Sequence[FloatArray] = (),
        transit: Sequence[FloatArray] = (),
    ) -> None:
        """The mowable area: ``outline`` and ``more_areas`` (mowing areas) minus the
        keep-outs; ``transit``: outlines where the mower may drive with the deck off
        (navigation areas, mowing areas not chosen), keep-outs and the mowable area taken
        out."""
        polys = [orient(Polygon(pts), 1.0) for pts in (outline, *more_areas)]
        if any(not poly.is_valid or poly.area <= 0 for poly in polys):
            raise ValueError("a mowing area's outline is not a simple polygon with an area")
        self.outline = polys[0]
        self.keepouts = [(name, Polygon(pts)) for name, pts in keepouts]
        area = polys[0] if len(polys) == 1 else shapely.union_all(polys)
        for _, zone in self.keepouts:
            area = area.difference(zone)
        if area.is_empty:
            raise ValueError("the keep-outs leave nothing to mow")
        self.area = area
        self.transit: shapely.Geometry | None = None
        if transit:
            way = shapely.union_all([Polygon(pts) for pts in transit]).difference(area)
            for _, zone in self.keepouts:
                way = way.difference(zone)
            if not way.is_empty:
                shapely.prepare(way)
                self.transit = way
        self.edges = area.boundary
        shapely.prepare(self.area)
        shapely.prepare(self.edges)
        inner = area.buffer(-self.INWARD_BAND_M)
        self._inner = inner if not inner.is_empty else None
        self._nearest = NearestEdge(*_segments(self.edges))
        self._sign_at: tuple[float, float, float] | None = None  # (x, y, s) of the last test

    def signed_distance(self, x: float, y: float) -> float:
        """Distance to the nearest edge (outline or keep-out), positive inside the mowable area.

        Called on every IMU sample, so without shapely's per-call cost: the distance from
        the few segments that can be nearest (:class:`NearestEdge`), and the inside test only
        when the point may have crossed an edge — a point within ``|s|`` of the last tested
        point (whose signed distance was ``s``) cannot have, so it keeps that point's side."""
        d = self._nearest.distance(x, y)
        last = self._sign_at
        if last is not None and math.hypot(x - last[0], y - last[1]) < abs(last[2]):
            inside = last[2] > 0.0
        else:
            inside = bool(shapely.contains_xy(self.area, x, y))
            self._sign_at = (x, y, d if inside else -d)
        return d if inside else -d

    def signed_distances(self, xy: FloatArray) -> FloatArray:
        pts = shapely.points(xy)
        d = shapely.distance(self.edges, pts)
        signed: FloatArray = np.where(shapely.contains_xy(self.area, xy[:, 0], xy[:, 1]), d, -d)
        return signed

    @classmethod
    def of_map(cls, lawn_map: LawnMap, mow_areas: Sequence[str] = ()) -> LawnGeometry:
        """The geometry of ``lawn_map``: its mowing areas (those named in ``mow_areas``,
        else all) to mow, its navigation areas and the other mowing areas to drive through;
        ValueError naming the areas there are for a name the map does not have."""
        problem = lawn_map.unknown_mow_areas(mow_areas)
        if problem:
            raise ValueError(problem)
        mow = {a.name: a.polygon for a in lawn_map.all_areas() if a.kind == "mow"}
        chosen = [pts for name, pts in mow.items() if not mow_areas or name in mow_areas]
        transit = [a.polygon for a in lawn_map.all_areas() if a.kind == "nav"]
        transit += [pts for name, pts in mow.items() if mow_areas and name not in mow_areas]
        keepouts = [(z.name, z.polygon) for z in lawn_map.keepouts]
        return cls(chosen[0], keepouts, chosen[1:], transit)

    def in_transit(self, x: float, y: float) -> bool:
        """In a navigation area (or a mowing area not chosen), outside every keep-out."""
        return self.transit is not None and bool(shapely.contains_xy(self.transit, x, y))

    def keepout_at(self, x: float, y: float) -> str | None:
        for name, zone in self.keepouts:
            if zone.covers(shapely.Point(x, y)):
                return name
        return None

    def inward_direction(self, x: float, y: float) -> FloatArray:
        """Unit vector into the mowable area. Within :data:`INWARD_BAND_M` of an edge (or
        outside): towards the nearest point of the area shrunk by that band — well defined on
        the edge itself, where the mower starts (the dock is on the taught edge) and where
        the direction from the nearest edge point is a millimetre's noise. Further in: away
        from the nearest edge."""
        p = shapely.Point(x, y)
        if self._inner is not None and not shapely.contains_xy(self._inner, x, y):
            near = shapely.ops.nearest_points(self._inner, p)[0]
            v = np.array([near.x - x, near.y - y])
            n = float(np.linalg.norm(v))
            if n > 1e-9:
                return v / n
        near = shapely.ops.nearest_points(self.edges, p)[0]
        v = np.array([x - near.x, y - near.y])
        n = float(np.linalg.norm(v))
        if n < 1e-9:  # on the edge: towards the area's representative point
            c = self.area.representative_point()
            v = np.array([c.x - x, c.y - y])
            n = float(np.linalg.norm(v))
        inside = shapely.contains_xy(self.area, x, y)
        return v / n if inside else -v / n


class NearestEdge:
    """The distance from a point to the nearest of many segments, for one point at a time
    at the IMU's rate. A square grid over the segments (and :data:`PAD_M` around) keeps,
    per cell, the segments that can be nearest to some point of it — those whose distance
    from the cell's centre is within the smallest such distance plus the cell's diagonal
    (every point of the cell is within half a diagonal of the centre) — so a query looks
    at a handful of segments in plain floats. A point off the grid, or in a cell with more
    than :data:`MAX_CANDIDATES`, is measured against every segment at once in numpy (the
    same answer: the nearest segment is always among a cell's candidates). Why not numpy
    every time: the daemon's CPU goes on wake-ups from idle, where each numpy call costs
    ten times what it costs warm (README, issue 15, stop 67: 139 → 32 µs a query)."""

    #: the grid's cell side at least (m); larger for a large lawn (at most MAX_CELLS cells)
    CELL_M = 0.5
    MAX_CELLS = 16384
    #: the grid reaches this far beyond the segments (m): a mower off the lawn by more is
    #: measured in numpy
    PAD_M = 2.0
    MAX_CANDIDATES = 24

    def __init__(self, starts: FloatArray, dirs: FloatArray, len2: FloatArray) -> None:
        self._a, self._d, self._len2 = starts, dirs, len2
        lo = starts.min(axis=0) - self.PAD_M
        hi = np.maximum(starts, starts + dirs).max(axis=0) + self.PAD_M
        span = hi - lo
        cell = max(self.CELL_M, math.sqrt(float(span[0] * span[1]) / self.MAX_CELLS))
        self._lo_x, self._lo_y, self._cell = float(lo[0]), float(lo[1]), cell
        self._nx, self._ny = (int(v) for v in np.ceil(span / cell).astype(np.int64))
        ix, iy = np.meshgrid(np.arange(self._nx), np.arange(self._ny), indexing="ij")
        centres = lo + cell * (np.stack([ix.ravel(), iy.ravel()], axis=1) + 0.5)
        rows = [tuple(float(v) for v in seg) for seg in np.column_stack([starts, dirs, len2])]
        self._cells: list[tuple[tuple[float, ...], ...] | None] = []
        for chunk in np.array_split(centres, max(1, len(centres) // 256)):
            d = np.sqrt(_distances_squared(chunk, starts, dirs, len2))
            near = d <= d.min(axis=1, keepdims=True) + cell * math.sqrt(2.0) + 1e-9
            for mask in near:
                idx = np.flatnonzero(mask)
                ok = idx.size <= self.MAX_CANDIDATES
                self._cells.append(tuple(rows[i] for i in idx) if ok else None)

    def distance(self, x: float, y: float) -> float:
        """The distance from (x, y) to the nearest segment."""
        i = math.floor((x - self._lo_x) / self._cell)
        j = math.floor((y - self._lo_y) / self._cell)
        segments = (
            self._cells[i * self._ny + j] if 0 <= i < self._nx and 0 <= j < self._ny else None
        )
        if segments is None:
            point = np.array([[x, y]])
            return math.sqrt(float(_distances_squared(point, self._a, self._d, self._len2).min()))
        best = math.inf
        for ax, ay, dx, dy, len2 in segments:
            rx, ry = x - ax, y - ay
            along = min(max((rx * dx + ry * dy) / len2, 0.0), 1.0)
            ex, ey = rx - along * dx, ry - along * dy
            best = min(best, ex * ex + ey * ey)
        return math.sqrt(best)


def _distances_squared(
    points: FloatArray, starts: FloatArray, dirs: FloatArray, len2: FloatArray
) -> FloatArray:
    """(P, S): each point's squared distance to each segment (start, direction, squared
    length)."""
    rel = points[:, None, :] - starts[None, :, :]
    along = np.clip(np.einsum("psk,sk->ps", rel, dirs) / len2, 0.0, 1.0)
    off = rel - along[:, :, None] * dirs[None, :, :]
    out: FloatArray = np.einsum("psk,psk->ps", off, off)
    return out


def _segments(edges: shapely.Geometry) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Every edge segment of ``edges`` (rings or lines) as start points, direction vectors and
    squared lengths (zero-length segments given length 1, which leaves their distance the
    distance to their point)."""
    starts, dirs = [], []
    for line in shapely.get_parts(edges).tolist():
        xy = np.asarray(line.coords, dtype=np.float64)[:, :2]
        starts.append(xy[:-1])
        dirs.append(np.diff(xy, axis=0))
    a, d = np.concatenate(starts), np.concatenate(dirs)
    len2 = np.einsum("ij,ij->i", d, d)
    len2[len2 == 0.0] = 1.0
    return a, d, len2


class Containment:
    """The containment decision with its soft/hard margins (see the module doc)."""

    def __init__(self, geometry: LawnGeometry, config: ContainmentConfig | None = None) -> None:
        self.geometry = geometry
        self.cfg = config or ContainmentConfig()
        self._t: float | None = None
        self._soft = 0  # consecutive samples of a soft violation
        self._clear = 0  # consecutive samples with m ≥ 0 while latched OUTSIDE
        self._latched = False
        self.last: ContainmentResult = unknown(Reason.NOT_LOCALIZED, "no estimate yet")

    def evaluate(
        self, t: float, x: float, y: float, sigma: float, halt: tuple[Reason, str] | None = None
    ) -> ContainmentResult:
        """Decide for the estimate (x, y, σ) at time t; ``halt`` forces UNKNOWN with a reason."""
        c = self.cfg
        # (a NaN time — no IMU sample yet — must not be kept: every later ``t > NaN`` would
        # be False, and the soft-violation and release counters would never count again)
        new_sample = math.isfinite(t) and (self._t is None or t > self._t)
        self._t = t if new_sample else self._t
        if halt is not None:
            self._soft = self._clear = 0
            self.last = unknown(halt[0], halt[1], t, sigma)
            return self.last
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(sigma)):
            self.last = unknown(Reason.FAULT, "non-finite position estimate", t, sigma)
            return self.last
        if sigma > c.sigma_max_m:
            self._soft = self._clear = 0
            self.last = unknown(
                Reason.UNCERTAIN, f"position σ {sigma:.2f} m > {c.sigma_max_m} m", t, sigma
            )
            return self.last
        s = self.geometry.signed_distance(x, y)
        m = s - c.k_sigma * sigma
        if m < -c.hard_margin_m:  # hard violation: at once
            self._latched, self._soft, self._clear = True, 0, 0
            return self._outside(t, x, y, s, sigma, "hard margin")
        if m < 0.0:  # soft violation: only if it persists
            self._clear = 0
            if new_sample:
                self._soft += 1
            if self._latched or self._soft >= c.soft_persist:
                self._latched = True
                return self._outside(t, x, y, s, sigma, f"{self._soft} samples past the edge")
            self.last = ContainmentResult(
                State.NEAR_EDGE, True, s, sigma, "", f"soft margin {self._soft}/{c.soft_persist}", t
            )
            return self.last
        self._soft = 0
        if self._latched:  # released only after m ≥ 0 persists
            if new_sample:
                self._clear += 1
            if self._clear < c.soft_persist:
                return self._outside(
                    t, x, y, s, sigma, f"back inside {self._clear}/{c.soft_persist}"
                )
            self._latched, self._clear = False, 0
        state = State.INSIDE if m >= c.margin_m else State.NEAR_EDGE
        self.last = ContainmentResult(state, True, s, sigma, "", "", t)
        return self.last

    def _outside(
        self, t: float, x: float, y: float, s: float, sigma: float, why: str
    ) -> ContainmentResult:
        zone = self.geometry.keepout_at(x, y) if self.geometry.keepouts else None
        if zone is None and self.geometry.in_transit(x, y):  # drive on, deck off
            detail = f"in transit, {max(-s, 0.0):.2f} m from a mowing area (σ {sigma:.2f} m); {why}"
            self.last = ContainmentResult(
                State.TRANSIT, False, s, sigma, Reason.TRANSIT.value, detail, t
            )
            return self.last
        where = f"inside keep-out {zone!r}" if zone else "outside the boundary"
        detail = f"{where} by {max(-s, 0.0):.2f} m (σ {sigma:.2f} m); {why}"
        self.last = ContainmentResult(
            State.OUTSIDE, False, s, sigma, Reason.OUTSIDE.value, detail, t
        )
        return self.last
