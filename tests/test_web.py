"""The status page's process (issue 19) against a daemon's control socket: the real
:class:`ControlServer` answering ``live`` like the daemon, the real aiohttp server, real
HTTP, WebSocket and Foxglove WebSocket clients. The page in Chromium against the real
daemon is in ``test_web_page.py``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import stat
import struct
from dataclasses import replace
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from mowerhw.config import Config
from mowerhw.runtime.control import ControlServer
from mowerhw.supervisor.status_socket import StatusSocket
from mowerhw.web.commands import CommandError, parse_command
from mowerhw.web.server import WebServer
from mowerhw.web.token import TokenError, load_or_create_token

TOKEN = "t" * 20 + "-secret"


class FakeDaemon:
    """Answers ``live`` as the daemon does (a mower driving east at 0.5 m/s, 5 points a
    second) and records the commands it gets."""

    def __init__(self) -> None:
        self.t = 0.0
        self.commands: list[tuple[str, dict[str, Any]]] = []
        self.lives = 0
        self.run = "run1"
        #: what the permit supervisor last said (None: a daemon without one)
        self.supervisor: dict[str, Any] | None = None

    async def handle(self, cmd: str, args: dict[str, Any]) -> dict[str, Any]:
        if cmd != "live":
            self.commands.append((cmd, args))
            return {"ok": True, "mode": cmd}
        self.lives += 1
        self.t += 0.1
        n = int(self.t / 0.2)
        since = args.get("since", 0)
        pts = [[0.2 * k, 0.1 * k, 0.0] for k in range(since, n)]
        x = 0.5 * self.t
        extra = {} if self.supervisor is None else {"supervisor": dict(self.supervisor)}
        return {
            **extra,
            "ok": True,
            "run": self.run,
            "epoch": 1,
            "now": round(self.t, 3),
            "mode": "mow",
            "permit": True,
            "state": "INSIDE",
            "reason": "NONE",
            "detail": "",
            "signed_distance_m": 1.0,
            "sensors": {"imu": {"age_s": 0.004, "rate_hz": 100.0}},
            "pose": {
                "t": round(self.t, 3),
                "x": x,
                "y": 2.0,
                "z": 0.3,
                "heading": 0.0,
                "q_wxyz": [1.0, 0.0, 0.0, 0.0],
                "cov_xy": [[1e-4, 0.0], [0.0, 1e-4]],
                "sigma_heading": 0.001,
                "sigma_xy_m": 0.01,
                "covariance": [0.0] * 36,
            },
            "trajectory": {"from": min(since, n), "points": pts},
            "map_problem": "",
            "fault": "",
        }


def _config(tmp_path: Path, **web: Any) -> Config:
    cfg = Config()
    rt = replace(cfg.runtime, control_socket=tmp_path / "control.sock")
    w = replace(cfg.web, enabled=True, port=0, token_file=tmp_path / "web-token", **web)
    return replace(cfg, runtime=rt, web=w, map=replace(cfg.map, path=tmp_path / "none.json"))


async def _with_page(tmp_path: Path, body: Any, **web: Any) -> Any:
    cfg = _config(tmp_path, **web)
    daemon = FakeDaemon()
    control = ControlServer(cfg.runtime.control_socket, daemon.handle)
    await control.start()
    server = WebServer(cfg, TOKEN, cfg.web.token_file)
    url = await server.start()
    try:
        return await asyncio.wait_for(body(url, server, daemon), 30.0)
    except TimeoutError:
        for task in asyncio.all_tasks():
            task.print_stack()
        raise
    finally:
        await server.close()
        await control.close()


# ------------------------------------------------------------------------------ requests


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (b'{"cmd": "idle",', "not valid JSON"),
        (b"[1, 2]", "must be a JSON object"),
        (b'{"cmd": "save-map"}', "unknown command 'save-map'; allowed: teach, mow, idle"),
        (b'{"cmd": "fault", "args": ["nan"]}', "unknown command 'fault'"),
        (b'{"cmd": "mow", "areas": "front"}', "areas: a list"),
        (b'{"cmd": "idle", "areas": ["a"]}', "areas: only with mow"),
        (b'{"cmd": "idle", "cmd": "mow"}', "appears twice"),
        (b'{"cmd": "mow", "x": NaN}', "NaN is not a number"),
        (b'{"cmd": "idle", "x": 1}', "unknown field 'x'"),
        (b"\xff\xfe", "not UTF-8"),
        (b'{"cmd": "idle", "pad": "' + b"A" * 2000 + b'"}', "at most 1024 allowed"),
    ],
)
def test_malformed_control_requests_are_refused_by_name(body: bytes, message: str) -> None:
    with pytest.raises(CommandError, match=message.replace("(", r"\(").replace("[", r"\[")):
        parse_command(body)


def test_allowed_control_requests() -> None:
    assert parse_command(b'{"cmd": "finish-teach"}') == {"cmd": "finish-teach"}
    assert parse_command(b'{"cmd": "mow", "areas": ["front", "back"]}') == {
        "cmd": "mow",
        "areas": ["front", "back"],
    }


def test_the_token_file_is_created_private_and_reused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("CREDENTIALS_DIRECTORY", raising=False)
    path = tmp_path / "state" / "web-token"
    token, where = load_or_create_token(path)
    assert where == path and len(token) >= 32
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert load_or_create_token(path)[0] == token
    path.chmod(0o644)
    with pytest.raises(TokenError, match="lets others read it"):
        load_or_create_token(path)
    # a systemd credential wins over the file
    creds = tmp_path / "creds"
    creds.mkdir()
    (creds / "web-token").write_text("c" * 24 + "\n")
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(creds))
    assert load_or_create_token(path) == ("c" * 24, creds / "web-token")


# ---------------------------------------------------------------------------- the server


def test_controls_need_the_token_and_bad_requests_never_reach_the_daemon(tmp_path) -> None:
    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> dict[str, Any]:
        out: dict[str, Any] = {}
        good = {"Authorization": f"Bearer {TOKEN}"}
        cases = {
            "no token": ({}, b'{"cmd": "idle"}'),
            "bad token": ({"Authorization": "Bearer wrong"}, b'{"cmd": "idle"}'),
            "not bearer": ({"Authorization": f"Basic {TOKEN}"}, b'{"cmd": "idle"}'),
            "malformed": (good, b'{"cmd": "idle",'),
            "unknown": (good, b'{"cmd": "save-map"}'),
            "oversized": (good, b'{"cmd": "idle", "x": "' + b"A" * 5000 + b'"}'),
        }
        async with aiohttp.ClientSession() as s:
            for name, (headers, data) in cases.items():
                async with s.post(url + "api/command", headers=headers, data=data) as r:
                    out[name] = (r.status, await r.json())
            assert daemon.commands == []  # none got through
            async with s.post(url + "api/command", headers=good, json={"cmd": "idle"}) as r:
                out["good"] = (r.status, await r.json())
            async with s.get(url + "api/status") as r:  # read-only: no token needed
                out["status"] = (r.status, await r.json())
            async with s.get(url + "api/nothing") as r:
                out["unknown route"] = (r.status, await r.json())
            async with s.get(url + "static/../../config.py") as r:
                out["traversal"] = r.status
            async with s.get(url) as r:
                out["page"] = (r.status, r.headers.get("Content-Security-Policy", ""))
        out["commands"] = list(daemon.commands)
        return out

    out = asyncio.run(_with_page(tmp_path, body))
    for name in ("no token", "bad token", "not bearer", "malformed", "unknown", "oversized"):
        assert out[name][1]["ok"] is False and out[name][1]["error"], name
    assert out["no token"][0] == 401 and "Authorization: Bearer" in out["no token"][1]["error"]
    assert out["bad token"] == (403, {"ok": False, "error": "wrong token"})
    assert out["not bearer"][0] == 403
    assert out["malformed"][0] == 400 and "not valid JSON" in out["malformed"][1]["error"]
    assert out["unknown"][0] == 400 and "allowed: teach, mow, idle" in out["unknown"][1]["error"]
    assert out["oversized"][0] == 413
    assert out["good"] == (200, {"ok": True, "mode": "idle"})
    assert out["commands"] == [("idle", {})]
    assert out["status"][0] == 200 and out["status"][1]["type"] == "live"
    assert out["unknown route"][0] == 404 and out["unknown route"][1]["ok"] is False
    assert out["traversal"] == 404
    assert out["page"][0] == 200 and "default-src 'self'" in out["page"][1]


def test_updates_at_the_rate_with_the_whole_trajectory_after_a_reconnect(tmp_path) -> None:
    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> dict[str, Any]:
        got: list[dict[str, Any]] = []
        async with aiohttp.ClientSession() as s:
            polls0 = server.feed.polls
            await asyncio.sleep(0.5)  # nobody watching: the daemon is not asked
            idle_polls = server.feed.polls - polls0
            async with s.ws_connect(url + "ws") as ws:
                hello = json.loads((await ws.receive(timeout=2)).data)
                t0 = asyncio.get_running_loop().time()
                while asyncio.get_running_loop().time() - t0 < 2.0:
                    got.append(json.loads((await ws.receive(timeout=2)).data))
            n_first = sum(len(m["trajectory"]["points"]) for m in got)
            await asyncio.sleep(0.3)
            async with s.ws_connect(url + "ws") as ws:  # a browser coming back
                await ws.receive(timeout=2)
                again = json.loads((await ws.receive(timeout=2)).data)
        return {
            "hello": hello,
            "got": got,
            "again": again,
            "n_first": n_first,
            "idle_polls": idle_polls,
        }

    out = asyncio.run(_with_page(tmp_path, body, rate_hz=10.0))
    assert out["idle_polls"] == 0
    assert out["hello"]["type"] == "hello" and "finish-teach" in out["hello"]["controls"]
    live = [m for m in out["got"] if m["daemon"]]
    assert 15 <= len(live) <= 25, len(live)  # 10 Hz for 2 s
    # the page shows what the daemon said: pose and state of its newest answer
    last = live[-1]["daemon"]
    assert last["state"] == "INSIDE" and last["permit"] is True
    assert last["pose"]["x"] == pytest.approx(0.5 * last["now"])
    # every point once, in order, then all of them again for a new connection
    idx = [p[0] for m in live for p in m["trajectory"]["points"]]
    assert idx == sorted(idx) and len(set(idx)) == len(idx) and out["n_first"] >= 5
    assert out["again"]["trajectory"]["from"] == 0
    assert len(out["again"]["trajectory"]["points"]) >= out["n_first"]


def test_a_browser_that_does_not_read_does_not_hold_up_another(tmp_path) -> None:
    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> dict[str, Any]:
        # a client that never reads: its socket buffers fill, its updates are skipped
        async with aiohttp.ClientSession() as s:
            stuck = await s.ws_connect(url + "ws", max_msg_size=0)
            stuck_transport = stuck._response.connection.transport  # type: ignore[union-attr]
            stuck_transport.pause_reading()
            async with s.ws_connect(url + "ws") as ws:
                n = 0
                t0 = asyncio.get_running_loop().time()
                while asyncio.get_running_loop().time() - t0 < 1.5:
                    msg = await ws.receive(timeout=2)
                    n += msg.type == aiohttp.WSMsgType.TEXT
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stuck.close(), 1.0)
        return {"n": n}

    out = asyncio.run(_with_page(tmp_path, body, rate_hz=10.0))
    assert out["n"] >= 10


#: what the permit supervisor's status socket says in the test of a daemon gone silent
SUPERVISOR_SAYS = {
    "ok": True,
    "permit": False,
    "reason": "ESTIMATOR_LATE",
    "detail": "no permit lease for 2.000 s",
    "estimation": {"pid": 7, "alive": True, "ready": True, "silent_s": 2.0},
}


def test_daemon_gone_is_said_on_the_page_and_it_comes_back(tmp_path) -> None:
    async def next_where(ws: Any, pred: Any) -> dict[str, Any] | None:
        for _ in range(60):
            m = json.loads((await ws.receive(timeout=3)).data)
            if m.get("type") == "live" and pred(m):
                return m
        return None

    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> dict[str, Any]:
        path = server.feed.socket_path
        # the permit supervisor's status socket, which the page asks when the daemon is silent
        supervisor = StatusSocket(path, 0o660)
        assert supervisor.open()

        async def serve() -> None:
            while True:
                supervisor.serve(lambda: SUPERVISOR_SAYS)
                await asyncio.sleep(0.01)

        serving = asyncio.create_task(serve())
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "ws") as ws:
            first = await next_where(ws, lambda m: m["ok"])
            os.unlink(path)  # the daemon goes away (its socket with it)
            server.feed._close()
            gone = await next_where(ws, lambda m: m["error"])
            serving.cancel()
            supervisor.close()
            both_gone = await next_where(ws, lambda m: "either" in m["error"])
            daemon.run = "run2"  # a new daemon on the same socket
            again = ControlServer(path, daemon.handle)
            await again.start()
            back = await next_where(ws, lambda m: m["ok"])
            await again.close()
            return {"first": first, "gone": gone, "back": back, "both_gone": both_gone}

    out = asyncio.run(_with_page(tmp_path, body))
    assert out["first"]["daemon"]["mode"] == "mow"
    assert out["gone"] is not None and "does not answer" in out["gone"]["error"]
    assert (  # and why the deck stopped, in the supervisor's words
        "; the permit supervisor holds the deck halted (ESTIMATOR_LATE: no permit lease for "
        "2.000 s); the estimation process (pid 7) has sent nothing for 2.0 s"
    ) in out["gone"]["error"]
    assert out["both_gone"] is not None
    assert (
        "the permit supervisor does not answer either (no such socket"
        in (out["both_gone"]["error"])
    )
    assert out["gone"]["daemon"] is not None  # the last known state stays on the page
    assert out["back"] is not None and out["back"]["session"] == "run2/1"
    assert out["back"]["trajectory"]["from"] == 0  # the new daemon's drive, from its start


@pytest.mark.slow
def test_the_page_shows_the_supervisors_own_halt(tmp_path) -> None:
    """The estimation side permits, the permit supervisor halts on its own (a tilt, a bump, a
    late estimator, its CAN address: it sends the frames): the page, in Chromium, says HALT
    with the supervisor's reason, and MOWING PERMITTED once the supervisor permits again."""
    from mowerhw.bench import browser

    why = browser.missing()
    if why:
        pytest.skip(f"the page's browser test needs {why}")
    read = """() => [document.body.dataset.permit].concat(
        ['permit', 'reason', 'detail'].map((id) => document.getElementById(id).textContent))"""

    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> Any:
        daemon.supervisor = {
            "permit": False,
            "reason": "TILTED",
            "detail": "tilted 45° (limit 35°), 0.0 s ago",
        }

        def look() -> tuple[Any, Any]:
            with browser.page(url) as pg:
                pg.wait_for_function("document.body.dataset.permit === 'false'", timeout=20_000)
                halted = pg.evaluate(read)
                daemon.supervisor = {"permit": True, "reason": "", "detail": ""}
                pg.wait_for_function("document.body.dataset.permit === 'true'", timeout=20_000)
                return halted, pg.evaluate(read)

        return await asyncio.get_running_loop().run_in_executor(None, look)

    halted, permitted = asyncio.run(_with_page(tmp_path, body))
    assert halted == [
        "false",
        "HALT",
        "TILTED",
        "permit supervisor: tilted 45° (limit 35°), 0.0 s ago",
    ]
    assert permitted[:3] == ["true", "MOWING PERMITTED", "–"]


