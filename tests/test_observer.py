"""Landmark observers (eqs 2–8), vectorised over landmarks."""

import numpy as np
import pytest

from mowerhw.estimation.odometry import BodyMotion
from mowerhw.teach.observer import LandmarkObservers, contraction_rate, observer_gain


def test_propagation_is_the_rigid_motion_of_eq_1():
    rng = np.random.default_rng(0)
    obs = LandmarkObservers(-2.0, -6.0, 0.5)
    x = rng.uniform(-8, 8, size=(50, 3))
    obs.add(np.arange(50), x, 1.0, 1.0, 1e-4)
    obs.d[:] = np.linalg.norm(x, axis=1)
    w, v = np.array([0.02, -0.01, 0.4]), np.array([0.5, 0.0, 0.0])
    for _ in range(100):  # 1 s at 100 Hz
        m = BodyMotion.of(w, v, 0.01)
        obs.propagate(m.c, m.disp)
    # closed form for constant ω, v: the body moves along an arc
    from scipy.integrate import solve_ivp

    sol = solve_ivp(
        lambda t, z: (-np.cross(w, z.reshape(-1, 3)) - v).ravel(),
        (0, 1),
        x.ravel(),
        rtol=1e-11,
        atol=1e-12,
    )
    assert np.allclose(obs.positions(), sol.y[:, -1].reshape(-1, 3), atol=1e-6)
    assert np.allclose(np.linalg.norm(obs.y, axis=1), 1.0)


def test_gain_of_eq_7():
    assert observer_gain(-2.0, np.array([0.0]), 0.25)[0] == pytest.approx(1 - np.exp(-0.25))
    # a faster-diverging prediction (larger λ) asks for a larger gain, never above 1
    g = observer_gain(-2.0, np.array([0.0, 1.0, 100.0]), 0.25)
    assert g[0] < g[1] < g[2] <= 1.0


def test_contraction_rate_is_the_largest_eigenvalue_of_the_symmetric_jacobian():
    rng = np.random.default_rng(1)
    d = rng.uniform(1, 10, 20)
    y = rng.normal(size=(20, 3))
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    v, w = np.array([0.4, 0.0, 0.0]), np.array([0.0, 0.0, 0.5])
    lam = contraction_rate(d, y, v, w)
    for k in range(20):  # eq. (8) written out for one landmark
        yy = y[k]
        wx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        f = np.zeros((4, 4))
        f[0, 1:] = -v
        f[1:, 0] = (np.eye(3) - np.outer(yy, yy)) @ v / d[k] ** 2
        f[1:, 1:] = -wx + (np.outer(yy, v) + (v @ yy) * np.eye(3)) / d[k]
        assert lam[k] == pytest.approx(np.linalg.eigvalsh(f + f.T)[-1])


def test_converges_from_a_wrong_depth_with_exact_measurements():
    """Noise-free: the hybrid observer contracts to the truth (Theorem 1)."""
    obs = LandmarkObservers(-2.0, -6.0, 0.3, weighted_depth=False)
    true_x = np.array([[4.0, 3.0, 1.0], [-6.0, 2.0, 0.5]])
    obs.add(np.array([1, 2]), true_x, 10.0, 25.0, 1e-4)  # depth 10 m, truth 5.1 and 6.3
    x = true_x.copy()
    w, v = np.array([0.0, 0.0, 0.1]), np.array([0.5, 0.0, 0.0])
    for _ in range(40):  # 10 s, camera at 4 Hz
        for _ in range(25):
            m = BodyMotion.of(w, v, 0.01)
            obs.propagate(m.c, m.disp)
            x = (x - m.disp) @ m.c
        d_true = np.linalg.norm(x, axis=1)
        obs.update(
            np.array([0, 1]), x / d_true[:, None], 1e-6, d_true, np.full(2, 1e-4), 0.25, v, w
        )
    assert np.allclose(obs.positions(), x, atol=1e-6)


def test_depth_is_clamped_and_direction_renormalised():
    obs = LandmarkObservers(-2.0, -6.0, 0.5)
    obs.add(np.array([7]), np.array([[1.0, 0, 0]]), 2.0, 1.0, 1e-4)
    for _ in range(20):  # a run of (wrong) pseudo-measurements below d_min
        obs.update(
            np.array([0]),
            np.array([[0.0, 1.0, 0.0]]),
            1e-4,
            np.array([0.01]),
            np.array([1e-6]),
            0.25,
            np.array([0.5, 0, 0]),
            np.zeros(3),
        )
    assert obs.d[0] == 0.5
    assert obs.stats.depth_clamped >= 1
    assert np.linalg.norm(obs.y[0]) == pytest.approx(1.0)


def test_landmarks_come_and_go_as_arrays():
    obs = LandmarkObservers(-2.0, -6.0, 0.5)
    obs.add(np.array([5, 9, 2]), np.eye(3), 3.0, 1.0, 1e-4)
    obs.add(np.array([11]), np.array([[0.0, 0.0, 1.0]]), 4.0, 1.0, 1e-4)
    assert obs.rows(np.array([2, 11, 99])).tolist() == [2, 3, -1]
    obs.remove(np.array([True, False, True, True]))
    assert obs.ids.tolist() == [5, 2, 11]
    assert obs.rows(np.array([11])).tolist() == [2]
    assert obs.positions().shape == (3, 3) and obs.covariances().shape == (3, 3, 3)


def test_rates_must_be_negative():
    with pytest.raises(ValueError, match="negative"):
        LandmarkObservers(0.5, -1.0, 0.5)


def test_precision_weighting_holds_a_good_estimate_against_poor_triangulations():
    obs = LandmarkObservers(-2.0, -6.0, 0.3, weighted_depth=True)
    obs.add(np.array([1]), np.array([[1.0, 0, 0]]), 5.0, 0.01**2, 1e-4)
    obs.update(
        np.array([0]),
        np.array([[1.0, 0, 0]]),
        1e-4,
        np.array([9.0]),
        np.array([3.0**2]),
        0.25,
        np.zeros(3),
        np.zeros(3),
    )
    assert obs.d[0] == pytest.approx(5.0, abs=0.01)  # a ±3 m triangulation barely moves it
    plain = LandmarkObservers(-2.0, -6.0, 0.3, weighted_depth=False)
    plain.add(np.array([1]), np.array([[1.0, 0, 0]]), 5.0, 0.01**2, 1e-4)
    plain.update(
        np.array([0]),
        np.array([[1.0, 0, 0]]),
        1e-4,
        np.array([9.0]),
        np.array([3.0**2]),
        0.25,
        np.zeros(3),
        np.zeros(3),
    )
    assert plain.d[0] > 5.5  # eq. (7)'s gain alone chases it
