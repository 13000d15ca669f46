"""Zones of a garden as other tools draw them: mowing areas, navigation (transit) areas and
keep-outs, each a named polygon in local metres, cleaned the way a map must be before
containment may trust it (issue 17).

Other tools' outlines come with quirks (the real OpenMower garden in
``shared/data/real/openmower-garden-map`` has all of them): either winding, the first vertex
repeated at the end or not, the same vertex twice in a row. :func:`clean_outline` repairs what
is safe to repair — it makes the winding counter-clockwise and drops the closing and
repeated vertices — and says each repair; what it cannot repair (too few vertices, crossing
edges, non-finite or far-off coordinates) is refused with :class:`ZoneError` naming the zone.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from shapely.geometry import Polygon
from shapely.validation import explain_validity

FloatArray = NDArray[np.float64]

KINDS = ("mow", "nav", "keepout")
#: the kinds of OpenMower's map backup and what they are here
OPENMOWER_KINDS = {"mow": "mow", "nav": "nav", "navigation": "nav", "obstacle": "keepout"}
#: every coordinate lies within this many metres of the origin (as in a lawn map)
MAX_COORDINATE_M = 10_000.0


class ZoneError(ValueError):
    """A zone that cannot be used (the message names it and says why)."""


@dataclass(frozen=True)
class Zone:
    name: str
    kind: str  # one of KINDS
    polygon: FloatArray  # counter-clockwise, open (the first vertex is not repeated)

    def area_m2(self) -> float:
        return float(Polygon(self.polygon).area)


@dataclass
class Garden:
    """A garden imported from another tool: its zones, its dock, and what was repaired."""

    zones: list[Zone]
    dock_xy: FloatArray | None = None
    dock_heading_rad: float | None = None
    repairs: list[str] = field(default_factory=list)

    def of_kind(self, kind: str) -> list[Zone]:
        return [z for z in self.zones if z.kind == kind]


def clean_outline(points: Any, where: str) -> tuple[FloatArray, list[str]]:
    """``points`` as a counter-clockwise open ring without repeated vertices, and the
    repairs made (each a sentence naming ``where``); :class:`ZoneError` if it is unusable."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ZoneError(f"{where}: the outline is not a list of [x, y] numbers") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ZoneError(f"{where}: the outline is not a list of [x, y] points")
    if not np.all(np.isfinite(arr)) or (arr.size and np.max(np.abs(arr)) > MAX_COORDINATE_M):
        raise ZoneError(
            f"{where}: coordinates that are not finite or beyond ±{MAX_COORDINATE_M:.0f} m"
        )
    repairs = []
    keep = np.r_[True, np.any(np.diff(arr, axis=0) != 0.0, axis=1)]
    if not keep.all():
        repairs.append(f"{where}: {int((~keep).sum())} repeated vertex(es) removed")
        arr = arr[keep]
    if len(arr) > 1 and np.array_equal(arr[0], arr[-1]):
        arr = arr[:-1]
        repairs.append(f"{where}: the closing vertex (a repeat of the first) removed")
    if len(arr) < 3:
        raise ZoneError(f"{where}: fewer than 3 distinct vertices")
    poly = Polygon(arr)
    if not poly.is_valid:
        raise ZoneError(f"{where}: not a simple polygon ({explain_validity(poly)})")
    if poly.area <= 0.0:
        raise ZoneError(f"{where}: encloses no area")
    if not poly.exterior.is_ccw:
        arr = arr[::-1].copy()
        repairs.append(f"{where}: clockwise outline made counter-clockwise")
    return arr, repairs


def read_openmower(path: str | Path) -> Garden:
    """An OpenMower map backup (the web UI's JSON: ``areas`` with ``properties.type`` mow,
    nav or obstacle and an ``outline`` of ``{x, y}``; ``docking_stations`` with ``position``
    and ``heading``), cleaned; :class:`ZoneError` naming the first unusable part."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ZoneError(f"{path}: not an OpenMower map backup ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("areas"), list):
        raise ZoneError(f"{path}: not an OpenMower map backup (no list of areas)")
    zones, repairs = [], []
    for k, area in enumerate(doc["areas"]):
        if not isinstance(area, dict):
            raise ZoneError(f"{path}: areas[{k}] is not an object")
        props = area.get("properties") if isinstance(area.get("properties"), dict) else {}
        kind = OPENMOWER_KINDS.get(str(props.get("type", "")))
        name = str(props.get("name") or area.get("id") or f"area {k}")
        where = f"{path.name}: {props.get('type')} area {name!r}"
        if kind is None:
            raise ZoneError(
                f"{where}: unknown type; OpenMower's are {', '.join(sorted(OPENMOWER_KINDS))}"
            )
        outline = area.get("outline")
        if not isinstance(outline, list):
            raise ZoneError(f"{where}: no outline")
        try:
            xy = [(float(p["x"]), float(p["y"])) for p in outline]
        except (TypeError, KeyError, ValueError):
            raise ZoneError(f"{where}: outline points need numbers x and y") from None
        ring, fixed = clean_outline(xy, where)
        zones.append(Zone(name, kind, ring))
        repairs += fixed
    dock_xy, heading = None, None
    docks = doc.get("docking_stations") or []
    if isinstance(docks, list) and docks and isinstance(docks[0], dict):
        try:
            pos = docks[0]["position"]
            dock_xy = np.array([float(pos["x"]), float(pos["y"])])
            heading = float(docks[0].get("heading", 0.0))
        except (TypeError, KeyError, ValueError):
            raise ZoneError(f"{path.name}: the docking station needs a position x, y") from None
        if not (np.all(np.isfinite(dock_xy)) and math.isfinite(heading)):
            raise ZoneError(f"{path.name}: the docking station's position is not finite")
    return Garden(zones, dock_xy, heading, repairs)
