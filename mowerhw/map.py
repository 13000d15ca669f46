"""The lawn map file: what teach writes and mow trusts (docs/design.md §1, §4).

A map is one JSON document, in local metres in the world frame of the teach run (the body
frame at its first sample: x forward, y left, z up, origin at the camera centre):

.. code-block:: text

    {
      "format": "mowerhw-map",          always this string
      "version": 2,                      the layout below (1 is read too, see below)
      "created_utc": "2026-11-22T10:00:00Z",
      "frame": "...",                    a sentence describing the frame, for people
      "areas": [{"name": "lawn", "kind": "mow", "polygon": [[x, y], ...]}, ...],
                                         named areas, each outline counter-clockwise, ≥ 3
                                         points, the first not repeated; kind "mow": a
                                         mowing area (the first is the taught lawn), "nav":
                                         a navigation (transit) area — driven, never cut
      "keepout_zones": [{"name": "pond", "polygon": [[x, y], ...]}, ...],
                                         no-go zones (flower beds, ponds, a sandpit),
                                         subtracted from the areas; they may cross edges
      "landmarks": [{"id": 7, "xyz": [x, y, z], "covariance": [[...], [...], [...]],
                     "descriptor": null | "<base64>", "keyframe": null | k}, ...],
                                         descriptor: one or more 32-byte ORB descriptors
                                         (views of the landmark), keyframe: where first seen
      "dock": {"position": [x, y, z], "quaternion_wxyz": [w, x, y, z],
               "approach": null | [[x, y], ...]},
                                         where teach started (or was marked): the default
                                         start of mow; approach: the way from the dock into
                                         the garden, inside its areas (for the mower's
                                         controller; version 2)
      "camera": {Kalibr camchain entry} | null,   the calibration the map was made with
      "teach": {...},                    how the map was made (duration, distance, closure)
      "compass": {"north_rad", "sigma_rad", "strength_t", "dip_rad", "samples"},
                                         optional: the Earth's field in the map's frame, as
                                         the teach drive read it (mowerhw.common.magnetic)
      "frame_covariance": [[...] × 4],   optional: the error the map's frame shares at every
                                         landmark and edge point, against the ground: a
                                         shift (x, y, m), a turn (rad) and a scale (1), about
                                         the origin (:func:`frame_pose_covariance`); the
                                         landmark covariances are each landmark's own error
                                         in the map's frame
      "checksum": "sha256:<hex>"         over the canonical JSON of everything else
    }

Version 1 had one outline, ``"boundary": [[x, y], ...]``, instead of ``areas``, and its
keep-outs inside it; it loads as the mowing area ``lawn`` (same decisions), and ``mowerhw
map upgrade`` rewrites it as version 2. Maps are always written as version 2.

The checksum is the SHA-256 of the document without ``checksum``, serialised with sorted
keys and no spaces. :func:`load` refuses, with a message that says what is wrong, a file
that is missing, truncated, not JSON, of another format or version, tampered with, or
geometrically unusable; it never returns a half-valid map. :meth:`LawnMap.save` writes
atomically (:mod:`mowerhw.common.fileio`).
"""

from __future__ import annotations

import base64
import datetime as _dt
import hashlib
import json
import math
import os
import stat
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient
from shapely.validation import explain_validity

from mowerhw import __version__
from mowerhw.common.fileio import write_atomic
from mowerhw.common.geometry import frame_jacobian
from mowerhw.common.magnetic import CompassReference
from mowerhw.common.strictjson import JsonLimitError, bounded_int, no_constant, unique_keys
from mowerhw.zones import Garden, Zone

FloatArray = NDArray[np.float64]

FORMAT = "mowerhw-map"
VERSION = 2
SUPPORTED_VERSIONS = (1, 2)
#: the kinds of area: mowing, navigation (transit)
AREA_KINDS = ("mow", "nav")
#: the name a version 1 map's outline (and a taught lawn) gets
TAUGHT_AREA = "lawn"
#: two mowing areas overlapping more than this (m²) are reported
OVERLAP_REPORT_M2 = 0.01
FRAME_DESCRIPTION = (
    "local metres; world frame = body frame at the first teach sample "
    "(x forward, y left, z up, origin at the camera centre)"
)
MIN_AREA_M2 = 4.0
MIN_LANDMARKS = 4
DESCRIPTOR_BYTES = 32  # one ORB descriptor (mowerhw.frontend.descriptors)
#: the dock (where teach started and mowing starts) lies on the taught edge: further out
#: than this (m), the map and its dock do not belong together
MAX_DOCK_OUTSIDE_M = 2.0
#: a map file is at most this big (bytes): ~60,000 landmarks with a few views each
MAX_MAP_BYTES = 64 << 20
#: every coordinate lies within this many metres of the map's origin (the teach start)
MAX_COORDINATE_M = 10_000.0
#: a landmark's position σ is at most this (m); a bigger one is no landmark
MAX_LANDMARK_SIGMA_M = 100.0
#: integers in the file (ids, key frames) fit in a signed 64-bit number
MAX_ID = 2**63 - 1


