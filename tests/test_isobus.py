"""ISO 11783 on CAN: speed decoding rules, the permit/halt output and the mock mower controller
on python-can's ``virtual`` bus (and ``vcan0`` when the kernel has it), DBC decoding, fuzzing."""

import itertools
import math
import threading
import time
from pathlib import Path

import can
import pytest
from _tools import load_tool
from _waiting import wait_for
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.can.address_claim import (
    PGN_ACKNOWLEDGMENT,
    PGN_ADDRESS_CLAIMED,
    PGN_REQUEST,
    AddressClaim,
    IsoName,
)
from drivers.can.isobus import (
    GLOBAL_ADDRESS,
    PGN_CCVS1,
    PGN_ETC2,
    PGN_GBSD,
    PGN_HEARTBEAT,
    PGN_ISB,
    PGN_WBSD,
    can_id,
    open_bus,
    parse_id,
    pgn_filters,
)
from drivers.can.mock_mower import MockMowerController
from drivers.can.mock_speed import MockSpeedSensor
from drivers.can.permit import (
    HB_INITIAL,
    HB_SHUTDOWN,
    PermitSender,
    Status,
    decode_isb,
    decode_status,
    encode_heartbeat,
    encode_isb,
    encode_status,
)
from drivers.can.speed import SpeedReader, decode_speed, encode_speed, invalid_detail

DBC = Path(__file__).resolve().parent.parent / "configs" / "mowerhw.dbc"
GBSD_ID = can_id(3, PGN_GBSD, 0x80)
_channels = itertools.count()


def fresh_channel() -> str:
    return f"test-isobus-{next(_channels)}-{time.monotonic_ns()}"


# --- identifiers --------------------------------------------------------------------------


def test_identifier_layout_of_design_section_7():
    assert can_id(3, PGN_GBSD, 0x80) == 0x0CFE4980
    assert can_id(3, PGN_ISB, 0x90) == 0x0CFD0290
    assert can_id(3, PGN_HEARTBEAT, 0x90) == 0x0CF0E490  # PF 0xF0 ≥ 240: broadcast
    # PF < 240 is addressed: PS is the destination, not part of the PGN
    addressed = can_id(6, 0xEA00, 0x26, destination=0x81)
    assert addressed == 0x18EA8126
    ident = parse_id(addressed)
    assert (ident.pgn, ident.source, ident.destination, ident.priority) == (0xEA00, 0x26, 0x81, 6)
    assert parse_id(0x0CFE4980).pgn == PGN_GBSD


# --- speed decoding rules -----------------------------------------------------------------


def frame(speed_raw: int, dist_raw: int = 0, byte7: int = 0xFD) -> bytes:
    return speed_raw.to_bytes(2, "little") + dist_raw.to_bytes(4, "little") + bytes([0xFF, byte7])


def test_speed_scaling_and_direction():
    s = decode_speed(GBSD_ID, frame(1234, 56789, 0xFD), t=1.0)
    assert s.valid and s.speed_mps == pytest.approx(1.234) and s.distance_m == pytest.approx(56.789)
    assert s.source == "ground" and s.source_address == 0x80 and s.t == 1.0
    rev = decode_speed(GBSD_ID, frame(500, 0, 0xFC), t=1.0)
    assert rev.valid and rev.speed_mps == pytest.approx(-0.5)
    top = decode_speed(GBSD_ID, frame(64255), t=0.0)
    assert top.valid and top.speed_mps == pytest.approx(64.255)
    wheel = decode_speed(can_id(3, PGN_WBSD, 0x21), frame(100), t=0.0)
    assert wheel.valid and wheel.source == "wheel" and wheel.source_address == 0x21


def test_reserved_bits_are_masked_not_required():
    # bits 3–8 of byte 7 and byte 6 are reserved: 1 on the wire, but 0 must not matter either
    for byte7, byte6 in [(0xFD, 0xFF), (0x01, 0x00), (0x55, 0x12)]:
        data = bytearray(frame(750, 0, byte7))
        data[6] = byte6
        s = decode_speed(GBSD_ID, bytes(data), t=0.0)
        assert s.valid and s.speed_mps == pytest.approx(0.75)


