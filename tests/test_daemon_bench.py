"""The daemon against mock hardware (the hardware-in-the-loop bench, short case).

A real ``mowerhw run`` process with its real drivers: VN-100 bytes on a pty, GBSD / ISB /
heartbeat / status frames on a CAN bus shared between processes, rendered frames through
the camera interface. The map comes from a pixel-level simulated teach of the same yard (the
full teach-then-mow run is ``mowerhw bench``; its figures are in the README)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from _tools import load_tool

from mowerhw.bench import Bench, FaultSpec

pytestmark = pytest.mark.slow


def test_mows_with_faults_and_recovers(yard_map, tmp_path) -> None:
    faults = [
        FaultSpec("imu-unplug", 8.0, 1.0),
        FaultSpec("speed-stop", 16.0, 1.0),
        FaultSpec("corrupt-map", 24.0, 1.0),
        FaultSpec("exception", 32.0, 1.0),
        FaultSpec("address-conflict", 38.0, 1.0),  # another node takes the CAN address
    ]
    res = Bench(duration_s=46.0, seed=7, out_dir=tmp_path, faults=faults, map_path=yard_map).run()
    print({k: res[k] for k in ("position_rmse_m", "missed_halts", "halt_latency_ms")})
    assert res["missed_halts"] == 0
    assert res["position_rmse_m"] is not None and res["position_rmse_m"] < 0.10
    # after each fault (an IMU gap, an estimator restart) the deck runs on a right pose only
    assert res["permitted_samples_off_over_0.15m"] == 0, res["position_max_while_permitted_m"]
    by_kind = {f["kind"]: f for f in res["faults"]}
    expected = {
        "imu-unplug": "SENSOR_STALE",
        "speed-stop": "SENSOR_STALE",
        "corrupt-map": "MAP_INVALID",
        "exception": "FAULT",
    }
    for kind, reason in expected.items():
        f = by_kind[kind]
        print(kind, f["stop_after_ms"], f["reason"], f["recovered_after_s"])
        if f["deck_was_running"]:  # how fast is measured by tools/bench_daemon.py
            assert f["stop_after_ms"] is not None, f
            # the fault's own reason, first or while it lasted (one CI run: a camera frame
            # 2 ms late in the instant of the exception — "camera silent for 0.252 s" was
            # the first reason asked, 25 ms after the injection)
            assert any(reason in r for r in [f["reason"], *f["daemon_reasons"]]), f
        else:  # halted already, for what halted it (one CI run: at 16 s a relocalization
            # after the IMU's gap was still checking, NOT_LOCALIZED)
            assert f["reason"], f
        assert f["recovered"], f
    # the CAN address taken: the supervisor yields it (silence: the controller stops the
    # deck), names the holder, and claims it again once the other node has left the bus
    f = by_kind["address-conflict"]
    assert f["recovered"], f
    held = "supervisor: FAULT: CAN source address 0x90 is held by another ECU"
    if f["deck_was_running"]:
        assert any(held in r for r in [f["reason"], *f["daemon_reasons"]]), f
    else:  # halted already, for what halted it (one CI run beside the browser test: the
        # estimator late at 38 s, the supervisor's settle second after it still running)
        assert f["reason"], f
    assert res["can_address"]["claims_seen"] == 2  # the start, the address regained
    assert res["can_address"]["frames_before_first_claim"] == 0
    # the map file was restored, never half-written by the daemon
    assert (tmp_path / "lawn.json").read_bytes() == yard_map.read_bytes()
    log = (tmp_path / "daemon.log").read_text()
    assert "HALT MAP_INVALID" in log
    # the supervisor yielded the address and said to whom, halted or not
    assert "another ECU claimed source address 0x90" in log
    # the IMU's silence is in the log: as the halt's reason, or — when another stream went
    # stale in the same instant and the halt named it (a frame late from the bench's renderer
    # on a busy machine, seen under the whole suite) — in the note of the IMU's gap
    assert "HALT SENSOR_STALE: imu silent" in log or "imu: a sample again after" in log


def test_bad_config_exits_78(tmp_path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("imu:\n  baudrate: 12345\nruntime:\n  mode: fly\n")
    proc = subprocess.run(
        [sys.executable, "-m", "mowerhw", "run", "--config", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 78
    assert "imu.baudrate: 12345 is not one of" in proc.stderr
    assert "runtime.mode: 'fly' is not one of" in proc.stderr


def test_recorded_run_replays_deterministically(yard_map, tmp_path) -> None:
    from mowerhw.recording.replay import Replay

    rec = tmp_path / "run.mcap"
    bench = Bench(
        duration_s=15.0, seed=7, out_dir=tmp_path / "bench", map_path=yard_map, record=rec
    )
    res = bench.run()
    assert res["missed_halts"] == 0
    outs = [
        Replay(rec, "mow", map_path=yard_map, out_dir=tmp_path / f"r{k}", speed=None).run()
        for k in range(2)
    ]
    for key in ("permit_sequence_sha256", "permit_fraction", "halts_by_reason", "localizer"):
        assert outs[0][key] == outs[1][key], key
    assert outs[0]["messages"]["/camera/image"] >= 40
    assert outs[0]["localizer"]["frames_with_fix"] > 0.5 * outs[0]["localizer"]["frames"]
    assert outs[0]["permit_fraction"] > 0.3
    # the camera's frames between the recorded ones (camera.device_fps 10, 4 recorded) are in
    # the live journal: the replay's camera is as alive as the live one was (without them,
    # 19 SENSOR_STALE halts in 15 s at the bench's 0.25 s limit). Against the live daemon's
    # own stale halts, from its log: the bench's 5-Hz look at the permit misses a halt of a
    # few ms (a loaded CI machine's sensor silent for 0.1 s, which the replay replays)
    stale = outs[0]["halts_by_reason"].get("SENSOR_STALE", 0)
    live_log = bench.daemon_log.read_text(errors="replace")
    live_stale = live_log.count("mowerhw.permit: HALT SENSOR_STALE")
    assert stale <= max(live_stale, res["halts_by_reason"].get("SENSOR_STALE", 0)), (
        outs[0]["halts_by_reason"],
        live_stale,
    )
    print(outs[0]["speed_x_real_time"], outs[0]["permit_fraction"])


def test_started_anywhere_with_no_pose_file_it_localizes_and_mows(yard_map, tmp_path) -> None:
    """``mowerhw bench --start random``: the daemon is stopped, its pose file deleted, the
    mower carried to a random pose inside the lawn; started again, the daemon checks the
    dock pose, finds it wrong, searches the whole map, and mows (issue 18)."""
    res = Bench(duration_s=25.0, seed=7, out_dir=tmp_path, map_path=yard_map, start="random").run()
    assert res["start"]["pose_file"] == "deleted"
    assert res["missed_halts"] == 0
    assert res["relocalization"]["relocalizations"] >= 1
    assert res["permit_fraction"] > 0.3, res["halts_by_reason"]
    assert res["position_rmse_m"] < 0.05
    assert res["permitted_samples_off_over_0.15m"] == 0, res["position_max_while_permitted_m"]


def test_the_bench_counts_only_the_mowings_halts_from_the_daemon_log(tmp_path) -> None:
    """``tools/bench_daemon.py`` counts the supervisor's lease halts and the "imu silent"
    halts in the log lines of the mowing only: the supervisor waiting for its first lease at
    start-up (before the mow request) and what happens after the mowing are not counted."""
    import time

    tool = load_tool("bench_daemon")
    t0 = time.mktime(time.strptime("2026-12-07 04:01:30", "%Y-%m-%d %H:%M:%S"))

    def at(s: float) -> str:
        whole = int(t0 + s)
        ms = round((t0 + s - whole) * 1e3)
        return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(whole)) + f",{ms:03d}"

    lease = "WARNING mowerhw.supervisor: supervisor: HALT ESTIMATOR_LATE: no permit lease"
    silent = "WARNING mowerhw.permit: HALT SENSOR_STALE: imu silent for 0.101 s (limit 0.1 s)"
    log = tmp_path / "daemon.log"
    log.write_text(
        "\n".join(
            [
                f"{at(-2.0)} {lease} yet: estimation starting",  # start-up
                f"{at(5.25)} {lease} for 0.081 s (limit 0.08 s)",  # mowing
                f"{at(7.5)} {silent}",  # mowing
                "a traceback line without a stamp",
                f"{at(12.0)} {lease} for 0.2 s (limit 0.08 s)",  # after the mowing
            ]
        )
    )
    lines = tool._lines_between(log, t0, t0 + 10.0)
    assert tool._lease_halts(lines) == 1 and tool._imu_silent_halts(lines) == 1
    everything = tool._lines_between(log, 0.0, t0 + 60.0)
    assert tool._lease_halts(everything) == 3
    assert tool._lease_halts(tool._lines_between(tmp_path / "none.log", 0.0, 1.0)) == -1
