#!/usr/bin/env python3
"""Containment against the peers' own test vectors: ArduPilot's point-in-polygon cases and
PX4's geofence cases (``../shared/data/real/peer-polygon-cases``), judged by mowerhw's
containment geometry (:class:`mowerhw.mow.LawnGeometry`, the signed distance the permit
uses). Prints one JSON object: per family, cases, passes, and each failure.

    .venv/bin/python tools/check_peer_polygons.py

Semantics carried over: a point on an edge is inside (ArduPilot: ``Polygon_outside`` false);
lat/lon are turned into local metres about the polygon's first vertex (equirectangular: the
polygons span at most a few kilometres). mowerhw judges positions, not segments: PX4's
segment cases are judged the way a mowing mower meets them — its positions along the
segment, 1 mm apart — an inclusion fence is violated if one of them is outside, an exclusion
(keep-out) if one is strictly inside.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from mowerhw.mow import LawnGeometry

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
DATA = REAL / "peer-polygon-cases" / "peer_polygon_cases.json"
EARTH_RADIUS_M = 6_371_000.0
#: how far inside counts as inside for a sampled segment (m): floating-point dust on edges
EDGE_TOLERANCE_M = 1e-9


def _open_ring(points: Any) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    return arr[:-1] if len(arr) > 3 and np.allclose(arr[0], arr[-1]) else arr


def _local_m(lat_lon_deg: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Equirectangular local metres (x east, y north) about ``origin`` (lat, lon in deg)."""
    lat0 = math.radians(origin[0])
    d = np.radians(lat_lon_deg - origin)
    return np.column_stack([d[:, 1] * math.cos(lat0), d[:, 0]]) * EARTH_RADIUS_M


def _inside(outline: np.ndarray, points: np.ndarray) -> np.ndarray:
    s = LawnGeometry(outline).signed_distances(np.atleast_2d(points))
    return s >= 0.0


def _family(cases: list[tuple[str, bool, bool]]) -> dict[str, Any]:
    failures = [name for name, got, want in cases if got != want]
    return {"cases": len(cases), "passed": len(cases) - len(failures), "failures": failures}


def ardupilot(doc: dict[str, Any]) -> dict[str, Any]:
    cases = []
    for k, c in enumerate(doc["triangles_float"]):
        got = bool(_inside(_open_ring(c["boundary"]), np.array(c["point"], float))[0])
        cases.append((f"triangle {k}", got, not c["outside"]))
    obc = doc["obc2010_boundary_lat_lon_1e7"]
    ring = _open_ring(obc["boundary_closed"]) * 1e-7
    origin = ring[0]
    outline = _local_m(ring, origin)
    for k, p in enumerate(obc["points"]):
        xy = _local_m(np.array([p["point"]], float) * 1e-7, origin)
        cases.append((f"obc2010 point {k}", bool(_inside(outline, xy)[0]), not p["outside"]))
    for name in ("prox_boundary", "simple_boundary"):
        b = doc[name]
        outline = _open_ring(b["boundary_closed"])
        for k, p in enumerate(b["points"]):
            got = bool(_inside(outline, np.array(p["point"], float))[0])
            cases.append((f"{name} point {k}", got, not p["outside"]))
    return _family(cases)


def px4_planner(doc: dict[str, Any]) -> dict[str, Any]:
    cases = []
    for name in ("exclusion_quad_concave", "inclusion_L_shape"):
        poly = np.asarray(doc[name]["vertices"], float)
        origin = poly[0]
        outline = _local_m(poly, origin)
        for k, p in enumerate(doc[name]["points"]):
            xy = _local_m(np.array([p["point"]], float), origin)
            cases.append((f"{name} point {k}", bool(_inside(outline, xy)[0]), p["inside"]))
    return _family(cases)


def _positions(a: Any, b: Any, step_m: float = 1e-3) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(2, math.ceil(float(np.linalg.norm(b - a)) / step_m) + 1)
    return a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)


def px4_segments(doc: dict[str, Any]) -> dict[str, Any]:
    cases = []
    for order in ("ccw", "cw"):
        square = np.asarray(doc["square"], float)
        square = square if order == "ccw" else square[::-1]
        fence = LawnGeometry(square)
        keepout = LawnGeometry(
            np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]),
            [("square", square)],
        )
        for k, c in enumerate(doc["segment_cases"]):
            pts = _positions(c["a"], c["b"])
            if "inclusion_violates" in c:
                got = bool(np.any(fence.signed_distances(pts) < -EDGE_TOLERANCE_M))
                cases.append((f"{order} segment {k} inclusion", got, c["inclusion_violates"]))
            if "exclusion_violates" in c:
                got = bool(np.any(keepout.signed_distances(pts) < -EDGE_TOLERANCE_M))
                cases.append((f"{order} segment {k} exclusion", got, c["exclusion_violates"]))
    return _family(cases)


def check(path: Path = DATA) -> dict[str, Any]:
    doc = json.loads(path.read_text())
    return {
        "ardupilot_test_polygon": ardupilot(doc["ardupilot_test_polygon"]),
        "px4_geofence_avoidance_planner": px4_planner(
            doc["px4_geofence_avoidance_planner_polygons"]
        ),
        "px4_geofence_utils_segments": px4_segments(doc["px4_geofence_utils_unit_square"]),
    }


def main() -> None:
    print(json.dumps(check()))


if __name__ == "__main__":
    main()