@pytest.mark.parametrize(
    "data, why",
    [
        (frame(0xFE00), "error"),
        (frame(0xFEFF), "error"),
        (frame(0xFF00), "not available"),
        (frame(0xFFFF), "not available"),
        (frame(64256), "out of range"),
        (frame(1000, 0, 0xFE), "a direction error"),
        (frame(1000, 0, 0xFF), "direction not available"),
        (frame(1000)[:7], "a 7-byte frame (8 expected)"),
        (b"", "a 0-byte frame (8 expected)"),
    ],
)
def test_error_and_not_available_give_an_invalid_sample_never_a_number(data, why):
    s = decode_speed(GBSD_ID, data, t=0.0)
    assert s is not None and not s.valid and math.isnan(s.speed_mps)
    assert s.reason == why and s.message == "GBSD"
    assert invalid_detail(s) == f"speed sensor reports {why} (GBSD from 0x80)"


def test_distance_not_available_keeps_the_speed():
    s = decode_speed(GBSD_ID, frame(300, 0xFFFFFFFF), t=0.0)
    assert s.valid and s.distance_m is None and s.speed_mps == pytest.approx(0.3)
    assert decode_speed(GBSD_ID, frame(300, 0xFE000000), t=0.0).distance_m is None


def test_frames_that_are_not_speed_give_none():
    assert decode_speed(can_id(3, PGN_ISB, 0x90), encode_isb(1, True)) is None
    assert decode_speed(can_id(6, 0xFF10, 0x90), bytes(8)) is None


def test_encode_decode_round_trip():
    for v in (-2.5, -0.001, 0.0, 0.4, 1.25, 64.255):
        ident, data = encode_speed(v, 10.0, source_address=0x44)
        s = decode_speed(ident, data, t=0.0)
        assert s.valid and s.speed_mps == pytest.approx(v, abs=5e-4)
        assert s.source_address == 0x44
    ident, data = encode_speed(1.0, error=True)
    assert not decode_speed(ident, data, t=0.0).valid


def test_speed_reader_filters_source_address():
    r = SpeedReader(source="ground", sensor_address=0x80)
    assert r.last_valid is None  # nothing heard yet
    assert r.handle(*encode_speed(1.0, 0.0, 0x80), t=1.0).valid
    assert r.handle(*encode_speed(9.0, 0.0, 0x81), t=1.05) is None  # another sensor
    assert r.handle(*encode_speed(9.0, 0.0, 0x80, pgn=PGN_WBSD), t=1.05) is None  # wheel-based
    assert r.stats.wrong_source == 1 and r.stats.other_frames == 1
    # an invalid sample does not refresh the speed; it is kept to say why
    assert not r.handle(*encode_speed(1.0, 0.0, 0x80, error=True), t=1.25).valid
    assert r.last_valid.t == 1.0 and r.last_invalid.t == 1.25 and r.stats.invalid == 1
    with pytest.raises(ValueError, match="ground, wheel, ccvs1, any"):
        SpeedReader(source="gps")


def ccvs1(kmh_raw: int, sa: int = 0x00) -> tuple[int, bytes]:
    """A CCVS1 frame as J1939-71 defines it: PGN 65265 (0xFEF1), priority 6, byte 1 parking
    brake / cruise switches (all 'not available' here), bytes 2–3 SPN 84 wheel-based vehicle
    speed, 1/256 km/h per bit, little-endian; the rest not available."""
    ident = (6 << 26) | (0xFE << 16) | (0xF1 << 8) | sa
    return ident, bytes([0xFF, kmh_raw & 0xFF, kmh_raw >> 8, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])


def etc2(selected_raw: int, current_raw: int, sa: int = 0x03) -> tuple[int, bytes]:
    """ETC2 (PGN 61445, 0xF005): byte 0 selected gear, byte 3 current gear, offset −125."""
    ident = (6 << 26) | (0xF0 << 16) | (0x05 << 8) | sa
    return ident, bytes([selected_raw, 0xFF, 0xFF, current_raw, 0xFF, 0xFF, 0xFF, 0xFF])


