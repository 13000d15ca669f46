"""The map file: versioned JSON with a checksum, written atomically, refused when broken."""

import json
import os

import numpy as np
import pytest

from mowerhw import map as lawnmap
from mowerhw.map import KeepOut, Landmark, LawnMap, MapError


def make_map(n_landmarks=6) -> LawnMap:
    a = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    boundary = np.column_stack([5 * np.cos(a), 4 * np.sin(a)])
    rng = np.random.default_rng(0)
    lms = [
        Landmark(i, rng.uniform(-8, 8, 3), np.eye(3) * 1e-4, descriptor=bytes([i] * 32))
        for i in range(n_landmarks)
    ]
    return LawnMap(boundary=boundary, landmarks=lms, camera=None, teach={"distance_m": 28.3})


def test_round_trip(tmp_path):
    m = make_map()
    m.save(tmp_path / "lawn.json")
    back = lawnmap.load(tmp_path / "lawn.json")
    assert np.allclose(back.boundary, m.boundary)
    assert [lm.id for lm in back.landmarks] == list(range(6))
    assert back.landmarks[3].descriptor == bytes([3] * 32)
    assert np.allclose(back.landmark_positions(), m.landmark_positions())
    assert back.checksum.startswith("sha256:") and back.checksum == m.checksum
    doc = json.loads((tmp_path / "lawn.json").read_text())
    assert doc["format"] == "mowerhw-map" and doc["version"] == 2


def test_write_is_atomic_and_leaves_no_temp_files(tmp_path):
    path = tmp_path / "lawn.json"
    make_map().save(path)
    before = path.read_bytes()

    class Boom(Exception):
        pass

    m = make_map()
    real = os.fsync

    def failing_fsync(fd):
        raise Boom()

    os.fsync = failing_fsync
    try:
        with pytest.raises(Boom):
            m.save(path)
    finally:
        os.fsync = real
    assert path.read_bytes() == before  # the old map is untouched
    assert [p.name for p in tmp_path.iterdir()] == ["lawn.json"]


def test_truncated_file_is_refused(tmp_path):
    path = tmp_path / "lawn.json"
    make_map().save(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapError, match=r"not valid JSON .*truncated or corrupt"):
        lawnmap.load(path)


def test_tampered_file_is_refused(tmp_path):
    path = tmp_path / "lawn.json"
    make_map().save(path)
    doc = json.loads(path.read_text())
    doc["areas"][0]["polygon"][0][0] += 0.5  # someone "fixed" the boundary by hand
    path.write_text(json.dumps(doc))
    with pytest.raises(MapError, match="checksum mismatch"):
        lawnmap.load(path)


def test_wrong_version_format_and_missing_checksum(tmp_path):
    path = tmp_path / "lawn.json"
    make_map().save(path)
    doc = json.loads(path.read_text())
    path.write_text(json.dumps({**doc, "version": 3}))
    with pytest.raises(MapError, match=r"version 3 is not supported .*supported: 1, 2"):
        lawnmap.load(path)
    path.write_text(json.dumps({**doc, "format": "gpx"}))
    with pytest.raises(
        MapError, match=r"not a mowerhw map .*'gpx'.*'mowerhw-map'.*import-openmower"
    ):
        lawnmap.load(path)
    no_sum = {k: v for k, v in doc.items() if k != "checksum"}
    path.write_text(json.dumps(no_sum))
    with pytest.raises(MapError, match="no checksum"):
        lawnmap.load(path)


def test_missing_and_empty(tmp_path):
    with pytest.raises(MapError, match="map file not found"):
        lawnmap.load(tmp_path / "nope.json")
    (tmp_path / "empty.json").write_text("")
    with pytest.raises(MapError, match="empty"):
        lawnmap.load(tmp_path / "empty.json")


def test_an_unusable_map_is_never_saved_nor_loaded(tmp_path):
    m = make_map(n_landmarks=2)
    with pytest.raises(MapError, match="at least 4 needed"):
        m.save(tmp_path / "x.json")
    # a well-formed file with a bow-tie boundary (checksum valid) still does not load
    bad = make_map()
    bad.boundary = np.array([[0, 0], [4, 4], [4, 0], [0, 4]], float)
    doc = bad.to_document()
    (tmp_path / "bow.json").write_text(json.dumps(doc))
    with pytest.raises(MapError, match="not a simple polygon"):
        lawnmap.load(tmp_path / "bow.json")


