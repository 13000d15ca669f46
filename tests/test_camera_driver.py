"""The camera interface: the V4L2 driver's reconnect logic (behind a capture that fails like a
real device does), the mock camera, and the hand-over to asyncio."""

import asyncio
import threading
import time

import numpy as np
import pytest
from _waiting import wait_for

from drivers.camera.base import asyncio_sink, synthetic_frame
from drivers.camera.mock import MockCamera
from drivers.camera.v4l2 import V4l2Camera


def collect(source, seconds: float) -> list:
    frames = []
    source.start(frames.append)
    time.sleep(seconds)
    source.stop()
    return frames


def test_mock_camera_rate_timestamps_and_sequence():
    frames = collect(MockCamera(fps=20.0, width=64, height=48), 0.55)
    assert 9 <= len(frames) <= 13
    assert all(f.shape == (48, 64) and f.image.dtype == np.uint8 for f in frames)
    assert [f.sequence for f in frames] == list(range(1, len(frames) + 1))
    dt = np.diff([f.t for f in frames])
    assert np.all(dt > 0) and np.median(dt) == pytest.approx(0.05, abs=0.01)


def test_mock_camera_freeze_delivers_nothing_then_resumes():
    cam = MockCamera(fps=20.0, width=32, height=32, freeze=[(0.2, 0.3)])
    frames = collect(cam, 0.8)
    rel = np.array([f.device_time_s for f in frames])
    assert not np.any((rel >= 0.2) & (rel < 0.5))
    assert np.any(rel < 0.2) and np.any(rel >= 0.5)
    assert np.max(np.diff([f.t for f in frames])) >= 0.3


def test_a_missing_device_is_retried_never_raised():
    cam = V4l2Camera("/dev/video-does-not-exist", width=64, height=48, fps=5)
    collect(cam, 0.5)
    assert cam.stats.frames == 0 and cam.stats.open_failures >= 2
    assert not cam.stats.connected and "video-does-not-exist" in cam.stats.last_error


class FlakyCapture:
    """Behaves like ``cv2.VideoCapture`` on a USB camera: delivers frames with a driver
    timestamp, then (when the device is unplugged) fails every read; a new one opens only while
    the device is present."""

    def __init__(self, device: "FakeDevice") -> None:
        self.device = device
        self.opened = device.present
        self.props: dict[int, float] = {}
        self.released = False

    def isOpened(self) -> bool:
        return self.opened

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        import cv2

        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.device.device_ms
        return self.props.get(prop, 0.0)

    def grab(self) -> bool:
        """The next frame, every 10 ms (a 100 fps camera), not decoded yet."""
        time.sleep(0.01)
        if not self.device.present or self.released:
            return False
        self.device.device_ms = 5000.0 + 1000.0 * (time.monotonic() - self.device.t0)
        self.device.grabbed += 1
        return True

    def retrieve(self):
        self.device.decoded += 1
        return True, np.full((48, 64, 3), 128, np.uint8)

    def read(self):
        return self.retrieve() if self.grab() else (False, None)

    def release(self) -> None:
        self.released = True


class FakeDevice:
    def __init__(self) -> None:
        self.present = True
        self.t0 = time.monotonic()
        self.device_ms = 0.0
        self.opens = 0
        self.grabbed = 0
        self.decoded = 0

    def open(self, path: str) -> FlakyCapture:
        self.opens += 1
        return FlakyCapture(self)


