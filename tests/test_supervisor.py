"""The permit supervisor: leases, and the supervisor process with a scripted estimation
process on python-can's virtual bus, the mock mower controller listening."""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import can
import pytest
from _supervisor import receiving
from _tools import load_tool

from drivers.can.isobus import open_bus, parse_id, pgn_filters
from drivers.can.mock_mower import MockMowerController
from drivers.can.mock_speed import MockSpeedSensor
from drivers.can.permit import HB_ERROR
from drivers.can.speed import SpeedReader
from mowerhw.common.strictjson import no_constant
from mowerhw.common.supervisor_socket import parse_reply, supervisor_socket
from mowerhw.config import config_from_dict, config_to_dict, default_config
from mowerhw.mow.containment import Reason, State
from mowerhw.runtime.devices import CanFrames
from mowerhw.supervisor.lease import Lease, SupervisorGate
from mowerhw.supervisor.mock_estimator import scripted_estimator
from mowerhw.supervisor.process import FORCE, Supervisor
from mowerhw.supervisor.status_socket import CLIENTS_PER_S, StatusSocket, ask_supervisor


def _lease(permit: bool = True, reason: str = "") -> Lease:
    return Lease(permit, "INSIDE", reason, "", 1.0, 0.0, 0.0, 0.0, 0.0)


def test_a_lease_permits_only_while_it_is_fresh() -> None:
    gate = SupervisorGate(0.08)
    d = gate.decide(0.0)
    assert not d.permit and d.reason == Reason.ESTIMATOR_LATE and "no permit lease yet" in d.detail
    gate.renew(_lease(), 1.0)
    assert gate.decide(1.05).permit
    late = gate.decide(1.1)
    assert not late.permit and late.reason == Reason.ESTIMATOR_LATE
    assert "no permit lease for 0.100 s (limit 0.08 s)" in late.detail
    assert gate.expired == 1 and not gate.decide(1.12).permit and gate.expired == 1
    gate.renew(_lease(False, "OUTSIDE"), 1.2)
    assert gate.decide(1.21).reason == "OUTSIDE"  # the estimator's own halt passes through
    gate.renew(_lease(), 1.25)
    settling = gate.decide(1.26)  # in time again, but it was late: settle first
    assert not settling.permit and "leases in time again for 0.06 of 1.0 s" in settling.detail
    for k in range(1, 21):
        gate.renew(_lease(), 1.25 + 0.05 * k)
    assert gate.decide(2.26).permit
    own = gate.decide(2.27, (Reason.SENSOR_STALE, "speed silent"))
    assert not own.permit and own.reason == Reason.SENSOR_STALE  # its own checks come first


@contextlib.contextmanager
def _supervised(
    tmp_path: Path, script: tuple[tuple[float, str], ...] | None = None, **supervisor: Any
) -> Iterator[tuple[Supervisor, MockMowerController]]:
    """A supervisor (its ``supervisor.*`` keys as given) with the scripted estimation
    process (its default script, or ``script``) on a virtual bus of its own, the mock mower
    controller and a speed sensor (which the supervisor sees too) beside it."""
    channel = f"sup-{uuid.uuid4().hex[:8]}"
    raw = config_to_dict(default_config())
    raw["can"].update(interface="virtual", channel=channel)
    raw["supervisor"].update(supervisor)
    raw["runtime"]["control_socket"] = str(tmp_path / "control.sock")  # its status socket's too
    cfg = config_from_dict(raw, tmp_path, "test config")
    bus, speed_bus = open_bus("virtual", channel), open_bus("virtual", channel)
    mower = MockMowerController(bus, permit_source=cfg.can.source_address).start()
    speed = MockSpeedSensor(speed_bus, lambda t: 0.3).start()
    target = scripted_estimator if script is None else partial(scripted_estimator, script=script)
    try:
        yield Supervisor(cfg, child_target=target), mower
    finally:
        mower.stop()
        speed.stop()
        bus.shutdown()
        speed_bus.shutdown()


