"""VectorNav VN-100 over serial: the wire protocol (docs/design.md §7) and the device driver.

Two layers:

* :class:`Vn100Parser` — pure and incremental: ``feed(bytes)`` returns every packet found in
  order, ASCII (``$VN…*CS``, XOR-8 or CRC-16 check, CRLF or LF) and binary (``0xFA``, groups,
  field masks, CRC-16) interleaved in one byte stream. After garbage it resynchronises on
  the next ``$`` / ``0xFA``; after a failed check it resumes at the byte after the false sync
  byte; every rejected byte or packet is counted by cause; it never raises on bad input.
* :class:`Vn100` — the device on a serial port (pyserial): finds the sensor's baud rate,
  configures it (pause async output, switch baud — the reply comes at the old rate —, write
  the binary output register 75, verify every reply, resume), then reads in a thread — or,
  given an asyncio loop, on that loop (``add_reader``, the way python-can's ``Notifier``
  reads a bus that has a file descriptor: one wake-up per packet instead of two),
  timestamps every packet on arrival, maps the sensor's ``TimeStartup`` onto the host clock
  (:class:`mowerhw.common.clocksync.ClockSync`), and reconnects with backoff when the port vanishes
  (USB unplugged) and comes back.

Between them, :class:`ImuExtractor` turns parsed messages into IMU samples: the angular rate
from whichever field or message the sensor sends (``imu.gyro_source``); a message with a
valid check that carries no such rate is counted as ``unused``, never as an error.

Units: the ASCII messages keep the sensor's units except where noted (YPR in degrees,
magnetic field in Gauss, acceleration m/s², angular rate rad/s); a binary packet's fields are
decoded to SI (:mod:`drivers.imu.vn100_binary`: angles rad, magnetic field T, pressure Pa, times
ns).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import math
import os
import re
import select
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any

import numpy as np

import drivers.imu.vn100_binary as binary
from drivers.imu.vn100_binary import BinaryPacket, crc16
from drivers.threaded import ThreadedDevice
from mowerhw.common.clocksync import ClockSync
from mowerhw.common.samples import ImuSample

__all__ = ["BinaryPacket", "crc16"]  # re-exported: the binary protocol lives in vn100_binary

log = logging.getLogger(__name__)

BAUDRATES = (9600, 19200, 38400, 57600, 115200, 128000, 230400, 460800, 921600)

ERROR_CODES = {
    1: "hard fault",
    2: "serial buffer overflow",
    3: "invalid checksum",
    4: "invalid command",
    5: "not enough parameters",
    6: "too many parameters",
    7: "invalid parameter",
    8: "invalid register",
    9: "unauthorized access",
    10: "watchdog reset",
    11: "output buffer overflow",
    12: "insufficient baud rate",
    255: "error buffer overflow",
}

# -------------------------------------------------------------------------------- checks


def xor8(body: bytes) -> int:
    """8-bit XOR of every byte (the bytes strictly between ``$`` and ``*``)."""
    c = 0
    for b in body:
        c ^= b
    return c


def ascii_command(body: str, crc: bool = False) -> bytes:
    """``"VNRRG,05"`` → ``b"$VNRRG,05*5D\\r\\n"`` (XOR-8, or CRC-16 with ``crc=True``)."""
    raw = body.encode("ascii")
    check = f"{crc16(raw):04X}" if crc else f"{xor8(raw):02X}"
    return b"$" + raw + b"*" + check.encode() + b"\r\n"


# ------------------------------------------------------------------------- ASCII messages


@dataclass(frozen=True)
class YmrMessage:
    """``$VNYMR``: yaw, pitch, roll (deg), magnetic (Gauss), acceleration (m/s²), rate (rad/s)."""

    yaw: float
    pitch: float
    roll: float
    mag: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray


@dataclass(frozen=True)
class QmrMessage:
    """``$VNQMR``: quaternion (sent x, y, z, w; kept here w first), mag, accel, gyro."""

    quaternion_wxyz: np.ndarray
    mag: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray


@dataclass(frozen=True)
class ImuMessage:
    """``$VNIMU``: uncompensated mag, accel, gyro, temperature (°C), pressure (kPa)."""

    mag: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    temperature: float
    pressure: float


@dataclass(frozen=True)
class YprAccelRateMessage:
    """``$VNYBA`` (body acceleration) / ``$VNYIA`` (inertial NED acceleration)."""

    header: str
    yaw: float
    pitch: float
    roll: float
    accel: np.ndarray
    gyro: np.ndarray


@dataclass(frozen=True)
class RateMessage:
    """``$VNGYR`` (rate) and ``$VNMAR`` (mag, accel, rate): the angular rate in rad/s."""

    header: str
    gyro: np.ndarray
    accel: np.ndarray | None = None
    mag: np.ndarray | None = None


@dataclass(frozen=True)
class DeltaMessage:
    """``$VNDTV``: Δt (s), Δθ (deg, as sent), Δv (m/s) integrated since the last output."""

    dt: float
    dtheta_deg: np.ndarray
    dvel: np.ndarray

    @property
    def gyro(self) -> np.ndarray:
        """The mean angular rate over the interval (rad/s); NaN for an empty interval."""
        if not self.dt > 0:
            return np.full(3, np.nan)
        return np.asarray(np.radians(self.dtheta_deg) / self.dt, dtype=np.float64)

    @property
    def accel(self) -> np.ndarray | None:
        """The mean specific force over the interval, Δv/Δt (m/s²); None for an empty one."""
        if not self.dt > 0:
            return None
        return np.asarray(self.dvel, dtype=np.float64) / self.dt


@dataclass(frozen=True)
class RegisterReply:
    """``$VNRRG`` / ``$VNWRG`` reply: the register and its values, as sent."""

    command: str
    register: int
    values: tuple[str, ...]


@dataclass(frozen=True)
class ErrorReply:
    """``$VNERR,<code>``: the sensor refused the last command."""

    code: int

    @property
    def meaning(self) -> str:
        return ERROR_CODES.get(self.code, f"unknown error {self.code}")


@dataclass(frozen=True)
class AsciiMessage:
    """Any other message with a valid check: command echoes (``$VNASY,0``), asynchronous
    outputs that carry no angular rate (``$VNYPR``, ``$VNQTN``, ``$VNGPS``, …) and headers no
    manual lists (``known`` False). Kept as sent."""

    header: str
    fields: tuple[str, ...]
    known: bool = True


#: the asynchronous output types of the VN-100 / VN-200 / VN-300 manuals (register 6), with
#: the number of fields of those that carry an angular rate
ASYNC_RATE_FIELDS = {
    "VNYMR": 12,
    "VNQMR": 13,
    "VNIMU": 11,
    "VNYBA": 9,
    "VNYIA": 9,
    "VNGYR": 3,
    "VNMAR": 9,
    "VNDTV": 7,
}
ASYNC_OTHER = frozenset(
    {
        "VNYPR",  # yaw, pitch, roll
        "VNQTN",  # quaternion
        "VNMAG",  # magnetic
        "VNACC",  # acceleration
        "VNGPS",  # GNSS LLA
        "VNGPE",  # GNSS ECEF
        "VNINS",  # INS LLA
        "VNINE",  # INS ECEF
        "VNISL",  # INS LLA, second solution layout
        "VNISE",  # INS ECEF, second solution layout
        "VNG2S",  # GNSS2 LLA
        "VNG2E",  # GNSS2 ECEF
        "VNHVE",  # heave and heave rate
    }
)
#: replies and command echoes (no data)
REPLIES = frozenset(
    {"VNASY", "VNWNV", "VNRFS", "VNRST", "VNCMD", "VNTAR", "VNKMD", "VNKAD", "VNSGB", "VNFWU"}
)


# ------------------------------------------------------------------------------- parser


@dataclass
class ParserStats:
    """Counts of what the parser saw; rejected packets by cause."""

    bytes_in: int = 0
    packets_ok: int = 0
    ascii_ok: int = 0
    binary_ok: int = 0
    garbage_bytes: int = 0  # skipped while looking for a sync byte
    bad_checksum: int = 0  # ASCII XOR-8 mismatch
    bad_crc: int = 0  # ASCII CRC-16 or binary CRC-16 mismatch
    malformed: int = 0  # a valid check, but a data message whose fields do not parse
    too_long: int = 0  # a ``$`` with no line end within the longest message
    bad_binary_header: int = 0  # 0xFA followed by a group byte or mask no sensor sends
    unknown_field: int = 0  # 0xFA and a mask naming a reserved bit (size unknown)
    truncated: int = 0  # a packet cut short at the end of the stream (``close``)
    headless_line: int = 0  # the end of an ASCII line whose start was lost (``…*CS\r\n``)
    other_ascii: int = 0  # a valid check on a header no VectorNav manual lists: another
    # device sharing the line (NMEA ``$GPRMC``), or a newer firmware's message (kept, unused)
    unchecked: int = 0  # ``*XX``: the sensor's error detection is off; never trusted
    #: reserved bits seen in packet headers ("Imu bit 13": count): a sensor configured with a
    #: field this driver cannot size shows one name at the packet rate; garbage shows many
    unknown_field_bits: Counter[str] = dc_field(default_factory=Counter)

    @property
    def rejected(self) -> int:
        return (
            self.bad_checksum
            + self.bad_crc
            + self.malformed
            + self.too_long
            + self.bad_binary_header
            + self.unknown_field
            + self.truncated
            + self.headless_line
            + self.unchecked
        )

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k != "unknown_field_bits"}
        out["unknown_field_bits"] = dict(self.unknown_field_bits)
        return out


_ASCII_MAX = 512
# The end of an ASCII message: its check and line end. Seen inside garbage, it is a line whose
# start was lost (the stream was opened mid-line, or the ``$`` was corrupted).
_LINE_TAIL = re.compile(rb"\*(?:[0-9A-Fa-f]{4}|[0-9A-Fa-f]{2})\r?\n")
_TAIL_KEEP = 7  # longest tail ``*XXXX\r\n``
_HEX = set(b"0123456789ABCDEFabcdef")
#: no binary packet is longer (the GNSS satellite and measurement lists are the longest part)
_BINARY_MAX = 16384


class Vn100Parser:
    """Incremental parser of a VN-100 byte stream (ASCII and binary interleaved)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._garbage_tail = b""  # the last garbage bytes, to find a line tail split by feeds
        self._base = 0  # stream offset of ``_buf[0]``
        self._rejected_line_end = -1  # stream offset of the LF of the last rejected ASCII line
        self.stats = ParserStats()

    def feed(self, data: bytes) -> list[Any]:
        """Add bytes; return every complete packet found, in order."""
        self.stats.bytes_in += len(data)
        self._buf += data
        out: list[Any] = []
        buf = self._buf
        i = 0
        n = len(buf)
        while i < n:
            b = buf[i]
            if b != 0x24 and b != 0xFA:  # '$' or 0xFA
                j = i + 1
                while j < n and buf[j] != 0x24 and buf[j] != 0xFA:
                    j += 1
                self.stats.garbage_bytes += j - i
                self._count_headless(bytes(buf[i:j]), self._base + j)
                i = j
                continue
            self._garbage_tail = b""
            step = self._ascii(buf, i, n, out) if b == 0x24 else self._binary(buf, i, n, out)
            if step == 0:  # need more bytes
                break
            i += step
        del buf[:i]
        self._base += i
        return out

    def _count_headless(self, run: bytes, run_end: int) -> None:
        """Count line tails in a garbage run ending at stream offset ``run_end`` (with the end
        of the previous run, if any), except the tail of a line already counted as rejected."""
        text = self._garbage_tail + run
        first = len(self._garbage_tail)  # tails ending before this were counted last time
        start = run_end - len(text)  # stream offset of text[0]
        self.stats.headless_line += sum(
            1
            for m in _LINE_TAIL.finditer(text)
            if m.end() > first and start + m.end() - 1 > self._rejected_line_end
        )
        self._garbage_tail = text[-_TAIL_KEEP:]

    def close(self) -> list[Any]:
        """End of stream: a pending partial packet is counted as truncated and dropped."""
        buf = self._buf
        if buf:
            if buf[0] in (0x24, 0xFA):
                self.stats.truncated += 1
            else:
                self.stats.garbage_bytes += len(buf)
                self._count_headless(bytes(buf), self._base + len(buf))
            buf.clear()
        return []

    # -- ASCII --------------------------------------------------------------------------

    def _ascii(self, buf: bytearray, i: int, n: int, out: list[Any]) -> int:
        end = buf.find(b"\n", i + 1, min(n, i + _ASCII_MAX))
        if end < 0:
            if n - i < _ASCII_MAX:
                return 0
            self.stats.too_long += 1
            return 1  # resume at the byte after the false sync
        step = self._ascii_line(buf, i, end, out)
        if step == 1:  # rejected: the rest of this line is not a separate headless line
            self._rejected_line_end = self._base + end
        return step

    def _ascii_line(self, buf: bytearray, i: int, end: int, out: list[Any]) -> int:
        line = bytes(buf[i + 1 : end])
        if line.endswith(b"\r"):
            line = line[:-1]
        star = line.rfind(b"*")
        if star < 0:
            self.stats.malformed += 1
            return 1
        body, check = line[:star], line[star + 1 :]
        if check == b"XX":  # error detection turned off on the sensor (register 30)
            self.stats.unchecked += 1
            return 1
        if len(check) == 2 and all(c in _HEX for c in check):
            if int(check, 16) != xor8(body):
                self.stats.bad_checksum += 1
                return 1
        elif len(check) == 4 and all(c in _HEX for c in check):
            if int(check, 16) != crc16(body):
                self.stats.bad_crc += 1
                return 1
        else:
            self.stats.malformed += 1
            return 1
        try:
            msg = _parse_ascii(body.decode("ascii"))
        except (ValueError, UnicodeDecodeError, IndexError):
            self.stats.malformed += 1
            return 1
        if isinstance(msg, AsciiMessage) and not msg.known:
            self.stats.other_ascii += 1
        out.append(msg)
        self.stats.packets_ok += 1
        self.stats.ascii_ok += 1
        return end + 1 - i

    # -- binary ---------------------------------------------------------------------------

    def _binary(self, buf: bytearray, i: int, n: int, out: list[Any]) -> int:
        try:
            found = binary.layout(buf, i, n)
        except binary.LayoutError as exc:
            if exc.unknown:
                self.stats.unknown_field += 1
                self.stats.unknown_field_bits.update(exc.unknown)
            else:
                self.stats.bad_binary_header += 1
            return 1  # resume at the byte after the false sync
        if found is None:
            return 0
        total = found.total
        if total > _BINARY_MAX:
            self.stats.bad_binary_header += 1
            return 1
        if n - i < total:
            # A packet is worth waiting for only while nothing complete follows its start: a
            # false sync in garbage must not hold back the real packets behind it.
            if self._complete_packet_within(buf, i + 1, n):
                self.stats.bad_binary_header += 1
                return 1
            return 0
        if crc16(memoryview(buf)[i + 1 : i + total]) != 0:  # CRC over all after 0xFA is 0
            self.stats.bad_crc += 1
            return 1
        out.append(binary.parse_packet(buf, i, found))
        self.stats.packets_ok += 1
        self.stats.binary_ok += 1
        return total

    def _complete_packet_within(self, buf: bytearray, start: int, end: int) -> bool:
        """Whether ``buf[start:end]`` holds a complete binary packet with a good CRC or a
        complete ASCII line with a good check."""
        j = start
        while True:
            j_bin = buf.find(b"\xfa", j, end)
            j_asc = buf.find(b"$", j, end)
            cands = [k for k in (j_bin, j_asc) if k >= 0]
            if not cands:
                return False
            j = min(cands)
            if buf[j] == 0xFA:
                try:
                    found = binary.layout(buf, j, end)
                except binary.LayoutError:
                    found = None
                size = found.total if found is not None else end + 1
                if size <= end - j and crc16(memoryview(buf)[j + 1 : j + size]) == 0:
                    return True
            else:
                stop = buf.find(b"\n", j + 1, min(end, j + _ASCII_MAX))
                star = buf.rfind(b"*", j + 1, stop) if stop > 0 else -1
                if star > 0:
                    check = bytes(buf[star + 1 : stop]).rstrip(b"\r")
                    body = bytes(buf[j + 1 : star])
                    if (len(check) == 2 and _hexval(check) == xor8(body)) or (
                        len(check) == 4 and _hexval(check) == crc16(body)
                    ):
                        return True
            j += 1