def test_v4l2_driver_reconnects_when_the_device_returns():
    import cv2

    dev = FakeDevice()
    cam = V4l2Camera("/dev/video0", width=64, height=48, fps=30, capture_factory=dev.open)
    frames = []
    cam.start(frames.append)
    try:
        assert wait_for(lambda: len(frames) > 5 and cam.stats.connected)
        n_before = len(frames)
        dev.present = False  # unplugged
        assert wait_for(lambda: cam.stats.reconnects >= 1 and not cam.stats.connected)
        assert wait_for(lambda: cam.stats.open_failures >= 1)
        n_gone = len(frames)
        dev.present = True  # plugged back in
        assert wait_for(lambda: len(frames) > n_gone + 5 and cam.stats.connected, timeout=5.0)
    finally:
        cam.stop()
    assert dev.opens >= 3
    # configured as asked, grey out, driver time mapped onto the host clock
    cap = FlakyCapture(dev)
    cam2 = V4l2Camera("x", width=64, height=48, fps=30, pixel_format="YUYV")
    cam2._factory = lambda _: cap
    cam2._open()
    assert cap.props[cv2.CAP_PROP_FRAME_WIDTH] == 64 and cap.props[cv2.CAP_PROP_FPS] == 30
    assert cap.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter_fourcc(*"YUYV")
    assert all(f.image.ndim == 2 for f in frames)
    assert all(f.device_time_s is not None for f in frames)
    host = np.array([f.t for f in frames[:n_before]])
    assert np.all(np.diff(host) > 0)
    assert abs(host[-1] - time.monotonic()) < 5.0  # host clock, not the device's 5000 s


def test_asyncio_sink_hands_frames_over_and_drops_the_oldest():
    async def main() -> list[int]:
        loop = asyncio.get_running_loop()
        q: asyncio.Queue = asyncio.Queue(maxsize=2)
        sink = asyncio_sink(loop, q)
        t = threading.Thread(target=lambda: [sink(i) for i in range(5)])
        t.start()
        t.join()
        await asyncio.sleep(0.05)
        return [q.get_nowait() for _ in range(q.qsize())]

    assert asyncio.run(main()) == [3, 4]


def test_test_pattern_moves():
    a, b = synthetic_frame(0.0, 64, 48), synthetic_frame(0.2, 64, 48)
    assert a.shape == (48, 64) and not np.array_equal(a, b)


def test_v4l2_driver_decodes_no_more_frames_than_its_rate():
    """A camera that delivers faster than ``camera.fps`` (a USB camera with no mode at the
    rate asked for; here 100 fps for 10 asked): the extra frames are grabbed and dropped
    undecoded, so the front end sees about the rate configured, not the camera's."""
    dev = FakeDevice()
    cam = V4l2Camera("/dev/video0", width=64, height=48, fps=10, capture_factory=dev.open)
    frames = []
    cam.start(frames.append)
    try:
        assert wait_for(lambda: dev.grabbed >= 60)
    finally:
        cam.stop()
    seconds = frames[-1].t - frames[0].t
    rate = (len(frames) - 1) / seconds
    assert 8.0 <= rate <= 12.0, (rate, len(frames), dev.grabbed)  # 10 fps
    assert dev.decoded == len(frames) and cam.stats.skipped >= 0.7 * dev.grabbed
    # a camera at the rate asked for keeps (nearly) every frame, its jitter notwithstanding
    dev = FakeDevice()
    cam = V4l2Camera("/dev/video0", width=64, height=48, fps=100, capture_factory=dev.open)
    cam.start(lambda f: None)
    try:
        assert wait_for(lambda: dev.grabbed >= 60)
    finally:
        cam.stop()
    assert cam.stats.skipped <= 0.1 * dev.grabbed, (cam.stats.skipped, dev.grabbed)


class AliveWatch:
    """What a consumer reading ``camera.alive_at`` every 2 ms sees: each new value."""

    def __init__(self, cam) -> None:
        self.seen: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(cam,), daemon=True)
        self._thread.start()

    def _run(self, cam) -> None:
        while not self._stop.is_set():
            t = cam.alive_at
            if t is not None and (not self.seen or t != self.seen[-1]):
                self.seen.append(t)
            time.sleep(0.002)

    def stop(self) -> list[float]:
        self._stop.set()
        self._thread.join()
        return self.seen