def test_the_supervisor_halts_a_quiet_estimator_and_ends_when_it_dies(tmp_path: Path) -> None:
    out: dict[str, Any] = {}
    heartbeats: list[int] = []
    with _supervised(tmp_path) as (sup, mower):

        def watch() -> None:
            while "status" not in out:
                hb = mower.state.hb_sequence
                if hb is not None and (not heartbeats or heartbeats[-1] != hb):
                    heartbeats.append(hb)
                mower.evaluate(time.monotonic())
                time.sleep(0.005)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        try:
            out["status"] = sup.run()
            time.sleep(0.1)
        finally:
            out.setdefault("status", None)
            watcher.join(2.0)
    events = mower.state.events
    runs = [e for e in events if e.running]
    stops = [e for e in events if not e.running]
    assert out["status"] == 1  # the estimation process died: the service ends, non-zero
    assert len(runs) >= 2, events  # permitted, halted while quiet, permitted again
    quiet_stop = next(e for e in stops if e.t > runs[0].t)
    assert quiet_stop.reason == "ISB stop"
    assert sup.gate.expired >= 1
    assert HB_ERROR in heartbeats  # the fault is announced by the heartbeat
    assert not mower.deck_running


#: the mock estimation process: permits for a second, then alive but silent (hung)
HANG_SCRIPT = ((1.0, "permit"), (60.0, "quiet"), (0.0, "exit"))


def test_a_hung_estimation_process_is_killed_and_the_service_ends(
    tmp_path: Path, caplog: Any
) -> None:
    """Alive but silent (a deadlock, a blocked read): the lease halts the deck at once, and
    after ``supervisor.child_hang_s`` the supervisor kills it and ends with exit status 1,
    for systemd to restart the service (before, it halted forever and fed the watchdog)."""
    with _supervised(tmp_path, HANG_SCRIPT, child_hang_s=1.5) as (sup, mower):
        t0 = time.monotonic()
        with caplog.at_level("ERROR", logger="mowerhw.supervisor"):
            status = sup.run()
        took = time.monotonic() - t0
        mower.evaluate(time.monotonic())
    assert status == 1
    assert "the estimation process has sent nothing for 1." in caplog.text
    assert "(limit 1.5 s, supervisor.child_hang_s): it is hung; killing it" in caplog.text
    assert "did not stop" not in caplog.text  # killed at once, not after 3 s
    assert took < 10.0  # not the script's 60 s: it was killed, not waited for
    assert not sup.child.is_alive() and sup.gate.expired >= 1
    assert not mower.deck_running


def test_the_supervisor_ends_when_its_can_receive_thread_dies(tmp_path: Path, caplog: Any) -> None:
    """Crash-only for the supervisor's own thread too: a CAN receive thread that dies (a bug
    on some frame) ends the service with exit status 1 and a line naming it, instead of a
    supervisor that goes on blind to the speed, the switches and address claims."""

    def bad_frame(*_: Any) -> None:
        raise RuntimeError("a bug on this frame")

    with _supervised(tmp_path, ((30.0, "permit"), (0.0, "exit"))) as (sup, mower):
        sup._speed.handle = bad_frame  # type: ignore[method-assign]
        t0 = time.monotonic()
        with caplog.at_level("ERROR", logger="mowerhw.supervisor"):
            status = sup.run()
        took = time.monotonic() - t0
    assert status == 1 and took < 15.0  # not the script's 30 s
    assert "the CAN receive thread died (RuntimeError('a bug on this frame'))" in caplog.text
    assert not mower.deck_running


def test_the_switch_frame_round_trips_and_decodes_with_the_shipped_dbc() -> None:
    from drivers.can.isobus import can_id
    from drivers.can.switches import PGN_SWITCHES, Switches, decode_switches, encode_switches

    for sw in (Switches(), Switches(lifted=True), Switches(bumped=True, stop=True)):
        assert decode_switches(encode_switches(sw)) == sw
    assert decode_switches(bytes([0x01] + [0xFF] * 7)) is None  # reserved bits not set: refused
    cantools = pytest.importorskip("cantools")
    dbc = Path(__file__).resolve().parents[1] / "configs" / "mowerhw.dbc"
    db = cantools.database.load_file(str(dbc), frame_id_mask=0x03FFFF00)
    msg = db.get_message_by_name("MowerSwitches")
    assert msg.frame_id & 0x03FFFF00 == can_id(6, PGN_SWITCHES, 0x28) & 0x03FFFF00
    got = msg.decode(encode_switches(Switches(lifted=True, stop=True)))
    assert got == {"Lifted": 1, "BumperPressed": 0, "StopButtonPressed": 1}