class MapError(ValueError):
    """A map file that must not be used; the message says what is wrong."""


@dataclass(frozen=True)
class Landmark:
    id: int
    xyz: FloatArray
    #: (3, 3) its own error in the map's frame (a map with ``frame_covariance``: what all
    #: landmarks share is there; an older map: the marginal, both in one)
    covariance: FloatArray
    descriptor: bytes | None = None
    keyframe: int | None = None


@dataclass(frozen=True)
class KeepOut:
    name: str
    polygon: FloatArray  # (M, 2)


@dataclass(frozen=True)
class Area:
    """A named mowing (``mow``) or navigation (``nav``) area."""

    name: str
    kind: str  # one of AREA_KINDS
    polygon: FloatArray  # (M, 2), counter-clockwise


@dataclass
class LawnMap:
    """A validated lawn map. ``boundary`` is the first mowing area (``boundary_name``: the
    taught lawn), ``areas`` the others, mowing or navigation (:meth:`all_areas`: every one)."""

    boundary: FloatArray
    landmarks: list[Landmark]
    dock_position: FloatArray = field(default_factory=lambda: np.zeros(3))
    dock_quaternion: FloatArray = field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    keepouts: list[KeepOut] = field(default_factory=list)
    camera: dict[str, Any] | None = None
    teach: dict[str, Any] = field(default_factory=dict)
    created_utc: str = ""
    version: int = VERSION
    checksum: str = ""
    boundary_name: str = TAUGHT_AREA
    areas: list[Area] = field(default_factory=list)
    dock_approach: FloatArray | None = None  # (K, 2): from the dock into the garden
    compass: CompassReference | None = None  # the field's direction in the map's frame
    #: (4, 4) the map frame's own error against the ground (module doc), when teach knew it
    frame_covariance: FloatArray | None = None

    # -- geometry -----------------------------------------------------------------------------

    def all_areas(self) -> list[Area]:
        """Every area, the taught lawn first."""
        return [Area(self.boundary_name, "mow", self.boundary), *self.areas]

    def area_names(self, kind: str) -> list[str]:
        return [a.name for a in self.all_areas() if a.kind == kind]

    def outline_polygon(self) -> Polygon:
        return Polygon(self.boundary)

    def lawn_polygon(self) -> BaseGeometry:
        """The mowable area: every mowing area with every keep-out zone taken out."""
        parts = [Polygon(a.polygon) for a in self.all_areas() if a.kind == "mow"]
        lawn = parts[0] if len(parts) == 1 else shapely.union_all(parts)
        for zone in self.keepouts:
            lawn = lawn.difference(Polygon(zone.polygon))
        return lawn

    def unknown_mow_areas(self, names: Sequence[str]) -> str:
        """Why ``names`` cannot be mowed here (a name that is no mowing area of this map), or
        "" (the one check for ``ctl mow --area`` and ``mow.areas``)."""
        mow = self.area_names("mow")
        unknown = [name for name in names if name not in mow]
        if not unknown:
            return ""
        return (
            f"no mowing area {', '.join(map(repr, unknown))} in the map (its mowing areas: "
            f"{', '.join(map(repr, mow))})"
        )

    def landmark_ids(self) -> NDArray[np.int64]:
        return np.array([lm.id for lm in self.landmarks], dtype=np.int64)

    def landmark_positions(self) -> FloatArray:
        return np.array([lm.xyz for lm in self.landmarks]).reshape(-1, 3)

    def landmark_covariances(self) -> FloatArray:
        return np.array([lm.covariance for lm in self.landmarks]).reshape(-1, 3, 3)

    def problems(self) -> list[str]:
        """Everything that makes this map unfit for mowing (empty: fit)."""
        out: list[str] = []
        shapes: dict[bytes, str] = {}

        def same_as(poly: Polygon, label: str) -> None:
            shape = orient(poly.normalize(), 1.0).wkb if poly.is_valid else b""
            if shape and shape in shapes:
                out.append(f"{label}: the same zone as {shapes[shape]}")
            shapes.setdefault(shape, label)

        names: set[str] = set()
        valid: list[Polygon] = []
        for area in self.all_areas():
            label = f"{'mowing' if area.kind == 'mow' else 'navigation'} area {area.name!r}"
            if area.kind == "mow" and area.name == self.boundary_name and not self.areas:
                label = "boundary"  # a map of one lawn says it as it always has
            poly = Polygon(area.polygon)
            if area.name in names:
                out.append(f"{label}: the name is used twice")
            names.add(area.name)
            same_as(poly, label)
            if area.kind not in AREA_KINDS:
                out.append(f"{label}: kind {area.kind!r} is not one of {', '.join(AREA_KINDS)}")
            if not poly.is_valid:
                out.append(f"{label}: not a simple polygon ({explain_validity(poly)})")
                continue
            if area.kind == "mow" and poly.area < MIN_AREA_M2:
                out.append(f"{label}: encloses {poly.area:.1f} m², less than {MIN_AREA_M2} m²")
            elif poly.area <= 0.0:
                out.append(f"{label}: has no area")
            valid.append(poly)
        names = set()
        for zone in self.keepouts:
            poly = Polygon(zone.polygon)
            label = f"keep-out {zone.name!r}"
            if zone.name in names:
                out.append(f"{label}: the name is used twice")
            names.add(zone.name)
            same_as(poly, label)
            if not poly.is_valid:
                out.append(f"{label}: not a simple polygon ({explain_validity(poly)})")
            elif poly.area <= 0.0:
                out.append(f"{label}: has no area")
        if len(valid) == len(self.all_areas()):
            try:
                left = float(self.lawn_polygon().area)
            except shapely.errors.GEOSException:
                left = 0.0
            if self.keepouts and left < MIN_AREA_M2:
                out.append(
                    f"keep-outs: they leave {left:.1f} m² to mow, less than {MIN_AREA_M2} m²"
                )
        everywhere = shapely.union_all(valid) if valid else None
        if everywhere is not None:
            dock = shapely.Point(float(self.dock_position[0]), float(self.dock_position[1]))
            off = float(everywhere.distance(dock))
            if off > MAX_DOCK_OUTSIDE_M:
                where = "the lawn" if len(valid) == 1 else "every area"
                out.append(
                    f"dock: {off:.1f} m outside {where} (at most {MAX_DOCK_OUTSIDE_M} m: "
                    "mowing starts there)"
                )
        if everywhere is not None and self.dock_approach is not None:
            way = shapely.LineString(self.dock_approach)
            outside = way.difference(everywhere.buffer(1e-3))
            if not outside.is_empty:
                x, y = np.asarray(shapely.get_coordinates(outside))[0]
                out.append(f"dock approach: leaves every area (at {x:.2f}, {y:.2f})")
        if len(self.landmarks) < MIN_LANDMARKS:
            out.append(
                f"landmarks: {len(self.landmarks)} mapped, at least {MIN_LANDMARKS} needed to "
                "localize"
            )
        ids = [lm.id for lm in self.landmarks]
        if len(set(ids)) != len(ids):
            out.append("landmarks: duplicate ids")
        return out

    def warnings(self) -> list[str]:
        """What is allowed but worth saying: mowing areas that overlap (mowed as one),
        keep-outs outside every area (they change nothing)."""
        out: list[str] = []
        polys = [(a, Polygon(a.polygon)) for a in self.all_areas()]
        polys = [(a, p) for a, p in polys if p.is_valid]
        mow = [(a, p) for a, p in polys if a.kind == "mow"]
        for i, (a, pa) in enumerate(mow):
            for b, pb in mow[i + 1 :]:
                overlap = float(pa.intersection(pb).area)
                if overlap > OVERLAP_REPORT_M2:
                    out.append(
                        f"mowing areas {a.name!r} and {b.name!r} overlap by {overlap:.2f} m² "
                        "(mowed as one)"
                    )
        if polys:
            everywhere = shapely.union_all([p for _, p in polys])
            for zone in self.keepouts:
                poly = Polygon(zone.polygon)
                if poly.is_valid and not poly.intersects(everywhere):
                    out.append(f"keep-out {zone.name!r}: outside every area (it changes nothing)")
        return out

    # -- editing (without re-driving) -----------------------------------------------------------

    def fit(self) -> LawnMap:
        """This map, or :class:`MapError` naming what makes it unfit (its :meth:`problems`)."""
        problems = self.problems()
        if problems:
            raise MapError("; ".join(problems))
        return self

    def with_keepout(self, name: str, polygon: FloatArray) -> LawnMap:
        poly = np.asarray(polygon, dtype=np.float64)
        if poly.ndim != 2 or poly.shape[1] != 2 or poly.shape[0] < 3:
            raise MapError("a keep-out zone needs at least 3 points x,y")
        if any(z.name == name for z in self.keepouts):
            raise MapError(f"a keep-out zone named {name!r} exists already")
        ccw = np.asarray(orient(Polygon(poly), 1.0).exterior.coords)[:-1]
        new = replace(self, keepouts=[*self.keepouts, KeepOut(name, ccw)])
        return new.fit()

    def dock_heading(self) -> float:
        """The dock's heading (rad, yaw of its quaternion)."""
        q = self.dock_quaternion
        return math.atan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))

    def garden(self) -> Garden:
        """The map's zones (its areas, the keep-outs) and its dock, as :mod:`mowerhw.zones`
        holds them (GeoJSON, other tools)."""
        zones = [Zone(a.name, a.kind, _ccw(a.polygon)) for a in self.all_areas()]
        zones += [Zone(z.name, "keepout", _ccw(z.polygon)) for z in self.keepouts]
        dock = np.asarray(self.dock_position[:2], float)
        return Garden(zones, dock, self.dock_heading(), approach=self.dock_approach)

    def with_zones(self, garden: Garden) -> LawnMap:
        """This map (landmarks, dock, frame) with the areas and keep-outs of ``garden`` (at
        least one mowing area; the first is the lawn); :class:`MapError` if unfit."""
        mow = garden.of_kind("mow")
        if not mow:
            raise MapError("the zones have no mowing area")
        others = [z for z in garden.zones if z.kind in AREA_KINDS and z is not mow[0]]
        new = replace(
            self,
            boundary=mow[0].polygon.copy(),
            boundary_name=mow[0].name,
            areas=[Area(z.name, z.kind, z.polygon.copy()) for z in others],
            keepouts=[KeepOut(z.name, z.polygon.copy()) for z in garden.of_kind("keepout")],
            dock_approach=self.dock_approach if garden.approach is None else garden.approach,
            version=VERSION,
        )
        return new.fit()

    def with_area(self, name: str, kind: str, polygon: FloatArray) -> LawnMap:
        """This map with one more area (``mow`` or ``nav``); :class:`MapError` if unfit."""
        poly = np.asarray(polygon, dtype=np.float64)
        if kind not in AREA_KINDS:
            raise MapError(f"area kind {kind!r} is not one of {', '.join(AREA_KINDS)}")
        if poly.ndim != 2 or poly.shape[1] != 2 or poly.shape[0] < 3:
            raise MapError("an area needs at least 3 points x,y")
        if name in {a.name for a in self.all_areas()}:
            raise MapError(f"an area named {name!r} exists already")
        new = replace(self, areas=[*self.areas, Area(name, kind, _ccw(poly))], version=VERSION)
        return new.fit()

    def with_dock_approach(self, path: FloatArray | None) -> LawnMap:
        """This map with the way from the dock into the garden (None: without one)."""
        way = None if path is None else np.asarray(path, dtype=np.float64).reshape(-1, 2)
        if way is not None and way.shape[0] < 2:
            raise MapError("a dock approach needs at least 2 points x,y")
        new = replace(self, dock_approach=way, version=VERSION)
        return new.fit()

    def without_area(self, name: str) -> LawnMap:
        """This map without the area ``name`` (not the taught lawn: the landmarks and the
        dock belong to it)."""
        if name == self.boundary_name:
            raise MapError(f"{name!r} is the taught lawn; it can be replaced, not removed")
        if not any(a.name == name for a in self.areas):
            known = ", ".join(repr(a.name) for a in self.all_areas())
            raise MapError(f"no area named {name!r} (areas: {known})")
        return replace(self, areas=[a for a in self.areas if a.name != name], version=VERSION)

    def without_keepout(self, name: str) -> LawnMap:
        if not any(z.name == name for z in self.keepouts):
            known = ", ".join(repr(z.name) for z in self.keepouts) or "none"
            raise MapError(f"no keep-out zone named {name!r} (zones: {known})")
        return replace(self, keepouts=[z for z in self.keepouts if z.name != name])

    # -- serialisation ------------------------------------------------------------------------

    def to_document(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "format": FORMAT,
            "version": VERSION,
            "created_utc": self.created_utc or _utc_now(),
            "frame": FRAME_DESCRIPTION,
            "areas": [
                {"name": a.name, "kind": a.kind, "polygon": _rows(a.polygon)}
                for a in self.all_areas()
            ],
            "keepout_zones": [{"name": z.name, "polygon": _rows(z.polygon)} for z in self.keepouts],
            "landmarks": [
                {
                    "id": int(lm.id),
                    "xyz": _rows(lm.xyz),
                    "covariance": _rows(lm.covariance),
                    "descriptor": base64.b64encode(lm.descriptor).decode("ascii")
                    if lm.descriptor is not None
                    else None,
                    "keyframe": lm.keyframe,
                }
                for lm in self.landmarks
            ],
            "dock": {
                "position": _rows(self.dock_position),
                "quaternion_wxyz": _rows(self.dock_quaternion),
                "approach": None if self.dock_approach is None else _rows(self.dock_approach),
            },
            "camera": self.camera,
            "teach": self.teach,
        }
        if self.compass is not None:  # only when read: a map without one keeps its bytes
            doc["compass"] = self.compass.to_dict()
        if self.frame_covariance is not None:  # likewise
            doc["frame_covariance"] = _rows(self.frame_covariance)
        doc["checksum"] = "sha256:" + _digest(doc)
        return doc

    def to_bytes(self) -> bytes:
        return (json.dumps(self.to_document(), indent=1, allow_nan=False) + "\n").encode()

    def save(self, path: str | Path) -> None:
        """Write atomically; refuses a map that is unfit for mowing."""
        problems = self.problems()
        if problems:
            raise MapError("refusing to save an unusable map: " + "; ".join(problems))
        data = self.to_bytes()
        write_atomic(path, data)
        self.checksum = json.loads(data)["checksum"]

    @classmethod
    def from_teach_result(cls, result: Any) -> LawnMap:
        landmarks = [
            Landmark(
                id=int(i),
                xyz=np.asarray(xyz, dtype=np.float64),
                covariance=np.asarray(result.landmark_covariances[i], dtype=np.float64),
                descriptor=result.descriptors.get(i) if result.descriptors else None,
                keyframe=getattr(result, "landmark_keyframes", {}).get(i),
            )
            for i, xyz in sorted(result.landmarks.items())
        ]
        pos, quat = result.start_pose
        camera = result.camera.to_kalibr() if result.camera is not None else None
        closure = result.closure
        teach = {
            "software": f"mowerhw {__version__}",
            "duration_s": float(result.trajectory[-1, 0] - result.trajectory[0, 0]),
            "distance_m": float(result.diagnostics.get("distance_m", 0.0)),
            "keyframes": len(result.keyframes),
            "gyro_yaw_scale_error": float(result.diagnostics.get("gyro_yaw_scale_error", 0.0)),
            "loop_closure": {
                "applied": closure.applied,
                "reason": closure.reason,
                "translation_m": closure.translation_m,
                "rotation_rad": closure.rotation_rad,
                **(
                    {"bearing_sigma_long_run_rad": closure.bearing_sigma_long_run_rad}
                    if math.isfinite(closure.bearing_sigma_long_run_rad)
                    else {}
                ),
            },
        }
        zones = getattr(result, "zones", [])
        mowing = [z for z in zones if z.kind == "mow"]
        return cls(
            boundary=np.asarray(result.boundary, dtype=np.float64),
            boundary_name=mowing[0].name if mowing else TAUGHT_AREA,
            areas=[
                Area(z.name, z.kind, z.polygon)
                for z in zones
                if z.kind != "keepout" and z is not mowing[0]
            ],
            keepouts=[KeepOut(z.name, z.polygon) for z in zones if z.kind == "keepout"],
            landmarks=landmarks,
            dock_position=pos,
            dock_quaternion=quat,
            camera=camera,
            teach=teach,
            created_utc=_utc_now(),
            compass=getattr(result, "compass", None),
            frame_covariance=getattr(result, "frame_covariance", None),
        )


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _ccw(points: FloatArray) -> FloatArray:
    return np.asarray(orient(Polygon(points), 1.0).exterior.coords)[:-1]


