"""``mowerhw sim teach|mow``: the estimators on the simulated bench, scored against truth."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from mowerhw.cli.common import (
    add_config_argument,
    load_config_or_exit,
    number,
    output_dir,
    print_json,
    seed_number,
    strict_json,
)


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
    teach.add_argument(
        "--landmarks",
        type=number(int, ge=4, le=100000),
        help="override the scenario's landmark count",
    )
    teach.set_defaults(handler=_teach)
    mow = ssub.add_parser(
        "mow",
        help="simulate closed-loop mowing with a map (paper §V): errors and missed halts",
        description="Mow the simulated yard the map was taught in: the mower drives by its "
        "estimate and turns at NEAR_EDGE (bang-bang, 0.4 m), the containment output is scored "
        "against the truth. Prints ONE JSON object.",
    )
    _common(mow)
    mow.add_argument(
        "--map", type=Path, help="a map from `mowerhw sim teach` (default: teach one first)"
    )
    mow.add_argument(
        "--duration",
        type=number(float, gt=0, le=1e6),
        default=500.0,
        help="simulated seconds (default 500)",
    )
    mow.add_argument(
        "--vision-dropout",
        metavar="START:SECONDS",
        help="the camera recognises nothing for SECONDS from START (e.g. 200:10)",
    )
    mow.add_argument(
        "--latency",
        type=number(float, ge=0, le=10),
        default=None,
        help="camera frames arrive this late (s; default: the scenario's, 0.15 for paper)",
    )
    mow.add_argument(
        "--fault",
        action="append",
        default=[],
        type=_handling_event,
        metavar="KIND@T[:D]",
        help="the mower is handled T s into mowing for D s: lift (default 2 s), tilt (3 s), "
        "bump (0.2 s); repeatable",
    )
    mow.set_defaults(handler=_mow)


def _handling_event(text: str) -> Any:
    from mowerhw.sim.handling import HandlingEvent

    try:
        return HandlingEvent.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _common(p: argparse.ArgumentParser) -> None:
    add_config_argument(p)
    p.add_argument(
        "--scenario",
        default="paper",
        choices=("paper", "large"),
        help="paper: 15 landmarks, ~60 s loop (§V); large: 160 m edge, 80 landmarks",
    )
    p.add_argument("--seed", type=seed_number, default=7, help="random seed (runs are repeatable)")
    p.add_argument(
        "--level",
        default="bearing",
        choices=("bearing", "pixel"),
        help="bench level (docs/design.md §9): bearing = ids + noisy bearings; pixel = rendered "
        "1540x1540 images through the front end (KLT tracking, re-identification)",
    )
    p.add_argument(
        "--out", type=output_dir, help="output folder (default build/sim/<phase>-<scenario>-<seed>)"
    )
    p.add_argument(
        "--plot", action="store_true", help="also write PNG figures to the output folder"
    )
    p.add_argument("--json", action="store_true", help="print only the JSON object")


def _out_dir(args: argparse.Namespace, phase: str) -> Path:
    return args.out or Path("build") / "sim" / f"{phase}-{args.scenario}-{args.seed}"


def _teach(args: argparse.Namespace) -> int:
    from mowerhw.map import MapError

    cfg = load_config_or_exit(args.config)
    out = _out_dir(args, "teach")
    truth = None
    if args.level == "pixel":
        from mowerhw.evaluation.pixel import run_teach_pixel

        if args.landmarks is not None:
            print("mowerhw: --landmarks is for the bearing level only", file=sys.stderr)
            return 2
        keep = (4.0, 22.0, 45.0) if args.plot else ()
        outcome = run_teach_pixel(args.scenario, args.seed, cfg, keep_images_at=keep)
        truth = outcome.landmark_truth
    else:
        from mowerhw.evaluation.teach import run_teach

        outcome = run_teach(
            args.scenario,
            args.seed,
            cfg.teach,
            n_landmarks=args.landmarks,
            record_history=args.plot,
        )
    metrics = dict(outcome.metrics)
    map_path = out / "map.json"
    if outcome.result is not None:
        try:
            _save_sim_map(outcome.result, map_path, args.scenario, args.seed, args.level, truth)
            metrics["map"] = str(map_path)
        except MapError as exc:
            metrics["map"] = None
            metrics["map_error"] = str(exc)
            metrics["diverged"] = True
    else:
        metrics["map"] = None
    if args.plot:
        if args.level == "pixel":
            from mowerhw.plots import frontend_figures

            metrics["figures"] = [str(f) for f in frontend_figures(outcome, out)]
        else:
            from mowerhw.plots import teach_figures

            metrics["figures"] = [str(f) for f in teach_figures(outcome, out)]
    _write_and_print(metrics, out, args.json)
    if not args.json and metrics.get("error"):
        print(f"mowerhw: teach failed: {metrics['error']}", file=sys.stderr)
    return 1 if metrics.get("diverged") else 0


def _save_sim_map(result, path: Path, scenario: str, seed: int, level: str = "bearing", truth=None):
    """Save a simulated teach map (:func:`mowerhw.evaluation.teach.sim_map`)."""
    from mowerhw.evaluation.teach import sim_map

    lawn_map = sim_map(result, scenario, seed, level, truth)
    lawn_map.save(path)
    return lawn_map


def _mow(args: argparse.Namespace) -> int:
    from mowerhw.config import EX_CONFIG
    from mowerhw.evaluation.mow import run_mow
    from mowerhw.evaluation.teach import run_teach
    from mowerhw.map import MapError, load

    cfg = load_config_or_exit(args.config)
    out = _out_dir(args, "mow")
    dropout = None
    if args.vision_dropout:
        try:
            start, dur = (float(x) for x in args.vision_dropout.split(":"))
        except ValueError:
            print(
                f"mowerhw: --vision-dropout {args.vision_dropout!r}: expected START:SECONDS, "
                "e.g. 200:10",
                file=sys.stderr,
            )
            return 2
        dropout = (start, dur)
    if args.map is None:
        if args.level == "pixel":
            from mowerhw.evaluation.pixel import run_teach_pixel

            taught = run_teach_pixel(args.scenario, args.seed, cfg)
            truth = taught.landmark_truth
        else:
            taught = run_teach(args.scenario, args.seed, cfg.teach)
            truth = None
        if taught.result is None:
            print(f"mowerhw: teaching the map failed: {taught.error}", file=sys.stderr)
            return 1
        lawn_map = _save_sim_map(
            taught.result, out / "map.json", args.scenario, args.seed, args.level, truth
        )
        map_path = out / "map.json"
    else:
        map_path = args.map
        try:
            lawn_map = load(map_path)
        except MapError as exc:
            print(f"mowerhw: {exc}", file=sys.stderr)
            return EX_CONFIG
        sim = lawn_map.teach.get("sim")
        if not isinstance(sim, dict):
            print(
                f"mowerhw: {map_path}: not taught on the simulator; `mowerhw sim mow` needs a "
                "map from `mowerhw sim teach`",
                file=sys.stderr,
            )
            return 2
        if (sim.get("scenario"), sim.get("seed")) != (args.scenario, args.seed):
            print(
                f"mowerhw: {map_path} was taught in the simulated yard {sim.get('scenario')!r} "
                f"seed {sim.get('seed')}; run with --scenario {sim.get('scenario')} "
                f"--seed {sim.get('seed')}",
                file=sys.stderr,
            )
            return 2
        if args.level == "pixel" and sim.get("level") != "pixel":
            print(
                f"mowerhw: {map_path} was taught at the bearing level (landmark ids, no "
                "descriptors); mow --level pixel needs a map from `sim teach --level pixel`",
                file=sys.stderr,
            )
            return 2
    outcome = run_mow(
        lawn_map,
        args.scenario,
        args.seed,
        args.duration,
        cfg,
        vision_dropout=dropout,
        frame_latency_s=args.latency,
        level=args.level,
        handling=args.fault,
    )
    metrics = {**outcome.metrics, "map": str(map_path)}
    if args.plot:
        from mowerhw.plots import mow_figures

        metrics["figures"] = [str(f) for f in mow_figures(outcome, out)]
    _write_and_print(metrics, out, args.json)
    return 0 if metrics["missed_halts"] == 0 else 1


def _write_and_print(metrics: dict[str, Any], out: Path, as_json: bool) -> None:
    """The run's figures into ``out/metrics.json`` and on stdout (one line with --json)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(strict_json(metrics, indent=1) + "\n")
    if as_json:
        print(strict_json(metrics))
    else:
        print_json(metrics)
