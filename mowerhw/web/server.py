"""The status page's web server (aiohttp, its own process; see :mod:`mowerhw.web`).

=====================  ==========================================================  =========
route                  what                                                        token
=====================  ==========================================================  =========
``GET /``              the page (``static/``: HTML, JS, CSS; no build, no CDN)     no
``GET /api/status``    the newest ``live`` update (JSON)                           no
``GET /api/map``       the map's plan view (:func:`.plan.map_plan`)                no
``GET /ws``            WebSocket: ``hello``, then a ``live`` update per poll        no
``POST /api/command``  ``{"cmd": "mow", "areas": [...]}`` (:mod:`.commands`)        yes
=====================  ==========================================================  =========

Each browser has its own sender that always sends the newest update and skips the ones it
was too slow for; one that does not take an update in 2 s is closed. Requests are validated
before anything else happens; every refusal is a JSON ``{"ok": false, "error": ...}``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from mowerhw.common.unreachable import unreachable
from mowerhw.config import EX_CONFIG, Config, WebConfig
from mowerhw.web.commands import CONTROLS, MAX_BODY_BYTES, CommandError, parse_command
from mowerhw.web.feed import DaemonFeed
from mowerhw.web.token import TokenError, load_or_create_token, token_matches

log = logging.getLogger("mowerhw.web")

#: files the page is made of (nothing else is served from the package)
STATIC = {
    "index.html": "text/html",
    "app.js": "text/javascript",
    "style.css": "text/css",
}
#: a browser that does not take an update within this long is closed (s)
SEND_TIMEOUT_S = 2.0
#: the page's commands, all browsers together, at most this many a second
COMMANDS_PER_S = 5
#: the largest WebSocket message a browser may send (it has nothing to say but pings)
MAX_WS_MESSAGE = 1024
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; connect-src 'self'; img-src 'self' data:; "
    "frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class WebServer:
    """The page for the daemon the config describes."""

    def __init__(self, config: Config, token: str, token_file: Path) -> None:
        self.cfg: WebConfig = config.web
        self.token, self.token_file = token, token_file
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="web-map")
        self.feed = DaemonFeed(
            config.runtime.control_socket,
            config.map.path,
            self.cfg.rate_hz,
            self.cfg.trajectory_points,
            self._executor,
        )
        self.clients: set[web.WebSocketResponse] = set()
        self.counts = {
            "browsers_total": 0,
            "browsers_refused": 0,
            "slow_browsers_closed": 0,
            "updates_sent": 0,
            "commands": 0,
            "commands_refused": 0,
        }
        self._command_times: deque[float] = deque()
        self._runner: web.AppRunner | None = None
        self._feed_task: asyncio.Task[None] | None = None
        self.foxglove: Any = None
        self.url = ""

    # ------------------------------------------------------------------------ lifecycle

    def app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_BODY_BYTES, middlewares=[self._guard])
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/api/status", self._status)
        app.router.add_get("/api/map", self._map)
        app.router.add_get("/ws", self._ws)
        app.router.add_post("/api/command", self._command)
        return app

    async def start(self) -> str:
        """Serve; the page's URL (with the port taken when ``web.port`` is 0)."""
        if self.cfg.foxglove:
            from mowerhw.web.foxglove_live import FoxgloveLive

            self.foxglove = FoxgloveLive(self.cfg.foxglove_host, self.cfg.foxglove_port)
            self.feed.always = True
            self.feed.on_update.append(self.foxglove.publish)
        self._feed_task = asyncio.create_task(self.feed.run(), name="web-feed")
        self._runner = web.AppRunner(
            self.app(), access_log=None, handle_signals=False, shutdown_timeout=1.0
        )
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.cfg.host, self.cfg.port, reuse_address=True)
        await site.start()
        port = self.cfg.port
        sockets = getattr(site._server, "sockets", None)  # the port when 0 was asked for
        if sockets:
            port = int(sockets[0].getsockname()[1])
        host = self.cfg.host if ":" not in self.cfg.host else f"[{self.cfg.host}]"
        self.url = f"http://{host}:{port}/"
        log.info(
            "web: status page on %s (controls need the token in %s)", self.url, self.token_file
        )
        return self.url

    async def close(self) -> None:
        if self._feed_task is not None:
            self.feed.stop()
            self._feed_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, TimeoutError):
                await asyncio.wait_for(self._feed_task, 2.0)
        for ws in list(self.clients):  # a browser that does not answer the close: 1 s
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(), 1.0)
        if self._runner is not None:
            await self._runner.cleanup()
        if self.foxglove is not None:
            self.foxglove.close()
        self._executor.shutdown(wait=False, cancel_futures=True)

    # --------------------------------------------------------------------------- routes

    @web.middleware
    async def _guard(self, request: web.Request, handler: Any) -> web.StreamResponse:
        """Security headers on every answer; API errors as JSON; a handler's bug is a 500
        naming it, never the end of the process."""
        try:
            resp: web.StreamResponse = await handler(request)
        except web.HTTPException as exc:
            if not request.path.startswith("/api/"):
                raise
            resp = _error(exc.status, f"{exc.reason}: {request.method} {request.path[:80]}")
        except Exception as exc:
            log.exception("web: %s %s failed", request.method, request.path[:80])
            resp = _error(500, f"internal error ({type(exc).__name__})")
        if not resp.prepared:
            resp.headers.update(SECURITY_HEADERS)
        return resp

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return self._file("index.html")

    async def _static(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        if name not in STATIC:
            raise web.HTTPNotFound()
        return self._file(name)

    @staticmethod
    def _file(name: str) -> web.Response:
        body = resources.files("mowerhw.web").joinpath("static", name).read_bytes()
        return web.Response(body=body, content_type=STATIC[name], charset="utf-8")

    async def _status(self, request: web.Request) -> web.StreamResponse:
        await self.feed.refresh()
        return web.json_response(self.update(), dumps=_dumps)

    async def _map(self, request: web.Request) -> web.StreamResponse:
        feed = self.feed
        await feed.refresh()
        if feed.map is None:
            return _error(404, feed.map_error or "no map yet")
        return web.json_response(
            {"ok": True, "version": feed.map_version, **feed.map}, dumps=_dumps
        )

    def update(self, index: int | None = None) -> dict[str, Any]:
        """The message a browser gets: the daemon's newest ``live`` reply, the trajectory
        from ``index`` (none when ``None``), and the page's own figures."""
        feed = self.feed
        out: dict[str, Any] = {
            "type": "live",
            "ok": not feed.error,
            "error": feed.error,
            "daemon": feed.latest,
            "session": feed.session,
            "map_version": feed.map_version,
            "map_error": feed.map_error,
            "polls": feed.polls,
            "browsers": len(self.clients),
        }
        if index is not None:
            start, pts = feed.points_since(index)
            out["trajectory"] = {"from": start, "points": pts, "total": feed.total}
        return out

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        if len(self.clients) >= self.cfg.max_clients:
            self.counts["browsers_refused"] += 1
            return _error(503, f"too many browsers (at most {self.cfg.max_clients}); try later")
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=MAX_WS_MESSAGE)
        await ws.prepare(request)
        self.clients.add(ws)
        self.counts["browsers_total"] += 1
        self.feed.watch()
        sender = asyncio.create_task(self._send_updates(ws), name="web-browser")
        try:
            async for msg in ws:  # the browser has nothing to say; reading sees it close
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
            self.clients.discard(ws)
            self.feed.unwatch()
        return ws

    async def _send_updates(self, ws: web.WebSocketResponse) -> None:
        hello = {
            "type": "hello",
            "rate_hz": self.cfg.rate_hz,
            "controls": list(CONTROLS),
            "token_hint": f"the token is in {self.token_file} on the mower",
        }
        try:
            await ws.send_str(_dumps(hello))
            await self._updates(ws)
        except (ConnectionError, RuntimeError):
            return  # the browser went away
        except Exception:  # a bug: that browser is told (1011) and closed, the page goes on
            log.exception("web: sending to a browser failed")
            await ws.close(code=1011, message=b"internal error")

    async def _updates(self, ws: web.WebSocketResponse) -> None:
        """One browser's updates: the newest one each time, until it goes away."""
        seen, session, index, landmarks = -1, None, 0, -1
        feed = self.feed
        while not ws.closed:
            await feed.wait_update(seen, timeout=5.0)
            seen = feed.version
            if feed.session != session:  # a new drive: the whole trajectory again
                session, index, landmarks = feed.session, 0, -1
            msg = self.update(index)
            index = msg["trajectory"]["total"]
            if feed.landmarks_version != landmarks:
                landmarks = feed.landmarks_version
                msg["landmarks"] = feed.landmarks
            try:
                await asyncio.wait_for(ws.send_str(_dumps(msg)), SEND_TIMEOUT_S)
            except (TimeoutError, ConnectionError, RuntimeError):
                self.counts["slow_browsers_closed"] += 1
                await ws.close()
                return
            self.counts["updates_sent"] += 1

    async def _command(self, request: web.Request) -> web.StreamResponse:
        """A control: size, then the token, then the pace, then the request itself."""
        self.counts["commands"] += 1
        length = request.content_length
        if length is not None and length > MAX_BODY_BYTES:
            return self._refuse(413, f"request of {length} bytes; at most {MAX_BODY_BYTES} allowed")
        body = await request.content.read(MAX_BODY_BYTES + 1)
        if len(body) > MAX_BODY_BYTES:
            return self._refuse(413, f"request over {MAX_BODY_BYTES} bytes")
        auth = request.headers.get("Authorization", "")
        scheme, _, given = auth.partition(" ")
        if not auth:
            return self._refuse(
                401,
                "controls need the token: send 'Authorization: Bearer <token>' (the token is "
                f"in {self.token_file} on the mower); the status is readable without it",
            )
        if scheme.lower() != "bearer" or not token_matches(given.strip(), self.token):
            log.warning("web: a control request with a wrong token from %s", request.remote)
            return self._refuse(403, "wrong token")
        now = time.monotonic()
        while self._command_times and now - self._command_times[0] > 1.0:
            self._command_times.popleft()
        if len(self._command_times) >= COMMANDS_PER_S:
            return self._refuse(429, f"at most {COMMANDS_PER_S} commands a second")
        self._command_times.append(now)
        try:
            req = parse_command(body)
        except CommandError as exc:
            return self._refuse(400, str(exc))
        try:
            reply = await self.feed.request(req)
        except (OSError, ConnectionError, TimeoutError, ValueError) as exc:
            return self._refuse(503, f"the daemon does not answer ({unreachable(exc)})")
        log.info(
            "web: %s from %s: %s",
            req["cmd"],
            request.remote,
            "done" if reply.get("ok") else reply.get("error"),
        )
        return web.json_response(reply, status=200 if reply.get("ok") else 409, dumps=_dumps)

    def _refuse(self, status: int, message: str) -> web.Response:
        self.counts["commands_refused"] += 1
        return _error(status, message)


