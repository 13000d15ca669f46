"""The bench's camera: serves rendered frames on a Unix socket to :class:`StreamCamera`.

``render(t) -> uint8 image`` is called at ``fps`` (t: host monotonic capture time); each frame
goes to every connected client as one message of :mod:`drivers.camera.stream`'s format, after
the rendering time (the delivery latency a real camera has too). ``frozen`` (set from outside)
stops delivery, like a hung camera driver; clients stay connected.
"""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drivers.camera.stream import encode_frame


class MockCameraServer:
    def __init__(
        self, path: str | Path, render: Callable[[float], np.ndarray], fps: float = 4.0
    ) -> None:
        self.path = str(path)
        self.render = render
        self.fps = fps
        self.frozen = threading.Event()
        self.frames_sent = 0
        self.render_s: list[float] = []
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._server: socket.socket | None = None
        self._threads: list[threading.Thread] = []

    def start(self) -> MockCameraServer:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
        srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        srv.bind(self.path)
        srv.listen(4)
        srv.settimeout(0.1)
        self._server = srv
        for target, name in ((self._accept, "camera-accept"), (self._run, "camera-render")):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def set_nice(self, nice: int) -> None:
        """The render-and-send thread's niceness (Linux: per thread); OSError without the
        right."""
        for th in self._threads:
            if th.name == "camera-render" and th.native_id is not None:
                os.setpriority(os.PRIO_PROCESS, th.native_id, nice)

    def stop(self) -> None:
        self._stop.set()
        for th in self._threads:
            th.join(timeout=2.0)
        with self._lock:
            for c in self._clients:
                with contextlib.suppress(OSError):
                    c.close()
            self._clients.clear()
        if self._server is not None:
            self._server.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()  # type: ignore[union-attr]
            except TimeoutError:
                continue
            except OSError:
                return
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 8 << 20)
            with self._lock:
                self._clients.append(conn)

    def _run(self) -> None:
        period = 1.0 / self.fps
        nxt = time.monotonic()
        seq = 0
        while not self._stop.is_set():
            wait = nxt - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            t_cap = time.monotonic()
            nxt += period
            if nxt < t_cap:  # fell behind: a fresh grid, no burst
                nxt = t_cap + period
            if self.frozen.is_set():
                continue
            r0 = time.perf_counter()
            img = self.render(t_cap)
            self.render_s.append(time.perf_counter() - r0)
            seq += 1
            msg = encode_frame(seq, t_cap, img)
            with self._lock:
                for c in list(self._clients):
                    try:
                        c.sendall(msg)
                    except OSError:
                        self._clients.remove(c)
                        with contextlib.suppress(OSError):
                            c.close()
            self.frames_sent += 1
