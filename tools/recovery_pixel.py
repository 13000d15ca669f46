#!/usr/bin/env python3
"""Starting anywhere and kidnaps at pixel level, closed loop (issue 18): prints JSON.

Teaches the pixel-level map of ``--scenario``/``--seed`` (or loads ``--map``, a map that
teach saved: ``--save-map`` writes it), then ``--starts`` random starts with no prior and
``--kidnaps`` kidnaps mid-mow (:mod:`mowerhw.evaluation.recovery`). ``--no-lift``: the
kidnaps do not show on the accelerometer or the lift switch (only the camera can tell).
``--matched-noise``: the mow filter's process noise is the simulated sensors' own
(:func:`mowerhw.evaluation.campaign.matched_noise`), not the shipped defaults' wider one.
``--per-run``: keep every run's figures in the JSON. ``--map-seeds 3-22``: teach each of
those yards and make ``--starts`` starts and ``--kidnaps`` kidnaps on each (one map draws its
errors once for all its runs; many maps let the Monte-Carlo draw them too), scores and NEES
pooled, each map's scores kept; ``--workers N`` runs N maps at a time (``--scheduler`` on a
Dask cluster), ``--map-dir DIR`` keeps the taught maps for the next run (and the JSON
then has ``map_frame``: the maps' frame errors against their frame covariance, the part of
the NEES against the truth that the teach owns). One run per map is
the Monte-Carlo whose NEES the χ² bounds are for: a map's runs all share its errors.

    .venv/bin/python tools/recovery_pixel.py --scenario paper --seed 1 --starts 100 --kidnaps 20
    .venv/bin/python tools/recovery_pixel.py --scenario look-alike --map-seeds 3-102 \
        --starts 1 --kidnaps 0 --workers 2 --map-dir maps/look-alike
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from mowerhw.evaluation.campaign import matched_noise, scenario_config, seeds_of
from mowerhw.evaluation.pixel import PixelMaps, pixel_map, yard_arguments
from mowerhw.evaluation.recovery import (
    kidnap_runs,
    map_frame_nees,
    map_landmark_nees,
    runs_over_maps,
    start_runs,
)


def _progress(kind: str) -> Any:
    def show(i: int, run: dict[str, Any]) -> None:
        print(f"{kind} {i}: {json.dumps(run)}", file=sys.stderr, flush=True)

    return show


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    yard_arguments(ap)
    ap.add_argument("--starts", type=int, default=100)
    ap.add_argument(
        "--kidnaps",
        type=int,
        help="kidnaps mid-mow (default 20; with --map-seeds: per map, default 0)",
    )
    ap.add_argument("--no-lift", action="store_true")
    ap.add_argument("--save-map", help="write the taught map here")
    ap.add_argument("--per-run", action="store_true")
    ap.add_argument("--no-compass", action="store_true", help="the search without the magnetometer")
    ap.add_argument(
        "--matched-noise",
        action="store_true",
        help="the mow filter's process noise set to the simulated sensors' (a consistency "
        "test of the filter: the shipped defaults are wider on purpose); the teach as shipped",
    )
    ap.add_argument(
        "--map-seeds",
        metavar="SEEDS",
        help="e.g. 3-22: teach each of these yards and make --starts starts and --kidnaps "
        "kidnaps on each (the Monte-Carlo draws the map too)",
    )
    ap.add_argument(
        "--map-dir",
        metavar="DIR",
        help="with --map-seeds: keep each taught map in DIR (<scenario>_<seed>.json) and "
        "load it from there next time instead of teaching it again (empty the folder after "
        "changing the teach: a kept map is checked for its yard and seed, not for the code)",
    )
    ap.add_argument(
        "--workers", type=int, default=1, help="with --map-seeds: maps run at a time (processes)"
    )
    ap.add_argument(
        "--scheduler",
        metavar="ADDR",
        help="with --map-seeds: a Dask scheduler (tcp://host:8786) runs the maps instead",
    )
    args = ap.parse_args()
    if args.workers < 1:
        ap.error(f"--workers {args.workers}: expected 1 or more")
    cfg = scenario_config(args.scenario)  # the yard mower's own IMU grade
    noise: dict[str, Any] = {}
    if args.matched_noise:
        cfg, unmatched = matched_noise(cfg, args.scenario)
        noise = {"mow_noise_matched": {**_noise(cfg), "not_matched": unmatched}}
    if args.map_seeds:
        _over_maps(args, cfg, noise)
        return
    kidnaps = 20 if args.kidnaps is None else args.kidnaps
    t0 = time.perf_counter()
    lawn_map = pixel_map(args.scenario, args.seed, cfg, args.map, args.save_map)
    out: dict[str, Any] = {"scenario": args.scenario, "seed": args.seed, **noise}
    out["teach_s"] = round(time.perf_counter() - t0, 1)
    # the map's landmark covariances against their truth in the map's frame
    out["map_landmarks"] = map_landmark_nees(lawn_map)
    # and the map frame's error against its frame covariance (the ground's part)
    out["map_frame"] = map_frame_nees([lawn_map])
    if args.starts:
        t1 = time.perf_counter()
        out["starts"] = start_runs(
            lawn_map,
            args.scenario,
            args.seed,
            args.starts,
            cfg,
            progress=_progress("start"),
            compass=not args.no_compass,
        )
        out["starts"]["wall_s"] = round(time.perf_counter() - t1, 1)
        if not args.per_run:
            out["starts"].pop("runs")
    if kidnaps:
        t1 = time.perf_counter()
        out["kidnaps"] = kidnap_runs(
            lawn_map,
            args.scenario,
            args.seed,
            kidnaps,
            cfg,
            lifted=not args.no_lift,
            progress=_progress("kidnap"),
            compass=not args.no_compass,
        )
        out["kidnaps"]["wall_s"] = round(time.perf_counter() - t1, 1)
        if not args.per_run:
            out["kidnaps"].pop("per_run")
    print(json.dumps(out))


def _noise(cfg: Any) -> dict[str, float]:
    """The mow filter's process noise in ``cfg`` (for the JSON)."""
    m = cfg.mow
    gyro_white, gyro_walk, _ = m.gyro()
    return {
        "speed_noise": round(m.speed_noise, 7),
        "lateral_noise": round(m.lateral_noise, 7),
        "gyro_noise": float(f"{gyro_white:.4g}"),
        "gyro_bias_walk": float(f"{gyro_walk:.4g}"),
        "gyro_scale_sigma": m.gyro_scale_sigma,
    }