def _hexval(text: bytes) -> int:
    try:
        return int(text, 16)
    except ValueError:
        return -1


# The sensor writes numbers as sign, digits, point, digits ("+170.786", "-00.1957"). Anything
# else behind a valid checksum is corruption the XOR-8 check could not see (an even number
# of flips of the same bit cancels out in XOR): it is refused, not guessed at.
_NUMBER = re.compile(r"[+-]?\d+(\.\d+)?\Z")
_HEADER = re.compile(r"VN[A-Z0-9]{3}\Z")
_FOREIGN_HEADER = re.compile(r"[A-Z][A-Z0-9]{1,9}\Z")
_VALUE = re.compile(r"[0-9A-Za-z+\-.]*\Z")


def _floats(fields: list[str], k: int) -> list[float]:
    if not all(_NUMBER.match(f) for f in fields[:k]):
        raise ValueError("a field is not a number as the sensor writes them")
    return [float(f) for f in fields[:k]]


def _parse_ascii(body: str) -> Any:
    parts = body.split(",")
    header = parts[0]
    fields = parts[1:]
    if not _HEADER.match(header):
        if _FOREIGN_HEADER.match(header):  # another device on the line (NMEA, a logger)
            return AsciiMessage(header, tuple(fields), known=False)
        raise ValueError(f"not a header: {header!r}")
    if header in ASYNC_RATE_FIELDS:
        if len(fields) != ASYNC_RATE_FIELDS[header]:
            raise ValueError(f"{header} with {len(fields)} fields")
        v = _floats(fields, ASYNC_RATE_FIELDS[header])
        a = np.asarray(v)
        if header == "VNYMR":
            return YmrMessage(v[0], v[1], v[2], a[3:6], a[6:9], a[9:12])
        if header == "VNQMR":
            return QmrMessage(np.array([v[3], v[0], v[1], v[2]]), a[4:7], a[7:10], a[10:13])
        if header == "VNIMU":
            return ImuMessage(a[0:3], a[3:6], a[6:9], v[9], v[10])
        if header == "VNGYR":
            return RateMessage(header, a[0:3])
        if header == "VNMAR":
            return RateMessage(header, a[6:9], accel=a[3:6], mag=a[0:3])
        if header == "VNDTV":
            return DeltaMessage(v[0], a[1:4], a[4:7])
        return YprAccelRateMessage(header, v[0], v[1], v[2], a[3:6], a[6:9])
    if header in ("VNRRG", "VNWRG"):
        if not fields or not fields[0].isdigit() or not all(_VALUE.match(f) for f in fields):
            raise ValueError("register reply without a register")
        return RegisterReply(header, int(fields[0]), tuple(fields[1:]))
    if header == "VNERR":
        if len(fields) != 1 or not fields[0].isdigit():
            raise ValueError("error reply without a code")
        return ErrorReply(int(fields[0]))
    if not all(_VALUE.match(f) for f in fields):
        raise ValueError(f"{header} with a field the sensor does not write")
    return AsciiMessage(header, tuple(fields), header in ASYNC_OTHER or header in REPLIES)


