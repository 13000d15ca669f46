"""ISO 11783-5 / J1939-81 network management: this ECU's NAME and the claim of its source
address (docs/design.md §7).

Every control function on an ISOBUS network claims its source address before it sends
anything else: an *Address Claimed* frame (PGN 60928, to the global address) carrying its
64-bit NAME, then 250 ms in which another claimant may contest it. Two claims of one address
are settled by the NAMEs: the lower one keeps it. A control function answers a *Request*
(PGN 59904) for PGN 60928 with its claim. One that loses its address and cannot take another
(mowerhw's address is fixed by the config: not self-configurable) sends *Cannot Claim* (an
Address Claimed frame from the null address 254) after a pseudo-random delay of 0–153 ms,
and nothing else but answers. A real tractor does this on every start (the John Deere logs in
``data/real``: each ECU claims, and three of them ask for everyone's claims).

A request addressed to this node for a PGN it does not send is answered with a negative
acknowledgement (J1939-21: Acknowledgment, PGN 59392, control byte 1, the requester's address
and the PGN), so the asker need not wait out its timeout; a request to everyone for such a
PGN gets no answer. The tractor's cluster (0x17 in the logs) asks each ECU that claimed an
address for a proprietary PGN by address.

:class:`AddressClaim` is the logic only (no bus, no clock of its own): it is told the time
and the frames received, and says which frames to send when, and whether the address is
held; :func:`serve` sends those frames on a bus. Whatever sends the permit frames drives it
(the permit supervisor, ``mowerhw/supervisor/process.py``, or the one-process daemon's
``CanLink``); while the address is not held it sends no permit frame, so the mower's
controller sees silence: stop.
"""

from __future__ import annotations

import logging
import random
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from drivers.can.isobus import GLOBAL_ADDRESS, can_id, parse_id

if TYPE_CHECKING:
    import can

log = logging.getLogger("mowerhw.can")

PGN_ADDRESS_CLAIMED = 60928  # 0xEE00, also "Cannot Claim" when sent from NULL_ADDRESS
PGN_REQUEST = 59904  # 0xEA00: bytes 0-2 the PGN requested (little-endian)
PGN_ACKNOWLEDGMENT = 59392  # 0xE800: byte 0 control (1 = NACK), byte 4 requester, 5-7 PGN
ACK_NACK = 1
NULL_ADDRESS = 254  # a control function without an address
#: ISO 11783-5: no other message until this long after the claim (s)
CONTENTION_S = 0.25
#: the pseudo-random delay of a Cannot Claim: 0.6 ms × 0..255 (s)
RANDOM_DELAY_STEP_S = 0.0006
#: how long the answers to a request may take (J1939-21's response time Tr, s)
RESPONSE_TIMEOUT_S = 1.25
PRIORITY = 6


@dataclass(frozen=True)
class IsoName:
    """The 64-bit NAME of ISO 11783-5 and J1939-81, its fields from bit 0 up:
    identity number (21 bits), manufacturer code (11), ECU instance (3), function instance
    (5), function (8), a reserved bit, device class (7; J1939's vehicle system), device
    class instance (4), industry group (3; 2 = agricultural and forestry equipment) and
    "self-configurable address" (1). Sent little-endian; the lower value wins a contest."""

    identity_number: int
    manufacturer_code: int
    ecu_instance: int = 0
    function_instance: int = 0
    function: int = 0
    device_class: int = 0
    device_class_instance: int = 0
    industry_group: int = 2
    self_configurable: bool = False

    _BITS = (
        ("identity_number", 0, 21),
        ("manufacturer_code", 21, 11),
        ("ecu_instance", 32, 3),
        ("function_instance", 35, 5),
        ("function", 40, 8),
        ("device_class", 49, 7),
        ("device_class_instance", 56, 4),
        ("industry_group", 60, 3),
        ("self_configurable", 63, 1),
    )

    def __post_init__(self) -> None:
        for name, _, bits in self._BITS:
            value = int(getattr(self, name))
            if not 0 <= value < 1 << bits:
                raise ValueError(f"NAME field {name}: {value} does not fit in {bits} bits")

    @property
    def value(self) -> int:
        out = 0
        for name, shift, _ in self._BITS:
            out |= int(getattr(self, name)) << shift
        return out

    def to_bytes(self) -> bytes:
        return self.value.to_bytes(8, "little")

    @classmethod
    def from_bytes(cls, data: bytes) -> IsoName:
        if len(data) < 8:
            raise ValueError(f"a NAME is 8 bytes, got {len(data)}")
        v = int.from_bytes(bytes(data[:8]), "little")
        f = {name: (v >> shift) & ((1 << bits) - 1) for name, shift, bits in cls._BITS}
        return cls(
            identity_number=f["identity_number"],
            manufacturer_code=f["manufacturer_code"],
            ecu_instance=f["ecu_instance"],
            function_instance=f["function_instance"],
            function=f["function"],
            device_class=f["device_class"],
            device_class_instance=f["device_class_instance"],
            industry_group=f["industry_group"],
            self_configurable=bool(f["self_configurable"]),
        )

    def describe(self) -> str:
        return (
            f"NAME 0x{self.value:016X} (manufacturer {self.manufacturer_code}, function "
            f"{self.function}, industry group {self.industry_group}, identity "
            f"{self.identity_number})"
        )


