"""The status page during a whole bench run, in headless Chromium (issue 19): screenshots
while teaching and while mowing (``docs/web-teach.png``, ``docs/web-mow.png``), what the
page showed and what the daemon said at that moment, and the bench's JSON (with ``--web``:
the page's CPU open and closed, the refused control requests). Prints one JSON object.

    .venv/bin/python tools/web_screenshots.py --duration 120 --out docs
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from mowerhw.bench import Bench, browser
from mowerhw.runtime.control_protocol import request

READ_PAGE = """() => ({
  now: Number(document.body.dataset.now), state: document.body.dataset.state,
  permit: document.body.dataset.permit, mode: document.getElementById('mode').textContent,
  x: document.getElementById('pose-x').textContent,
  y: document.getElementById('pose-y').textContent,
  points: Number(document.body.dataset.points),
  teach: document.getElementById('teach-state').textContent,
  landmarks: document.getElementById('teach-landmarks').textContent,
})"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=120.0, help="seconds of mowing")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", type=Path, default=Path("docs"), help="where the PNGs go")
    ap.add_argument("--teach-m", type=float, default=15.0, help="metres of edge driven at the shot")
    args = ap.parse_args()
    missing = browser.missing()
    if missing:
        raise SystemExit(f"web_screenshots: needs {missing}")
    run_dir = Path(tempfile.mkdtemp(prefix="mowerhw-web-"))
    bench = Bench(duration_s=args.duration, seed=args.seed, out_dir=run_dir, web=True)
    result: dict[str, Any] = {}
    runner = threading.Thread(target=lambda: result.update(bench.run()), daemon=True)
    runner.start()
    sock = run_dir / "control.sock"

    def live() -> dict[str, Any]:
        try:
            return request(sock, "live", timeout=2.0)
        except (OSError, ConnectionError, ValueError):
            return {}

    def wait(pred: Any, timeout: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and runner.is_alive():
            got = live()
            if got and pred(got):
                return got
            time.sleep(0.2)
        raise SystemExit("web_screenshots: the bench did not get there")

    shots: dict[str, Any] = {}
    wait(lambda s: s.get("mode") == "teach", 120.0)
    with browser.page(bench.web_url, 1400, 860) as pg:
        # teach: part of the edge driven (the paper yard's edge is about 27 m)
        wait(lambda s: (s.get("teach") or {}).get("distance_m", 0.0) > args.teach_m, 600)
        time.sleep(1.0)
        shots["teach"] = _shot(pg, args.out / "web-teach.png", live())
        wait(lambda s: s.get("mode") == "mow" and s.get("permit"), 600.0)
        time.sleep(min(30.0, 0.4 * args.duration))
        shots["mow"] = _shot(pg, args.out / "web-mow.png", live())
    runner.join()
    print(json.dumps({"screenshots": shots, "bench": result}, indent=1, allow_nan=False))


def _shot(pg: Any, path: Path, said: dict[str, Any]) -> dict[str, Any]:
    path.parent.mkdir(parents=True, exist_ok=True)
    shown = pg.evaluate(READ_PAGE)
    pg.screenshot(path=str(path))
    pose = said.get("pose") or {}
    return {
        "file": str(path),
        "page": shown,
        "daemon": {
            "now": said.get("now"),
            "mode": said.get("mode"),
            "state": said.get("state"),
            "permit": said.get("permit"),
            "x": pose.get("x"),
            "y": pose.get("y"),
            "teach": {k: v for k, v in (said.get("teach") or {}).items() if k != "landmarks"},
        },
    }


if __name__ == "__main__":
    main()