def _rows(a: Any) -> Any:
    return np.asarray(a, dtype=np.float64).tolist()


def _digest(doc: dict[str, Any]) -> str:
    body = {k: v for k, v in doc.items() if k != "checksum"}
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canon.encode()).hexdigest()


# ------------------------------------------------------------------------------------ loading


def _points(value: Any, where: str, min_points: int) -> FloatArray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise MapError(f"{where}: must be a list of [x, y] numbers") from None
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < min_points:
        raise MapError(f"{where}: must be a list of at least {min_points} [x, y] points")
    if not np.all(np.isfinite(arr)):
        raise MapError(f"{where}: has non-finite coordinates")
    if np.max(np.abs(arr)) > MAX_COORDINATE_M:
        raise MapError(f"{where}: coordinates beyond ±{MAX_COORDINATE_M:.0f} m of the map's origin")
    return arr


def _vector(value: Any, where: str, shape: tuple[int, ...], limit: float = math.inf) -> FloatArray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise MapError(f"{where}: must be numbers of shape {shape}") from None
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise MapError(f"{where}: must be finite numbers of shape {shape}")
    if np.max(np.abs(arr)) > limit:
        raise MapError(f"{where}: values beyond ±{limit:g}")
    return arr


def _symmetric_psd(
    value: Any, where: str, shape: tuple[int, int], atol: float, scale_floor: float
) -> tuple[FloatArray, FloatArray]:
    """A covariance of ``shape``: symmetric (to ``atol``) and positive semi-definite (to
    1e-12 of its largest eigenvalue, or of ``scale_floor`` when that is larger); with its
    eigenvalues."""
    cov = _vector(value, where, shape)
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=atol):
        raise MapError(f"{where}: not symmetric")
    eig = np.linalg.eigvalsh(cov)
    if eig[0] < -1e-12 * max(scale_floor, float(eig[-1])):
        raise MapError(f"{where}: not positive semi-definite (eigenvalue {eig[0]:.3g})")
    return cov, eig