def test_a_failing_can_bus_is_reopened_with_backoff_and_logged_per_change(
    tmp_path: Path, monkeypatch: Any, caplog: Any
) -> None:
    import mowerhw.supervisor.canport as canport

    raw = config_to_dict(default_config())
    raw["can"].update(interface="virtual", channel=f"down-{uuid.uuid4().hex[:8]}")
    cfg = config_from_dict(raw, tmp_path, "test config")
    fail = {"on": True}

    def fake_open(interface: str, channel: str, bitrate: int = 0, **kw: Any) -> Any:
        if fail["on"]:
            raise OSError("No such device")
        return open_bus(interface, channel)

    monkeypatch.setattr(canport, "open_bus", fake_open)
    port = canport.CanPort(cfg)
    t0 = time.monotonic()
    tries = [t for t in (t0 + k * 0.05 for k in range(4000)) if port.ensure(t) or True]
    # 200 s of retries: the backoff grows to 2 s, so ~100 attempts, not 4000
    assert port.bus is None and 90 <= port.errors <= 120
    text = caplog.text
    assert text.count("cannot open (No such device); reopening with backoff") == 1
    assert "still down after 6" in text  # the periodic summary (every 60 s)
    fail["on"] = False
    assert port.ensure(t0 + 1e6) and "open again after" in caplog.text
    assert tries
    port.bus.shutdown()  # type: ignore[union-attr]


def test_a_lease_goes_up_the_pipe_as_plain_values_and_comes_back_the_same() -> None:
    """A lease crosses the pipe as a tuple of numbers and strings (enum members become their
    values) and the supervisor makes the same lease from it."""
    import pickle

    lease = Lease(
        False,
        State.NEAR_EDGE,
        Reason.OUTSIDE,
        "past the edge",
        -0.2,
        1.5,
        -2.0,
        0.3,
        12.5,
        (0.1, -0.2, 9.8),
    )
    wire = pickle.loads(pickle.dumps(lease.wire()))
    assert all(type(v) in (bool, str, float, tuple) for v in wire)
    again = Lease.from_wire(wire)
    assert again == lease and type(again.reason) is str and again.accel == (0.1, -0.2, 9.8)
    assert again.earlier_forces == ()
    earlier = Lease(*lease.wire()[:-1], ((12.48, 0.0, 0.1, 9.8),))
    assert Lease.from_wire(pickle.loads(pickle.dumps(earlier.wire()))) == earlier


def test_every_samples_force_reaches_the_safety_checks_not_only_the_leases(
    tmp_path: Path,
) -> None:
    """An unchanged decision renews the lease at most every ``RENEW_S``: at 50 Hz about every
    other sample's decision went without a lease, and its specific force never reached the
    supervisor's safety checks (a bench run: 17,208 leases for about 32,500 samples) — a
    collision one sample long had an even chance of being missed. Such a force now rides on
    the next lease (``earlier_forces``), oldest first, and the supervisor feeds it to the checks
    before the lease's own: a jolt between two leases halts; a timer's decision repeating the
    same force adds nothing; a force-less IMU (NaN) queues nothing."""
    from mowerhw.mow.gate import Decision
    from mowerhw.supervisor.link import RENEW_S, SupervisorLink

    raw = config_to_dict(default_config())
    raw["can"].update(interface="virtual", channel=f"force-{uuid.uuid4().hex[:8]}")
    raw["can"]["address_claim"] = False
    cfg = config_from_dict(raw, tmp_path, "test config")
    sup = Supervisor(cfg)
    ours, theirs = multiprocessing.Pipe(duplex=True)
    sup.conn = theirs
    link = SupervisorLink(ours)
    mowing = Decision(True, "INSIDE", "", "", 1.0)
    still = (0.0, 0.0, 9.81)
    jolt = (cfg.safety.bump_accel_mps2 + 5.0, 0.0, 9.81)
    try:
        now = time.monotonic()
        link.send_decision(mowing, (0.0, 0.0, 0.0), now, still)  # a lease
        sup._drain(now)
        assert sup.counts["leases"] == 1 and sup.safety.halt(now) is None
        link.send_decision(mowing, (0.0, 0.0, 0.0), now + 0.002, jolt)  # within RENEW_S
        link.send_decision(mowing, (0.0, 0.0, 0.0), now + 0.003, jolt)  # a timer's repeat
        link.send_decision(mowing, (0.0, 0.0, 0.0), now + 0.004, (math.nan,) * 3)
        sup._drain(now + 0.004)
        assert sup.counts["leases"] == 1  # no lease of their own …
        assert sup.safety.halt(now + 0.004) is None  # … and, till the next, not seen
        time.sleep(RENEW_S)
        link.send_decision(mowing, (0.0, 0.0, 0.0), now + 0.025, still)
        sup._drain(now + 0.025)
        assert sup.counts["leases"] == 2
        halt = sup.safety.halt(now + 0.025)
        assert halt is not None and halt[0] == Reason.COLLISION, halt
        assert sup.gate.lease.earlier_forces == ((now + 0.002, *jolt),)
        assert not link._unsent_forces  # sent with that lease
    finally:
        if sup.port.bus is not None:
            sup.port.bus.shutdown()
        ours.close()
        theirs.close()


