"""Recordings: every raw input and the estimator's outputs in one MCAP file.

Channels (JSON encoding; Foxglove schemas where one exists, so the file opens in Foxglove):

============================  ==========================  ===================================
topic                         schema                      payload
============================  ==========================  ===================================
``/vn100/raw``                ``mowerhw.SerialBytes``     serial bytes as read, base64
``/can``                      ``mowerhw.CanFrame``        id, data (hex), extended, rx/tx
``/camera/image``             ``foxglove.CompressedImage`` JPEG, capture time as timestamp
``/estimate/pose``            ``foxglove.PoseInFrame``    pose in the lawn (map) frame
``/estimate/state``           ``mowerhw.EstimatorState``  containment, permit, reason, σ, cov
``/runtime/journal``          ``mowerhw.RuntimeJournal``  the runtime core's inputs/decisions
============================  ==========================  ===================================

Every payload carries ``host_time_ns`` (CLOCK_MONOTONIC when it was read: what a replay feeds
the parsers with); the MCAP log time is the wall clock. Metadata ``config`` holds the YAML of
the run's configuration; attachments hold the camera calibration and the map.

Writing happens on its own thread from a bounded queue, so a slow disk never delays the
caller; chunks are zstd-compressed and closed every ``chunk_size`` bytes, so a crash loses at
most the last chunk. A write error (disk full) stops the recording with an error in the log
and in :attr:`Recorder.error`; the caller carries on.
"""

from __future__ import annotations

import base64
import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("mowerhw.recording.mcap")

SCHEMAS: dict[str, dict[str, Any]] = {
    "mowerhw.SerialBytes": {
        "type": "object",
        "properties": {
            "host_time_ns": {"type": "integer"},
            "data": {"type": "string", "contentEncoding": "base64"},
        },
    },
    "mowerhw.CanFrame": {
        "type": "object",
        "properties": {
            "host_time_ns": {"type": "integer"},
            "id": {"type": "integer"},
            "data": {"type": "string", "description": "hex"},
            "extended": {"type": "boolean"},
            "direction": {"type": "string", "enum": ["rx", "tx"]},
        },
    },
    "foxglove.CompressedImage": {
        "type": "object",
        "title": "foxglove.CompressedImage",
        "properties": {
            "timestamp": {
                "type": "object",
                "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
            },
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
        },
    },
    "foxglove.PoseInFrame": {
        "type": "object",
        "title": "foxglove.PoseInFrame",
        "properties": {
            "timestamp": {
                "type": "object",
                "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
            },
            "frame_id": {"type": "string"},
            "pose": {
                "type": "object",
                "properties": {
                    "position": {
                        "type": "object",
                        "properties": {k: {"type": "number"} for k in "xyz"},
                    },
                    "orientation": {
                        "type": "object",
                        "properties": {k: {"type": "number"} for k in "xyzw"},
                    },
                },
            },
        },
    },
    "mowerhw.EstimatorState": {
        "type": "object",
        "properties": {
            "host_time_ns": {"type": "integer"},
            "mode": {"type": "string"},
            "state": {"type": "string"},
            "permit": {"type": "boolean"},
            "reason": {"type": "string"},
            "sigma_xy_m": {"type": "number"},
            "signed_distance_m": {"type": ["number", "null"]},
            "covariance": {"type": "array", "items": {"type": "number"}},
        },
    },
}

SCHEMAS["mowerhw.RuntimeJournal"] = {
    "type": "object",
    "description": "one input or decision of the runtime core (mowerhw.runtime.journal)",
    "properties": {"seq": {"type": "integer"}, "kind": {"type": "string"}},
}

TOPICS = {
    "/runtime/journal": "mowerhw.RuntimeJournal",
    "/vn100/raw": "mowerhw.SerialBytes",
    "/can": "mowerhw.CanFrame",
    "/camera/image": "foxglove.CompressedImage",
    "/estimate/pose": "foxglove.PoseInFrame",
    "/estimate/state": "mowerhw.EstimatorState",
}


def stamp(t_s: float) -> dict[str, int]:
    """A Foxglove time from seconds."""
    ns = round(t_s * 1e9)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def pose_message(t_s: float, position: Any, q_wxyz: Any, frame: str = "lawn") -> dict[str, Any]:
    w, x, y, z = (float(v) for v in q_wxyz)
    px, py, pz = (float(v) for v in position)
    return {
        "timestamp": stamp(t_s),
        "frame_id": frame,
        "pose": {
            "position": {"x": px, "y": py, "z": pz},
            "orientation": {"x": x, "y": y, "z": z, "w": w},
        },
    }


