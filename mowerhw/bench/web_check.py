"""``mowerhw bench --web``: the status page served during the run, and measured (issue 19).

Mowing is split in halves: the first with no browser, the second with a client on the
page's WebSocket taking every update (what an open page costs: the daemon answering ``live``
10 times a second, the page's process sending). At the start of the second half the page is
sent control requests without the token, with a wrong one, malformed and oversized; each
reply is kept verbatim, and the bench's own scores of the same run (halts, permit) show the
permit output did not notice.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
import urllib.error
import urllib.request
from typing import Any


def free_tcp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


#: a watcher whose connection failed or ended connects again after this long (s)
RECONNECT_S = 0.5


class PageWatcher:
    """A browser's share of the page: a WebSocket client on ``/ws`` in its own thread,
    counting the updates and the gaps between them (a gap across a reconnection too)."""

    def __init__(self, url: str) -> None:
        self.url = url.rstrip("/") + "/ws"
        self.updates = 0
        self.errors: list[str] = []
        self.gaps: list[float] = []
        self.last: dict[str, Any] | None = None
        self._t_last: float | None = None  # the previous update's time, across connections
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="page-watcher", daemon=True)

    def start(self) -> PageWatcher:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        asyncio.run(self._watch())

    async def _watch(self) -> None:
        """Connect, count, and connect again after ``RECONNECT_S`` when the connection fails
        or ends (as the page itself does: the page's process may be restarted meanwhile)."""
        import aiohttp

        while not self._stop.is_set():
            try:
                async with aiohttp.ClientSession() as session, session.ws_connect(self.url) as ws:
                    await self._count(ws)
            except Exception as exc:  # reported in the bench JSON, not raised
                self.errors.append(f"{type(exc).__name__}: {exc}")
            if not self._stop.is_set():
                await asyncio.sleep(RECONNECT_S)

    async def _count(self, ws: Any) -> None:
        """Count the live updates on ``ws`` until it ends or the watcher is stopped."""
        import aiohttp

        while not self._stop.is_set():
            try:
                msg = await ws.receive(timeout=0.5)
            except TimeoutError:
                continue
            if msg.type != aiohttp.WSMsgType.TEXT:
                self.errors.append(f"connection ended ({msg.type.name})")
                return
            body = json.loads(msg.data)
            if body.get("type") != "live":
                continue
            now = time.monotonic()
            if self._t_last is not None:
                self.gaps.append(now - self._t_last)
            self._t_last = now
            self.updates += 1
            self.last = body

    def summary(self, seconds: float) -> dict[str, Any]:
        gaps = sorted(self.gaps)
        return {
            "updates": self.updates,
            "rate_hz": round(self.updates / max(seconds, 1e-9), 2),
            "max_gap_ms": round(1e3 * gaps[-1], 1) if gaps else None,
            "p99_gap_ms": round(1e3 * gaps[int(0.99 * (len(gaps) - 1))], 1) if gaps else None,
            "errors": self.errors[:5],
        }


#: the refused control requests the bench sends: (what, headers, body)
BAD_REQUESTS: list[tuple[str, dict[str, str], bytes]] = [
    ("no token", {"Content-Type": "application/json"}, b'{"cmd": "idle"}'),
    (
        "wrong token",
        {"Content-Type": "application/json", "Authorization": "Bearer not-the-token-0000"},
        b'{"cmd": "idle"}',
    ),
    ("malformed", {"Content-Type": "application/json"}, b'{"cmd": "idle",'),
    (
        "oversized",
        {"Content-Type": "application/json"},
        b'{"cmd": "idle", "x": "' + b"A" * 8192 + b'"}',
    ),
]


def send_bad_requests(url: str, token: str) -> list[dict[str, Any]]:
    """Each of :data:`BAD_REQUESTS` (the malformed and oversized ones with the right token:
    they must be refused for what they are), with the reply verbatim."""
    out = []
    for what, headers, body in BAD_REQUESTS:
        if what in ("malformed", "oversized"):
            headers = {**headers, "Authorization": f"Bearer {token}"}
        req = urllib.request.Request(
            url.rstrip("/") + "/api/command", data=body, headers=headers, method="POST"
        )
        try:
            with urllib.request.urlopen(req, timeout=5.0) as resp:
                status, text = resp.status, resp.read().decode()
        except urllib.error.HTTPError as exc:
            status, text = exc.code, exc.read().decode()
        except OSError as exc:
            status, text = 0, f"{type(exc).__name__}: {exc}"
        out.append({"request": what, "bytes": len(body), "status": status, "response": text})
    return out