@dataclass(frozen=True)
class Frame:
    """A frame to send: 29-bit identifier and data."""

    arbitration_id: int
    data: bytes


def requested_pgn(data: bytes) -> int | None:
    """The PGN a Request (PGN 59904) asks for, or None if it is too short."""
    return int.from_bytes(bytes(data[:3]), "little") if len(data) >= 3 else None


class AddressClaim:
    """Claim ``address`` with ``name``; defend it against higher NAMEs, yield it to lower
    ones, answer requests. While another holds it, ask every ``retry_s`` who holds what (a
    Request for Address Claimed from the null address, which a node without an address may
    send): when no lower NAME claims the address within :data:`RESPONSE_TIMEOUT_S`, claim it
    again — it is never contested while its holder is there.

    Thread-safe: the receive thread calls :meth:`received`, the sending loop the rest.
    States: ``idle`` (no bus yet), ``claiming`` (claim sent, contention running),
    ``held``, ``lost``."""

    def __init__(
        self,
        name: IsoName,
        address: int,
        retry_s: float = 10.0,
        seed: int | None = None,
        sent_pgns: frozenset[int] = frozenset(),
    ) -> None:
        """``sent_pgns``: the PGNs the node sends on its own (the permit frames, every 100
        ms): a request for one of them gets no NACK, it comes anyway."""
        if not 0 <= address <= 253:
            raise ValueError(f"source address {address}: must be 0..253")
        self.name = name
        self.address = address
        self.retry_s = retry_s
        self.state = "idle"
        self.holder: IsoName | None = None  # who took the address from us
        self.sent_pgns = sent_pgns
        self.claims_sent = 0
        self.contests_won = 0
        self.nacks_sent = 0
        self.changes: list[str] = []  # what happened, for the caller to log (then cleared)
        self._since = 0.0
        self._retry_at = 0.0
        self._probe_until: float | None = None  # asked who holds it; answers until then
        self._pending: list[tuple[float, Frame]] = []
        self._rng = random.Random(seed)
        self._lock = threading.Lock()

    # ------------------------------------------------------------------------- frames

    def _claim_frame(self) -> Frame:
        return Frame(
            can_id(PRIORITY, PGN_ADDRESS_CLAIMED, self.address, GLOBAL_ADDRESS),
            self.name.to_bytes(),
        )

    def _request_frame(self) -> Frame:
        return Frame(
            can_id(PRIORITY, PGN_REQUEST, NULL_ADDRESS, GLOBAL_ADDRESS),
            PGN_ADDRESS_CLAIMED.to_bytes(3, "little"),
        )

    def _nack_frame(self, requester: int, pgn: int) -> Frame:
        data = bytes([ACK_NACK, 0xFF, 0xFF, 0xFF, requester]) + pgn.to_bytes(3, "little")
        return Frame(can_id(PRIORITY, PGN_ACKNOWLEDGMENT, self.address, GLOBAL_ADDRESS), data)

    def _cannot_claim_frame(self) -> Frame:
        return Frame(
            can_id(PRIORITY, PGN_ADDRESS_CLAIMED, NULL_ADDRESS, GLOBAL_ADDRESS),
            self.name.to_bytes(),
        )

    def _queue(self, at: float, frame: Frame) -> None:
        if frame not in (f for _, f in self._pending):
            self._pending.append((at, frame))

    # -------------------------------------------------------------------------- input

    def begin(self, now: float) -> None:
        """A bus (re)opened, or a retry: claim the address (sent at once)."""
        with self._lock:
            self._begin(now)

    def _begin(self, now: float) -> None:
        self.state, self._since, self._probe_until = "claiming", now, None
        self._pending = [(at, f) for at, f in self._pending if f != self._cannot_claim_frame()]
        self._queue(now, self._claim_frame())

    def received(self, arbitration_id: int, data: bytes, now: float) -> bool:
        """A frame from the bus; True when it was one of network management's (a claim, a
        request for claims, a request addressed to this node), which may have queued frames
        to send."""
        ident = parse_id(arbitration_id)
        if ident.pgn == PGN_REQUEST:
            if ident.destination not in (GLOBAL_ADDRESS, self.address):
                return False
            asked = requested_pgn(data)
            if asked is None:
                return False
            if asked != PGN_ADDRESS_CLAIMED:
                if ident.destination != self.address or asked in self.sent_pgns:
                    return False  # to everyone, or one that comes anyway: no answer
                with self._lock:
                    if self.state == "held":  # from an address that is ours only
                        self.nacks_sent += 1
                        self._queue(now, self._nack_frame(ident.source, asked))
                return True
            with self._lock:
                if self.state in ("claiming", "held"):
                    self._queue(now, self._claim_frame())
                elif self.state == "lost":
                    self._queue(now + self._random_delay(), self._cannot_claim_frame())
            return True
        if ident.pgn != PGN_ADDRESS_CLAIMED:
            return False
        if ident.source != self.address or len(data) < 8:
            return True  # another address's claim, or a Cannot Claim: not ours to answer
        theirs = int.from_bytes(bytes(data[:8]), "little")
        with self._lock:
            if theirs == self.name.value:
                return True  # our own claim back (a bus that echoes what it sends)
            if self.state == "lost":
                if theirs < self.name.value:  # its holder is still there: ask again later
                    self.holder = IsoName.from_bytes(data)
                    self._probe_until, self._retry_at = None, now + self.retry_s
                return True
            if self.state not in ("claiming", "held"):
                return True
            if theirs < self.name.value:  # theirs has the priority: yield
                holder = IsoName.from_bytes(data)
                known = holder == self.holder  # a retry answered by the same holder: no news
                self.holder = holder
                self.state, self._since = "lost", now
                self._retry_at = now + self.retry_s
                self._pending = [(at, f) for at, f in self._pending if f != self._claim_frame()]
                self._queue(now + self._random_delay(), self._cannot_claim_frame())
                if known:
                    return True
                self.changes.append(
                    f"another ECU claimed source address 0x{self.address:02X} with a lower "
                    f"(higher-priority) {self.holder.describe()} than ours "
                    f"(0x{self.name.value:016X}): mowerhw yields it and sends no permit frame "
                    "(the controller sees silence: stop); give can.source_address a free "
                    f"address; asking every {self.retry_s:g} s whether it is free again"
                )
            else:  # ours has the priority: say so again; the other must yield
                self.contests_won += 1
                self._queue(now, self._claim_frame())
        return True

    def _random_delay(self) -> float:
        return RANDOM_DELAY_STEP_S * self._rng.randrange(256)

    # ------------------------------------------------------------------------- output

    def holds(self, now: float) -> bool:
        """Whether the address is ours to send from (claimed, contention over)."""
        with self._lock:
            self._advance(now)
            return self.state == "held"

    def _advance(self, now: float) -> None:
        if self.state == "claiming" and now - self._since >= CONTENTION_S:
            self.state = "held"
            if self.holder is not None:
                self.changes.append(
                    f"source address 0x{self.address:02X} claimed again: its other "
                    "claimant has gone"
                )
                self.holder = None
        elif self.state == "lost":
            if self._probe_until is None and now >= self._retry_at:
                self._queue(now, self._request_frame())  # who holds what?
                self._probe_until = now + RESPONSE_TIMEOUT_S
            elif self._probe_until is not None and now >= self._probe_until:
                self._begin(now)  # no lower NAME answered for it: it is free

    def due(self, now: float) -> list[Frame]:
        """The frames to send now (claims, cannot-claims)."""
        with self._lock:
            self._advance(now)
            out = [f for at, f in self._pending if at <= now]
            self._pending = [(at, f) for at, f in self._pending if at > now]
            self.claims_sent += sum(1 for f in out if f == self._claim_frame())
            return out

    def next_due(self) -> float:
        """When something is next to happen (a frame due, the contention's end, a retry)."""
        with self._lock:
            times = [at for at, _ in self._pending]
            if self.state == "claiming":
                times.append(self._since + CONTENTION_S)
            elif self.state == "lost":
                times.append(self._retry_at if self._probe_until is None else self._probe_until)
            return min(times, default=float("inf"))

    def take_changes(self) -> list[str]:
        with self._lock:
            out, self.changes = self.changes, []
            return out

    def status(self) -> dict[str, object]:
        with self._lock:
            return {
                "state": self.state,
                "address": self.address,
                "name": f"0x{self.name.value:016X}",
                "holder": None if self.holder is None else f"0x{self.holder.value:016X}",
                "claims_sent": self.claims_sent,
                "contests_won": self.contests_won,
                "nacks_sent": self.nacks_sent,
            }


def serve(
    claim: AddressClaim,
    bus: can.BusABC,
    now: float,
    on_sent: Callable[[can.Message], None] | None = None,
) -> bool:
    """Send ``claim``'s due frames on ``bus`` (each also to ``on_sent``: a recording), log
    what changed (one line per change), and say whether the address is held, i.e. whether
    the permit frames may go out."""
    import can

    for frame in claim.due(now):
        msg = can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=True)
        try:
            bus.send(msg, timeout=0.0)
        except (can.CanError, OSError) as exc:  # the next request or retry sends it again
            log.warning("CAN: an address claim frame was not sent (%s)", exc)
        else:
            if on_sent is not None:
                on_sent(msg)
    for change in claim.take_changes():
        log.log(logging.ERROR if claim.state == "lost" else logging.WARNING, "CAN: %s", change)
    return claim.holds(now)