# ------------------------------------------------------------------------------- device

#: binary output fields we ask for (common group): TimeStartup, YawPitchRoll, AngularRate,
#: Accel, MagPres (the compensated magnetic field: the compass, issue 18) — bits 0, 3, 5, 8, 10
MAG_PRES = 1 << 10
COMMON_FIELDS = (1 << 0) | (1 << 3) | (1 << 5) | (1 << 8) | MAG_PRES
#: the common-group fields asked for per ``imu.gyro_source``: TimeStartup, YawPitchRoll, the
#: rate (AngularRate + Accel; Imu = uncompensated accel + gyro; Deltas = Δt, Δθ, Δv, whose
#: Δv/Δt is the acceleration), MagPres
COMMON_FIELDS_FOR = {
    "auto": COMMON_FIELDS,
    "angular_rate": COMMON_FIELDS,
    "uncomp_gyro": (1 << 0) | (1 << 3) | (1 << 9) | MAG_PRES,
    "delta_theta": (1 << 0) | (1 << 3) | (1 << 11) | MAG_PRES,  # accel: Δv/Δt
}


class Vn100Error(RuntimeError):
    """The VN-100 could not be reached or configured (the message says what happened)."""


class Vn100CommandError(Vn100Error):
    """The sensor answered ``$VNERR`` to a command."""

    def __init__(self, command: str, code: int) -> None:
        self.command = command
        self.code = code
        self.meaning = ERROR_CODES.get(code, f"unknown error {code}")
        super().__init__(f"VN-100 refused {command!r}: error {code} ({self.meaning})")


