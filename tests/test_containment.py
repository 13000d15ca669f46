"""Containment, tested the way ArduPilot tests its fences."""

import numpy as np
import pytest
import shapely

from mowerhw.config import ContainmentConfig
from mowerhw.mow.containment import Containment, LawnGeometry, NearestEdge, Reason, State

SQUARE = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
CFG = ContainmentConfig(
    margin_m=0.4, k_sigma=3.0, sigma_max_m=0.3, soft_persist=3, hard_margin_m=0.1
)


def decide(points, sigma=0.01, outline=SQUARE, keepouts=(), samples=1):
    c = Containment(LawnGeometry(outline, list(keepouts)), CFG)
    out = []
    for x, y in points:
        c2 = Containment(c.geometry, CFG)
        for k in range(samples):
            r = c2.evaluate(float(k), x, y, sigma)
        out.append(r)
    return out


@pytest.mark.parametrize("outline", [SQUARE, SQUARE[::-1]], ids=["ccw", "cw"])
def test_winding_order_does_not_matter(outline):
    r = decide([(5, 5), (5, 0.2), (5, -0.5), (12, 5)], outline=outline, samples=5)
    assert [x.state for x in r] == ["INSIDE", "NEAR_EDGE", "OUTSIDE", "OUTSIDE"]
    assert r[0].signed_distance_m == pytest.approx(5.0)
    assert r[3].signed_distance_m == pytest.approx(-2.0)


def test_points_on_edges_and_vertices_are_not_permitted():
    r = decide([(5, 0), (0, 0), (10, 10), (0, 5)], samples=5)
    assert all(x.state == "OUTSIDE" and not x.permit for x in r)
    assert all(x.signed_distance_m == pytest.approx(0.0, abs=1e-12) for x in r)


def test_large_coordinates():
    off = np.array([1.0e6, -2.0e6])
    a = decide([(5, 5), (5, 0.2), (5, -0.5)], samples=5)
    b = decide(
        [tuple(np.array(p) + off) for p in [(5, 5), (5, 0.2), (5, -0.5)]],
        outline=SQUARE + off,
        samples=5,
    )
    assert [x.state for x in a] == [x.state for x in b]
    assert [x.signed_distance_m for x in a] == pytest.approx(
        [x.signed_distance_m for x in b], abs=1e-6
    )


def test_keep_out_zones_are_holes():
    pond = ("pond", np.array([[4, 4], [6, 4], [6, 6], [4, 6]], float))
    r = decide([(5, 5), (3.8, 5), (3.0, 5), (4.05, 5)], keepouts=[pond], samples=5)
    assert r[0].state == "OUTSIDE" and "inside keep-out 'pond'" in r[0].detail
    assert r[1].state == "NEAR_EDGE"  # 0.2 m from the pond
    assert r[2].state == "INSIDE"
    assert r[3].state == "OUTSIDE"
    assert r[0].reason == Reason.OUTSIDE


def test_concave_lawn_notch_is_outside():
    u_shape = np.array([[0, 0], [9, 0], [9, 9], [6, 9], [6, 3], [3, 3], [3, 9], [0, 9]], float)
    r = decide([(4.5, 6), (1.5, 6), (7.5, 6), (4.5, 1.5)], outline=u_shape, samples=5)
    assert [x.state for x in r] == ["OUTSIDE", "INSIDE", "INSIDE", "INSIDE"]
    assert r[0].signed_distance_m == pytest.approx(-1.5)


def test_uncertainty_moves_the_edge_and_too_much_is_unknown():
    inside = decide([(5, 1.0)], sigma=0.01)[0]
    assert inside.state == "INSIDE"
    near = decide([(5, 1.0)], sigma=0.25)[0]  # 1.0 − 3·0.25 = 0.25 < margin
    assert near.state == "NEAR_EDGE" and near.permit
    lost = decide([(5, 5)], sigma=0.35)[0]
    assert lost.state == "UNKNOWN" and not lost.permit and lost.reason == Reason.UNCERTAIN


def test_soft_margin_must_persist_and_release_is_hysteretic():
    c = Containment(LawnGeometry(SQUARE), CFG)
    seq = [(5, -0.05)] * 4 + [(5, 0.5)] * 4
    res = [c.evaluate(float(k), x, y, 0.005) for k, (x, y) in enumerate(seq)]
    assert [r.permit for r in res] == [True, True, False, False, False, False, True, True]
    assert res[0].state == "NEAR_EDGE" and "soft margin 1/3" in res[0].detail
    assert res[4].state == "OUTSIDE" and "back inside 1/3" in res[4].detail


def test_hard_margin_halts_at_once():
    c = Containment(LawnGeometry(SQUARE), CFG)
    r = c.evaluate(0.0, 5, -0.3, 0.005)
    assert r.state == "OUTSIDE" and not r.permit and "hard margin" in r.detail


def test_repeated_evaluation_of_one_sample_does_not_count_twice():
    c = Containment(LawnGeometry(SQUARE), CFG)
    for _ in range(10):
        r = c.evaluate(1.0, 5, -0.05, 0.005)
    assert r.permit  # still one sample of a soft violation


def test_forced_halts_carry_their_reason():
    c = Containment(LawnGeometry(SQUARE), CFG)
    for reason in (Reason.NOT_LOCALIZED, Reason.SENSOR_STALE, Reason.FAULT):
        r = c.evaluate(0.0, 5, 5, 0.01, (reason, "why"))
        assert r.state == State.UNKNOWN and not r.permit and r.reason == reason.value
        assert r.detail == "why"
    r = c.evaluate(1.0, float("nan"), 5, 0.01)
    assert r.reason == Reason.FAULT and not r.permit


