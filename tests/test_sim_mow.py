"""Closed-loop mowing on the bench: the estimate drives the mower, containment must hold."""

import numpy as np
import pytest

from mowerhw.evaluation.mow import run_mow
from mowerhw.evaluation.teach import run_teach
from mowerhw.map import LawnMap


@pytest.fixture(scope="module")
def lawn_map():
    out = run_teach("paper", seed=9)
    m = LawnMap.from_teach_result(out.result)
    m.teach["sim"] = {"scenario": "paper", "seed": 9}
    return m


def test_short_mowing_run(lawn_map):
    o = run_mow(lawn_map, "paper", 9, duration_s=90.0)
    m = o.metrics
    assert m["missed_halts"] == 0
    assert m["position_rmse_m"] < 0.05
    assert m["quaternion_err_max"] < 0.03
    assert m["false_halt_fraction"] < 0.05
    assert m["edge_turns"] >= 2  # it reached the edge and turned back
    assert m["localizer"]["late_frames"] > 100


def test_keepout_zone_is_respected(lawn_map):
    c = lawn_map.lawn_polygon().representative_point()
    zone = np.array(
        [[c.x - 1, c.y - 1], [c.x + 1, c.y - 1], [c.x + 1, c.y + 1], [c.x - 1, c.y + 1]]
    )
    with_zone = lawn_map.with_keepout("sandpit", zone)
    o = run_mow(with_zone, "paper", 9, duration_s=90.0)
    assert o.metrics["missed_halts"] == 0
    inside_zone = (np.abs(o.true_xy[:, 0] - c.x) < 0.9) & (np.abs(o.true_xy[:, 1] - c.y) < 0.9)
    assert not np.any(o.permit & inside_zone)
