"""The runtime core's journal: its inputs and decisions as JSON, and their replay.

A record is ``{"seq", "kind", ...payload}``; numbers are written with Python's shortest exact
``repr`` (so they read back bit for bit), arrays as flat lists, descriptors as base64, a map
as its document the first time its checksum appears and by checksum after that. The kinds are
the :class:`~mowerhw.runtime.core.RuntimeCore` methods that wrote them.

:func:`mowerhw.recording.replay.replay_journal` drives a new core through a journal.
"""

from __future__ import annotations

import base64
import dataclasses
from typing import Any, Protocol

import numpy as np

from mowerhw.common.relocalization import Relocalization
from mowerhw.common.samples import ImuSample, SpeedSample
from mowerhw.frontend.tracker import FrameTracks
from mowerhw.map import LawnMap, from_document
from mowerhw.mow.gate import Decision
from mowerhw.runtime.pipelines import StartPose


class Journal(Protocol):
    """Where the core writes its inputs and decisions (a recording, or nothing)."""

    def write(self, kind: str, payload: dict[str, Any]) -> None: ...


def decision_key(d: Decision) -> list[Any]:
    """What a decision is, for comparing a replay with the live run."""
    return [bool(d.permit), str(d.state), d.reason]


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
                "mag": None if v.mag is None else _floats(v.mag),
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
                "relocalization": self._value(v.relocalization),
            }
        if isinstance(v, Relocalization):
            return {
                "ok": v.ok,
                "r_wb": _floats(v.r_wb),
                "p_wb": _floats(v.p_wb),
                "inliers": [[int(r), int(i)] for r, i in v.inliers],
                "runner_up": v.runner_up,
                "hypotheses": v.hypotheses,
                "ms": v.ms,
                "why": v.why,
                "covariance": None if v.covariance is None else _floats(v.covariance),
                "landmark_cross": None if v.landmark_cross is None else _floats(v.landmark_cross),
                "trusted": None if v.trusted is None else [bool(x) for x in v.trusted],
                "rival": v.rival,
            }
        if isinstance(v, LawnMap):
            if v.checksum in self._maps:
                return {"checksum": v.checksum}
            doc = v.to_document()
            key = v.checksum or doc["checksum"]  # a map never saved has no checksum yet
            self._maps.add(key)
            return {"checksum": key, "document": doc}
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
            None if d.get("mag") is None else np.asarray(d["mag"], dtype=np.float64),
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
            self.relocalization(d.get("relocalization")),
        )

    def relocalization(self, d: dict[str, Any] | None) -> Relocalization | None:
        if d is None:
            return None
        return Relocalization(
            bool(d["ok"]),
            np.asarray(d["r_wb"], dtype=np.float64).reshape(3, 3),
            np.asarray(d["p_wb"], dtype=np.float64).reshape(3),
            [(int(r), int(i)) for r, i in d["inliers"]],
            int(d["runner_up"]),
            int(d["hypotheses"]),
            float(d["ms"]),
            str(d["why"]),
            None
            if d.get("covariance") is None
            else np.asarray(d["covariance"], dtype=np.float64).reshape(3, 3),
            None
            if d.get("landmark_cross") is None
            else np.asarray(d["landmark_cross"], dtype=np.float64).reshape(3, -1),
            None if d.get("trusted") is None else np.asarray(d["trusted"], dtype=bool),
            bool(d.get("rival", False)),  # journals before stop 75 have none
        )

    def lawn_map(self, d: dict[str, Any]) -> LawnMap:
        key = d["checksum"]
        if "document" in d:
            self.maps[key] = from_document(d["document"], "journal map")  # checksum verified
        if key not in self.maps:
            raise JournalError(f"journal: map {key[:19]} used before it was written")
        return self.maps[key]

    def start_pose(self, d: dict[str, Any] | None) -> StartPose | None:
        if d is None:
            return None
        bias = d.get("gyro_bias")
        return StartPose(
            np.asarray(d["position"], dtype=np.float64),
            np.asarray(d["quaternion"], dtype=np.float64),
            None if bias is None else np.asarray(bias, dtype=np.float64),
        )
