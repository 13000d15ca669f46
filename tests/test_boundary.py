"""The taught boundary: closed, simplified, validated with shapely (docs/design.md §4)."""

import numpy as np
import pytest
from shapely.geometry import Polygon

from mowerhw.teach.boundary import BoundaryError, boundary_from_path, close_loop


def circle(n=400, r=4.0, turns=1.0, start=0.0):
    a = start + np.linspace(0, 2 * np.pi * turns, n)
    return np.column_stack([r * np.cos(a) - r, r * np.sin(a)])


def test_closed_loop_becomes_a_ccw_simple_polygon():
    out = boundary_from_path(circle())
    poly = Polygon(out)
    assert poly.is_valid and poly.exterior.is_ccw
    assert poly.area == pytest.approx(np.pi * 16, rel=0.01)
    assert not np.allclose(out[0], out[-1])  # the first point is not repeated


def test_clockwise_drive_is_returned_counter_clockwise():
    out = boundary_from_path(circle()[::-1])
    assert Polygon(out).exterior.is_ccw


def test_overshoot_past_the_start_is_cut_at_the_crossing():
    path = circle(n=500, turns=1.05)  # drove 5 % past the start
    wobble = path + np.column_stack([np.zeros(500), 0.01 * np.sin(np.arange(500))])
    out = boundary_from_path(wobble)
    assert Polygon(out).is_valid


def test_standstill_jitter_at_the_end_is_ignored():
    path = circle(n=400)
    rng = np.random.default_rng(0)
    jitter = path[-1] + rng.normal(0, 0.01, size=(50, 2))  # 0.5 s of estimate noise, still
    xy = np.vstack([path, jitter])
    dist = np.concatenate([np.arange(400) * 0.063, np.full(50, 399 * 0.063)])
    assert Polygon(boundary_from_path(xy, distance=dist)).is_valid


def test_open_loop_is_an_error_that_says_how_far():
    with pytest.raises(
        BoundaryError, match=r"open loop: the teach drive ended \d+\.\d\d m from where it started"
    ):
        boundary_from_path(circle(turns=0.5))


def test_a_figure_eight_is_refused():
    a = np.linspace(0, 2 * np.pi, 600)
    eight = np.column_stack([4 * np.sin(a), 2 * np.sin(2 * a)])
    with pytest.raises(BoundaryError, match="crosses itself"):
        boundary_from_path(eight)


def test_a_tiny_lawn_is_refused():
    with pytest.raises(BoundaryError, match="below the minimum"):
        boundary_from_path(circle(r=0.5), min_area_m2=4.0)


def test_no_motion_and_nan_are_refused():
    with pytest.raises(BoundaryError, match="hardly moved"):
        boundary_from_path(np.zeros((100, 2)))
    bad = circle()
    bad[10] = np.nan
    with pytest.raises(BoundaryError, match="non-finite"):
        boundary_from_path(bad)


def test_close_loop_reports_the_gap_when_the_ends_do_not_cross():
    path = circle(turns=0.98)
    loop, gap = close_loop(path, 2.0)
    assert 0.4 < gap < 0.6
    assert loop.shape[0] <= path.shape[0]