def test_the_link_reads_the_supervisor_on_the_event_loop() -> None:
    """In the estimation process the supervisor's messages are read on the daemon's event
    loop (no reader thread), when it polls before a decision — not by a wake-up of their
    own: a ground-speed frame reaches the daemon's callback before the poll returns, a lift
    notice too, and the supervisor's stop — or its pipe closing — ends the process."""
    import asyncio
    import multiprocessing

    from drivers.can.speed import encode_speed

    cfg = default_config()
    ours, theirs = multiprocessing.Pipe(duplex=True)
    got: dict[str, list[Any]] = {"speed": [], "lost": [], "lifted": []}

    async def main(stop_by: str) -> None:
        from mowerhw.supervisor.link import SupervisorLink

        link = SupervisorLink(ours)
        link.output(cfg, got["speed"].append, got["lost"].append, None, got["lifted"].append)
        assert link.open()
        assert theirs.recv() == ("ready", None)
        assert not any(t.name == "supervisor-rx" for t in threading.enumerate())
        can_id, data = encode_speed(0.42)
        theirs.send(("can", (time.monotonic(), can_id, data, True)))
        theirs.send(("lifted", True))
        await asyncio.sleep(0.05)
        assert not got["speed"] and not got["lifted"]  # the loop did not wake for them
        link.poll()  # a decision's
        assert got["speed"] and got["lifted"]  # handled within the poll: in the decision
        if stop_by == "stop":
            theirs.send(("stop", None))
        else:
            theirs.close()
        await asyncio.sleep(0.01)
        link.poll()

    asyncio.run(main("stop"))
    assert [round(s.speed_mps, 2) for s in got["speed"]] == [0.42]
    assert got["lifted"] == [True] and got["lost"] == ["the supervisor asked to stop"]
    ours, theirs = multiprocessing.Pipe(duplex=True)
    got = {"speed": [], "lost": [], "lifted": []}
    asyncio.run(main("close"))
    assert got["lost"] and "the supervisor's pipe closed" in got["lost"][0]


def test_the_supervisors_own_speed_halt_is_timed_from_the_speeds_limit(tmp_path: Path) -> None:
    """A mowing lease, then the ground speed silent past its limit: the supervisor stops the
    deck itself and times that stop from the moment the limit ran out (the halt latency of
    the process that sends the frames, whatever the estimation side is doing); a stop the
    lease already made is not its own."""
    raw = config_to_dict(default_config())
    # the frames from the first decision on (no 250 ms of address claim first)
    raw["can"].update(interface="virtual", channel=f"own-{uuid.uuid4().hex[:8]}")
    raw["can"]["address_claim"] = False
    cfg = config_from_dict(raw, tmp_path, "test config")
    sup = Supervisor(cfg)
    told: list[tuple[str, Any]] = []
    sup._to_child = told.append  # type: ignore[method-assign]
    limit = cfg.speed.stale_after_s
    try:
        now = time.monotonic()
        sup._arrival["speed"] = sup._arrival[FORCE] = now
        sup.gate.renew(_lease(), now)
        sup._decide(now)
        assert sup.gate.current.permit and not sup.own_halt_ms
        late = now + limit + 0.004
        sup.gate.renew(_lease(), late)
        sup._arrival[FORCE] = late  # the IMU's specific force keeps coming
        while time.monotonic() < late:
            time.sleep(0.001)
        sup._decide(late)
        assert not sup.gate.current.permit and "seen by the supervisor" in sup.gate.current.detail
        # the estimation side hears of it at once, not at the next 0.5 s status (the page)
        statuses = [body for kind, body in told if kind == "status"]
        assert [st["permit"] for st in statuses] == [True, False]
        assert "seen by the supervisor" in statuses[-1]["detail"]
        assert len(sup.own_halt_ms) == 1 and 4.0 <= sup.own_halt_ms[0] < 1000.0
        assert sup.status(late)["own_halt_ms"]["n"] == 1
        sup._decide(late + 0.01)  # still halted: no second stop, no second figure
        assert len(sup.own_halt_ms) == 1
    finally:
        if sup.port.bus is not None:
            sup.port.bus.shutdown()


