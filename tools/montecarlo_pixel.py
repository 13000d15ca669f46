#!/usr/bin/env python3
"""Pixel-level bench over many seeds: teach on rendered images, then mow with that map.

For each seed: ``run_teach_pixel`` (paper scenario: the drive is rendered at 4 Hz into
1540×1540 omni images, the front end finds and tracks features, the Teacher maps them),
the map saved as ``mowerhw sim teach --level pixel`` would, then ``run_mow(level="pixel")``
for ``--duration`` seconds (the mower re-identifies map landmarks in rendered images).
Prints one JSON line per seed and phase, then a summary object (medians, worst cases).

Run: ``.venv/bin/python tools/montecarlo_pixel.py --seeds 1-10 --duration 300``
(about 90 s per seed on one core).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from mowerhw.cli.sim_cmd import _save_sim_map
from mowerhw.config import Config
from mowerhw.evaluate_mow import run_mow
from mowerhw.evaluate_pixel import run_teach_pixel
from mowerhw.map import load

TEACH_KEYS = (
    "boundary_rmse_m",
    "boundary_rmse_no_closure_m",
    "landmark_rmse_m",
    "landmarks_mapped",
    "landmarks_in_map",
    "reidentifications",
    "association_precision",
    "tracks_per_frame",
    "track_length_median",
    "frontend_ms_per_frame",
    "loop_closure",
    "diverged",
)
MOW_KEYS = (
    "position_rmse_m",
    "position_max_m",
    "quaternion_err_max",
    "missed_halts",
    "false_halt_fraction",
    "permit_fraction",
    "association_precision",
    "associations_judged",
    "reidentifications",
    "associations_dropped",
    "tracks_per_frame",
    "track_length_median",
    "frontend_ms_per_frame",
    "real_time_factor",
)


def seeds_of(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--scenario", default="paper")
    args = ap.parse_args()
    cfg = Config()
    teach_rows, mow_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds_of(args.seeds):
            taught = run_teach_pixel(args.scenario, seed, cfg)
            t = {k: taught.metrics.get(k) for k in TEACH_KEYS}
            print(json.dumps({"seed": seed, "phase": "teach", **t}), flush=True)
            teach_rows.append(t)
            if taught.result is None:
                continue
            path = Path(tmp) / f"map-{seed}.json"
            _save_sim_map(taught.result, path, args.scenario, seed, "pixel", taught.landmark_truth)
            mowed = run_mow(load(path), args.scenario, seed, args.duration, cfg, level="pixel")
            m = {k: mowed.metrics.get(k) for k in MOW_KEYS}
            print(json.dumps({"seed": seed, "phase": "mow", **m}), flush=True)
            mow_rows.append(m)

    def med(rows: list[dict], key: str) -> float | None:
        vals = [r[key] for r in rows if isinstance(r.get(key), int | float)]
        return round(float(np.median(vals)), 5) if vals else None

    def worst(rows: list[dict], key: str, fn=max) -> float | None:
        vals = [r[key] for r in rows if isinstance(r.get(key), int | float)]
        return round(float(fn(vals)), 5) if vals else None

    summary = {
        "seeds": seeds_of(args.seeds),
        "mow_duration_s": args.duration,
        "teach": {
            "boundary_rmse_m_median": med(teach_rows, "boundary_rmse_m"),
            "boundary_rmse_m_max": worst(teach_rows, "boundary_rmse_m"),
            "landmark_rmse_m_median": med(teach_rows, "landmark_rmse_m"),
            "landmark_rmse_m_max": worst(teach_rows, "landmark_rmse_m"),
            "landmarks_in_map_median": med(teach_rows, "landmarks_in_map"),
            "reid_precision_min": worst(teach_rows, "association_precision", min),
            "diverged": sum(bool(r.get("diverged")) for r in teach_rows),
        },
        "mow": {
            "position_rmse_m_median": med(mow_rows, "position_rmse_m"),
            "position_rmse_m_max": worst(mow_rows, "position_rmse_m"),
            "missed_halts_total": sum(int(r["missed_halts"]) for r in mow_rows),
            "false_halt_fraction_max": worst(mow_rows, "false_halt_fraction"),
            "association_precision_median": med(mow_rows, "association_precision"),
            "association_precision_min": worst(mow_rows, "association_precision", min),
            "tracks_per_frame_median": med(mow_rows, "tracks_per_frame"),
            "track_length_median": med(mow_rows, "track_length_median"),
            "frontend_ms_per_frame_median": med(mow_rows, "frontend_ms_per_frame"),
        },
    }
    print(json.dumps({"summary": summary}, indent=1))


if __name__ == "__main__":
    main()
