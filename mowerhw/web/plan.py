"""The map as the page draws it: areas, keep-outs, navigation paths, landmarks, the dock."""

from __future__ import annotations

import math
from typing import Any

from mowerhw.map import LawnMap


def map_plan(lawn_map: LawnMap) -> dict[str, Any]:
    """Plain JSON of what the plan view draws (metres, map frame: x east, y north)."""

    def pts(a: Any) -> list[list[float]]:
        return [[round(float(x), 3), round(float(y), 3)] for x, y in a[:, :2]]

    dock = lawn_map.dock_position
    return {
        "areas": [
            {"name": a.name, "kind": a.kind, "polygon": pts(a.polygon)}
            for a in lawn_map.all_areas()
        ],
        "keepouts": [{"name": z.name, "polygon": pts(z.polygon)} for z in lawn_map.keepouts],
        "paths": [] if lawn_map.dock_approach is None else [pts(lawn_map.dock_approach)],
        "landmarks": [
            [int(lm.id), *(round(float(v), 3) for v in lm.xyz)] for lm in lawn_map.landmarks
        ],
        "dock": {
            "x": round(float(dock[0]), 3),
            "y": round(float(dock[1]), 3),
            "heading": round(lawn_map.dock_heading(), 4),
        },
        "mow_areas": lawn_map.area_names("mow"),
        "area_m2": round(float(lawn_map.lawn_polygon().area), 1),
        "created_utc": lawn_map.created_utc,
        "teach": {
            k: v
            for k, v in (lawn_map.teach or {}).items()
            if isinstance(v, str | int | float | bool)
            and not (isinstance(v, float) and not math.isfinite(v))
        },
    }
