#!/usr/bin/env python3
"""Check: the ground-speed reader and the permit gate on a real tractor's CAN bus.

``../shared/data/real/can-john-deere-tractor``: six candump logs (63,215 frames) of a John
Deere tractor's J1939 / ISO 11783 bus, standing still. Its GBSD (PGN 65097, source 0x47) is
always "not available"; its CCVS1 (PGN 65265) wheel-based speed is 0 km/h; ETC2 (PGN 61445)
gives the selected gear. Each log is read with python-can's candump reader and fed, at its
own timestamps, through :class:`drivers.can.speed.SpeedReader` and the permit gate's
staleness decision, as the daemon does, once per ``speed.source``. And its network management
(ISO 11783-5): each ECU's address claim with its NAME decoded, the requests for claims, and
what mowerhw's :class:`drivers.can.address_claim.AddressClaim` does on that bus at 0x90.

Prints one JSON object per log. Run: ``.venv/bin/python tools/check_real_can.py``.
"""

from __future__ import annotations

import itertools
import json
import sys
from collections import Counter
from pathlib import Path

import can

from drivers.can.address_claim import (
    NULL_ADDRESS,
    PGN_ADDRESS_CLAIMED,
    PGN_REQUEST,
    AddressClaim,
    IsoName,
    requested_pgn,
)
from drivers.can.isobus import parse_id
from drivers.can.speed import SpeedReader, invalid_detail
from mowerhw.mow.gate import PermitGate

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
LOGS = DATA / "can-john-deere-tractor" / "candump"
SPEED_STALE_S = 0.3  # speed.stale_after_s default


def replay(path: Path, source: str) -> dict[str, object]:
    """The log through the reader and the gate's staleness check (speed only)."""
    reader = SpeedReader(source=source)
    gate = PermitGate({"speed": SPEED_STALE_S})
    last: dict[str, float | None] = {"speed": None}
    notes: dict[str, tuple[float, str]] = {}
    details: Counter[str] = Counter()
    speeds: list[float] = []
    frames = 0
    t0 = t_end = None
    checks = fresh = 0
    next_check = None
    for msg in can.CanutilsLogReader(str(path)):
        t = msg.timestamp
        t0 = t if t0 is None else t0
        t_end = t
        frames += 1
        if msg.is_extended_id:
            s = reader.handle(msg.arbitration_id, bytes(msg.data), t)
            if s is not None:
                if s.valid:
                    last["speed"] = t
                    notes.pop("speed", None)
                    speeds.append(s.speed_mps)
                else:
                    notes["speed"] = (t, invalid_detail(s))
        # the daemon decides at every IMU sample: here every 10 ms of log time
        next_check = t if next_check is None else next_check
        while next_check <= t:
            stale = gate.stale(next_check, last, notes)
            checks += 1
            if stale is None:
                fresh += 1
            else:
                details[stale[1].split(" for ")[0].split(";")[0]] += 1
            next_check += 0.01
    return {
        "source": source,
        "speed_frames_recognised": reader.stats.frames,
        "valid": reader.stats.valid,
        "invalid": reader.stats.invalid,
        "speed_mps": sorted(set(speeds))[:3],
        "fresh_fraction": round(fresh / max(checks, 1), 4),
        "halt_details": dict(details.most_common(3)),
        "log_s": round((t_end or 0) - (t0 or 0), 2),
        "frames": frames,
    }


def gbsd_period_stats(path: Path) -> dict[str, float]:
    times = [
        m.timestamp
        for m in can.CanutilsLogReader(str(path))
        if m.is_extended_id and parse_id(m.arbitration_id).pgn == 65097
    ]
    gaps = sorted(b - a for a, b in itertools.pairwise(times))
    return {
        "gbsd_frames": len(times),
        "period_ms_median": round(1e3 * gaps[len(gaps) // 2], 1),
        "period_ms_max": round(1e3 * gaps[-1], 1),
    }


def network_management(path: Path, address: int = 0x90) -> dict[str, object]:
    """The log's address claims (the newest NAME of each address, decoded) and requests for
    claims; then the log fed to an :class:`AddressClaim` holding ``address``: the answers it
    sends, whether anyone contested it."""
    names: dict[int, IsoName] = {}
    claims = requests = 0
    ours = IsoName(identity_number=0, manufacturer_code=0, function=128)
    mowerhw = AddressClaim(ours, address, seed=0)
    mowerhw.begin(0.0)
    mowerhw.due(0.0)
    answers = 0
    for msg in can.CanutilsLogReader(str(path)):
        if not msg.is_extended_id:
            continue
        ident, data = parse_id(msg.arbitration_id), bytes(msg.data)
        if ident.pgn == PGN_ADDRESS_CLAIMED and ident.source != NULL_ADDRESS and len(data) >= 8:
            claims += 1
            names[ident.source] = IsoName.from_bytes(data)
        elif ident.pgn == PGN_REQUEST and requested_pgn(data) == PGN_ADDRESS_CLAIMED:
            requests += 1
        mowerhw.received(msg.arbitration_id, data, 1.0)
        answers += len(mowerhw.due(1.0))
    return {
        "claims": claims,
        "requests_for_claims": requests,
        "names": {
            f"0x{sa:02X}": {
                "name": f"0x{n.value:016X}",
                "manufacturer_code": n.manufacturer_code,
                "function": n.function,
                "device_class": n.device_class,
                "industry_group": n.industry_group,
                "self_configurable": n.self_configurable,
            }
            for sa, n in sorted(names.items())
        },
        f"mowerhw_at_0x{address:02X}": {
            "answers": answers,
            "holds_it": mowerhw.holds(1.0),
            "contested": mowerhw.contests_won > 0 or mowerhw.state == "lost",
        },
    }


def check(path: Path) -> dict[str, object]:
    return {
        "log": path.name,
        **gbsd_period_stats(path),
        "ground": replay(path, "ground"),
        "ccvs1": replay(path, "ccvs1"),
        "network_management": network_management(path),
    }


def main() -> None:
    if not LOGS.exists():
        sys.exit(f"no real data at {LOGS}")
    for path in sorted(LOGS.glob("*.log")):
        print(json.dumps(check(path)))


if __name__ == "__main__":
    main()
