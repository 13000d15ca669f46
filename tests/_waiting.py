"""Waiting on a condition with a deadline, so a test on a loaded machine is slow, never flaky."""

import time
from collections.abc import Callable


def wait_for(cond: Callable[[], bool], timeout: float = 2.0, poll_s: float = 0.005) -> bool:
    """True as soon as ``cond()`` holds; its last value once ``timeout`` seconds have passed."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(poll_s)
    return cond()
