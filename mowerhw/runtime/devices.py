"""The daemon's devices, opened from the config (docs/design.md §7): the VN-100, the camera,
the CAN bus (ground speed in, permit / halt out) and the recorder. Each hands its samples to a
callback on the device's own thread; the daemon moves them onto its event loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import can

from drivers.camera.base import CameraSource
from drivers.camera.v4l2 import V4l2Camera
from drivers.can.address_claim import AddressClaim, serve
from drivers.can.isobus import open_bus
from drivers.can.permit import PermitSender, Status
from drivers.can.speed import SpeedReader
from drivers.imu.vn100 import Vn100
from drivers.threaded import ThreadedDevice
from mowerhw.common.clocksync import FrameClock
from mowerhw.common.samples import FrameSample, ImuSample, SpeedSample
from mowerhw.config import Config
from mowerhw.mow.gate import Decision
from mowerhw.recording.mcap import Recorder
from mowerhw.runtime.core import RuntimeCore
from mowerhw.runtime.pipelines import MowPipeline
from mowerhw.supervisor.canport import address_claim, permit_sender

log = logging.getLogger("mowerhw.daemon")

#: how long the one-process daemon's permit frames may wait for room on the bus (s; the
#: permit supervisor's never wait)
SEND_TIMEOUT_S = 0.01


def open_imu(
    cfg: Config,
    on_sample: Callable[[ImuSample], None],
    recorder: Recorder | None,
    loop: asyncio.AbstractEventLoop | None = None,
) -> Vn100:
    """The VN-100 as configured, started (it reconnects by itself); read on ``loop`` when
    given (``on_sample`` then runs on it), else on the driver's thread."""
    c = cfg.imu
    dev = Vn100(
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
        on_raw=(lambda data, ns: recorder.serial(ns, data)) if recorder else None,
    )
    dev.start(loop)
    return dev


def open_camera(
    cfg: Config,
    on_frame: Callable[[FrameSample], None],
) -> CameraSource:
    """The camera driver ``camera.driver`` names, started: frames at ``camera.fps`` to
    ``on_frame``; the camera's other frames (``camera.device_fps``) are its ``alive_at``."""
    c = cfg.camera
    camera: CameraSource
    if c.driver == "stream":
        from drivers.camera.stream import StreamCamera

        camera = StreamCamera(c.device, fps=c.fps)
    elif c.driver == "mock":
        from drivers.camera.mock import MockCamera

        camera = MockCamera(fps=c.fps, device_fps=c.device_fps, width=c.width, height=c.height)
    else:
        camera = V4l2Camera(
            c.device,
            width=c.width,
            height=c.height,
            fps=c.fps,
            device_fps=c.device_fps,
            pixel_format=c.pixel_format,
            clock=FrameClock(c.timestamps),
        )
    camera.start(on_frame)
    return camera


class RecorderJournal:
    """The runtime core's journal, into the run's recording."""

    def __init__(self, recorder: Recorder) -> None:
        self.recorder = recorder

    def write(self, kind: str, payload: dict[str, Any]) -> None:
        self.recorder.journal(time.monotonic_ns(), kind, payload)


def open_recorder(cfg: Config, path: Path) -> Recorder:
    """A recording of this run: the config, the camera calibration and the map attached, and
    the runtime core's journal (so a replay gives the daemon's decisions)."""
    import yaml

    from mowerhw.config import config_to_dict
    from mowerhw.runtime.journal import JournalEncoder

    files = {"calibration.yaml": Path(cfg.camera.calibration)}
    if Path(cfg.map.path).exists():
        files["map.json"] = Path(cfg.map.path)
    attachments = {}
    for name, p in files.items():
        try:
            attachments[name] = p.read_bytes()
        except OSError as exc:
            log.warning("recording: cannot attach %s (%s)", p, exc)
    rec = Recorder(
        path,
        yaml.safe_dump(config_to_dict(cfg), sort_keys=False),
        attachments,
        journal_encoder=JournalEncoder().encode,
    )
    if rec.error:
        log.error("recording to %s failed: %s", path, rec.error)
    else:
        log.info("recording to %s", path)
    return rec


