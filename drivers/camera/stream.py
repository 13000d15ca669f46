"""A camera whose frames arrive over a Unix stream socket (the bench's rendered camera).

Same :class:`~drivers.camera.v4l2.CameraSource` interface as the V4L2 camera. The wire format
is one message per frame, the way a network camera or a V4L2 buffer carries it: a 32-byte
header then the pixels,

    magic "MWCF" | u32 sequence | f64 capture time (CLOCK_MONOTONIC, s) | u32 width |
    u32 height | u32 channels | u32 reserved,  then width × height × channels bytes (8-bit).

The capture time is on the host's monotonic clock, as V4L2 buffer timestamps are
(``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``), so it needs no clock mapping. A bad header (wrong
magic, absurd size) drops the connection with a logged error naming what was wrong; a lost
server is reconnected with backoff, like an unplugged USB camera.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import time

import numpy as np

from drivers.camera.base import CameraSource, FrameRate
from mowerhw.common.samples import FrameSample

log = logging.getLogger(__name__)

MAGIC = b"MWCF"
HEADER = struct.Struct("<4sIdIIII")
MAX_SIDE = 8192


def encode_frame(sequence: int, t_capture: float, image: np.ndarray) -> bytes:
    """One frame message (header + pixels)."""
    img = np.ascontiguousarray(image, dtype=np.uint8)
    h, w = img.shape[:2]
    ch = 1 if img.ndim == 2 else img.shape[2]
    return HEADER.pack(MAGIC, sequence & 0xFFFFFFFF, t_capture, w, h, ch, 0) + img.tobytes()


class FrameStreamError(ValueError):
    """A frame message that does not follow the format."""


def decode_header(raw: bytes | bytearray) -> tuple[int, float, int, int, int]:
    magic, seq, t, w, h, ch, _ = HEADER.unpack(raw)
    if magic != MAGIC:
        raise FrameStreamError(f"bad frame magic {magic!r} (expected {MAGIC!r})")
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE) or ch not in (1, 3):
        raise FrameStreamError(
            f"bad frame size {w}x{h}x{ch} (allowed: 1..{MAX_SIDE} px a side, 1 or 3 channels)"
        )
    return seq, t, w, h, ch


def _read_exact(sock: socket.socket, n: int, into: bytearray | None = None) -> bytearray:
    """``n`` bytes from ``sock`` (the buffer itself: a frame's 2.4 MB are not copied again),
    into a new buffer or, for bytes no one keeps, the start of ``into`` (at least ``n``)."""
    buf = bytearray(n) if into is None else into
    view = memoryview(buf)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:n], n - got)
        if k == 0:
            raise ConnectionError("camera stream closed")
        got += k
    return buf


class StreamCamera(CameraSource):
    """Frames from a Unix socket at ``path`` (see the module doc), delivered at most at
    ``fps`` (:class:`~drivers.camera.base.FrameRate`; None: every frame)."""

    def __init__(
        self, path: str, reconnect_max_backoff_s: float = 2.0, fps: float | None = None
    ) -> None:
        super().__init__()
        self.path = path
        self.fps = fps
        self.reconnect_max_backoff_s = reconnect_max_backoff_s
        self._sock: socket.socket | None = None

    def stop(self) -> None:
        self._stop.set()
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
        super().stop()

    def _run(self) -> None:
        backoff = 0.05
        while not self._stop.is_set():
            try:
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                sock.connect(self.path)
            except OSError as exc:
                self.stats.open_failures += 1
                self.stats.last_error = f"{self.path}: {exc}"
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.reconnect_max_backoff_s)
                continue
            self._sock = sock
            self.stats.connected = True
            backoff = 0.05
            log.info("camera: stream %s connected", self.path)
            rate = None if self.fps is None else FrameRate(self.fps)
            scratch = bytearray()  # a skipped frame's pixels, read and let go
            try:
                while not self._stop.is_set():
                    seq, t, w, h, ch = decode_header(_read_exact(sock, HEADER.size))
                    size = w * h * ch
                    if rate is not None:
                        host_s = time.monotonic()
                        if rate.skip(host_s):
                            # read (it is on the wire), not handed on: into one buffer
                            # kept for it, not a new 2.4 MB each time (page faults)
                            if len(scratch) < size:
                                scratch = bytearray(size)
                            _read_exact(sock, size, scratch)
                            self._skipped()
                            continue
                        rate.taken(host_s)
                    pixels = _read_exact(sock, size)
                    shape = (h, w) if ch == 1 else (h, w, ch)
                    img = np.frombuffer(pixels, np.uint8).reshape(shape)
                    img.flags.writeable = False  # as every frame a source hands out
                    self._emit(FrameSample(t=t, image=img, sequence=seq, device_time_s=t))
            except (OSError, ConnectionError, FrameStreamError, struct.error) as exc:
                if not self._stop.is_set():
                    self.stats.read_failures += 1
                    self.stats.reconnects += 1
                    self.stats.last_error = str(exc)
                    log.warning("camera: stream %s lost (%s); reconnecting", self.path, exc)
            finally:
                self.stats.connected = False
                self._sock = None
                with contextlib.suppress(OSError):
                    sock.close()
