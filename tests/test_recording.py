"""Recordings (MCAP): round trip, a cut-off file, a full disk, deterministic replay."""

from __future__ import annotations

import errno
import io

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mowerhw.recording.mcap import Recorder, RecordingRead


def _record(path, frames: int = 3) -> Recorder:
    rec = Recorder(path, "imu:\n  rate_hz: 100\n", {"calibration.yaml": b"cam0: {}\n"})
    img = (np.arange(64 * 64, dtype=np.uint32).reshape(64, 64) % 251).astype(np.uint8)
    for k in range(frames):
        ns = 1_000_000_000 + k * 250_000_000
        rec.serial(ns, b"\xfa\x01" + bytes([k]) * 10)
        rec.can(ns + 1, 0x0CFE4980, bytes([k, 0, 0, 0, 0, 0, 0xFF, 0xFD]), True)
        rec.frame(ns + 2, ns * 1e-9, k + 1, img)
        rec.estimate(
            ns + 3, "mow", (k, 0.0, 0.0), (1, 0, 0, 0), np.eye(6), "INSIDE", True, "", 0.01, 1.5
        )
    rec.close()
    return rec


def test_round_trip_with_foxglove_schemas(tmp_path) -> None:
    from mcap.reader import make_reader

    path = tmp_path / "r.mcap"
    rec = _record(path)
    assert not rec.error and rec.counts["/camera/image"] == 3
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    topics = {
        c.topic: summary.statistics.channel_message_counts.get(c.id, 0)
        for c in summary.channels.values()
    }
    assert topics["/vn100/raw"] == 3 and topics["/can"] == 3 and topics["/camera/image"] == 3
    schemas = {s.name for s in summary.schemas.values()}
    assert {"foxglove.CompressedImage", "foxglove.PoseInFrame"} <= schemas
    assert summary.chunk_indexes and all(ci.compression == "zstd" for ci in summary.chunk_indexes)
    rd = RecordingRead(path)
    msgs = list(rd.messages())
    assert rd.warning == "" and len(msgs) == 15
    assert rd.metadata["config"]["yaml"].startswith("imu:")
    assert rd.attachments["calibration.yaml"] == b"cam0: {}\n"
    img = next(m for t, _, m in msgs if t == "/camera/image")
    assert img["format"] == "jpeg" and img["timestamp"] == {"sec": 1, "nsec": 0}


def test_a_cut_off_recording_reads_up_to_the_cut(tmp_path) -> None:
    path = tmp_path / "r.mcap"
    rec = Recorder(path, chunk_size=2048)
    for k in range(400):
        rec.serial(k * 10_000_000, bytes(range(40)))
    rec.close()
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])  # a SIGKILL mid-run leaves no summary
    rd = RecordingRead(cut)
    n = sum(1 for _ in rd.messages())
    assert 0 < n < 400
    assert "ends abruptly" in rd.warning and f"after {n} messages" in rd.warning


class _DiskFull(io.RawIOBase):
    """A file that takes ``room`` bytes, then fails like a full disk."""

    def __init__(self, room: int) -> None:
        self.room = room
        self.written = 0

    def writable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.written

    def write(self, b) -> int:
        if self.written + len(b) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.written += len(b)
        return len(b)


def test_disk_full_stops_recording_not_the_caller(caplog: pytest.LogCaptureFixture) -> None:
    sink = _DiskFull(room=20_000)
    rec = Recorder(sink, chunk_size=4096)
    for k in range(2000):  # the caller never blocks nor sees an exception
        rec.serial(k * 10_000_000, bytes(200))
    rec.close()
    assert "No space left on device" in rec.error
    assert rec.status()["state"].startswith("failed: OSError")
    assert any(
        "recording to" in r.getMessage() and "stopped" in r.getMessage() for r in caplog.records
    )


def _long_recording(path, with_map_at: int = 1000) -> bytes:
    rec = Recorder(path, "imu: {}\n", chunk_size=4096)
    for k in range(2200):
        if k == with_map_at:
            rec.attach("map.json", b'{"format": "mowerhw-map"}')
        rec.serial(k * 10_000_000, bytes(range(40)))
    rec.close()
    return path.read_bytes()


def test_damage_is_skipped_and_reported_with_its_offset(tmp_path) -> None:
    data = bytearray(_long_recording(tmp_path / "r.mcap"))
    clean = RecordingRead(tmp_path / "r.mcap")
    assert sum(1 for _ in clean.messages()) == 2200 and clean.warning == ""
    data[len(data) // 3] ^= 0x10  # one bit flipped inside a chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    rd = RecordingRead(bad)
    n = sum(1 for _ in rd.messages())
    assert 2000 < n < 2200  # one chunk lost, the rest read
    assert rd.damage and rd.damage[0].startswith("chunk at byte ")  # CRC or zstd error
    assert "the recording is damaged" in rd.warning and "crash or power loss" not in rd.warning


def test_a_map_attached_mid_run_is_found(tmp_path) -> None:
    data = _long_recording(tmp_path / "r.mcap", with_map_at=1500)
    rd = RecordingRead(tmp_path / "r.mcap")
    assert rd.attachment("map.json") == b'{"format": "mowerhw-map"}'
    cut = tmp_path / "cut.mcap"  # no summary: found by reading the file
    cut.write_bytes(data[: len(data) * 9 // 10])
    assert RecordingRead(cut).attachment("map.json") == b'{"format": "mowerhw-map"}'


def test_a_file_that_is_no_recording_is_refused(tmp_path) -> None:
    from mowerhw.recording.mcap import RecordingError

    path = tmp_path / "x.mcap"
    path.write_bytes(np.random.default_rng(1).bytes(5000))
    with pytest.raises(RecordingError, match="not an MCAP recording"):
        list(RecordingRead(path).messages())


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory) -> bytes:
    return _long_recording(tmp_path_factory.mktemp("rec") / "r.mcap")


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    flips=st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), min_size=1, max_size=8),
    cut=st.floats(0.05, 1.0),
)
def test_fuzzed_damage_never_raises_anything_but_a_refusal(
    long_recording: bytes, tmp_path_factory, flips, cut
) -> None:
    from mowerhw.recording.mcap import RecordingError

    data = bytearray(long_recording[: max(16, int(len(long_recording) * cut))])
    for where, value in flips:
        data[min(len(data) - 1, int(where * len(data)))] = value
    path = tmp_path_factory.mktemp("fz") / "f.mcap"
    path.write_bytes(bytes(data))
    rd = RecordingRead(path)
    try:
        n = sum(1 for _ in rd.messages())
    except RecordingError as exc:
        assert "not an MCAP recording" in str(exc)
        return
    assert 0 <= n <= 2200
    if n < 2200:
        assert rd.warning
