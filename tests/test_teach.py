"""The teach phase end to end on the simulated bench (paper §V), through the pure API."""

import json
import math

import numpy as np
import pytest

from mowerhw import map as lawnmap
from mowerhw.config import TeachConfig
from mowerhw.evaluation.teach import run_teach
from mowerhw.sim import simulate_teach
from mowerhw.teach import Teacher, TeachError
from mowerhw.teach.boundary import BoundaryError


def feed_until(t: Teacher, run, until: float, on_imu=None) -> None:
    """The simulated drive's samples into the teacher up to time ``until``; ``on_imu(t)``
    after each IMU sample."""
    for kind, p in run.streams.events():
        if (p[0] if kind != "bearings" else p.t) > until:
            break
        if kind == "imu":
            t.imu(*p)
            if on_imu is not None:
                on_imu(p[0])
        elif kind == "speed":
            t.speed(*p)
        else:
            t.bearings(p.t, p.ids, p.bearings)


@pytest.fixture(scope="module")
def outcome():
    return run_teach("paper", seed=5)


def test_paper_scenario_accuracy(outcome):
    m = outcome.metrics
    assert not m["diverged"]
    assert m["boundary_rmse_m"] <= 0.02  # the figure (median over seeds 1–20)
    assert m["landmark_rmse_m"] <= 0.10
    assert m["landmarks_mapped"] == 15
    assert m["loop_closure"]["applied"]
    assert m["boundary_rmse_m"] < m["boundary_rmse_no_closure_m"]


def test_the_map_is_as_sure_as_the_bearings_are_not_as_the_config_says(outcome):
    """The landmark covariances are taken at the bearings' long-run σ, measured on the
    loop closure's residuals along each track. The simulated bearings here are white noise
    at about the configured σ, so the measured one is near it (rendered drives measure
    0.06–0.07° against the configured 0.46°: tests/test_smoother.py and the README)."""
    closure = outcome.result.closure
    configured = TeachConfig().bearing_sigma_rad
    assert 0.8 * configured <= closure.bearing_sigma_long_run_rad <= 1.2 * configured


def test_result_shape_follows_the_api(outcome):
    res = outcome.result
    assert res.boundary.ndim == 2 and res.boundary.shape[1] == 2
    assert res.trajectory.shape[1] == 8
    assert np.all(np.diff(res.trajectory[:, 0]) > 0)
    # the world frame is the body frame at the first sample
    assert np.allclose(res.trajectory[0, 1:4], 0.0) and np.allclose(
        res.trajectory[0, 4:], [1, 0, 0, 0]
    )
    assert np.allclose(np.linalg.norm(res.trajectory[:, 4:8], axis=1), 1.0)
    assert set(res.landmarks) == set(range(15))
    assert all(v.shape == (3,) for v in res.landmarks.values())


def test_result_saves_a_loadable_map(outcome, tmp_path):
    path = tmp_path / "lawn.json"
    outcome.result.save(path)
    m = lawnmap.load(path)
    assert len(m.landmarks) == 15
    assert m.camera["camera_model"] == "omni"
    closure = json.loads(path.read_text())["teach"]["loop_closure"]
    assert closure["applied"] is True
    assert closure["bearing_sigma_long_run_rad"] == pytest.approx(
        outcome.result.closure.bearing_sigma_long_run_rad
    )


def _through_the_standstill(run, bearings: bool) -> tuple[Teacher, int]:
    """A teacher fed ``run``'s samples up to the first speed that is not 0 (the standstill
    over, driving begun); with ``bearings`` the camera's frames too. The frames fed."""
    t = Teacher(TeachConfig())
    frames = 0
    for kind, p in run.streams.events():
        if kind == "speed" and p[1] != 0.0:
            t.speed(*p)
            break
        if kind == "imu":
            t.imu(*p)
        elif kind == "speed":
            t.speed(*p)
        elif bearings:
            t.bearings(p.t, p.ids, p.bearings)
            frames += 1
    return t, frames


def test_gyro_bias_is_calibrated_from_the_standstill():
    run = simulate_teach("paper", seed=8)
    t, _ = _through_the_standstill(run, bearings=False)
    assert t.phase == "driving"
    err = np.abs(t.ekf.bg - run.streams.gyro_bias[200])
    assert np.all(err < 2e-4)  # 0.002 rad/s of bias, calibrated to a few 1e-5


