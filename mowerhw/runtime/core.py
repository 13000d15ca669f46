"""The runtime's logic, with no I/O, no threads and no clock of its own (docs/design.md §8).

:class:`RuntimeCore` takes timestamped inputs (IMU and speed samples, camera arrivals, the
front end's tracks, the map as loaded, commands) and answers :meth:`RuntimeCore.decide`. It
owns the time-ordered sample buffer, the teach or mow estimator chain, the permit gate, the
fault / rebuild / resume policy and the halt-latency bookkeeping. The daemon is an asyncio
shell around it (devices, CAN, control socket, map file, systemd); a replay drives the same
core, so a recording gives the daemon's own decisions, faults included.

Every input that can change a decision is journaled before it is applied, every decision after
it. Chains take seconds to build: the core asks for one (``on_build``), the shell builds it off
its loop and hands it back (:meth:`install`); a replay builds it where the journal says.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mowerhw.common.buffer import SensorBuffer
from mowerhw.common.geometry import quat_to_rotmat, tuple3
from mowerhw.common.samples import FloatArray, ImuSample, SpeedSample, Stream
from mowerhw.config import Config
from mowerhw.estimation import compass
from mowerhw.frontend.tracker import FrameTracks
from mowerhw.map import LawnMap
from mowerhw.mow.containment import ContainmentResult
from mowerhw.mow.gate import Decision, PermitGate
from mowerhw.runtime.chains import ChainRequests, resume_localizer
from mowerhw.runtime.journal import Journal, decision_key
from mowerhw.runtime.pipelines import (
    TRACKS,
    BuildRequest,
    MowPipeline,
    Pipeline,
    StartPose,
    TeachPipeline,
    feed_ready,
)

log = logging.getLogger("mowerhw.daemon")

MODES = ("idle", "teach", "mow")
#: localized poses are offered for saving (restarts resume from them) at most this often (s)
POSE_SAVE_PERIOD_S = 0.1
FAULT_KINDS = ("nan", "exception")


@dataclass(frozen=True)
class HaltLatency:
    """One permit → halt transition: what halted it and how long after it was revealed."""

    reason: str
    latency_ms: float
    t: float


class RuntimeCore:
    """See the module doc. ``on_build`` receives every :class:`BuildRequest`."""

    def __init__(
        self,
        config: Config,
        journal: Journal | None = None,
        on_build: Callable[[BuildRequest], None] | None = None,
    ) -> None:
        self.cfg = config
        self.journal = journal
        self.r_bi = quat_to_rotmat(np.asarray(config.imu.q_bi, dtype=np.float64))
        #: the IMU is mounted with the body's axes (the usual case): no turning per sample
        self._imu_is_body = bool(np.array_equal(self.r_bi, np.eye(3)))
        self.buffer = SensorBuffer(capacity={TRACKS: 16})
        self.gate = PermitGate.from_config(config)
        self.decision: Decision = self.gate.current
        self.mode = "idle"
        self.t_imu_newest: float | None = None  # sensor time of the newest IMU sample
        self.mow_areas: tuple[str, ...] | None = None  # set by `ctl mow --area`; None: config
        self.pipeline: Pipeline | None = None
        self.map: LawnMap | None = None
        self.map_problem = ""
        self.fault = ""
        self.teach_state = ""  # "", "starting", "recording", "finishing", "saved", "failed: …"
        self.last_teach: dict[str, Any] = {}
        self.shutting_down = False
        self.last_arrival: dict[str, float | None] = {"imu": None, "speed": None, "camera": None}
        #: per stream, why its newest data could not be used (arrival, the device's words)
        self.stream_notes: dict[str, tuple[float, str]] = {}
        self.counts: Counter[str] = Counter()
        self.halt_latencies: list[HaltLatency] = []
        self.last_accel: tuple[float, float, float] | None = None
        self.chains = ChainRequests(on_build)
        self._inject = ""
        self._last_good_pose: StartPose | None = None
        self._good_pose_count = 0
        self._next_pose_save = -math.inf
        self._pose_to_save: StartPose | None = None
        self._revealed_at: float | None = None
        self.is_lifted = False  # the supervisor says the mower is lifted
        self._next_mag_t = -math.inf
        self._prev_device_ns: int | None = None  # the sensor time of the previous IMU sample
        #: when the newest decision was made, and the longest time between two decisions since
        #: the newest IMU sample: whether this daemon kept deciding through an IMU silence
        self._decided_at: float | None = None
        self._longest_undecided_s = 0.0

    # ------------------------------------------------------------------------- journal

    def _log(self, kind: str, **payload: Any) -> None:
        if self.journal is not None:
            self.journal.write(kind, payload)

    # -------------------------------------------------------------------------- inputs

    def imu(self, sample: ImuSample, now: float) -> Decision:
        """An IMU sample (IMU frame, as the device gave it) that arrived at ``now``: into the
        buffer, the estimator fed with what is ready, and the permit decided at once."""
        self._log("imu", sample=sample, now=now)
        self._note_imu_gap(sample, now)
        self.last_arrival["imu"] = now
        self.t_imu_newest = sample.t
        self.counts["imu"] += 1
        gyro = self._to_body(sample.gyro)
        accel = None if sample.accel is None else self._to_body(sample.accel)
        if accel is not None:  # for the supervisor's lift/tilt/collision checks
            self.last_accel = tuple3(accel)
        # the buffer holds what the estimators read: ``t``, the body-frame rate and force
        self.buffer.push(
            Stream.IMU,
            sample
            if self._imu_is_body
            else ImuSample(sample.t, gyro, accel, sample.device_time_ns, sample.host_time_ns),
        )
        if self.pipeline is not None:
            self.pipeline.vision.imu(sample.t, gyro)  # the front end's derotation history
            if sample.mag is not None and sample.t >= self._next_mag_t:  # the compass: 10 Hz
                self._next_mag_t = sample.t + compass.KEEP_AFTER_S
                self.pipeline.magnetometer(sample.t, self._to_body(sample.mag), accel)
        self._hold_pose()
        self._consume(sample.t)
        arrival = sample.host_time_ns * 1e-9 if sample.host_time_ns is not None else now
        d = self._decide(now, arrival)
        self._longest_undecided_s = 0.0  # the next silence is timed from this decision
        if self.journal is not None:
            self._log("imu_out", out=decision_key(d))
        return d

    def _note_imu_gap(self, sample: ImuSample, now: float) -> None:
        """After a silence longer than the IMU's staleness limit, say where it was: the
        sensor's own clock tells whether it was silent too (it sent late, or the cable or
        power failed) or sent on time and the bytes were held up on this computer (serial
        driver, kernel, a loaded machine) — counted apart (``imu_gaps_sensor``,
        ``imu_gaps_host``) and logged, so an integrator knows which to look at; and for the
        latter whether this daemon kept deciding meanwhile (its loop was on time: the bytes
        reached it late, from the serial adapter or the kernel's tty input work, which other
        CPU-bound work at nice 0 delays) or was held up itself."""
        last, dev = self.last_arrival["imu"], sample.device_time_ns
        prev_dev, self._prev_device_ns = self._prev_device_ns, dev
        if last is None or not self.gate.late("imu", now, last):  # the gate's one rule
            return
        gap = now - last
        if dev is None or prev_dev is None or dev <= prev_dev:
            self.counts["imu_gaps_unknown"] += 1
            log.warning("imu: a sample again after %.3f s (the sensor sends no time)", gap)
            return
        sensor_gap = (dev - prev_dev) * 1e-9
        held = gap - sensor_gap
        if held > 0.5 * gap:
            self.counts["imu_gaps_host"] += 1
            undecided = self._longest_undecided_s
            if self._decided_at is not None:
                undecided = max(undecided, now - self._decided_at)
            if undecided < 0.5 * gap:  # this daemon kept deciding: the bytes came late
                where = (
                    "it sent on time: the samples were held up on this computer before the "
                    f"daemon could read them (it went at most {undecided:.3f} s without a "
                    "decision meanwhile): the serial adapter, or the kernel's tty input "
                    "behind other CPU-bound work (systemd/README.md)"
                )
            else:
                where = (
                    "it sent on time: the samples were held up on this computer, in this "
                    f"daemon ({undecided:.3f} s without a decision)"
                )
        else:
            self.counts["imu_gaps_sensor"] += 1
            where = "the sensor itself was silent"
        log.warning(
            "imu: a sample again after %.3f s; by the sensor's own clock %.3f s passed (%s)",
            gap,
            sensor_gap,
            where,
        )

    def _to_body(self, v: FloatArray) -> FloatArray:
        """An IMU-frame vector in the body frame."""
        return v if self._imu_is_body else self.r_bi @ v

    def speed(self, sample: SpeedSample) -> None:
        """A ground speed sample (``t``: its arrival on the host clock)."""
        self._log("speed", sample=sample)
        if sample.valid:  # an invalid reading is not a fresh speed
            self.last_arrival["speed"] = sample.t
            self.stream_notes.pop("speed", None)
        else:
            self.stream_notes["speed"] = (sample.t, sample.invalid_detail())
        self.counts["speed" if sample.valid else "speed_invalid"] += 1
        self.buffer.push(Stream.SPEED, sample)

    def lifted(self, lifted: bool) -> None:
        """The supervisor's safety functions say the mower is lifted (True), or not any
        more: while it is, the localizer has no pose it may trust (it may be put down
        anywhere) and searches for one once the mower stands again (issue 18)."""
        self._log("lifted", lifted=lifted)
        if lifted != self.is_lifted:
            log.info(
                "lifted: the pose is given up; it is searched for once the mower stands"
                if lifted
                else "standing again: searching for the pose"
            )
        self.is_lifted = lifted
        self._hold_pose()

    def _hold_pose(self) -> None:
        if self.is_lifted and isinstance(self.pipeline, MowPipeline):
            self.pipeline.localizer.lifted()

    def camera_frame(self, now: float) -> None:
        """A camera frame arrived (the camera is alive, whatever the front end makes of it)."""
        self._log("camera_frame", now=now)
        self.last_arrival["camera"] = now
        self.stream_notes.pop("camera", None)
        self.counts["frames"] += 1

    def camera_alive(self, now: float) -> None:
        """A frame the camera delivered between the front end's (``camera.device_fps`` above
        ``camera.fps``), dropped undecoded: the camera is alive, unless the last one decoded
        was refused (the frames between are of the same mode)."""
        self._log("camera_alive", now=now)
        last = self.last_arrival["camera"]
        if "camera" not in self.stream_notes and (last is None or now > last):
            self.last_arrival["camera"] = now  # (read late, it may be older than a frame)

    def camera_refused(self, now: float, why: str) -> None:
        """A frame that cannot be used at all (not the calibration's size): not a fresh frame;
        ``why`` is the camera's halt detail while no good one comes."""
        self._log("camera_refused", now=now, why=why)
        self.stream_notes["camera"] = (now, why)
        self.counts["frames_refused"] += 1

    def frame_pipeline(self) -> tuple[int, Pipeline] | None:
        """The chain a new frame is for (its serial, for :meth:`tracks`), if wanted now."""
        if self.pipeline is None or (self.mode == "teach" and self.teach_state != "recording"):
            return None
        return self.chains.installed_serial, self.pipeline

    def tracks(self, serial: int, tracks: FrameTracks) -> None:
        """The front end's tracks of a frame, made for the chain ``serial`` (dropped if that
        chain has been replaced meanwhile)."""
        self._log("tracks", serial=serial, tracks=tracks)
        if self.pipeline is None or serial != self.chains.installed_serial:
            return
        self.buffer.push(TRACKS, tracks)
        if isinstance(self.pipeline, MowPipeline):
            self._consume(math.inf)  # the localizer takes late frames itself

    def frontend_error(self) -> None:
        self.counts["frontend_errors"] += 1

    # --------------------------------------------------------------------- estimator

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
            if isinstance(pipe, MowPipeline):
                for line in pipe.news():
                    log.info("localizer: %s", line)
            if self._inject == "nan" and isinstance(pipe, MowPipeline):
                self._inject = ""
                pipe.localizer.inject_fault()
        except Exception as exc:
            self._estimator_fault(f"estimator raised {type(exc).__name__}: {exc}", exc)

    def _estimator_fault(self, what: str, exc: BaseException | None = None) -> None:
        """Halt (FAULT), drop the estimator, ask for a new one from the last good pose."""
        self.counts["estimator_faults"] += 1
        self.fault = f"{what}; estimator restarted"
        log.error("FAULT: %s", self.fault, exc_info=exc)
        self.buffer.pop_ready()
        self.pipeline = None
        if self.mode == "mow" and self.map is not None:
            self._request_mow(self.map, self._last_good_pose)
        elif self.mode == "teach":
            log.error("teach: the recording so far is lost; drive the loop again")
            self.chains.request("teach")

    def install(self, serial: int, pipe: Pipeline) -> bool:
        """Use the chain built for request ``serial``, unless a newer request (a mode or map
        change, another fault) came since. True if it was installed."""
        self._log("install", serial=serial)
        req = self.chains.accept(serial, self.mode)
        if req is None:
            return False
        if isinstance(pipe, MowPipeline) and req.start_pose is not None:
            resume_localizer(pipe, req.start_pose, req.resumed)
        self.buffer.pop_ready()
        self.pipeline = pipe
        if req.kind == "teach":
            self.teach_state = "recording"
            log.info("teach: recording; hold still for the gyro calibration, then drive the edge")
        return True

    # ---------------------------------------------------------------------- decision

    def decide(self, now: float, revealed_at: float | None = None) -> Decision:
        """The permit for ``now``. ``revealed_at``: when the input that led to this decision
        arrived (for the halt latency), default ``now``."""
        d = self._decide(now, revealed_at)
        self._log("decide", now=now, revealed_at=revealed_at, out=decision_key(d))
        return d

    def _decide(self, now: float, revealed_at: float | None) -> Decision:
        if self._decided_at is not None:
            self._longest_undecided_s = max(self._longest_undecided_s, now - self._decided_at)
        self._decided_at = now
        pipe = self.pipeline
        containment = None
        if isinstance(pipe, MowPipeline) and not self.map_problem:
            if not pipe.finite():
                self._estimator_fault("estimator state is not finite (NaN/inf)")
                pipe = self.pipeline
            if isinstance(pipe, MowPipeline):
                containment = self._mow_state(pipe, now)
        stale = self.gate.stale(now, self.last_arrival, self.stream_notes)
        was = self.decision.permit
        d = self.gate.decide(
            now,
            self.mode,
            self.last_arrival,
            containment,
            self.map_problem,
            self.fault,
            self.shutting_down,
            stale,
        )
        self.decision = d
        if was and not d.permit:
            self._revealed_at = self.gate.revealed_at(now, stale, self.last_arrival, revealed_at)
        return d

    def _mow_state(self, pipe: MowPipeline, now: float) -> ContainmentResult:
        if self.fault and pipe.localizer.localized:
            log.info("fault cleared: localized again after the estimator restart")
            self.fault = ""
        containment = pipe.containment()
        self._good_pose_count += 1
        if self._good_pose_count % 10 == 0:
            self._last_good_pose = pipe.last_good_pose() or self._last_good_pose
        saving = pipe.localizer.localized and not self.fault and not self.shutting_down
        if saving and now >= self._next_pose_save:
            self._next_pose_save = now + POSE_SAVE_PERIOD_S
            self._pose_to_save = pipe.last_good_pose()  # what a rebuild resumes from, too
        return containment

    def halt_sent(self, sent: float) -> None:
        """The shell sent the halt of the newest decision at ``sent`` (its own clock)."""
        if self._revealed_at is None:
            return
        self.halt_latencies.append(
            HaltLatency(self.decision.reason, round((sent - self._revealed_at) * 1e3, 3), sent)
        )
        self._revealed_at = None
        del self.halt_latencies[:-1000]

    def take_pose_to_save(self) -> StartPose | None:
        """A localized pose to save for a restart, when one is due (then None until the
        next is due)."""
        pose, self._pose_to_save = self._pose_to_save, None
        return pose

    def next_deadline(self, now: float) -> float:
        """When the next sensor's staleness limit runs out, or ``inf``."""
        return self.gate.next_stale_deadline(now, self.last_arrival)

    # ------------------------------------------------------------------- modes, map

    def set_mode(self, mode: str, mow_areas: tuple[str, ...] | None = None) -> str:
        """Switch mode: ``""`` if done, else why not. Teach asks for a teach chain; mow waits
        for the shell's :meth:`map_loaded` / :meth:`map_invalid`. ``mow_areas``: mow only
        these mowing areas of the map, the others being transit (None: ``mow.areas``)."""
        if mode not in MODES:
            return f"mode {mode!r} is not one of {', '.join(MODES)}"
        if self.mode == "teach" and self.teach_state == "finishing":
            return "teach is finishing (loop closure); try again shortly"
        if mow_areas is not None and mode != "mow":
            return "areas are for mow mode only"
        self._log("set_mode", mode=mode, mow_areas=mow_areas)
        self.mow_areas = mow_areas
        self.buffer.pop_ready()
        self.fault = ""
        self.map_problem = ""
        self.pipeline = None
        self.chains.cancel()
        self.map = None
        self.mode = mode
        log.info("mode %s", mode)
        if mode == "teach":
            self.teach_state = "starting"
            self.chains.request("teach")
        return ""

    def switch_mow_areas(self, mow_areas: tuple[str, ...] | None) -> str | None:
        """While mowing on a running chain: mow only ``mow_areas`` (None: ``mow.areas``) from
        now on without rebuilding the chain (the pose goes on, no restart from the dock or a
        saved pose): ``""`` if done, why not if the map lacks an area, None if there is no
        running mow chain to switch (the caller sets the mode instead)."""
        pipe = self.pipeline
        if self.mode != "mow" or not isinstance(pipe, MowPipeline) or self.map_problem:
            return None
        self._log("switch_mow_areas", mow_areas=mow_areas)
        areas = mow_areas if mow_areas is not None else self.cfg.mow.areas
        try:
            pipe.mow_only(areas)
        except ValueError as exc:
            return str(exc)
        self.mow_areas = mow_areas
        log.info("mowing %s from now on", ", ".join(areas) if areas else "every mowing area")
        return ""

    def map_loaded(self, lawn_map: LawnMap, saved_pose: StartPose | None = None) -> None:
        """Mow mode: the map to mow on, checked; ``saved_pose``: a recent pose of this map a
        previous run saved (the localizer resumes from it instead of the dock)."""
        self._log("map_loaded", map=lawn_map, saved_pose=saved_pose)
        if self.mode != "mow":
            return
        self.map = lawn_map
        self.map_problem = ""
        problem = lawn_map.unknown_mow_areas(self.mow_areas or ())
        if problem:
            self.map_problem = problem
            return
        self._request_mow(lawn_map, saved_pose, resumed=saved_pose is not None)

    def _request_mow(
        self, lawn_map: LawnMap, pose: StartPose | None, resumed: bool = False
    ) -> None:
        self.chains.request("mow", lawn_map, pose, resumed=resumed, mow_areas=self.mow_areas)

    def map_invalid(self, problem: str) -> None:
        """The map file is unusable: halt MAP_INVALID naming the problem (the estimator keeps
        tracking on the map in memory, so a restored file resumes at once)."""
        self._log("map_invalid", problem=problem)
        self.map_problem = problem

    def map_reloaded(self, lawn_map: LawnMap) -> None:
        """The map file changed and is valid: the same map resumes, a new one is used."""
        self._log("map_reloaded", map=lawn_map)
        old = self.map
        self.map_problem = ""
        if old is not None and lawn_map.checksum == old.checksum:
            log.info("map file valid again, same map (checksum %s)", old.checksum[:19])
            if self.pipeline is None and self.chains.pending is None:
                self._request_mow(old, self._last_good_pose)
            return
        self.map, self.pipeline = lawn_map, None
        log.info("new map loaded: %d landmarks", len(lawn_map.landmarks))
        self._request_mow(lawn_map, self._last_good_pose)

    def inject(self, kind: str) -> str:
        """Fault injection (the shell checks ``runtime.fault_injection``): ``""`` or why not."""
        if kind not in FAULT_KINDS:
            return f"fault kind {kind!r}; allowed: {', '.join(FAULT_KINDS)}"
        self._log("inject", fault=kind)
        self._inject = kind
        log.warning("fault injection: %s", kind)
        return ""

    def shutdown(self) -> None:
        """From now on every decision halts (SHUTTING_DOWN)."""
        self._log("shutdown")
        self.shutting_down = True

    # -------------------------------------------------------------------------- teach

    def teach_loop_done(self) -> bool:
        """Teaching, and the operator has driven the loop and stopped back at the start."""
        pipe = self.pipeline
        return (
            isinstance(pipe, TeachPipeline) and self.teach_state == "recording" and pipe.loop_done()
        )

    def teach_mark(self, kind: str, name: str = "") -> str:
        """``ctl teach area NAME | keepout NAME | nav NAME | dock | end``: what the operator
        drives from now on (:mod:`mowerhw.teach.marks`), at the newest IMU sample's time;
        why not, or ""."""
        self._log("teach_mark", mark=kind, name=name, t=self.t_imu_newest)
        pipe = self.pipeline
        if self.mode != "teach" or not isinstance(pipe, TeachPipeline):
            return f"not teaching (mode {self.mode})"
        if self.teach_state != "recording":
            return f"teach is {self.teach_state or 'not started'}; mark once it is recording"
        if self.t_imu_newest is None:
            return "no IMU sample yet: mark once the IMU is read"
        problem = pipe.teacher.mark(self.t_imu_newest, kind, name)
        if not problem:
            log.info(
                "teach: marked %s at t=%.2f s",
                " ".join(filter(None, (kind, name))),
                self.t_imu_newest,
            )
        return problem

    def begin_finish_teach(self) -> TeachPipeline | str:
        """The teach chain to finish (loop closure, boundary: off the loop), or why not."""
        self._log("begin_finish_teach")
        pipe = self.pipeline
        if self.mode != "teach" or not isinstance(pipe, TeachPipeline):
            return f"not teaching (mode {self.mode})"
        if self.teach_state != "recording":
            return f"teach is {self.teach_state}"
        self.teach_state = "finishing"
        self.buffer.pop_ready()
        return pipe

    def end_finish_teach(self, error: str = "", summary: dict[str, Any] | None = None) -> None:
        """Teach finished: the map saved (``summary``), or failed (``error``); back to idle."""
        self._log("end_finish_teach", error=error, summary=summary or {})
        if error:
            self.teach_state = f"failed: {error}"
        else:
            self.teach_state = "saved"
            self.last_teach = dict(summary or {})
        self.pipeline = None
        self.mode = "idle"

    # ------------------------------------------------------------------------- status

    def pose_xyh(self) -> tuple[float, float, float]:
        """x, y, heading of the mow estimate (NaN when there is none)."""
        if isinstance(self.pipeline, MowPipeline):
            _, x, y, h, _ = self.pipeline.pose()
            return x, y, h
        return math.nan, math.nan, math.nan

    def status_line(self) -> str:
        d = self.decision
        if self.mode == "teach":
            return f"teach: {self.teach_state}; deck halted"
        if d.permit:
            return f"{self.mode}: {d.state}, mowing permitted"
        return f"{self.mode}: {d.state}, halted ({d.reason})"
