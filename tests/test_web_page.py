"""The status page in headless Chromium (Debian's chromium, driven by Playwright) against
the real daemon on the bench (issue 19): what the page shows is what the daemon says, within
one update; it comes back after a reload; its controls need the token. The screenshots under
``docs/`` come from ``tools/web_screenshots.py`` (a whole teach-then-mow bench run)."""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any

import pytest

from mowerhw.bench import Bench, browser
from mowerhw.config import load_config
from mowerhw.runtime.control_protocol import request

pytestmark = pytest.mark.slow

#: the page's process is killed this often: what a restart holds up, it holds up each time
KILLS = 2

#: what the page shows, read in one go
READ_PAGE = """() => ({
  now: Number(document.body.dataset.now),
  state: document.body.dataset.state,
  permit: document.body.dataset.permit,
  x: Number(document.getElementById('pose-x').textContent),
  y: Number(document.getElementById('pose-y').textContent),
  heading: Number(document.getElementById('pose-heading').textContent),
  mode: document.getElementById('mode').textContent,
  points: Number(document.body.dataset.points),
})"""


def _until(fn: Any, timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = fn()
        if got:
            return got
        time.sleep(0.1)
    raise AssertionError(f"no {what} within {timeout} s")


def _restarted(status: dict[str, Any], deaths: int) -> dict[str, Any] | None:
    """The supervisor's status once the page's process has died ``deaths`` times and runs
    again (a status from between a death and the restart has no pid to kill next)."""
    web = (status.get("supervisor") or {}).get("web") or {}
    if web.get("deaths") == deaths and web.get("alive") and web.get("pid"):
        return dict(status["supervisor"])
    return None


def test_the_page_shows_what_the_daemon_says_while_mowing(yard_map, tmp_path) -> None:
    why = browser.missing()
    if why:
        pytest.skip(f"the page's browser test needs {why}")
    bench = Bench(duration_s=55.0, seed=7, out_dir=tmp_path, map_path=yard_map, web=True)
    imu_period_s = 1.0 / load_config(bench.base_config).imu.rate_hz
    result: dict[str, Any] = {}
    runner = threading.Thread(target=lambda: result.update(bench.run()), daemon=True)
    runner.start()
    sock = tmp_path / "control.sock"

    def status() -> dict[str, Any]:  # what `mowerhw ctl status` prints
        try:
            return request(sock, "status", timeout=2.0)
        except (OSError, ConnectionError, ValueError):
            return {}

    _until(lambda: status().get("mode") == "mow" and bench.web_url, 90.0, "mowing")
    compared = []
    with browser.page(bench.web_url) as pg:
        pg.wait_for_function("document.body.dataset.permit === 'true'", timeout=60_000)
        for _ in range(8):
            t0 = time.monotonic()
            shown = pg.evaluate(READ_PAGE)
            said = status()
            took = time.monotonic() - t0
            compared.append((shown, said, took))
            time.sleep(0.37)
        # the sensors as the page lists them: late only as the permit gate judges it
        sensors = request(sock, "live", timeout=2.0)["sensors"]
        late_cells = pg.eval_on_selector_all("#sensors td.late", "cells => cells.length")
        # a reload (a browser coming back) draws the whole drive again
        n_before = pg.evaluate(READ_PAGE)["points"]
        pg.reload()
        pg.wait_for_function("document.body.dataset.connected === 'true'", timeout=10_000)
        pg.wait_for_function(f"Number(document.body.dataset.points) >= {n_before}")
        # the page's process killed, KILLS times: the supervisor starts it again each time,
        # the page reconnects, the estimation side does not notice (no lease runs out) —
        # after the bench's own requests to the page, which need it up
        assert bench.page_checked.wait(60.0), "the bench's look at the page"
        before = status()["supervisor"]
        after = before
        for kill in range(1, KILLS + 1):
            os.kill(after["web"]["pid"], signal.SIGKILL)
            pg.wait_for_function("document.body.dataset.connected === 'false'", timeout=10_000)
            pg.wait_for_function("document.body.dataset.connected === 'true'", timeout=20_000)
            after = _until(lambda k=kill: _restarted(status(), k), 5.0, "the page's restart")
        # the controls: refused without the token, done with it
        pg.click("button[data-cmd=idle]")
        refused = pg.wait_for_function(
            "document.getElementById('reply').textContent || false"
        ).json_value()
        token = (tmp_path / "web-token").read_text().strip()
        pg.fill("#token", token)
        pg.click("button[data-cmd=idle]")
        pg.wait_for_function("document.getElementById('reply').textContent.includes('done')")
        mode_after = _until(lambda: status().get("mode"), 5.0, "status")
        pg.wait_for_function("document.getElementById('mode').textContent === 'idle'")
    runner.join(timeout=120.0)
    assert not runner.is_alive()

    print("page behind ctl status (s):", [round(d["now"] - s["now"], 3) for s, d, _ in compared])
    for shown, said, took in compared:
        pose = said["pose"]
        lag = said["now"] - shown["now"]  # the daemon's time between page and status
        # within one update (0.1 s at 10 Hz), plus the time the two reads took and up to
        # 0.1 s for the update to travel (page process → WebSocket → Chromium)
        assert -0.01 <= lag <= 0.1 + took + 0.1, (lag, took)
        moved = abs(complex(pose["x"] - shown["x"], pose["y"] - shown["y"]))
        # ≤ 0.6 m/s over the lag and the age of the page's pose at its update (up to one IMU
        # interval: the pose is the newest sample's), plus the page's 1 mm rounding
        assert moved <= 0.6 * (max(lag, 0.0) + imu_period_s) + 0.002, (shown, pose, lag)
        assert shown["mode"] == "mow"
    # the state differs only across a change the daemon made between the two reads (the page
    # up to 0.12 s behind; at the edge NEAR_EDGE → OUTSIDE → UNKNOWN can follow one another
    # within a second: two such in one CI run): the page still shows what the status before
    # said, or the next page shows what this status said
    states = [(s["state"], d["state"]) for s, d, _ in compared]
    unexplained = [
        k
        for k, (shown, said) in enumerate(states)
        if shown != said
        and not (k > 0 and shown == states[k - 1][1])
        and not (k + 1 < len(states) and states[k + 1][0] == said)
    ]
    same_state = sum(shown == said for shown, said in states)
    assert not unexplained and same_state >= len(states) // 2, states
    assert "401" in refused and "token" in refused
    assert mode_after == "idle"
    assert set(sensors) == {"imu", "speed", "camera"}
    assert sensors["imu"]["limit_s"] == 0.1 and sensors["speed"]["limit_s"] == 0.3
    assert not any(s["late"] for s in sensors.values()) and late_cells == 0  # mowing
    assert after["web"]["deaths"] == KILLS and after["web"]["starts"] == KILLS + 1
    assert after["web"]["pid"] != before["web"]["pid"] and after["web"]["alive"]
    # the page's deaths and restarts hold nothing up: a restart that holds the estimation
    # side up does so each time (KILLS leases run out or more), where the machine's own
    # hiccup (one lease, once in four fresh-clone CI runs at stop 72) is a one-off —
    assert after["lease_expired"] - before["lease_expired"] <= 1, (before, after)
    # nor the supervisor, which starts the page's process again (spawned, not waited for)
    stalls = after["loop_stalls_over_20ms"] - before["loop_stalls_over_20ms"]
    assert stalls <= 1, (before, after)
    assert result["missed_halts"] == 0
    assert result["web"]["browser"]["updates"] > 0, result["web"]["browser"]["errors"]
    assert all(r["status"] in (400, 401, 403, 413) for r in result["web"]["refused_requests"])