def test_inward_direction_points_into_the_lawn():
    g = LawnGeometry(SQUARE)
    assert np.allclose(g.inward_direction(5, 0.2), [0, 1], atol=1e-9)
    assert np.allclose(g.inward_direction(5, -0.5), [0, 1], atol=1e-9)
    assert np.allclose(g.inward_direction(9.9, 5), [-1, 0], atol=1e-9)


def test_signed_distances_vectorised_match():
    g = LawnGeometry(SQUARE, [("pond", np.array([[4, 4], [6, 4], [6, 6], [4, 6]], float))])
    pts = np.random.default_rng(0).uniform(-2, 12, size=(200, 2))
    one = np.array([g.signed_distance(x, y) for x, y in pts])
    assert np.allclose(g.signed_distances(pts), one)


@pytest.mark.parametrize(
    "outline",
    [
        SQUARE,
        # a 200-gon of 40 m: its centre's cells have every segment as a candidate (measured
        # in numpy), and a large lawn's cells are larger than the smallest
        np.column_stack([np.cos(a := np.linspace(0, 2 * np.pi, 200, endpoint=False)), np.sin(a)])
        * 20.0,
        # a long thin strip with a notch: candidates on both sides of a narrow lawn
        np.array([[0, 0], [60, 0], [60, 3], [31, 3], [30, 1.5], [29, 3], [0, 3]], float),
    ],
    ids=["square", "circle", "strip"],
)
def test_the_nearest_edge_grid_gives_the_distance_to_every_segment(outline):
    """The per-sample distance (:class:`NearestEdge`: a few candidate segments per grid
    cell) is the distance to the nearest of all the edges, on and off the grid, against
    shapely's distance to the boundary."""
    pond = np.array([[4, 1], [6, 1], [6, 2], [4, 2]], float)
    g = LawnGeometry(outline, [("pond", pond)])
    grid: NearestEdge = g._nearest
    lo, hi = outline.min(axis=0) - 3.0, outline.max(axis=0) + 3.0
    pts = np.random.default_rng(5).uniform(lo, hi, size=(3000, 2))
    ours = np.array([grid.distance(x, y) for x, y in pts])
    theirs = shapely.distance(g.edges, shapely.points(pts))
    assert np.allclose(ours, theirs, atol=1e-9)
    inner = sum(c is None for c in grid._cells)
    assert (inner > 0) == (len(outline) == 200)  # only the 200-gon's centre falls back


def test_signed_distance_along_a_path_keeps_the_right_side():
    """Per sample the inside test is skipped while the point cannot have crossed an edge
    (closer to the last tested point than its distance): a path wandering in and out of
    the lawn and a keep-out, in small and large steps, against shapely's answer each time."""
    pond = np.array([[4, 4], [6, 4], [6, 6], [4, 6]], float)
    g = LawnGeometry(SQUARE, [("pond", pond)])
    rng = np.random.default_rng(3)
    steps = rng.normal(0.0, 0.05, size=(4000, 2)) * rng.choice([0.1, 1.0, 20.0], size=(4000, 1))
    path = np.clip(np.cumsum(steps, axis=0) + 5.0, -2.0, 12.0)
    path[::97] = [4.0, 5.0]  # exactly on the keep-out's edge now and then
    one = np.array([g.signed_distance(x, y) for x, y in path])
    assert np.allclose(g.signed_distances(path), one, atol=1e-12)
    assert (one < 0).any() and (one > 0).any()


def test_a_decision_before_the_first_sample_does_not_freeze_the_counters():
    """The daemon asks for a decision before any IMU sample (time NaN); the soft-margin and
    release counters must still count afterwards (found on the bench: a latched OUTSIDE
    never released)."""
    c = Containment(LawnGeometry(SQUARE), CFG)
    r = c.evaluate(float("nan"), 5, 5, 0.005, halt=(Reason.NOT_LOCALIZED, "no IMU sample yet"))
    assert r.reason == "NOT_LOCALIZED"
    seq = [(5, -0.05)] * 4 + [(5, 0.5)] * 4
    res = [c.evaluate(float(k), x, y, 0.005) for k, (x, y) in enumerate(seq)]
    assert [r.permit for r in res] == [True, True, False, False, False, False, True, True]


def test_inward_is_well_defined_on_the_edge_and_at_its_corners():
    """The dock lies on the taught edge: whatever millimetre of noise puts the estimate just
    inside or just outside, even at a corner, "inward" points into the lawn."""
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float)
    geom = LawnGeometry(square)
    rng = np.random.default_rng(0)
    for corner in square:
        for _ in range(50):
            p = corner + rng.normal(0.0, 0.002, 2)
            n = geom.inward_direction(*p)
            assert abs(np.linalg.norm(n) - 1.0) < 1e-9
            # a step of 0.5 m along it lands well inside the lawn
            assert geom.signed_distance(*(p + 0.5 * n)) > 0.3
    for p in ([5.0, 0.001], [5.0, -0.001], [10.002, 5.0], [4.0, 3.0], [12.0, 5.0]):
        n = geom.inward_direction(*p)
        assert geom.signed_distance(*(np.array(p) + 0.3 * n)) > geom.signed_distance(*p)