# ------------------------------------------------------------------------- Foxglove live


def test_foxglove_live_serves_the_recordings_pose_and_state_topics(tmp_path) -> None:
    """A client of the Foxglove WebSocket protocol (``websockets``): advertise, subscribe,
    binary message data (opcode 1, subscription id, log time, JSON payload)."""
    websockets = pytest.importorskip("websockets", reason="websockets (test extra) is missing")
    from mowerhw.recording.mcap import TOPICS

    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> dict[str, Any]:
        port = server.foxglove.port
        got: dict[str, dict[str, Any]] = {}
        async with websockets.connect(
            f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]
        ) as ws:
            channels: dict[int, dict[str, Any]] = {}
            while not channels:
                msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
                if msg["op"] == "advertise":
                    channels = {c["id"]: c for c in msg["channels"]}
            subs = [{"id": k, "channelId": cid} for k, cid in enumerate(channels)]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            topic_of = {k: channels[cid]["topic"] for k, cid in enumerate(channels)}
            while len(got) < 2:
                data = await asyncio.wait_for(ws.recv(), 5)
                if isinstance(data, bytes) and data[0] == 1:
                    sub, _log_ns = struct.unpack_from("<IQ", data, 1)
                    got[topic_of[sub]] = json.loads(data[13:])
        return {"channels": channels, "got": got}

    out = asyncio.run(_with_page(tmp_path, body, foxglove=True, foxglove_port=0))
    adv = {c["topic"]: c for c in out["channels"].values()}
    assert set(adv) == {"/estimate/pose", "/estimate/state"}
    for topic, c in adv.items():  # the same schemas as a recording's channels
        assert c["schemaName"] == TOPICS[topic] and c["encoding"] == "json"
    pose, st = out["got"]["/estimate/pose"], out["got"]["/estimate/state"]
    assert pose["frame_id"] == "lawn" and pose["pose"]["position"]["y"] == 2.0
    assert pose["pose"]["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    assert st["state"] == "INSIDE" and st["permit"] is True and st["mode"] == "mow"
    assert st["sigma_xy_m"] == 0.01 and len(st["covariance"]) == 36


# ----------------------------------------------------------- the page's process, supervised


def _dies(config: Config, log_level: int) -> None:
    raise SystemExit(int(os.environ.get("MOWERHW_TEST_EXIT", "1")))


def test_a_dead_page_process_is_started_again_with_backoff_and_a_bad_config_is_not(
    tmp_path, monkeypatch
) -> None:
    from mowerhw.config import EX_CONFIG
    from mowerhw.web.process import WebProcess

    cfg = _config(tmp_path)
    web = WebProcess(cfg, _dies)
    web.start()
    web.proc.join(10.0)
    web.check(now=100.0)  # dead: restart in 1 s
    assert web.deaths == 1 and web.starts == 1
    web.check(now=100.5)
    assert web.starts == 1  # not yet
    web.check(now=101.1)
    assert web.starts == 2  # started again
    web.proc.join(10.0)
    web.check(now=102.2)  # dead again: the backoff doubled
    web.check(now=103.3)
    assert web.starts == 2
    web.check(now=104.3)
    assert web.starts == 3 and web.deaths == 2
    monkeypatch.setenv("MOWERHW_TEST_EXIT", str(EX_CONFIG))
    bad = WebProcess(cfg, _dies)
    bad.start()
    bad.proc.join(10.0)
    bad.check(now=200.0)
    bad.check(now=300.0)
    assert bad.given_up and bad.starts == 1 and not bad.status()["alive"]


def test_an_oversized_websocket_message_closes_that_browser_only(tmp_path) -> None:
    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> dict[str, Any]:
        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(url + "ws") as bad,
            s.ws_connect(url + "ws") as good,
        ):
            await bad.receive(timeout=2)
            await bad.send_str("x" * 5000)  # the page's WebSocket takes at most 1 KiB
            closed = None
            for _ in range(50):
                msg = await bad.receive(timeout=2)
                if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                    closed = bad.close_code
                    break
            n = 0
            for _ in range(5):
                n += (await good.receive(timeout=2)).type == aiohttp.WSMsgType.TEXT
        return {"closed": closed, "n": n}

    out = asyncio.run(_with_page(tmp_path, body))
    assert out["closed"] == 1009  # "message too big"
    assert out["n"] == 5


