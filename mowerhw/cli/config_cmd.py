"""``mowerhw config check|show|schema``."""

from __future__ import annotations

import argparse
import sys

import yaml

from mowerhw.cli.common import add_config_argument, load_config_or_exit
from mowerhw.config import config_to_dict, describe_schema


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="validate and inspect runtime configuration files")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)

    check = csub.add_parser("check", help="validate FILE (exit 0, or 78 naming each bad key)")
    check.add_argument("file", type=__import__("pathlib").Path, metavar="FILE")
    check.set_defaults(handler=_check)

    show = csub.add_parser("show", help="print the effective config (file + defaults) as YAML")
    add_config_argument(show)
    show.set_defaults(handler=_show)

    schema = csub.add_parser("schema", help="list every key with its default and meaning")
    schema.set_defaults(handler=_schema)


def _check(args: argparse.Namespace) -> int:
    cfg = load_config_or_exit(args.file)
    print(
        f"{args.file}: ok (imu {cfg.imu.driver} on {cfg.imu.port}, CAN {cfg.can.interface} "
        f"{cfg.can.channel}, camera {cfg.camera.driver} {cfg.camera.device})"
    )
    return 0


def _show(args: argparse.Namespace) -> int:
    cfg = load_config_or_exit(args.config)
    sys.stdout.write(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
    return 0


def _schema(args: argparse.Namespace) -> int:
    print("\n".join(describe_schema()))
    return 0
