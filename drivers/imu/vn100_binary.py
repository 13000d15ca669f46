"""VN-100 binary output packets (docs/design.md §7): every group, every field, framing and CRC.

A packet is ``0xFA``, a group byte, one little-endian u16 field mask per group bit, the
payload (group order, then bit order, little-endian) and a CRC-16 over everything after
``0xFA``, appended big-endian. A parser can only skip a field it does not use if it knows its
length, so :data:`FIELDS` lists every field of every group with its layout, from VectorNav's
user manuals (VN-100, and VN-200/VN-300 for the GNSS, INS and GNSS2 groups a user may enable
on a sensor that shares the protocol):

* Common (group bit 0), Time (1), IMU (2), GNSS (3), Attitude (4), INS (5), GNSS2 (6);
* two GNSS fields are of variable length: SatInfo (``NumSats`` u8, a reserved byte, then 8
  bytes per satellite) and RawMeas (``Tow`` f64, ``Week`` u16, ``NumMeas`` u8, a reserved
  byte, then 28 bytes per measurement); their counts are read from the payload.

A packet whose masks name a field this table does not know (a reserved bit) is refused,
counted and reported by group and bit: its length, and so the next packet's start, cannot be
known. Fields are decoded lazily (:meth:`BinaryPacket.get`), in SI units: angles rad,
angular rates rad/s, magnetic field T, pressure Pa, times ns, temperature °C.
"""

from __future__ import annotations

import binascii
import functools
import math
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

GROUP_NAMES = ("Common", "Time", "Imu", "Gnss", "Attitude", "Ins", "Gnss2")
SYNC = 0xFA
#: the group byte's bit 7 is not a group in any VectorNav manual
VALID_GROUPS = (1 << len(GROUP_NAMES)) - 1

_DEG = math.pi / 180.0
_GAUSS = 1e-4  # T per Gauss
_KPA = 1000.0  # Pa per kPa


