"""The front end in its own process gives the same tracks as on a thread (issue 15)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from mowerhw.config import FrontendConfig
from mowerhw.frontend import FrontEnd
from mowerhw.runtime.frontend_worker import FrontendWorker, FrontendWorkerDied, HangWatch
from mowerhw.sim import make_world
from mowerhw.sim.render import OmniRenderer


def test_the_worker_process_tracks_as_the_thread_does():
    world = make_world("paper", 3)
    renderer = OmniRenderer(world, 3)
    args = (world.camera, tuple(float(v) for v in world.q_bc), FrontendConfig(), 0)
    here = FrontEnd(*args)
    worker = FrontendWorker()
    try:
        for k in range(4):
            image = renderer.render(0.1 * k, 0.05 * k, 0.02 * k)
            mine = here.process(0.25 * k, image, None)
            theirs = worker.track("chain-1", (args, None), 0.25 * k, image, None)
            assert np.array_equal(mine.ids, theirs.ids) and mine.ids.size > 20
            assert np.allclose(mine.pixels, theirs.pixels, atol=1e-9)
        # a new chain starts a new front end: ids from scratch, as a new FrontEnd would
        fresh = FrontEnd(*args).process(1.0, image, None)
        again = worker.track("chain-2", (args, None), 1.0, image, None)
        assert np.array_equal(fresh.ids, again.ids)
        worker._proc.kill()  # type: ignore[union-attr]  # the worker dies: crash-only
        worker._proc.wait()  # type: ignore[union-attr]
        with pytest.raises(FrontendWorkerDied, match=r"ended \(exit status -9\)"):
            worker.track("chain-2", (args, None), 1.5, image, None)
    finally:
        worker.close()


@pytest.mark.parametrize(
    ("hang_s", "idle_s", "said", "within_s"),
    [
        # the long limit: a worker that answers no frame within runtime.frontend_hang_s
        (1.0, 10.0, r"answered no frame for 1 s .*hung, killed", (1.0, 5.0)),
        # long before it: a worker whose CPU time does not grow with a frame in hand is not
        # searching (a search for the pose may take tens of seconds) but stuck
        (300.0, 1.5, r"computed nothing for 1.5 s .*hung, killed", (1.5, 6.0)),
    ],
)
def test_a_hung_worker_is_killed(
    hang_s: float, idle_s: float, said: str, within_s: tuple[float, float]
) -> None:
    """A worker stopped with SIGSTOP is taken for hung: killed, and FrontendWorkerDied ends
    the daemon (crash-only), where before stop 48 the frame task waited for it forever and
    the deck stayed halted; since stop 49, after ``idle_s`` rather than ``hang_s``."""
    import signal
    import time

    world = make_world("paper", 3)
    image = OmniRenderer(world, 3).render(0.0, 0.0, 0.0)
    args = (world.camera, tuple(float(v) for v in world.q_bc), FrontendConfig(), 0)
    worker = FrontendWorker(hang_s=60.0)  # the first frame includes the worker's start
    try:
        assert worker.track("chain-1", (args, None), 0.0, image, None).ids.size > 20
        worker.hang_s, worker.idle_hang_s = hang_s, idle_s
        proc = worker._proc
        assert proc is not None
        os.kill(proc.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(FrontendWorkerDied, match=said):
            worker.track("chain-1", (args, None), 0.25, image, None)
        assert within_s[0] <= time.monotonic() - t0 < within_s[1]
        assert proc.poll() == -signal.SIGKILL
    finally:
        worker.close()


def test_the_hang_watch_tells_a_slow_worker_from_a_stuck_one() -> None:
    """Computing (CPU time growing) it may take up to the long limit; idle, the short one."""
    busy = HangWatch(0.0, 1.0, hang_s=300.0, idle_s=10.0)
    for k in range(1, 600):  # a search that computes for 299.5 s
        assert busy.hung(0.5 * k, 1.0 + 0.4 * k) == ""
    assert "answered no frame for 300 s" in busy.hung(300.5, 300.0)
    stuck = HangWatch(0.0, 1.0, hang_s=300.0, idle_s=10.0)
    assert stuck.hung(5.0, 3.0) == ""  # computed until 5 s
    assert stuck.hung(15.0, 3.0) == ""  # idle for 10 s: not yet over
    assert "computed nothing for 10 s" in stuck.hung(15.5, 3.0)
    blind = HangWatch(0.0, None, hang_s=300.0, idle_s=10.0)  # no /proc: only the long limit
    assert blind.hung(200.0, None) == "" and blind.hung(301.0, None)


def test_the_worker_relocalizes_a_frame_when_asked() -> None:
    """A mow chain's search runs where the tracking runs: the worker builds the relocalizer
    from the map it is given and answers for the frames that ask (issue 18)."""
    from mowerhw.common.relocalization import SearchRequest
    from mowerhw.map import Landmark, LawnMap

    world = make_world("paper", 3)
    renderer = OmniRenderer(world, 3)
    args = (world.camera, tuple(float(v) for v in world.q_bc), FrontendConfig(), 0)
    pts = world.landmarks_map - world.landmarks_map.mean(axis=0) * [1, 1, 0]
    lms = [Landmark(i, pts[i], np.eye(3) * 1e-6) for i in range(len(pts))]
    ring = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    boundary = np.c_[3 * np.cos(ring), 3 * np.sin(ring)]
    lawn_map = LawnMap(boundary=boundary, landmarks=lms, camera=None, teach={})
    worker = FrontendWorker()
    try:
        image = renderer.render(0.0, 0.0, 0.0)
        plain = worker.track("chain-1", (args, (lawn_map,)), 0.0, image, None)
        asked = worker.track("chain-1", (args, (lawn_map,)), 0.25, image, None, SearchRequest())
        assert plain.relocalization is None
        assert asked.relocalization is not None and asked.relocalization.ms > 0
        carried = worker.track(
            "chain-1", (args, (lawn_map,)), 0.5, image, None, SearchRequest(carried=True)
        )
        assert carried.ids.size and not np.isin(carried.ids, asked.ids).any()  # all new
    finally:
        worker.close()


def test_a_frame_slot_hands_pixels_over_through_shared_memory() -> None:
    """The frame's pixels go through a memory file, not the pipe: what the worker's side
    reads is the sender's frame, a copy (the next frame may overwrite the slot), for any
    size or type the camera gives (a larger frame grows the file)."""
    from mowerhw.runtime.frontend_worker import FrameSlot

    rng = np.random.default_rng(4)
    sender = FrameSlot()
    reader = FrameSlot(os.dup(sender.fd))  # as the worker holds it: another descriptor
    try:
        for shape, dtype in (((48, 64), np.uint8), ((120, 90, 3), np.uint8), ((30, 40), ">u2")):
            image = rng.integers(0, 200, size=shape).astype(dtype)
            got = reader.take(*sender.put(image))
            assert got.shape == image.shape and got.dtype == image.dtype
            assert np.array_equal(got, image)
            sender.put(np.zeros_like(image))  # the next frame: the copy taken stays as it was
            assert np.array_equal(got, image)
        view = rng.integers(0, 255, size=(64, 64), dtype=np.uint8)[::2, ::2]  # not contiguous
        assert np.array_equal(reader.take(*sender.put(view)), view)
    finally:
        sender.close()
        reader.close()
