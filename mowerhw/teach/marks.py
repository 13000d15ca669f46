"""A whole garden in one teach drive (issue 17): what the operator marks while driving.

``mowerhw ctl teach area NAME | keepout NAME | nav NAME | dock | end`` marks, at the time it is
given, what the mower drives from then on, the way OpenMower records areas: each stretch of
the path from a mark to the next one (or to the end of the drive) is driven once around that
zone and becomes its outline (:func:`~mowerhw.teach.boundary.boundary_from_path`: the stretch
must end where it began, must not cross itself, is simplified and made counter-clockwise);
``dock`` marks where the dock is; ``end`` ends a stretch without starting another (driving
between zones). The drive is one SLAM session with one loop closure, so every zone is in the
frame of the same landmarks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.teach.boundary import BoundaryError, boundary_from_path

FloatArray = NDArray[np.float64]

#: what a mark may say, and the kind of zone a stretch after it becomes
MARK_KINDS = {"area": "mow", "nav": "nav", "keepout": "keepout", "dock": None, "end": None}
#: a keep-out or navigation area driven around encloses at least this much (m²)
MIN_ZONE_M2 = 0.25
LABELS = {"mow": "mowing area", "nav": "navigation area", "keepout": "keep-out"}


@dataclass(frozen=True)
class TeachMark:
    t: float  # sensor time of the mark (host clock, as the IMU samples)
    kind: str  # one of MARK_KINDS
    name: str = ""


@dataclass(frozen=True)
class TaughtZone:
    kind: str  # "mow", "nav" or "keepout"
    name: str
    polygon: FloatArray  # (M, 2), counter-clockwise


def check_mark(kind: str, name: str, marks: list[TeachMark]) -> str:
    """Why this mark cannot be taken ("" if it can)."""
    if kind not in MARK_KINDS:
        return f"teach mark {kind!r} is not one of {', '.join(MARK_KINDS)}"
    if MARK_KINDS[kind] is not None:
        if not name.strip() or len(name) > 100:
            return f"teach {kind}: give it a name (1 to 100 characters)"
        if any(m.name == name and MARK_KINDS[m.kind] is not None for m in marks):
            return f"teach {kind}: a zone named {name!r} is marked already"
    return ""


def zones_from_marks(
    t: FloatArray,
    xy: FloatArray,
    distance: FloatArray,
    marks: list[TeachMark],
    simplify_m: float = 0.02,
    min_area_m2: float = 4.0,
) -> list[TaughtZone]:
    """Each marked stretch of the path (times ``t``, positions ``xy``, odometer
    ``distance``) as its zone's outline; :class:`BoundaryError` naming the zone when a
    stretch does not make one."""
    zones = []
    ordered = sorted(marks, key=lambda m: m.t)
    for k, mark in enumerate(ordered):
        kind = MARK_KINDS.get(mark.kind)
        if kind is None:
            continue
        end = ordered[k + 1].t if k + 1 < len(ordered) else np.inf
        inside = (t >= mark.t) & (t < end)
        label = LABELS[kind]
        if int(inside.sum()) < 4:
            raise BoundaryError(f"{label} {mark.name!r}: hardly any drive after its mark")
        try:
            outline = boundary_from_path(
                xy[inside],
                simplify_m,
                min_area_m2 if kind == "mow" else MIN_ZONE_M2,
                distance=distance[inside],
            )
        except BoundaryError as exc:
            raise BoundaryError(f"{label} {mark.name!r}: {exc}") from None
        zones.append(TaughtZone(kind, mark.name, outline))
    return zones


def dock_index(t: FloatArray, marks: list[TeachMark]) -> int | None:
    """The trajectory sample of the last ``dock`` mark, if any."""
    docks = [m for m in marks if m.kind == "dock"]
    if not docks:
        return None
    k = int(np.searchsorted(t, docks[-1].t))
    return min(k, len(t) - 1)
