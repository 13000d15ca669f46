"""A whole garden in one teach drive: marked stretches of the path become zones (issue 17)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from shapely.geometry import Polygon

from mowerhw.teach.boundary import BoundaryError
from mowerhw.teach.marks import TeachMark, check_mark, dock_index, zones_from_marks


def drive(*legs: list[tuple[float, float]], step: float = 0.05):
    """A path through the waypoints of each leg, a sample every ``step`` metres, and the
    index where each leg starts."""
    pts, starts = [], []
    for leg in legs:
        starts.append(len(pts))
        for a, b in itertools.pairwise(leg):
            n = max(1, int(np.hypot(b[0] - a[0], b[1] - a[1]) / step))
            pts += [(a[0] + (b[0] - a[0]) * k / n, a[1] + (b[1] - a[1]) * k / n) for k in range(n)]
    pts.append(legs[-1][-1])
    xy = np.array(pts, float)
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    return np.arange(len(xy)) * 0.1, xy, dist, starts


def garden_drive():
    legs = [
        [(0, 0), (10, 0), (10, 10), (0, 10), (0, 0)],  # front lawn
        [(0, 0), (7, 7)],  # to the bed, unmarked
        [(7, 7), (12, 7), (12, 12), (7, 12), (7, 7)],  # the bed, across the lawn's edge
        [(7, 7), (10, 5)],
        [(10, 5), (20, 5), (20, 6), (10, 6), (10, 5)],  # the path
        [(10, 5), (20, 0)],
        [(20, 0), (30, 0), (30, 10), (20, 10), (20, 0)],  # the back lawn
        [(20, 0), (0, 0)],  # home
    ]
    t, xy, dist, s = drive(*legs)
    marks = [
        TeachMark(t[s[0]], "dock"),
        TeachMark(t[s[0]] + 1e-3, "area", "front"),
        TeachMark(t[s[1]], "end"),
        TeachMark(t[s[2]], "keepout", "bed"),
        TeachMark(t[s[3]], "end"),
        TeachMark(t[s[4]], "nav", "path"),
        TeachMark(t[s[5]], "end"),
        TeachMark(t[s[6]], "area", "back"),
        TeachMark(t[s[7]], "end"),
    ]
    return t, xy, dist, marks


def test_each_marked_stretch_becomes_its_zone():
    t, xy, dist, marks = garden_drive()
    zones = zones_from_marks(t, xy, dist, marks)
    got = {(z.kind, z.name): Polygon(z.polygon) for z in zones}
    assert list(got) == [("mow", "front"), ("keepout", "bed"), ("nav", "path"), ("mow", "back")]
    for key, area in {
        ("mow", "front"): 100.0,
        ("keepout", "bed"): 25.0,
        ("nav", "path"): 10.0,
        ("mow", "back"): 100.0,
    }.items():
        assert got[key].area == pytest.approx(area, rel=0.01)
        assert got[key].exterior.is_ccw
    assert dock_index(t, marks) == 0


def test_a_stretch_that_does_not_close_is_named():
    t, xy, dist, marks = garden_drive()
    marks = [m for m in marks if m is not marks[6]]  # the path's stretch runs on to the back
    with pytest.raises(BoundaryError, match=r"navigation area 'path': open loop"):
        zones_from_marks(t, xy, dist, marks)


def test_marks_are_checked():
    marks = [TeachMark(0.0, "area", "front")]
    assert (
        check_mark("area", "front", marks) == "teach area: a zone named 'front' is marked already"
    )
    assert check_mark("area", "", marks) == "teach area: give it a name (1 to 100 characters)"
    assert check_mark("pond", "x", marks).startswith("teach mark 'pond' is not one of area, nav")
    assert check_mark("dock", "", marks) == ""