def test_the_estimation_side_reads_a_real_tractors_speed_as_a_reader_on_the_bus_would(
    tmp_path: Path,
) -> None:
    """A real tractor's bus (John Deere log: CCVS1 speed signed by the ETC2 gear, among 9k
    frames of 37 PGNs in 33 s) into the supervisor: the frames its bus lets through and passes
    down give the estimation side the same speed samples as a reader on the bus itself (the
    gear's frames as well as the speed's: before, a CCVS1 speed was never valid behind the
    supervisor); it reads only those PGNs and the switches'; recording, it reads everything."""
    logs = sorted(load_tool("check_real_can").LOGS.glob("*.log"))
    if not logs:
        pytest.skip("real tractor CAN logs not present (../shared/data/real)")
    frames = [m for m in can.CanutilsLogReader(str(logs[-1])) if m.is_extended_id]
    channel = f"jd-{uuid.uuid4().hex[:8]}"
    raw = config_to_dict(default_config())
    raw["can"].update(interface="virtual", channel=channel)
    raw["speed"].update(source="ccvs1", ccvs1_direction="etc2")
    cfg = config_from_dict(raw, tmp_path, "test config")
    sup = Supervisor(cfg)
    passed: list[tuple[str, Any]] = []
    sup._to_child = passed.append  # type: ignore[method-assign]
    # ETC2, CCVS1, the switches; address claims and requests for them (ISO 11783-5)
    reads = {61445, 65265, cfg.safety.switches_pgn, 60928, 59904}
    assert sup.port.filters == pgn_filters(reads)
    direct = SpeedReader("ccvs1", ccvs1_direction="etc2")
    want = []
    with receiving(sup, channel) as tx:
        for m in frames:
            tx.send(m)
            s = direct.handle(m.arbitration_id, bytes(m.data), time.monotonic())
            if s is not None:
                want.append((s.valid, s.speed_mps if s.valid else None))
        t_end = time.monotonic() + 10.0
        while len(passed) < direct.stats.frames + direct.stats.gear_frames:
            assert time.monotonic() < t_end, (len(passed), vars(direct.stats))
            time.sleep(0.02)
    got: list[Any] = []
    child = CanFrames(cfg, got.append)
    for kind, body in passed:
        assert kind == "can"
        child.handle(*body)
    assert [(s.valid, s.speed_mps if s.valid else None) for s in got] == want
    assert sum(v for v, _ in want) > 100  # valid speeds: 0 m/s, signed by the gear
    assert len(passed) == direct.stats.frames + direct.stats.gear_frames < len(frames) // 10
    recording = Supervisor(cfg, record=tmp_path / "run.mcap")
    assert recording.port.filters is None  # it records every frame: no filter