class CanFrames:
    """What a received CAN frame means here: recorded, and ground speed decoded (everything
    else is counted by the reader and ignored; our own echo is skipped)."""

    def __init__(
        self,
        cfg: Config,
        on_speed: Callable[[SpeedSample], None],
        recorder: Recorder | None = None,
    ) -> None:
        self.own = cfg.can.source_address
        self.on_speed = on_speed
        self.recorder = recorder
        self.speed_reader = SpeedReader(
            cfg.speed.source, cfg.speed.sensor_address, cfg.speed.ccvs1_direction
        )

    def handle(self, now: float, arbitration_id: int, data: bytes, extended: bool) -> None:
        mine = extended and (arbitration_id & 0xFF) == self.own
        if self.recorder is not None:
            self.recorder.can(int(now * 1e9), arbitration_id, data, extended, not mine)
        if not extended or mine:
            return
        sample = self.speed_reader.handle(arbitration_id, data, now)
        if sample is not None:
            self.on_speed(sample)


class DecisionOutput(Protocol):
    """Where the daemon's decisions go: straight onto CAN (:class:`CanLink`, one process) or
    to the permit supervisor as leases (:class:`mowerhw.supervisor.link.SupervisorLink`)."""

    open_failures: int

    def open(self) -> bool: ...
    def retry(self, now: float) -> None: ...
    def poll(self) -> None: ...
    def send_decision(
        self,
        d: Decision,
        pose_xyh: tuple[float, float, float],
        now: float,
        accel: tuple[float, float, float] | None = None,
    ) -> bool: ...
    def tick(self, now: float) -> None: ...
    def next_due(self) -> float: ...
    def shutdown(self, now: float) -> None: ...
    def close(self) -> None: ...
    def status(self) -> dict[str, Any]: ...


def open_output(
    cfg: Config,
    link: Any,
    on_speed: Callable[[SpeedSample], None],
    on_lost: Callable[[str], None],
    recorder: Recorder | None,
    on_lifted: Callable[[bool], None] | None = None,
) -> DecisionOutput:
    """Where decisions go, opened: the supervisor's ``link`` if there is one (it also says
    when the mower is lifted: ``on_lifted``), else CAN."""
    out: DecisionOutput = (
        CanLink(cfg, on_speed, recorder)
        if link is None
        else link.output(cfg, on_speed, on_lost, recorder, on_lifted)
    )
    out.open()
    return out


