"""The control socket's server (docs/design.md §8): the protocol is in
:mod:`.control_protocol`, who may do what in :mod:`.control_access`.

The control plane must never hurt the control loop, whoever is at the other end:

* all clients share request slots (``4 × requests_per_s`` a second): however many are ready,
  one request is answered per slot, and each client at most ``requests_per_s`` a second; a
  pipelined flood is answered slowly, never all at once;
* at most ``max_clients`` connections, each closed after ``idle_s`` without a complete
  request; with every place taken, the connection idle longest (over a second) makes room for
  a new one, else the new one is told so and closed; replies to a client that does not read
  time out;
* accept errors (out of file descriptors) back off and are logged once per change;
* the commands that change the mower are refused to peers without the right.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from mowerhw.common.strictjson import finite
from mowerhw.config import Config
from mowerhw.runtime.control_access import ControlPolicy, Peer, listen_unix
from mowerhw.runtime.control_protocol import MAX_REQUEST_BYTES, READ_ONLY, parse_request

log = logging.getLogger("mowerhw.control")

#: a reply the client does not take within this long ends the connection (s)
REPLY_TIMEOUT_S = 5.0
#: with every place taken, a connection this long without a request makes room (s)
EVICT_IDLE_S = 1.0

Handler = Callable[[str, dict[str, Any]], Awaitable[dict[str, Any]]]


def control_server(cfg: Config, handler: Handler) -> ControlServer:
    """The control socket server the config describes (``runtime.control_*``)."""
    rt = cfg.runtime
    policy = ControlPolicy(
        rt.control_max_clients, rt.control_idle_s, rt.control_requests_per_s, rt.control_group
    )
    return ControlServer(rt.control_socket, handler, rt.socket_mode, policy)


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

    async def start(self) -> asyncio.Task[None]:
        """Bind and listen; the task accepting connections (it ends only when the server
        closes: the daemon watches it like its other tasks)."""
        self._sock = listen_unix(self.path, self.mode)
        self._accepting = asyncio.create_task(self._accept_loop(), name="control-accept")
        return self._accepting

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
                await asyncio.sleep(0)  # a connection storm still yields every turn
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
    """Strict JSON: a number that is not finite (a pose before the first fix) is null."""
    return (json.dumps(finite(reply), default=_jsonable, allow_nan=False) + "\n").encode()


def _jsonable(v: Any) -> Any:
    if hasattr(v, "tolist"):
        return v.tolist()
    return str(v)
