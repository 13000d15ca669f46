#!/usr/bin/env python3
"""What the pixel-level bearings' errors are made of while mowing (issue 18's NEES): prints
JSON.

Mows ``--duration`` seconds from the dock at pixel level (rendered frames, the front end,
the localizer) with the map of ``--scenario``/``--seed`` (``--map``: a map a pixel-level
teach saved, else it teaches one), and splits every right association's bearing error
against the truth (:func:`mowerhw.evaluation.pixel.bearing_error_figures`): what all
landmarks of a frame share, a bias that stays with a landmark, what is left and how alike it
is from frame to frame — beside the white bearing σ the localizer assumes and the map's
landmark σ (the localizer's model of a bearing: white noise, plus the landmark's map error
held for as long as it is seen).

    .venv/bin/python tools/bearing_errors_pixel.py --scenario paper --seed 1 --duration 60
"""

from __future__ import annotations

import argparse
import json
import math
import time

from mowerhw.evaluation.campaign import scenario_config
from mowerhw.evaluation.mow import run_mow
from mowerhw.evaluation.pixel import bearing_error_figures, pixel_map, yard_arguments
from mowerhw.evaluation.recovery import map_landmark_nees


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    yard_arguments(ap)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--mow-seed", type=int, default=11)
    args = ap.parse_args()
    cfg = scenario_config(args.scenario)  # the yard mower's own IMU grade
    lawn_map = pixel_map(args.scenario, args.seed, cfg, args.map)
    t0 = time.perf_counter()
    out = run_mow(
        lawn_map,
        args.scenario,
        args.seed,
        args.duration,
        cfg,
        mow_seed=args.mow_seed,
        level="pixel",
    )
    if out.bearing_errors is None:
        raise SystemExit("no bearing errors: not a pixel-level run")
    print(
        json.dumps(
            {
                "scenario": args.scenario,
                "seed": args.seed,
                "mow_s": args.duration,
                "localizer_bearing_sigma_deg": round(math.degrees(cfg.mow.bearing_sigma_rad), 3),
                "map_landmarks": map_landmark_nees(lawn_map),
                "bearing_errors": bearing_error_figures(out.bearing_errors),
                "wall_s": round(time.perf_counter() - t0, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
