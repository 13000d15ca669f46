"""The control socket: one JSON object per line over a Unix stream socket (docs/design.md §8).

Request: ``{"cmd": "status"}`` (or just the word ``status``), optional arguments as keys;
reply: ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``. Commands: status, idle,
teach, mow, finish-teach, save-map [path], and (only with ``runtime.fault_injection``) fault.

The control plane must never hurt the control loop, whoever is at the other end:

* a client gets one request per turn of the event loop and at most ``requests_per_s`` a second
  (all clients together at most ``4 × requests_per_s``): a pipelined flood is answered slowly,
  never all at once;
* at most ``max_clients`` connections, each closed after ``idle_s`` without a complete
  request; with every place taken, the connection idle longest (over a second) makes room for
  a new one, else the new one is told so and closed; replies to a client that does not read
  time out;
* a request is at most :data:`MAX_REQUEST_BYTES`, nested at most :data:`MAX_DEPTH` deep, with no
  duplicate keys and only strings, numbers, booleans, null or lists of those as arguments;
* accept errors (out of file descriptors) back off and are logged once per change;
* who may do what comes from the peer's credentials (SO_PEERCRED): ``status`` for anyone who
  can open the socket (its mode and group), everything else only for the service's own user,
  root, or members of ``runtime.control_group``.

Only one daemon serves a control socket: :func:`claim_control_socket` takes a lock beside it.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import grp
import json
import logging
import os
import pwd
import socket
import stat
import struct
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger("mowerhw.control")

COMMANDS = ("status", "idle", "teach", "mow", "finish-teach", "save-map", "fault")
#: commands anyone allowed to open the socket may send; the rest change the mower or files
READ_ONLY = frozenset({"status"})
#: the longest request line (bytes); requests are a command and a path at most
MAX_REQUEST_BYTES = 4096
#: deepest nesting of a request (the object, a list in it)
MAX_DEPTH = 2
#: a reply the client does not take within this long ends the connection (s)
REPLY_TIMEOUT_S = 5.0
#: with every place taken, a connection this long without a request makes room (s)
EVICT_IDLE_S = 1.0

Handler = Callable[[str, dict[str, Any]], Awaitable[dict[str, Any]]]


class ControlSocketBusy(RuntimeError):
    """Another daemon serves this control socket."""


@dataclass(frozen=True)
class Peer:
    """Who is at the other end of a connection (SO_PEERCRED)."""

    pid: int
    uid: int
    gid: int

    @classmethod
    def of(cls, conn: socket.socket) -> Peer:
        raw = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        pid, uid, gid = struct.unpack("3i", raw)
        return cls(pid, uid, gid)


@dataclass(frozen=True)
class ControlPolicy:
    """Limits and authorization of the control socket (``runtime.control_*`` keys)."""

    max_clients: int = 8
    idle_s: float = 60.0
    requests_per_s: float = 20.0
    group: str | None = None

    def may_change(self, peer: Peer) -> bool:
        """Commands that change the mode or write files: the service user, root, or a member
        (primary or supplementary, from the user database) of ``group``."""
        if peer.uid in (0, os.geteuid()):
            return True
        if self.group is None:
            return False
        try:
            gid = grp.getgrnam(self.group).gr_gid
            user = pwd.getpwuid(peer.uid).pw_name
            return gid == peer.gid or gid in os.getgrouplist(user, peer.gid)
        except (KeyError, OSError):
            return False

    def refusal(self, cmd: str, peer: Peer) -> str:
        who = f"uid {peer.uid}"
        allowed = "the service's user, root" + (
            f" or members of group {self.group!r}" if self.group else ""
        )
        return f"{cmd}: not allowed for {who}; commands that change the mower need {allowed}"


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
            req = json.loads(text, object_pairs_hook=_refuse_duplicate_keys)
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


def _refuse_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"duplicate key {key[:40]!r} in the request")
        out[key] = value
    return out


def _plain(value: Any) -> bool:
    if isinstance(value, list):
        return all(isinstance(v, str | int | float | bool) or v is None for v in value)
    return isinstance(value, str | int | float | bool) or value is None


def claim_control_socket(path: str | Path) -> int:
    """Lock ``<socket>.lock`` for this process's life (the descriptor is returned and must be
    kept open); :class:`ControlSocketBusy` naming the holder if another daemon has it."""
    lock = Path(str(path) + ".lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise ControlSocketBusy(
            f"another mowerhw daemon (pid {holder}) serves the control socket {path}; stop it "
            "first, or give this one its own runtime.control_socket"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


class ControlServer:
    """Serves requests on ``path`` with ``handler(cmd, args) -> reply dict``."""

    def __init__(
        self,
        path: str | Path,
        handler: Handler,
        mode: int = 0o660,
        policy: ControlPolicy | None = None,
    ) -> None:
        self.path = Path(path)
        self.handler = handler
        self.mode = mode
        self.policy = policy or ControlPolicy()
        self.requests = 0
        self.malformed = 0
        self.refused_clients = 0
        self.evicted_clients = 0
        self.unauthorized = 0
        self.accept_errors = 0
        self._sock: socket.socket | None = None
        self._accepting: asyncio.Task[None] | None = None
        #: each client's task and since when it has been idle (0: answering a request)
        self._clients: dict[asyncio.Task[None], float] = {}
        self._next_slot = 0.0

    async def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileNotFoundError):
            if not stat.S_ISSOCK(self.path.lstat().st_mode):
                raise OSError(f"{self.path} exists and is not a socket: refusing to replace it")
            self.path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(self.path))
            os.chmod(self.path, self.mode)
            sock.listen(64)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self._accepting = asyncio.create_task(self._accept_loop(), name="control-accept")

    async def close(self) -> None:
        if self._accepting is not None:
            self._accepting.cancel()
        for task in list(self._clients):
            task.cancel()
        if self._sock is not None:
            self._sock.close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    def status(self) -> dict[str, int]:
        return {
            "clients": len(self._clients),
            "requests": self.requests,
            "malformed": self.malformed,
            "refused_clients": self.refused_clients,
            "evicted_clients": self.evicted_clients,
            "unauthorized": self.unauthorized,
            "accept_errors": self.accept_errors,
        }

    # ----------------------------------------------------------------------------- accept

    async def _accept_loop(self) -> None:
        assert self._sock is not None
        loop = asyncio.get_running_loop()
        failing_since: float | None = None
        failures_logged = 0
        backoff = 0.05
        while True:
            try:
                conn, _ = await loop.sock_accept(self._sock)
            except OSError as exc:
                self.accept_errors += 1
                if failing_since is None:
                    failing_since, failures_logged = time.monotonic(), self.accept_errors - 1
                    log.error("control: cannot accept connections (%s); backing off", exc)
                await asyncio.sleep(backoff)
                backoff = min(2.0 * backoff, 2.0)
                continue
            if failing_since is not None:
                log.warning(
                    "control: accepting connections again after %.1f s (%d failed attempts)",
                    time.monotonic() - failing_since,
                    self.accept_errors - failures_logged,
                )
                failing_since, backoff = None, 0.05
            if len(self._clients) >= self.policy.max_clients:
                self._evict_idle()
            if len(self._clients) >= self.policy.max_clients:
                self.refused_clients += 1
                with contextlib.suppress(OSError):
                    conn.setblocking(False)
                    conn.send(
                        _encode(
                            {
                                "ok": False,
                                "error": f"too many clients (at most "
                                f"{self.policy.max_clients}); try again later",
                            }
                        )
                    )
                conn.close()
                continue
            task = asyncio.create_task(self._serve(conn), name="control-client")
            self._clients[task] = time.monotonic()
            task.add_done_callback(self._forget)

    def _forget(self, task: asyncio.Task[None]) -> None:
        self._clients.pop(task, None)

    def _evict_idle(self) -> None:
        """All places taken: close the connection idle longest (over :data:`EVICT_IDLE_S`
        without a request), so idle connections cannot lock out a client with a request."""
        now = time.monotonic()
        idle = [(since, task) for task, since in self._clients.items() if since > 0]
        if idle:
            since, task = min(idle, key=lambda x: x[0])
            if now - since >= EVICT_IDLE_S:
                self.evicted_clients += 1
                task.cancel()
                self._clients.pop(task, None)

    # ----------------------------------------------------------------------------- serve

    async def _serve(self, conn: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        conn.setblocking(False)
        client_next = 0.0
        buf = bytearray()
        try:
            peer = Peer.of(conn)
            while True:
                nl = buf.find(b"\n")
                if nl < 0:
                    if len(buf) > MAX_REQUEST_BYTES:
                        self.malformed += 1
                        await self._reply(
                            conn, _error(f"request line over {MAX_REQUEST_BYTES} bytes")
                        )
                        return
                    chunk = await asyncio.wait_for(
                        loop.sock_recv(conn, MAX_REQUEST_BYTES + 1), self.policy.idle_s
                    )
                    if not chunk:
                        if not buf.strip():
                            return
                        buf += b"\n"  # the last request, without its newline
                    buf += chunk
                    continue
                line = bytes(buf[:nl])
                del buf[: nl + 1]
                me = asyncio.current_task()
                if me is not None and me in self._clients:
                    self._clients[me] = 0.0  # busy: never evicted mid-request
                await self._take_slot()  # all clients: one request at a time, spaced
                await self._reply(conn, await self._answer(line, peer))
                if me is not None and me in self._clients:
                    self._clients[me] = time.monotonic()
                client_next = await self._pace(client_next)
        except (OSError, TimeoutError, ConnectionError):
            return
        finally:
            conn.close()

    async def _take_slot(self) -> None:
        """Wait for the next of the slots all clients share (``4 × requests_per_s`` a
        second): however many clients are ready at once, the loop answers one request per
        slot, so requests never pile up into one long turn of the loop."""
        now = time.monotonic()
        at = max(now, self._next_slot)
        self._next_slot = at + 0.25 / self.policy.requests_per_s
        await asyncio.sleep(at - now)  # 0 s: still a turn of the loop between requests

    async def _pace(self, client_next: float) -> float:
        """A client's own rate: the next request no sooner than ``1 / requests_per_s``."""
        now = time.monotonic()
        client_next = max(now, client_next) + 1.0 / self.policy.requests_per_s
        await asyncio.sleep(client_next - now)
        return client_next

    async def _answer(self, line: bytes, peer: Peer) -> dict[str, Any]:
        self.requests += 1
        try:
            cmd, args = parse_request(line)
        except (ValueError, UnicodeDecodeError, RecursionError) as exc:
            self.malformed += 1
            return _error(str(exc)[:300])
        if cmd not in READ_ONLY and not self.policy.may_change(peer):
            self.unauthorized += 1
            log.warning("control: refused %s from pid %d uid %d", cmd, peer.pid, peer.uid)
            return _error(self.policy.refusal(cmd, peer))
        try:
            return await self.handler(cmd, args)
        except Exception as exc:  # a handler bug must not take the daemon down
            log.exception("control: %s failed", cmd)
            return _error(f"{cmd} failed: {exc}")

    @staticmethod
    async def _reply(conn: socket.socket, reply: dict[str, Any]) -> None:
        loop = asyncio.get_running_loop()
        await asyncio.wait_for(loop.sock_sendall(conn, _encode(reply)), REPLY_TIMEOUT_S)


def _error(message: str) -> dict[str, Any]:
    return {"ok": False, "error": message}


def _encode(reply: dict[str, Any]) -> bytes:
    return (json.dumps(reply, default=_jsonable) + "\n").encode()


def _jsonable(v: Any) -> Any:
    if hasattr(v, "tolist"):
        return v.tolist()
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
