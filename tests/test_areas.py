"""Map format 2: named mowing and navigation areas, keep-outs across edges, the TRANSIT state,
mowing only some areas, and version 1 maps read as they always decided (issue 17)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.can.permit import Status, decode_status, encode_status
from mowerhw.cli import main
from mowerhw.common.reasons import Reason, State
from mowerhw.config import ContainmentConfig
from mowerhw.map import Area, KeepOut, Landmark, LawnMap, MapError, _digest, load
from mowerhw.mow import Containment, LawnGeometry


def box(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


def garden_map() -> LawnMap:
    """Two lawns joined by a path; a keep-out across the first lawn's top edge."""
    return LawnMap(
        boundary=box(0, 0, 10, 10),
        landmarks=[Landmark(i, np.array([i, 12.0, 1.0]), np.eye(3) * 1e-4) for i in range(6)],
        keepouts=[KeepOut("bed", box(7, 8, 12, 12))],
        areas=[Area("back", "mow", box(20, 0, 30, 10)), Area("path", "nav", box(10, 4, 20, 6))],
        dock_position=np.array([11.0, 5.0, 0.0]),
    )


def decide(geom: LawnGeometry, x: float, y: float) -> tuple[str, str, bool]:
    c = Containment(geom, ContainmentConfig())
    r = c.evaluate(1.0, x, y, 0.01)
    return r.state, r.reason, r.permit


def test_containment_over_areas_says_transit_on_the_path():
    m = garden_map()
    assert m.problems() == []
    geom = LawnGeometry.of_map(m)
    assert decide(geom, 5, 5) == (State.INSIDE, "", True)
    assert decide(geom, 25, 5) == (State.INSIDE, "", True)
    assert decide(geom, 15, 5) == (State.TRANSIT, Reason.TRANSIT, False)
    assert decide(geom, 15, 8) == (State.OUTSIDE, Reason.OUTSIDE, False)
    # the keep-out crosses the lawn's edge and the path's neighbourhood: no mowing, no transit
    state, reason, permit = decide(geom, 9, 9)
    assert (state, reason, permit) == (State.OUTSIDE, Reason.OUTSIDE, False)
    assert "inside keep-out 'bed'" in Containment(geom).evaluate(1.0, 9, 9, 0.01).detail
    assert decide(geom, 11, 9) == (State.OUTSIDE, Reason.OUTSIDE, False)


def test_mowing_only_some_areas_makes_the_others_transit():
    m = garden_map()
    geom = LawnGeometry.of_map(m, ("lawn",))
    assert decide(geom, 5, 5) == (State.INSIDE, "", True)
    assert decide(geom, 25, 5) == (State.TRANSIT, Reason.TRANSIT, False)
    with pytest.raises(ValueError, match=r"no mowing area 'front' in the map .*'lawn', 'back'"):
        LawnGeometry.of_map(m, ("front",))


def test_the_transit_state_on_can_and_back():
    st = Status("TRANSIT", False, "TRANSIT", -1.25, 15.0, 5.0, math.radians(90))
    back = decode_status(encode_status(st))
    assert (back.state, back.permit, back.reason) == ("TRANSIT", False, "TRANSIT")
    assert back.signed_distance_m == pytest.approx(-1.25)
    for state in ("INSIDE", "NEAR_EDGE", "OUTSIDE", "UNKNOWN"):  # the others unchanged
        assert decode_status(encode_status(Status(state, state == "INSIDE", ""))).state == state


def _as_version_1(doc: dict) -> dict:
    """A map document as the previous format wrote it (one outline, ``boundary``)."""
    old = {k: v for k, v in doc.items() if k not in ("areas", "checksum")}
    old["version"] = 1
    old["boundary"] = doc["areas"][0]["polygon"]
    old["checksum"] = "sha256:" + _digest(old)
    return old