def _over_maps(args: argparse.Namespace, cfg: Any, noise: dict[str, Any]) -> None:
    """``--map-seeds``: one pixel-level map per yard seed (taught, or kept in ``--map-dir``),
    ``--starts`` starts and ``--kidnaps`` kidnaps on each, ``--workers`` maps at a time."""
    try:
        seeds = seeds_of(args.map_seeds)
    except ValueError:
        sys.exit(f"--map-seeds {args.map_seeds!r}: expected e.g. 3-22 or 3,5,9")
    t0 = time.perf_counter()
    out = runs_over_maps(
        seeds,
        PixelMaps(args.scenario, cfg, args.map_dir),
        args.scenario,
        args.starts,
        args.kidnaps or 0,
        cfg,
        lifted=not args.no_lift,
        compass=not args.no_compass,
        workers=args.workers,
        scheduler=args.scheduler,
    )
    out = {**out, "map_seeds": seeds, **noise}
    if args.map_dir:  # every map is kept there now: how honest their frame covariances are
        maps = PixelMaps(args.scenario, cfg, args.map_dir)
        out["map_frame"] = map_frame_nees([maps(seed) for seed in seeds])
    if not args.per_run:
        out.get("starts", {}).pop("runs", None)
        out.get("kidnaps", {}).pop("per_run", None)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
