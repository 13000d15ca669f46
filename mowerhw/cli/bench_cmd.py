"""``mowerhw bench``: the daemon with its real drivers against mock hardware, scored."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mowerhw.cli.common import number, output_dir, seed_number, strict_json


def register(sub: argparse._SubParsersAction) -> None:
    from mowerhw.bench import FAULT_KINDS

    p = sub.add_parser(
        "bench",
        help="hardware-in-the-loop bench: teach, then mow, with the real daemon and mock devices",
        description=(
            "Mock VN-100 on a pty, mock speed sensor and mower controller on a CAN bus "
            "(python-can udp_multicast), rendered camera frames; the daemon (`mowerhw run`) "
            "teaches the boundary, saves the map and mows with the closed loop. Prints one JSON "
            "object. Takes about 70 s of teaching plus --duration of mowing, in real time."
        ),
    )
    p.add_argument(
        "--duration",
        type=number(float, gt=0, le=86400),
        default=120.0,
        help="seconds of mowing (default 120)",
    )
    p.add_argument("--seed", type=seed_number, default=7, help="which simulated yard (default 7)")
    p.add_argument(
        "--scenario",
        default="paper",
        choices=("paper", "garden"),
        help="yard type: paper (one lawn, mowed from the dock on its edge) or garden (two "
        "lawns, a path with the dock and a bed across an edge, taught with marks in one drive, "
        "then the front lawn and the back lawn mowed in turn)",
    )
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND@T[:D]",
        help=f"inject a fault T s into mowing for D s (default 3); KIND: {', '.join(FAULT_KINDS)}",
    )
    p.add_argument("--map", type=Path, help="skip teaching: mow with this map of the same yard")
    p.add_argument("--out", type=output_dir, help="run directory (default: a new temporary one)")
    p.add_argument(
        "--record", type=Path, metavar="FILE.mcap", help="the daemon records the run (MCAP)"
    )
    p.add_argument(
        "--load",
        type=number(int, ge=0, le=64),
        default=0,
        metavar="N",
        help="N CPU hogs beside the daemon (a loaded or slow mower computer)",
    )
    p.add_argument(
        "--estimator-delay",
        type=number(float, ge=0, le=60000),
        default=150.0,
        metavar="MS",
        help="during an estimator-delay fault the estimation process is blocked this long "
        "every 200 ms (default 150 ms, beyond the 80 ms lease)",
    )
    p.add_argument(
        "--start",
        choices=("dock", "random"),
        default="dock",
        help="where mowing starts: at the dock (default), or random: the daemon is stopped, "
        "its pose file deleted, the mower carried to a random pose inside the lawn and the "
        "daemon started again there (it finds its pose by global relocalization)",
    )
    p.add_argument(
        "--web",
        action="store_true",
        help="serve the status page during the run (its URL and token file are in the JSON); "
        "mowing's second half is watched by a client at 10 Hz and sent refused control "
        "requests, and the daemon's CPU is given for both halves",
    )
    p.add_argument("--json", action="store_true", help="print only the JSON object")
    p.set_defaults(handler=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> int:
    from mowerhw.bench import Bench, FaultSpec
    from mowerhw.bench.garden import GardenBench

    try:
        faults = [FaultSpec.parse(f) for f in args.fault]
    except ValueError as exc:
        print(f"mowerhw bench: {exc}", file=sys.stderr)
        return 2
    if not args.json:
        print("bench: teaching then mowing in real time; this takes a few minutes", file=sys.stderr)
    kind = GardenBench if args.scenario == "garden" else Bench
    bench = kind(
        duration_s=args.duration,
        seed=args.seed,
        scenario=args.scenario,
        out_dir=args.out,
        faults=faults,
        map_path=args.map,
        record=args.record,
        load=args.load,
        estimator_delay_ms=args.estimator_delay,
        start=args.start,
        web=args.web,
    )

    result = bench.run()
    print(strict_json(result, indent=None if args.json else 2))
    ok = result.get("missed_halts") == 0
    return 0 if ok else 1