def test_v4l2_driver_asks_the_device_rate_and_says_the_camera_lives_between_frames():
    """``camera.device_fps`` above ``camera.fps``: the camera is asked for its own rate, the
    front end gets ``fps``, and every frame dropped between says the camera is alive (its
    ``alive_at``, read by the runtime at each decision: liveness judged at the camera's rate,
    not the front end's)."""
    import cv2

    dev = FakeDevice()
    cam = V4l2Camera(
        "/dev/video0", width=64, height=48, fps=10, device_fps=100, capture_factory=dev.open
    )
    frames = []
    assert cam.alive_at is None
    cam.start(lambda f: frames.append(time.monotonic()))
    watch = AliveWatch(cam)
    try:
        assert wait_for(lambda: dev.grabbed >= 60)
    finally:
        cam.stop()
        alive = watch.stop()
    assert cam.stats.skipped >= 0.7 * dev.grabbed
    assert 0.5 * cam.stats.skipped <= len(alive) <= cam.stats.skipped
    assert cam.stats.skipped + len(frames) >= dev.grabbed - 2  # every grabbed frame, one way
    rate = (len(frames) - 1) / (frames[-1] - frames[0])
    assert 8.0 <= rate <= 12.0, rate  # the front end's 10 a second
    # the longest the runtime goes without hearing of the camera: its own period, not fps's
    heard = np.sort(np.concatenate([alive, frames]))
    assert np.max(np.diff(heard)) < 0.05, np.max(np.diff(heard))
    cap = FlakyCapture(dev)
    cam2 = V4l2Camera("x", 64, 48, fps=4, device_fps=30, capture_factory=lambda _: cap)
    cam2._open()
    assert cap.props[cv2.CAP_PROP_FPS] == 30


def test_a_camera_slower_than_asked_is_named_with_the_limit_it_needs(caplog):
    """A camera that has no mode at ``camera.device_fps`` runs slower: the staleness limit
    was judged at the rate asked for, so the log says what the camera runs at and what the
    limit must span."""
    import cv2

    class SlowCapture(FlakyCapture):
        def get(self, prop: int) -> float:
            return 15.0 if prop == cv2.CAP_PROP_FPS else super().get(prop)

    dev = FakeDevice()
    cam = V4l2Camera("x", 64, 48, fps=4, device_fps=30, capture_factory=lambda _: SlowCapture(dev))
    with caplog.at_level("WARNING", logger="drivers.camera.v4l2"):
        cam._open()
    assert "x runs at 15 fps, not the 30 asked for" in caplog.text
    assert "two of its periods (0.133 s)" in caplog.text


def test_the_stream_camera_delivers_at_its_rate_and_says_the_camera_lives_between():
    """The bench's camera over a real Unix socket: a server at 20 frames a second, the
    camera configured for 5: about 5 a second reach the front end, in order and with their
    capture times, and the 15 between are its ``alive_at`` (read from the socket, not handed
    on)."""
    import tempfile

    from drivers.camera.mock_server import MockCameraServer
    from drivers.camera.stream import StreamCamera

    with tempfile.TemporaryDirectory() as tmp:
        server = MockCameraServer(
            f"{tmp}/cam.sock", lambda t: synthetic_frame(t, 64, 48), fps=20.0
        ).start()
        cam = StreamCamera(f"{tmp}/cam.sock", fps=5.0)
        frames = []
        cam.start(frames.append)
        watch = AliveWatch(cam)
        try:
            assert wait_for(lambda: len(frames) >= 6, timeout=10.0)
        finally:
            cam.stop()
            server.stop()
            alive = watch.stop()
    rate = (len(frames) - 1) / (frames[-1].t - frames[0].t)
    assert 4.0 <= rate <= 6.0, rate
    assert [f.sequence for f in frames] == sorted({f.sequence for f in frames})
    assert all(f.image.shape == (48, 64) for f in frames)
    assert len(alive) <= cam.stats.skipped
    assert len(alive) >= 2 * (len(frames) - 1), (len(alive), len(frames))
    # the same camera without a rate hands on every frame
    with tempfile.TemporaryDirectory() as tmp:
        server = MockCameraServer(
            f"{tmp}/cam.sock", lambda t: synthetic_frame(t, 64, 48), fps=20.0
        ).start()
        cam = StreamCamera(f"{tmp}/cam.sock")
        every: list = []
        cam.start(every.append)
        try:
            assert wait_for(lambda: len(every) >= 10, timeout=10.0)
        finally:
            cam.stop()
            server.stop()
    assert cam.stats.skipped == 0
    assert np.median(np.diff([f.t for f in every])) == pytest.approx(0.05, abs=0.015)