def state_message(
    host_ns: int,
    mode: str,
    state: str,
    permit: bool,
    reason: str,
    sigma: float,
    signed_distance: float | None,
    covariance: Any,
) -> dict[str, Any]:
    """A ``/estimate/state`` message (``mowerhw.EstimatorState``): recorded, and served live
    by the status page's Foxglove server."""
    cov = [] if covariance is None else np.asarray(covariance, dtype=np.float64).ravel().tolist()
    sd = signed_distance if signed_distance is not None and np.isfinite(signed_distance) else None
    return {
        "host_time_ns": host_ns,
        "mode": mode,
        "state": state,
        "permit": bool(permit),
        "reason": reason,
        "sigma_xy_m": float(sigma) if sigma is not None and np.isfinite(sigma) else -1.0,
        "signed_distance_m": sd,
        "covariance": cov,
    }


class Recorder:
    """Records to ``path`` from any thread (see the module doc)."""

    def __init__(
        self,
        path: str | Path | Any,
        config_yaml: str = "",
        attachments: dict[str, bytes] | None = None,
        jpeg_quality: int = 90,
        chunk_size: int = 1 << 20,
        queue_size: int = 16384,
        journal_encoder: Callable[[str, dict[str, Any]], dict[str, Any]] | None = None,
    ) -> None:
        self.path = path
        #: turns a runtime core record into JSON (on the writer thread, off the caller's)
        self.journal_encoder = journal_encoder
        self.jpeg_quality = jpeg_quality
        self.chunk_size = chunk_size
        self.error = ""
        self.counts: dict[str, int] = dict.fromkeys(TOPICS, 0)
        self.dropped = 0
        self.bad_items = 0
        self.bytes_in = 0
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._config_yaml = config_yaml
        self._attachments = dict(attachments or {})
        self._wall0 = time.time_ns() - time.monotonic_ns()  # wall = monotonic + offset
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._started = threading.Event()
        self._closed = False
        self._thread.start()
        self._started.wait(5.0)

    # ------------------------------------------------------------------------ producers

    @property
    def ok(self) -> bool:
        return not self.error and not self._closed

    def _put(self, item: tuple) -> None:
        if not self.ok:
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:  # the disk cannot keep up: drop, never block the caller
            self.dropped += 1

    def journal(self, host_ns: int, kind: str, payload: dict[str, Any]) -> None:
        """A runtime core record (encoded on the writer thread by ``journal_encoder``)."""
        if self.journal_encoder is not None:
            self._put(("/runtime/journal", host_ns, (kind, payload)))

    def serial(self, host_ns: int, data: bytes) -> None:
        self._put(("/vn100/raw", host_ns, {"host_time_ns": host_ns, "data": data}))

    def can(self, host_ns: int, arbitration_id: int, data: bytes, extended: bool, rx: bool = True):
        msg = {
            "host_time_ns": host_ns,
            "id": int(arbitration_id),
            "data": bytes(data).hex(),
            "extended": bool(extended),
            "direction": "rx" if rx else "tx",
        }
        self._put(("/can", host_ns, msg))

    def frame(self, host_ns: int, t_capture: float, sequence: int, image: np.ndarray) -> None:
        self._put(("/camera/image", host_ns, (t_capture, sequence, image)))

    def estimate(
        self,
        host_ns: int,
        mode: str,
        position: Any,
        q_wxyz: Any,
        covariance: Any,
        state: str,
        permit: bool,
        reason: str,
        sigma: float,
        signed_distance: float | None,
    ) -> None:
        t = host_ns * 1e-9
        self._put(("/estimate/pose", host_ns, pose_message(t, position, q_wxyz)))
        msg = state_message(
            host_ns, mode, state, permit, reason, sigma, signed_distance, covariance
        )
        self._put(("/estimate/state", host_ns, msg))

    def attach(self, name: str, data: bytes) -> None:
        self._put(("@attach", time.monotonic_ns(), (name, data)))

    def close(self, timeout: float = 10.0) -> None:
        if self._closed:
            return
        self._queue.put(("@close", 0, None))
        self._thread.join(timeout)
        self._closed = True

    def status(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "state": f"failed: {self.error}"
            if self.error
            else ("closed" if self._closed else "recording"),
            "messages": dict(self.counts),
            "dropped": self.dropped,
        }

    # --------------------------------------------------------------------------- writer

    def _run(self) -> None:
        from mcap.writer import CompressionType, Writer

        fh = None
        try:
            fh = open(self.path, "wb") if isinstance(self.path, str | Path) else self.path  # noqa: SIM115
            writer = Writer(fh, chunk_size=self.chunk_size, compression=CompressionType.ZSTD)
            writer.start(profile="", library="mowerhw")
            channels = {}
            for topic, schema_name in TOPICS.items():
                sid = writer.register_schema(
                    name=schema_name,
                    encoding="jsonschema",
                    data=json.dumps(SCHEMAS[schema_name]).encode(),
                )
                channels[topic] = writer.register_channel(
                    topic=topic, message_encoding="json", schema_id=sid
                )
            if self._config_yaml:
                writer.add_metadata("config", {"yaml": self._config_yaml})
            now = time.time_ns()
            for name, data in self._attachments.items():
                writer.add_attachment(now, now, name, "application/octet-stream", data)
        except OSError as exc:
            self._fail(exc)
            self._started.set()
            return
        self._started.set()
        seq = 0
        while True:
            topic, host_ns, payload = self._queue.get()
            if topic == "@close":
                break
            if self.error:
                continue
            try:
                if topic == "@attach":
                    name, data = payload
                    writer.add_attachment(time.time_ns(), time.time_ns(), name, "", data)
                    continue
                data = self._encode(topic, payload)
                log_time = host_ns + self._wall0
                writer.add_message(channels[topic], log_time, data, log_time, seq)
                seq += 1
                self.counts[topic] += 1
                self.bytes_in += len(data)
            except OSError as exc:
                self._fail(exc)
            except Exception as exc:
                self.bad_items += 1
                if self.bad_items == 1:
                    log.error("recording: %s message not written: %r", topic, exc)
        if not self.error:
            try:
                writer.finish()
            except OSError as exc:
                self._fail(exc)
        if fh is not None and isinstance(self.path, str | Path):
            try:
                fh.close()
            except OSError as exc:
                self._fail(exc)

    def _encode(self, topic: str, payload: Any) -> bytes:
        if topic == "/runtime/journal":
            assert self.journal_encoder is not None
            payload = self.journal_encoder(*payload)
        elif topic == "/vn100/raw":
            payload = {**payload, "data": base64.b64encode(payload["data"]).decode()}
        elif topic == "/camera/image":
            import cv2

            t_capture, sequence, image = payload
            ok, jpg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if not ok:
                raise OSError("JPEG encoding failed")
            payload = {
                "timestamp": stamp(t_capture),
                "frame_id": f"omni/{sequence}",
                "data": base64.b64encode(jpg.tobytes()).decode(),
                "format": "jpeg",
            }
        return json.dumps(payload, separators=(",", ":")).encode()

    def _fail(self, exc: OSError) -> None:
        if not self.error:
            self.error = f"{type(exc).__name__}: {exc}"
            log.error(
                "recording to %s stopped: %s (estimation and permit carry on)", self.path, exc
            )


