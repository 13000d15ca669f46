"""The daemon (docs/design.md §8): an asyncio shell around :class:`~.core.RuntimeCore`.

Everything that decides lives in the core; this module moves data between it and the world:

* the VN-100 is read on the event loop itself (its thread only opens and reopens the port);
  other device threads (CAN receive, camera) hand samples over with ``call_soon_threadsafe``;
  the supervisor's messages (the ground speed among them) and the camera's liveness between
  the front end's frames are read before each decision instead, without a wake-up of their
  own; each IMU sample goes into the core, which decides at once, and the decision goes out
  — a halt leaves within the IMU period of the sample revealing it;
* camera frames wait in a one-slot queue (the oldest is dropped); the front end tracks one
  frame at a time in its own process (``frontend_worker``) and the tracks go into the core;
* estimator chains are built off the loop when the core asks for one;
* a decision timer, re-armed by every decision, decides when nothing else has: at the next
  staleness deadline, when a CAN frame is due, or 40 ms after the last decision (an IMU that
  keeps time leaves it nothing to do, and the loop does not wake for it);
* a ticker (every 0.1 s) feeds the status page, the recording, watches the map file,
  finishes a taught loop, pings systemd's watchdog; it runs with the first IMU sample after
  its period is up (the loop is awake for that sample anyway) and wakes the loop itself only
  when none comes within ``TICK_SLACK_S``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from drivers.camera.base import CameraSource, asyncio_sink
from drivers.imu.vn100 import Vn100
from mowerhw.camera import load_camchain
from mowerhw.common.samples import FrameSample, ImuSample, SpeedSample
from mowerhw.config import Config
from mowerhw.frontend.tracker import FrameTracks
from mowerhw.mow.gate import Decision
from mowerhw.recording.mcap import Recorder
from mowerhw.runtime.callbacks import HandlerCosts, crash_only, threadsafe
from mowerhw.runtime.commands import core_status, handle_command
from mowerhw.runtime.control import ControlServer, control_server
from mowerhw.runtime.core import MODES, RuntimeCore
from mowerhw.runtime.devices import (
    DecisionOutput,
    RecorderJournal,
    device_status,
    open_camera,
    open_imu,
    open_output,
    open_recorder,
    record_estimate,
)
from mowerhw.runtime.frontend_worker import FrontendWorker, FrontendWorkerDied, track_frame
from mowerhw.runtime.live import LiveView
from mowerhw.runtime.mapfiles import MapFile, PoseFile, save_map, teach_to_map_file
from mowerhw.runtime.pipelines import BuildRequest, build_pipeline
from mowerhw.runtime.process import LoopLag
from mowerhw.runtime.sdnotify import Notifier

log = logging.getLogger("mowerhw.daemon")

#: without IMU samples, a decision at least this often (it renews the supervisor's 80 ms lease)
DECIDE_MAX_S = 0.04
#: the ticker's period: the status page's samples, the recording, the map file, systemd
TICK_S = 0.1
#: how long after its period the ticker waits for an IMU sample to run with before it wakes
#: the loop itself: a sample comes every 20 ms, so while the IMU runs the ticker adds no
#: wake-up of its own (10 a second before; README, issue 15, stop 66: fewer wake-ups, though
#: not a measurably lower CPU); the loop's lag is measured from this deadline
TICK_SLACK_S = 0.03


class Daemon:
    """``await Daemon(config).run()`` until SIGTERM / SIGINT or :meth:`request_stop`."""

    def __init__(
        self,
        config: Config,
        mode: str | None = None,
        record: str | Path | None = None,
        link: Any = None,
    ) -> None:
        self.cfg = config
        self.start_mode = mode or config.runtime.mode
        if self.start_mode not in MODES:
            raise ValueError(f"mode {self.start_mode!r} is not one of {', '.join(MODES)}")
        self.record_path = Path(record) if record else None
        self.recorder: Recorder | None = None
        self.camera_model = load_camchain(config.camera.calibration, config.camera.camchain_key)
        self.core = RuntimeCore(config, on_build=self._on_build)
        self.notifier = Notifier()
        self.pose_file = PoseFile(Path(config.runtime.pose_file))
        self.map_file = MapFile.of(config)
        self.loop: asyncio.AbstractEventLoop | None = None
        #: where decisions go: the supervisor's pipe (``link``), else CAN in this process
        self.link = link
        self.can: DecisionOutput | None = None
        self.imu_dev: Vn100 | None = None
        self.camera: CameraSource | None = None
        self.loop_lag = LoopLag()
        self.handler_costs = HandlerCosts()
        self.live_view = LiveView(config.web.trajectory_points)
        self.control: ControlServer | None = None
        self.estimator_delay_s, self._next_delay = 0.0, 0.0
        self._frames: asyncio.Queue[FrameSample] | None = None
        self._stop_event: asyncio.Event | None = None
        self._frontend_pool = ThreadPoolExecutor(1, thread_name_prefix="frontend")
        rt = config.runtime
        self._worker = FrontendWorker(rt.frontend_hang_s) if rt.frontend_process else None
        self._work_pool = ThreadPoolExecutor(1, thread_name_prefix="build")
        self._pose_pool = ThreadPoolExecutor(1, thread_name_prefix="pose-writer")
        self._pose_future: Future[None] | None = None
        self._builds: dict[int, asyncio.Future[Any]] = {}
        self._names: dict[asyncio.Future[Any], str] = {}  # running tasks (kept referenced)
        self._decision_timer: asyncio.TimerHandle | None = None
        self._decision_due = 0.0
        self._timer_fired: Callable[[Any], None] | None = None  # set while running
        self.exit_status = 0
        self._next_map_check = self._next_record = 0.0
        self._started = time.monotonic()
        self._tick_due = float("inf")  # the ticker's period is up then (an IMU sample runs it)
        self._tick_now: asyncio.Event | None = None
        self._camera_alive_seen: float | None = None

    # ------------------------------------------------------------------------- lifecycle

    async def run(self) -> int:
        self.loop = loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        self._frames = asyncio.Queue(maxsize=1)
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, self.request_stop, sig.name)
        self.control = control = control_server(self.cfg, self.handle_command)
        self._watch(await control.start(), "control socket")
        if self.record_path is not None:
            self.recorder = open_recorder(self.cfg, self.record_path)
            self.core.journal = RecorderJournal(self.recorder)
        self.can = open_output(
            self.cfg,
            self.link,
            threadsafe(loop, self._handler(self._on_speed, "speed sample")),
            threadsafe(loop, self.request_stop),
            self.recorder,
            threadsafe(loop, self._handler(self.core.lifted, "lift notice")),
        )
        self.imu_dev = open_imu(
            self.cfg,
            self._handler(self._on_imu, "IMU sample"),
            self.recorder,
            loop,
        )
        # the camera is alive when its frames arrive, whatever the front end does with them
        # (a frame searched for the pose can take a second there); the frames it drops
        # between are read at each decision (:meth:`_read_before_deciding`)
        arrived = self._handler(self._on_frame, "camera frame")
        self.camera = open_camera(self.cfg, asyncio_sink(loop, self._frames, arrived))
        await self.set_mode(self.start_mode)
        self._timer_fired = self._handler(self._decision_timer_fired, "decision timer")
        tasks = [self._spawn(self._ticker(), "ticker"), self._spawn(self._frame_task(), "frontend")]
        self.notifier.ready(self.core.status_line())
        log.info("running: mode %s, control socket %s", self.core.mode, control.path)
        try:
            await self._stop_event.wait()
        finally:
            await self._shutdown(tasks, control)
        return self.exit_status

    def request_stop(self, why: str = "stop requested") -> None:
        if not self.core.shutting_down:
            log.warning("shutting down (%s): halting the deck", why)
            self.core.shutdown()
        if self._stop_event is not None:
            self._stop_event.set()

    async def _shutdown(self, tasks: list[asyncio.Future[Any]], control: ControlServer) -> None:
        if not self.core.shutting_down:
            self.core.shutdown()
        self.notifier.stopping()
        self._decide(time.monotonic())
        self._timer_fired = None  # no more timed decisions
        if self._decision_timer is not None:
            self._decision_timer.cancel()
            self._decision_timer = None
        if self.can is not None:
            self.can.shutdown(time.monotonic())
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await control.close()
        if self.imu_dev is not None:
            self.imu_dev.stop()
        if self.camera is not None:
            self.camera.stop()
        if self.can is not None:
            self.can.close()
        if self.recorder is not None:
            self.recorder.close()
        self._frontend_pool.shutdown(wait=False, cancel_futures=True)
        if self._worker is not None:
            self._worker.close()
        self._work_pool.shutdown(wait=False, cancel_futures=True)
        self._pose_pool.shutdown(wait=True)
        log.info("stopped")

    def _spawn(self, coro: Awaitable[Any], name: str) -> asyncio.Future[Any]:
        return self._watch(asyncio.ensure_future(coro), name)

    def _watch(self, task: asyncio.Future[Any], name: str) -> asyncio.Future[Any]:
        self._names[task] = name
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Future[Any]) -> None:
        """Crash-only: a task that dies halts the deck and ends the process (exit 1)."""
        name = self._names.pop(task, "?")
        if not task.cancelled() and (exc := task.exception()) is not None:
            log.error("the %s task died (%r): halting and ending the process", name, exc)
            self.exit_status = 1
            self.request_stop(f"the {name} task died")

    def _handler(self, fn: Callable[[Any], None], name: str) -> Callable[[Any], None]:
        """A loop callback that ends the process if it raises, its CPU counted."""
        return crash_only(fn, name, self._handler_failed, self.handler_costs)

    def _handler_failed(self, why: str) -> None:
        self.exit_status = 1
        self.request_stop(why)

    # --------------------------------------------------------------------------- inputs

    def _on_imu(self, s: ImuSample) -> None:
        self._read_before_deciding()
        now = time.monotonic()
        self._send(self.core.imu(s, now), time.monotonic(), decided_at=now)
        if now >= self._tick_due and self._tick_now is not None:
            self._tick_due = float("inf")
            self._tick_now.set()  # the ticker runs in this wake-up of the loop

    def _on_frame(self, frame: FrameSample) -> None:
        problem = self._frame_problem(frame)
        if problem:
            self.core.camera_refused(time.monotonic(), problem)
        else:
            self.core.camera_frame(time.monotonic())

    def _read_before_deciding(self) -> None:
        """What is read at each decision, not woken for: the supervisor's messages (the
        ground speed among them), and the newest frame the camera dropped between the
        front end's, if it is news. Decisions come with every IMU sample, and at least every
        ``DECIDE_MAX_S`` without (the decision timer)."""
        if self.can is not None:
            self.can.poll()
        alive_at = None if self.camera is None else self.camera.alive_at
        if alive_at is not None and alive_at != self._camera_alive_seen:
            self._camera_alive_seen = alive_at
            self.core.camera_alive(alive_at)

    def _frame_problem(self, frame: FrameSample) -> str:
        """Why a frame cannot be used at all, or "": its size must be the calibration's (a
        camera may deliver another mode than the one asked for; its pixels would be lifted
        to bearings through the wrong intrinsics)."""
        h, w = frame.image.shape[:2]
        cam = self.camera_model
        if (w, h) == (cam.width, cam.height):
            return ""
        return (
            f"the camera delivers {w}x{h} frames, the calibration is for {cam.width}x"
            f"{cam.height} ({self.cfg.camera.calibration}): frames refused; give camera.width/"
            "height a mode the camera has (v4l2-ctl --list-formats-ext) and calibrate at it"
        )

    def _on_speed(self, s: SpeedSample) -> None:
        self.core.speed(s)

    async def _frame_task(self) -> None:
        assert self._frames is not None
        loop = asyncio.get_running_loop()
        while True:
            frame = await self._frames.get()
            started = time.thread_time()
            if self.recorder is not None:
                self.recorder.frame(time.monotonic_ns(), frame.t, frame.sequence, frame.image)
            if self._frame_problem(frame):  # refused as it arrived
                continue
            target = self.core.frame_pipeline()
            if target is None:
                continue
            serial, pipe = target
            try:
                r, search = pipe.vision.prepare(frame.t), pipe.vision.wants_search()
                before = time.thread_time() - started  # the front end's wait is not counted
                tracks: FrameTracks = await loop.run_in_executor(
                    self._frontend_pool,
                    track_frame,
                    self._worker,
                    serial,
                    pipe.vision,
                    frame,
                    r,
                    search,
                )
            except FrontendWorkerDied:
                raise  # crash-only: the task dies, the deck halts, the process ends (exit 1)
            except Exception as exc:
                self.core.frontend_error()
                log.error("front end failed on frame %d: %s", frame.sequence, exc)
                continue
            started = time.thread_time()
            self.core.tracks(serial, tracks)
            self.handler_costs.add("frame tracks", before + time.thread_time() - started)

    # ------------------------------------------------------------------- chains, decisions

    def _on_build(self, req: BuildRequest) -> None:
        """The core wants a chain: build it off the loop, then hand it back."""

        async def build() -> None:
            loop = asyncio.get_running_loop()
            try:
                pipe = await loop.run_in_executor(
                    self._work_pool, build_pipeline, self.cfg, self.camera_model, req
                )
            except Exception as exc:  # a map the checks let through: halt, do not crash-loop
                if req.kind != "mow":
                    raise
                self.core.map_invalid(f"{self.cfg.map.path}: cannot localize on it ({exc!r})")
                return
            self.core.install(req.serial, pipe)

        self._builds = {req.serial: self._spawn(build(), "chain build")}

    async def _built(self) -> None:
        """Wait for the chain the core asked for last (mode changes answer after it)."""
        for fut in list(self._builds.values()):
            with contextlib.suppress(Exception):
                await fut

    def _decide(self, now: float) -> Decision:
        self._read_before_deciding()
        d = self.core.decide(now)
        self._send(d, time.monotonic(), decided_at=now)
        return d

    def _send(self, d: Decision, now: float, decided_at: float) -> None:
        """Decision ``d``, made at ``decided_at``, out at ``now``."""
        sent = self.can is not None and self.can.send_decision(
            d, self.core.pose_xyh(), now, self.core.last_accel
        )
        if sent:
            self.core.halt_sent(time.monotonic())
        pose = self.core.take_pose_to_save()
        lawn_map = self.core.map
        idle = self._pose_future is None or self._pose_future.done()  # else skip this one
        if pose is not None and lawn_map is not None and idle:
            self._pose_future = self._pose_pool.submit(self.pose_file.save, pose, lawn_map.checksum)
        self._arm_decision_timer(now, decided_at)

    def _arm_decision_timer(self, now: float, decided_at: float | None = None) -> None:
        """The next decision nothing else will make: at the next staleness deadline (a
        silent sensor halts within a millisecond or two of its limit), when a CAN frame is
        due, or ``DECIDE_MAX_S`` after this one (the lease renewed while the IMU is late).
        The deadlines are those after the decision (``decided_at``, default ``now``), not
        after ``now``: one that ran out while the decision was being made and sent is due
        at once — counted from ``now`` it was skipped, and the halt waited for the next IMU
        sample (the bench: 6 of 30 speed gaps halted 20 ms after the limit on the
        estimation side)."""
        loop = self.loop
        if loop is None or self._timer_fired is None:  # not running, or shut down
            return
        since = now if decided_at is None else decided_at
        due = min(now + DECIDE_MAX_S, self.core.next_deadline(since) + 1e-4)
        if self.can is not None:
            due = min(due, self.can.next_due())
        if self._decision_timer is not None:
            self._decision_timer.cancel()
        self._decision_due = due
        self._decision_timer = loop.call_at(due, self._timer_fired, None)  # loop time: monotonic

    def _decision_timer_fired(self, _: Any = None) -> None:
        self._decision_timer = None
        now = time.monotonic()
        self.loop_lag.woke(self._decision_due, now)
        assert self.can is not None
        self.can.retry(now)
        self._decide(now)  # re-arms the timer
        self.can.tick(now)

    # ---------------------------------------------------------------------------- modes

    async def set_mode(self, mode: str, mow_areas: tuple[str, ...] | None = None) -> dict[str, Any]:
        if mode == "mow":  # mowing already: other areas, the same chain
            switched = self.core.switch_mow_areas(mow_areas)
            if switched is not None:
                if switched:
                    return {"ok": False, "error": switched}
                return {"ok": True, "mode": mode, "map_problem": self.core.map_problem}
        problem = self.core.set_mode(mode, mow_areas)
        if problem:
            return {"ok": False, "error": problem}
        if mode == "mow":
            await self._load_map()
        await self._built()
        return {"ok": True, "mode": mode, "map_problem": self.core.map_problem}

    async def _load_map(self) -> None:
        """Load and check the map (halt MAP_INVALID naming the problem)."""
        got = await self.map_file.load(self._work_pool)
        if isinstance(got, str):
            self.core.map_invalid(got)
            return
        if self.core.mode != "mow":
            return
        area = got.lawn_polygon().area
        log.info(
            "map %s: %d landmarks, %.1f m² to mow", self.map_file.path, len(got.landmarks), area
        )
        if self.recorder is not None:
            self.recorder.attach("map.json", got.to_bytes())
        self.core.map_loaded(got, self.pose_file.load(got))

    def _check_map_file(self) -> None:
        """Mow mode: a map file that changed is reloaded. The deck halts at once (MAP_INVALID,
        "checking") and runs again only when the new file has loaded and checked: an edited
        keep-out must not be mowed on the old map meanwhile, and a damaged file stops the deck
        within ``runtime.map_check_period_s``, not after its load in a child interpreter
        (about 0.35 s more)."""
        if not self.map_file.changed():
            return
        if not self.map_file.retrying():
            path = self.map_file.path
            log.warning("map file %s changed: halting until it is reloaded and checked", path)
            self.core.map_invalid(f"{path} changed: checking it before mowing on it")

        async def reload() -> None:
            got = await self.map_file.load(self._work_pool)
            if isinstance(got, str):
                self.core.map_invalid(got)
            elif self.core.mode == "mow":  # a chain that cannot be built: MAP_INVALID
                self.core.map_reloaded(got)

        self._spawn(reload(), "map reload")

    async def finish_teach(self) -> dict[str, Any]:
        pipe = self.core.begin_finish_teach()
        if isinstance(pipe, str):
            return {"ok": False, "error": pipe}
        loop = asyncio.get_running_loop()
        path = Path(self.cfg.map.path)
        log.info("teach: finishing (loop closure, boundary)")
        try:
            summary = await loop.run_in_executor(self._work_pool, teach_to_map_file, pipe, path)
        except Exception as exc:
            log.error("teach failed: %s (any previous map is untouched)", exc)
            self.core.end_finish_teach(error=str(exc))
            return {"ok": False, "error": f"teach failed: {exc}"}
        if self.recorder is not None:
            self.recorder.attach("map.json", path.read_bytes())
        self.core.end_finish_teach(summary=summary)
        log.info("teach: map saved to %s (%s)", path, summary)
        return {"ok": True, **summary}

    # ---------------------------------------------------------------------------- ticker

    async def _ticker(self) -> None:
        self._arm_decision_timer(time.monotonic())
        self._tick_now = tick_now = asyncio.Event()
        while True:
            due = time.monotonic() + TICK_S
            tick_now.clear()
            self._tick_due = due
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(tick_now.wait(), TICK_S + TICK_SLACK_S)
            self._tick_due = float("inf")
            now = time.monotonic()
            self.loop_lag.woke(due + TICK_SLACK_S, now)
            if self.estimator_delay_s and now >= self._next_delay:
                # fault injection: the estimation side blocked this long every 200 ms (a
                # computer too slow for it): its decisions come late, the leases run out
                self._next_delay = now + 0.2
                time.sleep(self.estimator_delay_s)
            self.live_view.sample(self.core, now)
            if self.recorder is not None and now >= self._next_record:
                self._next_record = now + 0.1
                record_estimate(self.recorder, self.core, now)
            if self.core.mode == "mow" and now >= self._next_map_check:
                self._next_map_check = now + self.cfg.runtime.map_check_period_s
                self._check_map_file()
            if self.cfg.runtime.auto_finish_teach and self.core.teach_loop_done():
                log.info("teach: loop detected (stopped back at the start); finishing")
                self._spawn(self.finish_teach(), "teach finish")
            self.notifier.tick(now, self.core.status_line())

    # --------------------------------------------------------------------------- control

    async def handle_command(self, cmd: str, args: dict[str, Any]) -> dict[str, Any]:
        return await handle_command(self, cmd, args)

    async def save_map(self, path: Path) -> None:
        assert self.core.map is not None
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._work_pool, save_map, self.core.map, path)

    def live(self, since: int, landmarks: bool) -> dict[str, Any]:
        """What the status page shows (:mod:`.live`)."""
        sup = getattr(self.link, "supervisor_status", None)
        return self.live_view.snapshot(self.core, time.monotonic(), since, landmarks, sup)

    def status(self) -> dict[str, Any]:
        now = time.monotonic()
        out = {
            "pid": os.getpid(),
            "uptime_s": round(now - self._started, 3),
            "now": now,
            **core_status(self.core, now),
            "map": str(self.cfg.map.path),
            "loop_lag_ms_over_5": self.loop_lag.lags_ms[-50:],
            "loop_lag_times": self.loop_lag.lag_times[-50:],
            "handler_cpu": self.handler_costs.status(),
            "control": self.control.status() if self.control else {},
            **device_status(self.imu_dev, self.camera, self.can, self.recorder),
        }
        out["counts"]["can_open_failures"] = self.can.open_failures if self.can else 0
        out["counts"]["pose_save_errors"] = self.pose_file.errors
        return out


__all__ = ["MODES", "Daemon"]
