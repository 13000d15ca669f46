"""Ground speed over ISO 11783 (DESIGN.md §7): GBSD (PGN 65097) and WBSD (PGN 65096).

Bytes 0–1: speed, 0.001 m/s per bit (0–64255 valid; 0xFExx error, 0xFFxx not available);
bytes 2–5: distance, 0.001 m per bit (0xFE…… error, 0xFF…… not available); byte 7 bits 1–2:
direction, 00 reverse, 01 forward, 10 error, 11 not available. Reserved bits are sent as 1
and are masked, never required. An error or "not available" speed or direction gives a
sample marked invalid (with the reason), never a number.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from drivers.isobus import PGN_GBSD, PGN_WBSD, can_id, parse_id
from mowerhw.samples import SpeedSample

SPEED_MAX_RAW = 64255
DISTANCE_MAX_RAW = 0xFAFFFFFF
SPEED_PGNS = {PGN_GBSD: "ground", PGN_WBSD: "wheel"}


def decode_speed(arbitration_id: int, data: bytes, t: float | None = None) -> SpeedSample | None:
    """A :class:`SpeedSample` from a GBSD/WBSD frame; None for any other frame."""
    ident = parse_id(arbitration_id)
    source = SPEED_PGNS.get(ident.pgn)
    if source is None:
        return None
    t = time.monotonic() if t is None else t
    data = bytes(data)

    def invalid(reason: str) -> SpeedSample:
        return SpeedSample(
            t, float("nan"), valid=False, source=source, source_address=ident.source, reason=reason
        )

    if len(data) < 8:
        return invalid(f"frame has {len(data)} bytes, 8 expected")
    raw_speed = data[0] | (data[1] << 8)
    raw_dist = int.from_bytes(data[2:6], "little")
    direction = data[7] & 0x03
    distance = raw_dist * 0.001 if raw_dist <= DISTANCE_MAX_RAW else None
    if raw_speed > SPEED_MAX_RAW:
        kind = {0xFE: "error", 0xFF: "not available"}.get(data[1], "out of range")
        return invalid(f"speed {kind} (0x{raw_speed:04X})")
    if direction == 0b10:
        return invalid("direction error")
    if direction == 0b11:
        return invalid("direction not available")
    speed = raw_speed * 0.001
    signed = speed if direction == 0b01 else -speed
    return SpeedSample(
        t, signed, valid=True, source=source, distance_m=distance, source_address=ident.source
    )


def encode_speed(
    speed_mps: float,
    distance_m: float | None = 0.0,
    source_address: int = 0x80,
    pgn: int = PGN_GBSD,
    error: bool = False,
) -> tuple[int, bytes]:
    """A GBSD/WBSD frame (identifier, data) for a signed speed: the sensor side of the wire."""
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


@dataclass
class SpeedStats:
    frames: int = 0
    valid: int = 0
    invalid: int = 0
    wrong_source: int = 0
    other_frames: int = 0


class SpeedReader:
    """Which GBSD/WBSD frames count as this mower's ground speed, and whether it is stale."""

    def __init__(
        self, source: str = "ground", sensor_address: int | None = None, stale_after_s: float = 0.3
    ) -> None:
        if source not in ("ground", "wheel", "any"):
            raise ValueError(f"speed source {source!r} is not one of ground, wheel, any")
        self.source = source
        self.sensor_address = sensor_address
        self.stale_after_s = stale_after_s
        self.stats = SpeedStats()
        self.last_valid: SpeedSample | None = None

    def handle(self, arbitration_id: int, data: bytes, t: float) -> SpeedSample | None:
        """The sample this frame carries for us (valid or not), or None."""
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
        self.stats.frames += 1
        if sample.valid:
            self.stats.valid += 1
            self.last_valid = sample
        else:
            self.stats.invalid += 1
        return sample

    def stale(self, now: float) -> bool:
        return self.last_valid is None or now - self.last_valid.t > self.stale_after_s
