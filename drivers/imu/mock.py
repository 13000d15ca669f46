"""A simulated VN-100 on a pseudo-terminal, speaking the real byte protocol.

The mock opens a pty pair and publishes the slave behind a stable symlink (as udev's
``/dev/vn100`` would); the real driver opens that path with pyserial. The mock answers the
configuration commands the driver sends — ``$VNRRG``/``$VNWRG`` (replies echo the register),
``$VNASY``, ``$VNWNV`` — with ``$VNERR`` for bad checksums, commands, registers and values;
it switches baud rate after replying at the old one, and if the port is not at its baud rate
its output is garbled and commands go unanswered, as on a real line. It streams ``$VNYMR``
(or any ASCII type of register 6) or binary packets (register 75) at the configured rate from
a data source, stamped with ``TimeStartup`` since the mock started.

Faults, for tests and the bench: garbage bytes between packets, bit flips, dropped bytes,
stalls (no output for a while), and a port that vanishes (the pty is closed, the symlink
removed) and comes back as a new pty behind the same symlink.
"""

from __future__ import annotations

import contextlib
import math
import os
import pty
import random
import select
import termios
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import drivers.imu.vn100_binary as binary
from drivers.imu.vn100 import BAUDRATES, crc16, xor8
from drivers.threaded import ThreadedDevice

_BAUD_CONSTANTS = {getattr(termios, f"B{b}"): b for b in BAUDRATES if hasattr(termios, f"B{b}")}


@dataclass
class MockImuState:
    """What the sensor measures at one instant (sensor frame)."""

    gyro: np.ndarray  # rad/s
    accel: np.ndarray  # m/s²
    ypr_deg: np.ndarray  # yaw, pitch, roll
    quaternion_xyzw: np.ndarray
    mag_gauss: np.ndarray


def still_source(t: float) -> MockImuState:
    """A sensor at rest, level, heading 30°, with a little gyro bias."""
    yaw = math.radians(30.0)
    return MockImuState(
        gyro=np.array([0.001, -0.002, 0.0015]),
        accel=np.array([0.0, 0.0, -9.81]),
        ypr_deg=np.array([30.0, 0.0, 0.0]),
        quaternion_xyzw=np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]),
        mag_gauss=np.array([0.2, 0.05, 0.45]),
    )


@dataclass
class Faults:
    """Per-packet fault probabilities, and timed stalls / vanishings (s since start)."""

    garbage: float = 0.0  # insert 1–20 random bytes before a packet
    bit_flip: float = 0.0  # flip one bit of a packet
    drop_byte: float = 0.0  # lose one byte of a packet
    stalls: list[tuple[float, float]] = field(default_factory=list)
    vanish: list[tuple[float, float]] = field(default_factory=list)


@dataclass
class MockStats:
    packets: int = 0
    samples: int = 0  # packets carrying a measurement
    corrupted: int = 0  # packets a fault changed (bit flip, dropped byte)
    garbage_bytes: int = 0
    commands: int = 0
    errors_sent: int = 0
    vanished: int = 0
    #: output gaps not asked for (the sensor process was late: a loaded bench), wall time
    late_gaps_over_50ms: int = 0
    max_output_gap_s: float = 0.0
    #: (end time on the host's monotonic clock, length in s) of the last 1000 such gaps
    late_gaps: list[tuple[float, float]] = field(default_factory=list)
    #: packets written to the port more than 50 ms after the time stamped in them (the
    #: sensor process was held up between measuring and sending: a loaded bench, not the
    #: daemon), as (host monotonic time of the write, delay in s), the last 1000
    late_writes: list[tuple[float, float]] = field(default_factory=list)


