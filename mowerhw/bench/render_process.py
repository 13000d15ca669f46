"""The bench camera's renderer in a process of its own.

Rendering a 1540² omni frame is ~100 ms of numpy and OpenCV; in the bench's own process it
holds the GIL the mock sensors' threads need, so the mock VN-100 was itself late now and then
(up to ~200 ms under ``--load``) — a halt it caused looked like the daemon's. Here the
renderer lives in a child process (built there from the scenario and seed, so nothing large
crosses the pipe but the frames), and the bench's camera thread only sends the pose and
waits for the pixels.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from multiprocessing.connection import Connection
from typing import Any

import numpy as np


def _serve(conn: Connection, scenario: Any, seed: int) -> None:
    import cv2

    from mowerhw.sim import make_world
    from mowerhw.sim.render import OmniRenderer

    cv2.setNumThreads(1)  # one core's worth, like the thread it replaces
    renderer = OmniRenderer(make_world(scenario, seed), seed)
    conn.send(("ready", None))
    while True:
        try:
            pose = conn.recv()
        except EOFError:
            return
        if pose is None:
            return
        img = renderer.render(*pose)
        conn.send_bytes(np.ascontiguousarray(img).tobytes())
        conn.send((img.shape, str(img.dtype)))


class RenderProcess:
    """``render(x, y, yaw)`` → the frame, rendered in a child process."""

    def __init__(self, scenario: Any, seed: int, start_timeout_s: float = 120.0) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve, args=(child, scenario, seed), name="bench-renderer", daemon=True
        )
        self._proc.start()
        child.close()
        if not self._conn.poll(start_timeout_s):
            self.close()
            raise TimeoutError("the bench's renderer process did not start")
        self._conn.recv()

    def render(self, x: float, y: float, yaw: float) -> np.ndarray:
        self._conn.send((x, y, yaw))
        data = self._conn.recv_bytes()
        shape, dtype = self._conn.recv()
        return np.frombuffer(data, dtype=dtype).reshape(shape)

    def set_nice(self, nice: int) -> None:
        """The renderer process's niceness; OSError without the right."""
        if self._proc.pid is not None:
            os.setpriority(os.PRIO_PROCESS, self._proc.pid, nice)

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self._conn.send(None)
        self._proc.join(timeout=2.0)
        if self._proc.is_alive():
            self._proc.kill()
        self._conn.close()
