"""The ``mowerhw`` command line.

Each command group lives in its own module with a ``register(subparsers)`` function; this
module only assembles them. Exit status: 0 success, 1 a failed check or run, 2 bad usage,
78 (``EX_CONFIG``) a bad configuration, map or calibration file.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from mowerhw import __version__
from mowerhw.cli import (
    bench_cmd,
    camera_cmd,
    config_cmd,
    demo_cmd,
    eval_cmd,
    imu_cmd,
    map_cmd,
    replay_cmd,
    run_cmd,
    sim_cmd,
)

COMMAND_MODULES = (
    run_cmd,
    bench_cmd,
    replay_cmd,
    config_cmd,
    camera_cmd,
    sim_cmd,
    eval_cmd,
    imu_cmd,
    map_cmd,
    demo_cmd,
)

DESCRIPTION = """\
Wire-free, GPS-free containment for a robotic mower: VN-100 IMU + ISO 11783 ground speed +
omnidirectional camera -> teach a boundary and a landmark map, then localize against it and
drive a fail-safe mowing permit / halt signal on CAN (Yang et al., IROS 2013).
"""

EPILOG = """\
examples:
  mowerhw config check configs/mower.yaml    validate a config (exit 78 with the reason)
  mowerhw config schema                      every key, its default and what it means
  mowerhw camera info                        field of view and model check of a calibration
  mowerhw sim teach --scenario paper --seed 7 --plot   simulated teach drive, map, errors
  mowerhw sim mow --map MAP --seed 7 --duration 500 --plot   simulated closed-loop mowing
  mowerhw map show MAP                       what a lawn map holds (map check|plot|add-keepout)
  mowerhw demo                               a short tour of what this build can do
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mowerhw",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mowerhw {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `mowerhw ... | head`
        return 1
    except OSError as exc:  # a file that cannot be read or written: a failure, said plainly
        print(f"mowerhw {args.command}: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug: one line for the user, the traceback with -vv
        logging.getLogger("mowerhw").debug("internal error", exc_info=True)
        print(
            f"mowerhw {args.command}: internal error ({type(exc).__name__}: {str(exc)[:300]}); "
            "run again with -vv for the traceback and report it",
            file=sys.stderr,
        )
        return 70
