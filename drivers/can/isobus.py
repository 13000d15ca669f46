"""ISO 11783 / J1939 identifiers (docs/design.md §7).

A 29-bit identifier is ``priority<<26 | EDP<<25 | DP<<24 | PF<<16 | PS<<8 | SA``. With
``PF < 240`` the message is addressed (PS is the destination, not part of the PGN); with
``PF ≥ 240`` it is broadcast and PS is the low byte of the PGN.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import can

PGN_GBSD = 65097  # 0xFE49 Ground-based speed and distance
PGN_CCVS1 = 65265  # 0xFEF1 Cruise control / vehicle speed 1 (wheel-based vehicle speed)
PGN_ETC2 = 61445  # 0xF005 Electronic transmission controller 2 (selected / current gear)
PGN_WBSD = 65096  # 0xFE48 Wheel-based speed and distance
PGN_ISB = 64770  # 0xFD02 ISOBUS shortcut button: stop all implement operations
PGN_HEARTBEAT = 61668  # 0xF0E4 Heartbeat
GLOBAL_ADDRESS = 0xFF


@dataclass(frozen=True)
class J1939Id:
    priority: int
    pgn: int
    source: int
    destination: int  # GLOBAL_ADDRESS for broadcast PGNs


def can_id(priority: int, pgn: int, source: int, destination: int = GLOBAL_ADDRESS) -> int:
    """The 29-bit identifier of a PGN sent by ``source`` (to ``destination`` if addressed)."""
    if not (0 <= priority <= 7 and 0 <= pgn < 1 << 18 and 0 <= source <= 255):
        raise ValueError(
            f"invalid J1939 identifier parts: priority {priority}, PGN {pgn}, source {source}"
        )
    pf = (pgn >> 8) & 0xFF
    ps = pgn & 0xFF if pf >= 240 else destination
    dp = (pgn >> 16) & 1
    edp = (pgn >> 17) & 1
    return (priority << 26) | (edp << 25) | (dp << 24) | (pf << 16) | (ps << 8) | source


def pgn_filters(pgns: Iterable[int]) -> list[dict[str, Any]]:
    """python-can acceptance filters (``can_filters``) that let through the 29-bit frames of
    ``pgns`` from any source (and, addressed PGNs, to any destination). SocketCAN applies
    them in the kernel, so a busy tractor bus (the John Deere logs in ``data/real``: about
    300 frames a second) does not wake the reader for frames it does not read; other
    interfaces apply them in python-can."""
    out: list[dict[str, Any]] = []
    for pgn in sorted(set(pgns)):
        if not 0 <= pgn < 1 << 18:
            raise ValueError(f"PGN {pgn} is not an 18-bit parameter group number")
        pdu2 = ((pgn >> 8) & 0xFF) >= 240
        mask = 0x3FFFF00 if pdu2 else 0x3FF0000  # EDP, DP, PF (and PS when it is the PGN's)
        out.append({"can_id": (pgn << 8) & mask, "can_mask": mask, "extended": True})
    return out


def parse_id(arbitration_id: int) -> J1939Id:
    """Split a 29-bit identifier into priority, PGN, source and destination."""
    priority = (arbitration_id >> 26) & 0x7
    edp = (arbitration_id >> 25) & 1
    dp = (arbitration_id >> 24) & 1
    pf = (arbitration_id >> 16) & 0xFF
    ps = (arbitration_id >> 8) & 0xFF
    sa = arbitration_id & 0xFF
    if pf >= 240:
        return J1939Id(priority, (edp << 17) | (dp << 16) | (pf << 8) | ps, sa, GLOBAL_ADDRESS)
    return J1939Id(priority, (edp << 17) | (dp << 16) | (pf << 8), sa, ps)


def open_bus(
    interface: str,
    channel: str,
    bitrate: int = 250000,
    udp_port: int | None = None,
    **kwargs: Any,
) -> can.BusABC:
    """A python-can bus from config values (``can.interface``, ``can.channel``, and
    ``can.udp_port`` for ``udp_multicast``)."""
    import can

    if interface == "virtual":
        return can.Bus(interface="virtual", channel=channel, receive_own_messages=False, **kwargs)
    if interface == "udp_multicast":  # frames between processes on one host (the bench)
        if udp_port is not None:
            kwargs["port"] = udp_port
        return can.Bus(interface=interface, channel=channel, **kwargs)
    return can.Bus(interface=interface, channel=channel, bitrate=bitrate, **kwargs)
