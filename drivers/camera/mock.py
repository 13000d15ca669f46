"""A simulated camera behind the same interface as :class:`drivers.camera.v4l2.V4l2Camera`.

Frames come from a generator ``render(t) -> uint8 image`` (t: seconds since start) at the
camera's rate (``device_fps``; those beyond ``fps`` are dropped unrendered, as
:class:`~drivers.camera.base.FrameRate` says), stamped with their capture time and delivered
``latency_s`` later, as a V4L2 device would. It can freeze (deliver nothing for a while, like
a hung driver).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from drivers.camera.base import CameraSource, FrameRate, synthetic_frame
from mowerhw.common.samples import FrameSample


class MockCamera(CameraSource):
    def __init__(
        self,
        render: Callable[[float], np.ndarray] | None = None,
        fps: float = 4.0,
        device_fps: float | None = None,
        width: int = 1540,
        height: int = 1540,
        latency_s: float = 0.0,
        freeze: list[tuple[float, float]] | None = None,
    ) -> None:
        super().__init__()
        self.render = render or (lambda t: synthetic_frame(t, width, height))
        self.fps = fps
        self.device_fps = fps if device_fps is None else device_fps
        self.latency_s = latency_s
        self.freeze = list(freeze or [])
        self.frozen = False  # set from outside to freeze now (bench fault injection)
        self._seq = 0

    def _run(self) -> None:
        t0 = time.monotonic()
        period = 1.0 / self.device_fps
        rate = FrameRate(self.fps)
        nxt = t0
        self.stats.connected = True
        while not self._stop.is_set():
            wait = nxt - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                break
            t_cap = time.monotonic()
            nxt += period
            rel = t_cap - t0
            if self.frozen or any(a <= rel < a + d for a, d in self.freeze):
                continue
            if rate.skip(t_cap):
                self._skipped()  # not rendered: a V4L2 frame grabbed, not decoded
                continue
            rate.taken(t_cap)
            img = self.render(rel)
            if self.latency_s:
                self._stop.wait(self.latency_s)
            self._seq += 1
            self._emit(FrameSample(t=t_cap, image=img, sequence=self._seq, device_time_s=rel))