def test_the_bench_camera_renders_at_the_priority_it_is_given():
    """Under ``--load`` the bench gives its camera the mock sensors' priority (they stand for
    hardware): the render-and-send thread takes the niceness (a positive one here: no
    privilege needed)."""
    import os
    import tempfile

    from drivers.camera.mock_server import MockCameraServer

    with tempfile.TemporaryDirectory() as tmp:
        server = MockCameraServer(f"{tmp}/cam.sock", lambda t: synthetic_frame(t, 8, 8), 20.0)
        server.start()
        try:
            server.set_nice(7)
            (render,) = [th for th in server._threads if th.name == "camera-render"]
            assert os.getpriority(os.PRIO_PROCESS, render.native_id) == 7
        finally:
            server.stop()


def test_the_mock_camera_renders_only_the_frames_it_delivers():
    """The in-process mock at ``device_fps`` 20 with ``fps`` 5: 5 a second rendered and
    delivered, the others only its ``alive_at``."""
    rendered: list[float] = []

    def render(t: float) -> np.ndarray:
        rendered.append(t)
        return synthetic_frame(t, 32, 32)

    cam = MockCamera(render, fps=5.0, device_fps=20.0, width=32, height=32)
    frames = []
    cam.start(frames.append)
    watch = AliveWatch(cam)
    time.sleep(1.05)
    cam.stop()
    alive = watch.stop()
    assert len(rendered) == len(frames) and 4 <= len(frames) <= 7, len(frames)
    assert 13 <= cam.stats.skipped <= 17, cam.stats.skipped
    assert 13 <= len(alive) <= cam.stats.skipped, len(alive)


class StampedCapture:
    """``cv2.VideoCapture`` on a camera whose driver stamps each buffer (``CAP_PROP_POS_MSEC``)
    ``latency_s`` before ``grab`` returns it — a UVC camera stamps the start of the exposure,
    and the frame arrives after its exposure and its transfer — on the host's monotonic clock,
    or (``epoch``) on the wall clock as old drivers did."""

    def __init__(self, latency_s: float, epoch: bool = False, every_s: float = 0.02) -> None:
        self.latency_s, self.epoch, self.every_s = latency_s, epoch, every_s
        self.stamps: list[float] = []  # the buffer times, s on the host's monotonic clock
        self._stamp_ms = 0.0

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        return True

    def get(self, prop: int) -> float:
        import cv2

        sizes = {cv2.CAP_PROP_FRAME_WIDTH: 64.0, cv2.CAP_PROP_FRAME_HEIGHT: 48.0}
        return self._stamp_ms if prop == cv2.CAP_PROP_POS_MSEC else sizes.get(prop, 0.0)

    def grab(self) -> bool:
        time.sleep(self.every_s)
        stamp = time.monotonic() - self.latency_s
        self.stamps.append(stamp)
        shift = time.time() - time.monotonic() if self.epoch else 0.0
        self._stamp_ms = 1000.0 * (stamp + shift)
        return True

    def retrieve(self):
        return True, np.zeros((48, 64), np.uint8)

    def release(self) -> None:
        pass


@pytest.mark.parametrize("mode", ["auto", "monotonic"])
def test_v4l2_buffer_times_on_the_host_clock_are_the_frame_times(mode):
    """V4L2 stamps buffers on the host's monotonic clock: a frame's time is its buffer time
    as it is, not moved late by the 70 ms the frame took to arrive (mapped like a device's
    clock, every frame would be: the smallest delivery latency cannot be seen from arrivals)."""
    from mowerhw.common.clocksync import FrameClock

    cap = StampedCapture(latency_s=0.07)
    cam = V4l2Camera("x", width=64, height=48, fps=50, capture_factory=lambda _: cap)
    cam.clock = FrameClock(mode)
    frames = collect(cam, 0.5)
    assert len(frames) >= 5
    stamps = {round(s, 6) for s in cap.stamps}
    assert all(round(f.t, 6) in stamps for f in frames)  # the buffer times themselves
    status = cam.status()["clock"]
    assert status["source"] == "monotonic" and status["future_stamps"] == 0
    assert 0.07 <= status["min_latency_s"] < 0.5  # what the transfer took, seen