def test_ccvs1_speed_from_the_j1939_definition():
    """SPN 84: 0x0E10 = 3600/256 km/h = 14.0625 km/h = 3.90625 m/s; the sign from ETC2."""
    r = SpeedReader(source="ccvs1")
    s = r.handle(*ccvs1(0x0E10, sa=0x17), t=0.0)
    assert not s.valid and "no ETC2 gear" in s.reason  # no direction yet: never a guess
    r.handle(*etc2(125 + 3, 0xFF), t=0.05)  # selected gear 3, current not available
    s = r.handle(*ccvs1(0x0E10, sa=0x17), t=0.1)
    assert s.valid and s.speed_mps == pytest.approx(3.90625) and s.message == "CCVS1"
    r.handle(*etc2(125 - 1, 125 - 1), t=0.15)  # reverse
    assert r.handle(*ccvs1(256), t=0.2).speed_mps == pytest.approx(-1 / 3.6)
    assert r.handle(*ccvs1(256), t=1.3).reason.startswith("no direction")  # gear too old
    r.handle(*etc2(251, 0xFF), t=1.35)  # park
    assert r.handle(*ccvs1(0), t=1.4).speed_mps == 0.0
    assert r.handle(*ccvs1(0xFAFF), t=1.5).speed_mps == pytest.approx(0xFAFF / 256 / 3.6)
    for raw, why in [(0xFE00, "error"), (0xFFFF, "not available"), (0xFC00, "out of range")]:
        s = r.handle(*ccvs1(raw, sa=0x47), t=1.6)
        assert not s.valid and invalid_detail(s) == f"speed sensor reports {why} (CCVS1 from 0x47)"
    fwd = SpeedReader(source="ccvs1", ccvs1_direction="forward")
    assert fwd.handle(*ccvs1(512), t=0.0).speed_mps == pytest.approx(2 / 3.6)
    # a CCVS1 frame is not a ground speed unless asked for
    assert SpeedReader(source="ground").handle(*ccvs1(512), t=0.0) is None


def test_gate_names_what_the_speed_sensor_said():
    from mowerhw.mow.gate import PermitGate

    gate = PermitGate({"speed": 0.3})
    na = decode_speed(can_id(3, PGN_GBSD, 0x47), bytes([0xFF] * 8), t=10.0)
    notes = {"speed": (10.0, invalid_detail(na))}
    assert gate.stale(10.1, {"speed": None}, notes) == (
        "speed",
        "speed sensor reports not available (GBSD from 0x47)",
    )
    _, old = gate.stale(12.0, {"speed": None}, notes)
    assert old == "no speed data yet; last heard 2.0 s ago: " + notes["speed"][1]
    assert gate.stale(10.1, {"speed": 10.05}, notes) is None  # good data after the note
    _, silent = gate.stale(10.5, {"speed": 10.05}, notes)
    assert silent.startswith("speed silent for 0.450 s")


# --- fuzzing ------------------------------------------------------------------------------

ids = st.integers(min_value=0, max_value=(1 << 29) - 1)
payloads = st.binary(min_size=0, max_size=8)


@settings(max_examples=400, deadline=None)
@given(ids, payloads)
def test_fuzz_decode_speed_never_raises_and_never_accepts_a_bad_value(arb, data):
    s = decode_speed(arb, data, t=0.0)
    if s is None:
        assert parse_id(arb).pgn not in (PGN_GBSD, PGN_WBSD, 65265)
        return
    if s.message == "CCVS1":
        raw = data[1] | data[2] << 8 if len(data) >= 3 else None
        assert s.valid == (len(data) == 8 and raw <= 64255)
        assert s.valid or (math.isnan(s.speed_mps) and s.reason)
        return
    if s.valid:
        raw = data[0] | data[1] << 8
        assert len(data) == 8 and raw <= 64255 and data[7] & 3 in (0, 1)
        assert math.isfinite(s.speed_mps) and abs(s.speed_mps) == pytest.approx(raw / 1000)
    else:
        assert math.isnan(s.speed_mps) and s.reason


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["isb", "hb", "status", "other"]), payloads)))
def test_fuzz_mower_controller_never_runs_without_a_permit_frame(frames):
    ctl = MockMowerController(bus=None)
    pgn = {"isb": PGN_ISB, "hb": PGN_HEARTBEAT, "status": 0xFF10, "other": PGN_GBSD}
    for i, (kind, data) in enumerate(frames):
        ctl.handle(can_id(3, pgn[kind], 0x90), data, now=i * 0.01)
        running = ctl.evaluate(now=i * 0.01)
        if running:  # only ever on a well-formed ISB that says permit
            assert ctl.state.isb_permit
            assert any(k == "isb" and len(d) >= 8 and d[7] & 3 == 1 for k, d in frames[: i + 1])
    for _, data in frames:
        if len(data) >= 8:
            decode_status(data)  # never raises on any 8 bytes


