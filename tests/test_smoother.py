"""Loop-closure smoother: SO(3) helpers, preintegration, and the least-squares solve."""

import math
from typing import Any

import numpy as np
import pytest

from mowerhw.common.geometry import rotmat_exp, rotmat_log
from mowerhw.teach.smoother import (
    bearing_variance_factor,
    preintegrate_segments,
    right_jacobian,
    right_jacobian_inv,
)


def test_right_jacobian_and_inverse():
    rng = np.random.default_rng(0)
    phi = rng.normal(size=(20, 3)) * 0.8
    assert np.allclose(right_jacobian(phi) @ right_jacobian_inv(phi), np.eye(3), atol=1e-10)
    # Exp(φ + δ) ≈ Exp(φ) Exp(Jr(φ) δ)
    d = np.array([1e-6, -2e-6, 1.5e-6])
    for p in phi[:5]:
        lhs = rotmat_exp(p + d)
        rhs = rotmat_exp(p) @ rotmat_exp(right_jacobian(p)[0] @ d)
        assert np.allclose(lhs, rhs, atol=1e-11)
    assert np.allclose(right_jacobian(np.zeros((1, 3)))[0], np.eye(3))


def test_preintegration_of_a_constant_turn():
    n = 100
    w = np.array([0.0, 0.0, 0.5])
    log = np.column_stack([np.full(n, 0.01), np.tile(w, (n, 1)), np.full(n, 0.4), np.zeros(n)])
    (f,) = preintegrate_segments(log, np.array([0, n]), np.zeros(3), 1e-4, 2e-3, 3e-3)
    assert np.allclose(rotmat_log(f.dR), w * 1.0, atol=1e-12)
    # arc of radius v/ω through angle ω t
    r, ang = 0.4 / 0.5, 0.5
    assert f.dp == pytest.approx([r * np.sin(ang), r * (1 - np.cos(ang)), 0.0], abs=2e-4)
    assert np.all(np.linalg.eigvalsh(f.cov) > 0)
    # bias Jacobian: d(ΔR)/db by finite differences
    eps = 1e-6
    (g,) = preintegrate_segments(log, np.array([0, n]), np.array([0, 0, eps]), 1e-4, 2e-3, 3e-3)
    num = rotmat_log(f.dR.T @ g.dR) / eps
    assert np.allclose(num, f.j_rb[:, 2], atol=1e-5)
    assert np.allclose((g.dp - f.dp) / eps, f.j_pb[:, 2], atol=1e-4)