def test_a_version_1_map_loads_as_the_lawn_and_decides_the_same(tmp_path: Path):
    a = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    m = LawnMap(
        boundary=np.column_stack([5 * np.cos(a), 4 * np.sin(a)]),
        landmarks=[Landmark(i, np.array([i, 6.0, 1.0]), np.eye(3) * 1e-4) for i in range(6)],
        keepouts=[KeepOut("pond", box(-1, -1, 1, 1))],
    )
    path = tmp_path / "old.json"
    path.write_text(json.dumps(_as_version_1(m.to_document())))
    old = load(path)
    assert old.version == 1 and old.boundary_name == "lawn" and old.areas == []
    grid = np.random.default_rng(1).uniform(-7, 7, size=(3000, 2))
    before = LawnGeometry(old.boundary, [(z.name, z.polygon) for z in old.keepouts])
    after = LawnGeometry.of_map(old)
    assert np.array_equal(before.signed_distances(grid), after.signed_distances(grid))
    assert main(["map", "upgrade", str(path)]) == 0
    doc = json.loads(path.read_text())
    assert doc["version"] == 2 and "boundary" not in doc
    assert doc["areas"][0]["name"] == "lawn" and doc["areas"][0]["kind"] == "mow"
    new = load(path)
    upgraded = LawnGeometry.of_map(new)
    assert np.array_equal(before.signed_distances(grid), upgraded.signed_distances(grid))
    assert len(list(tmp_path.glob("old.json.*.bak"))) == 1
    assert main(["map", "upgrade", str(path)]) == 0  # already version 2: nothing written
    assert len(list(tmp_path.glob("old.json.*.bak"))) == 1


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(areas=[]), "areas must be a list of at least one area"),
        (
            lambda d: d.update(areas=[{**a, "kind": "nav"} for a in d["areas"]]),
            'no mowing area (kind "mow")',
        ),
        (lambda d: d["areas"][1].update(kind="road"), "kind 'road' is not one of mow, nav"),
        (lambda d: d["areas"][1].update(name="lawn"), "mowing area 'lawn': the name is used twice"),
        (
            lambda d: d["areas"][2].update(polygon=d["areas"][0]["polygon"]),
            "navigation area 'path': the same zone as mowing area 'lawn'",
        ),
        (
            lambda d: d["dock"].update(position=[60.0, 5.0, 0.0]),
            "dock: 30.0 m outside every area",
        ),
        (lambda d: d["areas"][1].update(name=""), "a name of 1 to 100 characters"),
    ],
)
def test_broken_areas_are_refused_by_name(tmp_path: Path, edit, message):
    doc = garden_map().to_document()
    edit(doc)
    doc["checksum"] = "sha256:" + _digest(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(MapError, match=re_escape(message)):
        load(path)


def re_escape(text: str) -> str:
    import re

    return re.escape(text)


def test_overlapping_lawns_and_a_stray_keep_out_are_warnings():
    m = garden_map().with_area("corner", "mow", box(8, 0, 12, 3))
    m = m.with_keepout("far", box(40, 40, 41, 41))
    assert m.problems() == []
    assert m.warnings() == [
        "mowing areas 'lawn' and 'corner' overlap by 6.00 m² (mowed as one)",
        "keep-out 'far': outside every area (it changes nothing)",
    ]


def test_areas_are_added_and_removed_without_driving(tmp_path: Path, capsys):
    path = tmp_path / "garden.json"
    garden_map().save(path)
    assert (
        main(
            [
                "map",
                "add-area",
                str(path),
                "--name",
                "shed",
                "--kind",
                "nav",
                "--polygon",
                "0,-3 10,-3 10,0 0,0",
            ]
        )
        == 0
    )
    assert [a.name for a in load(path).all_areas()] == ["lawn", "back", "path", "shed"]
    assert main(["map", "remove-area", str(path), "--name", "lawn"]) == 78
    assert "is the taught lawn" in capsys.readouterr().err
    assert main(["map", "remove-area", str(path), "--name", "back"]) == 0
    assert [a.name for a in load(path).all_areas()] == ["lawn", "path", "shed"]
    assert main(["map", "show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "area         'path' (navigation): 4 points, 20.0 m²" in out


def test_a_garden_goes_through_geojson_and_back(tmp_path: Path, capsys):
    path = tmp_path / "garden.json"
    garden_map().save(path)
    assert main(["map", "export-geojson", str(path)]) == 0
    doc = json.loads(path.with_suffix(".geojson").read_text())
    kinds = [(f["properties"]["kind"], f["properties"].get("name")) for f in doc["features"]]
    assert ("nav", "path") in kinds and ("mow", "back") in kinds and ("keepout", "bed") in kinds
    for f in doc["features"]:  # edited elsewhere: the path widened
        if f["properties"].get("name") == "path":
            f["geometry"]["coordinates"] = [[[10, 3], [20, 3], [20, 7], [10, 7], [10, 3]]]
    path.with_suffix(".geojson").write_text(json.dumps(doc))
    assert main(["map", "import-geojson", str(path), str(path.with_suffix(".geojson"))]) == 0
    back = load(path)
    assert [(a.name, a.kind) for a in back.all_areas()] == [
        ("lawn", "mow"),
        ("back", "mow"),
        ("path", "nav"),
    ]
    path_area = next(a for a in back.areas if a.name == "path")
    assert abs(float(np.ptp(path_area.polygon[:, 1])) - 4.0) < 1e-9
    assert decide(LawnGeometry.of_map(back), 15, 3.5)[0] == State.TRANSIT


def test_the_dock_approach_stays_inside_the_garden(tmp_path: Path, capsys):
    path = tmp_path / "garden.json"
    garden_map().save(path)  # the dock (11, 5) on the path between the lawns
    assert main(["map", "set-approach", str(path), "--path", "11,5 9,5 5,5"]) == 0
    assert np.allclose(load(path).dock_approach, [[11, 5], [9, 5], [5, 5]])
    assert main(["map", "set-approach", str(path), "--path", "11,5 15,8"]) == 78
    assert "dock approach: leaves every area (at 12.33, 6.00)" in capsys.readouterr().err
    assert main(["map", "show", str(path)]) == 0
    assert "approach of 3 points" in capsys.readouterr().out
    assert main(["map", "set-approach", str(path), "--path", "none"]) == 0
    assert load(path).dock_approach is None


def test_the_dock_approach_goes_through_geojson(tmp_path: Path):
    path = tmp_path / "garden.json"
    garden_map().with_dock_approach(np.array([[11.0, 5.0], [5.0, 5.0]])).save(path)
    assert main(["map", "export-geojson", str(path)]) == 0
    doc = json.loads(path.with_suffix(".geojson").read_text())
    way = next(f for f in doc["features"] if f["properties"]["kind"] == "approach")
    way["geometry"]["coordinates"] = [[11, 5], [8, 5], [4, 4]]  # edited
    path.with_suffix(".geojson").write_text(json.dumps(doc))
    assert main(["map", "import-geojson", str(path), str(path.with_suffix(".geojson"))]) == 0
    assert np.allclose(load(path).dock_approach, [[11, 5], [8, 5], [4, 4]])
