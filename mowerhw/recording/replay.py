"""Replay a recording through the runtime core the daemon runs, deterministically.

Two ways (both drive :class:`mowerhw.runtime.core.RuntimeCore`):

* **raw** (:class:`Replay`): the recorded raw inputs go through the code that read them live:
  serial bytes into :meth:`drivers.imu.vn100.Vn100.feed` (its parser and clock mapping), CAN
  frames into :class:`drivers.can.speed.SpeedReader`, JPEG frames into the front end; then
  the core, with the recording's host times as the clock. One thread, seeded front end, one
  OpenCV thread: the same file and config give the same map, byte for byte, and the same
  permit sequence. A config or map other than the recorded one may be given: this is the way
  to try a change on real data.
* **journal** (:func:`replay_decisions`): the core's own journal of the live run (every input
  in the order the daemon applied it, the front end's tracks, where estimator chains were
  installed, the faults injected) into a new core: it gives the daemon's decisions, faults
  and rebuilds included, and compares each with the one the daemon made.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import json
import logging
import tempfile
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.can.speed import SpeedReader
from drivers.imu.vn100 import Vn100
from mowerhw.camera import CameraModel
from mowerhw.common.samples import ImuSample
from mowerhw.config import Config, ConfigError, config_from_dict, parse_config_yaml
from mowerhw.map import LawnMap
from mowerhw.map import load as load_map
from mowerhw.recording.mcap import RecordingRead, decode_jpeg
from mowerhw.runtime.core import RuntimeCore
from mowerhw.runtime.journal import JournalDecoder, JournalError, decision_key
from mowerhw.runtime.pipelines import BuildRequest, MowPipeline, TeachPipeline, build_pipeline

log = logging.getLogger("mowerhw.recording.replay")


class ReplayError(RuntimeError):
    """A recording that cannot be replayed (no config, no map for mow, …)."""


class Replay:
    def __init__(
        self,
        path: str | Path,
        mode: str = "teach",
        config: Config | None = None,
        map_path: str | Path | None = None,
        out_dir: str | Path | None = None,
        speed: float | None = None,
        progress: bool = True,
    ) -> None:
        if mode not in ("teach", "mow"):
            raise ValueError(f"mode {mode!r}: replay takes teach or mow")
        self.path = Path(path)
        if not self.path.exists():
            raise ReplayError(f"{self.path}: no such recording")
        self.mode = mode
        self.config = config
        self.map_path = Path(map_path) if map_path else None
        self.out = Path(out_dir) if out_dir else self.path.with_suffix("")
        self.speed = speed  # None: as fast as possible
        self.progress = progress
        self.reader = RecordingRead(self.path)
        self.counts: Counter[str] = Counter()
        self.halts: Counter[str] = Counter()
        self.unreadable: Counter[str] = Counter()
        self.permit_samples = 0
        self.samples = 0
        self.t_first: float | None = None
        self.t_last = 0.0

    # ----------------------------------------------------------------------------- set-up

    def _setup(self) -> None:
        import cv2

        cv2.setNumThreads(1)
        self.out.mkdir(parents=True, exist_ok=True)
        if self.config is None:
            self.config = _recorded_config(self.reader, self.path, self.out)
        cfg = self.config
        from mowerhw.camera import load_camchain

        self.camera = load_camchain(cfg.camera.calibration, cfg.camera.camchain_key)
        self.core = RuntimeCore(cfg, on_build=self._build_now)
        self.vn = Vn100("replay", on_sample=self._on_imu, gyro_source=cfg.imu.gyro_source)
        self.speed_reader = SpeedReader(
            cfg.speed.source, cfg.speed.sensor_address, cfg.speed.ccvs1_direction
        )
        self.core.set_mode(self.mode)
        if self.mode == "mow":
            self.core.map_loaded(self._mow_map())
        self.now = 0.0
        self.prev_permit = False

    def _build_now(self, req: BuildRequest) -> None:
        """A replay builds the chain the core asks for at once (the daemon: off its loop)."""
        self.core.install(req.serial, build_pipeline(self.config, self.camera, req))

    def _mow_map(self) -> LawnMap:
        if self.map_path is not None:
            return load_map(self.map_path)
        data = self.reader.attachment("map.json")
        if data is None:
            raise ReplayError(f"{self.path}: no map in the recording; pass --map")
        path = self.out / "recorded-map.json"
        path.write_bytes(data)
        return load_map(path)

    # ---------------------------------------------------------------------------- inputs

    def _on_imu(self, s: ImuSample) -> None:
        d = self.core.imu(s, self.now)
        if self.mode != "mow":
            return
        self.samples += 1
        self.permit_samples += int(d.permit)
        if self.prev_permit and not d.permit:
            self.halts[d.reason] += 1
        self.prev_permit = d.permit
        self._permits.update(f"{int(d.permit)}{d.reason}".encode())

    def _message(self, topic: str, msg: dict[str, Any]) -> None:
        if topic == "/vn100/raw":
            self.now = msg["host_time_ns"] * 1e-9
            self.vn.feed(base64.b64decode(msg["data"]), int(msg["host_time_ns"]))
        elif topic == "/can":
            if msg.get("direction", "rx") != "rx" or not msg.get("extended", True):
                return
            self.now = msg["host_time_ns"] * 1e-9
            s = self.speed_reader.handle(int(msg["id"]), bytes.fromhex(msg["data"]), self.now)
            if s is not None:
                self.core.speed(s)
        elif topic == "/runtime/journal" and msg.get("kind") == "camera_alive":
            # a frame the camera sent between the recorded ones (camera.device_fps), not
            # stored: the live core's note of it is the raw input
            self.now = float(msg["now"])
            self.core.camera_alive(self.now)
            return
        elif topic == "/camera/image":
            ts = msg["timestamp"]
            t = ts["sec"] + ts["nsec"] * 1e-9
            self.core.camera_frame(self.now)
            target = self.core.frame_pipeline()
            if target is not None:
                serial, pipe = target
                image = decode_jpeg(msg["data"])
                vision = pipe.vision
                tracks = vision.track(t, image, vision.prepare(t), vision.wants_search())
                self.core.tracks(serial, tracks)
        else:
            return
        self.counts[topic] += 1
        if self.t_first is None:
            self.t_first = self.now
        self.t_last = self.now

    # ------------------------------------------------------------------------------- run

    def run(self) -> dict[str, Any]:
        from mowerhw.common.progress import Progress

        self._permits = hashlib.sha256()
        total = self.path.stat().st_size
        wall0 = time.monotonic()
        t_first: float | None = None
        last_log_ns = 0
        n = 0
        finished_by = "end of recording"
        ready = False
        with Progress(total, f"replay {self.path.name}", force=False) as bar:
            if not self.progress:
                bar.enabled = False
            for topic, log_ns, msg in self.reader.messages():
                if not ready:
                    self._setup()
                    ready = True
                host = msg.get("host_time_ns") if isinstance(msg, dict) else None
                if self.speed is not None and host is not None:
                    if t_first is None:
                        t_first = host * 1e-9
                    ahead = (host * 1e-9 - t_first) / self.speed - (time.monotonic() - wall0)
                    if ahead > 0:
                        time.sleep(ahead)
                try:
                    self._message(topic, msg)
                except Exception as exc:  # content the recorder never writes: damage
                    self.unreadable[f"{topic}: {type(exc).__name__}"] += 1
                    continue
                last_log_ns = log_ns
                n += 1
                if n % 256 == 0:
                    bar.advance(self.reader.bytes_read - bar.done)
                if self.config.runtime.auto_finish_teach and self.core.teach_loop_done():
                    finished_by = "loop detection"
                    break
            bar.done = total
        if not ready:
            raise ReplayError(f"{self.path}: no messages to replay ({self.reader.warning})")
        wall = time.monotonic() - wall0
        span = (self.t_last - self.t_first) if self.t_first is not None else 0.0
        out: dict[str, Any] = {
            "recording": str(self.path),
            "mode": self.mode,
            "messages": dict(self.counts),
            "recording_s": round(span, 2),
            "wall_s": round(wall, 2),
            "speed_x_real_time": round(span / wall, 2) if wall > 0 else None,
        }
        if self.unreadable:
            out["unreadable_messages"] = dict(self.unreadable)
        if self.reader.warning:
            out["warning"] = self.reader.warning
        pipe = self.core.pipeline
        if isinstance(pipe, TeachPipeline):
            out.update(self._finish_teach(pipe, last_log_ns, finished_by))
        elif isinstance(pipe, MowPipeline):
            loc = pipe.localizer
            out.update(
                permit_fraction=round(self.permit_samples / max(1, self.samples), 4),
                halts_by_reason=dict(self.halts),
                permit_sequence_sha256=self._permits.hexdigest(),
                localizer={k: v for k, v in vars(loc.counters).items()},
            )
        (self.out / "replay.json").write_text(json.dumps(out, indent=1))
        return out

    def _finish_teach(
        self, pipe: TeachPipeline, last_log_ns: int, finished_by: str
    ) -> dict[str, Any]:
        import datetime as dt

        result, lawn_map = pipe.finish()
        # the map's creation time is the recording's, so a replay is byte-for-byte repeatable
        lawn_map.created_utc = dt.datetime.fromtimestamp(last_log_ns * 1e-9, dt.UTC).strftime(
            "%Y-%m-%dT%H:%M:%SZ"
        )
        path = self.out / "map.json"
        lawn_map.save(path)
        data = path.read_bytes()
        try:
            from mowerhw.plots import map_figure

            map_figure(lawn_map, path.with_suffix(".png"), title=f"Map from {self.path.name}")
        except Exception as exc:
            log.warning("map picture not written: %s", exc)
        poly = lawn_map.lawn_polygon()
        return {
            "finished_by": finished_by,
            "map": str(path),
            "map_sha256": hashlib.sha256(data).hexdigest(),
            "map_checksum": lawn_map.checksum,
            "landmarks_mapped": len(lawn_map.landmarks),
            "boundary_length_m": round(float(poly.exterior.length), 3),
            "boundary_area_m2": round(float(poly.area), 3),
            "loop_closure": result.closure.reason,
        }


def _recorded_config(reader: RecordingRead, path: Path, out: Path) -> Config:
    """The run's own config, with the recorded calibration written into ``out``."""
    meta = reader.metadata.get("config", {}).get("yaml")
    if not meta:
        raise ReplayError(f"{path}: no config in the recording; pass --config")
    try:
        raw = parse_config_yaml(meta, f"{path} (config)")
    except ConfigError as exc:
        raise ReplayError(f"the recorded config cannot be used: {exc}") from None
    if not isinstance(raw, dict):
        raise ReplayError(f"{path}: the recorded config is not a mapping of sections")
    cal = reader.attachments.get("calibration.yaml")
    if cal is not None:
        cal_path = out / "calibration.yaml"
        cal_path.write_bytes(cal)
        raw.setdefault("camera", {})["calibration"] = str(cal_path)
    raw.setdefault("map", {})["path"] = str(out / "map.json")
    return config_from_dict(raw, out, f"{path} (config)")


