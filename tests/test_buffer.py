"""The time-ordered sensor buffer (docs/design.md §8)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mowerhw.common.buffer import SensorBuffer, StreamBuffer
from mowerhw.common.samples import BearingObservation, ImuSample, SpeedSample, Stream
from mowerhw.estimation.odometry import SpeedTrack, accel_shaped_speeds


def imu(t):
    return ImuSample(t=t, gyro=[0.0, 0.0, 0.1])


def speed(t, v=0.5, valid=True):
    return SpeedSample(t=t, speed_mps=v if valid else float("nan"), valid=valid)


def test_streams_are_merged_in_time_order_and_out_of_order_is_counted():
    buf = SensorBuffer()
    buf.push(Stream.IMU, imu(0.00))
    buf.push(Stream.IMU, imu(0.02))
    buf.push(Stream.SPEED, speed(0.015))
    buf.push(Stream.IMU, imu(0.01))  # late
    obs = BearingObservation(t=0.005, ids=[1, 2], bearings=[[1, 0, 0], [0, 1, 0]])
    buf.push(Stream.BEARINGS, obs)  # a late frame
    out = buf.pop_ready()
    assert [s.t for _, s in out] == [0.0, 0.005, 0.01, 0.015, 0.02]
    assert [name for name, _ in out] == ["imu", "bearings", "imu", "speed", "imu"]
    assert buf.stats()["imu"]["out_of_order"] == 1
    assert buf.stream(Stream.IMU).times().tolist() == [0.0, 0.01, 0.02]


def test_pop_ready_until_a_watermark():
    buf = SensorBuffer()
    for k in range(10):
        buf.push(Stream.IMU, imu(k * 0.01))
    first = buf.pop_ready(until=0.045)
    assert len(first) == 5 and buf.pending() == 5
    assert [s.t for _, s in buf.pop_ready()] == pytest.approx([0.05, 0.06, 0.07, 0.08, 0.09])


def test_history_is_bounded_and_drops_are_counted():
    buf = SensorBuffer(capacity={Stream.IMU: 100})
    for k in range(250):
        buf.push(Stream.IMU, imu(k * 0.01))
    hist = buf.stream(Stream.IMU)
    assert len(hist) == 100
    assert hist.stats.dropped_full == 150
    assert hist.oldest().t == pytest.approx(1.5)
    assert hist.latest().t == pytest.approx(2.49)


def test_pending_queue_is_bounded_when_the_consumer_stalls():
    buf = SensorBuffer(pending_capacity=50)
    for k in range(80):
        buf.push(Stream.IMU, imu(k * 0.01))
    assert buf.pending() == 50
    assert buf.stats()["imu"]["dropped_pending"] == 30
    assert buf.pop_ready()[0][1].t == pytest.approx(0.30)  # the oldest were dropped


def test_range_and_at_or_before():
    s = StreamBuffer("imu", 1000)
    for k in range(100):
        s.push(imu(k * 0.01))
    got = s.range(0.1, 0.2)
    assert [round(x.t, 2) for x in got] == [round(0.1 + 0.01 * i, 2) for i in range(11)]
    assert s.at_or_before(0.555).t == pytest.approx(0.55)
    assert s.at_or_before(-1.0) is None
    assert s.range(5.0, 6.0) == []


def test_non_finite_timestamps_are_rejected_and_counted():
    buf = SensorBuffer()
    assert not buf.push(Stream.IMU, ImuSample(t=float("nan"), gyro=[0, 0, 0]))
    assert buf.stats()["imu"]["rejected"] == 1
    assert buf.pending() == 0


def test_the_speed_model_interpolates_holds_and_never_extrapolates_through_a_stop():
    track = SpeedTrack()
    for k in range(11):
        track.add(0.1 * k, 0.05 * k)  # 0 → 0.5 m/s over 1 s
    t = np.arange(0.0, 1.0, 0.01)
    assert np.allclose(track.interpolate(t), 0.5 * t, atol=1e-12)
    assert track.at(1.05) == pytest.approx(0.525)  # first-order hold, a little ahead
    assert track.at(1.5) == 0.5  # too far ahead: the newest value
    stop = SpeedTrack()
    stop.add(0.0, 0.2)
    stop.add(0.1, 0.05)
    assert stop.at(0.2) == 0.0  # the trend points through zero: stopped, not reversing


def test_between_two_speed_samples_the_accelerometer_shapes_the_speed():
    """A set-off 30 ms after a sample at 1 m/s², an accelerometer 0.05 m/s² off: the
    speed it shapes is the true one between the samples (the bias taken out), the line
    between them 1.5 cm/s off; with no acceleration the shape is that line; a gap in the
    steps, or a miss beyond its bound (a bump's spike), gives none."""
    t0 = np.round(0.01 * np.arange(0, 12), 9)  # 10 ms steps from 0 to 0.12 s
    t1 = t0 + 0.01

    def true(t: np.ndarray) -> np.ndarray:
        return np.clip(np.asarray(t) - 0.03, 0.0, None)

    steps = np.c_[t0, t1, (true(t1) - true(t0)) / 0.01 + 0.05]
    mids = 0.5 * (t0 + t1)[:10]
    shaped = accel_shaped_speeds((0.0, 0.0), (0.1, 0.07), steps, mids, 0.03)
    assert shaped is not None and np.abs(shaped - true(mids)).max() < 1e-12
    line = 0.7 * mids
    assert np.abs(line - true(mids)).max() > 0.015  # what SpeedTrack.known gives
    flat = np.c_[t0, t1, np.zeros(12)]
    got = accel_shaped_speeds((0.0, 0.0), (0.1, 0.07), flat, mids, 0.1)
    assert got is not None and np.allclose(got, line, atol=1e-12)
    assert accel_shaped_speeds((0.0, 0.0), (0.1, 0.07), flat, mids, 0.03) is None  # 0.07 off
    assert accel_shaped_speeds((0.0, 0.0), (0.1, 0.07), steps[[0, 1, 3, 4]], mids, 0.03) is None
    assert accel_shaped_speeds((0.0, 0.0), (0.1, 0.07), steps[:5], mids, 0.03) is None


@given(
    st.lists(
        st.tuples(st.sampled_from(["imu", "speed", "bearings"]), st.floats(0, 100)),
        max_size=300,
    ),
    st.integers(1, 50),
)
def test_any_arrival_order_gives_sorted_bounded_streams(pushes, capacity):
    buf = SensorBuffer(capacity={"imu": capacity, "speed": capacity, "bearings": capacity})
    for stream, t in pushes:
        buf.push(stream, imu(t))
    out = [s.t for _, s in buf.pop_ready()]
    assert out == sorted(out) and len(out) == len(pushes)
    for name, hist in buf.streams.items():
        times = hist.times()
        assert np.all(np.diff(times) >= 0)
        assert len(hist) <= capacity
        stats = hist.stats
        assert stats.pushed == sum(1 for s, _ in pushes if s == name)
        assert len(hist) + stats.dropped_full == stats.pushed


def test_observation_shapes_are_checked():
    with pytest.raises(ValueError, match="2 landmark ids but 1 bearings"):
        BearingObservation(t=0.0, ids=[1, 2], bearings=[[1, 0, 0]])
    with pytest.raises(ValueError, match="3 components"):
        ImuSample(t=0.0, gyro=[1, 2])
    with pytest.raises(ValueError, match="finite speed"):
        SpeedSample(t=0.0, speed_mps=float("nan"), valid=True)


def test_an_imu_sample_is_frozen_checked_and_knows_when_it_is_not_finite():
    """A sample's vectors are read-only float64 3-vectors whatever it was given (a driver's
    own array is not copied, but cannot be written through the sample), a wrong shape is
    refused by name, and a NaN or an infinity in time, rate or acceleration is not finite."""
    own = np.array([0.0, 0.0, 0.1])
    s = ImuSample(t=1.0, gyro=own, accel=[0, 0, 9.8])
    assert s.gyro.dtype == np.float64 and s.accel is not None and s.accel.dtype == np.float64
    with pytest.raises(ValueError):
        s.gyro[0] = 1.0
    assert np.shares_memory(s.gyro, own) and own.flags.writeable  # the driver's is its own
    with pytest.raises(ValueError, match="gyro must have 3 components"):
        ImuSample(t=1.0, gyro=[0.0, 0.1])
    with pytest.raises(ValueError, match="accel must have 3 components"):
        ImuSample(t=1.0, gyro=own, accel=np.zeros(4))
    assert s.finite and ImuSample(t=1.0, gyro=np.float32([0, 0, 1])).finite
    bad = (np.nan, np.inf, -np.inf)
    for v in bad:
        assert not ImuSample(t=v, gyro=own).finite
        assert not ImuSample(t=1.0, gyro=[0.0, v, 0.0]).finite
        assert not ImuSample(t=1.0, gyro=own, accel=[v, 0.0, 9.8]).finite
    assert not ImuSample(t=1.0, gyro=[np.inf, -np.inf, 0.0]).finite  # inf − inf is NaN


def test_the_distance_driven_uses_only_the_speed_samples_up_to_its_end():
    track = SpeedTrack()
    for t, v in [(0.0, 0.0), (0.1, 0.5), (0.2, 0.5), (0.3, -0.5)]:
        track.add(t, v)
    # each reading is the speed of the interval before it; the newest is held after it
    assert abs(track.distance(0.0, 0.2) - 0.1) < 1e-12
    assert abs(track.distance(0.05, 0.15) - 0.05) < 1e-12
    assert abs(track.distance(0.2, 0.3) - 0.05) < 1e-12  # reversing counts as distance
    # up to 0.25 the sample at 0.3 is not known yet: 0.5 m/s held after 0.2
    assert abs(track.distance(0.15, 0.25) - 0.05) < 1e-12
    assert track.distance(0.0, 0.0) == 0.0 and SpeedTrack().distance(0.0, 1.0) == 0.0