def test_v4l2_buffer_times_on_another_clock_are_mapped_and_the_default_says_which():
    """A driver that stamps on the wall clock (or a camera's own clock): mapped onto the host
    clock (the smallest latency then cannot be seen: the mapped times are the arrivals')."""
    cap = StampedCapture(latency_s=0.07, epoch=True)
    cam = V4l2Camera("x", width=64, height=48, fps=50, capture_factory=lambda _: cap)
    frames = collect(cam, 0.5)
    assert len(frames) >= 5 and cam.status()["clock"]["source"] == "device"
    arrivals = np.array(cap.stamps[: len(frames)]) + 0.07
    t = np.array([f.t for f in frames])
    assert np.all(np.abs(t - arrivals) < 0.05)  # host clock, mapped: not the wall clock


def test_frame_clock_modes_and_a_stamp_after_its_arrival():
    from mowerhw.common.clocksync import FrameClock

    # auto: host-clock stamps, then one after its own arrival (impossible on that clock):
    # buffer times are mapped from then on, and it says so
    clock = FrameClock()
    assert clock.time(99.93, 100.0) == 99.93 and clock.stats.source == "monotonic"
    assert clock.time(None, 100.5) == 100.5 and clock.stats.unstamped == 1
    later = clock.time(101.1, 101.0)
    assert clock.stats.source == "device" and clock.stats.future_stamps == 1
    assert later <= 101.0  # never after the frame arrived
    # monotonic given by the user: such a stamp is not believed, the arrival is used
    clock = FrameClock("monotonic")
    assert clock.time(50.0, 49.9) == 49.9 and clock.stats.source == "monotonic"
    assert clock.time(49.95, 50.0) == 49.95
    # arrival: the stamps are not used
    clock = FrameClock("arrival")
    assert clock.time(10.0, 12.0) == 12.0 and clock.stats.unstamped == 0
    # device: mapped even when it looks like the host's clock
    clock = FrameClock("device")
    assert clock.time(99.93, 100.0) == 100.0 and clock.stats.min_latency_s == 0.0
    with pytest.raises(ValueError, match="frame clock 'gps' is not one of auto, monotonic"):
        FrameClock("gps")


