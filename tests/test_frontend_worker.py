"""The front end in its own process gives the same tracks as on a thread (issue 15)."""

from __future__ import annotations

import numpy as np
import pytest

from mowerhw.config import FrontendConfig
from mowerhw.frontend import FrontEnd
from mowerhw.runtime.frontend_worker import FrontendWorker, FrontendWorkerDied
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
