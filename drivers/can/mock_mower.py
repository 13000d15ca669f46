"""A simulated mower controller: runs the deck only while the CAN permit says so.

It listens to the ISB (PGN 64770) and heartbeat (PGN 61668) frames of ``permit_source`` and
permits the deck only while all of these hold: the last ISB says *permit*; its transition
counter is valid (the same as before, or one more — a jump by more than one is a lost
transition and means stop until the next valid change); ISB and heartbeat are both fresher
than ``timeout_s`` (300 ms); and the heartbeat does not say error (254) or shutting down
(255). It records every change of its deck state with the time and the reason, and also reads
the status frame (containment state) so a bench can turn the mower at NEAR_EDGE. It counts
the address claims (ISO 11783-5, PGN 60928) from that source, and its frames that came
before the first claim (an ISO 11783 node claims before it sends). :meth:`claim_address`
makes it a second node on the permit source's address for a while (a misconfigured unit):
it claims that address with a NAME of higher priority and defends it, answering every
request for claims, until it leaves the bus.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import can

from drivers.can.address_claim import PGN_ADDRESS_CLAIMED, PGN_REQUEST, IsoName, requested_pgn
from drivers.can.isobus import PGN_HEARTBEAT, PGN_ISB, can_id, parse_id
from drivers.can.permit import HB_ERROR, HB_SHUTDOWN, ISB_PERMIT, Status, decode_isb, decode_status
from drivers.can.switches import Switches, encode_switches
from drivers.threaded import ThreadedDevice


@dataclass
class DeckEvent:
    t: float
    running: bool
    reason: str


@dataclass
class MowerState:
    isb_time: float | None = None
    isb_counter: int | None = None
    isb_permit: bool = False
    counter_fault: bool = False
    hb_time: float | None = None
    hb_sequence: int | None = None
    status: Status | None = None
    events: list[DeckEvent] = field(default_factory=list)
    frames: int = 0
    address_claims: int = 0  # Address Claimed frames from the permit source
    frames_before_claim: int = 0  # its other frames before its first claim
    #: (time, sequence) of the recent heartbeats: what a controller saw around a fault
    heartbeats: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=4000))


class MockMowerController(ThreadedDevice):
    """Reads permit frames from a bus and decides whether the deck may run."""

    thread_name = "mock-mower"

    def __init__(
        self,
        bus: can.BusABC,
        permit_source: int = 0x90,
        timeout_s: float = 0.3,
        status_pgn: int = 0xFF10,
        poll_s: float = 0.005,
        switches_pgn: int | None = None,
        source_address: int = 0x28,
    ) -> None:
        super().__init__()
        self.bus = bus
        self.source = permit_source
        self.timeout_s = timeout_s
        self.status_pgn = status_pgn
        self.poll_s = poll_s
        self.state = MowerState()
        self.deck_running = False
        self._lock = threading.Lock()
        #: the controller's own lift / bump / stop switches, sent every 100 ms and on every
        #: change when ``switches_pgn`` is given (a test or the bench sets them)
        self.switches = Switches()
        self.switches_pgn = switches_pgn
        self.sa = source_address
        self._sent_switches: Switches | None = None
        self._next_switches = 0.0
        #: (NAME, until, claim due): claiming the permit source's address (claim_address)
        self._impostor: tuple[IsoName, float, bool] | None = None

    def start(self) -> MockMowerController:
        self._start_thread()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=self.poll_s)
            now = time.monotonic()
            if msg is not None:
                self.handle(msg.arbitration_id, bytes(msg.data), now)
            self.evaluate(now)
            if self.switches_pgn is not None:
                self._send_switches(now)
            self._send_impostor_claim(now)

    #: the lowest NAME there is: it wins every contest for an address
    IMPOSTOR_NAME = IsoName(identity_number=0, manufacturer_code=0, industry_group=0)

    def claim_address(self, seconds: float) -> None:
        """For ``seconds``, claim the permit source's address with :data:`IMPOSTOR_NAME`
        and answer requests for claims with it; then leave the bus silently."""
        self._impostor = (self.IMPOSTOR_NAME, time.monotonic() + seconds, True)

    def _send_impostor_claim(self, now: float) -> None:
        imp = self._impostor
        if imp is None:
            return
        name, until, due = imp
        if now >= until:
            self._impostor = None
            return
        if due:
            msg = can.Message(
                arbitration_id=can_id(6, PGN_ADDRESS_CLAIMED, self.source),
                data=name.to_bytes(),
                is_extended_id=True,
            )
            with contextlib.suppress(can.CanError, OSError):
                self.bus.send(msg, timeout=0.0)
            self._impostor = (name, until, False)

    def _send_switches(self, now: float) -> None:
        sw = self.switches
        if sw == self._sent_switches and now < self._next_switches:
            return
        msg = can.Message(
            arbitration_id=can_id(6, self.switches_pgn or 0, self.sa),
            data=encode_switches(sw),
            is_extended_id=True,
        )
        with contextlib.suppress(can.CanError, OSError):
            self.bus.send(msg, timeout=0.0)
        self._sent_switches, self._next_switches = sw, now + 0.1

    def handle(self, arbitration_id: int, data: bytes, now: float) -> None:
        ident = parse_id(arbitration_id)
        imp = self._impostor
        if imp is not None and ident.pgn == PGN_REQUEST:  # asked who holds what: we do
            if requested_pgn(data) == PGN_ADDRESS_CLAIMED:
                self._impostor = (imp[0], imp[1], True)
            return
        if ident.source != self.source or len(data) < 8:
            return
        if imp is not None and ident.pgn == PGN_ADDRESS_CLAIMED:
            if int.from_bytes(data[:8], "little") == imp[0].value:
                return  # our own impostor claim, echoed by the bench's bus
            self._impostor = (imp[0], imp[1], True)  # contested: defend it
        s = self.state
        with self._lock:
            if ident.pgn == PGN_ADDRESS_CLAIMED:
                s.address_claims += 1
                return
            s.frames += 1
            if s.address_claims == 0:
                s.frames_before_claim += 1
            if ident.pgn == PGN_ISB:
                counter, bits = decode_isb(data)
                if s.isb_counter is not None:
                    step = (counter - s.isb_counter) & 0xFF
                    if step > 1:
                        s.counter_fault = True  # a transition was lost: stop
                    elif step == 1:
                        s.counter_fault = False  # a proper change re-synchronises
                s.isb_counter = counter
                s.isb_permit = bits == ISB_PERMIT
                s.isb_time = now
            elif ident.pgn == PGN_HEARTBEAT:
                s.hb_sequence = data[0]
                s.hb_time = now
                s.heartbeats.append((now, data[0]))
            elif ident.pgn == self.status_pgn:
                s.status = decode_status(data)

    def why_not(self, now: float) -> str:
        """Why the deck may not run now ("" if it may)."""
        s = self.state
        if s.isb_time is None or now - s.isb_time > self.timeout_s:
            return "ISB timeout"
        if s.hb_time is None or now - s.hb_time > self.timeout_s:
            return "heartbeat timeout"
        if s.hb_sequence in (HB_ERROR, HB_SHUTDOWN):
            return f"heartbeat {s.hb_sequence}"
        if s.counter_fault:
            return "ISB counter jump"
        if not s.isb_permit:
            return "ISB stop"
        return ""

    def evaluate(self, now: float) -> bool:
        with self._lock:
            reason = self.why_not(now)
            running = reason == ""
            if running != self.deck_running:
                self.deck_running = running
                self.state.events.append(DeckEvent(now, running, reason or "permit"))
            return running

    def last_stop(self) -> DeckEvent | None:
        return next((e for e in reversed(self.state.events) if not e.running), None)
