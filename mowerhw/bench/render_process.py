"""The bench camera's renderer in a process of its own: rendering a 1540² frame is heavy
numpy work, and in the bench's process it would hold the GIL the mock sensors (VN-100, speed
sensor, mower controller) need to keep their rates — a loaded bench would then make the
*sensors* late and blame the daemon. A real camera costs the mower's computer nothing until
the frame arrives; this keeps the bench honest about that."""

from __future__ import annotations

import contextlib
import multiprocessing
import threading
from multiprocessing.connection import Connection
from typing import Any

import numpy as np


def _serve(scenario: str, seed: int, conn: Connection) -> None:
    import cv2

    from mowerhw.sim import make_world
    from mowerhw.sim.render import OmniRenderer

    cv2.setNumThreads(1)  # a camera's worth of work, not every core (OpenCV's pool spins)

    renderer = OmniRenderer(make_world(scenario, seed), seed)
    conn.send(("ready", tuple(renderer.table.shape)))
    while True:
        try:
            pose = conn.recv()
        except (EOFError, OSError):
            return
        if pose is None:
            return
        conn.send_bytes(np.ascontiguousarray(renderer.render(*pose)).tobytes())


class RenderProcess:
    """``render(x, y, heading)`` → the frame, from a child process (one frame at a time)."""

    def __init__(self, scenario: str, seed: int) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve, args=(scenario, seed, child), name="bench-render", daemon=True
        )
        self._proc.start()
        child.close()
        self._lock = threading.Lock()
        if not self._conn.poll(120.0):
            raise RuntimeError("the bench's renderer did not start within 120 s")
        _, shape = self._conn.recv()
        self.shape: tuple[int, int] = (int(shape[0]), int(shape[1]))

    def render(self, x: float, y: float, heading: float) -> Any:
        with self._lock:
            self._conn.send((x, y, heading))
            data = self._conn.recv_bytes()
        return np.frombuffer(data, dtype=np.uint8).reshape(self.shape)

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self._conn.send(None)
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.kill()