@dataclass
class DriverStats:
    samples: int = 0
    reconnects: int = 0
    reconfigurations: int = 0
    read_errors: int = 0
    last_error: str = ""
    baudrate: int = 0
    #: CPU time (s) of the event loop's thread reading the port, parsing and delivering —
    #: ``on_sample`` included (its consumer may count its own share apart)
    loop_read_cpu_s: float = 0.0


#: where the angular rate may come from (``imu.gyro_source``), each with the binary fields
#: that carry it, in the order they are looked for; ``auto`` tries them in this order
GYRO_SOURCES: dict[str, tuple[str, ...]] = {
    "angular_rate": ("Common.AngularRate", "Imu.AngularRate"),  # calibrated, compensated
    "uncomp_gyro": ("Imu.UncompGyro", "Common.Imu"),  # factory calibration only
    "delta_theta": ("Imu.DeltaTheta", "Common.Deltas"),  # integrated angle over Δt
}
_ACCEL_FIELDS = ("Common.Accel", "Imu.Accel", "Imu.UncompAccel", "Common.Imu")
#: the magnetic field (T, decoded), compensated first
_MAG_FIELDS = ("Imu.Mag", "Common.MagPres", "Imu.UncompMag")
GAUSS_T = 1e-4
_TIME_FIELDS = ("Common.TimeStartup", "Time.TimeStartup")
#: which ASCII asynchronous outputs carry which kind of angular rate
_ASCII_GYRO_KIND = {"VNIMU": "uncomp_gyro", "VNDTV": "delta_theta"}  # the rest: angular_rate


