"""The bearing-level simulator: repeatable, physically consistent streams (docs/design.md §9)."""

from dataclasses import replace

import numpy as np
import pytest

from mowerhw.common.geometry import quat_to_rotmat
from mowerhw.sim import IMU_GRADES, SCENARIOS, SensorSuite, simulate_teach
from mowerhw.sim.lawn import HarmonicLawn
from mowerhw.sim.sensors import CameraTiming, SpeedModel, body_points


@pytest.fixture(scope="module")
def paper_run():
    return simulate_teach("paper", seed=3)


def test_paper_scenario_matches_section_v(paper_run):
    run = paper_run
    assert run.world.n_landmarks == 15
    assert 55.0 <= run.duration_s <= 70.0  # a closed loop of about 60 s
    # begins with a 2 s standstill, ends where it started
    still = run.truth.t[run.truth.speed == 0.0]
    assert still[still < 5].max() >= 1.99
    assert np.linalg.norm(run.truth.xy[-1] - run.truth.xy[0]) < 1e-6
    # world frame = body frame at the first sample
    assert np.allclose(run.truth.xy[0], 0.0) and run.truth.yaw[0] == 0.0


def test_large_scenario_is_large():
    sc = SCENARIOS["large"]
    assert sc.perimeter_m >= 150 and sc.n_landmarks >= 60
    run = simulate_teach("large", seed=1)
    assert run.world.lawn.perimeter >= 150
    assert run.world.n_landmarks >= 60
    assert simulate_teach("large", seed=1, n_landmarks=200).world.n_landmarks == 200


def test_seeds_make_runs_repeatable():
    a = simulate_teach("paper", seed=11)
    b = simulate_teach("paper", seed=11)
    c = simulate_teach("paper", seed=12)
    assert np.array_equal(a.streams.gyro, b.streams.gyro)
    assert np.array_equal(a.streams.frames[40].bearings, b.streams.frames[40].bearings)
    assert not np.array_equal(a.landmarks_w, c.landmarks_w)


def test_rates_quantisation_and_noise(paper_run):
    s = paper_run.streams
    assert np.allclose(np.diff(s.imu_t), 0.01)
    assert np.allclose(np.diff(s.speed_t), 0.1)
    assert np.allclose(np.diff([f.t for f in s.frames]), 0.25)
    assert np.allclose(s.speed / 0.001, np.round(s.speed / 0.001))  # 0.001 m/s as on CAN
    assert np.all(s.speed[s.speed_t < 1.9] == 0.0)
    # gyro = truth + bias + white noise: the residual has the configured statistics
    resid = s.gyro - paper_run.truth.body_rate - s.gyro_bias
    assert 4e-4 < resid.std() < 8e-4


def test_noise_free_gyro_integrates_to_the_true_heading():
    still = replace(IMU_GRADES["vn100"], noise_density=0, rate_random_walk=0, turn_on_bias=0)
    quiet = SensorSuite(still, SpeedModel(white=0.0, quantum=1e-9), CameraTiming(pixel_sigma=0))
    run = simulate_teach("paper", seed=2, sensors=quiet)
    yaw = np.concatenate([[0.0], np.cumsum(run.streams.gyro[1:, 2] * 0.01)])
    assert np.abs(yaw - run.truth.yaw).max() < 1e-9


def test_bearings_are_unit_and_come_from_the_camera_model(paper_run):
    run = paper_run
    cam = run.world.camera
    r_bc = quat_to_rotmat(run.world.q_bc)
    errs = []
    for f, pix in zip(run.streams.frames[::10], run.streams.frame_pixels[::10], strict=True):
        assert np.allclose(np.linalg.norm(f.bearings, axis=1), 1.0)
        assert cam.valid(pix).all()
        k = run.truth.index_at(f.t)
        true_b = body_points(run.truth, k, run.landmarks_w)[f.ids]
        true_b /= np.linalg.norm(true_b, axis=1, keepdims=True)
        # the true pixels project from the true bearings (camera frame = R_bcᵀ body)
        assert np.allclose(cam.project(true_b @ r_bc), pix, atol=1e-6)
        errs.extend(np.degrees(np.arccos(np.clip(np.sum(true_b * f.bearings, 1), -1, 1))))
    assert 0.2 < np.median(errs) < 1.5  # 3 px through the Table I camera


def test_lawn_arc_length_parametrisation():
    lawn = HarmonicLawn(4.0, ((2, 0.1, 0.3),))
    s = np.linspace(0, lawn.perimeter, 2001)
    pts = lawn.point(s)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert np.allclose(seg, lawn.perimeter / 2000, rtol=1e-3)
    # heading is the direction of travel, curvature its derivative along s
    h = np.unwrap(lawn.heading(s))
    assert np.allclose(np.gradient(h, s)[5:-5], lawn.curvature(s)[5:-5], atol=2e-3)