class CanLink(ThreadedDevice):
    """The CAN bus: the permit sender, and a receive thread decoding ground speed (everything
    else is counted and ignored). A bus that cannot be opened is retried by :meth:`retry`."""

    def __init__(
        self,
        cfg: Config,
        on_speed: Callable[[SpeedSample], None],
        recorder: Recorder | None = None,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.frames = CanFrames(cfg, on_speed, recorder)
        self.speed_reader = self.frames.speed_reader
        self.bus: can.BusABC | None = None
        self.sender: PermitSender | None = None
        self.open_failures = 0
        #: its source address, claimed when the bus opens (ISO 11783-5; None: not claimed)
        self.claim: AddressClaim | None = address_claim(cfg)

    def open(self) -> bool:
        c = self.cfg.can
        try:
            self.bus = open_bus(c.interface, c.channel, c.bitrate, udp_port=c.udp_port)
        except Exception as exc:  # can.CanError, OSError: retried
            if self.open_failures == 0:
                log.error("CAN %s %s: cannot open (%s); retrying", c.interface, c.channel, exc)
            self.open_failures += 1
            return False
        if self.claim is not None:  # the address first; the permit frames once it is ours
            self.claim.begin(time.monotonic())
        self._start_thread()
        log.info("CAN %s %s open, sending as 0x%02X", c.interface, c.channel, c.source_address)
        return True

    def send_decision(
        self,
        d: Decision,
        pose_xyh: tuple[float, float, float],
        now: float,
        accel: tuple[float, float, float] | None = None,
    ) -> bool:
        """The permit or halt of a decision, with the status frame; True if it stopped a
        permit (a halt just went out)."""
        sender = self._sender(now)
        if sender is None:
            return False
        status = Status(d.state, d.permit, d.reason or "NONE", d.signed_distance_m, *pose_xyh)
        return sender.set(d.permit, now, status) and not d.permit

    def tick(self, now: float) -> None:
        sender = self._sender(now)
        if sender is not None:
            sender.tick(now)

    def _sender(self, now: float) -> PermitSender | None:
        """The permit frames' sender while the address is ours (claims due sent first)."""
        if self.bus is None:
            return None
        if self.claim is not None and not serve(self.claim, self.bus, now):
            self.sender = None
            return None
        if self.sender is None:
            self.sender = permit_sender(self.cfg, self.bus, now, SEND_TIMEOUT_S)
        return self.sender

    def next_due(self) -> float:
        due = self.sender.next_due() if self.sender is not None else math.inf
        return min(due, self.claim.next_due()) if self.claim is not None else due

    def shutdown(self, now: float) -> None:
        if self.sender is not None:  # only while the address is ours
            self.sender.shutdown(now)

    def status(self) -> dict[str, Any]:
        return {
            "speed_reader": vars(self.speed_reader.stats),
            "permit_sender": vars(self.sender.stats) if self.sender else {},
            "can_address": self.claim.status() if self.claim is not None else None,
        }

    def poll(self) -> None:
        """Nothing to read before a decision: the receive thread hands the speed over."""

    def retry(self, now: float) -> None:
        """Try to open a bus that failed, about once a second."""
        if self.bus is None and self.open_failures and now % 1.0 < 0.02:
            self.open()

    thread_name = "can-rx"

    def _run(self) -> None:
        bus = self.bus
        assert bus is not None  # the thread starts once the bus is open
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=0.1)
            except Exception as exc:  # the bus went away: the gate notices staleness
                log.warning("CAN receive failed: %s", exc)
                self._stop.wait(0.5)
                continue
            if msg is None:
                continue
            if self.claim is not None and msg.is_extended_id:  # claims, requests for them
                self.claim.received(msg.arbitration_id, bytes(msg.data), time.monotonic())
            self.frames.handle(
                time.monotonic(), msg.arbitration_id, bytes(msg.data), msg.is_extended_id
            )

    def close(self) -> None:
        self.stop()
        if self.bus is not None:
            with contextlib.suppress(Exception):
                self.bus.shutdown()


def record_estimate(rec: Recorder | None, core: RuntimeCore, now: float) -> None:
    """The mow estimate and the decision into the recording (Foxglove pose + state)."""
    pipe, d = core.pipeline, core.decision
    if rec is None or not rec.ok or not isinstance(pipe, MowPipeline):
        return
    p = pipe.localizer.pose()
    rec.estimate(
        int(now * 1e9),
        core.mode,
        p.position,
        p.quaternion,
        p.covariance,
        str(d.state),
        d.permit,
        d.reason,
        pipe.localizer.sigma_xy(),
        d.signed_distance_m,
    )


def device_status(
    imu: Vn100 | None,
    camera: CameraSource | None,
    output: DecisionOutput | None,
    rec: Recorder | None,
) -> dict[str, Any]:
    """The devices' counters, for the status command."""
    return {
        "imu_driver": vars(imu.stats) if imu else {},
        "camera": camera.status() if camera else {},
        "imu_parser": imu.parser.stats.as_dict() if imu else {},
        "imu_messages": vars(imu.extractor.stats) if imu else {},
        **(output.status() if output is not None else {}),
        "recording": rec.status() if rec is not None else None,
    }
