"""Depth pseudo-measurements (eq. 3)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mowerhw.common.geometry import rotmat_exp
from mowerhw.teach.depth import depth_pseudo_measurement


def _two_views(landmark_a, anchor_to_now_r, now_origin_a):
    """Anchor frame a; current frame b with axes R_ab (in a) and origin c (in a)."""
    r_ab = anchor_to_now_r
    y_a = landmark_a / np.linalg.norm(landmark_a)
    x_b = r_ab.T @ (landmark_a - now_origin_a)
    r_ba = r_ab.T
    anchor_origin_b = r_ab.T @ (-now_origin_a)
    return anchor_origin_b, r_ba, y_a, x_b


@given(
    st.floats(-10, 10),
    st.floats(3, 15),
    st.floats(-1, 2),
    st.floats(-0.5, 0.5),
    st.floats(0.5, 4.0),
    st.floats(-0.5, 0.5),
)
def test_exact_triangulation_without_noise(lx, ly, lz, yaw, cx, cy):
    landmark = np.array([lx, ly, lz])
    origin_b, r_ba, y_a, x_b = _two_views(landmark, rotmat_exp([0, 0, yaw]), np.array([cx, cy, 0]))
    dm = depth_pseudo_measurement(
        origin_b[None],
        r_ba[None],
        y_a[None],
        (x_b / np.linalg.norm(x_b))[None],
        0.005,
        np.radians(1),
        0.1,
    )
    if dm.ok[0]:
        assert dm.depth[0] == pytest.approx(np.linalg.norm(x_b), rel=1e-7)
        assert dm.variance[0] > 0


def test_guards_short_baseline_low_parallax_and_inconsistent_rays():
    landmark = np.array([2.0, 8.0, 1.0])
    # 5 cm baseline: refused
    ob, r, ya, xb = _two_views(landmark, np.eye(3), np.array([0.05, 0, 0]))
    dm = depth_pseudo_measurement(
        ob[None], r[None], ya[None], (xb / np.linalg.norm(xb))[None], 0.005, np.radians(3), 0.3
    )
    assert dm.low_parallax[0] and not dm.ok[0]
    # moving straight at the landmark: no parallax
    ob, r, ya, xb = _two_views(landmark, np.eye(3), landmark / np.linalg.norm(landmark) * 2)
    dm = depth_pseudo_measurement(
        ob[None], r[None], ya[None], (xb / np.linalg.norm(xb))[None], 0.005, np.radians(3), 0.3
    )
    assert not dm.ok[0]
    # a current bearing pointing away from where the anchor ray goes: no triangle
    ob, r, ya, xb = _two_views(landmark, np.eye(3), np.array([2.0, 0, 0]))
    wrong = np.array([0.0, -1.0, 0.0])
    dm = depth_pseudo_measurement(
        ob[None], r[None], ya[None], wrong[None], 0.005, np.radians(3), 0.3
    )
    assert dm.inconsistent[0] and not dm.ok[0]


def test_variance_grows_as_parallax_shrinks():
    out = []
    for baseline in (0.5, 1.0, 3.0):
        ob, r, ya, xb = _two_views(np.array([0.0, 6.0, 0.5]), np.eye(3), np.array([baseline, 0, 0]))
        dm = depth_pseudo_measurement(
            ob[None], r[None], ya[None], (xb / np.linalg.norm(xb))[None], 0.005, 0.01, 0.1
        )
        out.append(np.sqrt(dm.variance[0]) / dm.depth[0])
    assert out[0] > out[1] > out[2]