@dataclass
class ExtractStats:
    samples: int = 0
    unused: int = 0  # checksum-valid messages with no angular rate of the selected kind
    empty_interval: int = 0  # delta-theta with Δt ≤ 0


def device_time_ns(item: Any) -> int | None:
    """The sensor's ``TimeStartup`` (ns) in a binary packet, if it carries one."""
    if isinstance(item, BinaryPacket):
        found = item.first(_TIME_FIELDS)
        return None if found is None else int(found[1])
    return None


class ImuExtractor:
    """IMU samples from parsed VN-100 messages: the angular rate of ``gyro_source`` (one of
    :data:`GYRO_SOURCES`, or ``auto``: the first the sensor sends, compensated before
    uncompensated before integrated), the acceleration if there is one, and ``TimeStartup``.
    Messages with no such rate (``$VNYPR``, attitude-only packets, replies) count as unused."""

    def __init__(self, gyro_source: str = "auto") -> None:
        if gyro_source != "auto" and gyro_source not in GYRO_SOURCES:
            allowed = ", ".join(("auto", *GYRO_SOURCES))
            raise ValueError(f"gyro source {gyro_source!r} is not one of {allowed}")
        self.gyro_source = gyro_source
        kinds = list(GYRO_SOURCES) if gyro_source == "auto" else [gyro_source]
        self._binary_fields = tuple(name for k in kinds for name in GYRO_SOURCES[k])
        self._ascii_kinds = frozenset(kinds)
        self.stats = ExtractStats()

    def sample(
        self, item: Any, host_ns: int, t: float | None = None, device_ns: int | None = None
    ) -> ImuSample | None:
        """An :class:`ImuSample` (IMU frame, ``t`` = arrival on the host clock unless given:
        the driver maps the device time), or None. ``device_ns``: the packet's
        ``TimeStartup`` when the caller has it already."""
        gyro = accel = mag = None
        if isinstance(item, BinaryPacket):
            found = item.first(self._binary_fields)
            if found is not None:
                gyro = self._rate(*found)
                accel = _mean_specific_force(item, found)
                if accel is None:
                    acc = item.first(_ACCEL_FIELDS)
                    if acc is not None:
                        accel = acc[1][:3]
                field = item.first(_MAG_FIELDS)
                if field is not None:
                    mag = np.asarray(field[1][:3], dtype=np.float64)
        elif isinstance(
            item,
            YmrMessage | QmrMessage | ImuMessage | YprAccelRateMessage | RateMessage | DeltaMessage,
        ):
            header = getattr(item, "header", None) or _ascii_header(item)
            if _ASCII_GYRO_KIND.get(header, "angular_rate") in self._ascii_kinds:
                gyro = item.gyro
                accel = getattr(item, "accel", None)
                gauss = getattr(item, "mag", None)
                mag = None if gauss is None else np.asarray(gauss, dtype=np.float64) * GAUSS_T
                if isinstance(item, DeltaMessage) and not item.dt > 0:
                    self.stats.empty_interval += 1
                    return None
        if gyro is None:
            if not isinstance(item, RegisterReply | ErrorReply) and not (
                isinstance(item, AsciiMessage) and item.header in REPLIES
            ):
                self.stats.unused += 1
            return None
        self.stats.samples += 1
        if mag is not None and not math.isfinite(sum(mag.tolist())):
            mag = None
        return ImuSample(
            t=host_ns * 1e-9 if t is None else t,
            gyro=gyro,
            accel=accel,
            device_time_ns=device_time_ns(item) if device_ns is None else device_ns,
            host_time_ns=host_ns,
            mag=mag,
        )

    def _rate(self, name: str, value: Any) -> np.ndarray | None:
        v = np.asarray(value, dtype=np.float64)
        if name == "Common.Imu":
            return v[3:6]
        if name in ("Imu.DeltaTheta", "Common.Deltas"):
            dt = v[0]
            if not dt > 0:
                self.stats.empty_interval += 1
                return np.full(3, np.nan)
            rate: np.ndarray = v[1:4] / dt
            return rate
        return v


def _mean_specific_force(item: BinaryPacket, found: tuple[str, Any]) -> np.ndarray | None:
    """With an integrated angle, the matching integrated velocity over the same Δt: Δv/Δt
    (``Common.Deltas`` carries both; ``Imu.DeltaTheta`` pairs with ``Imu.DeltaVel``), the
    mean specific force the mean rate Δθ/Δt belongs with; None otherwise."""
    name, value = found
    if name == "Common.Deltas":
        dt, dv = value[0], value[4:7]
    elif name == "Imu.DeltaTheta" and "Imu.DeltaVel" in item.offsets:
        dt, dv = value[0], item.get("Imu.DeltaVel")
    else:
        return None
    if not dt > 0:
        return None
    force: np.ndarray = np.asarray(dv, dtype=np.float64) / dt
    return force


