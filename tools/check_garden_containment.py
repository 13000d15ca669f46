#!/usr/bin/env python3
"""Containment over a real garden: the OpenMower map backup in
``../shared/data/real/openmower-garden-map`` (9 mowing areas, 22 obstacles, 1 navigation area,
a dock), read and cleaned by :mod:`mowerhw.zones`, judged on a grid by mowerhw's containment
geometry (:class:`mowerhw.mow.LawnGeometry` as a map of format 2 builds it: the mowing areas
with the obstacles subtracted, crossing edges included; the navigation area as its transit
part), against an independent even-odd ray cast over the *raw* outlines
from the file (no repairs, no shapely). Prints one JSON object.

    .venv/bin/python tools/check_garden_containment.py [--step 0.05]

A grid point is MOW in an area and in no obstacle, TRANSIT in the navigation area and no
mowing area, else OUTSIDE. Points within 1 mm of an outline are on the edge, where even-odd
and "the edge belongs to the area" may differ by definition: they are counted, not compared.
``states``: the containment table with σ = 0 (MOW points INSIDE at least
``containment.margin_m`` from the edge of the mowable area, else NEAR_EDGE; TRANSIT; OUTSIDE).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from mowerhw.config import ContainmentConfig
from mowerhw.mow import LawnGeometry
from mowerhw.zones import OPENMOWER_KINDS, read_openmower

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
DATA = REAL / "openmower-garden-map" / "map_backup_2026-04-12.json"
EDGE_M = 1e-3


def even_odd(ring: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Ray casting (even-odd) of ``pts`` against a ring as given (closed or not)."""
    inside = np.zeros(len(pts), dtype=bool)
    lo, hi = ring.min(axis=0), ring.max(axis=0)
    box = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))
    px, py = pts[box, 0], pts[box, 1]
    hit = np.zeros(box.size, dtype=bool)
    for (xi, yi), (xj, yj) in zip(ring, np.roll(ring, -1, axis=0), strict=True):
        if yi == yj:
            continue
        crosses = (yi > py) != (yj > py)
        x_at = (xj - xi) * (py - yi) / (yj - yi) + xi
        hit ^= crosses & (px < x_at)
    inside[box] = hit
    return inside


def raw_rings(path: Path) -> dict[str, list[np.ndarray]]:
    doc = json.loads(path.read_text())
    rings: dict[str, list[np.ndarray]] = {"mow": [], "nav": [], "keepout": []}
    for area in doc["areas"]:
        kind = OPENMOWER_KINDS[area["properties"]["type"]]
        rings[kind].append(np.array([[p["x"], p["y"]] for p in area["outline"]], float))
    return rings


def check(path: Path = DATA, step: float = 0.05) -> dict[str, Any]:
    t0 = time.perf_counter()
    garden = read_openmower(path)
    obstacles = [(z.name, z.polygon) for z in garden.of_kind("keepout")]
    mow = [z.polygon for z in garden.of_kind("mow")]
    geom = LawnGeometry(mow[0], obstacles, mow[1:], [z.polygon for z in garden.of_kind("nav")])
    allpts = np.vstack([z.polygon for z in garden.zones])
    lo, hi = allpts.min(axis=0) - 1.0, allpts.max(axis=0) + 1.0
    gx = np.arange(lo[0], hi[0], step)
    gy = np.arange(lo[1], hi[1], step)
    pts = np.column_stack([np.repeat(gx, gy.size), np.tile(gy, gx.size)])
    # mowerhw: the containment geometry the permit uses
    s_mow = geom.signed_distances(pts)
    transit = (
        shapely.contains_xy(geom.transit, pts[:, 0], pts[:, 1])
        if geom.transit is not None
        else np.zeros(len(pts), bool)
    )
    ours = np.where(s_mow >= 0.0, "MOW", np.where(transit, "TRANSIT", "OUTSIDE"))
    # the reference: even-odd over the raw outlines of the file
    raw = raw_rings(path)
    in_obstacle = np.any([even_odd(r, pts) for r in raw["keepout"]], axis=0)
    in_mow = np.any([even_odd(r, pts) for r in raw["mow"]], axis=0) & ~in_obstacle
    in_nav = np.any([even_odd(r, pts) for r in raw["nav"]], axis=0) & ~in_obstacle
    ref = np.where(in_mow, "MOW", np.where(in_nav, "TRANSIT", "OUTSIDE"))
    edges = shapely.union_all(
        [shapely.LinearRing(r) for rs in raw.values() for r in rs if len(r) >= 3]
    )
    near_edge = shapely.distance(edges, shapely.points(pts)) < EDGE_M
    compared = ~near_edge
    disagree = compared & (ours != ref)
    margin = ContainmentConfig().margin_m
    mow_pts = ours == "MOW"
    states = Counter(
        {
            "INSIDE": int(np.sum(mow_pts & (s_mow >= margin))),
            "NEAR_EDGE": int(np.sum(mow_pts & (s_mow < margin))),
            "TRANSIT": int(np.sum(ours == "TRANSIT")),
            "OUTSIDE": int(np.sum(ours == "OUTSIDE")),
        }
    )
    examples = [
        {"x": round(float(x), 3), "y": round(float(y), 3), "mowerhw": o, "reference": r}
        for (x, y), o, r in zip(
            pts[disagree][:5], ours[disagree][:5], ref[disagree][:5], strict=True
        )
    ]
    return {
        "grid_step_m": step,
        "points": len(pts),
        "compared": int(compared.sum()),
        "on_an_edge_not_compared": int(near_edge.sum()),
        "disagreements": int(disagree.sum()),
        "disagreement_examples": examples,
        "states": dict(states),
        "zones": dict(Counter(z.kind for z in garden.zones)),
        "repairs": len(garden.repairs),
        "dock_xy": [round(float(v), 3) for v in garden.dock_xy]
        if garden.dock_xy is not None
        else None,
        "seconds": round(time.perf_counter() - t0, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", type=float, default=0.05, help="grid spacing (m)")
    args = ap.parse_args()
    print(json.dumps(check(step=args.step)))


if __name__ == "__main__":
    main()
