"""ISO 11783-5 address claiming (drivers/can/address_claim.py): the NAME's bit layout, checked
against a real tractor's claims; the claim, its defence, yielding, requests, retries."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import can
import pytest
from _supervisor import receiving
from _tools import load_tool

from drivers.can.address_claim import (
    CONTENTION_S,
    NULL_ADDRESS,
    PGN_ACKNOWLEDGMENT,
    PGN_ADDRESS_CLAIMED,
    PGN_REQUEST,
    RESPONSE_TIMEOUT_S,
    AddressClaim,
    IsoName,
    requested_pgn,
)
from drivers.can.isobus import GLOBAL_ADDRESS, PGN_ISB, can_id, parse_id
from drivers.can.permit import ISB_PERMIT, ISB_STOP, decode_isb
from mowerhw.common.reasons import Reason
from mowerhw.config import config_from_dict, config_to_dict, default_config
from mowerhw.supervisor.canport import ecu_name
from mowerhw.supervisor.lease import Lease
from mowerhw.supervisor.process import FORCE, Supervisor

OURS = IsoName(identity_number=0x1234, manufacturer_code=0, function=128)
LOWER = IsoName(identity_number=7, manufacturer_code=0, function=100)  # wins against OURS
HIGHER = IsoName(identity_number=9, manufacturer_code=1, function=200)  # loses against OURS


def claimed(name: IsoName, source: int) -> tuple[int, bytes]:
    return can_id(6, PGN_ADDRESS_CLAIMED, source), name.to_bytes()


def request(destination: int = GLOBAL_ADDRESS, source: int = 0x00) -> tuple[int, bytes]:
    return can_id(6, PGN_REQUEST, source, destination), PGN_ADDRESS_CLAIMED.to_bytes(3, "little")


def test_the_name_round_trips_and_orders_by_its_value() -> None:
    name = IsoName(
        identity_number=0x1ABCDE,
        manufacturer_code=0x5A5,
        ecu_instance=5,
        function_instance=17,
        function=0xC3,
        device_class=0x55,
        device_class_instance=9,
        industry_group=2,
        self_configurable=True,
    )
    assert IsoName.from_bytes(name.to_bytes()) == name
    assert name.value >> 63 == 1 and (name.value >> 60) & 7 == 2
    assert LOWER.value < OURS.value < HIGHER.value
    with pytest.raises(ValueError, match="identity_number: 2097152 does not fit in 21 bits"):
        IsoName(identity_number=1 << 21, manufacturer_code=0)


def test_a_real_tractors_claims_decode_as_agricultural_equipment() -> None:
    """The John Deere logs (``tools/check_real_can.py``): every ECU claims its address on
    start (PGN 60928, 8-byte NAME) and three of them ask for all claims (PGN 59904 for
    60928). Each NAME decodes with the industry group of agricultural and forestry
    equipment (2), and encodes back to its bytes. mowerhw at 0x90 on that bus answers every
    request once and is never contested."""
    tool = load_tool("check_real_can")
    logs = sorted(tool.LOGS.glob("*.log"))
    if not logs:
        pytest.skip("real tractor CAN logs not present (../shared/data/real)")
    for path in logs:
        nm = tool.network_management(path)
        names = {
            sa: IsoName.from_bytes(int(n["name"], 16).to_bytes(8, "little"))
            for sa, n in nm["names"].items()
        }
        assert set(names) == {"0x00", "0x03", "0x06", "0x17", "0x47"}, path.name
        assert {n.industry_group for n in names.values()} == {2}
        # the fields where J1939 puts them: the engine (function 0) at its preferred address
        # 0x00, the transmission (function 3) at 0x03, both of a tractor (device class 1)
        assert (names["0x00"].function, names["0x00"].device_class) == (0, 1)
        assert (names["0x03"].function, names["0x03"].device_class) == (3, 1)
        assert nm["claims"] >= 12 and nm["requests_for_claims"] >= 3
        assert "0x90" not in names  # mowerhw's default address is free on that bus
        ours = nm["mowerhw_at_0x90"]
        assert ours == {"answers": nm["requests_for_claims"], "holds_it": True, "contested": False}
    # the bytes as sent: a claim frame of the log decodes and encodes back to itself
    frame = next(
        m
        for m in can.CanutilsLogReader(str(logs[0]))
        if m.is_extended_id and parse_id(m.arbitration_id).pgn == PGN_ADDRESS_CLAIMED
    )
    assert IsoName.from_bytes(bytes(frame.data)).to_bytes() == bytes(frame.data)


def test_the_claim_holds_after_the_contention_time_and_answers_requests() -> None:
    ac = AddressClaim(OURS, 0x90, seed=1)
    assert not ac.holds(0.0) and ac.due(0.0) == []  # no bus yet: nothing
    ac.begin(10.0)
    (frame,) = ac.due(10.0)
    assert frame.arbitration_id == can_id(6, PGN_ADDRESS_CLAIMED, 0x90)
    assert frame.data == OURS.to_bytes()
    assert not ac.holds(10.0 + CONTENTION_S - 0.01)
    assert ac.next_due() == pytest.approx(10.0 + CONTENTION_S)
    assert ac.holds(10.0 + CONTENTION_S)
    assert ac.received(*claimed(OURS, 0x90), 10.3)  # our own claim echoed: ignored
    assert ac.holds(10.3) and ac.due(10.3) == []
    assert ac.received(*request(), 11.0)  # a request to everyone: our claim again
    assert [f.data for f in ac.due(11.0)] == [OURS.to_bytes()]
    assert ac.received(*request(0x90), 12.0)  # ... and to us
    assert len(ac.due(12.0)) == 1
    assert not ac.received(*request(0x27), 13.0)  # to someone else: not ours to answer
    other_pgn = can_id(6, PGN_REQUEST, 0x00, GLOBAL_ADDRESS), (65097).to_bytes(3, "little")
    assert not ac.received(*other_pgn, 13.0)
    assert ac.due(13.0) == []
    assert ac.received(*claimed(LOWER, 0x27), 14.0)  # another address's claim: nothing
    assert ac.holds(14.0) and ac.due(14.0) == []


def test_a_request_to_it_for_a_pgn_it_does_not_send_gets_a_nack() -> None:
    """J1939-21: a request addressed to the node for a PGN it does not send is answered with
    a NACK (Acknowledgment, PGN 59392: control 1, the requester, the PGN), to everyone; a
    request to everyone, or for a PGN it sends anyway, gets none; nor one before the address
    is ours. The request is the real tractor's: its cluster (0x17) asks each ECU by address
    for proprietary PGN 0xFF09 (the logs: 0x17 → 0x00, 0x03, 0x06, 0x47)."""
    ac = AddressClaim(OURS, 0x90, seed=0, sent_pgns=frozenset({PGN_ISB}))
    ff09 = (0xFF09).to_bytes(3, "little")
    ac.received(can_id(6, PGN_REQUEST, 0x17, 0x90), ff09, 0.0)
    assert ac.due(0.0) == []  # no address yet: no answer from it
    ac.begin(0.0)
    ac.due(0.0)
    assert ac.holds(1.0)
    assert ac.received(can_id(6, PGN_REQUEST, 0x17, 0x90), ff09, 1.0)
    (nack,) = ac.due(1.0)
    assert nack.arbitration_id == can_id(6, PGN_ACKNOWLEDGMENT, 0x90, GLOBAL_ADDRESS)
    assert nack.data == bytes([1, 0xFF, 0xFF, 0xFF, 0x17, 0x09, 0xFF, 0x00])
    assert not ac.received(can_id(6, PGN_REQUEST, 0x17, GLOBAL_ADDRESS), ff09, 2.0)
    assert not ac.received(can_id(6, PGN_REQUEST, 0x17, 0x00), ff09, 2.0)  # another's
    isb = PGN_ISB.to_bytes(3, "little")
    assert not ac.received(can_id(6, PGN_REQUEST, 0x17, 0x90), isb, 2.0)  # comes anyway
    assert ac.due(2.0) == [] and ac.status()["nacks_sent"] == 1
    assert ac.claims_sent == 1  # the NACK is not a claim


def test_a_higher_name_is_answered_and_a_lower_one_takes_the_address() -> None:
    ac = AddressClaim(OURS, 0x90, retry_s=10.0, seed=3)
    ac.begin(0.0)
    ac.due(0.0)
    assert ac.holds(1.0)
    ac.received(*claimed(HIGHER, 0x90), 2.0)  # ours has the priority: we say so again
    assert [f.arbitration_id & 0xFF for f in ac.due(2.0)] == [0x90]
    assert ac.holds(2.0) and ac.contests_won == 1
    ac.received(*claimed(LOWER, 0x90), 3.0)  # theirs has it: yield
    assert not ac.holds(3.0) and ac.state == "lost" and ac.holder == LOWER
    (change,) = ac.take_changes()
    assert "another ECU claimed source address 0x90" in change and "0x" in change
    # a Cannot Claim from the null address within 0-153 ms, nothing from 0x90
    cannot = ac.due(3.2)
    assert [f.arbitration_id for f in cannot] == [can_id(6, PGN_ADDRESS_CLAIMED, NULL_ADDRESS)]
    ac.received(*request(), 4.0)  # asked: Cannot Claim again
    assert [f.arbitration_id & 0xFF for f in ac.due(4.2)] == [NULL_ADDRESS]
    # the retry asks who holds what, from the null address; the holder answers: no claim of
    # ours contests it, no new log line, the next question retry_s later
    assert ac.next_due() == pytest.approx(13.0)
    (ask,) = ac.due(13.0)
    assert ask.arbitration_id == can_id(6, PGN_REQUEST, NULL_ADDRESS, GLOBAL_ADDRESS)
    assert requested_pgn(ask.data) == PGN_ADDRESS_CLAIMED
    ac.received(*claimed(LOWER, 0x90), 13.01)
    assert ac.due(14.5) == [] and ac.state == "lost" and ac.take_changes() == []
    assert ac.next_due() == pytest.approx(23.01)
    # the next question goes unanswered for the response time: the address is free, claimed
    assert [f.arbitration_id & 0xFF for f in ac.due(23.01)] == [NULL_ADDRESS]
    assert ac.due(23.01 + RESPONSE_TIMEOUT_S - 0.01) == []
    t = 23.01 + RESPONSE_TIMEOUT_S
    assert [f.arbitration_id & 0xFF for f in ac.due(t)] == [0x90]
    assert not ac.holds(t + 0.1)
    assert ac.holds(t + CONTENTION_S)
    (change,) = ac.take_changes()
    assert "claimed again" in change
    assert ac.holder is None


def test_the_ecu_name_comes_from_the_config_and_the_machine_id(tmp_path: Path) -> None:
    mid = tmp_path / "machine-id"
    mid.write_text("4f1c7d2e9b8a4c6d8e0f1a2b3c4d5e6f\n")
    cfg = config_from_dict({"can": {"name_manufacturer_code": 1407, "name_function": 130}})
    a = ecu_name(cfg.can, mid)
    assert a.manufacturer_code == 1407 and a.function == 130 and a.industry_group == 2
    assert not a.self_configurable
    assert a == ecu_name(cfg.can, mid)  # the same computer: the same NAME
    mid.write_text("0123456789abcdef0123456789abcdef\n")
    assert ecu_name(cfg.can, mid).identity_number != a.identity_number
    assert ecu_name(cfg.can, tmp_path / "none").identity_number == 0
    fixed = config_from_dict({"can": {"name_identity_number": 42}})
    assert ecu_name(fixed.can, mid).identity_number == 42


def test_the_supervisor_claims_first_answers_and_goes_silent_while_another_holds_it(
    tmp_path: Path,
) -> None:
    """The permit supervisor on a virtual bus beside another node: its first frame is its
    claim and its permit frames start after the contention time; it answers a request for
    claims; another ECU's lower NAME on its address silences it (a Cannot Claim from 254,
    then nothing from its address: the controller's silence timeout stops the deck; its own
    decision is a FAULT naming the holder) until a question to the bus finds the address
    free, when it claims it and the permit frames come back by themselves."""
    channel = f"claim-{uuid.uuid4().hex[:8]}"
    raw = config_to_dict(default_config())
    raw["can"].update(interface="virtual", channel=channel, address_claim_retry_s=0.6)
    raw["can"]["name_identity_number"] = 0x1234
    cfg = config_from_dict(raw, tmp_path, "test config")
    sup = Supervisor(cfg)
    ours = ecu_name(cfg.can)
    seen: list[tuple[float, int, int, bytes]] = []  # (time, PGN, source, data)

    def run(seconds: float) -> None:
        end = time.monotonic() + seconds
        while (now := time.monotonic()) < end:
            sup.gate.renew(Lease(True, "INSIDE", "", "", 1.0, 0.0, 0.0, 0.0, now), now)
            sup._arrival["speed"] = sup._arrival[FORCE] = now
            sup._decide(now)
            while (m := other.recv(0.0)) is not None:
                ident = parse_id(m.arbitration_id)
                seen.append((time.monotonic(), ident.pgn, ident.source, bytes(m.data)))
            time.sleep(0.005)

    def first(pgn: int, source: int, after: float = 0.0) -> float:
        return next(t for t, p, s, _ in seen if p == pgn and s == source and t > after)

    with receiving(sup, channel) as other:
        run(0.5)
        assert seen[0][1:] == (PGN_ADDRESS_CLAIMED, 0x90, ours.to_bytes())
        assert first(PGN_ISB, 0x90) - seen[0][0] >= CONTENTION_S - 0.01
        t = time.monotonic()
        other.send(can.Message(arbitration_id=request()[0], data=request()[1]))
        run(0.2)
        assert first(PGN_ADDRESS_CLAIMED, 0x90, t) - t < 0.1  # answered
        t = time.monotonic()
        ident, data = claimed(LOWER, 0x90)
        other.send(can.Message(arbitration_id=ident, data=data))
        run(0.3)
        cannot = first(PGN_ADDRESS_CLAIMED, NULL_ADDRESS, t)
        assert cannot - t <= 0.2
        d = sup.gate.current
        assert not d.permit and d.reason == Reason.FAULT and "held by another ECU" in d.detail
        assert sup.sender is None  # nothing due from it: the loop sleeps until the retry
        silent_from = time.monotonic()
        run(0.2)  # before the retry (0.6 s after the loss): nothing from 0x90
        assert not [x for x in seen if x[0] > silent_from and x[2] == 0x90]
        assert sup.status(time.monotonic())["can_address"]["state"] == "lost"
        run(0.5 + RESPONSE_TIMEOUT_S + 0.5)  # asked who holds it; no answer: claimed, permits
        asked = first(PGN_REQUEST, NULL_ADDRESS, silent_from)
        retry = first(PGN_ADDRESS_CLAIMED, 0x90, silent_from)
        assert retry - asked >= RESPONSE_TIMEOUT_S - 0.01
        back = first(PGN_ISB, 0x90, silent_from)
        assert back - retry >= CONTENTION_S - 0.01
        # a stop first (counter 0), then the permit as a change (counter 1): a controller
        # that counted the transitions before the silence follows the new sender
        isb = [decode_isb(x[3]) for x in seen if x[1] == PGN_ISB and x[0] >= back][:2]
        assert isb == [(0, ISB_STOP), (1, ISB_PERMIT)]
        assert sup.gate.current.permit
        assert sup.status(time.monotonic())["can_address"]["state"] == "held"
