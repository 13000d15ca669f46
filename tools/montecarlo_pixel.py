#!/usr/bin/env python3
"""Pixel-level bench over many seeds: teach on rendered images, then mow with that map.

A thin user of :mod:`mowerhw.evaluation.campaign` (``mowerhw eval --level pixel``): for each
seed the drive is rendered at 4 Hz into 1540×1540 omni images, the front end finds and tracks
features, the Teacher maps them, the map is saved, and the mower mows on it for ``--duration``
seconds re-identifying map landmarks in rendered images. Prints one JSON line per seed, then
the campaign's summary (the figures and the goals missed).

Run: ``.venv/bin/python tools/montecarlo_pixel.py --seeds 1-10 --duration 300``
(about 90 s per seed on one core; ``--workers 2``, or ``--scheduler ADDRESS`` for Dask).
"""

from __future__ import annotations

import argparse
import json

from mowerhw.evaluation.campaign import RunSpec, run_campaign, seeds_of, summarise


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--scheduler", help="a Dask scheduler address (tcp://host:8786)")
    args = ap.parse_args()
    specs = [RunSpec(args.scenario, s, "pixel", args.duration) for s in seeds_of(args.seeds)]
    rows = run_campaign(specs, workers=args.workers, scheduler=args.scheduler)
    for row in rows:
        print(json.dumps(row), flush=True)
    print(json.dumps({"summary": summarise(rows)}, indent=1))


if __name__ == "__main__":
    main()
