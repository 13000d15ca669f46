"""``mowerhw bench``: the real daemon, its real drivers, mock hardware, one simulated world.

What runs (docs/design.md §9, level 3):

* the mock VN-100 (:class:`drivers.imu.mock.MockVn100`) on a pseudo-terminal, measuring the
  simulated mower (:class:`.world.RealTimeMower`);
* a CAN bus shared between processes (python-can ``udp_multicast`` on the loopback, a random
  group per run) carrying the mock speed sensor's GBSD frames and the daemon's ISB /
  heartbeat / status frames, which the mock mower controller reads;
* the camera: frames rendered from the true pose (:class:`mowerhw.sim.render.OmniRenderer`,
  in a process of its own: :mod:`mowerhw.bench.render_process`)
  and served on a Unix socket (:mod:`drivers.camera.stream`);
* the daemon itself, ``mowerhw run`` in its own process, configured like the real mower
  except for device paths.

Timeline: the daemon starts in teach mode; the mower stands still (gyro calibration), the
"operator" drives the lawn edge once; the daemon detects the loop (or is told
``finish-teach``), saves the map; the bench switches it to ``mow`` over the control socket,
and the mower mows by itself for ``duration_s`` — steering by the daemon's CAN status frame,
stopping when the deck is halted — while faults are injected on schedule.

Scores against the truth: ``boundary_rmse_m`` (the taught boundary against the true lawn edge,
both ways), ``position_rmse_m`` (the daemon's pose, polled over the control socket, against
the true pose at its time stamp), ``missed_halts`` (world steps with the deck running while
the mower is truly more than 0.10 m outside), ``false_halt_fraction`` (share of steps more
than 1 m inside with the deck stopped, outside fault windows), ``halt_latency_ms`` (measured
by the daemon: arrival of the revealing sample → ISB stop sent), ``permit_gaps``, and the
daemon's ``cpu_percent`` and ``peak_rss_mb`` from ``/proc``.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import logging
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
import yaml

from drivers.can.isobus import open_bus
from drivers.can.switches import Switches
from mowerhw.bench.notify import NotifyListener
from mowerhw.evaluation.recovery import WRONG_M
from mowerhw.evaluation.scoring import score_halts
from mowerhw.runtime.control_protocol import request
from mowerhw.runtime.process import cpu_seconds
from mowerhw.supervisor.status_socket import ask_supervisor

log = logging.getLogger("mowerhw.bench")

FAULT_KINDS = (
    "imu-unplug",
    "speed-stop",
    "camera-freeze",
    "nan",
    "exception",
    "corrupt-map",
    "map-nested",
    "map-bigint",
    "map-devzero",
    "map-fifo",
    "map-huge",
    "sigterm",
    "sigkill",
    "estimator-stall",
    "estimator-kill",
    "can-down",
    "address-conflict",
    "lift",
    "tilt",
    "bump",
    "estimator-delay",
)
RECOVERY_WINDOW_S = 30.0


@dataclass
class FaultSpec:
    kind: str
    at_s: float  # after the start of mowing
    duration_s: float = 3.0

    @classmethod
    def parse(cls, text: str) -> FaultSpec:
        """``KIND@T[:D]`` — e.g. ``imu-unplug@20:2`` (at 20 s of mowing, for 2 s)."""
        try:
            kind, rest = text.split("@", 1)
            at, _, dur = rest.partition(":")
            spec = cls(kind, float(at), float(dur) if dur else 3.0)
        except ValueError:
            raise ValueError(f"fault {text!r}: expected KIND@SECONDS[:DURATION]") from None
        if spec.kind not in FAULT_KINDS:
            raise ValueError(f"fault kind {spec.kind!r}; allowed: {', '.join(FAULT_KINDS)}")
        if spec.at_s < 0 or spec.duration_s <= 0:
            raise ValueError(f"fault {text!r}: time must be ≥ 0 and duration > 0")
        return spec


@dataclass
class FaultResult:
    kind: str
    injected_at_s: float
    duration_s: float
    deck_was_running: bool
    stop_after_ms: float | None = None  # injection → the mock controller's deck stop
    reason: str = ""
    recovered: bool = False
    recovered_after_s: float | None = None  # the fault cleared → deck running again
    how: str = ""
    #: every halt reason the daemon gave while the fault lasted, the first the fault's (two
    #: conditions may hold at once: a camera frame late in the instant an exception halts)
    daemon_reasons: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    t0: float | None = None  # bookkeeping while the run goes on (cleared in the result)
    n_events: int | None = None
    t_clear: float | None = None


class Bench:
    """One bench run (see the module doc)."""

    def __init__(
        self,
        duration_s: float = 120.0,
        seed: int = 7,
        scenario: str = "paper",
        out_dir: str | Path | None = None,
        faults: list[FaultSpec] | None = None,
        map_path: str | Path | None = None,
        config_path: str | Path | None = None,
        record: str | Path | None = None,
        load: int = 0,
        estimator_delay_ms: float = 150.0,
        start: str = "dock",
        web: bool = False,
    ) -> None:
        if start not in ("dock", "random"):
            raise ValueError(f"start {start!r}: expected dock or random")
        self.start = start  # random: mowing starts anywhere in the lawn, with no pose file
        self.record = Path(record) if record else None
        self.load = load  # CPU hogs beside the daemon: a loaded mower computer
        self.estimator_delay_ms = estimator_delay_ms
        self.duration_s = duration_s
        self.seed = seed
        self.scenario = scenario
        self.out = Path(out_dir or tempfile.mkdtemp(prefix="mowerhw-bench-"))
        self.out.mkdir(parents=True, exist_ok=True)
        self.faults = sorted(faults or [], key=lambda f: f.at_s)
        self.given_map = Path(map_path) if map_path else None
        self.base_config = Path(config_path) if config_path else _shipped("bench.yaml")
        self.proc: subprocess.Popen | None = None
        self.daemon_log = self.out / "daemon.log"
        self.results: list[FaultResult] = []
        self.pose_samples: list[tuple[float, float, float, bool, float]] = []
        self.cpu_s_total = 0.0  # CPU seconds of daemons that have exited (restarts)
        self.peak_rss_mb = 0.0
        self.restarts = 0
        self.timeline: list[tuple] = []  # (s, state, reason, x, y, heading, detail) at 5 Hz
        self.rss_samples: list[tuple[float, float, float]] = []  # (s into mowing, RSS MB, CPU s)
        # (monotonic, wall) times the mowing began (the mow request answered) and ended
        self.mow_start: tuple[float, float] = (math.inf, math.inf)
        self.mow_end: tuple[float, float] = (math.inf, math.inf)
        self.notify = NotifyListener(self.out / "notify.sock")
        self.web = web  # serve the status page, and measure it (bench.web_check)
        self.web_url = ""
        self._web: dict[str, Any] = {}
        #: set once the bench's own look at the page (its watcher, the refused requests) began
        self.page_checked = threading.Event()
        # a run cut short (its test failed, its thread abandoned) must not leave the daemon
        # running past this process: in its own session it outlives us (one left behind by
        # a failed test was still running when the next session's benches failed)
        atexit.register(self._stop_daemon)

    # ----------------------------------------------------------------------------- set-up

    def _write_config(self) -> Path:
        raw = yaml.safe_load(self.base_config.read_text()) or {}
        group = f"239.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(1, 254)}"
        self.can_channel = group
        raw.setdefault("imu", {}).update(driver="mock", port=str(self.out / "vn100"))
        self.can_port = _free_udp_port()
        raw.setdefault("can", {}).update(
            interface="udp_multicast", channel=group, udp_port=self.can_port
        )
        cal = _shipped("camera/paper-table1.yaml")
        raw.setdefault("camera", {}).update(
            driver="stream", device=str(self.out / "camera.sock"), calibration=str(cal)
        )
        raw.setdefault("map", {})["path"] = str(self.out / "lawn.json")
        raw.setdefault("runtime", {}).update(
            control_socket=str(self.out / "control.sock"),
            pose_file=str(self.out / "pose.json"),
            fault_injection=True,
        )
        if self.web:
            from mowerhw.bench.web_check import free_tcp_port

            port = free_tcp_port()
            raw["web"] = {
                **raw.get("web", {}),
                "enabled": True,
                "host": "127.0.0.1",
                "port": port,
                "token_file": str(self.out / "web-token"),
            }
            self.web_url = f"http://127.0.0.1:{port}/"
            print(f"bench: status page on {self.web_url}", file=sys.stderr)
        path = self.out / "bench-config.yaml"
        path.write_text(yaml.safe_dump(raw, sort_keys=False))
        return path

    def _spawn(self, mode: str) -> None:
        cmd = [sys.executable, "-m", "mowerhw", "run", "--config", str(self.cfg_path)]
        cmd += ["--mode", mode]
        if self.record is not None:  # each start of the daemon gets its own file
            path = (
                self.record
                if not self.restarts
                else self.record.with_name(
                    f"{self.record.stem}.{self.restarts}{self.record.suffix}"
                )
            )
            cmd += ["--record", str(path)]
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **self.notify.env()}
        with open(self.daemon_log, "ab") as logf:
            self.proc = subprocess.Popen(
                cmd,
                stdout=subprocess.DEVNULL,
                stderr=logf,
                env=env,
                start_new_session=True,
            )
        self._wait(lambda s: s.get("sensor_age_s", {}).get("imu") is not None, 30.0, "IMU data")

    def _status(self, timeout: float = 2.0) -> dict[str, Any]:
        try:
            return request(self.sock, "status", timeout=timeout)
        except (OSError, ConnectionError, json.JSONDecodeError):
            return {}

    def _wait(self, pred, timeout: float, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc is not None and self.proc.poll() is not None:
                raise RuntimeError(
                    f"the daemon exited ({self.proc.returncode}) waiting for {what}; "
                    f"see {self.daemon_log}"
                )
            st = self._status()
            if st and pred(st):
                return st
            time.sleep(0.05)
        raise TimeoutError(f"bench: no {what} within {timeout} s (daemon log: {self.daemon_log})")

    def _proc_cpu_rss(self) -> tuple[float, float]:
        """(CPU seconds, peak RSS MB) of the running daemon: all its processes together (the
        permit supervisor and the estimation process it started)."""
        if self.proc is None or self.proc.poll() is not None:
            return 0.0, 0.0
        cpu = rss = 0.0
        for pid in _process_tree(self.proc.pid):
            cpu += cpu_seconds(pid) or 0.0  # 0 if it is gone
            rss += _pid_status_mb(pid, "VmHWM")
        return cpu, rss

    # -------------------------------------------------------------------------------- run

    #: under --load, the niceness of the mock sensors (VN-100, speed sensor, mower
    #: controller, the mower's motion, the camera and its renderer): they stand for hardware,
    #: which a loaded computer cannot slow down. The renderer costs CPU a real camera does
    #: not (about a third of a core at 10 Hz here), but left at the hogs' priority it
    #: delivered the frame in flight at a freeze ~60 ms late, a delay a real camera's frames
    #: do not take from the computer's load (stop 55)
    SENSOR_NICE = -15

    def _sensor_priority(self, devices: list[Any]) -> None:
        if not self.load:
            return
        try:
            for dev in devices:
                dev.set_nice(self.SENSOR_NICE)
        except OSError as exc:
            log.warning(
                "bench: mock sensors at normal priority (%s): under --load they may "
                "be late themselves",
                exc,
            )

    def run(self) -> dict[str, Any]:

        from drivers.camera.mock_server import MockCameraServer
        from drivers.can.mock_mower import MockMowerController
        from drivers.can.mock_speed import MockSpeedSensor
        from drivers.imu.mock import MockVn100
        from mowerhw.bench.render_process import RenderProcess
        from mowerhw.bench.world import RealTimeMower
        from mowerhw.config import load_config
        from mowerhw.sim import make_world

        t_wall0 = time.monotonic()
        self.cfg_path = self._write_config()
        cfg = load_config(self.cfg_path)
        self.sock = cfg.runtime.control_socket
        world = make_world(self.scenario, self.seed)
        truth = self._teach_truth(world)
        mower = RealTimeMower(world, truth, self.seed, q_bi=cfg.imu.q_bi)
        renderer = RenderProcess(self.scenario, self.seed)  # off this process's GIL
        bus = open_bus("udp_multicast", self.can_channel, udp_port=self.can_port)
        vn = MockVn100(self.out / "vn100", source=mower.imu_source, seed=self.seed)
        speed = MockSpeedSensor(bus, mower.speed_source)
        controller = MockMowerController(
            bus,
            cfg.can.source_address,
            status_pgn=cfg.permit.status_pgn,
            switches_pgn=cfg.safety.switches_pgn,
        )
        mower.deck_running = lambda: controller.deck_running
        camera = MockCameraServer(
            cfg.camera.device,
            lambda t: renderer.render(*mower.map_pose_at(t)),
            cfg.camera.camera_fps(),
        )
        self.mower, self.controller, self.vn, self.speed, self.camera = (
            mower,
            controller,
            vn,
            speed,
            camera,
        )
        started = [mower.start(), vn.start(), speed.start(), controller.start(), camera.start()]
        self._sensor_priority([mower, vn, speed, controller, camera, renderer])
        metrics: dict[str, Any] = {}
        hogs = [
            subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(self.load)
        ]
        try:
            if self.given_map is None:
                metrics.update(self._teach(world, truth))
            else:
                Path(cfg.map.path).write_bytes(self.given_map.read_bytes())
                self._spawn("idle")
            if self.start == "random":
                metrics["start"] = self._carry_to_random_pose(world, cfg)
            metrics.update(self._mow(world, cfg))
        finally:
            cpu, rss = self._proc_cpu_rss()
            self.peak_rss_mb = max(self.peak_rss_mb, rss)
            self.cpu_s_total += cpu
            self._stop_daemon()
            for hog in hogs:
                hog.kill()
                hog.wait()
            for dev in reversed(started):
                with contextlib.suppress(Exception):
                    dev.stop()
            renderer.close()  # after the camera that asks it for frames
            bus.shutdown()
            self.notify.close()
        if self.load:
            metrics["load_processes"] = self.load
        metrics["wall_s"] = round(time.monotonic() - t_wall0, 1)
        metrics["out_dir"] = str(self.out)
        return metrics

    def _carry_to_random_pose(self, world: Any, cfg: Any) -> dict[str, Any]:
        """``--start random``: the daemon stops, its pose file goes, the mower is carried to a
        random pose at least 0.5 m inside the lawn (uniform position and heading) and the
        daemon starts again: nothing tells it where the mower is."""
        self._stop_daemon()
        Path(cfg.runtime.pose_file).unlink(missing_ok=True)
        from mowerhw.evaluation.recovery import random_pose

        lawn = shapely.Polygon(world.lawn.outline(720)).buffer(-0.5)
        x, y, heading = random_pose(lawn, np.random.default_rng([self.seed, 18]))
        xy, yaw = self.mower.place_on_map(x, y, heading)
        self._spawn("idle")
        return {
            "kind": "random",
            "true_xy": [round(float(v), 3) for v in xy],
            "true_heading": round(yaw, 4),
            "pose_file": "deleted",
        }

    def _stop_daemon(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)

    # ------------------------------------------------------------------------------ teach

    def _teach_truth(self, world: Any) -> Any:
        """The operator's teach drive: once around the lawn edge."""
        from mowerhw.sim.motion import teach_loop

        sc = world.scenario
        return teach_loop(world.lawn, sc.speed_mps, sc.camera_height_m, standstill_s=1.0)

    def _drive_teach(self, truth: Any) -> None:
        """While the operator drives: nothing to say to the daemon."""
        self.mower.teach_done.wait(truth.t[-1] + 30.0)

    def _teach(self, world: Any, truth: Any) -> dict[str, Any]:
        from mowerhw.map import load as load_map

        self._spawn("teach")
        time.sleep(2.0)  # standing: the teacher calibrates the gyro
        self.mower.start_teach()
        log.info("bench: teach drive (%.0f s)", truth.t[-1])
        self._drive_teach(truth)
        try:  # the daemon usually notices the closed loop by itself
            st = self._wait(
                lambda s: s.get("teach", {}).get("state") in ("finishing", "saved"),
                4.0,
                "automatic loop detection",
            )
            auto = True
        except TimeoutError:
            request(self.sock, "finish-teach", timeout=120.0)
            auto = False
        st = self._wait(
            lambda s: (
                s.get("teach", {}).get("state") == "saved"
                or str(s.get("teach", {}).get("state", "")).startswith("failed")
            ),
            180.0,
            "saved map",
        )
        teach = st["teach"]
        if teach["state"] != "saved":
            raise RuntimeError(f"teach failed in the daemon: {teach['state']}")
        lawn_map = load_map(teach["map"])
        true_edge = self.mower.true_outline(world.lawn.outline(1440))
        return {
            **self._teach_scores(world, lawn_map),
            "teach": {
                "drive_s": round(float(truth.t[-1]), 1),
                "finished_by": "loop detection" if auto else "finish-teach command",
                "landmarks": teach.get("landmarks"),
                "area_m2": teach.get("area_m2"),
                "true_area_m2": round(float(shapely.Polygon(true_edge).area), 2),
                "loop_closure": teach.get("loop_closure"),
                "finish_s": teach.get("finish_s"),
                "map": teach.get("map"),
                "png": teach.get("png"),
            },
        }

    def _teach_scores(self, world: Any, lawn_map: Any) -> dict[str, Any]:
        """The taught boundary against the true lawn edge."""
        err = _boundary_errors(lawn_map.boundary, self.mower.true_outline(world.lawn.outline(1440)))
        return {
            "boundary_rmse_m": round(float(np.sqrt(np.mean(err**2))), 4),
            "boundary_max_m": round(float(err.max()), 4),
        }

    # -------------------------------------------------------------------------------- mow

    def _mow_driver(self, lawn_map: Any) -> Any:
        """The mower's own controller: random coverage with bang-bang edge turns, steering by
        the daemon's status frame (never the truth)."""
        from mowerhw.mow import LawnGeometry
        from mowerhw.sim.controller import BangBangMower

        geom = LawnGeometry.of_map(lawn_map)
        bang = BangBangMower(geom.inward_direction, np.random.default_rng([self.seed, 30]))
        ctl = self.controller

        def drive(now: float, _xy: Any, _yaw: float) -> tuple[float, float]:
            st = ctl.state.status
            if st is None or ctl.why_not(now) in ("ISB timeout", "heartbeat timeout"):
                return 0.0, 0.0  # the daemon is silent: stand
            if not math.isfinite(st.x_m) or not math.isfinite(st.heading_rad):
                return 0.0, 0.0
            state = (
                st.state
                if (ctl.deck_running or st.state in ("NEAR_EDGE", "OUTSIDE"))
                else ("UNKNOWN")
            )
            return bang.command(now - self.t_mow0, st.x_m, st.y_m, st.heading_rad, state)

        return drive

    def _mow_request(self) -> dict[str, Any]:
        """What ``mow`` is asked with (every mowing area)."""
        return {}

    def _mow_tick(self, now: float) -> None:
        """Once per bench loop while mowing (a plan that changes as it goes)."""

    def _mow(self, world: Any, cfg: Any) -> dict[str, Any]:
        from mowerhw.map import load as load_map

        lawn_map = load_map(cfg.map.path)
        self.map_bytes = Path(cfg.map.path).read_bytes()
        self.t_mow0 = time.monotonic()
        drive = self._mow_driver(lawn_map)
        reply = request(self.sock, "mow", timeout=10.0, **self._mow_request())
        if not reply.get("ok"):
            raise RuntimeError(f"daemon refused mow: {reply}")
        cpu0, _ = self._proc_cpu_rss()
        self.cpu_s_total -= cpu0
        t_mow0 = self.t_mow0 = time.monotonic()
        self.mow_start = (t_mow0, time.time())
        self.mower.start_mow(drive)
        pending = list(self.faults)
        windows: list[tuple[float, float]] = []
        end = t_mow0 + self.duration_s
        next_poll = t_mow0
        latencies: list[dict[str, Any]] = []
        self._actions: list[tuple[float, Any]] = []  # (when, what): fault clearing etc.
        if self.web:
            self._web_plan(t_mow0)
        next_rss = t_mow0
        while time.monotonic() < end:
            now = time.monotonic()
            if pending and now - t_mow0 >= pending[0].at_s:
                spec = pending.pop(0)
                res = self._inject(spec, t_mow0)
                self.results.append(res)
                windows.append((res.t0, res.t0 + spec.duration_s + 15.0))
                continue
            self._mow_tick(now)
            due = [a for a in self._actions if a[0] <= now]
            if due:
                self._actions = [a for a in self._actions if a[0] > now]
                for _, fn in due:
                    fn()
                continue
            if now >= next_rss:
                next_rss = now + 10.0
                cpu, _ = self._proc_cpu_rss()
                current = _proc_status_mb(self.proc, "VmRSS")
                self.rss_samples.append((round(now - t_mow0, 1), current, round(cpu, 2)))
            if now >= next_poll:
                next_poll = now + 0.2
                st = self._status(timeout=1.0)
                pose = st.get("pose")
                if pose and st.get("localizer", {}).get("localized"):
                    self.pose_samples.append(
                        (pose["t"], pose["x"], pose["y"], bool(st["permit"]), pose["sigma_xy_m"])
                    )
                if st:
                    latencies = _merge_latencies(latencies, st.get("halt_latencies", []))
                    p = st.get("pose") or {}
                    self.timeline.append(
                        (
                            round(now - t_mow0, 2),
                            st.get("state"),
                            st.get("reason"),
                            p.get("x"),
                            p.get("y"),
                            p.get("heading"),
                            st.get("detail", "")[:60],
                        )
                    )
            time.sleep(0.01)
        # when the mowing ended: the scoring after it holds this process's GIL for seconds,
        # the mock VN-100's too — what happens then is not the daemon's mowing
        self.mow_end = (time.monotonic(), time.time())
        for _, fn in sorted(self._actions, key=lambda a: a[0]):
            fn()  # clear what is still injected
        self._finish_faults()
        st = self._status(timeout=2.0)
        latencies = _merge_latencies(latencies, st.get("halt_latencies", []))
        cpu1, rss = self._proc_cpu_rss()
        self.cpu_s_total += cpu1
        self.peak_rss_mb = max(self.peak_rss_mb, rss)
        mow_s = time.monotonic() - t_mow0
        metrics = self._score_mow(world, t_mow0, windows, latencies, mow_s)
        metrics["watchdog"] = self.notify.gaps(t_mow0, time.monotonic())
        if self.web:
            metrics["web"] = self._web_result(st)
        vs = self.vn.stats  # the mock sensor's own lateness (a loaded bench, not the daemon)

        def while_mowing(t: float) -> bool:
            return t_mow0 <= t <= self.mow_end[0]

        mowing = [gap for t, gap in vs.late_gaps if while_mowing(t)]
        metrics["mock_imu"] = {
            "late_gaps_over_50ms": vs.late_gaps_over_50ms,
            "max_output_gap_ms": round(vs.max_output_gap_s * 1e3, 1),
            # while mowing; over 100 ms the mock alone makes the daemon halt "imu silent"
            "late_gaps_while_mowing": len(mowing),
            "late_gaps_over_100ms_while_mowing": sum(gap > 0.1 for gap in mowing),
            # stamped on time, written late: the daemon sees a silence the stamps do not show
            "late_writes_over_50ms_while_mowing": sum(while_mowing(t) for t, _ in vs.late_writes),
        }
        cs = self.controller.state  # ISO 11783-5: the supervisor claims before it sends
        metrics["can_address"] = {
            "claims_seen": cs.address_claims,
            "frames_before_first_claim": cs.frames_before_claim,
        }
        sup = st.get("supervisor")
        if sup:  # the permit supervisor's own figures (the process that sends the frames)
            metrics["supervisor"] = {
                k: sup.get(k)
                for k in (
                    "lease_to_frame_ms",
                    "own_halt_ms",
                    "max_loop_lag_ms",
                    "loop_stalls_over_20ms",
                    "lease_expired",
                    "leases",
                    "can_reopens",
                    "send_errors",
                )
            }
        metrics["halts_by_reason"] = dict(
            sorted(_count(d["reason"] for d in latencies).items())  # type: ignore[arg-type]
        )
        metrics["daemon_counts"] = st.get("counts", {})
        loc = st.get("localizer") or {}
        metrics["relocalization"] = {  # issue 18: searches for the pose and their checks
            k: loc.get(k) for k in ("searches", "relocalizations", "checks_passed", "checks_failed")
        }
        metrics["daemon_restarts"] = self.restarts
        if self.rss_samples:
            metrics["rss_mb"] = {
                "start": self.rss_samples[0][1],
                "end": self.rss_samples[-1][1],
                "samples": len(self.rss_samples),
            }
        if self.results:
            skip = ("t0", "n_events", "t_clear")
            metrics["faults"] = [
                {k: v for k, v in vars(r).items() if k not in skip} for r in self.results
            ]
        self._cpu_rss_done = True
        return metrics

    # -------------------------------------------------------------------- the status page

    def _web_pid(self) -> int | None:
        web = (self._status().get("supervisor") or {}).get("web") or {}
        return web.get("pid")

    def _web_cpu(self) -> tuple[float, float, float]:
        """(when, CPU s of all the daemon's processes, CPU s of the page's process)."""
        pid = self._web_pid()
        page_cpu = (cpu_seconds(pid) if pid is not None else None) or 0.0
        return time.monotonic(), self._proc_cpu_rss()[0], page_cpu

    def _web_plan(self, t_mow0: float) -> None:
        """First half of mowing with the page closed, second half open (web_check)."""
        from mowerhw.bench.web_check import PageWatcher, send_bad_requests

        w = self._web
        w["closed_from"] = self._web_cpu()

        def open_page() -> None:
            w["open_from"] = self._web_cpu()
            w["watcher"] = PageWatcher(self.web_url).start()
            token = (self.out / "web-token").read_text().strip()
            w["requests_at"] = round(time.monotonic() - t_mow0, 2)
            w["refused"] = send_bad_requests(self.web_url, token)
            self.page_checked.set()

        self._actions.append((t_mow0 + 0.5 * self.duration_s, open_page))

    def _web_result(self, status: dict[str, Any]) -> dict[str, Any]:
        w = self._web
        end = self._web_cpu()
        out: dict[str, Any] = {"url": self.web_url, "token_file": str(self.out / "web-token")}
        if "open_from" not in w:
            return out
        watcher = w["watcher"]
        watcher.stop()

        def share(a: tuple[float, float, float], b: tuple[float, float, float]) -> dict[str, Any]:
            dt = max(b[0] - a[0], 1e-9)
            return {
                "seconds": round(dt, 1),
                "daemon_cpu_percent": round(100.0 * (b[1] - a[1]) / dt, 2),
                "page_process_cpu_percent": round(100.0 * (b[2] - a[2]) / dt, 2),
            }

        out["page_process_peak_rss_mb"] = _pid_status_mb(self._web_pid() or -1, "VmHWM")
        out["page_closed"] = share(w["closed_from"], w["open_from"])
        out["page_open_10hz"] = share(w["open_from"], end)
        out["browser"] = watcher.summary(end[0] - w["open_from"][0])
        out["refused_requests_at_s"] = w["requests_at"]
        out["refused_requests"] = w["refused"]
        # the permit around the requests, from the bench's 5 Hz timeline of the daemon
        t0 = w["requests_at"]
        near = [row for row in self.timeline if t0 - 2.0 <= row[0] <= t0 + 5.0]
        out["states_around_requests"] = _count(row[1] for row in near)
        out["mode_after_requests"] = status.get("mode")
        return out

    def _true_signed_distance(self, world: Any, t: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """The true signed distance (positive inside) to where mowing is allowed at each
        time: here the whole lawn."""
        from mowerhw.mow import LawnGeometry

        true_geom = LawnGeometry(self.mower.true_outline(world.lawn.outline(1440)), [])
        return true_geom.signed_distances(xy)

    def _score_mow(self, world, t_mow0, windows, latencies, mow_s) -> dict[str, Any]:
        log_arr = self.mower.log_array()
        np.save(self.out / "truth.npy", log_arr)  # t, x, y, yaw, v, deck, phase (post-mortem)
        np.save(self.out / "poses.npy", np.array(self.pose_samples, dtype=np.float64))
        (self.out / "timeline.json").write_text(json.dumps(self.timeline))
        sel = log_arr[:, 6] == 2  # mowing phase
        t, x, y, deck = log_arr[sel, 0], log_arr[sel, 1], log_arr[sel, 2], log_arr[sel, 5] > 0
        s_true = self._true_signed_distance(world, t, np.column_stack([x, y]))
        first_permit = t[np.argmax(deck)] if deck.any() else math.inf
        in_fault = np.zeros(t.size, bool)
        for a, b in windows:
            in_fault |= (t >= a) & (t < b)
        halts = score_halts(t, deck, s_true, first_permit, 1.0 / 200.0, in_fault)
        # the daemon's estimate against the truth at its own time stamps
        errs, permitted = [], []
        for tp, xp, yp, permit, _ in self.pose_samples:
            k = int(np.searchsorted(t, tp))
            if 0 < k < t.size and t[k] - t[k - 1] < 0.05:
                f = (tp - t[k - 1]) / (t[k] - t[k - 1])
                xt = x[k - 1] + f * (x[k] - x[k - 1])
                yt = y[k - 1] + f * (y[k] - y[k - 1])
                errs.append(math.hypot(xp - xt, yp - yt))
                permitted.append(bool(permit))
        off = np.array(errs)[np.array(permitted, dtype=bool)] if errs else np.zeros(0)
        lat = np.array([d["latency_ms"] for d in latencies]) if latencies else np.zeros(0)
        gaps = _permit_gaps(t, deck, first_permit)
        cpu_percent = 100.0 * self.cpu_s_total / max(mow_s, 1e-9)
        return {
            "position_rmse_m": round(float(np.sqrt(np.mean(np.square(errs)))), 4) if errs else None,
            "position_max_m": round(float(np.max(errs)), 4) if errs else None,
            "pose_samples": len(errs),
            # issue 18: the deck ran while the pose was this wrong (polled at 5 Hz)
            "position_max_while_permitted_m": round(float(off.max()), 4) if off.size else None,
            "permitted_samples_off_over_0.15m": int(np.sum(off > WRONG_M)),
            "missed_halts": halts["missed_halts"],
            "false_halt_fraction": halts["false_halt_fraction"],
            "halt_latency_ms": {
                "p50": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
                "p99": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
                "max": round(float(lat.max()), 3) if lat.size else None,
                "n": int(lat.size),
                # the worst of each halt reason (a start at the dock on the edge is OUTSIDE
                # before the clock sync has settled; a silent sensor halts at its deadline)
                "max_by_reason": {
                    reason: max(d["latency_ms"] for d in latencies if d["reason"] == reason)
                    for reason in sorted({d["reason"] for d in latencies})
                },
            },
            "permit_gaps": gaps,
            "cpu_percent": round(cpu_percent, 1),
            "peak_rss_mb": round(self.peak_rss_mb, 1),
            "mow_s": round(mow_s, 1),
            "permit_fraction": round(float(np.mean(deck[t >= first_permit])), 4)
            if np.isfinite(first_permit)
            else 0.0,
            "time_truly_outside_s": halts["time_outside_s"],
        }

    # ----------------------------------------------------------------------------- faults

    def _inject(self, spec: FaultSpec, t_mow0: float) -> FaultResult:
        """Inject now; clearing it and the daemon's stated reason are scheduled, the stop
        and recovery are read from the mock controller's deck events afterwards."""
        ctl = self.controller
        t0 = time.monotonic()
        # one-shot faults last as long as they last; recovery counts from their end
        duration = {"bump": 0.2, "nan": 0.0, "exception": 0.0}.get(spec.kind, spec.duration_s)
        res = FaultResult(spec.kind, round(t0 - t_mow0, 2), duration, ctl.deck_running)
        res.t0 = t0
        res.n_events = len(ctl.state.events)
        clear: Any = None
        if spec.kind == "imu-unplug":
            self.vn.vanish(spec.duration_s)  # the pty comes back by itself
        elif spec.kind == "speed-stop":
            self.speed.paused.set()
            clear = self.speed.paused.clear
        elif spec.kind == "camera-freeze":
            self.camera.frozen.set()
            clear = self.camera.frozen.clear
        elif spec.kind in ("nan", "exception"):
            request(self.sock, "fault", args=[spec.kind])
        elif spec.kind == "estimator-delay":  # blocked estimator_delay_ms every 200 ms
            request(self.sock, "fault", args=[spec.kind, str(self.estimator_delay_ms)])
            clear = lambda: request(self.sock, "fault", args=[spec.kind, "0"])  # noqa: E731
        elif spec.kind in ("lift", "tilt", "bump"):
            clear = self._disturb(spec.kind, t0, spec.duration_s)
        elif spec.kind == "can-down":  # the supervisor's CAN interface away for D s
            request(self.sock, "fault", args=[spec.kind, str(spec.duration_s)])
            n_hb = len(ctl.state.heartbeats)

            def heartbeats_after() -> None:
                seen = [seq for _, seq in list(ctl.state.heartbeats)[n_hb:]][:12]
                res.notes.append(f"heartbeats seen from the fault on: {seen}")

            self._actions.append((t0 + spec.duration_s + 2.0, heartbeats_after))
        elif spec.kind == "address-conflict":  # another node claims the supervisor's address
            ctl.claim_address(spec.duration_s)
        elif spec.kind == "corrupt-map":
            path = Path(self.cfg_path.parent / "lawn.json")
            with open(path, "r+b") as fh:  # damaged in place, as a bad disk or editor would
                fh.seek(len(self.map_bytes) // 2)
                fh.write(b"\x00garbage\x00" * 8)
            clear = lambda: _restore(path, self.map_bytes)  # noqa: E731
        elif spec.kind.startswith("map-"):
            path = Path(self.cfg_path.parent / "lawn.json")
            _hostile_map(spec.kind, path, self.map_bytes)
            clear = lambda: _restore(path, self.map_bytes)  # noqa: E731
        elif spec.kind == "estimator-stall":  # the estimation process frozen (SIGSTOP)
            pid = int((self._status(timeout=1.0) or {}).get("pid") or 0)
            if pid and pid != self.proc.pid:  # type: ignore[union-attr]
                os.kill(pid, signal.SIGSTOP)

                def clear() -> None:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGCONT)
                    proc = self.proc
                    if proc is not None and proc.poll() is not None:
                        # stopped longer than supervisor.child_hang_s: the supervisor took
                        # it for hung, killed it and ended the service; systemd restarts it
                        res.notes.append(f"daemon exit status {proc.returncode}")
                        res.how = "restarted (the supervisor ended the service: estimator hung)"
                        self.restarts += 1
                        self._spawn("mow")
            else:
                res.notes.append("no separate estimation process (supervisor disabled)")
        elif spec.kind in ("sigterm", "sigkill", "estimator-kill"):
            cpu, rss = self._proc_cpu_rss()
            self.cpu_s_total += cpu
            self.peak_rss_mb = max(self.peak_rss_mb, rss)
            if spec.kind == "estimator-kill":  # the supervisor must halt and end the service
                pid = int((self._status(timeout=1.0) or {}).get("pid") or 0)
                os.kill(pid, signal.SIGKILL)
            else:
                self.proc.send_signal(  # type: ignore[union-attr]
                    signal.SIGTERM if spec.kind == "sigterm" else signal.SIGKILL
                )
            self.proc.wait(10.0)  # type: ignore[union-attr]
            res.notes.append(f"daemon exit status {self.proc.returncode}")  # type: ignore[union-attr]

            def clear() -> None:
                self.restarts += 1
                self._spawn("mow")

            res.how = (
                "clean stop (halt + heartbeat 255); restarted by the bench"
                if spec.kind == "sigterm"
                else "restarted (as systemd Restart=on-failure does after a failure)"
            )

        def note_reason() -> None:
            """The daemon's halt reason while the fault lasts (asked a few times: a map
            fault is seen after the next map check and the loader's start), the first one
            kept as the fault's: the estimation side's, or the permit supervisor's own
            (tilt, a bump, its CAN address taken) while the estimation side permits."""
            st = self._status(timeout=1.0)
            if not st:  # the estimation process is silent: its supervisor says why
                with contextlib.suppress(OSError, ConnectionError, ValueError):
                    st = {"supervisor": ask_supervisor(self.sock)}
            if not st:
                return
            sup = st.get("supervisor") or {}
            said = ""
            if not st.get("permit") and st.get("reason"):
                said = f"{st.get('reason', '')}: {st.get('detail', '')}".strip(": ")
            elif sup.get("permit") is False and sup.get("reason"):
                own = f"{sup.get('reason', '')}: {sup.get('detail', '')}".strip(": ")
                said = f"supervisor: {own}"
            if said and said not in res.daemon_reasons:
                res.daemon_reasons.append(said)

        def cleared() -> None:
            res.t_clear = time.monotonic()
            if clear is not None:
                clear()

        for share in (0.25, 0.5, 0.9):
            self._actions.append((t0 + max(duration, 0.1) * share, note_reason))
        self._actions.append((t0 + duration, cleared))
        return res

    def _disturb(self, kind: str, t0: float, duration_s: float) -> Any:
        """A lift (the lift switch, and the accelerometer reading 1.5 g for 0.3 s), a tilt
        (gravity 45° off the body's up axis for the duration) or a bump (a 3 g jolt for 60
        ms and the bumper for 0.2 s); what clears it."""
        g = 9.80665
        ctl, mower = self.controller, self.mower
        if kind == "lift":
            mower.accel_events.append((t0, t0 + 0.3, np.array([0.0, 0.0, 1.5 * g])))
            ctl.switches = Switches(lifted=True)
        elif kind == "tilt":
            c, s = math.cos(math.radians(45.0)), math.sin(math.radians(45.0))
            mower.accel_events.append((t0, t0 + duration_s, np.array([0.0, g * s, g * c])))
        else:
            mower.accel_events.append((t0, t0 + 0.06, np.array([-3.0 * g, 0.0, g])))
            ctl.switches = Switches(bumped=True)
            self._actions.append((t0 + 0.2, lambda: setattr(ctl, "switches", Switches())))
        return lambda: setattr(ctl, "switches", Switches())

    def _finish_faults(self) -> None:
        """Stop and recovery of each fault, from the mock controller's deck events."""
        events = self.controller.state.events
        for res in self.results:
            stop = next(
                (e for e in events[res.n_events :] if not e.running and e.t >= res.t0 - 1e-3),
                None,
            )
            if stop is not None and stop.t - res.t0 < 5.0:
                res.stop_after_ms = round((stop.t - res.t0) * 1e3, 1)
                res.reason = f"controller: {stop.reason}"
            if res.daemon_reasons:
                res.reason = f"{res.reason}; daemon: {res.daemon_reasons[0]}".strip("; ")
            t_clear = res.t_clear if res.t_clear is not None else res.t0 + res.duration_s
            back = next((e for e in events if e.running and e.t >= t_clear), None)
            if back is not None and back.t - t_clear <= RECOVERY_WINDOW_S:
                res.recovered = True
                res.recovered_after_s = round(back.t - t_clear, 2)
                res.how = res.how or "by itself, same process"
            for attr in ("t0", "n_events", "t_clear"):
                setattr(res, attr, None)


# ----------------------------------------------------------------------------- helpers


def _shipped(name: str) -> Path:
    here = Path(__file__).resolve().parents[2] / "configs" / name
    return here


def _free_udp_port() -> int:
    """A UDP port nobody uses now: each bench run gets its own bus (Linux hands every
    multicast datagram on a port to every socket bound to it, whatever the group)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


def _process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants (Linux ``/proc/PID/task/TID/children``)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo.extend(int(c) for c in (task / "children").read_text().split())
            except (OSError, ValueError):
                continue
    return out


def _pid_status_mb(pid: int, key: str) -> float:
    """A memory figure (``VmRSS``, ``VmHWM``) of a running process, MB; 0 if it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return 0.0


def _proc_status_mb(proc: Any, key: str) -> float:
    """A memory figure of the daemon: all its processes together, MB; 0 if it is gone."""
    if proc is None or proc.poll() is not None:
        return 0.0
    return round(sum(_pid_status_mb(p, key) for p in _process_tree(proc.pid)), 1)


def _restore(path: Path, data: bytes) -> None:
    from mowerhw.common.fileio import write_atomic

    if path.is_symlink() or (path.exists() and not path.is_file()):
        path.unlink()  # write_atomic renames over it either way; a FIFO/symlink goes first
    write_atomic(path, data)


def _hostile_map(kind: str, path: Path, good: bytes) -> None:
    """Put a hostile "map" where the daemon reads its map (the attacks of issue 16):
    deeply nested JSON, a 5000-digit integer, ``/dev/zero``, a FIFO nobody writes, and a
    valid map padded beyond the size limit (300 MB)."""
    from mowerhw.common.fileio import write_atomic

    tmp = path.with_name(path.name + ".hostile")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    if kind == "map-nested":
        write_atomic(path, b"[" * 200_000)
    elif kind == "map-bigint":
        write_atomic(path, b'{"format": "mowerhw-map", "version": 1' + b"0" * 5000 + b"}")
    elif kind == "map-devzero":
        tmp.symlink_to("/dev/zero")
        os.replace(tmp, path)
    elif kind == "map-fifo":
        os.mkfifo(tmp)
        os.replace(tmp, path)
    elif kind == "map-huge":  # valid JSON, whitespace after the document: 300 MB
        block = b" " * (8 << 20)  # spaces, not NUL bytes (NULs would not be JSON)
        with open(tmp, "wb") as fh:
            fh.write(good)
            left = (300 << 20) - len(good)
            while left > 0:
                fh.write(block[: min(left, len(block))])
                left -= len(block)
        os.replace(tmp, path)


def _stop_after(ctl: Any, n_events: int, t0: float) -> Any:
    """The mock controller's first deck stop since the injection, if any."""
    for e in ctl.state.events[n_events:]:
        if not e.running and e.t >= t0 - 0.001:
            return e
    return None


def _wait_for(fn, timeout: float) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = fn()
        if v:
            return v
        time.sleep(0.002)
    return None


def _merge_latencies(have: list[dict], new: list[dict]) -> list[dict]:
    seen = {(d["t"], d["reason"]) for d in have}
    return have + [d for d in new if (d["t"], d["reason"]) not in seen]


def _count(items) -> dict[str, int]:
    out: dict[str, int] = {}
    for k in items:
        out[k] = out.get(k, 0) + 1
    return out


def _permit_gaps(t: np.ndarray, deck: np.ndarray, first: float) -> dict[str, Any]:
    """Halts of the deck after mowing began: how many, how long."""
    sel = t >= first
    t, deck = t[sel], deck[sel]
    if t.size == 0:
        return {"count": 0}
    edges = np.flatnonzero(np.diff(deck.astype(np.int8)))
    gaps = []
    for k in edges:
        if deck[k] and not deck[k + 1]:
            ends = edges[edges > k]
            end_t = t[ends[0] + 1] if ends.size else t[-1]
            gaps.append(float(end_t - t[k + 1]))
    g = np.array(gaps)
    return {
        "count": int(g.size),
        "median_s": round(float(np.median(g)), 2) if g.size else None,
        "max_s": round(float(g.max()), 2) if g.size else None,
        "total_s": round(float(g.sum()), 2),
    }


def _boundary_errors(boundary: np.ndarray, true_edge: np.ndarray) -> np.ndarray:
    """Distances both ways: taught boundary vertices → true edge, true edge → boundary."""
    est = shapely.LinearRing(boundary)
    tru = shapely.LinearRing(true_edge)
    a = shapely.distance(tru, shapely.points(boundary))
    b = shapely.distance(est, shapely.points(true_edge))
    return np.concatenate([a, b])


def run_bench(**kwargs: Any) -> dict[str, Any]:
    return Bench(**kwargs).run()


__all__ = ["FAULT_KINDS", "Bench", "FaultResult", "FaultSpec", "run_bench"]
