"""``mowerhw eval``: a campaign of simulated teach + mow runs over scenarios and seeds."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mowerhw.cli.common import number, print_json


def register(sub: argparse._SubParsersAction) -> None:
    from mowerhw.sim.scenarios import MATRIX, SCENARIOS

    p = sub.add_parser(
        "eval",
        help="teach then mow on every scenario x seed, in parallel; a results table",
        description="Run the simulated teach drive and then closed-loop mowing on its map for "
        "every scenario and seed, on local worker processes or a Dask cluster, score every "
        "run against the truth, write one CSV row per run and print the summary per "
        f"scenario with the goals each misses. Scenarios: {', '.join(SCENARIOS)}.",
    )
    p.add_argument(
        "--scenarios",
        default=",".join(MATRIX),
        metavar="NAMES",
        help=f"comma-separated presets, or 'matrix' (default: {','.join(MATRIX)})",
    )
    p.add_argument("--seeds", default="1-20", metavar="SEEDS", help="e.g. 1-20 or 1,4,9")
    p.add_argument("--level", default="bearing", choices=("bearing", "pixel"))
    p.add_argument(
        "--mow-s",
        type=number(float, ge=0, le=86400),
        default=120.0,
        metavar="S",
        help="mowing time per run (0: none)",
    )
    p.add_argument(
        "--workers",
        type=number(int, ge=0, le=1024),
        default=0,
        help="local processes (default: CPUs)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run on the Dask distributed cluster at ADDRESS (tcp://host:8786) instead",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("build/eval"),
        help="folder for results.csv, summary.json (and the plot)",
    )
    p.add_argument("--plot", action="store_true", help="also draw the distributions (PNG)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(handler=_eval)


def _eval(args: argparse.Namespace) -> int:
    import os

    from mowerhw.cli.common import strict_json
    from mowerhw.common.fileio import write_atomic
    from mowerhw.evaluation.campaign import (
        RunSpec,
        format_summary,
        plot_distributions,
        run_campaign,
        seeds_of,
        summarise,
        write_table,
    )
    from mowerhw.sim.scenarios import MATRIX, SCENARIOS

    names = MATRIX if args.scenarios == "matrix" else [s.strip() for s in args.scenarios.split(",")]
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        print(
            f"mowerhw: unknown scenario {', '.join(unknown)}; allowed: {', '.join(SCENARIOS)}",
            file=sys.stderr,
        )
        return 2
    try:
        seeds = seeds_of(args.seeds)
    except ValueError:
        print(f"mowerhw: --seeds {args.seeds!r}: expected e.g. 1-20 or 1,4,9", file=sys.stderr)
        return 2
    if args.level == "pixel":
        flat = [n for n in names if SCENARIOS[n].slope_deg or SCENARIOS[n].bumps_per_m2]
        if flat:
            print(
                f"mowerhw: the pixel level renders flat ground only; not {', '.join(flat)}",
                file=sys.stderr,
            )
            return 2
    specs = [RunSpec(n, s, args.level, args.mow_s) for n in names for s in seeds]
    workers = args.workers or os.cpu_count() or 1
    t0 = time.monotonic()
    rows = run_campaign(specs, workers=workers, scheduler=args.scheduler)
    wall = time.monotonic() - t0
    summary = summarise(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    table = write_table(rows, args.out / "results.csv")
    result = {
        "runs": len(rows),
        "wall_s": round(wall, 1),
        "workers": "dask " + args.scheduler if args.scheduler else workers,
        "table": str(table),
        "summary": summary,
    }
    if args.plot:
        result["plot"] = str(plot_distributions(rows, args.out / "distributions.png"))
    write_atomic(args.out / "summary.json", (strict_json(result, indent=1) + "\n").encode())
    if args.json:
        print_json(result, indent=None)
    else:
        print(format_summary(summary))
        print(f"\n{len(rows)} runs in {wall:.0f} s on {result['workers']} workers; table {table}")
    missed = any(s["missed_halts"] for s in summary)
    return 1 if missed else 0