def replay_decisions(path: str | Path, config: Config | None = None) -> dict[str, Any]:
    """The daemon's decisions again, from the runtime journal in the recording ``path`` (see
    the module doc): counts, the sha256 of the live and the replayed decision sequences, and
    the first decision that differs, if any."""
    from mowerhw.camera import load_camchain

    rec_path = Path(path)
    reader = RecordingRead(rec_path)
    records = [m for topic, _, m in reader.messages() if topic == "/runtime/journal"]
    if not records:
        raise ReplayError(
            f"{rec_path}: no runtime journal in the recording (recorded before the journal "
            "existed?); replay it with --mode teach|mow instead"
        )
    with tempfile.TemporaryDirectory(prefix="mowerhw-replay-") as scratch:
        # the recorded config's calibration is written here, read once, then removed
        if config is None:
            config = _recorded_config(reader, rec_path, Path(scratch))
        camera = load_camchain(config.camera.calibration, config.camera.camchain_key)
    t0 = time.monotonic()
    result = replay_journal(config, camera, records).as_dict()
    result["wall_s"] = round(time.monotonic() - t0, 2)
    result["recording"] = str(rec_path)
    result["same_as_live"] = result["mismatches"] == 0 and result["gaps"] == 0
    if reader.warning:
        result["warning"] = reader.warning
    return result