@pytest.mark.parametrize(("landmarks", "seen"), [(4, 10), (60, 2)])  # dense, sparse product
def test_the_landmark_schur_solve_matches_a_direct_solve(
    landmarks: int, seen: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Eliminating the landmarks gives the direct solution and the landmarks' marginal
    covariances (diagonal blocks of the inverse), on a random system of the smoother's shape:
    pose–landmark and pose–pose couplings, none between two landmarks."""
    import scipy.sparse as sp

    from mowerhw.teach.smoother import _LandmarkSchur

    lay, a = _random_system(landmarks, seen)
    rng = np.random.default_rng(landmarks + 1)
    b = rng.normal(size=lay.size)
    damp = np.full(lay.size, 1e-3)
    dense = []
    product = _LandmarkSchur._m_a_lr

    def spy(self: _LandmarkSchur) -> np.ndarray:
        out = product(self)
        per_col = np.diff(self.a_rl.tocsc().indptr)
        r, c = self.a_rl.shape
        dense.append(r * r * c / self.DENSE_SPEEDUP < np.sum(per_col.astype(float) ** 2))
        return out

    monkeypatch.setattr(_LandmarkSchur, "_m_a_lr", spy)
    got = _LandmarkSchur(sp.csc_matrix(a), lay, damp).solve(b)
    assert dense == [landmarks == 4]
    assert np.allclose(got, np.linalg.solve(a + np.diag(damp), b), rtol=1e-8, atol=1e-10)
    cov = _LandmarkSchur(sp.csc_matrix(a), lay, np.zeros(lay.size)).landmark_covariances()
    inv = np.linalg.inv(a)
    for i in range(landmarks):
        s = lay.lm0 + 3 * i
        assert np.allclose(cov[i], inv[s : s + 3, s : s + 3], rtol=1e-6, atol=1e-12)


def test_the_frame_split_is_the_joint_covariance_of_the_frame_fit_and_its_residuals() -> None:
    """The map frame's covariance is that of the least-squares frame (shift, turn, scale)
    fitted to the landmarks' errors, and each landmark's own covariance that of its residual
    after the fit, both from the landmarks' joint covariance (here the dense inverse); the
    marginals are the joint's diagonal blocks."""
    import scipy.sparse as sp

    from mowerhw.common.geometry import frame_jacobian
    from mowerhw.teach.smoother import _LandmarkSchur

    lay, a = _random_system(30, 3)
    xy = np.random.default_rng(7).uniform(-8.0, 8.0, (30, 2))
    marginal, own, frame = _LandmarkSchur(sp.csc_matrix(a), lay, np.zeros(lay.size)).frame_split(xy)
    joint = np.linalg.inv(a)[lay.lm0 : lay.bias0, lay.lm0 : lay.bias0]
    big_a = frame_jacobian(np.column_stack([xy, np.zeros(30)])).reshape(-1, 4)
    g = np.linalg.solve(big_a.T @ big_a, big_a.T)
    assert np.allclose(frame, g @ joint @ g.T, rtol=1e-6, atol=1e-14)
    resid = np.eye(90) - big_a @ g
    full_own = resid @ joint @ resid.T
    for i in range(30):
        blk = slice(3 * i, 3 * i + 3)
        assert np.allclose(own[i], full_own[blk, blk], rtol=1e-6, atol=1e-14)
        assert np.allclose(marginal[i], joint[blk, blk], rtol=1e-6, atol=1e-14)


def _random_system(landmarks: int, seen: int) -> tuple[Any, np.ndarray]:
    """A random information matrix of the smoother's shape: pose–landmark and pose–pose
    couplings, none between two landmarks, every variable weakly constrained."""
    from mowerhw.teach.smoother import _Layout

    rng = np.random.default_rng(landmarks)
    lay = _Layout(k=12, n=landmarks, nseg=2)
    rows = []
    for _ in range(seen * landmarks):  # a bearing: one pose, one landmark
        j = np.zeros(lay.size)
        p, i = 6 * rng.integers(0, lay.k - 1), lay.lm0 + 3 * rng.integers(0, landmarks)
        j[p : p + 6] = rng.normal(size=6)
        j[i : i + 3] = rng.normal(size=3)
        rows.append(j)
    for p in range(lay.k - 2):  # odometry: consecutive poses, a bias, the scale
        for _ in range(6):
            j = np.zeros(lay.size)
            j[6 * p : 6 * p + 12] = rng.normal(size=12)
            j[lay.bias0 : lay.size] = rng.normal(size=lay.size - lay.bias0) * 0.1
            rows.append(j)
    for i in range(lay.lm0, lay.size):  # weak priors: every variable constrained
        j = np.zeros(lay.size)
        j[i] = 0.1
        rows.append(j)
    jac = np.array(rows)
    return lay, jac.T @ jac


def _tracks(n_landmarks: int, length: int, rho: float, sigma: float, seed: int = 0):
    """Whitened 2-D bearing residuals along tracks: AR(1) with lag-one correlation ``rho``
    and standard deviation ``sigma`` per axis; (residuals, frame, landmark)."""
    rng = np.random.default_rng(seed)
    res, frames, lms = [], [], []
    for j in range(n_landmarks):
        first = int(rng.integers(0, 50))
        e = rng.normal(size=2) * sigma
        for k in range(length):
            e = rho * e + math.sqrt(1 - rho**2) * sigma * rng.normal(size=2)
            res.append(e)
            frames.append(first + k)
            lms.append(j)
    return np.array(res), np.array(frames, dtype=np.int64), np.array(lms, dtype=np.int64)


def test_the_bearings_long_run_variance_is_their_variance_when_they_are_independent():
    res, frame, lm = _tracks(200, 40, 0.0, 0.3)
    assert bearing_variance_factor(res, frame, lm) == pytest.approx(0.09, rel=0.1)


def test_errors_correlated_along_a_track_count_for_more_than_their_variance():
    """A drifting KLT point: lag-one correlation 0.6. The Bartlett sum up to the bandwidth
    (3 for 40-bearing tracks) is γ0 (1 + 2 (¾ ρ + ½ ρ² + ¼ ρ³)) = 2.41 γ0."""
    res, frame, lm = _tracks(200, 40, 0.6, 0.3)
    expected = 0.09 * (1 + 2 * (0.75 * 0.6 + 0.5 * 0.36 + 0.25 * 0.216))
    assert bearing_variance_factor(res, frame, lm) == pytest.approx(expected, rel=0.12)


def test_bearings_of_different_landmarks_are_never_paired():
    """Each landmark's residuals a constant sign flip of the one before, tracks back to
    back in frame numbers: pairs across landmarks would pull the sum down."""
    rng = np.random.default_rng(1)
    n, length = 100, 5
    base = rng.normal(size=(length, 2))
    res = np.concatenate([base * (-1) ** j for j in range(n)])
    frame = np.tile(np.arange(length), n)
    lm = np.repeat(np.arange(n), length)
    alone = bearing_variance_factor(res, frame, lm)
    # the same tracks, each landmark's frames shifted so none shares a neighbour's numbers
    assert alone == pytest.approx(bearing_variance_factor(res, frame + 7 * lm, lm))


def test_too_few_bearings_leave_the_configured_sigma():
    res, frame, lm = _tracks(2, 20, 0.0, 0.1)
    assert bearing_variance_factor(res, frame, lm) == 1.0


def _circle_drive(gyro_error: float, seed: int = 3) -> tuple[Any, np.ndarray]:
    """A smoother problem of a drive most of the way round a 5 m circle, 30 landmarks around
    it seen from every pose: bearings 1 mrad off (white) but configured at 8 mrad, the way
    a pixel-level teach configures them; odometry true but for a gyro that adds
    ``gyro_error`` rad of turn to every step, within its 2 mrad σ. Returns the problem and
    the landmarks' true positions."""
    from mowerhw.common.geometry import tangent_basis
    from mowerhw.teach.smoother import Preintegrated, SmootherProblem

    rng = np.random.default_rng(seed)
    k = 40
    a = np.linspace(0.0, 0.9 * 2 * math.pi, k)
    t_wb = np.column_stack([5 * np.sin(a), 5 * (1 - np.cos(a)), np.zeros(k)])
    r_wb = rotmat_exp(np.column_stack([np.zeros(k), np.zeros(k), a]))
    ang = rng.uniform(0, 2 * math.pi, 30)
    rad = rng.uniform(8.0, 12.0, 30)
    lms = np.column_stack([rad * np.cos(ang), 5 + rad * np.sin(ang), rng.uniform(0.5, 1.5, 30)])
    fi = np.repeat(np.arange(k), 30)
    li = np.tile(np.arange(30), k)
    ell = np.einsum("nji,nj->ni", r_wb[fi], lms[li] - t_wb[fi])
    u = ell / np.linalg.norm(ell, axis=1, keepdims=True)
    u = u + np.einsum("nij,nj->ni", tangent_basis(u), rng.normal(0.0, 1e-3, (fi.size, 2)))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    cov = np.diag([2e-3**2] * 3 + [5e-3**2] * 3)
    odometry = [
        Preintegrated(
            r_wb[j].T @ r_wb[j + 1] @ rotmat_exp(np.array([[0.0, 0.0, gyro_error]]))[0],
            r_wb[j].T @ (t_wb[j + 1] - t_wb[j]),
            cov,
            np.zeros((3, 3)),
            np.zeros((3, 3)),
            0.5,
            np.zeros(3),
            np.zeros(3),
        )
        for j in range(k - 1)
    ]
    problem = SmootherProblem(
        r_wb=r_wb,
        t_wb=t_wb,
        odometry=odometry,
        obs_frame=fi,
        obs_landmark=li,
        obs_bearing=u,
        obs_sigma=np.full(fi.size, 8e-3),
        landmarks=lms + rng.normal(0.0, 0.05, lms.shape),
        bias0=np.zeros(3),
        bias_prior=np.zeros(3),
        bias_prior_cov=np.eye(3) * 1e-8,
    )
    return problem, lms


def _turn_of(est: np.ndarray, true: np.ndarray) -> float:
    """The map's turn against the truth about the fixed first pose (rad, least squares)."""
    e, t = est[:, :2], true[:, :2]
    return math.atan2(float(np.sum(e[:, 0] * t[:, 1] - e[:, 1] * t[:, 0])), float(np.sum(e * t)))


def test_the_smoother_weighs_the_bearings_at_the_sigma_they_turn_out_to_have() -> None:
    """Weighed at the configured 8 mrad, 1 mrad bearings leave the gyro's error of the drive
    in the map (its turn), which the frame covariance, taken at the bearings' measured σ,
    says is not there; solved again at that σ, the turn is gone, and the bearings' long-run
    variance the result reports is still relative to the configured σ."""
    from mowerhw.teach.smoother import smooth

    problem, true = _circle_drive(gyro_error=1.5e-3)
    before = smooth(problem, reweight_rounds=0)
    after = smooth(problem)
    turn_before = _turn_of(before.landmarks, true)
    turn_after = _turn_of(after.landmarks, true)
    assert before.frame_cov is not None and after.frame_cov is not None
    sd_before = math.sqrt(before.frame_cov[2, 2])
    sd_after = math.sqrt(after.frame_cov[2, 2])
    assert abs(turn_before) > 3 * sd_before  # the unweighted solve is over-confident
    assert abs(turn_after) < 2 * sd_after
    assert abs(turn_after) < abs(turn_before) / 3
    # against the configured σ, the 1 mrad of the bearings (their residuals a little less:
    # the fit takes some of their error in)
    assert (0.6 / 8) ** 2 < after.bearing_variance_factor < (1.2 / 8) ** 2