def _covariance(value: Any, where: str) -> FloatArray:
    """A landmark's 3×3 position covariance: symmetric, positive semi-definite, σ bounded."""
    cov, eig = _symmetric_psd(value, where, (3, 3), atol=1e-12, scale_floor=1.0)
    if eig[-1] > MAX_LANDMARK_SIGMA_M**2:
        raise MapError(
            f"{where}: σ of {math.sqrt(eig[-1]):.3g} m; at most {MAX_LANDMARK_SIGMA_M} m"
        )
    return cov


#: the map frame's σ at most: shift x, y (m), turn (rad), scale (1). A frame worse than
#: that is no map to mow by (the teach's closure would have failed long before)
MAX_FRAME_SIGMA = np.array([MAX_LANDMARK_SIGMA_M, MAX_LANDMARK_SIGMA_M, 0.1, 0.1])
_FRAME_PARTS = ("shift x (m)", "shift y (m)", "turn (rad)", "scale")


def _frame_covariance(value: Any, where: str) -> FloatArray:
    """The map frame's 4×4 covariance (shift x, y; turn; scale): symmetric, positive
    semi-definite, each σ within :data:`MAX_FRAME_SIGMA`."""
    cov, _ = _symmetric_psd(value, where, (4, 4), atol=1e-15, scale_floor=1e-6)
    sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
    if np.any(sigma > MAX_FRAME_SIGMA):
        k = int(np.argmax(sigma / MAX_FRAME_SIGMA))
        raise MapError(
            f"{where}: σ of {_FRAME_PARTS[k]} {sigma[k]:.3g}; at most {MAX_FRAME_SIGMA[k]:g}"
        )
    return cov


