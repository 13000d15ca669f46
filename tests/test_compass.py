"""The magnetometer as a coarse compass (issue 18): the field's direction learnt while
teaching, the heading it gives when mowing, disturbed readings refused, the map keeps it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mowerhw.common.geometry import rotmat_to_quat, wrap_angle, yaw_rotation
from mowerhw.common.magnetic import CompassReference, field_in_body
from mowerhw.estimation.compass import Compass, CompassCalibration
from mowerhw.map import Landmark, LawnMap, MapError, load
from mowerhw.sim.sensors import Magnetometer, MagnetometerModel

MODEL = MagnetometerModel(declination_rad=1.0)


def _tilted(yaw: float, roll: float) -> np.ndarray:
    c, s = math.cos(roll), math.sin(roll)
    r_roll = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return yaw_rotation(yaw) @ r_roll


def test_a_levelled_reading_gives_the_field_direction_in_the_body_frame() -> None:
    for yaw in np.linspace(-3.0, 3.0, 7):
        r_wb = _tilted(float(yaw), math.radians(12.0))
        mag = r_wb.T @ MODEL.field_w
        up = r_wb.T @ np.array([0.0, 0.0, 9.81])  # the accelerometer at rest
        reading = field_in_body(mag, up)
        assert reading is not None
        assert abs(wrap_angle(reading.alpha - (MODEL.declination_rad - yaw))) < 1e-9
        assert reading.dip_rad == pytest.approx(MODEL.dip_rad)
        # without the accelerometer the tilt bends the direction (the dip's vertical part)
        flat = field_in_body(mag)
        assert flat is not None and abs(wrap_angle(flat.alpha - reading.alpha)) > 0.05
    assert field_in_body([0.0, 0.0, 0.0]) is None
    assert field_in_body([math.nan, 0.0, 1e-5]) is None
    assert field_in_body([0.0, 0.0, -5e-5]) is None  # straight down: no direction
    assert field_in_body(MODEL.field_w, [9.81, 0.0, 0.0]) is None  # the mower on its end


def _drive(n: int = 600) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A loop around a lawn at 10 Hz: times, headings, trajectory rows (t, x, y, z, q)."""
    t = np.arange(n) * 0.1
    yaw = np.unwrap(np.linspace(0.0, 2 * math.pi, n) + 0.3 * np.sin(t))
    traj = np.zeros((n, 8))
    traj[:, 0] = t
    for k in range(n):
        traj[k, 4:8] = rotmat_to_quat(yaw_rotation(float(yaw[k])))
    return t, yaw, traj


def test_teaching_learns_where_the_field_points_in_the_map_frame() -> None:
    t, yaw, traj = _drive()
    mag = Magnetometer(MODEL, np.random.default_rng(2))
    cal = CompassCalibration()
    readings = mag.measure_all(np.array([yaw_rotation(float(a)) for a in yaw]))
    for tk, m in zip(t, readings, strict=True):
        cal.add(float(tk), m)
    ref = cal.fit(traj)
    assert ref is not None
    assert abs(wrap_angle(ref.north_rad - MODEL.declination_rad)) < math.radians(2.0)
    assert ref.sigma_rad < math.radians(6.0)
    assert ref.strength_t == pytest.approx(MODEL.strength_t, rel=0.05)
    assert ref.samples == t.size
    # too few readings: no compass rather than a guessed one
    short = CompassCalibration()
    for tk, m in zip(t[:20], readings[:20], strict=True):
        short.add(float(tk), m)
    assert short.fit(traj) is None


def test_mowing_the_compass_gives_the_heading_and_refuses_turns_and_disturbances() -> None:
    ref = CompassReference(MODEL.declination_rad, math.radians(3.0), 50e-6, MODEL.dip_rad, 500)
    mag = Magnetometer(MODEL, np.random.default_rng(3))
    compass = Compass(ref)
    assert compass.heading(0.0) is None  # nothing read yet
    yaw = -2.5
    for k in range(15):
        compass.add(0.1 * k, mag.measure(yaw_rotation(yaw)))
    got = compass.heading(1.4)
    assert got is not None
    # off by what the mower's own field (left after calibration) bends it, and the noise
    horizontal = MODEL.strength_t * math.cos(MODEL.dip_rad)
    bent = math.asin(float(np.linalg.norm(mag.residual[:2])) / horizontal)
    assert abs(wrap_angle(got[0] - yaw)) < bent + math.radians(2.0)
    assert math.radians(3.0) <= got[1] < math.radians(10.0)
    assert compass.heading(3.0) is None  # stale: no reading for 1.6 s
    turning = Compass(ref)
    for k in range(15):
        turning.add(0.1 * k, mag.measure(yaw_rotation(yaw + 0.5 * k)))
    assert turning.heading(1.4) is None
    disturbed = Compass(ref)
    for k in range(15):  # a steel plate under the mower: half again the field's strength
        disturbed.add(0.1 * k, 1.5 * mag.measure(yaw_rotation(yaw)))
    assert disturbed.heading(1.4) is None and disturbed.disturbed == 15


def _lawn_map(compass: CompassReference | None) -> LawnMap:
    ring = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    lms = [
        Landmark(i, np.array([8 * math.cos(a), 8 * math.sin(a), 1.0]), np.eye(3) * 1e-4)
        for i, a in enumerate(ring)
    ]
    return LawnMap(
        boundary=np.c_[4 * np.cos(ring), 3 * np.sin(ring)], landmarks=lms, compass=compass
    )


def test_the_map_keeps_the_taught_field_and_refuses_a_bad_one(tmp_path) -> None:
    ref = CompassReference(1.25, 0.04, 49e-6, 1.1, 321)
    path = tmp_path / "lawn.json"
    _lawn_map(ref).save(path)
    assert load(path).compass == ref
    plain = tmp_path / "plain.json"
    _lawn_map(None).save(plain)
    assert load(plain).compass is None
    assert "compass" not in json.loads(plain.read_text())  # no key: old readers unaffected
    doc = json.loads(path.read_text())
    for bad, says in (
        ({"north_rad": 1.0}, "missing"),
        ({**ref.to_dict(), "strength_t": 2.0}, "not a geomagnetic field"),
        ({**ref.to_dict(), "sigma_rad": "x"}, "finite number"),
        ({**ref.to_dict(), "samples": 0}, "positive whole number"),
        ([], "expected an object"),
    ):
        doc["compass"] = bad
        del doc["checksum"]
        from mowerhw.map import _digest  # the checksum of the altered document

        doc["checksum"] = "sha256:" + _digest(doc)
        path.write_text(json.dumps(doc))
        with pytest.raises(MapError, match=says):
            load(path)


def test_map_show_says_whether_the_map_has_a_compass(tmp_path, capsys) -> None:
    from mowerhw.cli import main

    ref = CompassReference(math.radians(57.6), math.radians(4.4), 50.1e-6, math.radians(65), 592)
    with_compass, without = tmp_path / "a.json", tmp_path / "b.json"
    _lawn_map(ref).save(with_compass)
    _lawn_map(None).save(without)
    assert main(["map", "show", str(with_compass)]) == 0
    assert "the field points 57.6° ± 4.4° in the map (50.1 µT, dip 65.0°, 592 readings)" in (
        capsys.readouterr().out
    )
    assert main(["map", "show", str(without)]) == 0
    assert "compass      none" in capsys.readouterr().out