def test_status_round_trip_and_not_available():
    s = Status("NEAR_EDGE", True, "", 0.42, 12.35, -3.1, math.radians(90))
    d = decode_status(encode_status(s))
    assert (d.state, d.permit, d.reason) == ("NEAR_EDGE", True, "")
    assert d.signed_distance_m == pytest.approx(0.42)
    assert d.x_m == pytest.approx(12.35) and d.y_m == pytest.approx(-3.1)
    assert d.heading_rad == pytest.approx(math.radians(90), abs=0.013)
    na = decode_status(encode_status(Status()))
    assert na.state == "UNKNOWN" and not na.permit and na.reason == "NOT_LOCALIZED"
    assert math.isnan(na.signed_distance_m) and math.isnan(na.x_m) and math.isnan(na.heading_rad)


# --- end to end on a virtual bus ------------------------------------------------------------


def test_speed_decoded_end_to_end_on_a_virtual_bus():
    ch = fresh_channel()
    sensor_bus, other_bus, rx = (open_bus("virtual", ch) for _ in range(3))
    profile = lambda t: 0.5 + 0.2 * math.sin(t)  # noqa: E731
    sensor = MockSpeedSensor(sensor_bus, profile, source_address=0x80).start()
    intruder = MockSpeedSensor(other_bus, lambda t: 9.0, source_address=0x81).start()
    reader = SpeedReader(sensor_address=0x80)
    got = []
    try:
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            msg = rx.recv(timeout=0.05)
            if msg is not None:
                s = reader.handle(msg.arbitration_id, bytes(msg.data), time.monotonic())
                if s is not None:
                    got.append(s)
        assert len(got) >= 8  # 10 Hz for 1 s
        assert all(s.valid and s.source_address == 0x80 for s in got)
        assert all(0.3 - 1e-3 <= s.speed_mps <= 0.7 + 1e-3 for s in got)  # never the intruder's 9
        assert reader.stats.wrong_source >= 8
        sensor.paused.set()  # unplugged
        t_pause = time.monotonic()
        after = []
        while time.monotonic() - t_pause < 0.5:
            msg = rx.recv(timeout=0.05)
            if msg is not None:
                s = reader.handle(msg.arbitration_id, bytes(msg.data), time.monotonic())
                if s is not None and s.valid:
                    after.append(s)
        assert len(after) <= 1  # at most the frame in flight: nothing fresh, the gate halts
    finally:
        sensor.stop()
        intruder.stop()
        for b in (sensor_bus, other_bus, rx):
            b.shutdown()


class AppLoop:
    """The application's loop, as the daemon will run it: tick the permit sender every 10 ms.
    ``kill()`` stops the loop dead (a hung or crashed application) without a shutdown."""

    def __init__(self, sender: PermitSender) -> None:
        self.sender = sender
        self.permit = False
        self.killed = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.killed.is_set():
            now = time.monotonic()
            self.sender.set(self.permit, now, Status("INSIDE", self.permit, "", 1.0, 0.0, 0.0, 0.0))
            self.sender.tick(now)
            time.sleep(0.01)

    def kill(self) -> float:
        self.killed.set()
        self.thread.join()
        return time.monotonic()


@pytest.fixture
def permit_link():
    ch = fresh_channel()
    tx, rx = open_bus("virtual", ch), open_bus("virtual", ch)
    sender = PermitSender(tx, source_address=0x90)
    mower = MockMowerController(rx, permit_source=0x90, timeout_s=0.3).start()
    app = AppLoop(sender)
    yield sender, mower, app
    app.killed.set()
    mower.stop()
    tx.shutdown()
    rx.shutdown()


def test_the_default_is_halt(permit_link):
    sender, mower, app = permit_link
    app.thread.start()
    assert wait_for(lambda: mower.state.isb_time is not None)
    time.sleep(0.3)
    assert not mower.deck_running and mower.why_not(time.monotonic()) == "ISB stop"
    assert mower.state.hb_sequence is not None and sender.stats.heartbeats_sent >= 3


