"""The page's view of the daemon: the ``live`` command polled over the control socket.

One connection, one request at a time, ``rate_hz`` a second and only while someone watches
(a browser, or the Foxglove live server): with the page closed the daemon is not asked at
all. The trajectory is kept here too (the daemon sends each point once), so every browser
gets the whole drive when it connects and only the new points after. A daemon that cannot be
reached is said on the page, and asked again every second.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import math
import os
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

from mowerhw.common.fileio import FileStamp, file_stamp
from mowerhw.common.supervisor_socket import (
    MAX_REPLY_BYTES as MAX_SUPERVISOR_REPLY_BYTES,
)
from mowerhw.common.supervisor_socket import (
    describe,
    parse_reply,
    supervisor_socket,
    supervisor_unreachable,
)
from mowerhw.common.unreachable import unreachable
from mowerhw.map import MapError
from mowerhw.map import load as load_map
from mowerhw.web.plan import map_plan

log = logging.getLogger("mowerhw.web")

#: the landmarks being mapped are asked for this often (s): they change slowly
LANDMARKS_PERIOD_S = 1.0
#: the map file is looked at this often (s)
MAP_CHECK_S = 1.0
#: the daemon's reply may be this large (bytes): hundreds of landmarks
MAX_REPLY_BYTES = 4 << 20
#: a reply that does not come within this long: the daemon is busy or gone
REPLY_TIMEOUT_S = 2.0
#: the permit supervisor's status socket answers at once, or not at all
SUPERVISOR_TIMEOUT_S = 0.5

Point = tuple[float, float, float]
Connection = tuple[asyncio.StreamReader, asyncio.StreamWriter]


class DaemonFeed:
    """Polls the daemon (see the module doc); consumers wait with :meth:`wait_update`."""

    def __init__(
        self,
        socket_path: str | Path,
        map_path: str | Path,
        rate_hz: float = 10.0,
        max_points: int = 36000,
        executor: Executor | None = None,
    ) -> None:
        self.socket_path = Path(socket_path)
        self.map_path = Path(map_path)
        self.period_s = 1.0 / rate_hz
        self.executor = executor
        self.latest: dict[str, Any] | None = None
        self.error = "not connected to the daemon yet"
        self._unreachable = ""  # why the daemon's control socket was silent, as logged
        self.version = 0  # updates so far
        self.session = ""  # run and epoch of the daemon's drawing
        self.points: deque[Point] = deque(maxlen=max_points)
        self.total = 0  # points received this session (the index after the newest)
        self.landmarks: list[list[float]] = []
        self.landmarks_version = 0
        self.map: dict[str, Any] | None = None
        self.map_error = ""
        self.map_version = ""
        self.polls = self.poll_errors = 0
        self.watchers = 0  # browsers connected
        self.always = False  # poll even with no browser (the Foxglove live server)
        self.on_update: list[Callable[[dict[str, Any]], None]] = []
        self._since = 0  # the daemon's trajectory index
        self._next_landmarks = 0.0
        self._next_map_check = 0.0
        self._map_key: FileStamp | None = None
        self._cond = asyncio.Condition()
        self._wake = asyncio.Event()
        self._conn: Connection | None = None
        self._stopping = False
        self._lock = asyncio.Lock()
        self._polled_at = -math.inf

    # ------------------------------------------------------------------------- consumers

    def stop(self) -> None:
        """End :meth:`run` (also where a cancellation was lost in ``wait_for``: Python 3.11
        can swallow one that comes as the awaited reply arrives)."""
        self._stopping = True
        self._wake.set()
        self._close()

    def watch(self) -> None:
        self.watchers += 1
        self._wake.set()

    def unwatch(self) -> None:
        self.watchers = max(0, self.watchers - 1)

    async def wait_update(self, seen: int, timeout: float) -> None:
        """Until an update newer than ``seen`` (or ``timeout``)."""
        async with self._cond:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._cond.wait_for(lambda: self.version > seen), timeout)

    def points_since(self, index: int) -> tuple[int, list[Point]]:
        """(index of the first point, points from ``index`` on; the oldest kept if gone)."""
        first = self.total - len(self.points)
        start = min(max(index, first), self.total)
        # from the newest end: an update costs the points it carries, not the whole drive
        return start, list(itertools.islice(reversed(self.points), self.total - start))[::-1]

    # ------------------------------------------------------------------------------ run

    async def run(self) -> None:
        """Poll until :meth:`stop` (a task of the page's process)."""
        loop = asyncio.get_running_loop()
        while not self._stopping:
            if not (self.watchers or self.always):
                self._close()
                self._wake.clear()
                await self._wake.wait()
            started = loop.time()
            if not await self._poll():
                await asyncio.sleep(1.0)  # the daemon does not answer: ask again in a second
            await self._check_map_when_due()
            await asyncio.sleep(max(0.0, started + self.period_s - loop.time()))

    async def refresh(self) -> None:
        """A reader with no stream (``GET /api/status``, ``/api/map``): ask the daemon now,
        unless the newest answer is younger than one period."""
        now = time.monotonic()
        if now - self._polled_at >= self.period_s:
            await self._poll()
        await self._check_map_when_due()

    async def _poll(self) -> bool:
        """Ask the daemon once; False when it did not answer."""
        async with self._lock:  # one request at a time on the one connection
            return await self._poll_once()

    async def _poll_once(self) -> bool:
        now = self._polled_at = time.monotonic()
        want_landmarks = now >= self._next_landmarks
        since = self._since
        try:
            reply = await self._request(
                {"cmd": "live", "since": since, "landmarks": want_landmarks}
            )
        except (OSError, ConnectionError, TimeoutError, ValueError) as exc:
            self.poll_errors += 1
            self._close()
            error = f"the daemon does not answer on {self.socket_path} ({unreachable(exc)})"
            if error != self._unreachable:
                log.warning("web: %s", error)
            self._unreachable = error
            self.error = f"{error}; {await self._supervisor_says()}"
            await self._publish()
            return False
        self.polls += 1
        if not reply.get("ok"):
            self.error = f"the daemon refused the status request: {reply.get('error')}"
            await self._publish()
            return True
        if self.error:
            log.info("web: reading the daemon on %s", self.socket_path)
        self.error = self._unreachable = ""
        if want_landmarks:
            self._next_landmarks = now + LANDMARKS_PERIOD_S
        if self._take(reply, since):
            await self._publish()
        return True

    def _take(self, reply: dict[str, Any], since: int) -> bool:
        """Keep a reply; False when it must be asked again (a new session, asked from the
        middle of the old one's trajectory)."""
        session = f"{reply.get('run')}/{reply.get('epoch')}"
        if session != self.session:  # a new drive, or a restarted daemon: start again
            self.session = session
            self.points.clear()
            self.total = 0
            self.landmarks, self._since = [], 0
            self.landmarks_version += 1
            self._next_landmarks = 0.0
            if since != 0:
                return False  # ask again for the whole of it
        traj = reply.pop("trajectory", {}) or {}
        pts = traj.get("points") or []
        for p in pts:
            self.points.append((float(p[0]), float(p[1]), float(p[2])))
        self.total += len(pts)
        self._since = int(traj.get("from", self._since)) + len(pts)
        lms = reply.pop("landmarks", None)
        if lms is not None:
            if lms != self.landmarks:
                self.landmarks_version += 1
            self.landmarks = lms
        reply.pop("ok", None)
        self.latest = reply
        return True

    async def _publish(self) -> None:
        async with self._cond:
            self.version += 1
            self._cond.notify_all()
        if self.latest is not None and not self.error:
            for fn in self.on_update:
                try:
                    fn(self.latest)
                except Exception:  # a consumer's bug must not stop the page
                    log.exception("web: an update consumer failed")

    async def request(self, req: dict[str, Any], timeout: float = 20.0) -> dict[str, Any]:
        """One command on a connection of its own (the operator's controls)."""
        conn = await self._connect(5.0)
        try:
            return await _exchange(conn, req, timeout)
        finally:
            conn[1].close()

    async def _supervisor_says(self) -> str:
        """The permit supervisor's word when the control socket is silent (its own status
        socket), or why it says nothing either."""
        try:
            status = await asyncio.wait_for(self._ask_supervisor(), SUPERVISOR_TIMEOUT_S)
        except (OSError, ConnectionError, TimeoutError, ValueError) as exc:
            return f"the permit supervisor does not answer either ({supervisor_unreachable(exc)})"
        return describe(status)

    async def _ask_supervisor(self) -> dict[str, Any]:
        """Read the supervisor's status socket (it writes one line and closes)."""
        path = supervisor_socket(self.socket_path)
        reader, writer = await asyncio.open_unix_connection(str(path))
        buf = bytearray()
        try:
            while len(buf) <= MAX_SUPERVISOR_REPLY_BYTES:
                chunk = await reader.read(MAX_SUPERVISOR_REPLY_BYTES + 1 - len(buf))
                if not chunk:
                    break
                buf += chunk
        finally:
            writer.close()
        return parse_reply(bytes(buf), path)

    async def _request(self, req: dict[str, Any]) -> dict[str, Any]:
        """One ``live`` request on the polling connection (opened when needed)."""
        if self._conn is None:
            self._conn = await self._connect(REPLY_TIMEOUT_S)
        return await _exchange(self._conn, req, REPLY_TIMEOUT_S)

    async def _connect(self, timeout: float) -> Connection:
        return await asyncio.wait_for(
            asyncio.open_unix_connection(str(self.socket_path), limit=MAX_REPLY_BYTES), timeout
        )

    def _close(self) -> None:
        if self._conn is not None:
            self._conn[1].close()
            self._conn = None

    # ------------------------------------------------------------------------------- map

    async def _check_map_when_due(self) -> None:
        """Look at the map file at most every :data:`MAP_CHECK_S`."""
        now = time.monotonic()
        if now >= self._next_map_check:
            self._next_map_check = now + MAP_CHECK_S
            await self._check_map()

    async def _check_map(self) -> None:
        key = file_stamp(self.map_path)
        if key == self._map_key:
            return
        self._map_key = key
        if key is None:
            self.map, self.map_version = None, ""
            exists = os.path.lexists(self.map_path)
            self.map_error = f"map {self.map_path}: cannot be read" if exists else "no map yet"
            return
        loop = asyncio.get_running_loop()
        try:
            plan = await loop.run_in_executor(self.executor, _load_plan, self.map_path)
        except (MapError, OSError) as exc:
            self.map, self.map_error = None, str(exc)[:300]
        else:
            self.map, self.map_error = plan, ""
        self.map_version = "-".join(str(k) for k in key)


async def _exchange(conn: Connection, req: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Send one request line, read its reply line (a NaN from an older daemon is null)."""
    reader, writer = conn
    writer.write((json.dumps(req) + "\n").encode())
    await writer.drain()
    line = await asyncio.wait_for(reader.readline(), timeout)
    if not line:
        raise ConnectionError("the daemon closed the connection without a reply")
    reply: dict[str, Any] = json.loads(line, parse_constant=_null)
    return reply


def _load_plan(path: Path) -> dict[str, Any]:
    return map_plan(load_map(path))


def _null(constant: str) -> None:
    """NaN or an infinity from a daemon that still sends them: no number (null)."""
    return None
