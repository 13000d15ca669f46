"""The control socket's protocol (docs/design.md §8): one JSON object per line over a Unix
stream socket, parsed with limits, and the blocking client the CLI and the bench use.

Request: ``{"cmd": "status"}`` (or just the word ``status``), optional arguments as keys;
reply: ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``. Commands: status, live
(what the status page shows: ``since`` trajectory index, ``landmarks`` true/false), idle,
teach, mow, finish-teach, save-map [path], and (only with ``runtime.fault_injection``) fault.
A request is at most :data:`MAX_REQUEST_BYTES`, nested at most :data:`MAX_DEPTH` deep, with no
duplicate keys and only strings, numbers, booleans, null or lists of those as arguments.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

from mowerhw.common.strictjson import unique_keys

COMMANDS = ("status", "live", "idle", "teach", "mow", "finish-teach", "save-map", "fault")
#: commands anyone allowed to open the socket may send; the rest change the mower or files
READ_ONLY = frozenset({"status", "live"})
#: the longest request line (bytes); requests are a command and a path at most
MAX_REQUEST_BYTES = 4096
#: deepest nesting of a request (the object, a list in it)
MAX_DEPTH = 2


def parse_request(line: bytes) -> tuple[str, dict[str, Any]]:
    """(command, arguments) of one request line; ValueError with a message if malformed."""
    if len(line) > MAX_REQUEST_BYTES:
        raise ValueError(f"request of {len(line)} bytes; at most {MAX_REQUEST_BYTES} allowed")
    text = line.decode("utf-8", errors="strict").strip()
    if not text:
        raise ValueError("empty request")
    if text[0] in '{["':
        depth = nesting_depth(text)
        if depth > MAX_DEPTH:
            raise ValueError(f"request nested {depth} deep; at most {MAX_DEPTH} allowed")
        try:
            req = json.loads(text, object_pairs_hook=unique_keys)
        except json.JSONDecodeError as exc:
            raise ValueError(
                f"request is not valid JSON ({exc.msg} at column {exc.colno})"
            ) from None
        if not isinstance(req, dict):
            raise ValueError("request must be a JSON object")
        cmd = req.pop("cmd", None)
        if not isinstance(cmd, str):
            raise ValueError('request needs "cmd": one of ' + ", ".join(COMMANDS))
        args = req
        for key, value in args.items():
            if not _plain(value):
                raise ValueError(
                    f"argument {key!r}: must be a string, number, true/false, null or a list "
                    "of those"
                )
        if "args" in args and not isinstance(args["args"], list):
            raise ValueError('argument "args" must be a list')
    else:
        words = text.split()
        cmd, args = words[0], ({"args": words[1:]} if len(words) > 1 else {})
    if cmd not in COMMANDS:
        raise ValueError(f"unknown command {cmd[:40]!r}; allowed: {', '.join(COMMANDS)}")
    return cmd, args


def nesting_depth(text: str) -> int:
    """How deep ``[`` and ``{`` nest in JSON text (outside strings), without parsing it."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _plain(value: Any) -> bool:
    if isinstance(value, list):
        return all(isinstance(v, str | int | float | bool) or v is None for v in value)
    return isinstance(value, str | int | float | bool) or value is None


def request(path: str | Path, cmd: str, timeout: float = 5.0, **args: Any) -> dict[str, Any]:
    """Send one command, return the reply (blocking; for the CLI and the bench)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(path))
        s.sendall((json.dumps({"cmd": cmd, **args}) + "\n").encode())
        buf = b""
        while not buf.endswith(b"\n"):
            chunk = s.recv(65536)
            if not chunk:
                break
            buf += chunk
    if not buf:
        raise ConnectionError(f"{path}: the daemon closed the connection without a reply")
    reply: dict[str, Any] = json.loads(buf)
    return reply
