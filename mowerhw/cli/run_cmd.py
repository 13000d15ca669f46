"""``mowerhw run`` (the daemon) and ``mowerhw ctl`` (talk to it over its control socket)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from mowerhw.cli.common import (
    add_config_argument,
    load_config_or_exit,
    number,
    output_file,
    strict_json,
)
from mowerhw.config import EX_CONFIG, Config
from mowerhw.runtime.control_protocol import COMMANDS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="the on-board daemon: devices, estimators, fail-safe permit (systemd service)",
        description=(
            "Run the daemon: read the VN-100, CAN ground speed and the camera, teach or mow, "
            "and drive the mowing permit / halt on CAN (default: halt). Stops on SIGTERM "
            "with a halt and heartbeat 255. Exit status 78: bad configuration."
        ),
    )
    add_config_argument(p)
    p.add_argument(
        "--mode",
        choices=("idle", "teach", "mow"),
        help="start-up mode (default: runtime.mode of the config)",
    )
    p.add_argument(
        "--record",
        type=output_file,
        metavar="FILE.mcap",
        help="record every raw input and the estimates",
    )
    p.add_argument("--duration", type=number(float, gt=0), help="stop after this many seconds")
    p.set_defaults(handler=cmd_run)

    r = sub.add_parser(
        "record",
        help="record the sensors (no estimation) to an MCAP file",
        description=(
            "Open the VN-100, the CAN bus and the camera as the daemon does and record every "
            "raw input (serial bytes, CAN frames, JPEG frames) with its host time, plus the "
            "config and calibration, to one MCAP file (zstd chunks; opens in Foxglove). The "
            "permit output stays at halt. Stop with Ctrl-C / SIGTERM or --duration."
        ),
    )
    add_config_argument(r)
    r.add_argument("--out", type=output_file, required=True, metavar="FILE.mcap")
    r.add_argument("--duration", type=number(float, gt=0), help="stop after this many seconds")
    r.set_defaults(handler=cmd_record)

    w = sub.add_parser(
        "web",
        help="serve the status page for a running daemon (what web.enabled starts itself)",
        description=(
            "Serve the status page (web.host, web.port) for the daemon on the config's "
            "control socket: live map, pose, decision and sensors; controls with the token "
            "in web.token_file. Runs until Ctrl-C / SIGTERM."
        ),
    )
    add_config_argument(w)
    w.add_argument("--port", type=number(int, ge=0, le=65535), help="instead of web.port")
    w.add_argument("--host", help="instead of web.host")
    w.set_defaults(handler=cmd_web)

    c = sub.add_parser(
        "ctl",
        help="control a running daemon: status|teach|mow|idle|finish-teach|save-map|supervisor",
        description=(
            "Send one command to the daemon's control socket and print its reply. "
            "`supervisor` reads the permit supervisor's own status socket instead "
            "(<control socket>.supervisor): it answers at once, also while the estimation "
            "process, which serves the control socket, is stalled or restarting."
        ),
    )
    add_config_argument(c)
    c.add_argument("command", choices=[x for x in COMMANDS if x != "fault"] + ["fault", SUPERVISOR])
    c.add_argument(
        "args",
        nargs="*",
        help="save-map: PATH; fault: nan|exception; teach (while teaching): area NAME | "
        "keepout NAME | nav NAME | dock | end — what is driven from now on",
    )
    c.add_argument(
        "--area",
        action="append",
        help="mow: mow only this mowing area of the map (repeat for more); the others are "
        "driven with the deck off (TRANSIT). Default: the config's mow.areas (empty: all)",
    )
    c.add_argument("--socket", type=Path, help="control socket (default: from the config)")
    c.add_argument(
        "--timeout",
        type=number(float, gt=0, le=3600),
        default=30.0,
        help="seconds to wait for a reply",
    )
    c.add_argument("--json", action="store_true", help="print the reply as JSON")
    c.set_defaults(handler=cmd_ctl)


def _claim_socket_or_exit(cfg: Config) -> int:
    """The control socket's lock (kept for the process's life), or exit 78: two daemons on
    one socket would take each other's commands."""
    from mowerhw.runtime.control_access import ControlSocketBusy, claim_control_socket

    try:
        return claim_control_socket(cfg.runtime.control_socket)
    except ControlSocketBusy as exc:
        print(f"mowerhw run: {exc}", file=sys.stderr)
    except OSError as exc:
        print(
            f"mowerhw run: cannot lock the control socket {cfg.runtime.control_socket}: {exc}",
            file=sys.stderr,
        )
    raise SystemExit(EX_CONFIG)


