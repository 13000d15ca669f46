"""Omnidirectional camera model (DESIGN.md §6): round trips, cv2.omnidir agreement, Kalibr I/O."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from mowerhw.camera import (
    Annulus,
    CameraCalibrationError,
    OmniRadtanCamera,
    load_camchain,
    paper_table1_camera,
    save_camchain,
)
from mowerhw.camera_check import angle_between, check_against_opencv, sample_valid_pixels

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
TABLE1 = CONFIGS / "camera" / "paper-table1.yaml"


@pytest.fixture(scope="module")
def cam() -> OmniRadtanCamera:
    return load_camchain(TABLE1)


@pytest.fixture(scope="module")
def opencv_report(cam):
    return check_against_opencv(cam, n=20000, seed=0)


def test_shipped_table1_matches_the_paper(cam):
    ref = paper_table1_camera()
    assert cam == ref  # every intrinsic, the distortion, resolution and mask
    assert (cam.width, cam.height) == (1540, 1540)
    assert cam.xi == 0.92036 and cam.fu == 476.60667 and cam.fv == 476.74991
    assert (cam.k1, cam.k2, cam.p1, cam.p2) == (-0.17357, 0.02025, -0.00209, 0.00091)


def test_project_lift_round_trip_over_the_valid_field_of_view(cam):
    pix = sample_valid_pixels(cam, 50000, seed=7)
    bearings = cam.lift(pix)
    assert np.allclose(np.linalg.norm(bearings, axis=-1), 1.0, atol=1e-12)
    assert np.abs(cam.project(bearings) - pix).max() < 1e-6


def test_lift_project_round_trip_on_random_directions(cam):
    rng = np.random.default_rng(11)
    dirs = rng.normal(size=(100000, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    pix, visible = cam.visible(dirs * rng.uniform(0.5, 50.0, size=(100000, 1)))
    assert visible.sum() > 30000  # the annulus covers a good part of the sphere
    assert angle_between(cam.lift(pix[visible]), dirs[visible]).max() < 1e-9


def test_agrees_with_cv2_omnidir_project_points(opencv_report):
    assert opencv_report["project_vs_opencv_px_max"] < 1e-6
    assert opencv_report["roundtrip_px_max"] < 1e-6


def test_agrees_with_cv2_omnidir_undistort_points_where_it_converges(opencv_report):
    # Same pixel and the same bearing wherever OpenCV's own (fixed 20-step) undistortion has
    # converged; the share of the annulus where it has is reported and must not be tiny.
    assert opencv_report["lift_vs_opencv_px_max_where_opencv_converged"] < 1e-6
    assert opencv_report["lift_vs_opencv_rad_max_where_opencv_converged"] < 1e-8
    assert opencv_report["opencv_converged_fraction"] > 0.4


def test_undistort_points_agreement_with_tangential_and_skew():
    cam = OmniRadtanCamera(
        xi=0.8,
        fu=300.0,
        fv=305.0,
        cu=320.5,
        cv=240.25,
        k1=-0.05,
        k2=0.004,
        p1=0.001,
        p2=-0.002,
        width=640,
        height=480,
        skew=0.001,
    )
    rep = check_against_opencv(cam, n=5000, seed=3)
    assert rep["project_vs_opencv_px_max"] < 1e-6
    assert rep["roundtrip_px_max"] < 1e-6
    assert rep["lift_vs_opencv_px_max_where_opencv_converged"] < 1e-6
    assert rep["opencv_converged_fraction"] > 0.9  # mild distortion: OpenCV converges


@given(st.floats(180.0, 760.0), st.floats(0.0, 2 * np.pi))
def test_lift_is_unit_and_invertible_anywhere_in_the_annulus(radius, angle):
    cam = paper_table1_camera()
    pix = np.array([[cam.cu + radius * np.cos(angle), cam.cv + radius * np.sin(angle)]])
    if not cam.valid(pix)[0]:
        return  # clipped by the image border
    b = cam.lift(pix)
    assert np.isclose(np.linalg.norm(b), 1.0)
    assert np.abs(cam.project(b) - pix).max() < 1e-6


def test_mask_is_the_annulus_within_the_image(cam):
    c = np.array([cam.cu, cam.cv])
    assert not cam.valid(c[None])[0]  # the camera's own reflection
    assert not cam.valid((c + [100.0, 0.0])[None])[0]
    assert cam.valid((c + [300.0, 0.0])[None])[0]
    assert not cam.valid(np.array([[-1.0, 700.0]]))[0]  # off the image
    assert not cam.valid((c + [540.0, 540.0])[None])[0]  # beyond the mirror rim
    mask = cam.mask_image()
    assert mask.shape == (1540, 1540) and mask.dtype == np.uint8
    assert set(np.unique(mask)) == {0, 255}


def test_directions_behind_the_mirror_are_not_imaged(cam):
    pix = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.01, -1.0]]))
    assert np.all(np.isnan(pix))
    _, visible = cam.visible(np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.2]]))
    assert visible.tolist() == [False, True]


def test_bearing_sigma_is_about_one_over_focal_length_near_the_horizon(cam):
    sigma = cam.bearing_sigma(np.array([[cam.cu + 426.0, cam.cv]]), 3.0)[0]
    assert 0.003 < sigma < 0.02


def test_kalibr_round_trip_with_t_cam_imu(tmp_path):
    t = np.eye(4)
    t[:3, :3] = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]])
    t[:3, 3] = [0.01, 0.02, -0.05]
    cam = OmniRadtanCamera(
        xi=0.9,
        fu=400,
        fv=401,
        cu=320,
        cv=240,
        k1=-0.1,
        k2=0.01,
        p1=0,
        p2=0,
        width=640,
        height=480,
        T_cam_imu=t,
        mask=Annulus((320, 240), 30, 230),
    )
    path = tmp_path / "camchain.yaml"
    save_camchain(cam, path)
    back = load_camchain(path)
    assert back == cam
    assert np.allclose(back.T_cam_imu, t)


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (
            lambda e: e.update(camera_model="pinhole"),
            "cam0.camera_model: 'pinhole' is not supported",
        ),
        (lambda e: e.update(distortion_model="equidistant"), "cam0.distortion_model"),
        (lambda e: e.update(intrinsics=[1, 2, 3]), "cam0.intrinsics"),
        (lambda e: e.update(intrinsics=[0.9, "f", 1, 1, 1]), "cam0.intrinsics"),
        (lambda e: e.update(distortion_coeffs=[0.1, 0.2, 0.3]), "cam0.distortion_coeffs"),
        (lambda e: e.update(resolution=[1540.5, 1540]), "cam0.resolution"),
        (
            lambda e: e.update(T_cam_imu=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
            "cam0.T_cam_imu",
        ),
        (lambda e: e.update(T_cam_imu=[[1, 0], [0, 1]]), "cam0.T_cam_imu"),
        (lambda e: e.update(mask={"inner_radius": 500, "outer_radius": 100}), "cam0.mask"),
        (lambda e: e.update(intrinsics=[0.9, -400, 400, 1, 1]), "focal lengths must be positive"),
        (lambda e: e.update(intrinsics=[0.9, float("nan"), 400, 1, 1]), "finite"),
    ],
)
def test_bad_camchain_files_name_what_is_wrong(tmp_path, mutate, expected):
    doc = yaml.safe_load(TABLE1.read_text())
    mutate(doc["cam0"])
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(CameraCalibrationError, match=expected.replace("(", r"\(")):
        load_camchain(path)


def test_missing_or_unparsable_camchain(tmp_path):
    with pytest.raises(CameraCalibrationError, match="file not found"):
        load_camchain(tmp_path / "nope.yaml")
    (tmp_path / "junk.yaml").write_text("cam0: [unclosed\n")
    with pytest.raises(CameraCalibrationError, match="not valid YAML"):
        load_camchain(tmp_path / "junk.yaml")
    (tmp_path / "other.yaml").write_text("cam1: {}\n")
    with pytest.raises(CameraCalibrationError, match="no 'cam0' entry"):
        load_camchain(tmp_path / "other.yaml")
