"""Device clock → host clock on synthetic jittered, drifting, stalling timestamps."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mowerhw.common.clocksync import ClockSync, _lower_hull

MIN_LATENCY = 0.0008


def stream(
    n=6000, rate_hz=100.0, drift_ppm=60.0, jitter_ms=1.5, stall_prob=0.01, seed=0, dev_start_ns=5e9
):
    """True event times, device ns stamps, and host arrival times with one-sided delays."""
    rng = np.random.default_rng(seed)
    true = 1000.0 + np.arange(n) / rate_hz
    device_ns = np.round((true - 1000.0) * (1 + drift_ppm * 1e-6) * 1e9 + dev_start_ns)
    delay = MIN_LATENCY + rng.exponential(jitter_ms * 1e-3, n)
    stalls = rng.random(n) < stall_prob
    delay[stalls] += rng.uniform(0.02, 0.2, int(stalls.sum()))
    return true, device_ns, true + delay


def run(sync, device_ns, arrival):
    return np.array([sync.update(d, a) for d, a in zip(device_ns, arrival, strict=True)])


def test_maps_to_event_time_despite_jitter_drift_and_stalls():
    true, dev, arr = stream()
    sync = ClockSync(device_unit_s=1e-9)
    mapped = run(sync, dev, arr)
    err = mapped[1000:] - (true[1000:] + MIN_LATENCY)
    raw = arr[1000:] - true[1000:]
    assert np.percentile(np.abs(err), 99) < 0.3e-3  # 0.3 ms, from arrival p99 of many ms
    assert np.abs(err).max() < 1e-3
    assert np.percentile(raw, 99) > 5e-3
    assert abs(sync.drift_ppm - 60.0) < 15.0
    assert sync.stats.resets == 0
    assert np.all(np.diff(mapped) > 0)  # time never runs backwards
    assert sync.to_host(dev[-1]) == pytest.approx(mapped[-1])


def test_mapping_never_lies_after_arrival():
    # Each arrival is an upper bound on when the sample happened.
    _true, dev, arr = stream(seed=4)
    mapped = run(ClockSync(), dev, arr)
    assert np.all(mapped <= arr + 1e-12)


def test_device_reboot_is_detected_and_resynchronised():
    true, dev, arr = stream(n=4000)
    dev2 = dev.copy()
    dev2[2000:] = dev2[2000:] - dev2[2000] + 1e6  # TimeStartup restarts near zero
    sync = ClockSync()
    mapped = run(sync, dev2, arr)
    assert sync.stats.resets == 1
    err = mapped[3000:] - (true[3000:] + MIN_LATENCY)
    assert np.percentile(np.abs(err), 99) < 0.5e-3


def test_drift_beyond_the_bound_is_clamped():
    _true, dev, arr = stream(drift_ppm=3000.0, n=3000, stall_prob=0.0)
    sync = ClockSync(max_drift_ppm=500.0)
    run(sync, dev, arr)
    assert abs(sync.drift_ppm) <= 500.0 + 1e-6


def test_millisecond_device_unit_for_v4l2():
    true = 50.0 + np.arange(400) * 0.25  # 4 Hz camera
    dev_ms = (true - 50.0) * 1000.0 + 123.0
    arr = true + 0.03 + np.random.default_rng(1).exponential(0.004, true.size)
    sync = ClockSync(device_unit_s=1e-3)
    mapped = run(sync, dev_ms, arr)
    assert np.abs(mapped[50:] - (true[50:] + 0.03)).max() < 2e-3


def test_unsynchronised_use_is_an_error():
    with pytest.raises(RuntimeError, match="not synchronised"):
        ClockSync().to_host(123)


@settings(max_examples=25)
@given(st.floats(-400, 400), st.floats(0.1, 5.0), st.integers(0, 10_000))
def test_error_bounded_for_any_drift_and_jitter(drift_ppm, jitter_ms, seed):
    true, dev, arr = stream(n=3000, drift_ppm=drift_ppm, jitter_ms=jitter_ms, seed=seed)
    mapped = run(ClockSync(), dev, arr)
    err = mapped[1000:] - (true[1000:] + MIN_LATENCY)
    # Bounded by a fraction of the jitter, never by the stalls.
    assert np.percentile(np.abs(err), 95) < max(0.5e-3, 0.5 * jitter_ms * 1e-3)
    assert np.all(mapped <= arr + 1e-12)


def test_the_lower_hull_keeps_exactly_the_points_no_segment_passes_under():
    """The fit's lower envelope (:func:`_lower_hull`): a point is a vertex exactly when it
    lies strictly below the segment of its neighbours on the hull; every point is on or
    above the hull, and points on a segment are not vertices."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(2, 40))
        x = np.cumsum(rng.uniform(0.01, 1.0, n)) + 1e4
        y = 1.00002 * x + rng.exponential(1e-3, n)
        hx, hy = _lower_hull(x, y)
        assert hx[0] == x[0] and hx[-1] == x[-1] and np.all(np.diff(hx) > 0)
        below = np.interp(x, hx, hy)
        assert np.all(y >= below - 1e-9)  # nothing under the hull
        # each inner vertex is strictly below the chord of its neighbours: a convex chain
        for k in range(1, hx.size - 1):
            chord = hy[k - 1] + (hy[k + 1] - hy[k - 1]) * (hx[k] - hx[k - 1]) / (
                hx[k + 1] - hx[k - 1]
            )
            assert hy[k] < chord
    # collinear points: only the ends
    hx, hy = _lower_hull(np.array([0.0, 1.0, 2.0, 3.0]), np.array([0.0, 1.0, 2.0, 3.0]))
    assert hx.tolist() == [0.0, 3.0] and hy.tolist() == [0.0, 3.0]
