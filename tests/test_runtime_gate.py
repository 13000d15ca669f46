"""The fail-safe permit decision and the control socket protocol (mowerhw.runtime)."""

from __future__ import annotations

import asyncio
import json
import logging

import pytest

from mowerhw.mow.containment import ContainmentResult
from mowerhw.mow.gate import PermitGate
from mowerhw.runtime.control import ControlServer
from mowerhw.runtime.control_protocol import parse_request, request

LIMITS = {"imu": 0.1, "speed": 0.3, "camera": 1.0}
FRESH = {"imu": 10.0, "speed": 10.0, "camera": 10.0}
INSIDE = ContainmentResult("INSIDE", True, 2.0, 0.01, "", "", 10.0)


def test_permits_only_when_every_condition_holds() -> None:
    gate = PermitGate(LIMITS)
    assert gate.decide(10.0, "mow", FRESH, INSIDE).permit
    cases = {
        "SHUTTING_DOWN": dict(shutting_down=True),
        "NOT_MOWING": dict(mode="teach"),
        "MAP_INVALID": dict(map_problem="lawn.json: not valid JSON"),
        "SENSOR_STALE": dict(last={"imu": 9.85, "speed": 10.0, "camera": 10.0}),
        "FAULT": dict(fault="estimator raised"),
        "NOT_LOCALIZED": dict(containment=None),
    }
    for reason, kw in cases.items():
        d = gate.decide(
            10.0,
            kw.get("mode", "mow"),
            kw.get("last", FRESH),
            kw.get("containment", INSIDE),
            kw.get("map_problem", ""),
            kw.get("fault", ""),
            kw.get("shutting_down", False),
        )
        assert not d.permit and d.reason == reason, (reason, d)
    outside = ContainmentResult("OUTSIDE", False, -0.2, 0.01, "OUTSIDE", "past the edge", 10.0)
    assert gate.decide(10.0, "mow", FRESH, outside).reason == "OUTSIDE"
    nan = ContainmentResult("INSIDE", True, float("nan"), 0.01, "", "", 10.0)
    assert not gate.decide(10.0, "mow", FRESH, nan).permit  # a NaN never permits


def test_each_stream_goes_stale_at_its_own_limit() -> None:
    gate = PermitGate(LIMITS)
    for name, limit in LIMITS.items():
        last = dict(FRESH)
        last[name] = 10.0 - limit - 1e-3
        d = gate.decide(10.0, "mow", last, INSIDE)
        assert d.reason == "SENSOR_STALE" and name in d.detail
        last[name] = 10.0 - limit + 1e-3
        assert gate.decide(10.0, "mow", last, INSIDE).permit
    assert gate.decide(10.0, "mow", {"imu": 10.0}, INSIDE).detail == "no speed data yet"


def test_each_change_is_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    gate = PermitGate(LIMITS)
    caplog.set_level(logging.INFO, logger="mowerhw.permit")
    for _ in range(5):
        gate.decide(10.0, "mow", FRESH, INSIDE)
    for _ in range(5):
        gate.decide(10.0, "mow", FRESH, None)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2, lines
    assert lines[0].startswith("PERMIT") and lines[1].startswith("HALT NOT_LOCALIZED")


@pytest.mark.parametrize(
    ("line", "error"),
    [
        (b"{not json\n", "not valid JSON"),
        (b"[1, 2]\n", "must be a JSON object"),
        (b'{"command": "status"}\n', 'needs "cmd"'),
        (b"explode\n", "unknown command 'explode'; allowed: status"),
        (b"\n", "empty request"),
    ],
)
def test_malformed_requests_are_named(line: bytes, error: str) -> None:
    with pytest.raises(ValueError, match=error.replace("(", r"\(")):
        parse_request(line)
    assert parse_request(b"save-map /tmp/x.json\n") == ("save-map", {"args": ["/tmp/x.json"]})
    assert parse_request(b'{"cmd": "fault", "kind": "nan"}') == ("fault", {"kind": "nan"})


def test_control_server_answers_errors_and_keeps_serving(tmp_path) -> None:
    path = tmp_path / "ctl.sock"

    async def handler(cmd, args):
        if cmd == "mow":
            raise RuntimeError("boom")
        return {"ok": True, "cmd": cmd}

    async def main() -> list:
        server = ControlServer(path, handler, mode=0o660)
        await server.start()
        assert oct(path.stat().st_mode & 0o777) == "0o660"
        loop = asyncio.get_running_loop()
        replies = []
        reader, writer = await asyncio.open_unix_connection(str(path))
        for line in (b"garbage{\n", b"\xff\xfe\n", b'{"cmd": "mow"}\n', b"status\n"):
            writer.write(line)
            await writer.drain()
            replies.append(json.loads(await reader.readline()))
        writer.close()
        # a blocking client (the CLI's) in a thread
        replies.append(await loop.run_in_executor(None, request, path, "idle"))
        await server.close()
        return replies

    r = asyncio.run(main())
    assert r[0]["ok"] is False and "unknown command" in r[0]["error"]
    assert r[1]["ok"] is False
    assert r[2] == {"ok": False, "error": "mow failed: boom"}
    assert r[3] == {"ok": True, "cmd": "status"}
    assert r[4] == {"ok": True, "cmd": "idle"}
    assert not path.exists()


def test_sd_notify_speaks_the_protocol(tmp_path, monkeypatch) -> None:
    import os
    import socket

    from mowerhw.runtime.sdnotify import Notifier

    path = tmp_path / "notify.sock"
    rx = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    rx.bind(str(path))
    rx.settimeout(1.0)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    n = Notifier()
    assert n.enabled and n.watchdog_period_s == 0.5
    assert n.ready("mow: INSIDE, mowing permitted")
    assert rx.recv(4096) == b"READY=1\nSTATUS=mow: INSIDE, mowing permitted"
    assert n.watchdog()
    assert rx.recv(4096) == b"WATCHDOG=1"
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not Notifier().ready()  # outside systemd: nothing, no error