def test_mower_stops_within_300_ms_when_the_permit_sender_is_killed(permit_link):
    sender, mower, app = permit_link
    app.permit = True
    app.thread.start()
    assert wait_for(lambda: mower.deck_running), "the mock mower never started the deck"
    time.sleep(0.3)
    assert mower.deck_running
    t_kill = app.kill()
    last_frame = sender.last_isb_time
    assert wait_for(lambda: not mower.deck_running, timeout=1.0)
    stop = mower.last_stop()
    assert stop.reason in ("ISB timeout", "heartbeat timeout")
    after_kill, after_last = stop.t - t_kill, stop.t - last_frame
    print(
        f"killed sender: deck stopped {after_kill * 1e3:.0f} ms after the kill, "
        f"{after_last * 1e3:.0f} ms after the last ISB frame ({stop.reason})"
    )
    # The timeout runs from the last frame heard (≤ 10 ms before the kill): 300 ms, plus the
    # controller's 5 ms poll and thread scheduling.
    assert after_kill <= 0.3 + 0.05


def test_mower_stops_on_a_counter_jump_and_recovers_on_a_proper_transition(permit_link):
    sender, mower, app = permit_link
    app.permit = True
    app.thread.start()
    assert wait_for(lambda: mower.deck_running)
    t_jump = time.monotonic()
    sender.counter = (sender.counter + 2) & 0xFF  # two transitions lost: the counter jumps by 2
    assert wait_for(lambda: not mower.deck_running, timeout=0.5)
    stop = mower.last_stop()
    assert stop.reason == "ISB counter jump"
    print(f"counter jump: deck stopped {(stop.t - t_jump) * 1e3:.0f} ms after the jump")
    assert stop.t - t_jump <= 0.3
    time.sleep(0.3)
    assert not mower.deck_running  # stays stopped although ISB still says permit
    app.permit = False  # a proper stop → permit transition re-synchronises
    time.sleep(0.05)
    app.permit = True
    assert wait_for(lambda: mower.deck_running, timeout=0.5)


def test_shutdown_sends_stop_then_heartbeat_255(permit_link):
    sender, mower, app = permit_link
    app.permit = True
    app.thread.start()
    assert wait_for(lambda: mower.deck_running)
    app.kill()
    t = time.monotonic()
    sender.shutdown(t)
    assert wait_for(lambda: not mower.deck_running, timeout=0.2)
    assert wait_for(lambda: mower.state.hb_sequence == HB_SHUTDOWN, timeout=0.2)
    assert not mower.state.isb_permit
    assert mower.state.status.reason == "SHUTTING_DOWN"


def test_heartbeat_sequence_and_isb_counter_on_the_wire():
    ch = fresh_channel()
    tx, rx = open_bus("virtual", ch), open_bus("virtual", ch)
    try:
        sender = PermitSender(tx, source_address=0x90, period_s=0.1, heartbeat_period_s=0.1)
        for k in range(260):  # 26 s of simulated time, sent at once
            sender.tick(k * 0.1)
        sender.set(True, 26.0)
        sender.set(False, 26.01)
        frames = []
        while (msg := rx.recv(timeout=0.05)) is not None:
            frames.append(msg)
        hb = [m.data[0] for m in frames if parse_id(m.arbitration_id).pgn == PGN_HEARTBEAT]
        assert hb[0] == HB_INITIAL and hb[1:252] == list(range(251)) and hb[252] == 0
        isb = [decode_isb(m.data) for m in frames if parse_id(m.arbitration_id).pgn == PGN_ISB]
        assert isb[0] == (0, 0) and isb[-2] == (1, 1) and isb[-1] == (2, 0)
        pgns = {PGN_ISB: 3, PGN_HEARTBEAT: 3, 0xFF10: 6}
        assert all(
            parse_id(m.arbitration_id).priority == pgns[parse_id(m.arbitration_id).pgn]
            for m in frames
        )
    finally:
        tx.shutdown()
        rx.shutdown()