def cmd_run(args: argparse.Namespace) -> int:
    cfg = load_config_or_exit(args.config)
    root = logging.getLogger()
    root.setLevel(min(getattr(logging, cfg.runtime.log_level), root.level))
    _claim_socket_or_exit(cfg)
    if cfg.supervisor.enabled:  # the permit supervisor owns CAN; estimation in a child
        from mowerhw.supervisor.process import run_supervised

        return run_supervised(cfg, args.mode, args.record, args.duration)
    from mowerhw.runtime.process import run_daemon

    return run_daemon(cfg, args.mode, record=args.record, duration_s=args.duration)


def cmd_web(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from mowerhw.web.server import web_main

    cfg = load_config_or_exit(args.config)
    web = replace(
        cfg.web,
        port=cfg.web.port if args.port is None else args.port,
        host=args.host or cfg.web.host,
    )
    try:
        web_main(replace(cfg, web=web), logging.getLogger().level or logging.INFO)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    cfg = load_config_or_exit(args.config)
    root = logging.getLogger()
    root.setLevel(min(getattr(logging, cfg.runtime.log_level), root.level))
    _claim_socket_or_exit(cfg)
    from mowerhw.runtime.process import run_daemon

    return run_daemon(cfg, "idle", record=args.out, duration_s=args.duration)


#: ``mowerhw ctl supervisor``: the permit supervisor's status socket, not the control socket
SUPERVISOR = "supervisor"
#: how long ``ctl`` waits for the permit supervisor's status socket (it answers at once)
SUPERVISOR_TIMEOUT_S = 2.0


def _supervisor_says(sock: str | Path) -> tuple[dict[str, Any] | None, str]:
    """What the permit supervisor says when the control socket is silent (its own status
    socket, :mod:`mowerhw.common.supervisor_socket`) and in words, or why it says nothing."""
    from mowerhw.common.supervisor_socket import (
        describe,
        supervisor_socket,
        supervisor_unreachable,
    )
    from mowerhw.supervisor.status_socket import ask_supervisor

    try:
        status = ask_supervisor(sock, timeout=SUPERVISOR_TIMEOUT_S)
    except (OSError, ConnectionError, ValueError) as exc:
        path = supervisor_socket(sock)
        why = supervisor_unreachable(exc)
        return None, f"the permit supervisor does not answer on {path} either: {why}"
    return status, describe(status)


def cmd_ctl(args: argparse.Namespace) -> int:
    from mowerhw.common.unreachable import unreachable
    from mowerhw.runtime.control_protocol import request

    sock = args.socket
    if sock is None:
        sock = load_config_or_exit(args.config).runtime.control_socket
    if args.command == SUPERVISOR:
        status, says = _supervisor_says(sock)
        print(f"mowerhw ctl: {says}", file=sys.stderr)
        print(strict_json(status if status is not None else {"ok": False, "error": says}, indent=2))
        return 0 if status is not None else 1
    extra: dict[str, Any] = {"args": args.args} if args.args else {}
    if args.area:
        if args.command != "mow":
            print("mowerhw ctl: --area is for mow", file=sys.stderr)
            return 2
        extra["areas"] = args.area
    try:
        reply = request(sock, args.command, timeout=args.timeout, **extra)
    except (OSError, ConnectionError) as exc:
        error = f"cannot reach the daemon at {sock}: {unreachable(exc, args.timeout)}"
        supervisor, says = _supervisor_says(sock)
        if supervisor is not None and isinstance(exc, FileNotFoundError | ConnectionRefusedError):
            # the daemon runs (its supervisor answered): its estimation process serves no socket
            error = (
                f"cannot reach the daemon at {sock}: its estimation process does not serve it "
                "(starting, restarting or ended)"
            )
        print(f"mowerhw ctl: {error}", file=sys.stderr)
        print(f"mowerhw ctl: {says}", file=sys.stderr)
        if args.json or args.command == "status":  # strict JSON still: the error, the supervisor
            print(strict_json({"ok": False, "error": error, "supervisor": supervisor}, indent=2))
        return 1
    if args.json or args.command == "status":
        print(strict_json(reply, indent=2))
    else:
        print(reply.get("error") or strict_json(reply))
    return 0 if reply.get("ok") else 1
