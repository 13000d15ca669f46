"""Conventions of docs/design.md §3 and the kinematics of §4/§5, as properties."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

import mowerhw.common.geometry as g

finite = st.floats(-1e3, 1e3, allow_nan=False)
vec3 = arrays(np.float64, 3, elements=st.floats(-10, 10, allow_nan=False))
small_vec3 = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False))


@st.composite
def unit_quats(draw):
    q = draw(arrays(np.float64, 4, elements=st.floats(-1, 1, allow_nan=False)))
    if np.linalg.norm(q) < 1e-3:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    return g.quat_normalize(q)


@st.composite
def rotvecs(draw, max_angle=np.pi - 1e-6):
    v = draw(small_vec3)
    n = np.linalg.norm(v)
    return v if n <= max_angle else v / n * max_angle


def test_identity_and_scalar_first():
    assert np.allclose(g.quat_to_rotmat(g.IDENTITY_QUAT), np.eye(3))
    # 90° about z, scalar first: (cos 45°, 0, 0, sin 45°) turns x into y.
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert np.allclose(g.quat_rotate(q, [1, 0, 0]), [0, 1, 0])
    assert np.allclose(g.quat_to_rotmat(q), Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix())


@given(unit_quats(), unit_quats(), vec3)
def test_product_is_composition(p, q, v):
    # R(p ⊗ q) = R(p) R(q): q_ac = q_ab ⊗ q_bc.
    assert np.allclose(
        g.quat_to_rotmat(g.quat_multiply(p, q)),
        g.quat_to_rotmat(p) @ g.quat_to_rotmat(q),
        atol=1e-12,
    )
    ref = (g.quat_to_scipy(p) * g.quat_to_scipy(q)).apply(v)
    assert np.allclose(g.quat_rotate(g.quat_multiply(p, q), v), ref, atol=1e-9)


@given(unit_quats(), unit_quats())
def test_unit_product_is_the_normalised_product(p, q):
    # the filters' per-sample attitude step: the same numbers as the two steps it fuses
    fused = g.quat_multiply_unit(p, q)
    assert np.array_equal(fused, g.quat_normalize(g.quat_multiply(p, q)))
    assert fused[0] >= 0.0 and abs(np.linalg.norm(fused) - 1.0) < 1e-12


@given(unit_quats())
def test_rotmat_is_rotation_and_matches_scipy(q):
    r = g.quat_to_rotmat(q)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)
    assert np.allclose(r, g.quat_to_scipy(q).as_matrix(), atol=1e-12)
    assert g.quat_distance(g.rotmat_to_quat(r), q) < 1e-7


@given(unit_quats(), vec3)
def test_conjugate_is_inverse(q, v):
    assert np.allclose(g.quat_rotate(g.quat_conjugate(q), g.quat_rotate(q, v)), v, atol=1e-9)
    assert np.allclose(g.quat_normalize(g.quat_multiply(q, g.quat_conjugate(q))), g.IDENTITY_QUAT)


@given(vec3, vec3)
def test_skew_is_cross_product(a, b):
    assert np.allclose(g.skew(a) @ b, np.cross(a, b), atol=1e-9)
    assert np.allclose(g.skew(a), -g.skew(a).T)


@given(rotvecs())
def test_exp_log_round_trip(phi):
    q = g.quat_exp(phi)
    assert np.isclose(np.linalg.norm(q), 1.0)
    assert np.allclose(g.quat_log(q), phi, atol=1e-9)
    assert np.allclose(g.quat_to_rotmat(q), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    assert np.allclose(g.rotmat_exp(phi), g.quat_to_rotmat(q), atol=1e-12)


@given(unit_quats())
def test_log_exp_round_trip(q):
    assert g.quat_distance(g.quat_exp(g.quat_log(q)), q) < 1e-7
    assert np.linalg.norm(g.quat_log(q)) <= np.pi + 1e-12


@given(st.floats(1e-12, 1e-5), arrays(np.float64, 3, elements=st.floats(-1, 1)))
def test_small_angles_keep_precision(angle, axis):
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    phi = axis / np.linalg.norm(axis) * angle
    q = g.quat_exp(phi)
    assert np.allclose(q[1:], phi / 2, rtol=1e-9, atol=1e-9 * angle)
    assert np.allclose(g.quat_log(q), phi, rtol=1e-9, atol=1e-9 * angle)


def test_vectorised_over_leading_axes():
    rng = np.random.default_rng(0)
    qs = g.quat_normalize(rng.normal(size=(5, 7, 4)))
    vs = rng.normal(size=(5, 7, 3))
    out = g.quat_rotate(qs, vs)
    assert out.shape == (5, 7, 3)
    assert np.allclose(out[2, 3], g.quat_rotate(qs[2, 3], vs[2, 3]))
    assert g.quat_multiply(qs, qs).shape == (5, 7, 4)
    assert g.skew(vs).shape == (5, 7, 3, 3)


@given(unit_quats(), small_vec3)
def test_world_to_body_kinematics_finite_difference(q_wb, w):
    """q̇_wb = ½ q_wb ⊗ (0, ω) (docs/design.md §5) against the exact motion q_wb ⊗ exp(ω t)."""
    h = 1e-6
    ahead = g.integrate_body_rate(q_wb, w, h)
    behind = g.integrate_body_rate(q_wb, w, -h)
    numeric = (ahead - behind) / (2 * h)
    assert np.allclose(numeric, g.quat_derivative_world_to_body(q_wb, w), atol=1e-6)


@given(unit_quats(), small_vec3)
def test_robot_centric_kinematics_finite_difference(q_wx, w):
    """q̇^{bj} = ½ Ω(ω) q^{bj} (eq. 14/15) for q^{bj} = q_{b←x}, x fixed in the world.

    The body turns at ω (body frame): q_wb(t) = q_wb(0) ⊗ exp(ω t), so
    q_{b←x}(t) = q_wb(t)* ⊗ q_wx.
    """
    q_wb0 = g.quat_normalize(np.array([0.3, -0.2, 0.9, 0.1]))

    def q_bx(t):
        return g.quat_multiply(g.quat_conjugate(g.integrate_body_rate(q_wb0, w, t)), q_wx)

    h = 1e-6
    numeric = (q_bx(h) - q_bx(-h)) / (2 * h)
    assert np.allclose(numeric, g.quat_derivative_body_to_fixed(q_bx(0.0), w), atol=1e-6)


@given(small_vec3)
def test_omega_is_left_product_with_minus_omega(w):
    q = g.quat_normalize(np.array([0.5, 0.1, -0.4, 0.7]))
    pure = np.concatenate([[0.0], -w])
    assert np.allclose(g.omega_matrix(w) @ q, g.quat_multiply(pure, q), atol=1e-12)


@given(vec3, unit_quats())
def test_landmark_body_kinematics_finite_difference(v_world, q_wb):
    """ẋ_i = −[ω]× x_i − v (eq. 1): a fixed world point seen from a moving, turning body."""
    w = np.array([0.1, -0.3, 0.7])
    v_body = np.array([0.4, 0.0, 0.0])
    p_world = v_world  # a fixed landmark

    def x_body(t):
        q = g.integrate_body_rate(q_wb, w, t)
        # position of the body: moves with v in its own (turning) frame; to first order
        pos = g.quat_rotate(q_wb, v_body) * t
        return g.quat_rotate(g.quat_conjugate(q), p_world - pos)

    h = 1e-6
    numeric = (x_body(h) - x_body(-h)) / (2 * h)
    x0 = x_body(0.0)
    assert np.allclose(numeric, -np.cross(w, x0) - v_body, atol=1e-4)


def test_ypr_matches_vn100_convention():
    # Yaw 90° (NED): body x points east = NED y.
    q = g.ypr_deg_to_quat(90.0, 0.0, 0.0)
    assert np.allclose(g.quat_rotate(q, [1, 0, 0]), [0, 1, 0], atol=1e-12)
    # Pitch 90° nose up: body x points to NED −z (up).
    q = g.ypr_deg_to_quat(0.0, 90.0, 0.0)
    assert np.allclose(g.quat_rotate(q, [1, 0, 0]), [0, 0, -1], atol=1e-12)
    ypr = np.array([170.786, -5.153, 9.880])
    assert np.allclose(g.quat_to_ypr_deg(g.ypr_deg_to_quat(*ypr)), ypr)


@given(st.floats(-3.1, 3.1))
def test_yaw_helpers(yaw):
    assert np.isclose(g.quat_to_yaw(g.yaw_to_quat(yaw)), yaw, atol=1e-12)


def test_bad_quaternion_shape_is_a_clear_error():
    try:
        g.quat_to_rotmat([1.0, 0.0, 0.0])
    except ValueError as exc:
        assert "4 components" in str(exc)
    else:
        raise AssertionError("a 3-vector was accepted as a quaternion")


def test_tangent_basis_and_cross_rows_are_np_cross_to_the_bit():
    """The written-out products are np.cross's own, so the residual bases are the same to the
    last bit (a replayed recording gives the same decisions), on both sides of the helper's
    switch (|u_x| = 0.9); the basis is orthonormal and right-handed with u."""
    rng = np.random.default_rng(7)
    u = rng.normal(size=(500, 3))
    u[:100, 0] *= 20.0  # near ±x̂: the ŷ helper
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    helper = np.where(np.abs(u[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    want = np.stack([e1, np.cross(u, e1)], axis=-1)
    got = g.tangent_basis(u)
    assert np.array_equal(got, want)
    assert np.allclose(np.einsum("nki,nkj->nij", got, got), np.eye(2), atol=1e-12)
    assert np.allclose(np.cross(got[:, :, 0], got[:, :, 1]), u, atol=1e-12)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    assert np.array_equal(g.cross_rows(a, b), np.cross(a, b))
