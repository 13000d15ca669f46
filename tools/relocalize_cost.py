#!/usr/bin/env python3
"""What global relocalization costs as the map grows (issue 18): prints JSON.

For maps of ``--sizes`` landmarks (a random smooth lawn whose area grows with the map, the
landmarks 1.5–6 m around its edge, as the simulator places them), each frame is what an
omnidirectional camera at a random pose inside the lawn would see: the bearings of the
landmarks within 15 m (σ 0.1°) plus 30 % clutter (features on nothing in the map). Per size:

* ``map_bytes_per_100_landmarks``: the landmarks' part of the saved map (JSON, with ORB
  descriptor sets as the pixel-level teach stores them: 8 per landmark) per 100 landmarks,
  and without the descriptors: all the relocalizer reads (it stores no index of its own —
  positions only; the descriptors serve the tracking association after it);
* ``relocalizer_mb``: its precomputed search grid in memory (the position–landmark pairs in
  range, three numbers each);
* ``global_ms`` / ``near_ms``: time per frame (median, p95) of a search everywhere and of a
  check near a prior (0.2 m, 3° off), on this machine, one core;
* ``found``: share of frames answered within 0.10 m and 3° (none answered wrong is the goal).

    .venv/bin/python tools/relocalize_cost.py --sizes 25,50,100,200,400 --frames 20
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import shapely

from mowerhw.common.geometry import yaw_rotation
from mowerhw.evaluation.recovery import random_pose
from mowerhw.map import Landmark, LawnMap
from mowerhw.mow.relocalize import GlobalRelocalizer
from mowerhw.sim.lawn import random_lawn
from mowerhw.sim.world import place_landmarks


def _world(n: int, rng: np.random.Generator) -> tuple[LawnMap, shapely.Polygon]:
    perimeter = 26.0 * math.sqrt(n / 15.0)  # the paper's lawn holds 15 landmarks
    outline = random_lawn(rng, perimeter, 2, 0.15).outline(720)
    xy = place_landmarks(rng, outline, (1.5, 6.0), n)
    pts = np.c_[xy, rng.uniform(-0.5, 1.7, n)]
    desc = [rng.integers(0, 256, 8 * 32, dtype=np.uint8).tobytes() for _ in range(n)]
    lms = [Landmark(i, pts[i], np.eye(3) * 1e-4, descriptor=desc[i]) for i in range(n)]
    lawn_map = LawnMap(boundary=outline, landmarks=lms, camera=None, teach={})
    return lawn_map, shapely.Polygon(outline).buffer(-0.3)


def _view(lawn_map: LawnMap, p: np.ndarray, yaw: float, rng: np.random.Generator) -> np.ndarray:
    pts = lawn_map.landmark_positions()
    near = np.linalg.norm(pts[:, :2] - p[:2], axis=1) < 15.0
    b = (pts[near] - p) @ yaw_rotation(yaw)
    b = b / np.linalg.norm(b, axis=1, keepdims=True) + rng.normal(0, math.radians(0.1), b.shape)
    clutter = rng.normal(0, 1, (max(1, int(0.3 * b.shape[0])), 3))
    out = np.vstack([b, clutter])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _pct(a: list[float], q: float) -> float:
    return round(float(np.percentile(a, q)), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="25,50,100,200,400")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rows = []
    for n in (int(v) for v in args.sizes.split(",")):
        rng = np.random.default_rng([args.seed, n])
        lawn_map, inside = _world(n, rng)
        t0 = time.perf_counter()
        reloc = GlobalRelocalizer(lawn_map)
        build_ms = 1e3 * (time.perf_counter() - t0)
        grid_bytes = reloc.table_bytes
        entries = lawn_map.to_document()["landmarks"]
        doc_bytes = len(json.dumps(entries, indent=1))
        pos_bytes = len(json.dumps([{**e, "descriptor": None} for e in entries], indent=1))
        g_ms, n_ms, good, wrong = [], [], 0, 0
        for _ in range(args.frames):
            x, y, yaw = random_pose(inside, rng)
            p = np.array([x, y, 0.0])
            obs = _view(lawn_map, p, yaw, rng)
            res = reloc.locate(obs)
            g_ms.append(res.ms)
            if res.ok:
                err = float(np.linalg.norm(res.p_wb[:2] - p[:2]))
                dyaw = abs(math.remainder(res.yaw - yaw, 2 * math.pi))
                good += err < 0.10 and dyaw < math.radians(3.0)
                wrong += err > 0.15
            near = (x + 0.2, y, yaw + math.radians(3.0))
            n_ms.append(reloc.locate(obs, near).ms)
        rows.append(
            {
                "landmarks": n,
                "grid_points": int(reloc.grid.shape[0]),
                "map_bytes_per_100_landmarks": round(100 * doc_bytes / n),
                "map_bytes_per_100_landmarks_without_descriptors": round(100 * pos_bytes / n),
                "relocalizer_index_bytes_in_map": 0,
                "relocalizer_mb": round(grid_bytes / 2**20, 2),
                "relocalizer_build_ms": round(build_ms, 1),
                "global_ms": {"median": _pct(g_ms, 50), "p95": _pct(g_ms, 95)},
                "near_ms": {"median": _pct(n_ms, 50), "p95": _pct(n_ms, 95)},
                "found": round(good / args.frames, 3),
                "answered_wrong_over_0.15m": wrong,
            }
        )
    print(json.dumps({"frames_per_size": args.frames, "sizes": rows}))


if __name__ == "__main__":
    main()