def test_an_imu_without_specific_force_cannot_mow(tmp_path: Path) -> None:
    """Lift and tilt are judged by the specific force the leases carry: leases without it
    (an IMU configured for rates only) permit only until its limit, then the supervisor
    halts naming why; leases with it permit again (fail-closed, not a silent loss of the
    lift and tilt checks)."""
    raw = config_to_dict(default_config())
    raw["can"].update(interface="virtual", channel=f"force-{uuid.uuid4().hex[:8]}")
    cfg = config_from_dict(raw, tmp_path, "test config")
    sup = Supervisor(cfg)
    limit = cfg.safety.specific_force_stale_s
    estimator, sup.conn = multiprocessing.Pipe()

    step = 0.02  # a lease every 20 ms
    sent: list[tuple[float, bool]] = []  # (time, with specific force) of every lease

    def leases(n: int, accel: tuple[float, float, float]) -> float | None:
        """``n`` leases with ``accel``, one a step after the last; when the deck first halted."""
        halted = None
        for _ in range(n):
            t = sent[-1][0] + step if sent else time.monotonic()
            sent.append((t, not math.isnan(accel[0])))
            estimator.send(("lease", Lease(True, "INSIDE", "", "", 1.0, 0, 0, 0, t, accel).wire()))
            sup._drain(t)
            sup._decide(t)
            if halted is None and not sup.gate.current.permit:
                halted = t
        return halted

    try:
        sup._arrival["speed"] = time.monotonic() + 60.0  # the ground speed fresh throughout
        level = (0.0, 0.0, 9.81)
        assert leases(10, level) is None
        last_level = sent[-1][0]
        nan = (math.nan, math.nan, math.nan)
        stopped = leases(round(2 * limit / step), nan)  # the IMU sends rates only
        assert stopped is not None and limit < stopped - last_level <= limit + step + 1e-6
        d = sup.gate.current
        assert not d.permit and d.reason == Reason.SENSOR_STALE, d
        assert "sends no acceleration: lift and tilt cannot be checked" in d.detail
        leases(60, level)  # it comes again
        assert sup.gate.current.permit, sup.gate.current
    finally:
        estimator.close()
        if sup.port.bus is not None:
            sup.port.bus.shutdown()


def test_the_switch_frame_counts_only_from_the_controllers_address_when_set(
    tmp_path: Path,
) -> None:
    """Proprietary B PGNs are each maker's own: with ``safety.switches_address`` set, the
    same PGN from another ECU saying "lifted" is not the mower's lift switch; from the
    controller it is (and with no address set, from anyone)."""
    from drivers.can.isobus import can_id
    from drivers.can.switches import Switches, encode_switches

    def lifted_after(address: int | None, sender: int) -> bool:
        channel = f"sw-{uuid.uuid4().hex[:8]}"
        raw = config_to_dict(default_config())
        raw["can"].update(interface="virtual", channel=channel)
        raw["safety"].update(switches_address=address)
        cfg = config_from_dict(raw, tmp_path, "test config")
        sup = Supervisor(cfg)
        with receiving(sup, channel) as tx:
            frame_id = can_id(6, cfg.safety.switches_pgn, sender)
            data = encode_switches(Switches(lifted=True))
            tx.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=True))
            time.sleep(0.3)
            halt = sup.safety.halt(time.monotonic())
        return halt is not None and halt[0] == Reason.LIFTED

    assert lifted_after(0x28, 0x28) and lifted_after(None, 0x31)
    assert not lifted_after(0x28, 0x31)


def test_a_recording_gets_every_frame_the_supervisor_receives_and_sends(tmp_path: Path) -> None:
    """Recording, the supervisor passes down every frame it receives — the switches' too —
    and every frame it sends (SocketCAN gives a sender none of its own back), so the
    estimation process's recording holds the bus both ways: rx and tx."""
    from drivers.can.isobus import PGN_HEARTBEAT, PGN_ISB, can_id
    from drivers.can.switches import Switches, encode_switches

    channel = f"rec-{uuid.uuid4().hex[:8]}"
    raw = config_to_dict(default_config())
    raw["can"].update(interface="virtual", channel=channel)
    cfg = config_from_dict(raw, tmp_path, "test config")
    sup = Supervisor(cfg, record=tmp_path / "run.mcap")
    passed: list[tuple[str, Any]] = []
    sup._to_child = passed.append  # type: ignore[method-assign]
    with receiving(sup, channel) as tx:
        switches = can_id(6, cfg.safety.switches_pgn, 0x28)
        tx.send(can.Message(arbitration_id=switches, data=encode_switches(Switches())))
        sup._send_frames(_lease(), time.monotonic())  # the address claim first
        time.sleep(0.3)
        sup._send_frames(_lease(), time.monotonic())  # claimed: the permit frames
        time.sleep(0.1)
    recorded: list[tuple[int, bool]] = []

    class Recorder:
        def can(self, _ns: int, ident: int, _data: bytes, _ext: bool, is_rx: bool) -> None:
            recorded.append((parse_id(ident).pgn, is_rx))

    child = CanFrames(cfg, lambda s: None, Recorder())  # type: ignore[arg-type]
    for kind, body in passed:
        assert kind == "can"
        child.handle(*body)
    assert (cfg.safety.switches_pgn, True) in recorded  # received
    assert {(PGN_ISB, False), (PGN_HEARTBEAT, False)} <= set(recorded)  # sent
    assert recorded.index((60928, False)) < recorded.index((PGN_ISB, False))  # claim first


