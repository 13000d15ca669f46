"""The real VN-100 driver against the mock VN-100 on a real pseudo-terminal (pyserial)."""

import math
import time

import numpy as np
import pytest
from _waiting import wait_for

from drivers.imu.mock import Faults, MockImuState, MockVn100
from drivers.imu.vn100 import Vn100, Vn100CommandError


def moving_source(t: float) -> MockImuState:
    """A sensor turning in a known way, so every sample can be checked against its time."""
    gyro = np.array([0.1 * math.sin(t), 0.2 * math.cos(t), 0.3 + 0.01 * t])
    return MockImuState(
        gyro,
        np.array([0.0, 0.0, -9.81]),
        np.array([10 * t % 360, 0, 0]),
        np.array([0, 0, 0, 1.0]),
        np.array([0.2, 0.0, 0.4]),
    )


def run_for(drv: Vn100, seconds: float) -> None:
    drv.start()
    time.sleep(seconds)
    drv.stop()


@pytest.fixture
def link(tmp_path):
    return tmp_path / "vn100"


def test_driver_configures_the_mock_from_factory_settings(link):
    with MockVn100(link) as mock:
        assert mock.baud == 115200 and mock.registers[6] == ["14"]
        drv = Vn100(str(link), baudrate=921600, rate_hz=100, output="binary")
        drv.open()
        assert mock.baud == 921600 and drv.stats.baudrate == 921600
        # TimeStartup, YawPitchRoll, AngularRate, Accel, MagPres (the compass)
        assert mock.registers[75] == ["1", "8", "01", "0529"]
        assert mock.registers[6] == ["0"]
        assert mock.async_on
        drv.close()


@pytest.mark.parametrize("output", ["binary", "ascii"])
def test_every_sample_carries_the_magnetic_field_in_tesla(link, output):
    """The compass's input (issue 18), over the pty: binary MagPres and ASCII $VNYMR both
    give the field the sensor sent (gauss) in tesla."""
    samples = []
    with MockVn100(link, source=moving_source) as _mock:
        drv = Vn100(str(link), on_sample=samples.append, output=output)
        drv.open()
        run_for(drv, 0.5)
    assert len(samples) > 20
    for s in samples:
        assert s.mag is not None
        np.testing.assert_allclose(s.mag, [0.2e-4, 0.0, 0.4e-4], rtol=1e-6, atol=1e-12)


@pytest.mark.slow
def test_ten_seconds_of_100_hz_binary_with_one_percent_garbage(link):
    faults = Faults(garbage=0.01, bit_flip=0.005, drop_byte=0.005)
    samples = []
    with MockVn100(link, source=moving_source, faults=faults, seed=3) as mock:
        drv = Vn100(str(link), on_sample=samples.append)
        drv.open()
        sent_before = mock.stats.samples
        run_for(drv, 10.0)
        sent = mock.stats.samples - sent_before
        corrupted_sent = mock.stats.corrupted
    stats = drv.parser.stats
    # the factory default $VNYMR (no TimeStartup) may stream until the driver's set-up has
    # turned it off (commands can be garbled too, and are then sent again); after the first
    # binary packet, every sample is binary
    first = next(k for k, s in enumerate(samples) if s.device_time_ns is not None)
    assert all(s.device_time_ns is not None for s in samples[first:])
    samples = samples[first:]
    # every accepted sample is exactly what the sensor measured at its own TimeStartup
    bad = [
        s
        for s in samples
        if not np.allclose(s.gyro, moving_source(s.device_time_ns * 1e-9).gyro, atol=1e-6)
    ]
    print(
        f"\nsent {sent} samples ({corrupted_sent} corrupted, {mock.stats.garbage_bytes} garbage "
        f"bytes); accepted {len(samples)}; rejected {stats.rejected} "
        f"(bad CRC {stats.bad_crc}, bad header {stats.bad_binary_header}); garbage bytes "
        f"skipped {stats.garbage_bytes}; corrupted samples accepted {len(bad)}"
    )
    assert bad == []
    assert sent > 500  # the rate itself is timed in tools/bench_vn100_parser.py
    assert len(samples) >= sent - corrupted_sent - 10  # only damaged packets are lost
    assert stats.rejected >= corrupted_sent // 2
    t = np.array([s.t for s in samples])
    assert np.all(np.diff(t) > 0)  # clock-synced, monotonic


def test_vnerr_is_a_failed_command_with_its_meaning(link):
    with MockVn100(link) as _mock:
        drv = Vn100(str(link))
        drv.open()
        with pytest.raises(Vn100CommandError, match=r"error 7 \(invalid parameter\)"):
            drv.command("VNWRG,75,9,8,01,0129")
        with pytest.raises(Vn100CommandError, match=r"error 8 \(invalid register\)"):
            drv.command("VNRRG,99")
        drv.close()


