"""The lawn boundary from the taught trajectory (docs/design.md §4), validated with shapely.

The closed path on the ground becomes the boundary: consecutive duplicates (standstill) are
dropped, the loop must end near where it began, the outline is simplified (Douglas–Peucker,
topology preserved), must be a simple polygon of at least the configured area, and is
returned counter-clockwise. Anything else is a :class:`BoundaryError` with a message a
mower operator can act on; a wrong map is never made silently.
"""

from __future__ import annotations

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient
from shapely.validation import explain_validity

FloatArray = NDArray[np.float64]


class BoundaryError(ValueError):
    """The taught path does not make a usable lawn boundary."""


def boundary_from_path(
    xy: FloatArray,
    simplify_m: float = 0.02,
    min_area_m2: float = 4.0,
    close_tolerance_m: float = 1.5,
    distance: FloatArray | None = None,
    spacing_m: float = 0.05,
) -> FloatArray:
    """Closed, simplified, validated, counter-clockwise outline (M, 2) of a driven loop.

    ``distance`` is the odometer along the path (m); the path is sampled every
    ``spacing_m`` of it, so standing still (where the estimate may still move by
    millimetres as frames arrive) adds no zig-zag to the outline.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
        raise BoundaryError("the taught path has invalid (non-finite) positions")
    if distance is None:
        distance = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    bins = np.floor(np.asarray(distance) / spacing_m).astype(np.int64)
    keep = np.concatenate([[True], np.diff(bins) > 0])
    keep[-1] = True
    pts = xy[keep]
    if pts.shape[0] < 4:
        raise BoundaryError("the mower hardly moved: drive once around the lawn edge")
    pts, gap = close_loop(pts, close_tolerance_m)
    if gap > close_tolerance_m:
        raise BoundaryError(
            f"open loop: the teach drive ended {gap:.2f} m from where it started "
            f"(at most {close_tolerance_m} m allowed); drive back to the start point"
        )
    poly = Polygon(pts)
    if not poly.is_valid:
        reason = explain_validity(poly)
        raise BoundaryError(
            f"the taught path crosses itself ({reason}); drive the edge once without "
            "crossing your own track"
        )
    if simplify_m > 0:
        poly = poly.simplify(simplify_m, preserve_topology=True)
    if not poly.is_valid or poly.is_empty or poly.geom_type != "Polygon":
        raise BoundaryError(f"the simplified boundary is not a simple polygon ({poly.geom_type})")
    if poly.area < min_area_m2:
        raise BoundaryError(
            f"the enclosed lawn is {poly.area:.1f} m², below the minimum of {min_area_m2} m²"
        )
    poly = orient(poly, sign=1.0)
    return np.asarray(poly.exterior.coords)[:-1]


def close_loop(pts: FloatArray, reach_m: float) -> tuple[FloatArray, float]:
    """Cut a driven loop where its end meets its beginning.

    A real drive over- or under-shoots its start. Within the head (first ``reach_m`` of path)
    and the tail (last ``reach_m``): where the tail crosses the head, the loop is the path
    between the crossing points, closed at the crossing; otherwise it is cut at the closest
    pair of points. Returns the loop and the gap left between its ends (0 at a crossing).
    """
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(seg)])
    total = along[-1]
    reach = min(reach_m, 0.25 * total)
    head = np.flatnonzero(along <= reach)
    tail = np.flatnonzero(along >= total - reach)
    crossing = _first_crossing(pts, head, tail)
    if crossing is not None:
        i, j, point = crossing  # head segment i → i+1 and tail segment j → j+1 cross at point
        return np.vstack([point, pts[i + 1 : j + 1]]), 0.0
    d = np.linalg.norm(pts[head][:, None, :] - pts[tail][None, :, :], axis=-1)
    i, j = (int(k) for k in np.unravel_index(int(np.argmin(d)), d.shape))
    start, end = int(head[i]), int(tail[j])
    return pts[start : end + 1], float(d[i, j])


def _first_crossing(
    pts: FloatArray, head: NDArray[np.int64], tail: NDArray[np.int64]
) -> tuple[int, int, FloatArray] | None:
    """The crossing of a head segment with a tail segment, the latest along the tail."""
    a0, a1 = pts[head[:-1]], pts[head[:-1] + 1]
    b0, b1 = pts[tail[:-1]], pts[tail[:-1] + 1]
    r = a1 - a0  # (H, 2)
    s = b1 - b0  # (T, 2)
    den = r[:, None, 0] * s[None, :, 1] - r[:, None, 1] * s[None, :, 0]
    qp = b0[None, :, :] - a0[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (qp[..., 0] * s[None, :, 1] - qp[..., 1] * s[None, :, 0]) / den
        tb = (qp[..., 0] * r[:, None, 1] - qp[..., 1] * r[:, None, 0]) / den
    hit = (np.abs(den) > 1e-15) & (ta >= 0) & (ta <= 1) & (tb >= 0) & (tb <= 1)
    hit &= head[:-1, None] + 1 < tail[None, :-1]  # not neighbouring segments
    if not hit.any():
        return None
    hi, tj = np.nonzero(hit)
    k = int(np.argmax(tj))  # the crossing latest along the tail
    i, j = int(head[hi[k]]), int(tail[tj[k]])
    point = pts[i] + ta[hi[k], tj[k]] * (pts[i + 1] - pts[i])
    return i, j, point


def polygon_of(outline: FloatArray) -> Polygon:
    return Polygon(outline)


def outline_distance(a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance from each vertex of outline ``a`` to the outline ``b`` (m)."""
    ring = shapely.LinearRing(b)
    dist: FloatArray = shapely.distance(ring, shapely.points(a))
    return dist
