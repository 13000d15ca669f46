"""The supervisor's CAN bus: reopened with backoff when it fails (bus-off, interface down,
adapter unplugged), one log line per change of state, never a line per retry; and this ECU's
ISO 11783-5 NAME, from the config."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from drivers.can.address_claim import AddressClaim, IsoName
from drivers.can.isobus import PGN_HEARTBEAT, PGN_ISB, open_bus
from drivers.can.permit import PermitSender
from mowerhw.config import CanConfig, Config

log = logging.getLogger("mowerhw.supervisor")

#: while CAN stays down, one summary line this often (s)
SUMMARY_PERIOD_S = 60.0


MACHINE_ID = Path("/etc/machine-id")


def ecu_name(c: CanConfig, machine_id: Path = MACHINE_ID) -> IsoName:
    """This ECU's NAME from the ``can.name_*`` keys; without ``can.name_identity_number``, 21
    bits of a hash of the computer's machine id (another mower's differs), or 0 without one."""
    identity = c.name_identity_number
    if identity is None:
        try:
            digest = hashlib.sha256(machine_id.read_bytes().strip()).digest()
            identity = int.from_bytes(digest[:3], "little") & ((1 << 21) - 1)
        except OSError:
            identity = 0
    # every other field from the key of its name: can.name_manufacturer_code, …
    keys = {
        f.name: getattr(c, f"name_{f.name}")
        for f in dataclasses.fields(IsoName)
        if f.name not in ("identity_number", "self_configurable")
    }
    # the address is the config's: mowerhw does not pick another (not self-configurable)
    return IsoName(identity_number=identity, self_configurable=False, **keys)


def address_claim(cfg: Config) -> AddressClaim | None:
    """The claim of ``can.source_address`` (ISO 11783-5) for whatever sends the permit
    frames, or None with ``can.address_claim: false``. Requests for the permit frames'
    PGNs get no NACK: they come every 100 ms anyway."""
    c = cfg.can
    if not c.address_claim:
        return None
    sent = frozenset({PGN_ISB, PGN_HEARTBEAT, cfg.permit.status_pgn})
    return AddressClaim(ecu_name(c), c.source_address, c.address_claim_retry_s, sent_pgns=sent)


def permit_sender(
    cfg: Config,
    bus: can.BusABC,
    now: float,
    send_timeout_s: float,
    on_sent: Callable[[can.Message], None] | None = None,
) -> PermitSender:
    """A new sender of the permit frames on ``bus`` (each frame also to ``on_sent``: a
    recording), for both senders (the supervisor and the one-process daemon's ``CanLink``).
    Its first frames go out now: a stop (counter 0) and heartbeat 251. After any silence of
    ours (a start, a bus reopened, the address regained) a controller that counted another
    sender's transitions sees a jump, then a valid change it follows."""
    c, p = cfg.can, cfg.permit
    sender = PermitSender(
        bus, c.source_address, p.status_pgn, p.period_s, p.heartbeat_period_s, send_timeout_s
    )
    sender.on_sent = on_sent
    sender.tick(now)
    return sender


class CanPort:
    """The bus, reopened with backoff when it fails; one log line per change of state."""

    def __init__(self, cfg: Config, filters: list[dict[str, Any]] | None = None) -> None:
        """``filters``: python-can acceptance filters for every bus opened (None: every
        frame)."""
        self.cfg = cfg
        self.filters = filters
        self.bus: can.BusABC | None = None
        self.up_since: float | None = None
        self.down_since: float | None = time.monotonic()
        self.reopens = 0
        self.errors = 0
        self._backoff = 0.1
        self._next_try = 0.0
        self._last_error = ""
        self._gone_until = 0.0  # fault injection: the interface is away until then
        self._attempts = 0  # failed opens since the bus went down
        self._next_summary = 0.0

    def ensure(self, now: float) -> bool:
        """Open the bus if it is closed and a retry is due; whether it is up."""
        if self.bus is not None:
            return True
        if now < self._next_try:
            return False
        c = self.cfg.can
        if now < self._gone_until:
            self._failed(now, "cannot open (No such device: the interface is away)")
            return False
        try:
            self.bus = open_bus(
                c.interface, c.channel, c.bitrate, udp_port=c.udp_port, can_filters=self.filters
            )
        except Exception as exc:
            self._failed(now, f"cannot open ({exc})")
            return False
        if self.reopens or self._last_error:
            log.warning(
                "CAN %s %s open again after %.1f s",
                c.interface,
                c.channel,
                now - (self.down_since or now),
            )
        else:
            log.info("CAN %s %s open, sending as 0x%02X", c.interface, c.channel, c.source_address)
        self.reopens += 1
        self._attempts = 0
        self.up_since, self.down_since = now, None
        self._backoff, self._last_error = 0.1, ""
        return True

    def take_away(self, now: float, seconds: float) -> None:
        """Fault injection: the interface disappears for ``seconds`` (an adapter unplugged)."""
        self._gone_until = now + seconds
        self.failed(now, "the interface went away (fault injection)")

    def failed(self, now: float, why: str) -> None:
        """The bus stopped working: close it; :meth:`ensure` reopens it with backoff."""
        bus, self.bus = self.bus, None
        if bus is not None:
            with contextlib.suppress(Exception):
                bus.shutdown()
        self._failed(now, why)

    def _failed(self, now: float, why: str) -> None:
        self.errors += 1
        if self.down_since is None or self.up_since is not None:
            self.down_since = now
        self.up_since = None
        self._attempts += 1
        if why == self._last_error and now >= self._next_summary:  # the periodic summary
            log.error(
                "CAN %s %s still down after %.0f s (%d attempts to reopen; last: %s)",
                self.cfg.can.interface,
                self.cfg.can.channel,
                now - (self.down_since or now),
                self._attempts,
                why,
            )
        if why != self._last_error or now >= self._next_summary:
            self._next_summary = now + SUMMARY_PERIOD_S
        if why != self._last_error:  # one line per change, not per retry
            log.error(
                "CAN %s %s: %s; reopening with backoff",
                self.cfg.can.interface,
                self.cfg.can.channel,
                why,
            )
            self._last_error = why
        self._next_try = now + self._backoff
        self._backoff = min(self._backoff * 2, self.cfg.supervisor.can_reopen_max_backoff_s)
