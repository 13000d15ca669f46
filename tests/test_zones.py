"""Zones from other tools (issue 17): outlines cleaned with each repair said, unusable ones
refused by name, the real OpenMower garden read, and containment over it against an
independent even-odd reference (the full grid: tools/check_garden_containment.py)."""

import numpy as np
import pytest
from _tools import load_tool

from mowerhw.zones import ZoneError, clean_outline, read_openmower

garden = load_tool("check_garden_containment")
needs_garden = pytest.mark.skipif(
    not garden.DATA.exists(), reason=f"the OpenMower garden map is not present ({garden.DATA})"
)


def test_outlines_are_repaired_and_each_repair_is_said() -> None:
    cw_closed_dup = [[0, 0], [0, 0], [0, 4], [3, 4], [3, 0], [0, 0]]
    ring, repairs = clean_outline(cw_closed_dup, "bed")
    assert ring.tolist() == [[3, 0], [3, 4], [0, 4], [0, 0]]  # counter-clockwise, open
    assert repairs == [
        "bed: 1 repeated vertex(es) removed",
        "bed: the closing vertex (a repeat of the first) removed",
        "bed: clockwise outline made counter-clockwise",
    ]
    ring, repairs = clean_outline([[0, 0], [3, 0], [3, 4]], "ok")
    assert repairs == [] and ring.shape == (3, 2)


@pytest.mark.parametrize(
    ("points", "message"),
    [
        ([[0, 0], [2, 2], [2, 0], [0, 2]], "not a simple polygon (Self-intersection"),
        ([[0, 0], [1, 1], [0, 0]], "fewer than 3 distinct vertices"),
        ([[0, 0], [1, float("nan")], [0, 1]], "not finite"),
        ([[0, 0], [1e9, 0], [0, 1]], "beyond ±10000 m"),
        ([[0, 0], [1, 0], [2, 0]], "not a simple polygon"),  # collinear: no area
        ("abc", "not a list of [x, y]"),
    ],
)
def test_unusable_outlines_are_refused_by_name(points, message) -> None:
    with pytest.raises(ZoneError) as err:
        clean_outline(points, "pond")
    assert str(err.value).startswith("pond: ") and message in str(err.value)


@needs_garden
def test_the_real_openmower_garden_is_read_with_its_quirks_repaired() -> None:
    g = read_openmower(garden.DATA)
    kinds = [z.kind for z in g.zones]
    assert (kinds.count("mow"), kinds.count("keepout"), kinds.count("nav")) == (9, 22, 1)
    assert all(z.area_m2() > 0 for z in g.zones)
    assert any("clockwise outline made counter-clockwise" in r for r in g.repairs)
    assert any("repeated vertex" in r for r in g.repairs)
    assert any("closing vertex" in r for r in g.repairs)
    assert g.dock_xy is not None and np.isfinite(g.dock_xy).all()


@needs_garden
def test_containment_over_the_garden_agrees_with_even_odd() -> None:
    r = garden.check(step=0.25)
    assert r["disagreements"] == 0 and r["compared"] > 30_000
    assert r["states"]["INSIDE"] > 0 and r["states"]["TRANSIT"] > 0


def test_the_even_odd_reference_can_disagree() -> None:
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    pts = np.array([[0.5, 0.5], [1.5, 0.5], [0.5, -0.2]])
    assert garden.even_odd(square, pts).tolist() == [True, False, False]
    assert garden.even_odd(square + 1.0, pts).tolist() == [False, False, False]


def test_a_broken_backup_is_refused(tmp_path) -> None:
    path = tmp_path / "m.json"
    path.write_text('{"areas": [{"properties": {"type": "lawn"}, "outline": []}]}')
    with pytest.raises(ZoneError, match="unknown type"):
        read_openmower(path)
    path.write_text("[" * 100_000)
    with pytest.raises(ZoneError, match="not an OpenMower map backup"):
        read_openmower(path)


def test_geojson_round_trip_and_an_edit_come_back_into_the_map(map_file, tmp_path, capsys) -> None:
    import json

    from mowerhw.cli import main
    from mowerhw.map import load
    from mowerhw.zones import read_geojson

    path = map_file
    assert main(["map", "export-geojson", str(path)]) == 0
    gj = path.with_suffix(".geojson")
    doc = json.loads(gj.read_text())
    assert doc["type"] == "FeatureCollection" and "local metres" in doc["mowerhw"]["frame"]
    back = read_geojson(gj)
    assert [z.kind for z in back.zones] == ["mow"] and back.repairs == []
    assert np.allclose(back.zones[0].polygon, load(path).garden().zones[0].polygon, atol=1e-6)
    # an editor adds a clockwise keep-out with the ring closed
    doc["features"].append(
        {
            "type": "Feature",
            "properties": {"kind": "keepout", "name": "sandpit"},
            "geometry": {
                "type": "Polygon",
                "coordinates": [[[1, 1], [1, 2], [2, 2], [2, 1], [1, 1]]],
            },
        }
    )
    gj.write_text(json.dumps(doc))
    assert main(["map", "import-geojson", str(path), str(gj)]) == 0
    out = capsys.readouterr().out
    assert "sandpit': clockwise outline made counter-clockwise" in out
    m = load(path)
    assert [z.name for z in m.keepouts] == ["sandpit"] and len(m.landmarks) == 6
    assert list(tmp_path.glob("lawn.json.*.bak"))


