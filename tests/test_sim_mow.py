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


def test_a_lifted_tilted_and_bumped_mower_halts_in_the_simulator(lawn_map):
    """The simulator's handling events reach the same safety functions as on the mower: each
    halts with its own reason, nothing is permitted while one holds, the deck runs again
    after the clear time."""
    from mowerhw.sim.handling import HandlingEvent

    events = [HandlingEvent.parse(x) for x in ("lift@20:2", "tilt@40:3", "bump@60")]
    o = run_mow(lawn_map, "paper", 9, duration_s=75.0, handling=events)
    got = {h["kind"]: h for h in o.metrics["handling"]}
    assert got["lift"]["reason"] == "LIFTED" and got["lift"]["halted_after_ms"] <= 100.0
    assert got["bump"]["reason"] == "COLLISION" and got["bump"]["halted_after_ms"] <= 100.0
    # tilt: the 1 s debounce plus the 0.3 s gravity filter, then at once
    assert got["tilt"]["reason"] == "TILTED" and 1000.0 <= got["tilt"]["halted_after_ms"] <= 1600.0
    for h in got.values():
        assert h["deck_running"] and h["permits_while_held"] == 0
        assert h["deck_again_after_end_s"] is not None and h["deck_again_after_end_s"] >= 2.0
    assert o.metrics["missed_halts"] == 0
    assert o.metrics["halts_by_reason"].keys() >= {"LIFTED", "TILTED", "COLLISION"}


def test_handling_events_are_parsed_or_refused_by_name():
    import pytest

    from mowerhw.sim.handling import HandlingEvent

    assert HandlingEvent.parse("tilt@5") == HandlingEvent("tilt", 5.0, 3.0)
    for bad in ("fly@3", "lift@x", "lift@-1", "lift@3:0"):
        with pytest.raises(ValueError, match=r"KIND@T|T must be"):
            HandlingEvent.parse(bad)


def test_the_plants_speed_reading_is_true_at_its_stamp():
    """The plant's ground speed is that of the IMU interval just moved; stamped at the
    interval's middle, the estimators' speed model (samples true at their stamps, linear in
    between) integrates a drive-off to the distance the mower really rolled. Stamped at the
    interval's end it fell half a step behind at every start (2.25 mm at 0.45 m/s, 100 Hz)."""
    from dataclasses import replace

    from mowerhw.estimation.odometry import SpeedTrack
    from mowerhw.sim import make_world
    from mowerhw.sim.plant import MowerPlant

    plant = MowerPlant(make_world("paper", 1), 5)
    plant.speedometer.model = replace(plant.speedometer.model, white=0.0, quantum=1e-9)
    plant.speedometer.scale = 1.0
    track = SpeedTrack()
    track.add(*plant.first_output().speed)
    start = plant.xy.copy()
    times = [float(plant.t)]
    for k in range(round(1.5 / plant.dt)):
        out = plant.step(0.0 if k < 22 else 0.45, 0.0)  # starts between two speed readings
        times.append(float(plant.t))
        if out.speed is not None:
            track.add(*out.speed)
    t = np.array(times)
    mids = 0.5 * (t[1:] + t[:-1])
    driven = float(np.sum(track.interpolate(mids) * np.diff(t)))
    rolled = float(np.linalg.norm(plant.xy - start))
    assert rolled > 0.4
    assert abs(driven - rolled) < 5e-4, (driven, rolled)


def test_the_mowers_gyro_is_its_teach_runs_unit_changed_by_its_drift():
    """The simulated mower mows with the gyro it taught with: the teach run's scale per
    axis (:func:`mower_gyro_scale`), changed by the grade's ``scale_drift`` — a new unit
    each run would make a taught scale worthless (and the filter's trust in it wrong)."""
    from dataclasses import replace

    from mowerhw.imu.grades import IMU_GRADES
    from mowerhw.sim import make_world
    from mowerhw.sim.plant import MowerPlant
    from mowerhw.sim.scenarios import SCENARIOS
    from mowerhw.sim.sensors import Gyro, mower_gyro_scale

    world = make_world("paper", 1)
    grade = IMU_GRADES["mpu6050"]
    sensors = replace(SCENARIOS["paper"].sensors, imu=grade)
    taught = mower_gyro_scale(sensors, 4)
    teach_unit = Gyro(grade, np.random.default_rng([4, 2]), sensors.rates.imu_hz)
    assert np.array_equal(taught, teach_unit.scale) and np.any(np.abs(taught - 1.0) > 0.005)
    changes = []
    for seed in range(40):
        plant = MowerPlant(world, seed, sensors=sensors, gyro_scale=taught)
        changes.append(plant.gyro.scale / taught - 1.0)
    assert np.std(changes) == pytest.approx(grade.scale_drift, rel=0.25)
    still = replace(sensors, imu=replace(grade, scale_drift=0.0))
    assert np.array_equal(MowerPlant(world, 1, sensors=still, gyro_scale=taught).gyro.scale, taught)