class MockVn100(ThreadedDevice):
    """A VN-100 behind ``link`` (a symlink to a pty)."""

    thread_name = "mock-vn100"

    def __init__(
        self,
        link: str | Path,
        source: Callable[[float], MockImuState] = still_source,
        baudrate: int = 115200,
        faults: Faults | None = None,
        seed: int = 0,
        power_cycle_on_vanish: bool = False,
    ) -> None:
        super().__init__()
        self.link = Path(link)
        self.source = source
        self.faults = faults or Faults()
        self.power_cycle_on_vanish = power_cycle_on_vanish  # USB powers it: unplugging resets
        self.rng = random.Random(seed)
        self.stats = MockStats()
        self._last_emit: float | None = None
        #: device time (s) of the last packet with a measurement: a Δθ/Δv field integrates
        #: from there, as the sensor's own integrator does between two outputs
        self._last_sample_t: float | None = None
        self._factory_baud = baudrate
        self.baud = baudrate
        self.async_on = True
        self.registers: dict[int, list[str]] = {}
        self._factory_reset()
        self._master = -1
        self._slave = -1
        self._t0 = time.monotonic()
        self._inbuf = bytearray()
        self._gone_until = 0.0
        self._vanish_done: set[int] = set()

    def _factory_reset(self) -> None:
        """Factory defaults: $VNYMR at 40 Hz, binary outputs off, the factory baud rate."""
        self.baud = self._factory_baud
        self.async_on = True
        self.registers = {
            1: ["VN-100T-CR"],
            3: ["0100023456"],
            4: ["2.1.0.0"],
            5: [str(self._factory_baud)],
            6: ["14"],
            7: ["40"],
            75: ["0", "0", "00"],
            76: ["0", "0", "00"],
            77: ["0", "0", "00"],
        }

    # -- the port -----------------------------------------------------------------------------

    def _open_pty(self) -> None:
        self._master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        attrs = termios.tcgetattr(self._slave)
        speed = getattr(termios, f"B{self.baud}")
        attrs[4] = attrs[5] = speed
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        os.set_blocking(self._master, False)
        tmp = self.link.with_name(self.link.name + ".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(os.ttyname(self._slave), tmp)
        os.replace(tmp, self.link)

    def _close_pty(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.link.unlink()
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def vanish(self, seconds: float) -> None:
        """Unplug the USB cable for ``seconds``: the pty and its symlink disappear."""
        self._close_pty()
        self._gone_until = time.monotonic() + seconds
        self.stats.vanished += 1
        if self.power_cycle_on_vanish:
            self._factory_reset()

    def _line_baud(self) -> int | None:
        """The baud rate the far end (the driver) has set on the port."""
        try:
            return _BAUD_CONSTANTS.get(termios.tcgetattr(self._master)[5])
        except termios.error:
            return None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> MockVn100:
        self._t0 = time.monotonic()
        self._open_pty()
        self._start_thread()
        return self

    def stop(self) -> None:
        super().stop()
        self._close_pty()

    def __enter__(self) -> MockVn100:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        next_out = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            t = now - self._t0
            for k, (at, dur) in enumerate(self.faults.vanish):
                if k not in self._vanish_done and t >= at:
                    self._vanish_done.add(k)
                    self.vanish(dur)
            if self._master < 0:
                if now >= self._gone_until:
                    self._open_pty()
                else:
                    time.sleep(0.005)
                    continue
            try:
                r, _, _ = select.select([self._master], [], [], max(0.0, min(next_out - now, 0.01)))
                if r:
                    self._read_commands()
            except OSError:
                pass
            now = time.monotonic()
            if now >= next_out:
                rate = self._output_rate()
                if rate > 0 and self.async_on and not self._stalled(now - self._t0):
                    self._note_gap(now)
                    self._emit(now - self._t0)
                period = 1.0 / rate if rate > 0 else 0.05
                next_out = now + period if now - next_out > 0.1 else next_out + period

    def _note_gap(self, now: float) -> None:
        last = self._last_emit
        self._last_emit = now
        if last is None or now - last > 1.0:  # a fault or a reconnect, not lateness
            return
        gap = now - last
        self.stats.max_output_gap_s = max(self.stats.max_output_gap_s, gap)
        if gap > 0.05:
            self.stats.late_gaps_over_50ms += 1
            self.stats.late_gaps.append((now, gap))
            del self.stats.late_gaps[:-1000]

    def _stalled(self, t: float) -> bool:
        return any(a <= t < a + d for a, d in self.faults.stalls)

    # -- commands -----------------------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        if self._master < 0:
            return
        if self._line_baud() not in (None, self.baud):  # wrong baud on the line: garbage
            data = bytes((b ^ 0x5A) | 0x80 for b in data)
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._master, data)

    def _reply(self, body: str) -> None:
        raw = body.encode()
        self._write(b"$" + raw + f"*{xor8(raw):02X}\r\n".encode())

    def _error(self, code: int) -> None:
        self.stats.errors_sent += 1
        self._reply(f"VNERR,{code:02d}")

    def _read_commands(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return
        if self._line_baud() not in (None, self.baud):
            return  # at the wrong baud rate the sensor sees only framing errors
        self._inbuf += data
        while True:
            nl = self._inbuf.find(b"\n")
            if nl < 0:
                if len(self._inbuf) > 512:
                    self._inbuf.clear()
                return
            line = bytes(self._inbuf[:nl]).strip()
            del self._inbuf[: nl + 1]
            start = line.find(b"$")
            if start >= 0:
                self._command(line[start + 1 :])

    def _command(self, line: bytes) -> None:
        self.stats.commands += 1
        star = line.rfind(b"*")
        if star < 0:
            self._error(3)
            return
        body, check = line[:star], line[star + 1 :]
        if check.upper() != b"XX":  # "XX": no check, as the real sensor allows
            ok = (len(check) == 2 and _hex(check) == xor8(body)) or (
                len(check) == 4 and _hex(check) == crc16(body)
            )
            if not ok:
                self._error(3)
                return
        try:
            parts = body.decode("ascii").split(",")
        except UnicodeDecodeError:
            self._error(4)
            return
        cmd, args = parts[0], parts[1:]
        if cmd == "VNASY":
            if args not in (["0"], ["1"]):
                self._error(7)
                return
            self.async_on = args == ["1"]
            self._reply(body.decode())
        elif cmd == "VNRRG":
            reg = _int(args[0]) if args else None
            if reg is None or reg not in self.registers:
                self._error(8)
                return
            self._reply(f"VNRRG,{reg:02d}," + ",".join(self.registers[reg]))
        elif cmd == "VNWRG":
            self._write_register(args)
        elif cmd in ("VNWNV", "VNRFS", "VNRST"):
            self._reply(cmd)
        else:
            self._error(4)

    def _write_register(self, args: list[str]) -> None:
        reg = _int(args[0]) if args else None
        values = args[1:]
        if reg is None or reg not in self.registers or reg in (1, 3, 4):
            self._error(8)
            return
        if reg == 5:
            baud = _int(values[0]) if values else None
            if baud not in BAUDRATES:
                self._error(7)
                return
            self.registers[5] = [str(baud)]
            self._reply(f"VNWRG,05,{baud}")  # the reply goes out at the old rate
            time.sleep(0.005)
            self.baud = baud
            return
        if reg == 6:
            typ = _int(values[0]) if values else None
            if typ not in (0, 1, 2, 8, 14, 19, 20, 22, 252):
                self._error(7)
                return
        if reg == 7:
            hz = _int(values[0]) if values else None
            if hz not in (1, 2, 4, 5, 10, 20, 25, 40, 50, 100, 200):
                self._error(7)
                return
            if self.baud * 0.8 / 10 < 160 * hz and int(self.registers[6][0]) != 0:
                self._error(12)  # ASCII at this rate does not fit the line
                return
        if reg in (75, 76, 77) and not _valid_binary_register(values):
            self._error(7)
            return
        self.registers[reg] = list(values)
        self._reply(f"VNWRG,{reg:02d}," + ",".join(values))

    # -- output ---------------------------------------------------------------------------------

    def _output_rate(self) -> float:
        mode, divisor = _int(self.registers[75][0]) or 0, _int(self.registers[75][1]) or 0
        if mode and divisor:
            return 800.0 / divisor
        if int(self.registers[6][0]) != 0:
            return float(self.registers[7][0])
        return 0.0

    def _emit(self, t: float) -> None:
        s = self.source(t)
        mode = _int(self.registers[75][0]) or 0
        packet = self._binary_packet(t, s) if mode else self._ascii_packet(s)
        if packet is None:
            return
        f, rng = self.faults, self.rng
        if f.garbage and rng.random() < f.garbage:
            junk = bytes(rng.randrange(256) for _ in range(rng.randint(1, 20)))
            self.stats.garbage_bytes += len(junk)
            self._write(junk)
        if f.bit_flip and rng.random() < f.bit_flip:
            k = rng.randrange(len(packet))
            packet = packet[:k] + bytes([packet[k] ^ (1 << rng.randrange(8))]) + packet[k + 1 :]
            self.stats.corrupted += 1
        if f.drop_byte and rng.random() < f.drop_byte:
            k = rng.randrange(len(packet))
            packet = packet[:k] + packet[k + 1 :]
            self.stats.corrupted += 1
        self.stats.packets += 1
        self.stats.samples += 1
        self._write(packet)
        written = time.monotonic()
        if written - self._t0 - t > 0.05:
            self.stats.late_writes.append((written, written - self._t0 - t))
            del self.stats.late_writes[:-1000]

    def _ascii_packet(self, s: MockImuState) -> bytes | None:
        typ = int(self.registers[6][0])
        if typ != 14:  # only $VNYMR is generated; other types are accepted but silent
            return None
        vals = [*s.ypr_deg, *s.mag_gauss, *s.accel, *s.gyro]
        fmt = ["{:+08.3f}"] * 3 + ["{:+08.4f}"] * 3 + ["{:+07.3f}"] * 3 + ["{:+010.6f}"] * 3
        body = "VNYMR," + ",".join(f.format(v) for f, v in zip(fmt, vals, strict=True))
        raw = body.encode()
        return b"$" + raw + f"*{xor8(raw):02X}\r\n".encode()

    def _binary_packet(self, t: float, s: MockImuState) -> bytes | None:
        groups = int(self.registers[75][2], 16)
        masks = [int(v, 16) for v in self.registers[75][3:]]
        active = [g for g in range(len(binary.GROUP_NAMES)) if groups >> g & 1]
        period = 1.0 / max(self._output_rate(), 1e-9)
        last, self._last_sample_t = self._last_sample_t, t
        # the integrator restarts at each output; after a stall or at the first packet, one
        # output period (the sensor integrates from its previous output, not from start-up)
        dt = period if last is None or not 0.0 < t - last < 10 * period else t - last
        fields = {
            f"{binary.GROUP_NAMES[g]}.{binary.FIELDS[(g, bit)].name}": _field_bytes(
                g, bit, t, s, dt
            )
            for g, mask in zip(active, masks, strict=True)
            for bit in range(16)
            if mask >> bit & 1
        }
        return binary.encode_packet(fields)


def _field_bytes(g: int, bit: int, t: float, s: MockImuState, dt: float) -> bytes:
    """What the mock measures, in field (group, bit); zeros for what it does not. The
    source's rates are means over the ``dt`` since the previous output, so Δθ = ω·Δt and
    Δv = a·Δt are that interval's integrals (VN-100 manual: Delta Theta and Delta Velocity)."""
    name = f"{binary.GROUP_NAMES[g]}.{binary.FIELDS[(g, bit)].name}"
    rad_to_deg = 180.0 / math.pi
    values: dict[str, list[float]] = {
        "Common.TimeStartup": [int(t * 1e9)],
        "Common.TimeSyncIn": [int(t * 1e9)],
        "Time.TimeStartup": [int(t * 1e9)],
        "Common.YawPitchRoll": list(s.ypr_deg),
        "Attitude.YawPitchRoll": list(s.ypr_deg),
        "Common.Quaternion": list(s.quaternion_xyzw),
        "Attitude.Quaternion": list(s.quaternion_xyzw),
        "Common.AngularRate": list(s.gyro),
        "Imu.AngularRate": list(s.gyro),
        "Imu.UncompGyro": list(s.gyro),
        "Common.Accel": list(s.accel),
        "Imu.Accel": list(s.accel),
        "Imu.UncompAccel": list(s.accel),
        "Common.Imu": [*s.accel, *s.gyro],
        "Common.MagPres": [*s.mag_gauss, 25.0, 101.3],
        "Imu.UncompMag": list(s.mag_gauss),
        "Imu.Mag": list(s.mag_gauss),
        "Imu.Temp": [25.0],
        "Imu.Pres": [101.3],
    }
    if name in values:
        return binary.pack_values(name, values[name])
    spec = binary.FIELDS[(g, bit)]
    if name in ("Imu.DeltaTheta", "Common.Deltas"):  # since the previous output
        dtheta = [w * dt * rad_to_deg for w in s.gyro]
        extra = [a * dt for a in s.accel] if name == "Common.Deltas" else []
        return binary.pack_values(name, [dt, *dtheta, *extra])
    if name == "Imu.DeltaVel":
        return binary.pack_values(name, [a * dt for a in s.accel])
    if spec.variable == "satinfo":
        return bytes(2)  # no satellites
    if spec.variable == "rawmeas":
        return bytes(12)  # no measurements
    return bytes(spec.size)


def _valid_binary_register(values: list[str]) -> bool:
    try:
        mode, divisor, groups = int(values[0]), int(values[1]), int(values[2], 16)
        masks = [int(v, 16) for v in values[3:]]
    except (ValueError, IndexError):
        return False
    if mode not in (0, 1, 2, 3) or divisor < 0 or groups & ~binary.VALID_GROUPS:
        return False
    active = [g for g in range(len(binary.GROUP_NAMES)) if groups >> g & 1]
    if len(masks) != len(active):
        return False
    return all(m and not m & ~binary.KNOWN_BITS[g] for g, m in zip(active, masks, strict=True))


def _hex(b: bytes) -> int:
    try:
        return int(b, 16)
    except ValueError:
        return -1


def _int(s: str) -> int | None:
    try:
        return int(s)
    except (TypeError, ValueError):
        return None
