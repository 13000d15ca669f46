"""The daemon (DESIGN.md §8): devices → time-ordered buffer → estimator → fail-safe permit.

One asyncio event loop owns all estimator state. Device readers run in their own threads (the
drivers' own) and hand each sample to the loop with ``call_soon_threadsafe``:

* IMU (VN-100): every sample is pushed into the :class:`~mowerhw.buffer.SensorBuffer`, the
  estimator consumes what is ready in time order, and the permit is decided at once — so a
  halt goes out within the IMU period of the sample that revealed it;
* ground speed (ISO 11783 GBSD on CAN): a reader thread decodes frames (unknown ones are
  counted and ignored) and hands samples to the loop;
* camera: frames go to a one-slot queue (the oldest is dropped); the costly tracking runs on a
  worker thread, one frame at a time, so a slow frame never delays IMU processing or the
  permit; its tracks enter the buffer stamped with the frame's capture time.

A ticker (waking at the next deadline, at least every 20 ms) sends the periodic ISB /
heartbeat / status frames, catches silent sensors (staleness is judged on the host clock of
arrival), watches the map file, and pings systemd's
watchdog — from the loop, so a hung estimator stops the pings and systemd restarts it.

Modes: idle (halt), teach (halt; maps), mow (permit when :class:`~.gate.PermitGate` allows).
An estimator exception or non-finite state halts with FAULT, rebuilds the estimator from the
last good pose, and the daemon carries on; it recovers by itself once localized again.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import shutil
import signal
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from drivers.camera_v4l2 import CameraSource, V4l2Camera, asyncio_sink
from drivers.isobus import open_bus
from drivers.isobus_speed import SpeedReader, invalid_detail
from drivers.permit import PermitSender, Status
from drivers.vn100 import Vn100
from mowerhw.buffer import SensorBuffer
from mowerhw.camera import load_camchain
from mowerhw.config import Config
from mowerhw.fileio import write_atomic
from mowerhw.geometry import quat_to_rotmat
from mowerhw.map import LawnMap, MapError
from mowerhw.map import load as load_map
from mowerhw.mow.containment import Reason
from mowerhw.runtime.control import ControlServer
from mowerhw.runtime.gate import Decision, PermitGate
from mowerhw.runtime.pipelines import TRACKS, MowPipeline, TeachPipeline, feed_ready
from mowerhw.runtime.sdnotify import Notifier
from mowerhw.samples import ImuSample, SpeedSample, Stream

log = logging.getLogger("mowerhw.daemon")

MODES = ("idle", "teach", "mow")
TICK_MIN_S = 0.0005
#: a pose saved by a previous run is resumed from if it is at most this old (s)
RESUME_MAX_AGE_S = 120.0
#: good frames a rebuilt or resumed estimator needs before it may permit (4 Hz: 2.5 s)
REBUILT_FRAMES = 10
TICK_MAX_S = 0.02


class Daemon:
    """``await Daemon(config).run()`` until SIGTERM / SIGINT or :meth:`request_stop`."""

    def __init__(
        self, config: Config, mode: str | None = None, record: str | Path | None = None
    ) -> None:
        self.cfg = config
        self.record_path = Path(record) if record else None
        self.recorder: Any = None
        self.start_mode = mode or config.runtime.mode
        if self.start_mode not in MODES:
            raise ValueError(f"mode {self.start_mode!r} is not one of {', '.join(MODES)}")
        self.mode = "idle"
        self.camera_model = load_camchain(config.camera.calibration, config.camera.camchain_key)
        self.r_bi = quat_to_rotmat(np.asarray(config.imu.q_bi, dtype=np.float64))
        self.buffer = SensorBuffer(capacity={TRACKS: 16})
        self.gate = PermitGate.from_config(config)
        self.last_arrival: dict[str, float | None] = {"imu": None, "speed": None, "camera": None}
        self.counts: Counter[str] = Counter()
        self.pipeline: TeachPipeline | MowPipeline | None = None
        self.map: LawnMap | None = None
        self.map_problem = ""
        self.fault = ""
        self.teach_state = ""  # "", "recording", "finishing", "saved", "failed: …"
        self.last_teach: dict[str, Any] = {}
        self.halt_latencies: list[dict[str, Any]] = []
        self.decision: Decision = self.gate.current
        self.notifier = Notifier()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.sender: PermitSender | None = None
        self.bus: Any = None
        self.imu_dev: Vn100 | None = None
        self.camera: CameraSource | None = None
        self.speed_reader = SpeedReader(
            config.speed.source, config.speed.sensor_address, config.speed.ccvs1_direction
        )
        #: per stream, why its newest data could not be used (arrival, the device's words)
        self.stream_notes: dict[str, tuple[float, str]] = {}
        self._frames: asyncio.Queue | None = None
        self._stop_event: asyncio.Event | None = None
        self._shutting_down = False
        self._can_stop = threading.Event()
        self._can_thread: threading.Thread | None = None
        self._frontend_pool = ThreadPoolExecutor(1, thread_name_prefix="frontend")
        self._work_pool = ThreadPoolExecutor(1, thread_name_prefix="teach-finish")
        self._pose_pool = ThreadPoolExecutor(1, thread_name_prefix="pose-writer")
        self._pose_future: Any = None
        self.loop_lag_ms: list[float] = []  # how late the ticker woke (the loop was busy)
        self._inject: str = ""
        self._finish_task: asyncio.Task | None = None
        self._map_reload: asyncio.Future | None = None
        self._tasks: set[asyncio.Future] = set()
        self._map_stat: tuple[int, int, int] | None = None
        self._next_map_check = 0.0
        self._next_watchdog = 0.0
        self._sd_status = ""
        self._last_good_pose: tuple[np.ndarray, ...] | None = None
        self._good_pose_count = 0
        self._next_pose_save = 0.0
        self._next_record = 0.0
        self._started = time.monotonic()

    # ------------------------------------------------------------------------- lifecycle

    async def run(self) -> int:
        self.loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        self._frames = asyncio.Queue(maxsize=1)
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                self.loop.add_signal_handler(sig, self.request_stop, sig.name)
        rt = self.cfg.runtime
        control = ControlServer(rt.control_socket, self.handle_command, rt.socket_mode)
        await control.start()
        self._start_recorder()
        self._open_can()
        self._start_imu()
        self._start_camera()
        await self.set_mode(self.start_mode)
        tasks = [
            asyncio.create_task(self._ticker(), name="ticker"),
            asyncio.create_task(self._frame_task(), name="frontend"),
        ]
        self.notifier.ready(self._status_line())
        log.info(
            "running: mode %s, control socket %s, pid %d", self.mode, rt.control_socket, os.getpid()
        )
        try:
            await self._stop_event.wait()
        finally:
            await self._shutdown(tasks, control)
        return 0

    def request_stop(self, why: str = "stop requested") -> None:
        if not self._shutting_down:
            log.warning("shutting down (%s): halting the deck", why)
        self._shutting_down = True
        if self._stop_event is not None:
            self._stop_event.set()

    async def _shutdown(self, tasks: list[asyncio.Task], control: ControlServer) -> None:
        self._shutting_down = True
        self.notifier.stopping()
        self._decide(time.monotonic())
        if self.sender is not None:
            self.sender.shutdown(time.monotonic())
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await control.close()
        if self.imu_dev is not None:
            self.imu_dev.stop()
        if self.camera is not None:
            self.camera.stop()
        self._can_stop.set()
        if self._can_thread is not None:
            self._can_thread.join(timeout=1.0)
        if self.bus is not None:
            with contextlib.suppress(Exception):
                self.bus.shutdown()
        if self.recorder is not None:
            self.recorder.close()
        self._frontend_pool.shutdown(wait=False, cancel_futures=True)
        self._work_pool.shutdown(wait=False, cancel_futures=True)
        self._pose_pool.shutdown(wait=True)
        log.info("stopped")

    # --------------------------------------------------------------------------- devices

    def _start_recorder(self) -> None:
        if self.record_path is None:
            return
        import yaml

        from mowerhw.config import config_to_dict
        from mowerhw.recording import Recorder

        files = {"calibration.yaml": Path(self.cfg.camera.calibration)}
        if Path(self.cfg.map.path).exists():
            files["map.json"] = Path(self.cfg.map.path)
        attachments = {}
        for name, path in files.items():
            try:
                attachments[name] = path.read_bytes()
            except OSError as exc:
                log.warning("recording: cannot attach %s (%s)", path, exc)
        self.recorder = Recorder(
            self.record_path,
            yaml.safe_dump(config_to_dict(self.cfg), sort_keys=False),
            attachments,
        )
        if self.recorder.error:
            log.error("recording to %s failed: %s", self.record_path, self.recorder.error)
        else:
            log.info("recording to %s", self.record_path)

    def _record_estimate(self, now: float) -> None:
        rec = self.recorder
        pipe = self.pipeline
        if rec is None or not rec.ok:
            return
        d = self.decision
        if isinstance(pipe, TeachPipeline) and pipe.teacher.phase == "driving":
            pos, q = pipe.teacher.world_pose()
            rec.estimate(
                int(now * 1e9),
                "teach",
                pos,
                q,
                np.zeros(36),
                "TEACH",
                False,
                d.reason,
                float("nan"),
                None,
            )
            return
        if not isinstance(pipe, MowPipeline):
            return
        p = pipe.localizer.pose()
        rec.estimate(
            int(now * 1e9),
            self.mode,
            p.position,
            p.quaternion,
            p.covariance,
            str(d.state),
            d.permit,
            d.reason,
            pipe.localizer.sigma_xy(),
            d.signed_distance_m,
        )

    def _open_can(self) -> None:
        c = self.cfg.can
        try:
            extra = {"port": c.udp_port} if c.interface == "udp_multicast" else {}
            self.bus = open_bus(c.interface, c.channel, c.bitrate, **extra)
        except Exception as exc:  # can.CanError, OSError: retried by the ticker
            if self.bus is None and self.counts["can_open_failures"] == 0:
                log.error("CAN %s %s: cannot open (%s); retrying", c.interface, c.channel, exc)
            self.counts["can_open_failures"] += 1
            return
        p = self.cfg.permit
        self.sender = PermitSender(
            self.bus, c.source_address, p.status_pgn, p.period_s, p.heartbeat_period_s
        )
        self._can_stop.clear()
        self._can_thread = threading.Thread(target=self._can_reader, name="can-rx", daemon=True)
        self._can_thread.start()
        log.info("CAN %s %s open, sending as 0x%02X", c.interface, c.channel, c.source_address)

    def _can_reader(self) -> None:
        """Ground speed from the bus (DESIGN.md §7); everything else is counted and ignored."""
        loop = self.loop
        own = self.cfg.can.source_address
        while not self._can_stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.1)
            except Exception as exc:  # the bus went away: the ticker notices staleness
                log.warning("CAN receive failed: %s", exc)
                self._can_stop.wait(0.5)
                continue
            if msg is None:
                continue
            now = time.monotonic()
            rec = self.recorder
            if rec is not None:
                mine = msg.is_extended_id and (msg.arbitration_id & 0xFF) == own  # our echo
                rec.can(
                    int(now * 1e9),
                    msg.arbitration_id,
                    bytes(msg.data),
                    msg.is_extended_id,
                    not mine,
                )
            if not msg.is_extended_id or (msg.arbitration_id & 0xFF) == own:
                continue
            sample = self.speed_reader.handle(msg.arbitration_id, bytes(msg.data), now)
            if sample is not None and loop is not None:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(self._on_speed, sample)

    def _start_imu(self) -> None:
        c = self.cfg.imu
        loop = self.loop

        def on_sample(s: ImuSample) -> None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._on_imu, s)  # type: ignore[union-attr]

        self.imu_dev = Vn100(
            c.port,
            baudrate=c.baudrate,
            initial_baudrate=c.initial_baudrate,
            rate_hz=c.rate_hz,
            output=c.output,
            low_latency=c.low_latency,
            reconnect_max_backoff_s=c.reconnect_max_backoff_s,
            gyro_source=c.gyro_source,
            configure_sensor=c.configure_sensor,
            on_sample=on_sample,
            on_raw=(lambda data, ns: rec.serial(ns, data)) if (rec := self.recorder) else None,
        )
        self.imu_dev.start()

    def _start_camera(self) -> None:
        c = self.cfg.camera
        if c.driver == "stream":
            from drivers.camera_stream import StreamCamera

            self.camera = StreamCamera(c.device)
        elif c.driver == "mock":
            from drivers.mock.camera import MockCamera

            self.camera = MockCamera(fps=c.fps, width=c.width, height=c.height)
        else:
            self.camera = V4l2Camera(
                c.device, width=c.width, height=c.height, fps=c.fps, pixel_format=c.pixel_format
            )
        sink = asyncio_sink(self.loop, self._frames)  # type: ignore[arg-type]

        def on_frame(frame: Any) -> None:
            sink(frame)

        self.camera.start(on_frame)

    # ------------------------------------------------------------------ samples → estimator

    def _on_imu(self, s: ImuSample) -> None:
        now = time.monotonic()
        self.last_arrival["imu"] = now
        self.counts["imu"] += 1
        gyro = self.r_bi @ s.gyro
        self.buffer.push(Stream.IMU, ImuSample(s.t, gyro, None, s.device_time_ns, s.host_time_ns))
        pipe = self.pipeline
        if pipe is not None:
            pipe.vision.imu(s.t, gyro)  # gyro history for the front end's derotation
        self._consume(s.t)
        arrival = s.host_time_ns * 1e-9 if s.host_time_ns is not None else now
        self._decide(time.monotonic(), arrival)

    def _on_speed(self, s: SpeedSample) -> None:
        if s.valid:  # an invalid reading is not a fresh speed
            self.last_arrival["speed"] = s.t
            self.stream_notes.pop("speed", None)
        else:
            self.stream_notes["speed"] = (s.t, invalid_detail(s))
        self.counts["speed" if s.valid else "speed_invalid"] += 1
        self.buffer.push(Stream.SPEED, s)

    def _consume(self, newest_t: float) -> None:
        """Feed the estimator everything ready, in time order (teach holds back ``lag_s`` so
        frames, which come late, are not overtaken by the IMU)."""
        pipe = self.pipeline
        if pipe is None:
            self.buffer.pop_ready()
            return
        if self.mode == "teach" and self.teach_state != "recording":
            return
        try:
            if self._inject == "exception":
                self._inject = ""
                raise RuntimeError("injected estimator exception (fault injection)")
            feed_ready(pipe, self.buffer, newest_t - pipe.lag_s)
            if self._inject == "nan" and isinstance(pipe, MowPipeline):
                self._inject = ""
                pipe.localizer.ekf.x[:] = np.nan  # fault injection: a diverged estimator
        except Exception as exc:
            self._estimator_fault(f"estimator raised {type(exc).__name__}: {exc}", exc)

    def _estimator_fault(self, what: str, exc: BaseException | None = None) -> None:
        """Halt (FAULT), drop the estimator, rebuild it off the loop from the last good pose."""
        self.counts["estimator_faults"] += 1
        self.fault = f"{what}; estimator restarted"
        if exc is not None:
            log.error("FAULT: %s", self.fault, exc_info=exc)
        else:
            log.error("FAULT: %s", self.fault)
        self.buffer.pop_ready()
        self.pipeline = None
        if self.mode == "mow" and self.map is not None:
            self._spawn(self._install_mow(self.map, self._last_good_pose))
        elif self.mode == "teach":
            log.error("teach: the recording so far is lost; drive the loop again")
            self._spawn(self._install_teach())

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _install_teach(self) -> None:
        loop = asyncio.get_running_loop()
        pipe = await loop.run_in_executor(
            self._work_pool, TeachPipeline, self.cfg, self.camera_model
        )
        if self.mode == "teach":
            self.buffer.pop_ready()
            self.pipeline = pipe
            self.teach_state = "recording"
            log.info("teach: recording; hold still for the gyro calibration, then drive the edge")

    async def _install_mow(
        self, lawn_map: LawnMap, start_pose: Any = None, resumed: bool = False
    ) -> None:
        """Build the localizer + front end off the loop (it takes a while), then use it."""
        loop = asyncio.get_running_loop()
        pipe = await loop.run_in_executor(
            self._work_pool, _build_mow, self.cfg, self.camera_model, lawn_map, start_pose
        )
        if self.mode != "mow" or self.map is not lawn_map:
            return  # the mode or the map changed meanwhile
        if start_pose is not None:
            self._relocalize(pipe, start_pose, calibrate=resumed)
        self.buffer.pop_ready()
        self.pipeline = pipe

    @staticmethod
    def _relocalize(pipe: MowPipeline, pose: Any, calibrate: bool = False) -> None:
        """A new localizer resumes from a pose it had, widened: 0.1 m, 5° after an estimator
        fault in this run; 0.12 m, 6° after a restart (saved at 10 Hz, the mower stopped
        within 0.3 s), and then it calibrates the gyro first (the mower stands)."""
        loc = pipe.localizer
        if calibrate:  # a restart: the mower stopped within 0.3 s of the last saved pose
            # (σ under a third of the 0.4 m pane spacing of window landmarks: a wider prior
            # was seen to lock onto the neighbouring corners, 0.43 m off, on the bench)
            loc.reinitialise(pose[:2], 0.12, math.radians(6.0))
        else:  # an estimator rebuilt in this run: from a pose ≤ 0.1 s old, tracked since
            loc.reinitialise(pose[:2], 0.05, math.radians(3.0))
            if len(pose) > 2:
                loc.ekf.bg = np.asarray(pose[2], dtype=np.float64).copy()  # keep calibration
        loc.calibrating = calibrate
        loc.require_frames(REBUILT_FRAMES)  # a run of good frames before it is trusted

    def _pose_file(self) -> Path:
        return Path(self.cfg.runtime.pose_file)

    def _queue_pose_save(self, pipe: MowPipeline) -> None:
        """Hand the newest localized pose to the pose writer thread: file system calls never
        run on the event loop (a rename can stall for 100 ms behind a journal commit)."""
        if self._pose_future is not None and not self._pose_future.done():
            return  # the previous one is still being written: skip this one
        loc = pipe.localizer
        doc = {
            "wall_time": time.time(),
            "map_checksum": pipe.map.checksum,
            "position": loc.ekf.x.tolist(),
            "quaternion": loc.ekf.q.tolist(),
        }
        self._pose_future = self._pose_pool.submit(self._save_pose, doc)

    def _save_pose(self, doc: dict[str, Any]) -> None:
        """The newest localized pose, for a restart (a crash, SIGKILL, power loss) to resume
        from instead of the dock. Renamed into place (no fsync: at worst an older pose)."""
        try:
            write_atomic(self._pose_file(), json.dumps(doc).encode(), durable=False)
        except OSError as exc:
            self.counts["pose_save_errors"] += 1
            if self.counts["pose_save_errors"] == 1:
                log.warning("cannot save the pose for restarts: %s", exc)

    def _saved_pose(self, lawn_map: LawnMap) -> Any:
        """The pose saved by a previous run, if it is recent and of this map."""
        try:
            doc = json.loads(self._pose_file().read_text())
            age = time.time() - float(doc["wall_time"])
            pos = np.asarray(doc["position"], dtype=np.float64).reshape(3)
            quat = np.asarray(doc["quaternion"], dtype=np.float64).reshape(4)
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if doc.get("map_checksum") != lawn_map.checksum or not 0 <= age <= RESUME_MAX_AGE_S:
            return None
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
            return None
        log.info("resuming from the pose saved %.1f s ago (σ widened to 0.12 m, 6°)", age)
        return pos, quat / np.linalg.norm(quat)

    async def _frame_task(self) -> None:
        assert self._frames is not None
        loop = asyncio.get_running_loop()
        while True:
            frame = await self._frames.get()
            self.last_arrival["camera"] = time.monotonic()
            self.counts["frames"] += 1
            if self.recorder is not None:
                self.recorder.frame(time.monotonic_ns(), frame.t, frame.sequence, frame.image)
            pipe = self.pipeline
            if pipe is None or (self.mode == "teach" and self.teach_state != "recording"):
                continue
            try:
                r = pipe.vision.prepare(frame.t)
                tracks = await loop.run_in_executor(
                    self._frontend_pool, pipe.vision.track, frame.t, frame.image, r
                )
            except Exception as exc:
                self.counts["frontend_errors"] += 1
                log.error("front end failed on frame %d: %s", frame.sequence, exc)
                continue
            if self.pipeline is not pipe:
                continue  # the mode changed meanwhile
            self.buffer.push(TRACKS, tracks)
            if isinstance(pipe, MowPipeline):
                self._consume(math.inf)  # the localizer takes late frames itself

    # -------------------------------------------------------------------------- decision

    def _decide(self, now: float, revealed_at: float | None = None) -> Decision:
        pipe = self.pipeline
        containment = None
        if isinstance(pipe, MowPipeline) and not self.map_problem:
            if not pipe.finite():
                self._estimator_fault("estimator state is not finite (NaN/inf)")
                pipe = self.pipeline
            if isinstance(pipe, MowPipeline):
                if self.fault and pipe.localizer.localized:
                    log.info("fault cleared: localized again after the estimator restart")
                    self.fault = ""
                containment = pipe.containment(now)
                self._good_pose_count += 1
                if self._good_pose_count % 10 == 0 and pipe.finite():
                    self._last_good_pose = pipe.last_good_pose()
                if now >= self._next_pose_save and pipe.localizer.localized and not self.fault:
                    self._next_pose_save = now + 0.1
                    self._queue_pose_save(pipe)
        stale = self.gate.stale(now, self.last_arrival, self.stream_notes)
        d = self.gate.decide(
            now,
            self.mode,
            self.last_arrival,
            containment,
            self.map_problem,
            self.fault,
            self._shutting_down,
            stale,
        )
        self.decision = d
        if self.sender is not None:
            x = y = h = float("nan")
            if isinstance(pipe, MowPipeline):
                _, x, y, h, _ = pipe.pose()
            status = Status(d.state, d.permit, d.reason or "NONE", d.signed_distance_m, x, y, h)
            was = self.sender.permit
            self.sender.set(d.permit, now, status)
            if was and not d.permit:
                sent = time.monotonic()
                if stale is not None:
                    name = stale[0]
                    last = self.last_arrival[name]
                    limit = self.gate.stale_limits_s[name]
                    revealed_at = (last + limit) if last is not None else now
                reveal = revealed_at if revealed_at is not None else now
                self.halt_latencies.append(
                    {"reason": d.reason, "latency_ms": round((sent - reveal) * 1e3, 3), "t": sent}
                )
                del self.halt_latencies[:-1000]
        return d

    # ------------------------------------------------------------------------------ modes

    async def set_mode(self, mode: str) -> dict[str, Any]:
        if mode not in MODES:
            raise ValueError(f"mode {mode!r} is not one of {', '.join(MODES)}")
        if self.mode == "teach" and self.teach_state == "finishing":
            return {"ok": False, "error": "teach is finishing (loop closure); try again shortly"}
        self.buffer.pop_ready()
        self.fault = ""
        self.map_problem = ""
        self.pipeline = None
        self.map = None
        self.mode = mode
        log.info("mode %s", mode)
        if mode == "teach":
            self.teach_state = "starting"
            await self._install_teach()
        elif mode == "mow":
            await self._load_map_for_mow()
        return {"ok": True, "mode": mode, "map_problem": self.map_problem}

    async def _load_map_for_mow(self, start_pose: Any = None) -> None:
        """Load and check the map (halt MAP_INVALID naming the problem), then the estimator."""
        path = self.cfg.map.path
        loop = asyncio.get_running_loop()
        self._map_stat = _stat(path)
        try:
            lawn_map = await loop.run_in_executor(self._work_pool, _load_checked_map, path)
        except MapError as exc:
            self.map_problem = str(exc)
            self.map = None
            self.pipeline = None
            log.error("MAP_INVALID: %s", exc)
            return
        if self.mode != "mow":
            return
        self.map = lawn_map
        self.map_problem = ""
        log.info(
            "map %s: %d landmarks, %.1f m² to mow",
            path,
            len(lawn_map.landmarks),
            lawn_map.lawn_polygon().area,
        )
        resumed = False
        if start_pose is None:
            start_pose = self._saved_pose(lawn_map)
            resumed = start_pose is not None
        await self._install_mow(lawn_map, start_pose, resumed)

    def _check_map_file(self) -> None:
        """Mow mode: a map file that changed is reloaded (an edited keep-out zone takes
        effect; a corrupt file halts with MAP_INVALID until it is fixed)."""
        st = _stat(self.cfg.map.path)
        if st == self._map_stat or self._map_reload is not None:
            return
        log.warning("map file %s changed: reloading", self.cfg.map.path)
        self._map_stat = st
        old = self.map
        pose = self._last_good_pose

        async def reload() -> None:
            try:
                path = self.cfg.map.path
                loop = asyncio.get_running_loop()
                try:
                    lawn_map = await loop.run_in_executor(self._work_pool, _load_checked_map, path)
                except MapError as exc:
                    # halt; the estimator keeps tracking on the map in memory, so a restored
                    # file resumes at once
                    self.map_problem = str(exc)
                    log.error("MAP_INVALID: %s", exc)
                    return
                if old is not None and lawn_map.checksum == old.checksum:
                    self.map_problem = ""
                    log.info("map file valid again, same map (checksum %s)", old.checksum[:19])
                    if self.pipeline is None:
                        await self._install_mow(old, pose)
                    return
                self.map, self.map_problem, self.pipeline = lawn_map, "", None
                log.info("new map loaded: %d landmarks", len(lawn_map.landmarks))
                await self._install_mow(lawn_map, pose)
            finally:
                self._map_reload = None

        self._map_reload = asyncio.ensure_future(reload())

    async def finish_teach(self) -> dict[str, Any]:
        pipe = self.pipeline
        if self.mode != "teach" or not isinstance(pipe, TeachPipeline):
            return {"ok": False, "error": f"not teaching (mode {self.mode})"}
        if self.teach_state != "recording":
            return {"ok": False, "error": f"teach is {self.teach_state}"}
        self.teach_state = "finishing"
        self.buffer.pop_ready()
        loop = asyncio.get_running_loop()
        path = Path(self.cfg.map.path)
        t0 = time.monotonic()
        log.info("teach: finishing (loop closure, boundary)")
        try:
            result, lawn_map = await loop.run_in_executor(self._work_pool, pipe.finish)
            await loop.run_in_executor(self._work_pool, _save_map, lawn_map, path)
        except Exception as exc:
            self.teach_state = f"failed: {exc}"
            log.error("teach failed: %s (any previous map is untouched)", exc)
            self.pipeline = None
            self.mode = "idle"
            return {"ok": False, "error": f"teach failed: {exc}"}
        self.last_teach = {
            "map": str(path),
            "png": str(path.with_suffix(".png")),
            "landmarks": len(lawn_map.landmarks),
            "boundary_points": int(lawn_map.boundary.shape[0]),
            "area_m2": round(float(lawn_map.lawn_polygon().area), 2),
            "loop_closure": result.closure.reason,
            "finish_s": round(time.monotonic() - t0, 3),
            "checksum": lawn_map.checksum,
        }
        if self.recorder is not None:
            self.recorder.attach("map.json", path.read_bytes())
        self.teach_state = "saved"
        self.pipeline = None
        self.mode = "idle"
        log.info("teach: map saved to %s (%s)", path, self.last_teach)
        return {"ok": True, **self.last_teach}

    # ----------------------------------------------------------------------------- ticker

    async def _ticker(self) -> None:
        while True:
            wait = self._next_tick_wait(time.monotonic())
            due = time.monotonic() + wait
            await asyncio.sleep(wait)
            now = time.monotonic()
            lag = (now - due) * 1e3
            if lag > 5.0:  # the loop was blocked: keep the evidence (status: loop_lag_ms)
                self.loop_lag_ms.append(round(lag, 1))
                del self.loop_lag_ms[:-200]
                if lag > 50.0:
                    log.warning("event loop was blocked for %.0f ms", lag)
            if self.sender is None and self.counts["can_open_failures"] and now % 1.0 < TICK_MAX_S:
                self._open_can()
            self._decide(now)
            if self.sender is not None:
                self.sender.tick(now)
            if self.recorder is not None and now >= self._next_record:
                self._next_record = now + 0.1
                self._record_estimate(now)
            if self.mode == "mow" and now >= self._next_map_check:
                self._next_map_check = now + self.cfg.runtime.map_check_period_s
                self._check_map_file()
            pipe = self.pipeline
            if (
                isinstance(pipe, TeachPipeline)
                and self.teach_state == "recording"
                and self.cfg.runtime.auto_finish_teach
                and pipe.loop_done()
            ):
                log.info("teach: loop detected (stopped back at the start); finishing")
                self._finish_task = asyncio.create_task(self.finish_teach())
            period = self.notifier.watchdog_period_s
            if period is not None and now >= self._next_watchdog:
                self._next_watchdog = now + period
                self.notifier.watchdog()
            line = self._status_line()
            if line != self._sd_status:
                self._sd_status = line
                self.notifier.status(line)

    def _next_tick_wait(self, now: float) -> float:
        """Sleep until the next thing due: a sensor's staleness deadline (so a silent sensor
        halts within a millisecond or two of its limit), the next periodic CAN frame, or at
        most ``TICK_MAX_S``."""
        due = now + TICK_MAX_S
        for name, limit in self.gate.stale_limits_s.items():
            last = self.last_arrival[name]
            if last is not None and last + limit > now:
                due = min(due, last + limit + 1e-4)
        if self.sender is not None:
            due = min(due, self.sender.next_due())
        return max(TICK_MIN_S, due - now)

    def _status_line(self) -> str:
        d = self.decision
        if self.mode == "teach":
            return f"teach: {self.teach_state}; deck halted"
        if d.permit:
            return f"{self.mode}: {d.state}, mowing permitted"
        return f"{self.mode}: {d.state}, halted ({d.reason})"

    # ---------------------------------------------------------------------------- control

    async def handle_command(self, cmd: str, args: dict[str, Any]) -> dict[str, Any]:
        if cmd == "status":
            return {"ok": True, **self.status()}
        if cmd in MODES:
            return await self.set_mode(cmd)
        if cmd == "finish-teach":
            return await self.finish_teach()
        if cmd == "save-map":
            return await self._save_map_command(args)
        if cmd == "fault":
            if not self.cfg.runtime.fault_injection:
                return {"ok": False, "error": "fault injection is off (runtime.fault_injection)"}
            kind = str(args.get("kind") or (args.get("args") or [""])[0])
            if kind not in ("nan", "exception"):
                return {"ok": False, "error": f"fault kind {kind!r}; allowed: nan, exception"}
            self._inject = kind
            log.warning("fault injection: %s", kind)
            return {"ok": True, "injected": kind}
        return {"ok": False, "error": f"unknown command {cmd!r}"}

    async def _save_map_command(self, args: dict[str, Any]) -> dict[str, Any]:
        if self.mode == "teach" and self.teach_state == "recording":
            return await self.finish_teach()
        target = args.get("path") or (args.get("args") or [None])[0]
        if self.map is None:
            return {"ok": False, "error": "no map loaded (mow mode loads one; teach makes one)"}
        path = Path(target) if target else Path(self.cfg.map.path)
        loop = asyncio.get_running_loop()
        try:
            await loop.run_in_executor(self._work_pool, _save_map, self.map, path)
        except (MapError, OSError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True, "map": str(path)}

    def status(self) -> dict[str, Any]:
        now = time.monotonic()
        d = self.decision
        pipe = self.pipeline
        out: dict[str, Any] = {
            "pid": os.getpid(),
            "uptime_s": round(now - self._started, 3),
            "now": now,
            "mode": self.mode,
            "permit": d.permit,
            "state": str(d.state),
            "reason": d.reason,
            "detail": d.detail,
            "signed_distance_m": None if math.isnan(d.signed_distance_m) else d.signed_distance_m,
            "sensor_age_s": {
                k: (None if v is None else round(now - v, 4)) for k, v in self.last_arrival.items()
            },
            "counts": dict(self.counts),
            "map": str(self.cfg.map.path),
            "map_problem": self.map_problem,
            "fault": self.fault,
            "teach": {"state": self.teach_state, **self.last_teach},
            "halt_latencies": self.halt_latencies[-200:],
            "loop_lag_ms_over_5": self.loop_lag_ms[-50:],
            "imu_driver": vars(self.imu_dev.stats) if self.imu_dev else {},
            "imu_parser": self.imu_dev.parser.stats.as_dict() if self.imu_dev else {},
            "imu_messages": vars(self.imu_dev.extractor.stats) if self.imu_dev else {},
            "speed_reader": vars(self.speed_reader.stats),
            "permit_sender": vars(self.sender.stats) if self.sender else {},
            "recording": self.recorder.status() if self.recorder is not None else None,
        }
        if isinstance(pipe, MowPipeline):
            t, x, y, h, sig = pipe.pose()
            out["pose"] = {"t": t, "x": x, "y": y, "heading": h, "sigma_xy_m": sig}
            out["localizer"] = pipe.status()
        elif isinstance(pipe, TeachPipeline):
            out["teach"].update(pipe.status())
        return out


def _stat(path: Path) -> tuple[int, int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


def _load_checked_map(path: Path) -> LawnMap:
    lawn_map = load_map(path)
    problems = lawn_map.problems()
    if problems:
        raise MapError(f"{path}: " + "; ".join(problems))
    return lawn_map


def _build_mow(cfg: Config, camera: Any, lawn_map: LawnMap, start_pose: Any) -> MowPipeline:
    return MowPipeline(cfg, camera, lawn_map, start_pose=start_pose)


def _save_map(lawn_map: LawnMap, path: Path) -> None:
    """Write the map atomically (keeping the previous one as ``.bak``) and its PNG."""
    path = Path(path)
    if path.exists():
        with contextlib.suppress(OSError):
            shutil.copy2(path, path.with_name(path.name + ".bak"))
    lawn_map.save(path)
    try:
        import tempfile

        from mowerhw.plots import map_figure

        with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
            png = map_figure(lawn_map, Path(tmp) / "map.png", title=f"Lawn map {path.name}")
            write_atomic(path.with_suffix(".png"), png.read_bytes())
    except Exception as exc:
        log.warning("map picture not written: %s", exc)


def run_daemon(
    config: Config,
    mode: str | None = None,
    record: str | Path | None = None,
    duration_s: float | None = None,
) -> int:
    """Run until stopped; the exit status (0 after a clean stop)."""
    import gc
    import sys

    import cv2

    sys.setswitchinterval(0.001)  # the front-end thread must not hold the GIL for 5 ms
    cv2.setNumThreads(1)  # one frame at a time on one worker; OpenCV's pool would spin
    gc.collect()
    gc.freeze()  # the start-up objects (modules, config) are never scanned by a full collection
    started: list[float] = [0.0]

    def gc_watch(phase: str, info: dict[str, int]) -> None:  # a long collection stalls the loop
        if phase == "start":
            started[0] = time.perf_counter()
        elif (ms := (time.perf_counter() - started[0]) * 1e3) > 20.0:
            log.warning("garbage collection (generation %d) took %.0f ms", info["generation"], ms)

    gc.callbacks.append(gc_watch)
    daemon = Daemon(config, mode, record)

    async def main() -> int:
        if duration_s is not None:
            asyncio.get_running_loop().call_later(duration_s, daemon.request_stop, "duration")
        return await daemon.run()

    return asyncio.run(main())


__all__ = ["MODES", "Daemon", "Reason", "run_daemon"]
