"""The scenario matrix: lawns, ground, landmark layouts and sensor grades of the simulator."""

import math

import numpy as np
import pytest
import shapely

from mowerhw.imu.grades import IMU_GRADES
from mowerhw.sim import MATRIX, SCENARIOS, simulate_teach
from mowerhw.sim.lawn import SHAPES, shaped_lawn
from mowerhw.sim.sensors import Gyro
from mowerhw.sim.terrain import Terrain


@pytest.mark.parametrize("name", MATRIX)
def test_every_preset_simulates_a_closed_consistent_drive(name):
    run = simulate_teach(name, seed=3)
    tr, st = run.truth, run.streams
    assert np.linalg.norm(tr.position[-1] - tr.position[0]) < 0.02  # back at the start
    assert np.allclose(tr.position[0], 0.0) and np.allclose(tr.rot[0], np.eye(3))
    # the gyro integrates to the true attitude (its own bias and scale taken out)
    gyro = st.gyro  # noisy: only its statistics are checked here
    assert gyro.shape == (tr.t.size, 3) and np.all(np.isfinite(gyro))
    sc = SCENARIOS[name]
    views = np.array([len(f.ids) for f in st.frames])
    seen = views[views > 0]
    assert seen.min() >= 3, f"{name}: a frame sees only {seen.min()} landmarks"
    empty = float(np.mean(views == 0))  # frames that recognise nothing (blur, glare)
    assert empty == pytest.approx(sc.sensors.camera.frame_drop, abs=0.06)
    if sc.slope_deg or sc.bumps_per_m2:
        assert np.ptp(tr.position[:, 2]) > 0.05  # not a plane in the world frame
        assert np.abs(tr.body_rate[:, :2]).max() > 0.002  # it pitches and rolls
    else:
        assert np.ptp(tr.position[:, 2]) < 1e-9


def test_body_rates_integrate_to_the_attitude_on_bumpy_ground():
    from scipy.spatial.transform import Rotation

    run = simulate_teach("strip-bumps", seed=2)
    tr = run.truth
    r = np.eye(3)
    for k in range(1, tr.t.size):
        r = r @ Rotation.from_rotvec(tr.body_rate[k] * (tr.t[k] - tr.t[k - 1])).as_matrix()
    err = Rotation.from_matrix(r.T @ tr.rot[-1]).magnitude()
    assert err < 1e-6


@pytest.mark.parametrize("shape", list(SHAPES))
def test_shapes_are_closed_smooth_and_concave_where_they_should_be(shape):
    lawn = shaped_lawn(shape)
    s = np.linspace(0, lawn.perimeter, 4000, endpoint=False)
    p = lawn.point(s)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.allclose(step, lawn.perimeter / 4000, rtol=1e-3)  # arc length
    h = lawn.heading(np.array([0.0, lawn.perimeter - 1e-9]))
    assert h[1] - h[0] == pytest.approx(2 * math.pi, abs=1e-6)  # one turn, counter-clockwise
    poly = shapely.Polygon(p)
    assert poly.is_valid
    concave = poly.convex_hull.area - poly.area > 1.0
    assert concave == (shape in ("L", "U", "garden")) and (lawn.curvature(s) < 0).any() == concave


def test_terrain_slope_grows_smoothly_and_the_mower_tilts_with_it():
    t = Terrain(slope_deg=8.0, slope_dir_deg=0.0, slope_width_m=2.0)
    x = np.array([-20.0, 0.0, 20.0])
    gx, _ = t.gradient(x, np.zeros(3))
    assert gx[0] == pytest.approx(0.0, abs=1e-4) and gx[2] == pytest.approx(
        math.tan(math.radians(8)), rel=1e-3
    )
    r = t.attitude(x, np.zeros(3), np.zeros(3))
    pitch = np.degrees(np.arcsin(r[:, 2, 0]))  # body x's rise
    assert pitch[0] == pytest.approx(0.0, abs=0.01) and pitch[2] == pytest.approx(8.0, abs=0.01)


@pytest.mark.parametrize("grade", ["bmi088", "mpu6050"])
def test_gyro_grades_carry_their_datasheet_errors(grade):
    g = IMU_GRADES[grade]
    offsets, scales = [], []
    for seed in range(40):
        gyro = Gyro(g, np.random.default_rng(seed), 100.0)
        offsets.append(gyro.turn_on)
        scales.append(gyro.scale - 1.0)
    assert np.std(offsets) == pytest.approx(g.turn_on_bias, rel=0.25)
    assert np.std(scales) == pytest.approx(g.scale_factor, rel=0.25)
    # white noise at 100 Hz: density × √100 per sample
    gyro = Gyro(g, np.random.default_rng(1), 100.0)
    out, bias = gyro.measure_all(np.zeros((20000, 3)))
    assert np.std(out - bias) == pytest.approx(g.noise_density * 10, rel=0.03)