def test_a_change_goes_out_at_once_and_the_periodic_frames_stay_together():
    """ISB, status and heartbeat of one period leave in one tick (one wake-up of the loop),
    also after changes at odd times; a change is sent at once, between the periods."""
    ch = fresh_channel()
    tx, rx = open_bus("virtual", ch), open_bus("virtual", ch)
    try:
        sender = PermitSender(tx, source_address=0x90, period_s=0.1, heartbeat_period_s=0.1)
        sent_at: list[tuple[float, int]] = []
        changes = {1.037: True, 2.561: False, 2.604: True, 4.299: False}
        for k in range(600):  # 6 s of a loop ticking every 10 ms, the changes between ticks
            now = k * 0.01
            for t_change, permit in list(changes.items()):
                if t_change <= now:
                    del changes[t_change]
                    before = sender.stats.isb_sent
                    assert sender.set(permit, t_change)
                    assert sender.stats.isb_sent == before + 1  # at once
                    sent_at.extend((t_change, m.arbitration_id) for m in drain(rx))
            if now >= sender.next_due():
                sender.tick(now)
                sent_at.extend((now, m.arbitration_id) for m in drain(rx))
        periodic = {}
        for t, arb in sent_at:
            if round(t, 3) not in (1.037, 2.561, 2.604, 4.299):
                periodic.setdefault(round(t, 3), set()).add(parse_id(arb).pgn)
        assert len(periodic) == 60  # one tick a period, every frame in it
        assert all(pgns == {PGN_ISB, PGN_HEARTBEAT, 0xFF10} for pgns in periodic.values())
        ticks = sorted(periodic)
        assert all(abs(b - a - 0.1) < 1e-6 for a, b in itertools.pairwise(ticks))
    finally:
        tx.shutdown()
        rx.shutdown()


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(timeout=0.0)) is not None:
        out.append(msg)
    return out


@pytest.mark.skipif(not Path("/sys/class/net/vcan0").exists(), reason="no vcan0 on this kernel")
def test_permit_over_socketcan_vcan0():  # pragma: no cover - needs the vcan kernel module
    tx, rx = open_bus("socketcan", "vcan0"), open_bus("socketcan", "vcan0")
    try:
        sender = PermitSender(tx, source_address=0x90)
        mower = MockMowerController(rx, permit_source=0x90).start()
        for _ in range(30):
            now = time.monotonic()
            sender.set(True, now)
            sender.tick(now)
            time.sleep(0.01)
        assert mower.deck_running
        time.sleep(0.4)
        assert not mower.deck_running and mower.last_stop().reason.endswith("timeout")
        mower.stop()
    finally:
        tx.shutdown()
        rx.shutdown()


# --- DBC ---------------------------------------------------------------------------------