@pytest.mark.parametrize(
    ("feature", "message"),
    [
        ({"kind": "mow", "name": "patch"}, "mowing area 'patch': encloses 1.0 m², less than 4.0"),
        ({"kind": "lawn", "name": "x"}, "kind must be one of mow, nav, keepout, dock or approach"),
        ({"kind": "keepout", "name": "hole", "hole": True}, "holes are not allowed"),
    ],
)
def test_geojson_that_the_map_cannot_take_is_refused(map_file, capsys, feature, message) -> None:
    import json

    from mowerhw.cli import main

    path = map_file
    main(["map", "export-geojson", str(path)])
    gj = path.with_suffix(".geojson")
    doc = json.loads(gj.read_text())
    ring = [[10, 10], [11, 10], [11, 11], [10, 11], [10, 10]]
    rings = (
        [ring, [[10.2, 10.2], [10.4, 10.2], [10.4, 10.4], [10.2, 10.2]]]
        if feature.pop("hole", False)
        else [ring]
    )
    doc["features"].append(
        {
            "type": "Feature",
            "properties": feature,
            "geometry": {"type": "Polygon", "coordinates": rings},
        }
    )
    gj.write_text(json.dumps(doc))
    before = path.read_bytes()
    assert main(["map", "import-geojson", str(path), str(gj)]) == 78
    assert message in capsys.readouterr().err
    assert path.read_bytes() == before


def _openmower_file(tmp_path, dock=(1.0, 1.0), heading=0.0):
    import json

    def outline(pts):
        return [{"x": x, "y": y} for x, y in pts]

    doc = {
        "areas": [
            {
                "id": "front",
                "properties": {"type": "mow"},
                "outline": outline([[0, 0], [0, 8], [10, 8], [10, 0]]),
            },
            {
                "id": "back",
                "properties": {"type": "mow"},
                "outline": outline([[20, 0], [30, 0], [30, 5], [20, 5]]),
            },
            {
                "id": "bed",
                "properties": {"type": "obstacle"},
                "outline": outline([[8, 3], [12, 3], [12, 5], [8, 5], [8, 3]]),
            },
            {
                "id": "path",
                "properties": {"type": "nav"},
                "outline": outline([[10, 3], [20, 3], [20, 4], [10, 4]]),
            },
        ],
        "docking_stations": [{"position": {"x": dock[0], "y": dock[1]}, "heading": heading}],
    }
    path = tmp_path / "openmower.json"
    path.write_text(json.dumps(doc))
    return path


def test_an_openmower_garden_is_imported_by_the_dock(map_file, tmp_path, capsys) -> None:
    from mowerhw.cli import main
    from mowerhw.map import load

    m = map_file
    om = _openmower_file(tmp_path, dock=(1.0, 1.0), heading=0.5)
    assert main(["map", "import-openmower", str(om), "--into", str(m)]) == 0
    out = capsys.readouterr().out
    assert "imported 2 mowing area(s), 1 navigation area(s) and 1 obstacle(s)" in out
    assert "clockwise outline made counter-clockwise" in out
    lawn = load(m)
    assert [(a.name, a.kind) for a in lawn.all_areas()] == [
        ("lawn", "mow"),
        ("front", "mow"),
        ("back", "mow"),
        ("path", "nav"),
    ]
    # aligned: the OpenMower dock (1, 1, heading 0.5) lands on the map's dock (0, 0, heading 0)
    c, s = np.cos(-0.5), np.sin(-0.5)
    corner = np.array([[c, -s], [s, c]]) @ (np.array([10.0, 8.0]) - [1.0, 1.0])
    front = next(a for a in lawn.areas if a.name == "front")
    assert np.min(np.linalg.norm(front.polygon - corner, axis=1)) < 1e-6
    # the obstacle crosses the front lawn's edge into the path: kept whole (it is taken out)
    assert [z.name for z in lawn.keepouts] == ["bed"] and len(lawn.keepouts[0].polygon) == 4
    assert len(lawn.landmarks) == 6


def test_openmower_areas_are_chosen_and_refused_by_name(map_file, tmp_path, capsys) -> None:
    from mowerhw.cli import main
    from mowerhw.map import load

    m = map_file
    om = _openmower_file(tmp_path)
    before = m.read_bytes()
    assert main(["map", "import-openmower", str(om), "--into", str(m), "--area", "nope"]) == 78
    err = capsys.readouterr().err
    assert "no mowing area 'nope' in" in err and "(its mowing areas: 'back', 'front')" in err
    assert m.read_bytes() == before
    assert main(["map", "import-openmower", str(om), "--into", str(m), "--area", "back"]) == 0
    assert load(m).area_names("mow") == ["lawn", "back"]
    assert main(["map", "import-openmower", str(om), "--into", str(m), "--area", "back"]) == 78
    assert "'back', 'bed', 'path': already in" in capsys.readouterr().err


def test_alignment_by_reference_points_finds_the_rigid_motion() -> None:
    from mowerhw.zones import Garden, Zone, align_by_points

    square = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]])
    g = Garden([Zone("a", "mow", square)])
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s], [s, c]])
    target = square @ rot.T + [5.0, -2.0]
    moved, rms = align_by_points(g, square[:3], target[:3])
    assert rms < 1e-9 and np.allclose(moved.zones[0].polygon, target)
    with pytest.raises(ZoneError, match="two or more distinct pairs"):
        align_by_points(g, square[:1], target[:1])
