"""``mowerhw replay`` and ``mowerhw plot``: recordings, offline."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mowerhw.cli.common import load_config_or_exit, number, output_dir, output_file, strict_json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="feed a recording (MCAP) through the parsers and estimators again",
        description=(
            "Replay FILE.mcap through the same driver parsers, estimators and permit gate as "
            "the daemon: deterministic (same file + config → same map bytes, same permit "
            "sequence). A truncated recording replays up to the cut, with a warning."
        ),
    )
    p.add_argument("recording", type=Path, metavar="FILE.mcap")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--mode", choices=("teach", "mow"), help="raw: the sensor data through the parsers"
    )
    what.add_argument(
        "--decisions",
        action="store_true",
        help="the runtime core's journal of the live run: the daemon's own decisions again, "
        "faults included, each compared with the live one",
    )
    p.add_argument("--map", type=Path, help="mow: the map (default: the one in the recording)")
    p.add_argument("--config", type=Path, help="config (default: the one in the recording)")
    pace = p.add_mutually_exclusive_group()
    pace.add_argument(
        "--speed", type=number(float, gt=0, le=1000), default=1.0, help="× real time (default 1)"
    )
    pace.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--out", type=output_dir, help="output directory (default: next to the file)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(handler=cmd_replay)

    q = sub.add_parser(
        "plot",
        help="figures of a recording: trajectory, map, containment, sensor rates and gaps",
    )
    q.add_argument("recording", type=Path, metavar="FILE.mcap")
    q.add_argument("--out", type=output_file, help="PNG path (default: FILE.png)")
    q.set_defaults(handler=cmd_plot)


def cmd_replay(args: argparse.Namespace) -> int:
    import logging

    from mowerhw.map import MapError
    from mowerhw.recording.replay import Replay, ReplayError

    if not args.verbose:  # every halt of the replayed gate is in the summary, not the log
        logging.getLogger("mowerhw.permit").setLevel(logging.ERROR)
    cfg = load_config_or_exit(args.config) if args.config else None
    if args.decisions:
        from mowerhw.recording.replay import replay_decisions

        if not args.verbose:  # the live run's faults were logged live; the result says it all
            logging.getLogger("mowerhw.daemon").setLevel(logging.CRITICAL)
        try:
            out = replay_decisions(args.recording, cfg)
        except (ReplayError, MapError, ValueError, OSError) as exc:
            print(f"mowerhw replay: {exc}", file=sys.stderr)
            return 1
        print(strict_json(out, indent=None if args.json else 2))
        return 0 if out["same_as_live"] else 3
    try:
        rep = Replay(
            args.recording,
            args.mode,
            config=cfg,
            map_path=args.map,
            out_dir=args.out,
            speed=None if args.fast else args.speed,
        )
        out = rep.run()
    except (ReplayError, MapError, ValueError) as exc:
        print(f"mowerhw replay: {exc}", file=sys.stderr)
        return 1
    if "warning" in out:
        print(f"mowerhw replay: warning: {out['warning']}", file=sys.stderr)
    print(strict_json(out, indent=None if args.json else 2))
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from mowerhw.plots import recording_figure

    out = args.out or args.recording.with_suffix(".png")
    try:
        path, warning = recording_figure(args.recording, out)
    except (OSError, ValueError) as exc:
        print(f"mowerhw plot: {exc}", file=sys.stderr)
        return 1
    if warning:
        print(f"mowerhw plot: warning: {warning}", file=sys.stderr)
    print(path)
    return 0