def test_keepouts_edit_and_validate(tmp_path):
    m = make_map()
    m2 = m.with_keepout("pond", np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float))
    assert m2.lawn_polygon().area == pytest.approx(m.outline_polygon().area - 1.0, rel=1e-6)
    m2.save(tmp_path / "k.json")
    back = lawnmap.load(tmp_path / "k.json")
    assert [z.name for z in back.keepouts] == ["pond"]
    # a keep-out may cross the edge (version 2): it is taken out of the lawn
    road = m.with_keepout("road", np.array([[4, -1], [12, -1], [12, 1], [4, 1]], float))
    assert road.problems() == [] and road.lawn_polygon().area < m.lawn_polygon().area
    with pytest.raises(MapError, match="the same zone as keep-out 'pond'"):
        m2.with_keepout("pond2", np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)[::-1])
    with pytest.raises(MapError, match="exists already"):
        m2.with_keepout("pond", np.array([[2, 0], [3, 0], [3, 1]], float))
    assert m2.without_keepout("pond").keepouts == []
    with pytest.raises(MapError, match="no keep-out zone named 'lake'"):
        m2.without_keepout("lake")
    assert isinstance(back.keepouts[0], KeepOut)


def test_non_finite_numbers_are_refused(tmp_path):
    path = tmp_path / "lawn.json"
    make_map().save(path)
    text = path.read_text().replace('"distance_m": 28.3', '"distance_m": NaN')
    path.write_text(text)
    with pytest.raises(MapError):
        lawnmap.load(path)


def test_the_map_frames_covariance_round_trips_and_a_bad_one_is_named(tmp_path):
    """A taught map keeps its frame's 4×4 covariance (shift, turn, scale); one that is not
    a covariance, or says the frame is off by more than a map could be, is refused by name.
    A map without one loads without one (older maps)."""
    m = make_map()
    frame = np.diag([1e-6, 2e-6, 1e-8, 4e-7])
    frame[0, 3] = frame[3, 0] = 1e-7
    with_frame = LawnMap(**{**vars(m), "frame_covariance": frame})
    path = tmp_path / "lawn.json"
    with_frame.save(path)
    assert np.allclose(lawnmap.load(path).frame_covariance, frame)
    m.save(tmp_path / "old.json")
    assert lawnmap.load(tmp_path / "old.json").frame_covariance is None
    assert "frame_covariance" not in json.loads((tmp_path / "old.json").read_text())
    bad = {
        "not symmetric": np.triu(np.ones((4, 4))) * 1e-6,
        "not positive semi-definite": np.diag([1e-6, 1e-6, -1e-6, 1e-6]),
        "σ of scale": np.diag([1e-6, 1e-6, 1e-8, 0.5]),
        "shape (4, 4)": np.eye(3) * 1e-6,
    }
    for why, cov in bad.items():
        doc = json.loads(path.read_text())
        doc["frame_covariance"] = cov.tolist()
        doc["checksum"] = "sha256:" + lawnmap._digest(doc)
        path.write_text(json.dumps(doc))
        with pytest.raises(MapError, match="frame_covariance") as err:
            lawnmap.load(path)
        assert why in str(err.value)


def test_the_frames_error_at_a_pose_grows_with_its_distance_from_the_origin():
    """Against the ground, a pose on the map carries the frame's error: its shift anywhere,
    its turn and scale in proportion to the distance from the map's origin; the turn is
    the heading's too."""
    frame = np.diag([1e-6, 1e-6, 1e-8, 1e-6])
    at_origin = lawnmap.frame_pose_covariance(frame, np.array([0.0, 0.0]))
    assert np.allclose(at_origin, np.diag([1e-6, 1e-6, 1e-8]))
    far = lawnmap.frame_pose_covariance(frame, np.array([10.0, 0.0]))
    # along x: the scale (10 m × 1e-3); across: the turn (10 m × 1e-4 rad)
    assert far[0, 0] == pytest.approx(1e-6 + 100 * 1e-6)
    assert far[1, 1] == pytest.approx(1e-6 + 100 * 1e-8)
    assert far[1, 2] == pytest.approx(10 * 1e-8) and far[2, 2] == pytest.approx(1e-8)