# ------------------------------------------------------------------------------------ CRC


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16, polynomial 0x1021, initial 0, not reflected ("XMODEM"): b"123456789" → 0x31C3
    (the standard library's CRC-CCITT, in C: a Python loop over each packet's bytes was the
    largest part of parsing one)."""
    return binascii.crc_hqx(data, crc)


# ---------------------------------------------------------------------------- field table


@dataclass(frozen=True)
class FieldSpec:
    """One field of one group: its name, byte layout and the factors to SI units.

    ``fmt`` is a little-endian :mod:`struct` format; ``scale`` multiplies the unpacked values
    (one factor for all, or one per value); ``None`` keeps integers as they are (counters,
    status words, dates). ``variable`` fields have a count in their payload (GNSS).
    """

    name: str
    fmt: str = ""
    scale: float | tuple[float, ...] | None = 1.0
    unit: str = ""
    variable: str = ""  # "satinfo" or "rawmeas"

    @property
    def size(self) -> int:
        return struct.calcsize(self.fmt) if self.fmt else 0


def _f(name: str, n: int, scale: float | tuple[float, ...] = 1.0, unit: str = "") -> FieldSpec:
    return FieldSpec(name, f"<{n}f" if n > 1 else "<f", scale, unit)


def _int(name: str, fmt: str, unit: str = "") -> FieldSpec:
    return FieldSpec(name, fmt, None, unit)


_TIME_NS = _int  # u64 nanoseconds
_UTC = FieldSpec("UTC", "<bBBBBBH", None, "year-2000, month, day, hour, min, s, ms")
_GNSS: dict[int, FieldSpec] = {
    0: _UTC,
    1: _TIME_NS("Tow", "<Q", "ns"),
    2: _int("Week", "<H"),
    3: _int("NumSats", "<B"),
    4: _int("Fix", "<B"),
    5: FieldSpec("PosLla", "<3d", (_DEG, _DEG, 1.0), "rad, rad, m"),
    6: FieldSpec("PosEcef", "<3d", 1.0, "m"),
    7: _f("VelNed", 3, 1.0, "m/s"),
    8: _f("VelEcef", 3, 1.0, "m/s"),
    9: _f("PosU", 3, 1.0, "m"),
    10: _f("VelU", 1, 1.0, "m/s"),
    11: _f("TimeU", 1, 1.0, "ns"),
    12: _int("TimeInfo", "<Bb", "status, leap seconds"),
    13: _f("Dop", 7),
    14: FieldSpec("SatInfo", "", None, variable="satinfo"),
    15: FieldSpec("RawMeas", "", None, variable="rawmeas"),
}

#: (group index, bit) → field. Sizes follow VectorNav's manuals; see the module doc.
FIELDS: dict[tuple[int, int], FieldSpec] = {}
for _bit, _spec in {
    0: _TIME_NS("TimeStartup", "<Q", "ns"),
    1: _TIME_NS("TimeGps", "<Q", "ns"),
    2: _TIME_NS("TimeSyncIn", "<Q", "ns"),
    3: _f("YawPitchRoll", 3, _DEG, "rad"),
    4: _f("Quaternion", 4, 1.0, "x, y, z, w"),
    5: _f("AngularRate", 3, 1.0, "rad/s"),
    6: FieldSpec("Position", "<3d", (_DEG, _DEG, 1.0), "rad, rad, m"),
    7: _f("Velocity", 3, 1.0, "m/s"),
    8: _f("Accel", 3, 1.0, "m/s²"),
    9: _f("Imu", 6, 1.0, "uncompensated accel m/s², gyro rad/s"),
    10: _f("MagPres", 5, (_GAUSS, _GAUSS, _GAUSS, 1.0, _KPA), "T, °C, Pa"),
    11: _f("Deltas", 7, (1.0, _DEG, _DEG, _DEG, 1.0, 1.0, 1.0), "s, rad, m/s"),
    12: _int("InsStatus", "<H"),
    13: _int("SyncInCnt", "<I"),
    14: _TIME_NS("TimeGpsPps", "<Q", "ns"),
}.items():
    FIELDS[(0, _bit)] = _spec
for _bit, _spec in {
    0: _TIME_NS("TimeStartup", "<Q", "ns"),
    1: _TIME_NS("TimeGps", "<Q", "ns"),
    2: _TIME_NS("GpsTow", "<Q", "ns"),
    3: _int("GpsWeek", "<H"),
    4: _TIME_NS("TimeSyncIn", "<Q", "ns"),
    5: _TIME_NS("TimeGpsPps", "<Q", "ns"),
    6: FieldSpec("TimeUTC", _UTC.fmt, None, _UTC.unit),
    7: _int("SyncInCnt", "<I"),
    8: _int("SyncOutCnt", "<I"),
    9: _int("TimeStatus", "<B"),
}.items():
    FIELDS[(1, _bit)] = _spec
for _bit, _spec in {
    0: _int("ImuStatus", "<H"),
    1: _f("UncompMag", 3, _GAUSS, "T"),
    2: _f("UncompAccel", 3, 1.0, "m/s²"),
    3: _f("UncompGyro", 3, 1.0, "rad/s"),
    4: _f("Temp", 1, 1.0, "°C"),
    5: _f("Pres", 1, _KPA, "Pa"),
    6: _f("DeltaTheta", 4, (1.0, _DEG, _DEG, _DEG), "s, rad"),
    7: _f("DeltaVel", 3, 1.0, "m/s"),
    8: _f("Mag", 3, _GAUSS, "T"),
    9: _f("Accel", 3, 1.0, "m/s²"),
    10: _f("AngularRate", 3, 1.0, "rad/s"),
    11: _int("SensSat", "<H"),
    12: _f("Raw", 10, 1.0, "raw mag, accel, gyro, temperature (factory use)"),
}.items():
    FIELDS[(2, _bit)] = _spec
for _bit, _spec in _GNSS.items():
    FIELDS[(3, _bit)] = _spec
    FIELDS[(6, _bit)] = _spec
for _bit, _spec in {
    0: _int("VpeStatus", "<H"),
    1: _f("YawPitchRoll", 3, _DEG, "rad"),
    2: _f("Quaternion", 4, 1.0, "x, y, z, w"),
    3: _f("DCM", 9, 1.0, "as sent"),
    4: _f("MagNed", 3, _GAUSS, "T"),
    5: _f("AccelNed", 3, 1.0, "m/s²"),
    6: _f("LinearAccelBody", 3, 1.0, "m/s²"),
    7: _f("LinearAccelNed", 3, 1.0, "m/s²"),
    8: _f("YprU", 3, _DEG, "rad"),
    9: _f("Reserved9", 3),  # sizes of bits 9–11 as in VectorNav's programming library
    10: _f("Reserved10", 7),
    11: _f("Reserved11", 6),
    12: _f("Heave", 3, 1.0, "heave m, heave rate m/s, delayed heave m"),
}.items():
    FIELDS[(4, _bit)] = _spec
for _bit, _spec in {
    0: _int("InsStatus", "<H"),
    1: FieldSpec("PosLla", "<3d", (_DEG, _DEG, 1.0), "rad, rad, m"),
    2: FieldSpec("PosEcef", "<3d", 1.0, "m"),
    3: _f("VelBody", 3, 1.0, "m/s"),
    4: _f("VelNed", 3, 1.0, "m/s"),
    5: _f("VelEcef", 3, 1.0, "m/s"),
    6: _f("MagEcef", 3, _GAUSS, "T"),
    7: _f("AccelEcef", 3, 1.0, "m/s²"),
    8: _f("LinearAccelEcef", 3, 1.0, "m/s²"),
    9: _f("PosU", 1, 1.0, "m"),
    10: _f("VelU", 1, 1.0, "m/s"),
    11: _f("Reserved11", 17),
    12: _f("Reserved12", 16),
}.items():
    FIELDS[(5, _bit)] = _spec

#: "Group.Field" → (group index, bit)
FIELD_INDEX: dict[str, tuple[int, int]] = {
    f"{GROUP_NAMES[g]}.{spec.name}": (g, bit) for (g, bit), spec in FIELDS.items()
}
#: per group, the mask of the bits this table knows
KNOWN_BITS = tuple(
    sum(1 << bit for (g, bit) in FIELDS if g == group) for group in range(len(GROUP_NAMES))
)
_SATINFO_HEAD, _SATINFO_EACH = 2, 8
_RAWMEAS_HEAD, _RAWMEAS_EACH = 12, 28


def field_size(group: int, bit: int) -> int:
    """Bytes of a fixed-size field (0 for unknown and variable-size ones)."""
    spec = FIELDS.get((group, bit))
    return spec.size if spec is not None else 0


# ------------------------------------------------------------------------------- packets


@dataclass(frozen=True)
class BinaryPacket:
    """A CRC-checked binary output packet. ``offsets`` maps each field's full name
    (``"Imu.UncompGyro"``) to its place in ``payload``; :meth:`get` decodes on demand."""

    groups: int
    masks: tuple[int, ...]
    payload: bytes
    offsets: Mapping[str, tuple[int, int]]

    def __contains__(self, name: str) -> bool:
        return name in self.offsets

    def __getitem__(self, name: str) -> Any:
        if name not in self.offsets:
            raise KeyError(name)
        return self.get(name)

    @property
    def field_names(self) -> tuple[str, ...]:
        return tuple(self.offsets)

    def raw(self, name: str) -> bytes:
        start, end = self.offsets[name]
        return self.payload[start:end]

    def get(self, name: str, default: Any = None) -> Any:
        """The field in SI units (a float, an int, a tuple of ints, or a float64 array)."""
        span = self.offsets.get(name)
        if span is None:
            return default
        return decode_field(FIELDS[FIELD_INDEX[name]], self.payload[span[0] : span[1]])

    def first(self, names: Iterable[str]) -> tuple[str, Any] | None:
        """The first of ``names`` this packet carries, decoded: (name, value)."""
        for name in names:
            if name in self.offsets:
                return name, self.get(name)
        return None


def decode_field(spec: FieldSpec, chunk: bytes) -> Any:
    """One field's bytes → its value in SI units."""
    if spec.variable == "satinfo":
        return {"NumSats": chunk[0], "bytes": chunk[_SATINFO_HEAD:]}
    if spec.variable == "rawmeas":
        tow, week, count = struct.unpack_from("<dHB", chunk)
        return {"Tow": tow, "Week": week, "NumMeas": count, "bytes": chunk[_RAWMEAS_HEAD:]}
    vals = struct.unpack(spec.fmt, chunk)
    scale = spec.scale
    if scale is None:
        return vals[0] if len(vals) == 1 else vals
    if len(vals) == 1:
        return float(vals[0]) * float(scale if isinstance(scale, float) else scale[0])
    out = np.array(vals, dtype=np.float64)
    if scale != 1.0:  # (most fields are in SI units already: no multiplication)
        out *= _scale_array(scale)
    return out