# ------------------------------------------------------------------------------ reading


#: an MCAP chunk record as the recorder writes it: opcode 0x06, then length, start and end
#: time, uncompressed size and CRC (8 + 8 + 8 + 8 + 4 bytes), then the compression "zstd"
_CHUNK_OPCODE = 0x06
_ZSTD_FIELD = b"\x04\x00\x00\x00zstd"
_ZSTD_FIELD_AT = 1 + 8 + 8 + 8 + 8 + 4
#: no record of a recording is bigger (a corrupt length field must not allocate gigabytes)
MAX_RECORD_BYTES = 256 << 20


class RecordingError(ValueError):
    """A file that is not a recording at all."""


class RecordingRead:
    """Messages of a recording in file order, tolerant of a cut-off end and of damage.

    Chunk CRCs are checked; a damaged chunk (bad CRC, does not decompress, bad records in
    it) is skipped, and damage to the file's structure is skipped to the next chunk that
    reads; each is reported in :attr:`damage` with its byte offset, and summed up in
    :attr:`warning`. A file that merely ends early (a crash or power loss) says so. A
    message whose content is not the JSON the recorder writes is skipped and counted."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.warning = ""
        self.damage: list[str] = []
        self.skipped_messages = 0
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.bytes_read = 0  # how far into the file the reader is (progress bars)

    def messages(self) -> Iterator[tuple[str, int, Any]]:
        """(topic, log_time_ns, decoded JSON) for every readable message; stops at a
        truncation, skips damage, with :attr:`warning` set."""
        from mcap.records import Chunk
        from mcap.stream_reader import StreamReader

        self._channels: dict[int, str] = {}
        self._n = 0
        size = self.path.stat().st_size
        with open(self.path, "rb") as fh:
            pos, first = 0, True
            while pos < size:
                fh.seek(pos)
                good_end = pos
                reader = StreamReader(
                    fh,
                    skip_magic=not first,
                    emit_chunks=True,
                    validate_crcs=True,
                    record_size_limit=MAX_RECORD_BYTES,
                )
                first = False
                try:
                    for rec in reader.records:
                        start, good_end = good_end, fh.tell()
                        self.bytes_read = good_end
                        if isinstance(rec, Chunk):
                            yield from self._chunk(rec, start)
                        else:
                            yield from self._record(rec)
                    break  # the end of the file, read cleanly
                except Exception as exc:
                    why = f"{type(exc).__name__}{': ' + str(exc)[:120] if str(exc) else ''}"
                    if good_end == 0:
                        raise RecordingError(
                            f"{self.path}: not an MCAP recording ({why})"
                        ) from None
                    nxt = self._next_chunk(fh, good_end + 1, size)
                    if nxt is None and self._cut_off(fh, good_end, size):
                        self.warning = (
                            f"{self.path}: the recording ends abruptly after {self._n} messages "
                            f"({why}; the writer did not finish it: a crash or power loss); "
                            "replayed up to the cut"
                        )
                        break
                    skipped = (nxt if nxt is not None else size) - good_end
                    self.damage.append(f"byte {good_end}: {why}; skipped {skipped} bytes")
                    if nxt is None:
                        break
                    pos = nxt
        if self.damage:
            self.warning = (
                f"{self.path}: the recording is damaged ({len(self.damage)} place(s): "
                + "; ".join(self.damage[:5])
                + ("; ..." if len(self.damage) > 5 else "")
                + f"); {self._n} messages read, the damaged parts skipped"
                + (f"; {self.warning}" if self.warning else "")
            )
        if self.skipped_messages:
            self.warning += (
                f"{'; ' if self.warning else ''}{self.skipped_messages} message(s) with unreadable "
                "content skipped"
            )
        if self.warning:
            log.warning(self.warning)

    def attachment(self, name: str) -> bytes | None:
        """The attachment ``name`` wherever it is in the file (a map attached mid-run):
        from the summary's index when the end is intact, else by reading the whole file."""
        if name in self.attachments:
            return self.attachments[name]
        from mcap.reader import make_reader

        try:
            with open(self.path, "rb") as fh:
                for att in make_reader(fh).iter_attachments():
                    self.attachments.setdefault(att.name, bytes(att.data))
        except Exception:  # no usable summary (a cut or damaged end): read it all
            other = RecordingRead(self.path)
            for _ in other.messages():
                pass
            for key, data in other.attachments.items():
                self.attachments.setdefault(key, data)
        return self.attachments.get(name)

    def _chunk(self, chunk: Any, offset: int) -> Iterator[tuple[str, int, Any]]:
        from mcap.stream_reader import breakup_chunk

        try:
            records = breakup_chunk(chunk, validate_crc=True)
        except Exception as exc:
            why = f"{type(exc).__name__}{': ' + str(exc)[:120] if str(exc) else ''}"
            self.damage.append(f"chunk at byte {offset}: {why}; skipped")
            return
        for rec in records:
            yield from self._record(rec)

    def _record(self, rec: Any) -> Iterator[tuple[str, int, Any]]:
        from mcap.records import Attachment, Channel, Message, Metadata

        if isinstance(rec, Channel):
            self._channels[rec.id] = rec.topic
        elif isinstance(rec, Metadata):
            self.metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Attachment):
            self.attachments[rec.name] = bytes(rec.data)
        elif isinstance(rec, Message):
            topic = self._channels.get(rec.channel_id)
            try:
                body = json.loads(rec.data)
            except (ValueError, RecursionError):
                body = None
            if topic is None or not isinstance(body, dict):
                self.skipped_messages += 1
                return
            self._n += 1
            yield topic, rec.log_time, body

    @staticmethod
    def _next_chunk(fh: Any, start: int, size: int) -> int | None:
        """The offset of the next chunk record at or after ``start``, by its "zstd" field."""
        block = 1 << 20
        at = start
        while at < size:
            fh.seek(at)
            data = fh.read(block + len(_ZSTD_FIELD))
            k = 0
            while (k := data.find(_ZSTD_FIELD, k)) >= 0:
                cand = at + k - _ZSTD_FIELD_AT
                if cand >= start:
                    fh.seek(cand)
                    if fh.read(1) == bytes([_CHUNK_OPCODE]):
                        return cand
                k += 1
            at += block
        return None

    @staticmethod
    def _cut_off(fh: Any, good_end: int, size: int) -> bool:
        """The failure at ``good_end`` is the file ending inside a record (a cut), not a
        damaged middle: the record's own length reaches past the end of the file."""
        fh.seek(good_end)
        head = fh.read(9)
        if len(head) < 9:
            return True
        length = int.from_bytes(head[1:9], "little")
        return good_end + 9 + length > size


def decode_jpeg(b64: str) -> np.ndarray:
    import cv2

    buf = np.frombuffer(base64.b64decode(b64), np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError("camera frame in the recording is not a valid JPEG")
    return img
