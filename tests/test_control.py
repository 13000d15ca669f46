"""The control socket as an attacker and a careless user would use it (issue 16): pipelined
floods, too many or idle clients, nested and duplicate-key JSON, unauthorised peers, paths
outside the map directory, a second daemon on the same socket."""

from __future__ import annotations

import asyncio
import json
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mowerhw.runtime import control_protocol as control
from mowerhw.runtime.commands import map_save_path
from mowerhw.runtime.control import ControlServer
from mowerhw.runtime.control_access import (
    ControlPolicy,
    ControlSocketBusy,
    Peer,
    claim_control_socket,
)
from mowerhw.runtime.control_protocol import parse_request


async def _echo(cmd: str, args: dict[str, Any]) -> dict[str, Any]:
    return {"ok": True, "cmd": cmd}


async def _readline(reader: asyncio.StreamReader, timeout: float = 5.0) -> dict[str, Any]:
    line = await asyncio.wait_for(reader.readline(), timeout)
    reply: dict[str, Any] = json.loads(line)
    return reply


def test_a_pipelined_flood_is_answered_at_the_clients_rate(tmp_path: Path) -> None:
    """Thousands of requests in one write: answered one per turn, at most
    ``requests_per_s`` a second, while the loop keeps running other work."""
    calls: list[float] = []
    ticks = [0]

    async def handler(cmd: str, args: dict[str, Any]) -> dict[str, Any]:
        calls.append(asyncio.get_running_loop().time())
        return {"ok": True}

    async def main() -> None:
        server = ControlServer(
            tmp_path / "c.sock", handler, policy=ControlPolicy(requests_per_s=20)
        )
        await server.start()

        async def ticker() -> None:
            while True:
                ticks[0] += 1
                await asyncio.sleep(0.005)

        t = asyncio.create_task(ticker())
        _reader, writer = await asyncio.open_unix_connection(str(tmp_path / "c.sock"))
        writer.write(b"status\n" * 2000 + b"\n" * 2000 + b"explode\n" * 500)
        await writer.drain()
        await asyncio.sleep(0.5)
        t.cancel()
        writer.close()
        await server.close()

    asyncio.run(main())
    # 20 a second: at most 11 in 0.5 s, however many were sent; the ticker ran throughout
    assert 1 <= len(calls) <= 12
    assert ticks[0] >= 50


def test_too_many_clients_are_told_so_and_idle_ones_are_closed(tmp_path: Path) -> None:
    path = tmp_path / "c.sock"

    async def main() -> tuple[list[dict[str, Any]], bytes, dict[str, int]]:
        server = ControlServer(path, _echo, policy=ControlPolicy(max_clients=3, idle_s=0.3))
        await server.start()
        conns = [await asyncio.open_unix_connection(str(path)) for _ in range(3)]
        await asyncio.sleep(0.05)
        extra = []
        for _ in range(2):
            reader, writer = await asyncio.open_unix_connection(str(path))
            extra.append(await _readline(reader))
            writer.close()
        # the three idle ones are closed after idle_s
        reader0 = conns[0][0]
        eof = await asyncio.wait_for(reader0.read(), 3.0)
        # and then a new client is served again
        reader, writer = await asyncio.open_unix_connection(str(path))
        writer.write(b"status\n")
        extra.append(await _readline(reader))
        writer.close()
        status = server.status()
        await server.close()
        return extra, eof, status

    extra, eof, status = asyncio.run(main())
    assert extra[0] == {"ok": False, "error": "too many clients (at most 3); try again later"}
    assert extra[1]["ok"] is False
    assert extra[2] == {"ok": True, "cmd": "status"}
    assert eof == b""
    assert status["refused_clients"] == 2


def test_idle_connections_make_room_for_a_client_with_a_request(tmp_path: Path) -> None:
    path = tmp_path / "c.sock"

    async def main() -> tuple[dict[str, Any], dict[str, int]]:
        server = ControlServer(path, _echo, policy=ControlPolicy(max_clients=2, idle_s=60))
        await server.start()
        idle = [await asyncio.open_unix_connection(str(path)) for _ in range(2)]
        await asyncio.sleep(1.2)  # idle for longer than a second: they may be evicted
        reader, writer = await asyncio.open_unix_connection(str(path))
        writer.write(b"status\n")
        reply = await _readline(reader)
        writer.close()
        status = server.status()
        for _, w in idle:
            w.close()
        await server.close()
        return reply, status

    reply, status = asyncio.run(main())
    assert reply == {"ok": True, "cmd": "status"}
    assert status["evicted_clients"] == 1 and status["refused_clients"] == 0


@pytest.mark.parametrize(
    ("line", "error"),
    [
        (b"[" * 100_000 + b"\n", "request of 100001 bytes; at most 4096"),
        (b'{"cmd": ' + b"[" * 50 + b"\n", "request nested 51 deep; at most 2"),
        (b'{"cmd": "status", "cmd": "mow"}\n', "the key 'cmd' appears twice in one object"),
        (b'{"cmd": "save-map", "args": "abc"}\n', 'argument "args" must be a list'),
        (b'{"cmd": "mow", "x": {"y": 1}}\n', "argument 'x': must be a string"),
        (b"\xff\xfe\n", "can't decode"),
    ],
)
def test_hostile_requests_are_refused_by_name(line: bytes, error: str) -> None:
    with pytest.raises(ValueError, match=error.replace("[", r"\[").replace("(", r"\(")):
        parse_request(line)