def test_the_supervisor_answers_on_its_own_socket_while_the_estimation_process_is_silent(
    tmp_path: Path,
) -> None:
    """The control socket is the estimation process's: while that process is hung, `mowerhw
    ctl status` gets no reply there, and asks the supervisor's status socket, which says the
    deck is halted, why (the lease ran out) and for how long the process has been silent."""
    replies: list[dict[str, Any]] = []
    ctl: list[subprocess.CompletedProcess[str]] = []
    done = threading.Event()
    hang_s = 8.0  # room for two `mowerhw ctl` runs to start on a loaded machine
    with _supervised(tmp_path, HANG_SCRIPT, child_hang_s=hang_s) as (sup, _mower):
        sock = sup.cfg.runtime.control_socket

        def ask() -> None:
            while not done.is_set():
                with contextlib.suppress(OSError, ConnectionError, ValueError):
                    replies.append(ask_supervisor(sock, 0.5))
                    est = replies[-1]["estimation"]
                    if not ctl and est["alive"] and (est["silent_s"] or 0.0) > 1.0:
                        # both at once: each starts a Python, which on a loaded CI machine
                        # takes seconds, and the supervisor ends the service at the hang limit
                        procs = [
                            subprocess.Popen(
                                [sys.executable, "-m", "mowerhw", "ctl", "--socket"]
                                + [str(sock), "--timeout", "0.5", cmd],
                                stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE,
                                text=True,
                            )
                            for cmd in ("status", "supervisor")
                        ]
                        for proc in procs:
                            out, err = proc.communicate(timeout=30)
                            ctl.append(
                                subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
                            )
                time.sleep(0.05)

        asker = threading.Thread(target=ask, daemon=True)
        asker.start()
        try:
            assert sup.run() == 1
        finally:
            done.set()
            asker.join(35.0)
        left = supervisor_socket(sock).exists()
    assert any(r["permit"] for r in replies)  # permitted while the leases came
    silent = [
        r for r in replies if r["estimation"]["alive"] and (r["estimation"]["silent_s"] or 0) > 0.5
    ]
    assert silent, replies[-3:]
    assert all(not r["permit"] and r["reason"] == Reason.ESTIMATOR_LATE for r in silent)
    assert "no permit lease for" in silent[-1]["detail"]
    assert silent[-1]["estimation"]["hang_limit_s"] == hang_s and silent[-1]["who"] == "supervisor"
    assert ctl, "the estimation process was never silent for a second"
    out = ctl[0]
    assert out.returncode == 1
    assert "mowerhw ctl: cannot reach the daemon at" in out.stderr  # the control socket
    assert "the permit supervisor holds the deck halted (ESTIMATOR_LATE: no permit lease for" in (
        out.stderr
    )
    assert "has sent nothing for" in out.stderr
    reply = json.loads(out.stdout, parse_constant=no_constant)  # strict JSON on stdout
    assert reply["ok"] is False and reply["supervisor"]["reason"] == Reason.ESTIMATOR_LATE
    # `ctl supervisor` asks the supervisor alone: at once, exit 0, its status as JSON
    asked = ctl[1]
    assert asked.returncode == 0 and "holds the deck halted (ESTIMATOR_LATE" in asked.stderr
    status = json.loads(asked.stdout, parse_constant=no_constant)
    assert status["who"] == "supervisor" and status["estimation"]["alive"] is True
    assert not left  # removed when the supervisor stopped


