"""The permit supervisor's status socket, served from its own loop (docs/design.md §8;
the protocol: :mod:`mowerhw.common.supervisor_socket`), and its blocking client.

The control socket is served by the estimation process: when that process is stalled, hung
or restarting, ``mowerhw ctl status`` and the status page hear nothing, at the moment an
operator most needs to know why the deck stopped. The supervisor knows (its lease ran out,
its own checks), so it says so here. It never waits on a client: the listening socket and
every connection are non-blocking, a reply that does not fit the socket's buffer at once is
dropped, and at most :data:`ACCEPTS_PER_WAKE` clients are answered per turn of its loop
and :data:`CLIENTS_PER_S` a second: beyond that, the socket is not listened to until the next
second (the supervisor runs at real-time priority, so a flood of clients must not keep it
busy; clients wait in the kernel's backlog meanwhile)."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mowerhw.common.strictjson import finite
from mowerhw.common.supervisor_socket import MAX_REPLY_BYTES, parse_reply, supervisor_socket
from mowerhw.runtime.control_access import listen_unix

log = logging.getLogger("mowerhw.supervisor")

#: clients answered per turn of the supervisor's loop (the rest wait for the next turn)
ACCEPTS_PER_WAKE = 4
#: clients answered a second at most (``ctl`` and the page ask about once a second)
CLIENTS_PER_S = 20


class StatusSocket:
    """Bind ``<control socket>.supervisor``; :meth:`serve` answers waiting clients."""

    def __init__(self, control_socket: str | Path, mode: int) -> None:
        self.path = supervisor_socket(control_socket)
        self.mode = mode
        self.answered = 0
        self.dropped = 0
        self._sock: socket.socket | None = None
        self._second = 0.0  # the start of the second being counted
        self._in_second = 0  # clients taken in it

    def open(self) -> bool:
        """Listen; False (said once in the log) when it cannot: mowing does not need it."""
        try:
            sock = listen_unix(self.path, self.mode)
        except OSError as exc:
            log.warning(
                "the permit supervisor's status socket %s cannot be opened (%s): `mowerhw "
                "ctl` and the status page cannot hear it while the estimation process is silent",
                self.path,
                exc,
            )
            return False
        self._sock = sock
        return True

    def listener(self, now: float) -> socket.socket | None:
        """For the loop's ``wait``: readable when a client waits (None: not open, or this
        second's :data:`CLIENTS_PER_S` taken)."""
        if now - self._second >= 1.0:
            self._second, self._in_second = now, 0
        return self._sock if self._in_second < CLIENTS_PER_S else None

    def serve(self, status: Callable[[], dict[str, Any]]) -> None:
        """Answer the clients waiting now (at most :data:`ACCEPTS_PER_WAKE`): one line of
        ``status()`` as strict JSON each, then close."""
        if self._sock is None:
            return
        reply = b""
        for _ in range(min(ACCEPTS_PER_WAKE, CLIENTS_PER_S - self._in_second)):
            try:
                conn, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # out of descriptors: the next turn tries again
                log.debug("status socket: accept failed (%s)", exc)
                return
            self._in_second += 1
            with conn:
                conn.setblocking(False)
                if not reply:
                    reply = _encode(status())
                try:
                    sent = conn.send(reply)
                except OSError:
                    sent = 0
                if sent == len(reply):
                    self.answered += 1
                else:  # a client that does not read: never waited for
                    self.dropped += 1

    def close(self) -> None:
        if self._sock is None:
            return
        self._sock.close()
        self._sock = None
        with contextlib.suppress(OSError):
            self.path.unlink()


def ask_supervisor(control_socket: str | Path, timeout: float = 1.0) -> dict[str, Any]:
    """The status of the supervisor of the daemon serving ``control_socket`` (blocking: the
    CLI, the bench). OSError, ConnectionError or ValueError when it does not answer or
    answers nonsense."""
    path = supervisor_socket(control_socket)
    buf = bytearray()
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(path))
        while len(buf) <= MAX_REPLY_BYTES:
            chunk = s.recv(MAX_REPLY_BYTES + 1 - len(buf))
            if not chunk:
                break
            buf += chunk
    return parse_reply(bytes(buf), path)


def _encode(status: dict[str, Any]) -> bytes:
    return (json.dumps(finite(status), allow_nan=False, default=str) + "\n").encode()