def data_after_outage_s(samples: list) -> float:
    """Seconds of samples after the longest gap (> 1 s) in their host times; 0 before one."""
    if len(samples) < 2:
        return 0.0
    t = np.array([s.host_time_ns for s in samples]) * 1e-9
    gaps = np.diff(t)
    k = int(np.argmax(gaps))
    return float(t[-1] - t[k + 1]) if gaps[k] > 1.0 else 0.0


@pytest.mark.parametrize("power_cycle", [False, True], ids=["usb-link", "power-cycle"])
def test_reconnects_when_the_port_vanishes_and_returns(link, power_cycle):
    samples = []
    with MockVn100(
        link,
        source=moving_source,
        faults=Faults(vanish=[(2.0, 1.5)]),
        power_cycle_on_vanish=power_cycle,
    ) as mock:
        drv = Vn100(str(link), on_sample=samples.append, reconnect_max_backoff_s=0.5)
        drv.start()
        # the outage starts 2 s into the mock's stream and lasts 1.5 s; wait for 1.5 s of data
        # after it (a loaded machine configures the sensor more slowly: up to 15 s in all)
        wait_for(lambda: data_after_outage_s(samples) > 1.5, timeout=15.0, poll_s=0.1)
        drv.stop()
        assert mock.stats.vanished == 1
    assert drv.stats.reconnects >= 1
    assert drv.stats.reconfigurations >= 2
    t = np.array([s.host_time_ns for s in samples]) * 1e-9
    gaps = np.diff(t)
    assert gaps.max() > 1.0  # the outage
    assert t[np.argmax(gaps)] - t[0] > 1.0  # data before the outage
    assert data_after_outage_s(samples) > 1.5  # and after it
    print(
        f"port vanished for 1.5 s ({'sensor power-cycled' if power_cycle else 'USB link only'}): "
        f"gap in samples {gaps.max():.2f} s, reconnects {drv.stats.reconnects}, "
        f"configurations {drv.stats.reconfigurations}, "
        f"samples {len(samples)} in {t[-1] - t[0]:.1f} s"
    )


def test_read_on_an_event_loop_and_reconnected_by_the_thread(link):
    """The daemon's way: samples read and delivered on the event loop (no hand-off between
    threads); the port vanishing and returning is still the driver thread's to handle."""
    import asyncio
    import threading

    samples, threads = [], set()

    def on_sample(s):
        samples.append(s)
        threads.add(threading.get_ident())

    async def main():
        drv = Vn100(str(link), on_sample=on_sample, reconnect_max_backoff_s=0.5)
        drv.start(asyncio.get_running_loop())
        deadline = time.monotonic() + 15.0  # as above: a loaded machine reconfigures slowly
        while time.monotonic() < deadline and not data_after_outage_s(samples) > 1.5:
            await asyncio.sleep(0.1)
        drv.stop()
        return drv

    with MockVn100(link, source=moving_source, faults=Faults(vanish=[(2.0, 1.5)])) as mock:
        loop_thread = threading.get_ident()
        drv = asyncio.run(main())
        assert mock.stats.vanished == 1
    assert threads == {loop_thread}
    assert drv.stats.reconnects >= 1 and drv.stats.reconfigurations >= 2
    t = np.array([s.host_time_ns for s in samples]) * 1e-9
    gaps = np.diff(t)
    assert gaps.max() > 1.0 and data_after_outage_s(samples) > 1.5  # data after the outage
    assert t[np.argmax(gaps)] - t[0] > 1.0  # and before it
    # 100 Hz for the time the stream ran, less the outage
    assert 0.8 < len(samples) / (100 * (t[-1] - t[0] - gaps.max())) < 1.2


def test_driver_asks_for_the_configured_gyro_field(link):
    """imu.gyro_source: uncomp_gyro → register 75 asks for Common.Imu, and the samples carry
    the uncompensated gyro."""
    samples = []
    mock = MockVn100(link, source=moving_source)
    # no ASCII output before the driver's own: a factory $VNYMR already in the port's buffer
    # when the driver pauses output (a loaded machine) is rightly counted unused, and this
    # test is about the configured packets
    mock.registers[6] = ["0"]
    with mock:
        drv = Vn100(str(link), gyro_source="uncomp_gyro", on_sample=samples.append)
        drv.open()
        assert mock.registers[75] == ["1", "8", "01", "0609"]  # TimeStartup, YPR, Imu, MagPres
        run_for(drv, 1.0)
    assert len(samples) >= 80 and drv.extractor.stats.unused == 0
    s = samples[-1]
    assert np.allclose(s.gyro, moving_source(s.device_time_ns * 1e-9).gyro, atol=1e-6)


