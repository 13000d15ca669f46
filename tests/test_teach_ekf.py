"""Robot-centric EKF (eqs 14–18): covariance propagation and measurement Jacobians."""

import numpy as np
import pytest

from mowerhw.common.geometry import quat_exp, quat_multiply, quat_normalize, quat_to_rotmat, skew
from mowerhw.estimation.odometry import BodyMotion
from mowerhw.teach.ekf import EkfNoise, RobotCentricEKF


def _random_ekf(seed=0):
    rng = np.random.default_rng(seed)
    ekf = RobotCentricEKF(EkfNoise())
    ekf.p = rng.normal(size=3) * 3
    ekf.q = quat_normalize(rng.normal(size=4))
    a = rng.normal(size=(9, 9)) * 1e-2
    ekf.P = a @ a.T
    return ekf, rng


def test_covariance_propagation_matches_the_dense_error_dynamics():
    ekf, _ = _random_ekf()
    w, v, dt = np.array([0.1, -0.2, 0.3]), np.array([0.5, 0, 0]), 0.01
    p0, P0 = ekf.p.copy(), ekf.P.copy()
    ekf.propagate(BodyMotion.of(w, v, dt))
    f = np.zeros((9, 9))
    f[0:3, 0:3], f[0:3, 6:9] = -skew(w), -skew(p0)
    f[3:6, 3:6], f[3:6, 6:9] = -skew(w), np.eye(3)
    phi = np.eye(9) + f * dt + 0.5 * (f * dt) @ (f * dt)
    g = np.eye(9)
    g[0:3, 3:6] = -skew(p0)
    n = ekf.noise
    qc = np.diag(
        [n.speed**2, n.lateral**2, n.lateral**2, *[n.gyro**2] * 3, *[n.gyro_bias_walk**2] * 3]
    )
    assert np.allclose(ekf.P, phi @ P0 @ phi.T + g @ qc @ g.T * dt, atol=1e-15)


def test_mean_propagation_keeps_a_world_point_fixed():
    """x^{bj} is the keyframe origin seen from the body: it must move like any world point."""
    ekf = RobotCentricEKF(EkfNoise())
    ekf.p = np.array([3.0, -1.0, 0.2])
    world_pt = ekf.p.copy()
    for _ in range(200):
        m = BodyMotion.of(np.array([0.0, 0.05, 0.3]), np.array([0.4, 0, 0]), 0.01)
        ekf.propagate(m)
        world_pt = m.c.T @ (world_pt - m.disp)
    assert np.allclose(ekf.p, world_pt)


def test_bearing_jacobians_match_finite_differences():
    ekf, rng = _random_ekf(1)
    n = 4
    r_ja = np.stack([quat_to_rotmat(quat_normalize(rng.normal(size=4))) for _ in range(n)])
    t_ja = rng.normal(size=(n, 3))
    x = rng.normal(size=(n, 3)) * 5
    h0, hx, hl = ekf.predict_anchor_bearings(x, r_ja, t_ja)
    e = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = e
        p0 = ekf.p.copy()
        ekf.p = p0 + d
        num = (ekf.predict_anchor_bearings(x, r_ja, t_ja)[0] - h0) / e
        ekf.p = p0
        assert np.allclose(hx[:, :, k], num, atol=1e-5)
        q0 = ekf.q.copy()
        ekf.q = quat_multiply(quat_exp(d), q0)
        num = (ekf.predict_anchor_bearings(x, r_ja, t_ja)[0] - h0) / e
        ekf.q = q0
        assert np.allclose(hx[:, :, 3 + k], num, atol=1e-5)
        xx = x.copy()
        xx[:, k] += e
        num = (ekf.predict_anchor_bearings(xx, r_ja, t_ja)[0] - h0) / e
        assert np.allclose(hl[:, :, k], num, atol=1e-5)


def test_epipolar_update_pulls_a_perturbed_state_back():
    """Noise-free epipolar constraints from landmarks all around correct a rotation error."""
    rng = np.random.default_rng(3)
    lms = rng.uniform(-8, 8, size=(20, 3))
    lms[:, 2] = rng.uniform(-0.5, 1.5, 20)
    true_p, true_q = np.array([-2.0, 1.0, 0.0]), quat_exp(np.array([0.0, 0.0, 0.4]))
    r = quat_to_rotmat(true_q)
    anchor = lms / np.linalg.norm(lms, axis=1, keepdims=True)  # bearings at the keyframe
    now = (lms @ r.T) + true_p  # landmarks in the current body: R x + p
    y_now = now / np.linalg.norm(now, axis=1, keepdims=True)
    ekf = RobotCentricEKF(EkfNoise())
    ekf.p, ekf.q = true_p.copy(), quat_multiply(quat_exp(np.array([0, 0, 0.01])), true_q)
    ekf.P = np.diag([1e-4] * 3 + [1e-4] * 3 + [1e-10] * 3)
    eye = np.broadcast_to(np.eye(3), (20, 3, 3)).copy()
    for _ in range(5):
        ekf.update_epipolar(
            y_now, 1e-8, anchor, np.full(20, 1e-8), eye, np.zeros((20, 3)), 0.3, np.radians(5)
        )
    err = quat_multiply(ekf.q, quat_normalize(true_q * np.array([1, -1, -1, -1])))
    assert 2 * np.linalg.norm(err[1:]) < 1e-4


def test_gate_rejects_a_wild_bearing():
    ekf = RobotCentricEKF(EkfNoise())
    ekf.P = np.eye(9) * 1e-6
    ekf.p = np.array([-1.0, 0, 0])
    x = np.array([[5.0, 1.0, 0.5], [4.0, -3.0, 0.0]])
    good = (x - ekf.p) / np.linalg.norm(x - ekf.p, axis=1, keepdims=True)
    anchors = good.copy()
    anchors[1] = np.array([0.0, 0.0, 1.0])  # way off
    eye = np.broadcast_to(np.eye(3), (2, 3, 3)).copy()
    ok = ekf.update(x, np.zeros((2, 3, 3)), anchors, np.full(2, 1e-5), eye, np.zeros((2, 3)))
    assert ok.tolist() == [True, False]
    assert ekf.stats.gated == 1


def test_keyframe_reset_is_exact_and_keeps_the_bias():
    ekf, _ = _random_ekf(4)
    ekf.bg = np.array([1e-3, 2e-3, -1e-3])
    bias_var = ekf.P[6:9, 6:9].copy()
    ekf.reset_keyframe()
    assert np.all(ekf.p == 0) and np.allclose(ekf.q, [1, 0, 0, 0])
    assert np.all(ekf.P[:6] == 0) and np.all(ekf.P[:, :6] == 0)
    assert np.allclose(ekf.P[6:9, 6:9], bias_var)
    assert ekf.bg[1] == pytest.approx(2e-3)
