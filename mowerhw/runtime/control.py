"""The control socket: one JSON object per line over a Unix stream socket.

Request: ``{"cmd": "status"}`` (or just the word ``status``), optional arguments as keys;
reply: ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``. Commands: status, idle,
teach, mow, finish-teach, save-map [path], and (only with ``runtime.fault_injection``) fault.
A malformed request (not JSON, not an object, an unknown command, a line over 64 KiB) gets an
error reply naming what is allowed; the connection and the daemon carry on.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

log = logging.getLogger("mowerhw.control")

COMMANDS = ("status", "idle", "teach", "mow", "finish-teach", "save-map", "fault")
MAX_LINE = 65536

Handler = Callable[[str, dict[str, Any]], Awaitable[dict[str, Any]]]


def parse_request(line: bytes) -> tuple[str, dict[str, Any]]:
    """(command, arguments) of one request line; ValueError with a message if malformed."""
    text = line.decode("utf-8", errors="strict").strip()
    if not text:
        raise ValueError("empty request")
    if text[0] in '{["':
        try:
            req = json.loads(text)
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
    else:
        words = text.split()
        cmd, args = words[0], ({"args": words[1:]} if len(words) > 1 else {})
    if cmd not in COMMANDS:
        raise ValueError(f"unknown command {cmd!r}; allowed: {', '.join(COMMANDS)}")
    return cmd, args


class ControlServer:
    """Serves requests on ``path`` with ``handler(cmd, args) -> reply dict``."""

    def __init__(self, path: str | Path, handler: Handler, mode: int = 0o660) -> None:
        self.path = Path(path)
        self.handler = handler
        self.mode = mode
        self.requests = 0
        self.malformed = 0
        self._server: asyncio.base_events.Server | None = None

    async def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        self._server = await asyncio.start_unix_server(
            self._serve, path=str(self.path), limit=MAX_LINE
        )
        os.chmod(self.path, self.mode)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                try:
                    line = await reader.readuntil(b"\n")
                except asyncio.IncompleteReadError as exc:
                    if not exc.partial.strip():
                        return
                    line = exc.partial
                except asyncio.LimitOverrunError:
                    self.malformed += 1
                    await self._reply(writer, {"ok": False, "error": "request line too long"})
                    return
                self.requests += 1
                try:
                    cmd, args = parse_request(line)
                except (ValueError, UnicodeDecodeError) as exc:
                    self.malformed += 1
                    await self._reply(writer, {"ok": False, "error": str(exc)})
                    continue
                try:
                    reply = await self.handler(cmd, args)
                except Exception as exc:  # a handler bug must not take the daemon down
                    log.exception("control: %s failed", cmd)
                    reply = {"ok": False, "error": f"{cmd} failed: {exc}"}
                await self._reply(writer, reply)
        except (ConnectionError, OSError):
            return
        finally:
            with contextlib.suppress(Exception):
                writer.close()

    @staticmethod
    async def _reply(writer: asyncio.StreamWriter, reply: dict[str, Any]) -> None:
        writer.write((json.dumps(reply, default=_jsonable) + "\n").encode())
        await writer.drain()


def _jsonable(v: Any) -> Any:
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    return str(v)


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