def _error(status: int, message: str) -> web.Response:
    return web.json_response({"ok": False, "error": message}, status=status, dumps=_dumps)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, allow_nan=False, separators=(",", ":"))


# ------------------------------------------------------------------------------ process


async def serve(config: Config, ready: Any = None) -> None:
    """Serve until cancelled (or SIGTERM in :func:`web_main`)."""
    token, path = load_or_create_token(config.web.token_file)
    server = WebServer(config, token, path)
    url = await server.start()
    if ready is not None:
        ready(url)
    try:
        await asyncio.Event().wait()
    finally:
        await server.close()


def web_main(config: Config, log_level: int) -> None:
    """Serve the page in this process until SIGTERM (``mowerhw web``; the supervisor's child
    :func:`mowerhw.supervisor.web_child.web_child_main`)."""
    import os
    import signal

    os.environ.pop("NOTIFY_SOCKET", None)
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, config.web.nice)

    async def main() -> None:
        task = asyncio.current_task()
        assert task is not None
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, task.cancel)
        await serve(config)

    try:
        asyncio.run(main())
    except (asyncio.CancelledError, KeyboardInterrupt):
        pass
    except (TokenError, OSError) as exc:  # the token file, or the address is taken
        log.error("web: cannot serve the status page: %s", exc)
        raise SystemExit(EX_CONFIG) from None
