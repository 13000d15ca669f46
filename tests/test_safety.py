"""Lift, tilt, rollover and collision: the supervisor's own checks (pure)."""

from __future__ import annotations

import math

from mowerhw.config import SafetyConfig
from mowerhw.estimation.safety import G, SafetyMonitor
from mowerhw.mow.containment import Reason


def _feed(m: SafetyMonitor, t0: float, t1: float, accel: tuple[float, float, float]) -> float:
    t = t0
    while t < t1 - 1e-9:
        m.imu(t, accel)
        t += 0.01
    return t


def _tilted(deg: float) -> tuple[float, float, float]:
    a = math.radians(deg)
    return (0.0, G * math.sin(a), G * math.cos(a))


def test_a_tilt_halts_after_its_debounce_and_clears_after_clear_s() -> None:
    m = SafetyMonitor(SafetyConfig())
    t = _feed(m, 0.0, 1.0, (0.0, 0.0, G))
    assert m.halt(t) is None
    t = _feed(m, t, t + 0.8, _tilted(45.0))
    assert m.halt(t) is None  # under the 1 s debounce (the filter takes ~0.3 s too)
    t = _feed(m, t, t + 0.8, _tilted(45.0))
    h = m.halt(t)
    assert h is not None and h[0] == Reason.TILTED and "tilted 45°" in h[1]
    t = _feed(m, t, t + 1.5, (0.0, 0.0, G))
    assert m.halt(t) is not None  # latched: not clear for 2 s yet
    t = _feed(m, t, t + 1.5, (0.0, 0.0, G))
    assert m.halt(t) is None


def test_a_rollover_halts_at_once_and_a_jolt_is_a_collision_not_a_rollover() -> None:
    m = SafetyMonitor(SafetyConfig())
    t = _feed(m, 0.0, 1.0, (0.0, 0.0, G))
    t = _feed(m, t, t + 0.06, (-3.0 * G, 0.0, G))  # 60 ms, 3 g: a bump
    h = m.halt(t)
    assert h is not None and h[0] == Reason.COLLISION and "jolt" in h[1]
    assert m.tilt.latched_at is None  # the slow gravity filter did not see a rollover
    m2 = SafetyMonitor(SafetyConfig())
    t = _feed(m2, 0.0, 1.0, (0.0, 0.0, G))
    t = _feed(m2, t, t + 0.6, _tilted(120.0))
    h = m2.halt(t)
    assert h is not None and h[0] == Reason.TILTED and "rolled over" in h[1]


def test_lift_from_the_accelerometer_and_the_switches() -> None:
    m = SafetyMonitor(SafetyConfig())
    t = _feed(m, 0.0, 0.5, (0.0, 0.0, G))
    t = _feed(m, t, t + 0.3, (0.0, 0.0, 1.5 * G))
    h = m.halt(t)
    assert h is not None and h[0] == Reason.LIFTED and "upwards" in h[1]
    s = SafetyMonitor(SafetyConfig())
    s.switches(0.0, lifted=False, bumped=False, stop=False)
    assert s.halt(0.0) is None
    s.switches(0.1, lifted=False, bumped=False, stop=True)
    assert s.halt(0.1) == (Reason.COLLISION, "the mower's stop button, 0.0 s ago")
    s.switches(0.2, lifted=True, bumped=False, stop=False)
    assert s.halt(0.2)[0] == Reason.LIFTED  # type: ignore[index]
    m.imu(t + 0.01, (math.nan, 0.0, G))  # a broken sample is ignored, never a crash
