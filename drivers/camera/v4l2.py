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

import numpy as np

from drivers.camera.base import CameraSource, FrameRate
from mowerhw.common.clocksync import FrameClock
from mowerhw.common.samples import FrameSample

log = logging.getLogger(__name__)


_FOURCC = {"GREY": "GREY", "YUYV": "YUYV", "MJPG": "MJPG", "BGR3": "BGR3"}
#: bytes per pixel of the uncompressed formats' buffers
_BYTES_PER_PIXEL = {"GREY": 1, "YUYV": 2, "BGR3": 3}
#: a driver may pad each row of a buffer to an alignment (bytes): more is another mode
_MAX_ROW_PADDING = 255


def grey_from_buffer(buf: Any, pixel_format: str, width: int, height: int) -> np.ndarray | None:
    """The grey image in a V4L2 buffer as OpenCV hands it over with ``CAP_PROP_CONVERT_RGB``
    off (one row of the buffer's bytes; rows may be padded to a stride), or an image OpenCV
    decoded after all (BGR, or grey): GREY as it is, YUYV's luma, MJPG decoded to grey only,
    BGR3 converted. None when the buffer is no ``width``×``height`` frame of that format (the
    camera runs another mode)."""
    import cv2

    a = np.asarray(buf)
    if a.ndim == 3 and a.shape[2] == 3:
        out: np.ndarray = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
        return out
    if a.shape == (height, width):
        return a
    data = a.reshape(-1)
    if pixel_format == "MJPG":
        return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)  # None if it is no JPEG
    bpp = _BYTES_PER_PIXEL[pixel_format]
    stride, rest = divmod(data.size, height)
    if rest or not 0 <= stride - width * bpp <= _MAX_ROW_PADDING:
        return None
    rows = data.reshape(height, stride)[:, : width * bpp]
    if pixel_format == "GREY":
        return np.ascontiguousarray(rows)
    code = cv2.COLOR_YUV2GRAY_YUYV if pixel_format == "YUYV" else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(np.ascontiguousarray(rows).reshape(height, width, bpp), code)


class V4l2Camera(CameraSource):
    """A V4L2 camera through OpenCV (see the module doc): asked for ``device_fps`` (default
    ``fps``), it delivers frames at ``fps`` (:class:`~drivers.camera.base.FrameRate`)."""

    def __init__(
        self,
        device: str,
        width: int = 1540,
        height: int = 1540,
        fps: float = 4.0,
        device_fps: float | None = None,
        pixel_format: str = "GREY",
        reconnect_max_backoff_s: float = 5.0,
        failures_before_reconnect: int = 5,
        clock: FrameClock | None = None,
        capture_factory: Callable[[str], Any] | None = None,
    ) -> None:
        super().__init__()
        self.device = device
        self.width, self.height, self.fps = width, height, fps
        self.device_fps = fps if device_fps is None else device_fps
        self.pixel_format = pixel_format
        self.reconnect_max_backoff_s = reconnect_max_backoff_s
        self.failures_before_reconnect = failures_before_reconnect
        self.clock = clock or FrameClock()
        self._factory = capture_factory
        self._seq = 0
        #: frames come as the buffer's bytes (``CAP_PROP_CONVERT_RGB`` off), not decoded
        self.raw_buffers = False

    def status(self) -> dict[str, Any]:
        """The counters, and where the frame times come from (:class:`FrameClock`)."""
        return {
            **super().status(),
            "raw_buffers": self.raw_buffers,
            "clock": dict(vars(self.clock.stats)),
        }

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
        cap.set(cv2.CAP_PROP_FPS, self.device_fps)
        runs_at = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if 0.0 < runs_at < 0.95 * self.device_fps:
            log.warning(
                "camera: %s runs at %g fps, not the %g asked for: camera.stale_after_s must "
                "span two of its periods (%.3g s), or every late frame halts",
                self.device,
                runs_at,
                self.device_fps,
                2.0 / runs_at,
            )
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a backlog
        # the buffer's bytes, not a BGR image: OpenCV would expand a GREY frame to three
        # channels (and decode an MJPG one in colour) for the grey to be taken back out.
        # Only in the mode asked for: another one's bytes could be read as a frame of this
        # size, where OpenCV, decoding, knows the mode (and the runtime refuses its size)
        mode = (cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        asked = mode == (self.width, self.height)
        self.raw_buffers = asked and bool(cap.set(cv2.CAP_PROP_CONVERT_RGB, 0))
        if not asked:
            log.warning(
                "camera: %s runs at %gx%g, not the %dx%d asked for",
                self.device,
                *mode,
                self.width,
                self.height,
            )
        return cap

    def _run(self) -> None:
        import cv2

        cap = None
        backoff = 0.1
        failures = 0
        rate = FrameRate(self.fps)
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
            if ok and rate.skip(host_s):
                # faster than camera.fps (camera.device_fps, or a USB camera with no mode at
                # the rate asked for): the frame is dropped before it is decoded, or the
                # front end would track every one of them on a computer sized for the rate
                # configured; it still says the camera is alive
                self._skipped()
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
            rate.taken(host_s)
            grey = grey_from_buffer(img, self.pixel_format, self.width, self.height)
            if grey is None and self.raw_buffers and self.pixel_format != "MJPG":
                # not the mode asked for: OpenCV decodes it from now on (the runtime then
                # refuses a frame of another size, saying which)
                log.warning(
                    "camera: a %s buffer of %d bytes is no %dx%d frame; OpenCV decodes "
                    "the frames from now on",
                    self.pixel_format,
                    np.asarray(img).size,
                    self.width,
                    self.height,
                )
                cap.set(cv2.CAP_PROP_CONVERT_RGB, 1)
                self.raw_buffers = False
                continue
            if grey is None:  # a JPEG that does not decode (a USB glitch)
                self.stats.read_failures += 1
                self.stats.last_error = f"{self.device}: a {self.pixel_format} frame, no image"
                continue
            img = grey
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
