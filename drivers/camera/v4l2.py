"""The V4L2 camera (OpenCV): a :class:`~drivers.camera.base.CameraSource`.

:class:`V4l2Camera` opens ``cv2.VideoCapture(device, cv2.CAP_V4L2)`` with the
configured size, pixel format and rate, reads frames in its own thread (at most at that rate:
a camera that delivers faster has the extra frames dropped undecoded), times each frame by the
driver's buffer timestamp (``CAP_PROP_POS_MSEC``) through a
:class:`mowerhw.common.clocksync.FrameClock` (on the host's monotonic clock as V4L2 stamps it:
as it is; on another clock: mapped), and when the device disappears (USB unplugged, driver
reset) releases it and reopens it with backoff.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from drivers.camera.base import CameraSource
from mowerhw.common.clocksync import FrameClock
from mowerhw.common.samples import FrameSample

log = logging.getLogger(__name__)


_FOURCC = {"GREY": "GREY", "YUYV": "YUYV", "MJPG": "MJPG", "BGR3": "BGR3"}


class V4l2Camera(CameraSource):
    """A V4L2 camera through OpenCV (see the module doc)."""

    #: a frame is decoded from this share of a period before it is due (a camera at the
    #: rate asked for, with its jitter, keeps every frame)
    RATE_TOLERANCE = 0.25

    def __init__(
        self,
        device: str,
        width: int = 1540,
        height: int = 1540,
        fps: float = 4.0,
        pixel_format: str = "GREY",
        reconnect_max_backoff_s: float = 5.0,
        failures_before_reconnect: int = 5,
        clock: FrameClock | None = None,
        capture_factory: Callable[[str], Any] | None = None,
    ) -> None:
        super().__init__()
        self.device = device
        self.width, self.height, self.fps = width, height, fps
        self.pixel_format = pixel_format
        self.reconnect_max_backoff_s = reconnect_max_backoff_s
        self.failures_before_reconnect = failures_before_reconnect
        self.clock = clock or FrameClock()
        self._factory = capture_factory
        self._seq = 0

    def status(self) -> dict[str, Any]:
        """The counters, and where the frame times come from (:class:`FrameClock`)."""
        return {**super().status(), "clock": dict(vars(self.clock.stats))}

    def _open(self) -> Any:
        import cv2

        if self._factory is not None:
            cap = self._factory(self.device)
        else:
            cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            with contextlib.suppress(Exception):
                cap.release()
            raise OSError(f"cannot open camera {self.device}")
        fourcc = cv2.VideoWriter_fourcc(*_FOURCC[self.pixel_format])  # type: ignore[attr-defined]
        cap.set(cv2.CAP_PROP_FOURCC, fourcc)
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        cap.set(cv2.CAP_PROP_FPS, self.fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a backlog
        return cap

    def _run(self) -> None:
        import cv2

        cap = None
        backoff = 0.1
        failures = 0
        next_due = 0.0  # when the next frame to decode is due (host s)
        period = 1.0 / self.fps
        while not self._stop.is_set():
            if cap is None:
                try:
                    cap = self._open()
                    self.stats.connected = True
                    backoff, failures = 0.1, 0
                    log.info("camera: %s open", self.device)
                except Exception as exc:  # OSError, cv2.error
                    self.stats.open_failures += 1
                    self.stats.last_error = str(exc)
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, self.reconnect_max_backoff_s)
                    continue
            ok = cap.grab()
            host_s = time.monotonic()
            if ok and host_s < next_due - self.RATE_TOLERANCE * period:
                # faster than camera.fps (many USB cameras have no mode at the rate asked
                # for): the frame is dropped before it is decoded, or the front end would
                # track every one of them on a computer sized for the rate configured
                self.stats.skipped += 1
                failures = 0
                continue
            ok, img = cap.retrieve() if ok else (False, None)
            if not ok or img is None:
                failures += 1
                self.stats.read_failures += 1
                if failures >= self.failures_before_reconnect:
                    self.stats.last_error = f"{self.device}: {failures} failed reads"
                    log.warning("camera: %s stopped delivering; reconnecting", self.device)
                    with contextlib.suppress(Exception):
                        cap.release()
                    cap = None
                    self.stats.connected = False
                    self.stats.reconnects += 1
                else:
                    self._stop.wait(0.05)
                continue
            failures = 0
            # on the rate's grid (a faster camera gives the rate itself), and not a burst to
            # catch up after a stall: never due within half a period of this frame
            next_due = max(next_due + period, host_s + 0.5 * period)
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            dev_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0)
            t = self.clock.time(dev_ms / 1000.0 if dev_ms > 0 else None, host_s)
            self._seq += 1
            self._emit(
                FrameSample(
                    t=t,
                    image=img,
                    sequence=self._seq,
                    device_time_s=dev_ms / 1000.0 if dev_ms > 0 else None,
                )
            )
        if cap is not None:
            with contextlib.suppress(Exception):
                cap.release()