def _grey_pattern(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return ((x * 7 + y * 13) % 256).astype(np.uint8)


def test_grey_from_the_buffers_opencv_hands_over_undecoded():
    """With ``CAP_PROP_CONVERT_RGB`` off OpenCV hands over the V4L2 buffer's bytes as one row
    (rows padded to a stride on some drivers): GREY is the image, YUYV's luma is, MJPG is
    decoded to grey only, BGR3 converted; a buffer of another mode is no frame (None)."""
    import cv2

    from drivers.camera.v4l2 import grey_from_buffer

    h, w = 48, 64
    grey = _grey_pattern(h, w)
    row = grey.reshape(1, -1)
    assert np.array_equal(grey_from_buffer(row, "GREY", w, h), grey)
    padded = np.zeros((h, w + 16), np.uint8)  # a stride of 80 bytes
    padded[:, :w] = grey
    assert np.array_equal(grey_from_buffer(padded.reshape(1, -1), "GREY", w, h), grey)
    wide = np.zeros((h, w + 300), np.uint8)  # rows of another, wider mode: no padding
    assert grey_from_buffer(wide.reshape(1, -1), "GREY", w, h) is None
    yuyv = np.empty((h, w, 2), np.uint8)
    yuyv[..., 0], yuyv[..., 1] = grey, 77  # Y, then U/V alternating
    assert np.array_equal(grey_from_buffer(yuyv.reshape(1, -1), "YUYV", w, h), grey)
    bgr = np.dstack([grey, grey, grey])
    assert np.array_equal(grey_from_buffer(bgr.reshape(1, -1), "BGR3", w, h), grey)
    ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    decoded = grey_from_buffer(jpg.reshape(1, -1), "MJPG", w, h)
    assert decoded is not None and decoded.shape == (h, w)
    assert np.array_equal(decoded, cv2.imdecode(jpg, cv2.IMREAD_GRAYSCALE))
    assert np.abs(decoded.astype(int) - grey).mean() < 3.0
    # an image OpenCV decoded after all (it kept CONVERT_RGB on): BGR, or grey as it is
    assert np.array_equal(grey_from_buffer(bgr, "GREY", w, h), grey)
    assert grey_from_buffer(grey, "YUYV", w, h) is grey
    # another mode's buffer, a JPEG that is none
    assert grey_from_buffer(_grey_pattern(30, 40).reshape(1, -1), "GREY", w, h) is None
    assert grey_from_buffer(row, "YUYV", w, h) is None  # half the bytes YUYV needs
    assert grey_from_buffer(jpg[:200].reshape(1, -1) * 0, "MJPG", w, h) is None


class RawCapture:
    """``cv2.VideoCapture`` on a GREY camera as OpenCV's V4L2 backend behaves: with
    ``CAP_PROP_CONVERT_RGB`` on it expands each frame to BGR, off it hands over the buffer's
    bytes as one row. ``mode``: the size the camera really delivers."""

    def __init__(self, mode: tuple[int, int]) -> None:
        self.mode = mode
        self.convert = True
        self.frames = 0

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        import cv2

        if prop == cv2.CAP_PROP_CONVERT_RGB:
            self.convert = bool(value)
        return True

    def get(self, prop: int) -> float:
        import cv2

        h, w = self.mode
        return {cv2.CAP_PROP_FRAME_WIDTH: w, cv2.CAP_PROP_FRAME_HEIGHT: h}.get(prop, 0.0)

    def grab(self) -> bool:
        time.sleep(0.02)
        return True

    def retrieve(self):
        import cv2

        self.frames += 1
        grey = _grey_pattern(*self.mode)
        return True, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR) if self.convert else grey.reshape(1, -1)

    def release(self) -> None:
        pass


def test_v4l2_driver_reads_grey_frames_undecoded_and_falls_back_for_another_mode(caplog):
    cap = RawCapture((48, 64))
    cam = V4l2Camera("x", width=64, height=48, fps=50, capture_factory=lambda _: cap)
    frames = collect(cam, 0.3)
    assert len(frames) >= 3 and not cap.convert and cam.status()["raw_buffers"]
    assert all(np.array_equal(f.image, _grey_pattern(48, 64)) for f in frames)
    # a camera that runs another mode than the one asked for, and says so: OpenCV decodes
    # its frames, which come at their own size (the runtime refuses them, saying so)
    cap = RawCapture((30, 40))
    cam = V4l2Camera("x", width=64, height=48, fps=50, capture_factory=lambda _: cap)
    frames = collect(cam, 0.3)
    assert cap.convert and not cam.status()["raw_buffers"]
    assert frames and all(f.image.shape == (30, 40) for f in frames)
    assert "camera: x runs at 40x30, not the 64x48 asked for" in caplog.text
    # … and one that says the mode asked for and delivers another: found by the bytes
    cap = RawCapture((30, 40))
    cap.get = lambda prop: {3: 64.0, 4: 48.0}.get(prop, 0.0)  # type: ignore[method-assign]
    cam = V4l2Camera("x", width=64, height=48, fps=50, capture_factory=lambda _: cap)
    frames = collect(cam, 0.3)
    assert cap.convert and not cam.status()["raw_buffers"]
    assert frames and all(f.image.shape == (30, 40) for f in frames)
    assert "a GREY buffer of 1200 bytes is no 64x48 frame; OpenCV decodes" in caplog.text
