"""The mower controller's own safety switches on CAN (a frame of mowerhw's: Proprietary B
PGN 0xFF11, configurable ``safety.switches_pgn``, sent by the mower's controller every 100 ms
and on every change; described in ``configs/mowerhw.dbc``).

Byte 0: bit 0 lifted, bit 1 bumper pressed, bit 2 stop button pressed (1 = active); bytes 1–7
0xFF. A frame whose byte 0 has any of bits 3–7 clear is malformed and ignored."""

from __future__ import annotations

from dataclasses import dataclass

PGN_SWITCHES = 0xFF11


@dataclass(frozen=True, slots=True)
class Switches:
    lifted: bool = False
    bumped: bool = False
    stop: bool = False


def encode_switches(s: Switches) -> bytes:
    b0 = 0xF8 | int(s.lifted) | (int(s.bumped) << 1) | (int(s.stop) << 2)
    return bytes([b0] + [0xFF] * 7)


def decode_switches(data: bytes) -> Switches | None:
    """The switches of one frame, or None if it is malformed."""
    if len(data) < 1 or data[0] & 0xF8 != 0xF8:
        return None
    b0 = data[0]
    return Switches(bool(b0 & 1), bool(b0 & 2), bool(b0 & 4))
