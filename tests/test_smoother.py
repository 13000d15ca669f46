"""Loop-closure smoother: SO(3) helpers, preintegration, and the least-squares solve."""

import numpy as np
import pytest

from mowerhw.common.geometry import rotmat_exp, rotmat_log
from mowerhw.teach.smoother import preintegrate_segments, right_jacobian, right_jacobian_inv


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