def test_every_frame_decodes_with_cantools_against_the_shipped_dbc():
    cantools = pytest.importorskip("cantools")
    db = cantools.database.load_file(str(DBC), frame_id_mask=0x03FFFF00)

    def decode(arb: int, data: bytes) -> tuple[str, dict]:
        msg = db.get_message_by_frame_id(arb)  # masked: any source address, any priority
        return msg.name, msg.decode(data, decode_choices=True)

    name, sig = decode(*encode_speed(1.234, 56.789, source_address=0x33))
    assert name == "GBSD" and sig["GroundBasedMachineSpeed"] == pytest.approx(1.234)
    assert sig["GroundBasedMachineDistance"] == pytest.approx(56.789)
    assert sig["GroundBasedDirection"] == "Forward"
    name, sig = decode(*encode_speed(-0.5, 1.0, pgn=PGN_WBSD))
    assert name == "WBSD" and sig["WheelBasedMachineDirection"] == "Reverse"
    assert sig["WheelBasedMachineSpeed"] == pytest.approx(0.5)

    name, sig = decode(*encode_speed(0.0, pgn=PGN_WBSD, error=True))
    assert name == "WBSD" and sig["WheelBasedMachineSpeed"] == "Error"
    name, sig = decode(*ccvs1(0x0E10, sa=0x47))
    assert name == "CCVS1" and sig["WheelBasedVehicleSpeed"] == pytest.approx(14.0625)
    assert decode(*ccvs1(0xFFFF))[1]["WheelBasedVehicleSpeed"] == "NotAvailable"
    gbsd_na = decode(can_id(3, PGN_GBSD, 0x47), bytes([0xFF] * 8))[1]  # the tractor's frame
    assert gbsd_na["GroundBasedMachineSpeed"] == "NotAvailable"
    assert gbsd_na["GroundBasedDirection"] == "NotAvailable"
    name, sig = decode(*etc2(125 - 2, 251))
    assert name == "ETC2" and sig["TransmissionSelectedGear"] == -2
    assert sig["TransmissionCurrentGear"] == "Park"

    name, sig = decode(can_id(3, PGN_ISB, 0x90), encode_isb(7, True))
    assert name == "ISB" and sig["IsbTransitionCounter"] == 7
    assert sig["IsbStopAllImplementOperations"] == "Permit"
    assert (
        decode(can_id(3, PGN_ISB, 0x90), encode_isb(8, False))[1]["IsbStopAllImplementOperations"]
        == "Stop"
    )

    name, sig = decode(can_id(3, PGN_HEARTBEAT, 0x90), encode_heartbeat(HB_SHUTDOWN))
    assert name == "Heartbeat" and sig["HeartbeatSequenceNumber"] == "ShuttingDown"
    assert decode(can_id(3, PGN_HEARTBEAT, 0x90), encode_heartbeat(17))[1] == {
        "HeartbeatSequenceNumber": 17
    }

    st_ = Status("NEAR_EDGE", False, "UNCERTAIN", -0.37, 20.5, -7.25, math.radians(45))
    name, sig = decode(can_id(6, 0xFF10, 0x90), encode_status(st_))
    assert name == "MowerhwStatus"
    assert sig["ContainmentState"] == "NEAR_EDGE" and sig["HaltReason"] == "UNCERTAIN"
    assert sig["MowingPermitted"] == 0
    assert sig["SignedDistanceToEdge"] == pytest.approx(-0.37)
    assert sig["PositionX"] == pytest.approx(20.5) and sig["PositionY"] == pytest.approx(-7.25)
    assert sig["Heading"] == pytest.approx(45.0)
    print(f"cantools decoded GBSD, WBSD, ISB, Heartbeat, MowerhwStatus: {sig}")

    name_ = IsoName(0x1ABCDE, 1407, 5, 17, 130, 3, 9, 2, False)
    name, sig = decode(can_id(6, PGN_ADDRESS_CLAIMED, 0x90), name_.to_bytes())
    assert name == "AddressClaimed"
    assert (sig["NameIdentityNumber"], sig["NameManufacturerCode"]) == (0x1ABCDE, 1407)
    assert (sig["NameEcuInstance"], sig["NameFunctionInstance"], sig["NameFunction"]) == (
        5,
        17,
        130,
    )
    assert (sig["NameDeviceClass"], sig["NameDeviceClassInstance"]) == (3, 9)
    assert (sig["NameIndustryGroup"], sig["NameSelfConfigurableAddress"]) == (2, 0)
    # the real tractor's request for every claim (ECU 0x00 to the global address)
    request = can_id(6, PGN_REQUEST, 0x00, GLOBAL_ADDRESS), bytes.fromhex("00EE00")
    assert decode(*request) == ("RequestForAddressClaimed", {"RequestedPgn": PGN_ADDRESS_CLAIMED})
    # mowerhw's NACK of the tractor cluster's request for 0xFF09 (addressed to it)
    ac = AddressClaim(name_, 0x90, seed=0)
    ac.begin(0.0)
    ac.due(0.0)
    assert ac.holds(1.0)
    ac.received(can_id(6, PGN_REQUEST, 0x17, 0x90), (0xFF09).to_bytes(3, "little"), 1.0)
    (nack,) = ac.due(1.0)
    name, sig = decode(nack.arbitration_id, nack.data)
    assert name == "Acknowledgment" and sig["AckControlByte"] == "NACK"
    assert (sig["AckAddress"], sig["AckPgn"]) == (0x17, 0xFF09)


