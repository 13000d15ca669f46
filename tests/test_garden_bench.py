"""The two-lawn garden of the bench (issue 17): its teach drive and the mower's controller."""

from __future__ import annotations

import math

import numpy as np
import shapely

from mowerhw.bench.garden import RouteThenCover, _coverage
from mowerhw.runtime.pipelines import TeachPipeline
from mowerhw.sim import make_world
from mowerhw.sim.garden import DOCK, garden_drive, zone_outline
from mowerhw.teach.marks import MARK_KINDS, TeachMark, dock_index, zones_from_marks


def test_the_garden_drive_marks_every_zone_and_ends_on_the_dock() -> None:
    drive = garden_drive(0.45, 0.8)
    tr = drive.truth
    xy = tr.map_xy
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    marks = [TeachMark(t, kind, name) for t, kind, name in drive.marks]
    zones = {z.name: z for z in zones_from_marks(tr.t, xy, dist, marks)}
    assert [(z.kind, n) for n, z in zones.items()] == [
        ("nav", "path"),
        ("mow", "front"),
        ("keepout", "bed"),
        ("mow", "back"),
    ]
    for name, zone in zones.items():  # each zone is the track driven around it
        got, want = shapely.Polygon(zone.polygon), shapely.Polygon(zone_outline(name))
        assert got.symmetric_difference(want).area < 0.02 * want.area, name
    front, bed = shapely.Polygon(zone_outline("front")), shapely.Polygon(zone_outline("bed"))
    assert bed.intersects(front.boundary)  # the bed crosses the front lawn's edge
    dock = shapely.Point(DOCK[0], DOCK[1])
    path = shapely.Polygon(zone_outline("path"))
    assert path.contains(dock) and not front.contains(dock)
    assert dock_index(tr.t, marks) is not None and np.allclose(xy[0], DOCK[:2])
    assert np.allclose(xy[-1], DOCK[:2], atol=1e-6)
    assert math.isclose(math.cos(tr.map_heading[-1] - DOCK[2]), 1.0, abs_tol=1e-9)
    # the daemon's automatic end of teach (stopped, near the start, no zone open) must not
    # fire before the drive is home: never stopped that long near the dock between zones
    open_zone = np.zeros(tr.t.size, bool)
    for k, m in enumerate(marks):
        end = marks[k + 1].t if k + 1 < len(marks) else np.inf
        open_zone |= (tr.t >= m.t) & (tr.t < end) & (MARK_KINDS[m.kind] is not None)
    near = np.hypot(xy[:, 0] - DOCK[0], xy[:, 1] - DOCK[1]) < TeachPipeline.AUTO_CLOSE_M
    still = tr.speed == 0.0
    home = tr.t >= tr.t[-1] - 10.0
    run = 0.0
    for k in range(1, tr.t.size):
        run = run + (tr.t[k] - tr.t[k - 1]) if still[k] and near[k] and not open_zone[k] else 0.0
        assert run < TeachPipeline.AUTO_STOPPED_S or home[k] or tr.t[k] < 5.0


def test_the_garden_world_has_landmarks_around_both_lawns() -> None:
    w = make_world("garden", 7)
    xy = w.landmarks_map[:, :2]
    assert w.n_landmarks == 36
    assert (xy[:, 0] < 10).sum() >= 10 and (xy[:, 0] > 10).sum() >= 10


def test_the_controller_follows_its_route_then_covers() -> None:
    ctl = RouteThenCover(seed=1)
    assert ctl.command(0.0, 0.0, 0.0, 0.0, "TRANSIT", False) == (0.0, 0.0)  # no plan yet
    ctl.go("front", [np.array([2.0, 0.0]), np.array([2.0, 2.0])], lambda x, y: np.array([1, 0]))
    assert ctl.command(0.0, 0.0, 0.0, 0.0, "UNKNOWN", False) == (0.0, 0.0)
    v, w = ctl.command(0.0, 0.0, 0.0, 0.0, "TRANSIT", False)  # deck off, in the path: drives
    assert v > 0 and abs(w) < 1e-9
    v, w = ctl.command(0.0, 2.0, 0.0, 0.0, "TRANSIT", False)  # first waypoint: turn left
    assert v == 0.0 and w > 0
    ctl.command(0.0, 2.0, 2.0, math.pi / 2, "INSIDE", True)  # there: covering
    assert ctl.phase == "cover"
    assert ctl.command(1.0, 2.0, 2.0, math.pi / 2, "INSIDE", True)[0] > 0
    assert ctl.command(1.0, 2.0, 2.0, math.pi / 2, "INSIDE", False) == (0.0, 0.0)  # halted


def test_coverage_counts_cells_passed() -> None:
    square = shapely.box(0, 0, 2, 2)  # 16 cells of 0.5 m
    assert _coverage(square, np.zeros((0, 2))) == 0.0
    assert _coverage(square, np.array([[0.1, 0.1], [0.2, 0.2], [1.9, 1.9]])) == 2 / 16