def test_an_oversized_line_ends_the_connection_with_an_error(tmp_path: Path) -> None:
    path = tmp_path / "c.sock"

    async def main() -> tuple[dict[str, Any], bytes]:
        server = ControlServer(path, _echo)
        await server.start()
        reader, writer = await asyncio.open_unix_connection(str(path))
        writer.write(b"x" * 20_000)
        await writer.drain()
        reply = await _readline(reader)
        try:  # closed with unread bytes: a reset, or an end of file
            rest = await asyncio.wait_for(reader.read(), 3.0)
        except ConnectionResetError:
            rest = b""
        writer.close()
        await server.close()
        return reply, rest

    reply, rest = asyncio.run(main())
    assert reply == {"ok": False, "error": "request line over 4096 bytes"}
    assert rest == b""


def test_commands_that_change_the_mower_need_an_authorised_peer(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "c.sock"
    monkeypatch.setattr(Peer, "of", classmethod(lambda cls, conn: cls(4242, 54321, 54321)))

    async def main() -> list[dict[str, Any]]:
        server = ControlServer(path, _echo)
        await server.start()
        reader, writer = await asyncio.open_unix_connection(str(path))
        out = []
        for line in (b"status\n", b"mow\n", b"save-map x.json\n"):
            writer.write(line)
            out.append(await _readline(reader))
        writer.close()
        await server.close()
        return out

    status, mow, save = asyncio.run(main())
    assert status == {"ok": True, "cmd": "status"}
    assert mow == {
        "ok": False,
        "error": "mow: not allowed for uid 54321; commands that change the mower need the "
        "service's user, root",
    }
    assert save["ok"] is False and "save-map: not allowed" in save["error"]
    assert ControlPolicy().may_change(Peer(1, 0, 0))  # root
    import os

    assert ControlPolicy().may_change(Peer(1, os.geteuid(), os.getegid()))  # the service
    assert not ControlPolicy(group="no-such-group-here").may_change(Peer(1, 54321, 54321))


def test_the_peer_credentials_are_the_real_ones(tmp_path: Path) -> None:
    import os

    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with a, b:
        assert Peer.of(a) == Peer(os.getpid(), os.geteuid(), os.getegid())


def test_save_map_writes_only_into_the_map_directory(tmp_path: Path) -> None:
    m = tmp_path / "maps" / "lawn.json"
    m.parent.mkdir()
    (m.parent / "link.json").symlink_to(tmp_path / "elsewhere.json")
    assert map_save_path(m, None) == m
    assert map_save_path(m, "backup.json") == m.parent.resolve() / "backup.json"
    for bad in ("/etc/passwd", "../x.json", "sub/x.json", "x.txt", ".hidden.json", "link.json"):
        with pytest.raises(ValueError, match=r"maps are saved as NAME\.json in the map directory"):
            map_save_path(m, bad)
    with pytest.raises(ValueError, match="at most 255"):
        map_save_path(m, ["a"])


def test_one_daemon_per_control_socket(tmp_path: Path) -> None:
    sock = tmp_path / "c.sock"
    fd = claim_control_socket(sock)
    try:
        with pytest.raises(ControlSocketBusy, match=r"another mowerhw daemon \(pid \d+\)"):
            claim_control_socket(sock)
        cfg = tmp_path / "c.yaml"
        cfg.write_text(f"runtime:\n  control_socket: {sock}\n  pose_file: {tmp_path / 'p'}\n")
        run = subprocess.run(
            [sys.executable, "-m", "mowerhw", "run", "--config", str(cfg)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 78, run.stderr
        assert "another mowerhw daemon" in run.stderr and "Traceback" not in run.stderr
    finally:
        import os

        os.close(fd)


def test_a_file_in_the_sockets_place_is_not_deleted(tmp_path: Path) -> None:
    path = tmp_path / "lawn.json"
    path.write_text("{}")

    async def main() -> None:
        await ControlServer(path, _echo).start()

    with pytest.raises(OSError, match="exists and is not a socket"):
        asyncio.run(main())
    assert path.read_text() == "{}"


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300) | st.text(max_size=200).map(str.encode))
def test_fuzzed_request_lines_parse_or_fail_with_a_message(line: bytes) -> None:
    try:
        cmd, args = parse_request(line)
    except ValueError as exc:
        assert str(exc)
        return
    assert cmd in control.COMMANDS
    assert isinstance(args, dict)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3)
    ),
    max_leaves=10,
)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.sampled_from(["cmd", "args", "path", "kind", "x"]), json_values))
def test_fuzzed_json_requests_parse_or_fail_with_a_message(req: dict[str, Any]) -> None:
    try:
        cmd, args = parse_request(json.dumps(req).encode())
    except ValueError as exc:
        assert str(exc)
        return
    assert cmd in control.COMMANDS
    assert all(not isinstance(v, dict) for v in args.values())
