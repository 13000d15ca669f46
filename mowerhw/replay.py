"""Replay a recording through the same parsers and estimators, deterministically.

The recorded raw inputs go through the code that read them live: serial bytes into
:meth:`drivers.vn100.Vn100.feed` (its parser and clock mapping), CAN frames into
:class:`drivers.isobus_speed.SpeedReader`, JPEG frames into the front end; then the time-ordered
buffer and the teach or mow pipeline exactly as the daemon feeds them
(:func:`mowerhw.runtime.pipelines.feed_ready`), and the same fail-safe gate, with the
recording's host times as the clock. One thread, seeded front end, one OpenCV thread: the same
file and config give the same map, byte for byte, and the same permit sequence.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import math
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from drivers.isobus_speed import SpeedReader, invalid_detail
from drivers.vn100 import Vn100
from mowerhw.buffer import SensorBuffer
from mowerhw.config import Config, config_from_dict
from mowerhw.geometry import quat_to_rotmat
from mowerhw.map import LawnMap
from mowerhw.map import load as load_map
from mowerhw.recording import RecordingRead, decode_jpeg
from mowerhw.runtime.gate import PermitGate
from mowerhw.runtime.pipelines import TRACKS, MowPipeline, TeachPipeline, feed_ready
from mowerhw.samples import ImuSample, Stream

log = logging.getLogger("mowerhw.replay")


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
            meta = self.reader.metadata.get("config", {}).get("yaml")
            if not meta:
                raise ReplayError(f"{self.path}: no config in the recording; pass --config")
            raw = yaml.safe_load(meta)
            cal = self.reader.attachments.get("calibration.yaml")
            if cal is not None:
                cal_path = self.out / "calibration.yaml"
                cal_path.write_bytes(cal)
                raw.setdefault("camera", {})["calibration"] = str(cal_path)
            raw.setdefault("map", {})["path"] = str(self.out / "map.json")
            self.config = config_from_dict(raw, self.out, f"{self.path} (config)")
        cfg = self.config
        from mowerhw.camera import load_camchain

        self.camera = load_camchain(cfg.camera.calibration, cfg.camera.camchain_key)
        self.r_bi = quat_to_rotmat(np.asarray(cfg.imu.q_bi, dtype=np.float64))
        self.buffer = SensorBuffer(capacity={TRACKS: 16})
        self.gate = PermitGate.from_config(cfg)
        self.last: dict[str, float | None] = {"imu": None, "speed": None, "camera": None}
        self.vn = Vn100("replay", on_sample=self._on_imu, gyro_source=cfg.imu.gyro_source)
        self.speed_reader = SpeedReader(
            cfg.speed.source, cfg.speed.sensor_address, cfg.speed.ccvs1_direction
        )
        self.notes: dict[str, tuple[float, str]] = {}
        if self.mode == "teach":
            self.pipe: Any = TeachPipeline(cfg, self.camera)
        else:
            lawn_map = self._mow_map()
            self.pipe = MowPipeline(cfg, self.camera, lawn_map)
        self.now = 0.0
        self.prev_permit = False

    def _mow_map(self) -> LawnMap:
        if self.map_path is not None:
            return load_map(self.map_path)
        data = self.reader.attachments.get("map.json")
        if data is None:
            raise ReplayError(f"{self.path}: no map in the recording; pass --map")
        path = self.out / "recorded-map.json"
        path.write_bytes(data)
        return load_map(path)

    # ---------------------------------------------------------------------------- inputs

    def _on_imu(self, s: ImuSample) -> None:
        gyro = self.r_bi @ s.gyro
        self.last["imu"] = self.now
        self.buffer.push(Stream.IMU, ImuSample(s.t, gyro, None, s.device_time_ns, s.host_time_ns))
        self.pipe.vision.imu(s.t, gyro)
        feed_ready(self.pipe, self.buffer, s.t - self.pipe.lag_s)
        self._decide()

    def _decide(self) -> None:
        if not isinstance(self.pipe, MowPipeline):
            return
        c = self.pipe.containment(self.now) if self.pipe.finite() else None
        stale = self.gate.stale(self.now, self.last, self.notes)
        d = self.gate.decide(self.now, "mow", self.last, c, stale=stale)
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
                if s.valid:
                    self.last["speed"] = s.t
                    self.notes.pop("speed", None)
                else:
                    self.notes["speed"] = (s.t, invalid_detail(s))
                self.buffer.push(Stream.SPEED, s)
        elif topic == "/camera/image":
            ts = msg["timestamp"]
            t = ts["sec"] + ts["nsec"] * 1e-9
            self.last["camera"] = self.now
            image = decode_jpeg(msg["data"])
            v = self.pipe.vision
            tracks = v.track(t, image, v.prepare(t))
            self.buffer.push(TRACKS, tracks)
            if isinstance(self.pipe, MowPipeline):
                feed_ready(self.pipe, self.buffer, math.inf)
        else:
            return
        self.counts[topic] += 1
        if self.t_first is None:
            self.t_first = self.now
        self.t_last = self.now

    # ------------------------------------------------------------------------------- run

    def run(self) -> dict[str, Any]:
        from mowerhw.progress import Progress

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
                self._message(topic, msg)
                last_log_ns = log_ns
                n += 1
                if n % 256 == 0:
                    bar.advance(self.reader.bytes_read - bar.done)
                if (
                    isinstance(self.pipe, TeachPipeline)
                    and self.config.runtime.auto_finish_teach
                    and self.pipe.loop_done()
                ):
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
        if self.reader.warning:
            out["warning"] = self.reader.warning
        if isinstance(self.pipe, TeachPipeline):
            out.update(self._finish_teach(last_log_ns, finished_by))
        else:
            loc = self.pipe.localizer
            out.update(
                permit_fraction=round(self.permit_samples / max(1, self.samples), 4),
                halts_by_reason=dict(self.halts),
                permit_sequence_sha256=self._permits.hexdigest(),
                localizer={k: v for k, v in vars(loc.counters).items()},
            )
        (self.out / "replay.json").write_text(json.dumps(out, indent=1))
        return out

    def _finish_teach(self, last_log_ns: int, finished_by: str) -> dict[str, Any]:
        import datetime as dt

        result, lawn_map = self.pipe.finish()
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
