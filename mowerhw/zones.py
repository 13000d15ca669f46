"""Zones of a garden as other tools draw them: mowing areas, navigation (transit) areas and
keep-outs, each a named polygon in local metres, cleaned the way a map must be before
containment may trust it (issue 17). Read from an OpenMower map backup or from GeoJSON
(:func:`read_geojson`; :func:`to_geojson` writes one, so a map can be edited in QGIS or any
GeoJSON editor).

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
    approach: FloatArray | None = None  # (K, 2): the way from the dock into the garden

    def of_kind(self, kind: str) -> list[Zone]:
        return [z for z in self.zones if z.kind == kind]

    def moved(self, rotation_rad: float, translation: Any) -> Garden:
        """The garden turned by ``rotation_rad`` about the origin, then shifted."""
        c, s = math.cos(rotation_rad), math.sin(rotation_rad)
        rot = np.array([[c, -s], [s, c]])
        t = np.asarray(translation, dtype=np.float64)
        zones = [Zone(z.name, z.kind, z.polygon @ rot.T + t) for z in self.zones]
        dock = None if self.dock_xy is None else rot @ self.dock_xy + t
        heading = None if self.dock_heading_rad is None else self.dock_heading_rad + rotation_rad
        way = None if self.approach is None else self.approach @ rot.T + t
        return Garden(zones, dock, heading, list(self.repairs), way)


def align_by_dock(garden: Garden, dock_xy: Any, dock_heading_rad: float) -> Garden:
    """``garden`` moved so its dock lands on ``dock_xy`` facing ``dock_heading_rad`` (the dock
    pose both maps have); :class:`ZoneError` if it has no dock."""
    if garden.dock_xy is None or garden.dock_heading_rad is None:
        raise ZoneError("the imported map has no dock to align by; give reference points")
    turn = float(dock_heading_rad) - garden.dock_heading_rad
    c, s = math.cos(turn), math.sin(turn)
    turned = np.array([[c, -s], [s, c]]) @ garden.dock_xy
    return garden.moved(turn, np.asarray(dock_xy, dtype=np.float64) - turned)


def align_by_points(garden: Garden, source: Any, target: Any) -> tuple[Garden, float]:
    """``garden`` moved by the rigid motion (rotation + shift) that best takes the
    ``source`` points onto the ``target`` points (least squares, two or more pairs), and the
    RMS residual (m); :class:`ZoneError` for fewer than two distinct points."""
    src = np.asarray(source, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(target, dtype=np.float64).reshape(-1, 2)
    if len(src) < 2 or len(src) != len(dst) or np.ptp(src, axis=0).max() < 1e-3:
        raise ZoneError("alignment needs two or more distinct pairs of reference points")
    sc, dc = src.mean(axis=0), dst.mean(axis=0)
    h = (src - sc).T @ (dst - dc)
    turn = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(turn), math.sin(turn)
    rot = np.array([[c, -s], [s, c]])
    shift = dc - rot @ sc
    rms = float(np.sqrt(np.mean(np.sum((src @ rot.T + shift - dst) ** 2, axis=1))))
    return garden.moved(turn, shift), rms


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


#: GeoJSON as mowerhw writes it: local metres, not longitude/latitude (RFC 7946 has no
#: "crs"; the foreign member ``mowerhw`` says so)
GEOJSON_FRAME = "local metres of the mowerhw map (x forward, y left at the teach start)"


def to_geojson(garden: Garden, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """A GeoJSON FeatureCollection: one Polygon feature per zone (``properties``: ``kind``
    mow | nav | keepout, ``name``; closed counter-clockwise rings), the dock as a Point
    with its heading, the dock approach as a LineString (``kind`` approach)."""
    features: list[dict[str, Any]] = []
    for z in garden.zones:
        ring = np.vstack([z.polygon, z.polygon[:1]]).round(6).tolist()
        features.append(
            {
                "type": "Feature",
                "properties": {"kind": z.kind, "name": z.name},
                "geometry": {"type": "Polygon", "coordinates": [ring]},
            }
        )
    if garden.dock_xy is not None:
        features.append(
            {
                "type": "Feature",
                "properties": {"kind": "dock", "heading_rad": garden.dock_heading_rad or 0.0},
                "geometry": {"type": "Point", "coordinates": np.round(garden.dock_xy, 6).tolist()},
            }
        )
    if garden.approach is not None:
        features.append(
            {
                "type": "Feature",
                "properties": {"kind": "approach"},
                "geometry": {
                    "type": "LineString",
                    "coordinates": garden.approach.round(6).tolist(),
                },
            }
        )
    return {
        "type": "FeatureCollection",
        "mowerhw": {"frame": GEOJSON_FRAME, **(extra or {})},
        "features": features,
    }


def read_geojson(path: str | Path) -> Garden:
    """Zones from a GeoJSON FeatureCollection as :func:`to_geojson` writes it (an editor may
    have changed, added or removed features); :class:`ZoneError` naming the first feature
    that cannot be used. Polygons with holes are refused (a hole is a keep-out feature)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ZoneError(f"{path}: not GeoJSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise ZoneError(f"{path}: not a GeoJSON FeatureCollection")
    features = doc.get("features")
    if not isinstance(features, list):
        raise ZoneError(f"{path}: the FeatureCollection has no list of features")
    zones, repairs = [], []
    dock_xy, heading = None, None
    approach: FloatArray | None = None
    for k, f in enumerate(features):
        props = f.get("properties") if isinstance(f, dict) else None
        geom = f.get("geometry") if isinstance(f, dict) else None
        if not isinstance(props, dict) or not isinstance(geom, dict):
            raise ZoneError(f"{path.name}: feature {k} needs properties and a geometry")
        kind = props.get("kind")
        name = str(props.get("name") or f"{kind}-{k + 1}")
        where = f"{path.name}: {kind} {name!r}"
        if kind == "dock" and geom.get("type") == "Point":
            try:
                dock_xy = np.array([float(v) for v in geom["coordinates"][:2]])
                heading = float(props.get("heading_rad", 0.0))
            except (TypeError, KeyError, ValueError, IndexError):
                raise ZoneError(f"{where}: the dock needs coordinates [x, y]") from None
            continue
        if kind == "approach" and geom.get("type") == "LineString":
            try:
                approach = np.asarray(geom["coordinates"], dtype=np.float64)[:, :2]
            except (TypeError, KeyError, ValueError, IndexError):
                raise ZoneError(f"{where}: the approach needs coordinates [[x, y], ...]") from None
            if approach.shape[0] < 2 or not np.all(np.isfinite(approach)):
                raise ZoneError(f"{where}: the approach needs 2 or more finite points")
            continue
        if kind not in KINDS:
            raise ZoneError(f"{where}: kind must be one of {', '.join(KINDS)}, dock or approach")
        rings = geom.get("coordinates")
        if geom.get("type") != "Polygon" or not isinstance(rings, list) or not rings:
            raise ZoneError(f"{where}: a zone is a Polygon")
        if len(rings) > 1:
            raise ZoneError(f"{where}: holes are not allowed (draw a keep-out feature instead)")
        outer = rings[0]
        if isinstance(outer, list) and len(outer) > 3 and outer[0] == outer[-1]:
            outer = outer[:-1]  # GeoJSON closes every ring: not a repair
        ring, fixed = clean_outline(outer, where)
        zones.append(Zone(name, str(kind), ring))
        repairs += fixed
    names = [(z.kind, z.name) for z in zones]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise ZoneError(f"{path.name}: two {dup[0]} zones named {dup[1]!r}")
    if dock_xy is not None and not (np.all(np.isfinite(dock_xy)) and math.isfinite(heading or 0.0)):
        raise ZoneError(f"{path.name}: the dock's position is not finite")
    return Garden(zones, dock_xy, heading, repairs, approach)