@dataclass
class JournalReplay:
    """What :func:`replay_journal` found."""

    records: int = 0
    decisions: int = 0
    mismatches: int = 0
    first_mismatch: str = ""
    permit_decisions: int = 0
    halts_by_reason: dict[str, int] = field(default_factory=dict)
    live_sha256: str = ""
    replay_sha256: str = ""
    gaps: int = 0  # records missing from the journal (the recorder dropped them)

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def replay_journal(
    config: Config, camera: CameraModel, records: Iterable[dict[str, Any]]
) -> JournalReplay:
    """Drive a new :class:`RuntimeCore` through a journal: every input applied in order, a
    chain built (synchronously) where the journal says the daemon installed one, and every
    decision compared with the one the daemon made."""
    requests: dict[int, BuildRequest] = {}
    core = RuntimeCore(config, on_build=lambda r: requests.__setitem__(r.serial, r))
    dec = JournalDecoder()
    out = JournalReplay()
    live, mine = hashlib.sha256(), hashlib.sha256()
    last_seq = 0
    prev_permit = False
    pending: Any = None  # the decision of the newest "imu" record, compared at "imu_out"

    def compare(d: Any, want: list[Any], seq: int) -> None:
        nonlocal prev_permit
        got = decision_key(d)
        live.update(repr(want).encode())
        mine.update(repr(got).encode())
        out.decisions += 1
        out.permit_decisions += int(d.permit)
        if prev_permit and not d.permit:
            out.halts_by_reason[d.reason] = out.halts_by_reason.get(d.reason, 0) + 1
        prev_permit = d.permit
        if got != want:
            out.mismatches += 1
            if not out.first_mismatch:
                out.first_mismatch = f"record {seq}: live {want}, replay {got}"

    for rec in records:
        out.records += 1
        seq = int(rec.get("seq", 0))
        if seq != last_seq + 1:
            out.gaps += 1
        last_seq = seq
        kind = rec.get("kind")
        if kind == "imu":
            pending = core.imu(dec.imu(rec["sample"]), rec["now"])
        elif kind == "imu_out":
            if pending is not None:
                compare(pending, rec["out"], seq)
            pending = None
        elif kind == "speed":
            core.speed(dec.speed(rec["sample"]))
        elif kind == "lifted":
            core.lifted(bool(rec["lifted"]))
        elif kind == "camera_frame":
            core.camera_frame(rec["now"])
        elif kind == "camera_alive":
            core.camera_alive(rec["now"])
        elif kind == "camera_refused":
            core.camera_refused(rec["now"], rec["why"])
        elif kind == "tracks":
            core.tracks(int(rec["serial"]), dec.tracks(rec["tracks"]))
        elif kind == "install":
            req = requests.get(int(rec["serial"]))
            if req is not None:
                core.install(req.serial, build_pipeline(config, camera, req))
        elif kind == "decide":
            compare(core.decide(rec["now"], rec["revealed_at"]), rec["out"], seq)
        elif kind == "teach_mark":
            core.teach_mark(rec["mark"], rec["name"])
        elif kind == "set_mode":
            areas = rec.get("mow_areas")
            core.set_mode(rec["mode"], tuple(areas) if areas is not None else None)
        elif kind == "switch_mow_areas":
            areas = rec.get("mow_areas")
            core.switch_mow_areas(tuple(areas) if areas is not None else None)
        elif kind == "map_loaded":
            core.map_loaded(dec.lawn_map(rec["map"]), dec.start_pose(rec["saved_pose"]))
        elif kind == "map_invalid":
            core.map_invalid(rec["problem"])
        elif kind == "map_reloaded":
            core.map_reloaded(dec.lawn_map(rec["map"]))
        elif kind == "inject":
            core.inject(rec["fault"])
        elif kind == "shutdown":
            core.shutdown()
        elif kind == "begin_finish_teach":
            core.begin_finish_teach()
        elif kind == "end_finish_teach":
            core.end_finish_teach(rec["error"], rec["summary"])
        else:
            raise JournalError(f"journal record {seq}: unknown kind {kind!r}")
    out.live_sha256 = live.hexdigest()
    out.replay_sha256 = mine.hexdigest()
    return out