def test_dbc_lists_the_identifiers_the_drivers_build():
    cantools = pytest.importorskip("cantools")
    db = cantools.database.load_file(str(DBC))
    ids = {m.name: m.frame_id for m in db.messages}
    assert ids["GBSD"] == can_id(3, PGN_GBSD, 0x80)
    assert ids["WBSD"] == can_id(3, PGN_WBSD, 0x80)
    assert ids["ISB"] == can_id(3, PGN_ISB, 0x90)
    assert ids["Heartbeat"] == can_id(3, PGN_HEARTBEAT, 0x90)
    assert ids["MowerhwStatus"] == can_id(6, 0xFF10, 0x90)
    assert ids["AddressClaimed"] == can_id(6, PGN_ADDRESS_CLAIMED, 0x90)
    assert ids["RequestForAddressClaimed"] == can_id(6, PGN_REQUEST, 0x00, GLOBAL_ADDRESS)
    assert ids["Acknowledgment"] == can_id(6, PGN_ACKNOWLEDGMENT, 0x90, GLOBAL_ADDRESS)
    assert all(m.is_extended_frame for m in db.messages)


def test_a_failing_bus_is_counted_not_raised():
    class BrokenBus:
        def send(self, msg, timeout=None):
            raise can.CanOperationError("bus-off")

    sender = PermitSender(BrokenBus())
    sender.set(True, 0.0)
    sender.tick(0.0)
    assert sender.stats.send_errors >= 3


# --- a real tractor's bus --------------------------------------------------------------------


real_can = load_tool("check_real_can")
TRACTOR_LOGS = sorted(real_can.LOGS.glob("*.log")) if real_can.LOGS.exists() else []


@pytest.mark.skipif(not TRACTOR_LOGS, reason=f"real tractor CAN logs not present ({real_can.LOGS})")
@pytest.mark.parametrize("log", TRACTOR_LOGS, ids=lambda p: p.stem)
def test_real_tractor_bus(log):
    """GBSD from 0x47 is always 'not available': every frame is recognised, the speed is never
    fresh, and the halt says what the sensor said; CCVS1 gives a real 0 m/s, signed by ETC2."""
    r = real_can.check(log)
    print(r)
    ground, wheel = r["ground"], r["ccvs1"]
    assert ground["speed_frames_recognised"] == r["gbsd_frames"] >= 128
    assert ground["valid"] == 0 and ground["fresh_fraction"] == 0.0
    assert "speed sensor reports not available (GBSD from 0x47)" in ground["halt_details"]
    assert wheel["valid"] >= 0.9 * wheel["speed_frames_recognised"] > 100
    assert wheel["speed_mps"] == [0.0] and wheel["fresh_fraction"] > 0.3


@pytest.mark.skipif(not TRACTOR_LOGS, reason=f"real tractor CAN logs not present ({real_can.LOGS})")
def test_pgn_filters_let_through_exactly_the_pgns_asked_for_on_a_real_bus() -> None:
    """Every frame of a real tractor's log through python-can's acceptance filters (the
    masks SocketCAN applies in the kernel): what comes out is every frame of the PGNs asked
    for, from any source, and nothing else — an addressed PGN (TP.CM, PF < 240) too."""
    frames = [m for m in can.CanutilsLogReader(str(TRACTOR_LOGS[0])) if m.is_extended_id]
    pgns = {PGN_CCVS1, PGN_ETC2, 0xEC00, 0xFF11}  # with TP.CM, addressed (PS = destination)
    present = {parse_id(m.arbitration_id).pgn for m in frames}
    assert {PGN_CCVS1, PGN_ETC2, 0xEC00} <= present and len(present) > 10
    channel = f"filters-{time.monotonic_ns()}"
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel, can_filters=pgn_filters(pgns))
    try:
        for m in frames:
            tx.send(m)
        got = []
        while (m := rx.recv(timeout=0.2)) is not None:
            got.append(m.arbitration_id)
    finally:
        tx.shutdown()
        rx.shutdown()
    want = [m.arbitration_id for m in frames if parse_id(m.arbitration_id).pgn in pgns]
    assert got == want and 100 < len(want) < len(frames) // 4
    with pytest.raises(ValueError, match="18-bit"):
        pgn_filters([1 << 18])


def test_a_speed_reader_says_which_pgns_it_reads() -> None:
    assert SpeedReader("ground").pgns == {PGN_GBSD}
    assert SpeedReader("ccvs1").pgns == {PGN_CCVS1, PGN_ETC2}  # the gear signs the speed
    assert SpeedReader("ccvs1", ccvs1_direction="forward").pgns == {PGN_CCVS1}
    assert SpeedReader("any").pgns == {PGN_GBSD, PGN_WBSD, PGN_CCVS1, PGN_ETC2}
