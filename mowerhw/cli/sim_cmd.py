"""``mowerhw sim teach|mow``: the estimators on the simulated bench, scored against truth."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mowerhw.cli.common import add_config_argument, load_config_or_exit, print_json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="run the estimators on a simulated yard and score them")
    ssub = p.add_subparsers(dest="sim_command", metavar="PHASE", required=True)
    teach = ssub.add_parser(
        "teach",
        help="simulate a teach drive (paper §V), map it, save the map, print the errors",
        description="Simulate a teach drive around a random lawn, run the teach estimators "
        "(landmark observers + robot-centric EKF + loop closure) on the sensor streams, save "
        "the map, and print ONE JSON object of errors against the ground truth.",
    )
    _common(teach)
    teach.add_argument("--landmarks", type=int, help="override the scenario's landmark count")
    teach.set_defaults(handler=_teach)


def _common(p: argparse.ArgumentParser) -> None:
    add_config_argument(p)
    p.add_argument(
        "--scenario",
        default="paper",
        choices=("paper", "large"),
        help="paper: 15 landmarks, ~60 s loop (§V); large: 160 m edge, 80 landmarks",
    )
    p.add_argument("--seed", type=int, default=7, help="random seed (runs are repeatable)")
    p.add_argument(
        "--level",
        default="bearing",
        choices=("bearing",),
        help="bench level (DESIGN.md §9): bearing = ids + noisy bearings",
    )
    p.add_argument(
        "--out", type=Path, help="output folder (default build/sim/<phase>-<scenario>-<seed>)"
    )
    p.add_argument(
        "--plot", action="store_true", help="also write PNG figures to the output folder"
    )
    p.add_argument("--json", action="store_true", help="print only the JSON object")


def _out_dir(args: argparse.Namespace, phase: str) -> Path:
    return args.out or Path("build") / "sim" / f"{phase}-{args.scenario}-{args.seed}"


def _teach(args: argparse.Namespace) -> int:
    from mowerhw.evaluate import run_teach
    from mowerhw.map import MapError

    cfg = load_config_or_exit(args.config)
    out = _out_dir(args, "teach")
    outcome = run_teach(
        args.scenario, args.seed, cfg.teach, n_landmarks=args.landmarks, record_history=args.plot
    )
    metrics = dict(outcome.metrics)
    map_path = out / "map.json"
    if outcome.result is not None:
        try:
            outcome.result.save(map_path)
            metrics["map"] = str(map_path)
        except MapError as exc:
            metrics["map"] = None
            metrics["map_error"] = str(exc)
            metrics["diverged"] = True
    else:
        metrics["map"] = None
    if args.plot:
        from mowerhw.plots import teach_figures

        metrics["figures"] = [str(f) for f in teach_figures(outcome, out)]
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    if args.json:
        print(json.dumps(metrics))
    else:
        print_json(metrics)
    if not args.json and metrics.get("error"):
        print(f"mowerhw: teach failed: {metrics['error']}", file=sys.stderr)
    return 1 if metrics.get("diverged") else 0
