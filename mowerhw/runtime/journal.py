"""The runtime core's journal: its inputs and decisions as JSON, and their replay.

A record is ``{"seq", "kind", ...payload}``; numbers are written with Python's shortest exact
``repr`` (so they read back bit for bit), arrays as flat lists, descriptors as base64, a map
as its document the first time its checksum appears and by checksum after that. The kinds are
the :class:`~mowerhw.runtime.core.RuntimeCore` methods that wrote them.

:func:`replay_journal` drives a new core through a journal: every input applied in order, a
chain built (synchronously) where the journal says the daemon installed one, and every
decision compared with the one the daemon made.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mowerhw.camera import CameraModel
from mowerhw.common.samples import ImuSample, SpeedSample
from mowerhw.config import Config
from mowerhw.frontend.tracker import FrameTracks
from mowerhw.map import LawnMap, from_document
from mowerhw.runtime.core import RuntimeCore, decision_key
from mowerhw.runtime.pipelines import BuildRequest, StartPose, build_pipeline


class JournalError(ValueError):
    """A journal that cannot be replayed (a record of an unknown kind, a missing map, …)."""


def _floats(a: Any) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=np.float64).ravel()]


class JournalEncoder:
    """Turns core records into JSON-ready dicts (one per journal; it remembers the maps it
    has written out in full)."""

    def __init__(self) -> None:
        self.seq = 0
        self._maps: set[str] = set()

    def encode(self, kind: str, payload: dict[str, Any]) -> dict[str, Any]:
        self.seq += 1
        out: dict[str, Any] = {"seq": self.seq, "kind": kind}
        for key, value in payload.items():
            out[key] = self._value(value)
        return out

    def _value(self, v: Any) -> Any:
        if isinstance(v, ImuSample):
            return {
                "t": v.t,
                "gyro": _floats(v.gyro),
                "accel": None if v.accel is None else _floats(v.accel),
                "device_time_ns": v.device_time_ns,
                "host_time_ns": v.host_time_ns,
            }
        if isinstance(v, SpeedSample):
            return dataclasses.asdict(v)
        if isinstance(v, FrameTracks):
            return {
                "t": v.t,
                "ids": [int(i) for i in v.ids],
                "bearings": _floats(v.bearings),
                "pixels": _floats(v.pixels),
                "ages": [int(a) for a in v.ages],
                "ms": v.ms,
                "descriptor_counts": [int(d.shape[0]) for d in v.descriptors],
                "descriptors": base64.b64encode(
                    b"".join(np.ascontiguousarray(d, np.uint8).tobytes() for d in v.descriptors)
                ).decode(),
            }
        if isinstance(v, LawnMap):
            if v.checksum in self._maps:
                return {"checksum": v.checksum}
            self._maps.add(v.checksum)
            return {"checksum": v.checksum, "document": v.to_document()}
        if isinstance(v, StartPose):
            return {
                "position": _floats(v.position),
                "quaternion": _floats(v.quaternion),
                "gyro_bias": None if v.gyro_bias is None else _floats(v.gyro_bias),
            }
        if isinstance(v, float | int | str | bool) or v is None:
            return v
        if isinstance(v, dict):
            return {str(k): self._value(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [self._value(x) for x in v]
        raise TypeError(f"journal: cannot encode {type(v).__name__}")


class JournalDecoder:
    """The inverse of :class:`JournalEncoder`."""

    def __init__(self) -> None:
        self.maps: dict[str, LawnMap] = {}

    def imu(self, d: dict[str, Any]) -> ImuSample:
        return ImuSample(
            float(d["t"]),
            np.asarray(d["gyro"], dtype=np.float64),
            None if d["accel"] is None else np.asarray(d["accel"], dtype=np.float64),
            d["device_time_ns"],
            d["host_time_ns"],
        )

    def speed(self, d: dict[str, Any]) -> SpeedSample:
        return SpeedSample(**d)

    def tracks(self, d: dict[str, Any]) -> FrameTracks:
        raw = base64.b64decode(d["descriptors"])
        counts = d["descriptor_counts"]
        descs = []
        at = 0
        for k in counts:
            descs.append(np.frombuffer(raw[at : at + 32 * k], np.uint8).reshape(k, 32).copy())
            at += 32 * k
        n = len(d["ids"])
        return FrameTracks(
            float(d["t"]),
            np.asarray(d["ids"], dtype=np.int64),
            np.asarray(d["bearings"], dtype=np.float64).reshape(n, 3),
            np.asarray(d["pixels"], dtype=np.float64).reshape(n, 2),
            np.asarray(d["ages"], dtype=np.int64),
            float(d["ms"]),
            tuple(descs),
        )

    def lawn_map(self, d: dict[str, Any]) -> LawnMap:
        checksum = d["checksum"]
        if "document" in d:
            m = from_document(d["document"], "journal map")
            if m.checksum != checksum:
                raise JournalError(f"journal map {checksum[:19]}: its checksum does not match")
            self.maps[checksum] = m
        if checksum not in self.maps:
            raise JournalError(f"journal: map {checksum[:19]} used before it was written")
        return self.maps[checksum]

    def start_pose(self, d: dict[str, Any] | None) -> StartPose | None:
        if d is None:
            return None
        bias = d.get("gyro_bias")
        return StartPose(
            np.asarray(d["position"], dtype=np.float64),
            np.asarray(d["quaternion"], dtype=np.float64),
            None if bias is None else np.asarray(bias, dtype=np.float64),
        )


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
    """Drive a new :class:`RuntimeCore` through ``records`` (see the module doc)."""
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
        elif kind == "camera_frame":
            core.camera_frame(rec["now"])
        elif kind == "tracks":
            core.tracks(int(rec["serial"]), dec.tracks(rec["tracks"]))
        elif kind == "install":
            req = requests.get(int(rec["serial"]))
            if req is not None:
                core.install(req.serial, build_pipeline(config, camera, req))
        elif kind == "decide":
            compare(core.decide(rec["now"], rec["revealed_at"]), rec["out"], seq)
        elif kind == "set_mode":
            core.set_mode(rec["mode"])
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
