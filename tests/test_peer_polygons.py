"""Containment against ArduPilot's and PX4's own polygon test vectors (issue 17; the JSON
run: tools/check_peer_polygons.py)."""

import pytest
from _tools import load_tool

peers = load_tool("check_peer_polygons")

needs_cases = pytest.mark.skipif(
    not peers.DATA.exists(), reason=f"the peers' polygon cases are not present ({peers.DATA})"
)


@needs_cases
def test_every_peer_case_is_judged_as_the_peers_expect() -> None:
    result = peers.check()
    for family, r in result.items():
        assert r["cases"] > 0, family
        assert r["failures"] == [], family
    assert result["ardupilot_test_polygon"]["cases"] == 46


def test_the_segment_judgement_can_fail() -> None:
    """The sampled-segment judgement sees a corner cut 2 cm deep, and not a touch."""
    doc = {
        "square": [[0, 0], [1, 0], [1, 1], [0, 1]],
        "segment_cases": [
            {"a": [2, 0], "b": [0, 1.98], "exclusion_violates": False},  # wrong on purpose
            {"a": [2, 0], "b": [0, 2], "exclusion_violates": True},  # wrong on purpose
        ],
    }
    r = peers.px4_segments(doc)
    assert r["passed"] == 0 and len(r["failures"]) == 4