def test_the_status_socket_never_waits_for_a_client(tmp_path: Path) -> None:
    """A client that connects and never reads, many at once, or one that sends garbage: the
    supervisor's loop answers or drops each at once and keeps serving."""
    sock_path = tmp_path / "control.sock"
    server = StatusSocket(sock_path, 0o660)
    assert server.open()
    big = {"ok": True, "pad": "x" * 400_000}  # more than a socket's buffer holds
    try:
        hogs = [socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) for _ in range(3)]
        for h in hogs:
            h.connect(str(server.path))
            h.sendall(b"\x00garbage{\n")
        t0 = time.monotonic()
        for _ in range(3):
            assert server.listener(t0) is not None
            server.serve(lambda: big)
        assert time.monotonic() - t0 < 1.0
        assert server.dropped == 3 and server.answered == 0
        got: dict[str, Any] = {}

        def read() -> None:
            got.update(ask_supervisor(sock_path, 2.0))

        reader = threading.Thread(target=read)
        reader.start()
        deadline = time.monotonic() + 3.0
        while reader.is_alive() and time.monotonic() < deadline:
            if server.listener(time.monotonic()) is not None:
                server.serve(lambda: {"ok": True, "permit": False, "x": math.nan})
            time.sleep(0.01)
        reader.join()
        assert got == {"ok": True, "permit": False, "x": None}  # strict JSON: NaN is null
        for h in hogs:
            h.close()
    finally:
        server.close()
    assert not server.path.exists()


def test_the_status_socket_answers_a_flood_at_a_bounded_rate(tmp_path: Path) -> None:
    """The supervisor runs at real-time priority: a flood of clients gets at most
    CLIENTS_PER_S answers a second, then the socket is not listened to until the next
    second (the rest wait in the kernel's backlog)."""
    server = StatusSocket(tmp_path / "control.sock", 0o660)
    assert server.open()
    flood = [socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) for _ in range(CLIENTS_PER_S + 5)]
    try:
        for f in flood:
            f.connect(str(server.path))
        turns = 0
        while server.listener(100.0) is not None and turns < 100:
            server.serve(lambda: {"ok": True})
            turns += 1
        assert server.answered == CLIENTS_PER_S and turns == -(-CLIENTS_PER_S // 4)
        assert server.listener(100.9) is None  # this second's share is taken
        assert server.listener(101.0) is not None  # the next second's
        server.serve(lambda: {"ok": True})
        assert server.answered == CLIENTS_PER_S + 4
    finally:
        for f in flood:
            f.close()
        server.close()


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        (b"", "closed the connection without a reply"),
        (b'{"permit": NaN}\n', "NaN is not an allowed number"),
        (b'{"permit": true, "permit": false}\n', "appears twice"),
        (b"[1, 2]\n", "not a JSON object"),
        (b"[" * 50_000, "nested too deep"),
        (b"\xff\xfe{}", "Expecting value|decode"),
        (b"{" + b" " * 70_000 + b"}", "a reply over 65536 bytes"),
    ],
)
def test_a_status_reply_that_is_not_the_supervisors_is_refused_by_name(
    tmp_path: Path, raw: bytes, message: str
) -> None:
    """Whatever answers on the status socket's path, a client gets the reply's fault named
    (ConnectionError or ValueError), never a crash or a reply it should not trust."""
    with pytest.raises((ValueError, ConnectionError), match=message):
        parse_reply(raw, tmp_path / "control.sock.supervisor")


def test_the_supervisors_loop_busy_past_the_stall_limit_counts_as_a_stall(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A loop held up by its own work — here one decision 50 ms long, while leases keep
    coming — is a stall, though no wake-up came past its deadline (a message was waiting
    each time: stop 73 found a 0.3 s hold-up in the page's restart counted as none)."""
    original = Supervisor._decide
    held: list[float] = []

    def held_once(self: Supervisor, now: float) -> None:
        if not held and self.counts["leases"] > 10:
            held.append(now)
            time.sleep(0.05)
        original(self, now)

    monkeypatch.setattr(Supervisor, "_decide", held_once)
    with _supervised(tmp_path, script=((1.0, "permit"), (0.0, "exit"))) as (sup, _):
        sup.run()
    assert held
    assert sup.counts["loop_stalls_over_20ms"] >= 1
    assert sup.max_loop_lag_ms >= 50.0
