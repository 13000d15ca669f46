"""The runtime core on its own: no I/O, no threads, no clock — inputs in, decisions out."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest

from mowerhw.camera import load_camchain
from mowerhw.common.magnetic import CompassReference
from mowerhw.common.relocalization import Relocalization
from mowerhw.common.samples import ImuSample, SpeedSample
from mowerhw.config import default_config
from mowerhw.frontend.tracker import FrameTracks
from mowerhw.map import Landmark, LawnMap
from mowerhw.recording.replay import replay_journal
from mowerhw.runtime.core import RuntimeCore
from mowerhw.runtime.journal import JournalDecoder, JournalEncoder
from mowerhw.runtime.pipelines import BuildRequest, MowPipeline, build_pipeline


def _map() -> LawnMap:
    ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    rng = np.random.default_rng(0)
    lms = [
        Landmark(i, rng.uniform(-8, 8, 3), np.eye(3) * 1e-4, descriptor=bytes([i] * 32))
        for i in range(8)
    ]
    boundary = np.c_[6 * np.cos(ang), 4 * np.sin(ang)]
    return LawnMap(boundary=boundary, landmarks=lms, camera=None, teach={})


class ListJournal:
    def __init__(self) -> None:
        self.enc = JournalEncoder()
        self.records: list[dict[str, Any]] = []

    def write(self, kind: str, payload: dict[str, Any]) -> None:  # through JSON, as recorded
        self.records.append(json.loads(json.dumps(self.enc.encode(kind, payload))))


@pytest.fixture(scope="module")
def camera() -> Any:
    cfg = default_config()
    return load_camchain(cfg.camera.calibration, cfg.camera.camchain_key)


def _core(camera: Any, journal: Any = None, build_now: bool = True) -> tuple[RuntimeCore, list]:
    cfg = default_config()
    asked: list[BuildRequest] = []

    def on_build(req: BuildRequest) -> None:
        asked.append(req)
        if build_now:
            core.install(req.serial, build_pipeline(cfg, camera, req))

    core = RuntimeCore(cfg, journal, on_build)
    return core, asked


def _feed(core: RuntimeCore, t0: float, t1: float) -> Any:
    d = None
    for k in range(round((t1 - t0) * 100)):
        t = t0 + 0.01 * k
        d = core.imu(ImuSample(t, np.array([0.0, 0.0, 0.001])), t)
        if k % 10 == 0:
            core.speed(SpeedSample(t, 0.0))
            core.camera_frame(t)
    return d


def test_frames_the_front_end_does_not_take_keep_the_camera_alive(camera: Any) -> None:
    """``camera.device_fps`` above ``camera.fps``: the frames dropped between the front end's
    keep the camera fresh (its limit can be under the front end's period), unless the last
    frame taken was refused (the ones between are of the same mode)."""
    import dataclasses

    cfg = default_config()
    cfg = dataclasses.replace(
        cfg, camera=dataclasses.replace(cfg.camera, device_fps=10.0, stale_after_s=0.25)
    )
    core = RuntimeCore(cfg, None, lambda req: None)

    def late(t: float) -> bool:
        return core.gate.late("camera", t, core.last_arrival["camera"])

    for k in range(100):  # 1 s: frames taken at 4 Hz, the camera's others at 10 Hz
        t = 0.01 * k
        if k % 25 == 0:
            core.camera_frame(t)
        elif k % 10 == 0:
            core.camera_alive(t)
        core.imu(ImuSample(t, np.array([0.0, 0.0, 0.001])), t)
        if k % 10 == 0:
            core.speed(SpeedSample(t, 0.0))
        assert not late(t), t
    # the camera freezes: late once its own limit has passed, not the front end's 0.5 s
    assert not late(0.9 + 0.24) and late(0.9 + 0.26)
    core.camera_refused(1.2, "the camera delivers 640x480 frames")
    core.camera_alive(1.3)
    assert late(1.35)
    core.camera_frame(1.4)
    core.camera_alive(1.5)
    assert not late(1.6)
    # a dropped frame's time read after a newer frame arrived (the runtime reads it at its
    # next decision) does not move the camera's liveness back
    core.camera_frame(1.7)
    core.camera_alive(1.65)
    assert core.last_arrival["camera"] == 1.7


def test_a_chain_built_for_a_request_that_was_overtaken_is_not_installed(camera: Any) -> None:
    core, asked = _core(camera, build_now=False)
    assert core.set_mode("teach") == ""
    old = asked[-1]
    assert core.set_mode("idle") == ""
    assert not core.install(old.serial, build_pipeline(default_config(), camera, old))
    assert core.pipeline is None
    assert core.set_mode("bogus").startswith("mode 'bogus' is not one of")


def test_mow_faults_rebuild_and_halt_with_the_reason(camera: Any) -> None:
    core, asked = _core(camera)
    core.set_mode("mow")
    core.map_loaded(_map())
    assert core.pipeline is not None and asked[-1].kind == "mow"
    d = _feed(core, 0.0, 1.0)
    assert not d.permit and d.reason == "NOT_LOCALIZED"  # no landmark seen yet
    assert core.inject("exception") == ""
    d = _feed(core, 1.0, 1.1)
    assert d.reason == "FAULT" and "estimator restarted" in d.detail
    assert core.counts["estimator_faults"] == 1 and len(asked) == 2  # a new chain was asked for
    assert core.inject("bogus").endswith("allowed: nan, exception")
    d = core.decide(1.5)  # nothing for 0.4 s
    assert d.reason == "SENSOR_STALE" and "imu silent" in d.detail
    core.map_invalid("lawn.json: not valid JSON")
    assert core.decide(1.5).reason == "MAP_INVALID"
    core.shutdown()
    assert core.decide(1.5).reason == "SHUTTING_DOWN"


def test_the_journal_replays_to_the_same_decisions(camera: Any) -> None:
    journal = ListJournal()
    core, _ = _core(camera, journal)
    core.set_mode("mow")
    core.map_loaded(_map())
    _feed(core, 0.0, 1.0)
    core.tracks(
        core.chains.installed_serial,
        FrameTracks(0.95, np.array([1, 2]), np.eye(3)[:2], np.zeros((2, 2)), np.array([0, 3])),
    )
    core.inject("nan")
    _feed(core, 1.0, 2.0)
    for t in (2.05, 2.2, 2.5):
        core.decide(t)
    r = replay_journal(default_config(), camera, journal.records)
    assert r.mismatches == 0 and r.gaps == 0, r.first_mismatch
    assert r.decisions == 203 and r.live_sha256 == r.replay_sha256
    assert r.halts_by_reason == {} and r.permit_decisions == 0  # never permitted: no landmark
    # the comparison can fail: without the injected fault the replay decides otherwise
    tampered = [rec for rec in journal.records if rec["kind"] != "inject"]
    bad = replay_journal(default_config(), camera, tampered)
    assert bad.mismatches > 0 and bad.gaps == 1 and bad.live_sha256 != bad.replay_sha256


def test_the_journal_codec_round_trips_exactly(tmp_path: Any) -> None:
    enc, dec = JournalEncoder(), JournalDecoder()
    rng = np.random.default_rng(1)
    tracks = FrameTracks(
        1.25,
        np.array([4, 9]),
        rng.normal(size=(2, 3)),
        rng.normal(size=(2, 2)),
        np.array([0, 7]),
        3.5,
        (rng.integers(0, 255, (2, 32), dtype=np.uint8), np.zeros((0, 32), np.uint8)),
    )
    rec = json.loads(json.dumps(enc.encode("tracks", {"tracks": tracks})))
    back = dec.tracks(rec["tracks"])
    assert np.array_equal(back.bearings, tracks.bearings) and back.t == tracks.t
    assert back.relocalization is None
    # a frame searched for the pose carries the answer (a replay must not search again)
    found = Relocalization(
        True, rng.normal(size=(3, 3)), rng.normal(size=3), [(0, 4), (1, 9)], 3, 8, 12.5, ""
    )
    searched = dataclasses.replace(tracks, relocalization=found)
    rec = json.loads(json.dumps(enc.encode("tracks", {"tracks": searched})))
    again_found = dec.tracks(rec["tracks"]).relocalization
    assert again_found is not None and again_found.inliers == found.inliers
    assert np.array_equal(again_found.r_wb, found.r_wb) and again_found.ms == found.ms
    assert again_found.covariance is None
    sure = dataclasses.replace(
        found,
        covariance=np.diag([1e-4, 4e-5, 1e-6]),
        landmark_cross=rng.normal(scale=1e-5, size=(3, 6)),
    )
    rec = json.loads(
        json.dumps(
            enc.encode("tracks", {"tracks": dataclasses.replace(tracks, relocalization=sure)})
        )
    )
    back_sure = dec.tracks(rec["tracks"]).relocalization
    assert back_sure is not None and np.array_equal(back_sure.covariance, sure.covariance)
    assert back_sure.landmark_cross is not None
    assert np.array_equal(back_sure.landmark_cross, sure.landmark_cross)
    assert [d.tolist() for d in back.descriptors] == [d.tolist() for d in tracks.descriptors]
    imu = ImuSample(0.1 + 1e-12, np.array([1e-7, -2.5, np.pi]), None, 12, 34)
    back_imu = dec.imu(json.loads(json.dumps(enc.encode("imu", {"s": imu})))["s"])
    assert np.array_equal(back_imu.gyro, imu.gyro) and back_imu.t == imu.t
    assert back_imu.mag is None
    field = np.array([2e-5, -1e-6, -4.5e-5])
    imu = ImuSample(0.2, np.zeros(3), np.array([0.0, 0.0, 9.8]), None, None, field)
    back_imu = dec.imu(json.loads(json.dumps(enc.encode("imu", {"s": imu})))["s"])
    assert back_imu.mag is not None and np.array_equal(back_imu.mag, imu.mag)
    m = _map()
    m.save(tmp_path / "lawn.json")  # as the daemon's maps are: saved, with a checksum
    first = json.loads(json.dumps(enc.encode("map_loaded", {"map": m})))["map"]
    again = json.loads(json.dumps(enc.encode("map_loaded", {"map": m})))["map"]
    assert "document" in first and "document" not in again  # the map is written out once
    assert (
        dec.lawn_map(first).checksum == m.checksum and dec.lawn_map(again) is dec.maps[m.checksum]
    )


def test_mowing_only_named_areas_and_teach_marks_through_the_core(camera: Any) -> None:
    """`ctl mow --area NAME`: the chain is built for those areas, a name the map does not have
    halts MAP_INVALID naming the map's areas; teach marks only while teaching."""
    core, asked = _core(camera)
    assert core.teach_mark("area", "front") == "not teaching (mode idle)"
    assert core.set_mode("idle", ("lawn",)) == "areas are for mow mode only"
    assert core.set_mode("mow", ("back",)) == ""
    core.map_loaded(_map())
    assert core.map_problem == "no mowing area 'back' in the map (its mowing areas: 'lawn')"
    assert not asked
    assert core.set_mode("mow", ("lawn",)) == ""
    core.map_loaded(_map())
    assert core.map_problem == "" and asked[-1].mow_areas == ("lawn",)
    assert core.pipeline is not None
    assert core.pipeline.localizer.geometry.transit is None  # type: ignore[union-attr]


def test_switching_areas_while_mowing_keeps_the_chain_and_replays(camera: Any) -> None:
    """`ctl mow --area B` while mowing A: the same chain (the localizer's pose goes on, no
    restart from the dock or a saved pose), A becomes transit; an unknown name is refused
    and changes nothing; the switch is journalled and replays."""
    from mowerhw.map import Area

    journal = ListJournal()
    core, asked = _core(camera, journal)
    m = _map()
    ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    m.areas = [Area("back", "mow", np.c_[20 + 4 * np.cos(ang), 4 * np.sin(ang)])]
    assert core.set_mode("mow", ("lawn",)) == ""
    core.map_loaded(m)
    pipe = core.pipeline
    assert pipe is not None and len(asked) == 1
    _feed(core, 0.0, 0.5)
    geometry = pipe.localizer.geometry  # type: ignore[union-attr]
    assert geometry.in_transit(20.0, 0.0) and not geometry.in_transit(0.0, 0.0)
    assert core.switch_mow_areas(("nope",)) == (
        "no mowing area 'nope' in the map (its mowing areas: 'lawn', 'back')"
    )
    assert core.mow_areas == ("lawn",)
    assert core.switch_mow_areas(("back",)) == ""
    assert core.pipeline is pipe and len(asked) == 1 and core.mow_areas == ("back",)
    geometry = pipe.localizer.geometry  # type: ignore[union-attr]
    assert geometry.in_transit(0.0, 0.0) and not geometry.in_transit(20.0, 0.0)
    _feed(core, 0.5, 1.0)
    idle, _ = _core(camera)
    assert idle.switch_mow_areas(("back",)) is None  # nothing mowing: the caller sets the mode
    rep = replay_journal(default_config(), camera, journal.records)
    assert rep.mismatches == 0 and rep.decisions == 100, rep.first_mismatch
    assert any(r["kind"] == "switch_mow_areas" for r in journal.records)


def test_teach_marks_are_taken_while_recording_and_journalled(camera: Any) -> None:
    journal = ListJournal()
    core, _ = _core(camera, journal)
    assert core.set_mode("teach") == "" and core.teach_state == "recording"
    assert core.teach_mark("area", "front") == "no IMU sample yet: mark once the IMU is read"
    core.imu(ImuSample(1.0, np.array([0.0, 0.0, 0.001])), 1.0)
    assert core.teach_mark("area", "front") == ""
    assert core.teach_mark("area", "front").endswith("is marked already")
    assert core.teach_mark("dock") == ""
    pipe = core.pipeline
    assert pipe is not None
    assert [(m.kind, m.name, m.t) for m in pipe.teacher.marks] == [  # type: ignore[union-attr]
        ("area", "front", 1.0),
        ("dock", "", 1.0),
    ]
    marks = [r for r in journal.records if r["kind"] == "teach_mark"]
    assert [(r["mark"], r["name"]) for r in marks][-2:] == [("area", "front"), ("dock", "")]


def test_the_log_says_when_the_pose_is_given_up_and_found(camera: Any) -> None:
    """A mow chain tells the log, once each, that it searches for its pose (here: the check
    of the start pose every pixel-level start makes), that it gave it up and why, and that
    it found it again (issue 18)."""
    from mowerhw.common.geometry import yaw_rotation

    pipe = build_pipeline(default_config(), camera, BuildRequest(1, "mow", _map()))
    assert isinstance(pipe, MowPipeline)
    first = pipe.news()
    assert len(first) == 1 and "check the start pose" in first[0]
    assert pipe.news() == []
    loc = pipe.localizer
    loc.lose("since a test")
    assert any("since a test" in line for line in pipe.news())
    loc.imu(0.0, np.zeros(3))
    for t in (0.25, 0.5):
        loc.imu(t, np.zeros(3))
        loc.relocalization(t, Relocalization(True, yaw_rotation(0.3), np.array([1.0, 2.0, 0.0])))
    found = pipe.news()
    assert len(found) == 1 and found[0].startswith("pose found: x 1.00 m, y 2.00 m")


def test_the_magnetometer_reaches_the_localizer_at_10_hz(camera: Any) -> None:
    """The compass's readings (issue 18): the IMU's magnetic field and specific force, turned
    into the body frame, go to the mow chain's localizer ten times a second (the journal
    keeps them with the IMU sample: the codec test above)."""
    reference = CompassReference(0.7, math.radians(3.0), 5e-5, math.radians(65.0), 400)
    lawn = dataclasses.replace(_map(), compass=reference)
    core, _ = _core(camera)
    core.set_mode("mow")
    core.map_loaded(lawn)
    heading = 0.3  # the field in the body frame of a mower facing 0.3 rad in the map
    alpha, dip = 0.7 - heading, 1.134
    field_b = 5e-5 * np.array(
        [math.cos(alpha) * math.cos(dip), math.sin(alpha) * math.cos(dip), -math.sin(dip)]
    )
    r_ib = core.r_bi.T
    for k in range(150):
        t = 0.01 * k
        core.imu(ImuSample(t, np.zeros(3), r_ib @ [0.0, 0.0, 9.81], None, None, r_ib @ field_b), t)
        if k % 10 == 0:
            core.speed(SpeedSample(t, 0.0))
    assert isinstance(core.pipeline, MowPipeline)
    compass = core.pipeline.localizer.compass
    assert compass is not None and len(compass._t) == 10  # the last second, at 10 Hz
    found = compass.heading(1.49)
    assert found is not None and abs(found[0] - heading) < 1e-6
    # the status page's `live` reply and the status say it too
    from mowerhw.runtime.live import LiveView

    live = LiveView().snapshot(core, 1.49)
    assert live["localizer"]["compass_deg"] == [round(math.degrees(heading), 1), 3.0]
    assert core.pipeline.localizer.status()["compass"]["heading_deg"] == 17.2


def test_an_imu_silence_is_told_apart_by_the_sensors_own_clock(
    camera: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """A silence past the IMU's staleness limit halts either way; when the samples come again
    the sensor's own stamps say whether it was silent itself or sent on time and its samples
    were held up on this computer — counted apart and logged for the integrator."""
    core, _ = _core(camera)

    def sample(t_host: float, t_dev: float) -> None:
        core.imu(ImuSample(t_host, np.zeros(3), None, round(t_dev * 1e9), None), t_host)

    for k in range(20):  # on time
        sample(1.0 + 0.01 * k, 0.01 * k)
    limit = default_config().imu.stale_after_s
    assert not core.decide(1.19 + limit + 0.01).permit  # silent: a halt, whoever is late
    # held up here: 0.15 s between arrivals, one period between the sensor's stamps
    sample(1.34, 0.20)
    sample(1.345, 0.21)  # the rest of the batch behind it: no gap
    # the sensor itself silent: its stamps 0.15 s apart too
    sample(1.50, 0.36)
    sample(1.51, 0.37)
    counts = core.counts
    assert counts["imu_gaps_host"] == 1 and counts["imu_gaps_sensor"] == 1
    assert counts["imu_gaps_unknown"] == 0
    text = caplog.text
    assert "by the sensor's own clock 0.010 s passed (it sent on time" in text
    assert "by the sensor's own clock 0.150 s passed (the sensor itself was silent)" in text
    core.imu(ImuSample(1.8, np.zeros(3)), 1.8)  # no device time: said, not guessed
    assert counts["imu_gaps_unknown"] == 1


def test_a_held_up_imu_sample_says_whether_this_daemon_kept_deciding(
    camera: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """Samples sent on time and held up: if the daemon's loop kept deciding through the
    silence (its deadline timer, every 40 ms), the bytes reached it late — the serial adapter
    or the kernel's tty input (traced on the loaded bench: its worker waiting behind nice-0
    CPU hogs) — else the daemon itself was held up."""
    core, _ = _core(camera)

    def sample(t_host: float, t_dev: float) -> None:
        core.imu(ImuSample(t_host, np.zeros(3), None, round(t_dev * 1e9), None), t_host)

    for k in range(20):
        sample(1.0 + 0.02 * k, 0.02 * k)  # the last at 1.38 (sensor 0.38)
    for t in (1.42, 1.46, 1.49, 1.50):  # the loop on time: deadline decisions
        core.decide(t)
    sample(1.51, 0.40)  # 0.13 s after the last, one period by the sensor's clock
    assert "before the daemon could read them (it went at most 0.040 s without" in caplog.text
    for k in range(1, 5):
        sample(1.51 + 0.02 * k, 0.40 + 0.02 * k)  # on time again: the last at 1.59
    caplog.clear()
    sample(1.72, 0.50)  # 0.13 s, no decision meanwhile: the daemon's own loop was stuck
    assert "held up on this computer, in this daemon (0.130 s without a decision)" in caplog.text
    for k in range(1, 5):
        sample(1.72 + 0.02 * k, 0.50 + 0.02 * k)  # on time again: the last at 1.80
    caplog.clear()
    for t in (1.84, 1.88, 1.91, 1.92):
        core.decide(t)
    sample(1.93, 0.60)  # the stuck loop before the last gap does not count for this one
    assert "before the daemon could read them (it went at most 0.040 s without" in caplog.text
    assert core.counts["imu_gaps_host"] == 3


def test_a_restart_resumes_with_the_gyro_bias_it_had_not_one_learnt_while_turning(
    camera: Any,
) -> None:
    """A restart within the same boot resumes with the gyro bias the saved pose carries: a
    standstill cannot tell a bias from a steady turn (measured in the simulator: restarted
    while turning on the spot at 0.8 rad/s, the daemon learnt 0.8 rad/s of bias and never
    relocalized again). Fed that turn, the resumed localizer keeps the bias and turns with
    it; without a saved bias it calibrates on the readings, as before — and learns the turn."""
    from mowerhw.runtime.pipelines import StartPose

    bias = np.array([0.001, -0.002, 0.003])
    turning = 0.8

    def resumed(saved_bias: Any) -> Any:
        core, _ = _core(camera)
        assert core.set_mode("mow") == ""
        pose = StartPose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), saved_bias)
        core.map_loaded(_map(), pose)
        loc = core.pipeline.localizer  # type: ignore[union-attr]
        for k in range(150):  # 1.5 s turning on the spot at a steady rate, then standing
            t = 0.01 * k
            rate = turning if t < 1.0 else 0.0
            core.imu(ImuSample(t, bias + np.array([0.0, 0.0, rate])), t)
            if k % 10 == 0:
                core.speed(SpeedSample(t, 0.0))
        return loc

    kept = resumed(bias)
    assert not kept.calibrating
    np.testing.assert_allclose(kept.gyro_bias, bias)
    learnt = resumed(None)  # the old way: the turn is taken for a bias
    assert abs(learnt.gyro_bias[2]) > 0.5 * turning  # (the IMU is mounted upside down)
