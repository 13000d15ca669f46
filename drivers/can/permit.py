"""Mowing permit / halt on CAN (docs/design.md §7): ISO 11783 ISB, heartbeat, and a status frame.

* **ISB**, PGN 64770 ("stop all implement operations"), priority 3: bytes 0–5 0xFF, byte 6 the
  transition counter (incremented on every change of state), byte 7 bits 1–2 ``00`` stop,
  ``01`` permit (the other bits 1). Sent on every change and every ``period_s`` (100 ms, not
  ISO's 1 s: a deck moving at 0.5 m/s must not run on for seconds). A change goes out at once
  and leaves the periodic grid where it was: with equal periods the ISB, status and heartbeat
  frames of a period go out together, one wake-up of the sender's loop a period (a change
  moving the ISB's grid put them half a period apart for good, two wake-ups — and on a bus
  that echoes them, two more of its receiver).
* **Heartbeat**, PGN 61668, every ``heartbeat_period_s``: sequence 251 first, then 0…250
  cycling; 254 error; 255 shutting down (ISO: "not available").
* **Status**, Proprietary B (PGN 0xFF00–0xFFFF, ``status_pgn``), for the mower's own
  controller: containment state, permit, halt reason, signed distance to the edge, position
  and heading (layout in :func:`encode_status` and ``configs/mowerhw.dbc``).

Everything is sent from the application's own loop (:meth:`PermitSender.tick`), never with
python-can's ``send_periodic``: if the application hangs, the frames stop and every receiver
times out into *stop* (300 ms).
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass

import can

from drivers.can.isobus import PGN_HEARTBEAT, PGN_ISB, can_id, parse_id

log = logging.getLogger(__name__)

ISB_STOP = 0b00
ISB_PERMIT = 0b01
HB_INITIAL = 251
HB_ERROR = 254
HB_SHUTDOWN = 255
_TICK_TOLERANCE_S = 1e-6  # a tick "at" the deadline counts, whatever the float rounding

STATE_CODES = {"INSIDE": 0, "NEAR_EDGE": 1, "OUTSIDE": 2, "UNKNOWN": 3, "TRANSIT": 4}
REASON_CODES = {
    "": 0,
    "OUTSIDE": 1,
    "UNCERTAIN": 2,
    "NOT_LOCALIZED": 3,
    "SENSOR_STALE": 4,
    "FAULT": 5,
    "MAP_INVALID": 6,
    "NOT_MOWING": 7,
    "SHUTTING_DOWN": 8,
    "ESTIMATOR_LATE": 9,
    "LIFTED": 10,
    "TILTED": 11,
    "COLLISION": 12,
    "TRANSIT": 13,
}
REASON_OTHER = 15  # a reason this table does not know (4 bits)
REASON_NAMES = {v: k for k, v in REASON_CODES.items()}
STATE_NAMES = {v: k for k, v in STATE_CODES.items()}


def encode_isb(counter: int, permit: bool) -> bytes:
    return bytes([0xFF] * 6 + [counter & 0xFF, 0xFC | (ISB_PERMIT if permit else ISB_STOP)])


def decode_isb(data: bytes) -> tuple[int, int]:
    """(transition counter, state bits) of an ISB frame."""
    return data[6], data[7] & 0x03


def encode_heartbeat(sequence: int) -> bytes:
    return bytes([sequence & 0xFF] + [0xFF] * 7)


@dataclass(frozen=True)
class Status:
    """What the status frame carries."""

    state: str = "UNKNOWN"
    permit: bool = False
    reason: str = "NOT_LOCALIZED"
    signed_distance_m: float = float("nan")
    x_m: float = float("nan")
    y_m: float = float("nan")
    heading_rad: float = float("nan")


def _i16(value: float, scale: float) -> int:
    if not math.isfinite(value):
        return 0x7FFF  # not available
    return max(-0x7FFE, min(0x7FFE, round(value / scale)))


def encode_status(s: Status) -> bytes:
    """Byte 0: state (bits 0–2), permit (bit 3), reason (bits 4–7); bytes 1–2: signed distance
    (int16, 0.01 m); 3–4: x, 5–6: y (int16, 0.05 m); 7: heading (uint8, 1.40625 °/bit).
    Not available: 0x7FFF (int16), 0xFF (heading). (configs/mowerhw.dbc, MowerhwStatus.)"""
    reason = REASON_CODES.get(s.reason, REASON_OTHER)
    b0 = STATE_CODES.get(s.state, 3) | (8 if s.permit else 0) | (reason << 4)
    if math.isfinite(s.heading_rad):
        heading = round(math.degrees(s.heading_rad) % 360.0 / 1.40625) % 256
        heading = min(heading, 0xFE)  # 0xFF means "not available"
    else:
        heading = 0xFF
    return struct.pack(
        "<BhhhB",
        b0,
        _i16(s.signed_distance_m, 0.01),
        _i16(s.x_m, 0.05),
        _i16(s.y_m, 0.05),
        heading,
    )


def decode_status(data: bytes) -> Status:
    b0, dist, x, y = struct.unpack_from("<Bhhh", data)
    na = 0x7FFF

    def val(v: int, scale: float) -> float:
        return float("nan") if v == na else v * scale

    heading = float("nan") if data[7] == 0xFF else math.radians(data[7] * 1.40625)
    return Status(
        STATE_NAMES.get(b0 & 7, "UNKNOWN"),
        bool(b0 & 8),
        REASON_NAMES.get(b0 >> 4, "?"),
        val(dist, 0.01),
        val(x, 0.05),
        val(y, 0.05),
        heading,
    )


@dataclass
class SenderStats:
    isb_sent: int = 0
    heartbeats_sent: int = 0
    status_sent: int = 0
    changes: int = 0
    send_errors: int = 0


class PermitSender:
    """ISB + heartbeat + status on a python-can bus, driven by the application's loop."""

    def __init__(
        self,
        bus: can.BusABC,
        source_address: int = 0x90,
        status_pgn: int = 0xFF10,
        period_s: float = 0.1,
        heartbeat_period_s: float = 0.1,
        send_timeout_s: float = 0.01,
    ) -> None:
        self.bus = bus
        #: how long a send may wait for room in the bus's queue (0: never, a full queue is an
        #: error: the supervisor's loop must never block on CAN)
        self.send_timeout_s = send_timeout_s
        self._next_error_log = 0.0
        self._errors_since_log = 0
        self.sa = source_address
        self.status_pgn = status_pgn
        self.period_s = period_s
        self.heartbeat_period_s = heartbeat_period_s
        self.permit = False  # the default is halt
        self.counter = 0
        self.sequence = HB_INITIAL
        self.status = Status()
        self.stats = SenderStats()
        self._next_isb = 0.0
        self._next_hb = 0.0
        self.last_isb_time: float | None = None  # when a stop/permit frame last went out
        #: while set, every heartbeat says 254 (an internal fault: the sender is not healthy)
        self.fault = False
        #: called with each frame sent (a recording of the bus: SocketCAN does not give a
        #: sender its own frames back)
        self.on_sent: Callable[[can.Message], None] | None = None

    def _send(self, pgn: int, data: bytes, priority: int = 3) -> None:
        import can

        msg = can.Message(
            arbitration_id=can_id(priority, pgn, self.sa), data=data, is_extended_id=True
        )
        try:
            self.bus.send(msg, timeout=self.send_timeout_s)
            if self.on_sent is not None:
                self.on_sent(msg)
        except (can.CanError, OSError) as exc:
            self.stats.send_errors += 1
            self._errors_since_log += 1
            now = time.monotonic()
            if now >= self._next_error_log:  # the first, then a summary every 10 s
                more = self._errors_since_log - 1
                log.warning(
                    "permit: CAN send failed: %s%s", exc, f" (+{more} since)" if more else ""
                )
                self._next_error_log, self._errors_since_log = now + 10.0, 0

    def _send_isb(self, now: float) -> None:
        self._send(PGN_ISB, encode_isb(self.counter, self.permit))
        self.stats.isb_sent += 1
        self.last_isb_time = now

    @staticmethod
    def _due(now: float, scheduled: float) -> bool:
        return now >= scheduled - _TICK_TOLERANCE_S

    @staticmethod
    def _advance(now: float, scheduled: float, period: float) -> float:
        """The next deadline on the period grid (no drift from tick jitter); after a stall,
        start a fresh grid rather than bursting to catch up."""
        nxt = scheduled + period
        return nxt if nxt > now else now + period

    def set(self, permit: bool, now: float, status: Status | None = None) -> bool:
        """The decision for now; a change goes out at once (with the counter incremented),
        the periodic frames stay on their grid. Returns whether it changed."""
        if status is not None:
            self.status = status
        changed = bool(permit) != self.permit
        if changed:
            self.permit = bool(permit)
            self.counter = (self.counter + 1) & 0xFF
            self.stats.changes += 1
            self._send_isb(now)
            self._send(self.status_pgn, encode_status(self.status), priority=6)
            self.stats.status_sent += 1
        return changed

    def tick(self, now: float) -> None:
        """Send whatever is due: ISB and status every period, the heartbeat."""
        if self._due(now, self._next_isb):
            scheduled = self._next_isb
            self._send_isb(now)
            self._next_isb = self._advance(now, scheduled, self.period_s)
            self._send(self.status_pgn, encode_status(self.status), priority=6)
            self.stats.status_sent += 1
        if self._due(now, self._next_hb):
            if self.fault:
                self._send(PGN_HEARTBEAT, encode_heartbeat(HB_ERROR))
            else:
                self._send(PGN_HEARTBEAT, encode_heartbeat(self.sequence))
                self.sequence = 0 if self.sequence >= 250 else self.sequence + 1
            self.stats.heartbeats_sent += 1
            self._next_hb = self._advance(now, self._next_hb, self.heartbeat_period_s)

    def next_due(self) -> float:
        """When :meth:`tick` next has something to send (host monotonic s)."""
        return min(self._next_isb, self._next_hb) - _TICK_TOLERANCE_S

    def error(self, now: float) -> None:
        """An internal fault: stop, and say so in the heartbeat (254)."""
        self.set(False, now)
        self._send(PGN_HEARTBEAT, encode_heartbeat(HB_ERROR))

    def shutdown(self, now: float) -> None:
        """Stop, then heartbeat 255 (shutting down)."""
        self.set(False, now, Status(reason="SHUTTING_DOWN"))
        self._send_isb(now)
        self._send(PGN_HEARTBEAT, encode_heartbeat(HB_SHUTDOWN))


def is_isb(arbitration_id: int) -> bool:
    return parse_id(arbitration_id).pgn == PGN_ISB


def is_heartbeat(arbitration_id: int) -> bool:
    return parse_id(arbitration_id).pgn == PGN_HEARTBEAT