@functools.lru_cache(maxsize=64)
def _scale_array(scale: float | tuple[float, ...]) -> NDArray[np.float64]:
    return np.asarray(scale, dtype=np.float64)


class LayoutError(ValueError):
    """A packet header that no VectorNav sensor sends; ``unknown`` names reserved bits."""

    def __init__(self, message: str, unknown: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.unknown = unknown


@dataclass(frozen=True)
class Layout:
    """Where a binary packet's parts are: its length (sync byte to CRC), its header's
    (group byte and field masks), the masks, and each field's span in the payload."""

    total: int
    head: int
    masks: tuple[int, ...]
    offsets: Mapping[str, tuple[int, int]]


def layout(buf: bytes | bytearray, start: int, end: int) -> Layout | None:
    """The layout of the packet starting at ``buf[start] == 0xFA``, or None if more bytes
    are needed (``end``: bytes available). Raises :class:`LayoutError` for a header that
    cannot be a packet. A header whose fields all have a fixed size is worked out once
    (the sensor sends the same one at its output rate); a GNSS list's size is read from
    the packet's own bytes."""
    if end - start < 2:
        return None
    groups = buf[start + 1]
    if groups == 0:
        raise LayoutError("no group")
    if groups & ~VALID_GROUPS:
        raise LayoutError(f"group byte 0x{groups:02X} names a group no manual defines")
    head = 2 + 2 * bin(groups).count("1")
    if end - start < head:
        return None
    header = bytes(buf[start + 1 : start + head])
    fixed = _fixed_layout(header)
    if fixed is not None:
        return fixed
    return _walk(header, buf, start + head, end)


@functools.lru_cache(maxsize=16)
def _fixed_layout(header: bytes) -> Layout | None:
    """:func:`_walk` of a header whose fields all have a fixed size; None for one with a
    variable-size field (its layout depends on the payload)."""
    return _walk(header, None, 0, 0)


def _walk(header: bytes, buf: bytes | bytearray | None, pos: int, end: int) -> Layout | None:
    """The fields of ``header`` (group byte and masks) laid out from ``pos``, the payload's
    start in ``buf`` (``end``: bytes available). ``buf`` None: fixed-size fields only (None
    at a variable-size one)."""
    groups = header[0]
    active = [g for g in range(len(GROUP_NAMES)) if groups >> g & 1]
    masks = struct.unpack_from(f"<{len(active)}H", header, 1)
    offsets: dict[str, tuple[int, int]] = {}
    first = pos
    for g, mask in zip(active, masks, strict=True):
        if mask == 0:
            raise LayoutError(f"group {GROUP_NAMES[g]} with an empty field mask")
        unknown = mask & ~KNOWN_BITS[g]
        if unknown:
            bits = tuple(f"{GROUP_NAMES[g]} bit {b}" for b in range(16) if unknown >> b & 1)
            raise LayoutError("fields of unknown size: " + ", ".join(bits), bits)
        for bit in range(16):
            if not mask >> bit & 1:
                continue
            spec = FIELDS[(g, bit)]
            size = spec.size
            if spec.variable:
                if buf is None:  # the size is in the payload
                    return None
                if spec.variable == "satinfo":
                    if end - pos < 1:
                        return None
                    size = _SATINFO_HEAD + _SATINFO_EACH * buf[pos]
                else:  # "rawmeas"
                    if end - pos < 11:
                        return None
                    size = _RAWMEAS_HEAD + _RAWMEAS_EACH * buf[pos + 10]
            offsets[f"{GROUP_NAMES[g]}.{spec.name}"] = (pos - first, pos - first + size)
            pos += size
    head = 1 + len(header)
    total = head + (pos - first) + 2
    return Layout(total, head, tuple(masks), MappingProxyType(offsets))


def parse_packet(buf: bytes | bytearray, start: int, lay: Layout) -> BinaryPacket:
    """A :class:`BinaryPacket` from a packet whose layout and CRC were checked."""
    payload = bytes(buf[start + lay.head : start + lay.total - 2])
    return BinaryPacket(buf[start + 1], lay.masks, payload, lay.offsets)


def encode_packet(fields: Mapping[str, bytes]) -> bytes:
    """A packet from ``{"Group.Field": bytes}`` (the sensor side: mocks, tests, tools).
    Fields are put in group then bit order whatever the mapping's order."""
    by_place: dict[tuple[int, int], bytes] = {}
    for name, data in fields.items():
        if name not in FIELD_INDEX:
            raise KeyError(f"no VN-100 binary field {name!r}")
        g, bit = FIELD_INDEX[name]
        spec = FIELDS[(g, bit)]
        if not spec.variable and len(data) != spec.size:
            raise ValueError(f"{name} takes {spec.size} bytes, got {len(data)}")
        by_place[(g, bit)] = data
    groups = 0
    masks = [0] * len(GROUP_NAMES)
    for g, bit in by_place:
        groups |= 1 << g
        masks[g] |= 1 << bit
    body = bytearray([groups])
    for g in range(len(GROUP_NAMES)):
        if groups >> g & 1:
            body += struct.pack("<H", masks[g])
    for place in sorted(by_place):
        body += by_place[place]
    return bytes([SYNC]) + bytes(body) + struct.pack(">H", crc16(body))


def pack_values(name: str, values: Iterable[float] | float) -> bytes:
    """The bytes of field ``name`` holding ``values`` in the sensor's own units."""
    spec = FIELDS[FIELD_INDEX[name]]
    vals = [values] if isinstance(values, int | float) else list(values)
    if spec.scale is None:
        return struct.pack(spec.fmt, *(int(v) for v in vals))
    return struct.pack(spec.fmt, *vals)