def test_live_replies_are_strict_json_before_the_first_imu_sample() -> None:
    """Found by the browser test: the localizer's pose time is NaN until the first IMU
    sample; a `live` reply then carried it, and the page's sender died on it."""
    import numpy as np

    from mowerhw.runtime.control import _encode
    from mowerhw.runtime.live import _pose_json
    from mowerhw.runtime.pipelines import PlanPose

    pose = PlanPose(float("nan"), np.array([1.0, 2.0, 0.3]), np.array([1.0, 0, 0, 0]), None)
    out = _pose_json(pose)
    assert out["t"] is None and out["x"] == 1.0
    json.dumps(out, allow_nan=False)
    wire = _encode({"ok": True, "a": float("nan"), "b": [float("inf"), 1.5]})
    assert json.loads(wire) == {"ok": True, "a": None, "b": [None, 1.5]}


def test_a_plain_status_request_asks_the_daemon_with_no_browser_open(tmp_path, map_file) -> None:
    async def body(url: str, server: WebServer, daemon: FakeDaemon) -> dict[str, Any]:
        server.feed.map_path = map_file
        async with aiohttp.ClientSession() as s:
            async with s.get(url + "api/status") as r:
                status = await r.json()
            lives = daemon.lives  # before /api/map, which asks again when a period has passed
            async with s.get(url + "api/map") as r:
                plan = (r.status, await r.json())
        return {"status": status, "plan": plan, "lives": lives}

    out = asyncio.run(_with_page(tmp_path, body))
    assert out["status"]["ok"] and out["status"]["daemon"]["state"] == "INSIDE"
    assert out["lives"] == 1  # asked once, for this request
    code, plan = out["plan"]
    assert code == 200 and plan["mow_areas"] and len(plan["landmarks"]) == 6
    assert plan["areas"][0]["kind"] == "mow" and len(plan["areas"][0]["polygon"]) == 80


def test_trajectory_points_since_an_index_with_the_oldest_dropped() -> None:
    """The daemon's buffer and the page's keep the newest points; a caller gets the points
    from its index on, or from the oldest kept."""
    from mowerhw.runtime.live import LiveView
    from mowerhw.web.feed import DaemonFeed

    async def feed_points() -> list[Any]:
        f = DaemonFeed("/nowhere", "/nowhere", max_points=5)
        for k in range(8):
            f.points.append((k, k, k))
            f.total += 1
        return [f.points_since(i) for i in (0, 7, 8)]

    view = LiveView(max_points=5)
    for k in range(8):  # as sample() appends them
        view._points.append((k, k, k))
        view._total += 1
    pts = [(k, k, k) for k in range(8)]
    assert view.trajectory_since(0) == (3, pts[3:])
    assert view.trajectory_since(6) == (6, pts[6:])
    assert view.trajectory_since(8) == view.trajectory_since(100) == (8, [])
    assert asyncio.run(feed_points()) == [(3, pts[3:]), (7, pts[7:]), (8, [])]