def test_driver_keeps_the_users_own_output_configuration(link):
    """configure_sensor: false — a sensor set up by its user (IMU + Attitude groups at 40 Hz,
    as the real SD-card logger's) is read as it is: no register written, gyro from UncompGyro."""
    samples = []
    with MockVn100(link, source=moving_source, baudrate=115200) as mock:
        mock.registers[6] = ["0"]
        mock.registers[75] = ["1", "20", "14", "003E", "003A"]
        drv = Vn100(str(link), baudrate=115200, configure_sensor=False, on_sample=samples.append)
        drv.open()
        assert mock.registers[75] == ["1", "20", "14", "003E", "003A"]
        run_for(drv, 1.0)
    assert 30 <= len(samples) <= 50 and drv.parser.stats.rejected == 0
    assert all(s.device_time_ns is None for s in samples)  # no time field: arrival time
    assert np.allclose(samples[-1].gyro[2], moving_source(0).gyro[2], atol=0.02)


def test_the_mock_counts_packets_it_sent_late_after_stamping_them(link):
    """A mock held up between measuring and writing (a loaded bench) stamps a packet on time
    and writes it late: the daemon sees a silence the sensor's stamps do not show, so the
    mock says so itself (``late_writes``) — the bench does not blame that on the daemon."""
    calls = [0]

    def slow_now_and_then(t: float) -> MockImuState:
        calls[0] += 1
        if calls[0] % 25 == 0:
            time.sleep(0.08)  # after the stamp (t), before the write
        return moving_source(t)

    samples = []
    with MockVn100(link, source=slow_now_and_then) as mock:
        drv = Vn100(str(link), on_sample=samples.append, output="binary")
        drv.open()
        run_for(drv, 1.0)
    late = mock.stats.late_writes
    assert late and all(0.05 < delay < 0.2 for _, delay in late)
    stamps = np.diff([s.device_time_ns for s in samples if s.device_time_ns is not None])
    assert len(stamps) > 40 and np.median(stamps) == pytest.approx(1e7, rel=0.2)


def test_fifty_hz_integrated_outputs_cover_each_interval_exactly(link):
    """imu.gyro_source delta_theta at 50 Hz (the bench's setting): register 75 asks for
    Deltas (no instantaneous Accel), each packet's Δt is the time since the one before (what
    the sensor's integrator covers), and Δθ/Δt, Δv/Δt are the source's mean rate and force."""
    samples = []
    with MockVn100(link, source=moving_source) as mock:
        drv = Vn100(str(link), gyro_source="delta_theta", rate_hz=50, on_sample=samples.append)
        drv.open()
        assert mock.registers[75] == ["1", "16", "01", "0C09"]  # TimeStartup, YPR, Deltas, Mag
        run_for(drv, 1.0)
    assert 40 <= len(samples) <= 55 and drv.extractor.stats.unused == 0
    for s in samples[-5:]:
        assert np.allclose(s.gyro, moving_source(s.device_time_ns * 1e-9).gyro, atol=1e-6)
        assert np.allclose(s.accel, (0.0, 0.0, -9.81), atol=1e-5)


def test_the_mocks_integrated_fields_span_the_time_since_its_previous_output(link):
    from drivers.imu.vn100 import Vn100Parser

    mock = MockVn100(link, source=moving_source)
    mock.registers[75] = ["1", "16", "01", "0800"]  # Common.Deltas at 50 Hz
    parser = Vn100Parser()
    deltas = []
    for t in (1.0, 1.02, 1.05, 9.0):  # on time; 10 ms late; after a 8 s stall
        (item,) = parser.feed(mock._binary_packet(t, moving_source(t)))
        deltas.append(item.get("Common.Deltas"))
    assert [round(d[0], 6) for d in deltas] == [0.02, 0.02, 0.03, 0.02]
    s = moving_source(1.05)
    assert np.allclose(np.asarray(deltas[2][1:4]) / 0.03, s.gyro, atol=1e-6)
    assert np.allclose(np.asarray(deltas[2][4:7]) / 0.03, s.accel, atol=1e-6)


def test_a_port_it_may_not_open_says_what_to_change(tmp_path) -> None:
    """EPERM (a device policy: the systemd unit's DevicePolicy=closed, which allows USB serial
    adapters only) and EACCES (the port's group) each name what to change; a missing port
    says only that."""
    import errno

    import serial

    from drivers.imu.vn100 import Vn100Error

    def refused(code: int, text: str):
        def factory(port: str, **_kw):  # what pyserial raises for the OS's refusal
            raise serial.SerialException(
                code, f"could not open port {port}: [Errno {code}] {text}: {port!r}"
            )

        return factory

    said = {}
    for code, text in (
        (errno.EPERM, "Operation not permitted"),
        (errno.EACCES, "Permission denied"),
    ):
        drv = Vn100("/dev/ttyAMA0", serial_factory=refused(code, text))
        with pytest.raises(Vn100Error) as err:
            drv.open()
        said[code] = str(err.value)
    assert "DeviceAllow=char-ttyAMA rw" in said[errno.EPERM]
    assert "only USB serial adapters" in said[errno.EPERM]
    assert "needs the port's group, usually dialout" in said[errno.EACCES]
    missing = Vn100(str(tmp_path / "ttyNOPE0"))
    with pytest.raises(Vn100Error) as err:
        missing.open()
    assert "No such file or directory" in str(err.value) and "DeviceAllow" not in str(err.value)
