"""The camera interface: :class:`CameraSource` delivers
:class:`~mowerhw.common.samples.FrameSample` objects from its own thread to a callback; the
V4L2 camera (:mod:`.v4l2`), a socket stream (:mod:`.stream`) and the synthetic mock
(:mod:`.mock`) implement it. :func:`asyncio_sink` hands frames to an asyncio queue without
blocking the reader thread (the oldest frame is dropped when full)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.threaded import ThreadedDevice
from mowerhw.common.samples import FrameSample


@dataclass
class CameraStats:
    frames: int = 0
    read_failures: int = 0
    reconnects: int = 0
    open_failures: int = 0
    #: frames the camera delivered faster than its configured rate, dropped undecoded
    skipped: int = 0
    last_error: str = ""
    connected: bool = False


class FrameRate:
    """Which of a camera's frames are delivered at ``fps`` (the rate the front end is sized
    for) when the camera runs faster (``camera.device_fps``, or a camera without a mode at
    the rate asked for): a frame is taken once it is due, on a grid of ``1/fps`` with a
    tolerance of :data:`TOLERANCE` of a period (a camera at the rate itself, with its
    jitter, keeps every frame), and the grid never bursts to catch up after a stall. The
    one owner of that policy for every driver (V4L2, the socket stream, the mock)."""

    #: a frame is taken from this share of a period before it is due
    TOLERANCE = 0.25

    def __init__(self, fps: float) -> None:
        self.period = 1.0 / fps
        self.next_due = 0.0  # host s

    def skip(self, host_s: float) -> bool:
        """True: the frame that arrived at ``host_s`` comes before its turn; drop it (before
        decoding it)."""
        return host_s < self.next_due - self.TOLERANCE * self.period

    def taken(self, host_s: float) -> None:
        """A frame arriving at ``host_s`` was delivered: the next is due a period on, and
        never within half a period of this one."""
        self.next_due = max(self.next_due + self.period, host_s + 0.5 * self.period)


class CameraSource(ThreadedDevice, ABC):
    """A source of timestamped frames, delivered from its own thread to ``on_frame``. The
    arrival of the newest frame :class:`FrameRate` dropped is :attr:`alive_at`: the camera
    is alive between the frames delivered, and its liveness is judged at its own rate, not
    the front end's."""

    def __init__(self) -> None:
        super().__init__()
        self.thread_name = type(self).__name__
        self.stats = CameraStats()
        self.on_frame: Callable[[FrameSample], None] | None = None
        #: host monotonic time (s) of the newest frame dropped by the rate, None before one:
        #: read by the consumer when it decides (one float, written by this thread only) —
        #: not pushed to it, which woke its loop for every dropped frame (26 a second for a
        #: 30-fps camera and a 4-fps front end)
        self.alive_at: float | None = None

    def start(self, on_frame: Callable[[FrameSample], None]) -> None:
        """Deliver frames to ``on_frame`` (from this device's thread)."""
        self.on_frame = on_frame
        self._start_thread()

    def _skipped(self) -> None:
        """A frame came before its turn (:class:`FrameRate`) and was dropped undecoded."""
        self.stats.skipped += 1
        self.alive_at = time.monotonic()

    @abstractmethod
    def _run(self) -> None: ...

    def status(self) -> dict[str, Any]:
        """The counters, for the status command."""
        return dict(vars(self.stats))

    def _emit(self, frame: FrameSample) -> None:
        self.stats.frames += 1
        if self.on_frame is not None:
            self.on_frame(frame)


def asyncio_sink(
    loop: asyncio.AbstractEventLoop,
    queue: asyncio.Queue[Any],
    arrived: Callable[[Any], None] | None = None,
) -> Callable[[Any], None]:
    """A callback for a reader thread that puts items on an asyncio queue, thread-safely,
    dropping the oldest item when the queue is full (the newest frame matters most);
    ``arrived`` is told of every item on the loop first, dropped ones too."""

    def put(item: Any) -> None:
        if arrived is not None:
            arrived(item)
        if queue.full():
            with contextlib.suppress(asyncio.QueueEmpty):
                queue.get_nowait()
        queue.put_nowait(item)

    def sink(item: Any) -> None:
        with contextlib.suppress(RuntimeError):  # the loop is closing
            loop.call_soon_threadsafe(put, item)

    return sink


def synthetic_frame(t: float, width: int = 1540, height: int = 1540) -> np.ndarray:
    """A synthetic 8-bit frame: a gradient with a bright square moving with time."""
    img = np.add.outer(np.arange(height, dtype=np.uint16), np.arange(width, dtype=np.uint16))
    img = (img * (255 / (width + height))).astype(np.uint8)
    s = max(8, min(width, height) // 20)
    x = int((t * 100) % max(1, width - s))
    img[height // 2 : height // 2 + s, x : x + s] = 255
    return img