def _ascii_header(item: Any) -> str:
    return {
        YmrMessage: "VNYMR",
        QmrMessage: "VNQMR",
        ImuMessage: "VNIMU",
        DeltaMessage: "VNDTV",
    }[type(item)]


def imu_sample_from(item: Any, host_ns: int, clock: ClockSync | None = None) -> ImuSample | None:
    """An :class:`ImuSample` from a parsed message with any kind of angular rate (``auto``);
    with ``clock``, a device ``TimeStartup`` is mapped onto the host clock."""
    sample = ImuExtractor().sample(item, host_ns)
    if sample is None or clock is None or sample.device_time_ns is None:
        return sample
    t = clock.update(sample.device_time_ns, host_ns * 1e-9)
    return ImuSample(t, sample.gyro, sample.accel, sample.device_time_ns, host_ns, sample.mag)


def _why_denied(exc: OSError) -> str:
    """What to change when the port may not be opened: the port's group (EACCES), or a
    device policy (EPERM: the systemd unit's ``DevicePolicy=closed`` allows USB serial
    adapters only, not a computer's own UART)."""
    if exc.errno == errno.EACCES:
        return (
            " (the service's user needs the port's group, usually dialout: "
            "SupplementaryGroups= in the systemd unit)"
        )
    if exc.errno == errno.EPERM:
        return (
            " (a device policy forbids it: the systemd unit allows only USB serial adapters, "
            "char-ttyUSB and char-ttyACM; for a UART such as /dev/ttyAMA0 or /dev/ttyS0 add "
            "DeviceAllow=char-ttyAMA rw or DeviceAllow=char-ttyS rw in a drop-in: "
            "systemd/README.md)"
        )
    return ""