def test_a_standstill_counts_as_one_view_not_as_many():
    """The standstill's frames see a still scene: their bearings share their tracking
    errors, so each landmark's mean bearing is kept as sure as one bearing (σ²), not n
    frames' worth (σ²/n), which pinned the map's frame to the dock too tightly (README,
    issue 18, stop 71)."""
    t, frames = _through_the_standstill(simulate_teach("paper", seed=8), bearings=True)
    assert t.phase == "driving" and frames >= 5
    kept = t._still_obs  # the smoother's standstill rows (the keyframe-0 bearings)
    assert len(kept) >= 5
    assert all(var == pytest.approx(t.sigma**2) for _, var in kept.values())


def test_bad_inputs_are_counted_not_fatal():
    t = Teacher()
    t.imu(0.0, [0, 0, 0])
    t.imu(0.01, [np.nan, 0, 0])
    t.speed(0.02, float("inf"))
    t.bearings(0.03, [1, 2], [[np.nan, 0, 0], [0, 1, 0]])
    assert t.counters["nonfinite_inputs"] == 3
    with pytest.raises(ValueError, match="2 ids but 1 bearings"):
        t.bearings(0.04, [1, 2], [[1, 0, 0]])


def test_finish_without_driving_is_a_clear_error():
    t = Teacher()
    for k in range(100):
        t.imu(k * 0.01, [0, 0, 0])
    with pytest.raises(TeachError, match="never drove"):
        t.finish()


def test_an_unfinished_loop_is_refused():
    run = simulate_teach("paper", seed=4)
    t = Teacher()
    half = run.duration_s / 2
    feed_until(t, run, half)
    with pytest.raises(BoundaryError, match="open loop"):
        t.finish()


def test_large_lawn_with_keyframes_and_landmarks_coming_and_going():
    out = run_teach("large", seed=2)
    m = out.metrics
    assert not m["diverged"]
    assert m["keyframes"] > 1
    assert out.result.diagnostics["retired"] > 0
    assert m["boundary_rmse_m"] < 0.05


@pytest.mark.parametrize("seed", [1, 2])
def test_the_smoother_measures_a_mems_gyros_yaw_scale_error(seed):
    """An MPU-6050-class gyro reads its yaw rate a few per cent off: teaching finds by how
    much (vision sees the true turn), and the map is not bent by it."""
    from mowerhw.config import config_from_dict
    from mowerhw.evaluation.teach import run_teach
    from mowerhw.sim import simulate_teach

    run = simulate_teach("U-sparse", seed)
    cfg = config_from_dict({"imu": {"grade": "mpu6050"}})
    out = run_teach(run=run, config=cfg.teach)
    true_error = run.streams.gyro_scale[2] - 1.0
    assert abs(true_error) > 0.015  # these seeds have a scale error worth finding
    assert out.result.diagnostics["gyro_yaw_scale_error"] == pytest.approx(true_error, abs=0.003)
    assert out.metrics["boundary_rmse_scale_free_m"] < 0.03


def test_a_marked_drive_makes_named_zones_in_one_map(tmp_path):
    """``ctl teach area NAME`` / ``dock`` through the Teacher: the whole loop marked as the
    mowing area 'front' becomes the map's lawn by that name; the dock where it was marked."""
    run = simulate_teach("paper", seed=4)
    t = Teacher(camera=run.world.camera)
    marked = []

    def mark(tt: float) -> None:
        if not marked and t.phase == "driving":
            assert t.mark(tt, "dock") == ""
            assert t.mark(tt + 1e-6, "area", "front") == ""
            marked.append(t.mark(tt + 2e-6, "area", "front"))

    feed_until(t, run, math.inf, on_imu=mark)
    assert marked == ["teach area: a zone named 'front' is marked already"] and t.zone_open
    result = t.finish()
    assert [(z.kind, z.name) for z in result.zones] == [("mow", "front")]
    m = lawnmap.LawnMap.from_teach_result(result)
    assert m.boundary_name == "front" and m.areas == [] and m.problems() == []
    assert m.lawn_polygon().area > 50.0
    assert result.dock_index is not None and result.dock_index > 0
    m.save(tmp_path / "front.json")
    assert lawnmap.load(tmp_path / "front.json").area_names("mow") == ["front"]


def test_zones_without_a_lawn_are_refused():
    run = simulate_teach("paper", seed=4)
    t = Teacher(camera=run.world.camera)
    feed_until(
        t,
        run,
        math.inf,
        on_imu=lambda tt: t.phase == "driving" and not t.marks and t.mark(tt, "keepout", "bed"),
    )
    with pytest.raises(BoundaryError, match="no mowing area: mark each lawn too"):
        t.finish()