def frame_pose_covariance(frame_cov: FloatArray, xy: FloatArray) -> FloatArray:
    """(3, 3): what the map frame's error (``frame_cov``, :attr:`LawnMap.frame_covariance`)
    adds to the covariance of a pose's (x, y, heading) at ``xy`` when the pose is taken
    against the ground rather than the map (:func:`~mowerhw.common.geometry.frame_jacobian`;
    the turn turns the heading too)."""
    jac = np.zeros((3, 4))
    jac[:2] = frame_jacobian(np.array([[xy[0], xy[1], 0.0]]))[0, :2]
    jac[2, 2] = 1.0
    out: FloatArray = jac @ frame_cov @ jac.T
    return out


def _int_id(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_ID


def from_document(doc: Any, source: str = "map", strict: bool = True) -> LawnMap:
    """Validate a parsed map document; raise :class:`MapError` on anything wrong.
    ``strict=False``: a map whose content is readable but unfit for mowing (its
    :meth:`LawnMap.problems`) is returned anyway, to be shown with its problems."""
    try:
        return _from_document(doc, source, strict)
    except MapError:
        raise
    except (TypeError, ValueError, AttributeError, KeyError, IndexError, OverflowError) as exc:
        # a shape no check above names: still a refusal with a message, never a traceback
        raise MapError(
            f"{source}: malformed map ({type(exc).__name__}: {str(exc)[:200]})"
        ) from None


def _from_document(doc: Any, source: str, strict: bool) -> LawnMap:
    if not isinstance(doc, dict):
        raise MapError(f"{source}: not a mowerhw map (the top level is not an object)")
    if doc.get("format") != FORMAT:
        raise MapError(
            f'{source}: not a mowerhw map (its "format" is {doc.get("format")!r}, a mowerhw '
            f"map's is {FORMAT!r}; an OpenMower map or a GeoJSON outline is brought in with "
            "`mowerhw map import-openmower` or `mowerhw map import-geojson`)"
        )
    version = doc.get("version")
    if version not in SUPPORTED_VERSIONS:
        raise MapError(
            f"{source}: map version {version!r} is not supported by mowerhw {__version__} "
            f"(supported: {', '.join(map(str, SUPPORTED_VERSIONS))})"
        )
    checksum = doc.get("checksum")
    if not isinstance(checksum, str) or not checksum.startswith("sha256:"):
        raise MapError(f"{source}: no checksum; the file is incomplete or was not made by mowerhw")
    try:
        expected = _digest(doc)
    except ValueError:
        raise MapError(f"{source}: has non-finite numbers") from None
    if checksum != "sha256:" + expected:
        raise MapError(
            f"{source}: checksum mismatch: the file was modified or corrupted after it was "
            "saved (edit maps with `mowerhw map`, or teach again)"
        )
    boundary_name, boundary, areas = _areas(doc, int(version), source)
    keepouts = []
    zones = doc.get("keepout_zones") or []
    if not isinstance(zones, list):
        raise MapError(f"{source}: keepout_zones must be a list")
    for k, zone in enumerate(zones):
        if not isinstance(zone, dict) or not isinstance(zone.get("name"), str):
            raise MapError(f"{source}: keepout_zones[{k}] needs a name and a polygon")
        keepouts.append(
            KeepOut(zone["name"], _points(zone.get("polygon"), f"keep-out {zone['name']!r}", 3))
        )
    landmarks = []
    raw_lms = doc.get("landmarks")
    if not isinstance(raw_lms, list):
        raise MapError(f"{source}: landmarks must be a list")
    for k, lm in enumerate(raw_lms):
        where = f"{source}: landmarks[{k}]"
        if not isinstance(lm, dict) or not _int_id(lm.get("id")):
            raise MapError(f"{where}: needs an integer id from 0 to 2**63 - 1")
        desc = lm.get("descriptor")
        try:
            desc_bytes = base64.b64decode(desc, validate=True) if desc is not None else None
        except (ValueError, TypeError):
            raise MapError(f"{where}: descriptor is not base64") from None
        if desc_bytes is not None and (not desc_bytes or len(desc_bytes) % DESCRIPTOR_BYTES):
            raise MapError(
                f"{where}: descriptor has {len(desc_bytes)} bytes; it must be one or more "
                f"{DESCRIPTOR_BYTES}-byte ORB descriptors"
            )
        kf = lm.get("keyframe")
        if kf is not None and not _int_id(kf):
            raise MapError(f"{where}.keyframe: must be null or an integer from 0 to 2**63 - 1")
        landmarks.append(
            Landmark(
                id=lm["id"],
                xyz=_vector(lm.get("xyz"), f"{where}.xyz", (3,), MAX_COORDINATE_M),
                covariance=_covariance(lm.get("covariance"), f"{where}.covariance"),
                descriptor=desc_bytes,
                keyframe=kf,
            )
        )
    dock = doc.get("dock") or {}
    if not isinstance(dock, dict):
        raise MapError(f"{source}: dock must be an object")
    dock_pos = _vector(
        dock.get("position", [0, 0, 0]), f"{source}: dock.position", (3,), MAX_COORDINATE_M
    )
    dock_q = _vector(
        dock.get("quaternion_wxyz", [1, 0, 0, 0]), f"{source}: dock.quaternion_wxyz", (4,)
    )
    if not math.isclose(float(np.linalg.norm(dock_q)), 1.0, abs_tol=1e-6):
        raise MapError(f"{source}: dock.quaternion_wxyz is not a unit quaternion")
    approach = dock.get("approach")
    dock_approach = None if approach is None else _points(approach, "dock approach", 2)
    camera = doc.get("camera")
    if camera is not None:
        from mowerhw.camera import CameraCalibrationError, OmniRadtanCamera

        try:
            OmniRadtanCamera.from_kalibr(camera, where="camera")
        except CameraCalibrationError as exc:
            raise MapError(f"{source}: {exc}") from None
    compass = None
    if doc.get("compass") is not None:
        try:
            compass = CompassReference.from_dict(doc["compass"])
        except ValueError as exc:
            raise MapError(f"{source}: {exc}") from None
    frame_cov = None
    if doc.get("frame_covariance") is not None:
        frame_cov = _frame_covariance(doc["frame_covariance"], f"{source}: frame_covariance")
    lawn = LawnMap(
        compass=compass,
        frame_covariance=frame_cov,
        boundary=boundary,
        boundary_name=boundary_name,
        areas=areas,
        landmarks=landmarks,
        dock_position=dock_pos,
        dock_quaternion=dock_q,
        dock_approach=dock_approach,
        keepouts=keepouts,
        camera=camera,
        teach=doc.get("teach") if isinstance(doc.get("teach"), dict) else {},
        created_utc=str(doc.get("created_utc", "")),
        version=int(version),
        checksum=checksum,
    )
    problems = lawn.problems()
    if problems and strict:
        raise MapError(f"{source}: " + "; ".join(problems))
    return lawn


def _areas(doc: dict[str, Any], version: int, source: str) -> tuple[str, FloatArray, list[Area]]:
    """The taught lawn's name and outline and the other areas: version 1's ``boundary`` is
    the one mowing area ``lawn``; version 2 lists ``areas``, the first mowing one the lawn."""
    if version == 1:
        return TAUGHT_AREA, _points(doc.get("boundary"), f"{source}: boundary", 3), []
    raw = doc.get("areas")
    if not isinstance(raw, list) or not raw:
        raise MapError(f"{source}: areas must be a list of at least one area")
    areas = []
    for k, entry in enumerate(raw):
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise MapError(f"{source}: areas[{k}] needs a name, a kind and a polygon")
        name, kind = entry["name"], entry.get("kind")
        if not name.strip() or len(name) > 100:
            raise MapError(f"{source}: areas[{k}]: a name of 1 to 100 characters")
        if kind not in AREA_KINDS:
            raise MapError(
                f"{source}: area {name!r}: kind {kind!r} is not one of {', '.join(AREA_KINDS)}"
            )
        areas.append(Area(name, kind, _points(entry.get("polygon"), f"area {name!r}", 3)))
    first = next((a for a in areas if a.kind == "mow"), None)
    if first is None:
        raise MapError(f'{source}: no mowing area (kind "mow")')
    return first.name, first.polygon, [a for a in areas if a is not first]


def check_map_file(path: str | Path, max_bytes: int = MAX_MAP_BYTES) -> None:
    """The refusals that need no reading: the file is missing or unreadable, is no regular
    file (a FIFO or device could block or never end), or is over ``max_bytes``."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise _unreadable(Path(path), exc) from None
    _check_stat(Path(path), st, max_bytes)


def _unreadable(path: Path, exc: OSError) -> MapError:
    if isinstance(exc, FileNotFoundError):
        return MapError(
            f"{path}: map file not found (teach a map first: `mowerhw run --mode teach`)"
        )
    return MapError(f"{path}: cannot read the map file ({exc.strerror})")


def _check_stat(path: Path, st: os.stat_result, max_bytes: int) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise MapError(f"{path}: not a regular file (a map is a JSON file)")
    if st.st_size > max_bytes:
        raise MapError(f"{path}: {st.st_size} bytes; a map is at most {max_bytes} bytes")


def read_map_bytes(path: str | Path, max_bytes: int = MAX_MAP_BYTES) -> bytes:
    """The bytes of a map file that passes :func:`check_map_file` (checked on the open file,
    so it cannot be swapped in between); :class:`MapError` otherwise."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise _unreadable(path, exc) from None
    try:
        _check_stat(path, os.fstat(fd), max_bytes)
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise _unreadable(path, exc) from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise MapError(f"{path}: more than {max_bytes} bytes; a map is at most that")
    return data


def parse_map_json(data: bytes, source: str) -> Any:
    """The JSON document of a map file, parsed with limits (digits of an integer, no
    duplicate keys, no NaN, nesting within the interpreter's recursion limit);
    :class:`MapError` naming the problem."""
    if not data.strip():
        raise MapError(f"{source}: the map file is empty")
    try:
        return json.loads(
            data,
            parse_int=bounded_int,
            parse_constant=no_constant,
            object_pairs_hook=unique_keys,
        )
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        where = (
            f" at line {exc.lineno}, column {exc.colno}"
            if isinstance(exc, json.JSONDecodeError)
            else ""
        )
        raise MapError(
            f"{source}: not valid JSON{where}: the file is truncated or corrupt"
        ) from None
    except JsonLimitError as exc:
        raise MapError(f"{source}: {exc}") from None
    except RecursionError:
        raise MapError(f"{source}: JSON nested too deeply") from None


def load(path: str | Path, max_bytes: int = MAX_MAP_BYTES, strict: bool = True) -> LawnMap:
    """Load and fully validate a map file (see the module doc for what is refused);
    ``strict=False`` returns a readable map unfit for mowing too (see :func:`from_document`)."""
    doc = parse_map_json(read_map_bytes(path, max_bytes), str(path))
    return from_document(doc, str(path), strict)


def polygon_area(points: FloatArray) -> float:
    return float(shapely.area(Polygon(points)))