class Vn100(ThreadedDevice):
    """The VN-100 on a serial port: configure, read in a thread, reconnect (see the module doc)."""

    thread_name = "vn100"

    def __init__(
        self,
        port: str,
        baudrate: int = 921600,
        initial_baudrate: int = 115200,
        rate_hz: int = 100,
        output: str = "binary",
        low_latency: bool = True,
        reconnect_max_backoff_s: float = 5.0,
        on_sample: Callable[[ImuSample], None] | None = None,
        clock: ClockSync | None = None,
        on_raw: Callable[[bytes, int], None] | None = None,
        serial_factory: Callable[..., Any] | None = None,
        gyro_source: str = "auto",
        configure_sensor: bool = True,
    ) -> None:
        super().__init__()
        if baudrate not in BAUDRATES or initial_baudrate not in BAUDRATES:
            raise ValueError(f"baud rates must be one of {BAUDRATES}")
        if 800 % rate_hz:
            raise ValueError("rate_hz must divide 800 (the VN-100's internal rate)")
        self.port = port
        self.baudrate = baudrate
        self.initial_baudrate = initial_baudrate
        self.rate_hz = rate_hz
        self.output = output
        self.low_latency = low_latency
        self.reconnect_max_backoff_s = reconnect_max_backoff_s
        self.on_sample = on_sample
        self.on_raw = on_raw  # every chunk of bytes as read, with its host time (recording)
        self.clock = clock or ClockSync(device_unit_s=1e-9)
        self.parser = Vn100Parser()
        self.extractor = ImuExtractor(gyro_source)
        self.configure_sensor = configure_sensor
        self.stats = DriverStats()
        self._serial: Any = None
        self._factory = serial_factory
        self._pending: list[tuple[Any, int]] = []  # async packets read while waiting for replies
        self._low_latency_warned = False
        self._warned_fields: set[str] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_fd: int | None = None  # the descriptor the loop watches, while it does
        self._loop_lost = threading.Event()
        self._last_t = -math.inf
        self._rate_since: tuple[int, int] | None = None  # (host ns, samples) at the first
        self._rate_checked = False

    # -- connection -------------------------------------------------------------------------

    def _open_port(self, baud: int) -> Any:
        import serial

        factory = self._factory or serial.Serial
        ser = factory(self.port, baudrate=baud, timeout=0.02, write_timeout=1.0)
        if self.low_latency and hasattr(ser, "set_low_latency_mode"):
            try:
                ser.set_low_latency_mode(True)
            except (OSError, ValueError, AttributeError) as exc:
                if not self._low_latency_warned:
                    log.info("vn100: %s has no low-latency mode (%s)", self.port, exc)
                    self._low_latency_warned = True
        return ser

    def open(self) -> None:
        """Open the port at whichever baud rate the sensor answers, then configure it."""
        self.close()
        tried = []
        for baud in dict.fromkeys((self.baudrate, self.initial_baudrate, *BAUDRATES)):
            tried.append(baud)
            try:
                self._serial = self._open_port(baud)
            except OSError as exc:
                raise Vn100Error(f"cannot open {self.port}: {exc}{_why_denied(exc)}") from exc
            self.parser = Vn100Parser()
            try:
                self.command("VNASY,0", timeout=0.3, retries=1)
                self.stats.baudrate = baud
                break
            except (Vn100Error, OSError):
                self.close()
        else:
            raise Vn100Error(f"no VN-100 answers on {self.port} at {tried} baud")
        if self.configure_sensor:
            self.configure()
        else:  # the user's own output configuration, as it is: only resume it
            self.command("VNASY,1")
            self.stats.reconfigurations += 1

    def configure(self) -> None:
        """Pause output, switch baud, set the output registers, verify, resume."""
        self.command("VNASY,0")
        if self.stats.baudrate != self.baudrate:
            # the reply to the baud change comes at the old rate; then the port follows
            self.command(f"VNWRG,05,{self.baudrate}", expect=("VNWRG", 5, (str(self.baudrate),)))
            self._serial.baudrate = self.baudrate
            self.stats.baudrate = self.baudrate
            time.sleep(0.02)
            self._serial.reset_input_buffer()
        reply = self.command("VNRRG,05")
        if not reply.values or int(reply.values[0]) != self.baudrate:
            raise Vn100Error(
                f"VN-100 reports baud {reply.values} after switching to {self.baudrate}"
            )
        divisor = 800 // self.rate_hz
        if self.output == "binary":
            fields = COMMON_FIELDS_FOR[self.extractor.gyro_source]
            self.command("VNWRG,06,0", expect=("VNWRG", 6, ("0",)))
            self.command(
                f"VNWRG,75,1,{divisor},01,{fields:04X}",
                expect=("VNWRG", 75, ("1", str(divisor), "01", f"{fields:04X}")),
            )
        else:
            self.command("VNWRG,75,0,0,00", expect=("VNWRG", 75, ("0", "0", "00")))
            self.command("VNWRG,06,14", expect=("VNWRG", 6, ("14",)))
            self.command(f"VNWRG,07,{self.rate_hz}", expect=("VNWRG", 7, (str(self.rate_hz),)))
        self.command("VNASY,1")
        self.stats.reconfigurations += 1

    def close(self) -> None:
        if self._serial is not None:
            with contextlib.suppress(Exception):
                self._serial.close()
        self._serial = None

    # -- commands ---------------------------------------------------------------------------

    def command(
        self,
        body: str,
        timeout: float = 0.5,
        retries: int = 2,
        expect: tuple[str, int, tuple[str, ...]] | None = None,
    ) -> Any:
        """Send ``$<body>*CS`` and wait for its reply; ``$VNERR`` raises
        :class:`Vn100CommandError`; async packets meanwhile are kept for the reader."""
        header = body.split(",")[0]
        reg = int(body.split(",")[1]) if header in ("VNRRG", "VNWRG") else None
        for _attempt in range(retries + 1):
            self._serial.write(ascii_command(body))
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                data = self._serial.read(4096)
                if not data:
                    continue
                now = time.monotonic_ns()
                if self.on_raw is not None:
                    self.on_raw(data, now)
                for item in self.parser.feed(data):
                    if isinstance(item, ErrorReply):
                        raise Vn100CommandError(body, item.code)
                    if (
                        isinstance(item, RegisterReply)
                        and item.command == header
                        and item.register == reg
                    ):
                        if expect is not None and item.values[: len(expect[2])] != expect[2]:
                            raise Vn100Error(f"VN-100 answered {item} to {body!r}")
                        return item
                    if isinstance(item, AsciiMessage) and item.header == header:
                        return item
                    self._pending.append((item, now))
        raise Vn100Error(f"no reply from the VN-100 on {self.port} to {body!r}")

    # -- reading ----------------------------------------------------------------------------

    def _deliver(self, batch: list[tuple[Any, int]]) -> None:
        """Map a batch's device times (all of it updates the clock first, so packets that
        arrived together are spread by their device stamps) and deliver its samples."""
        devs = [device_time_ns(item) for item, _ in batch]
        for (_, host_ns), dev in zip(batch, devs, strict=True):
            if dev is not None:
                self.clock.update(dev, host_ns * 1e-9)
        for (item, host_ns), dev in zip(batch, devs, strict=True):
            t = None
            if dev is not None and self.clock.synced:
                # never backwards, even while syncing
                t = max(self.clock.to_host(dev), self._last_t + 1e-6)
            sample = self.extractor.sample(item, host_ns, t, dev)
            if sample is None or not sample.finite:
                continue
            self._last_t = sample.t
            self.stats.samples += 1
            self._check_rate(host_ns)
            if self.on_sample is not None:
                self.on_sample(sample)

    #: how long the sensor's own rate is measured before it is compared with ``rate_hz`` (s)
    RATE_CHECK_S = 5.0

    def _check_rate(self, host_ns: int) -> None:
        """Say once if the sensor sends far from ``rate_hz`` (half or twice): the staleness
        limit is checked against that rate, and the estimation's CPU grows with the real one
        (a sensor that keeps its own output, ``imu.configure_sensor: false``, at 400 Hz)."""
        if self._rate_checked:
            return
        if self._rate_since is None:
            self._rate_since = (host_ns, self.stats.samples)
            return
        t0, n0 = self._rate_since
        seconds = (host_ns - t0) * 1e-9
        if seconds < self.RATE_CHECK_S:
            return
        self._rate_checked = True
        rate = (self.stats.samples - n0) / seconds
        if 0.5 * self.rate_hz <= rate <= 2.0 * self.rate_hz:
            return
        kept = (
            "was configured for it"
            if self.configure_sensor
            else "keeps its own output: imu.configure_sensor false"
        )
        log.warning(
            "vn100: the sensor sends %.0f samples a second, imu.rate_hz says %d (it %s): the "
            "staleness limit is judged against imu.rate_hz, the estimation's CPU grows with "
            "the real rate; set imu.rate_hz to what the sensor sends",
            rate,
            self.rate_hz,
            kept,
        )

    def read_once(self) -> int:
        """Read what has arrived and deliver its samples; returns the bytes read."""
        if self._pending:
            self._deliver(self._pending)
            self._pending = []
        data = self._read_available()
        if data:
            self.feed(data, time.monotonic_ns())
        return len(data)

    def feed(self, data: bytes, host_ns: int) -> None:
        """Bytes read at host time ``host_ns`` → samples (also how a replay feeds recorded
        serial bytes through this same code)."""
        if self.on_raw is not None:
            self.on_raw(data, host_ns)
        self._deliver([(item, host_ns) for item in self.parser.feed(data)])
        self._warn_unknown_fields()

    def _warn_unknown_fields(self) -> None:
        """A field the sensor sends at its output rate that no manual sizes: say which, once
        (a few in garbage are noise; ten of the same are the sensor's configuration)."""
        for name, count in self.parser.stats.unknown_field_bits.items():
            if count >= 10 and name not in self._warned_fields:
                self._warned_fields.add(name)
                log.warning(
                    "vn100: packets with a field of unknown size (%s) are refused; turn it "
                    "off in the sensor's binary output register (75-77)",
                    name,
                )

    def _read_available(self) -> bytes:
        """Wait (up to the port timeout) for data, then take all there is. ``read(4096)``
        would wait for 4096 bytes or the timeout, delaying every packet; on a real port one
        ``select`` + one ``read`` per wake-up is also the cheapest (the daemon reads 100
        packets a second)."""
        ser = self._serial
        try:
            fd = ser.fileno()
        except (AttributeError, OSError, ValueError):  # a port object without a descriptor
            data = bytes(ser.read(1))
            waiting = ser.in_waiting if data else 0
            return data + bytes(ser.read(min(waiting, 65536))) if waiting else data
        ready, _, _ = select.select([fd], [], [], ser.timeout or 0.02)
        if not ready:
            return b""
        data = os.read(fd, 65536)
        if not data:  # readable but nothing: the device went away (USB unplugged)
            raise OSError("the serial device reports data but returns none (disconnected?)")
        return data

    def _run(self) -> None:
        """Read until :meth:`stop`; reconnect with exponential backoff when the port fails."""
        backoff = 0.1
        while not self._stop.is_set():
            if self._serial is None:
                try:
                    self.open()
                    backoff = 0.1
                    log.info("vn100: connected on %s at %d baud", self.port, self.stats.baudrate)
                except (Vn100Error, OSError) as exc:
                    self.stats.last_error = str(exc)
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, self.reconnect_max_backoff_s)
                    continue
            if self._loop is not None and self._read_on_loop():
                continue
            try:
                self.read_once()
            except Exception as exc:  # serial.SerialException, OSError: the port went away
                self._note_lost(exc)
                self.close()

    def _note_lost(self, exc: BaseException) -> None:
        self.stats.read_errors += 1
        self.stats.reconnects += 1
        self.stats.last_error = f"{type(exc).__name__}: {exc}"
        log.warning("vn100: %s lost (%s); reconnecting", self.port, exc)

    def _read_on_loop(self) -> bool:
        """Hand the open port to the event loop and wait until the loop finds it lost (the
        thread then reconnects) or the driver stops; False for a port without a descriptor
        (read here, as without a loop)."""
        loop = self._loop
        try:
            fd = self._serial.fileno()
        except (AttributeError, OSError, ValueError):
            return False
        assert loop is not None
        self._loop_lost.clear()
        try:
            loop.call_soon_threadsafe(self._watch_on_loop, fd)
        except RuntimeError:  # the loop is closed: nothing will read any more
            self._stop.wait()
            return True
        while not self._stop.is_set() and not self._loop_lost.wait(0.5):
            pass
        if self._loop_lost.is_set():
            self.close()
        return True

    def _watch_on_loop(self, fd: int) -> None:
        assert self._loop is not None
        if self._stop.is_set() or self._serial is None:
            return
        self._loop_fd = fd
        self._loop.add_reader(fd, self._readable, fd)

    def _unwatch(self) -> None:
        fd, self._loop_fd = self._loop_fd, None
        if fd is not None and self._loop is not None:
            self._loop.remove_reader(fd)

    def _readable(self, fd: int) -> None:
        """On the loop: the port has bytes (or failed). A failure is handed to the thread,
        which reconnects; an exception from a sample's consumer is not the port's and goes
        to the loop (the daemon's handler halts)."""
        started = time.thread_time()
        try:
            self._read_on_loop_once(fd)
        finally:
            self.stats.loop_read_cpu_s += time.thread_time() - started

    def _read_on_loop_once(self, fd: int) -> None:
        """:meth:`_readable`'s work: what waits, then what the port has."""
        try:
            if self._pending:
                pending, self._pending = self._pending, []
                self._deliver(pending)
            try:
                data = os.read(fd, 65536)
            except BlockingIOError:
                return
            if not data:
                raise OSError("the serial device reports data but returns none (disconnected?)")
        except OSError as exc:
            self._unwatch()
            self._note_lost(exc)
            self._loop_lost.set()  # the thread closes the port and reconnects
            return
        self.feed(data, time.monotonic_ns())

    def start(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Start reading: on this driver's thread, or — given the event loop the samples
        are for — on that loop, ``on_sample`` then being called on it (the thread only
        opens, configures and reopens the port)."""
        self._loop = loop
        self._start_thread()

    def stop(self) -> None:
        """Stop reading and close the port (in loop mode: call it on the loop)."""
        self._unwatch()
        super().stop()
        self.close()
