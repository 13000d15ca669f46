"""Ground speed over ISO 11783 / J1939 (docs/design.md §7): GBSD, WBSD and CCVS1.

* Ground-based (GBSD, PGN 65097) and wheel-based (WBSD, PGN 65096) speed and distance: bytes
  0–1 speed, 0.001 m/s per bit (0–64255 valid; 0xFExx error, 0xFFxx not available); bytes
  2–5 distance, 0.001 m per bit (0xFE…… error, 0xFF…… not available); byte 7 bits 1–2
  direction: 00 reverse, 01 forward, 10 error, 11 not available.
* Cruise Control/Vehicle Speed 1 (CCVS1, PGN 65265, SPN 84): bytes 1–2 wheel-based vehicle
  speed, 1/256 km/h per bit, same error / not-available ranges. It has no direction: the sign
  comes from the transmission's gear in ETC2 (PGN 61445: byte 3 current gear, byte 0 selected
  gear, offset −125, negative = reverse, 251 = park), or, if the user says the machine never
  reverses, is taken as forward (``speed.ccvs1_direction``).

Reserved bits are sent as 1 and are masked, never required. An error or "not available" speed
or direction gives a sample marked invalid, with a reason that names what the sensor said,
which message and which source address — never a number.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from drivers.can.isobus import PGN_CCVS1, PGN_ETC2, PGN_GBSD, PGN_WBSD, can_id, parse_id
from mowerhw.common.samples import SpeedSample

SPEED_MAX_RAW = 64255
DISTANCE_MAX_RAW = 0xFAFFFFFF
CCVS1_SCALE = 1.0 / 256.0 / 3.6  # m/s per bit (1/256 km/h)
#: PGN → (``speed.source`` name, message name as the halt reason shows it)
SPEED_PGNS = {
    PGN_GBSD: ("ground", "GBSD"),
    PGN_WBSD: ("wheel", "WBSD"),
    PGN_CCVS1: ("ccvs1", "CCVS1"),
}
SOURCES = ("ground", "wheel", "ccvs1", "any")
GEAR_OFFSET = -125
GEAR_PARK = 251
#: an ETC2 gear older than this does not sign a CCVS1 speed (ETC2 comes every 100 ms)
GEAR_MAX_AGE_S = 1.0


def _raw_kind(high_byte: int) -> str:
    return {0xFE: "error", 0xFF: "not available"}.get(high_byte, "out of range")


def decode_speed(arbitration_id: int, data: bytes, t: float | None = None) -> SpeedSample | None:
    """A :class:`SpeedSample` from a GBSD/WBSD/CCVS1 frame; None for any other frame. A CCVS1
    speed comes unsigned (positive, ``direction_known`` False): :class:`SpeedReader` signs it."""
    ident = parse_id(arbitration_id)
    found = SPEED_PGNS.get(ident.pgn)
    if found is None:
        return None
    source, message = found
    t = time.monotonic() if t is None else t
    data = bytes(data)

    def invalid(reason: str) -> SpeedSample:
        return SpeedSample(
            t,
            float("nan"),
            valid=False,
            source=source,
            source_address=ident.source,
            reason=reason,
            message=message,
        )

    if len(data) < 8:
        return invalid(f"a {len(data)}-byte frame (8 expected)")
    if source == "ccvs1":
        raw = data[1] | (data[2] << 8)
        if raw > SPEED_MAX_RAW:
            return invalid(_raw_kind(data[2]))
        return SpeedSample(
            t,
            raw * CCVS1_SCALE,
            valid=True,
            source=source,
            source_address=ident.source,
            message=message,
            direction_known=False,
        )
    raw_speed = data[0] | (data[1] << 8)
    raw_dist = int.from_bytes(data[2:6], "little")
    direction = data[7] & 0x03
    distance = raw_dist * 0.001 if raw_dist <= DISTANCE_MAX_RAW else None
    if raw_speed > SPEED_MAX_RAW:
        return invalid(_raw_kind(data[1]))
    if direction == 0b10:
        return invalid("a direction error")
    if direction == 0b11:
        return invalid("direction not available")
    speed = raw_speed * 0.001
    signed = speed if direction == 0b01 else -speed
    return SpeedSample(
        t,
        signed,
        valid=True,
        source=source,
        distance_m=distance,
        source_address=ident.source,
        message=message,
    )


def decode_gear(data: bytes) -> int | None:
    """The transmission gear in an ETC2 frame (current gear, else selected gear): negative
    is reverse, 0 neutral, :data:`GEAR_PARK` park; None if neither is available."""
    if len(data) < 4:
        return None
    for raw in (data[3], data[0]):
        if raw == GEAR_PARK:
            return GEAR_PARK
        if raw <= 250:
            return raw + GEAR_OFFSET
    return None


def encode_speed(
    speed_mps: float,
    distance_m: float | None = 0.0,
    source_address: int = 0x80,
    pgn: int = PGN_GBSD,
    error: bool = False,
) -> tuple[int, bytes]:
    """A GBSD/WBSD/CCVS1 frame (identifier, data): the sensor side of the wire."""
    if pgn == PGN_CCVS1:
        raw = 0xFE00 if error else min(round(abs(speed_mps) / CCVS1_SCALE), SPEED_MAX_RAW)
        data = bytes([0xFF]) + raw.to_bytes(2, "little") + bytes([0xFF] * 5)
        return can_id(6, pgn, source_address), data
    if error:
        raw_speed, direction = 0xFE00, 0b10
    else:
        raw_speed = min(round(abs(speed_mps) * 1000), SPEED_MAX_RAW)
        direction = 0b00 if speed_mps < 0 else 0b01
    raw_dist = 0xFFFFFFFF if distance_m is None else min(round(distance_m * 1000), DISTANCE_MAX_RAW)
    data = (
        raw_speed.to_bytes(2, "little")
        + raw_dist.to_bytes(4, "little")
        + bytes([0xFF, 0xFC | direction])
    )
    return can_id(3, pgn, source_address), data


def encode_gear(gear: int | None, source_address: int = 0x03) -> tuple[int, bytes]:
    """An ETC2 frame with ``gear`` as the current and the selected gear (None: not available)."""
    raw = 0xFF if gear is None else (GEAR_PARK if gear == GEAR_PARK else gear - GEAR_OFFSET)
    return can_id(6, PGN_ETC2, source_address), bytes(
        [raw, 0xFF, 0xFF, raw, 0xFF, 0xFF, 0xFF, 0xFF]
    )


@dataclass
class SpeedStats:
    frames: int = 0
    valid: int = 0
    invalid: int = 0
    wrong_source: int = 0
    other_frames: int = 0
    gear_frames: int = 0


class SpeedReader:
    """Which frames count as this mower's ground speed (``speed.source``,
    ``speed.sensor_address``), signed by ETC2 for CCVS1. Whether the speed is fresh is the
    permit gate's decision (:mod:`mowerhw.mow.gate`), not this reader's."""

    def __init__(
        self,
        source: str = "ground",
        sensor_address: int | None = None,
        ccvs1_direction: str = "etc2",
    ) -> None:
        if source not in SOURCES:
            raise ValueError(f"speed source {source!r} is not one of {', '.join(SOURCES)}")
        if ccvs1_direction not in ("etc2", "forward"):
            raise ValueError(f"ccvs1_direction {ccvs1_direction!r} is not one of etc2, forward")
        self.source = source
        self.sensor_address = sensor_address
        self.ccvs1_direction = ccvs1_direction
        #: the PGNs this reader reads: its speed message(s), and ETC2 when a CCVS1 speed is
        #: signed by the gear (what a bus filter must let through, and a process that reads
        #: the bus for another must pass on)
        self.pgns = frozenset(
            [pgn for pgn, (name, _) in SPEED_PGNS.items() if source in (name, "any")]
            + ([PGN_ETC2] if source in ("ccvs1", "any") and ccvs1_direction == "etc2" else [])
        )
        self.stats = SpeedStats()
        self.last_valid: SpeedSample | None = None
        self.last_invalid: SpeedSample | None = None
        self._gear: tuple[float, int] | None = None  # (t, gear) of the newest ETC2

    def handle(self, arbitration_id: int, data: bytes, t: float) -> SpeedSample | None:
        """The sample this frame carries for us (valid or not), or None."""
        ident = parse_id(arbitration_id)
        if ident.pgn == PGN_ETC2:
            self.stats.gear_frames += 1
            gear = decode_gear(bytes(data))
            if gear is not None:
                self._gear = (t, gear)
            return None
        sample = decode_speed(arbitration_id, data, t)
        if sample is None:
            self.stats.other_frames += 1
            return None
        if self.source != "any" and sample.source != self.source:
            self.stats.other_frames += 1
            return None
        if self.sensor_address is not None and sample.source_address != self.sensor_address:
            self.stats.wrong_source += 1
            return None
        if sample.valid and not sample.direction_known:
            sample = self._signed(sample)
        self.stats.frames += 1
        if sample.valid:
            self.stats.valid += 1
            self.last_valid = sample
        else:
            self.stats.invalid += 1
            self.last_invalid = sample
        return sample

    def _signed(self, s: SpeedSample) -> SpeedSample:
        """A CCVS1 speed with the sign of the transmission's gear (or forward, if so set)."""
        sign = 1.0
        if self.ccvs1_direction == "etc2":
            gear = self._gear
            if gear is None or s.t - gear[0] > GEAR_MAX_AGE_S:
                return SpeedSample(
                    s.t,
                    math.nan,
                    valid=False,
                    source=s.source,
                    source_address=s.source_address,
                    message=s.message,
                    reason="no direction: no ETC2 gear on the bus "
                    "(set speed.ccvs1_direction: forward if the mower never reverses)",
                )
            sign = -1.0 if gear[1] < 0 else 1.0
        return SpeedSample(
            s.t,
            sign * s.speed_mps,
            valid=True,
            source=s.source,
            distance_m=s.distance_m,
            source_address=s.source_address,
            message=s.message,
        )


def invalid_detail(sample: SpeedSample) -> str:
    """What a halt says about an invalid speed (:meth:`SpeedSample.invalid_detail`)."""
    return sample.invalid_detail()
