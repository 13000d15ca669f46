"""Omnidirectional camera model (docs/design.md §6): round trips, cv2.omnidir, Kalibr I/O."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from _tools import load_tool
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
from mowerhw.camera.check import angle_between, check_against_opencv, sample_valid_pixels

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
    # a hand edit that pastes a second distortion under the first: refused, not the later kept
    good = (Path(__file__).parent.parent / "configs/camera/paper-table1.yaml").read_text()
    twice = good.replace(
        "  distortion_coeffs:", "  distortion_coeffs: [0, 0, 0, 0]\n  distortion_coeffs:", 1
    )
    assert twice != good
    (tmp_path / "twice.yaml").write_text(twice)
    with pytest.raises(CameraCalibrationError, match="the key 'distortion_coeffs' is given twice"):
        load_camchain(tmp_path / "twice.yaml")
    (tmp_path / "other.yaml").write_text("cam1: {}\n")
    with pytest.raises(CameraCalibrationError, match="no 'cam0' entry"):
        load_camchain(tmp_path / "other.yaml")


# ---------------------------------------------------------------- any Mei lens (ξ up to 3+)


def fisheye(xi: float, **kw) -> OmniRadtanCamera:
    """A wide lens fitted with the Mei model (ξ > 1), as Kalibr fits fisheyes: 640x480."""
    base = dict(fu=xi * 230.0, fv=xi * 230.0, cu=322.0, cv=238.0, k1=0.2, k2=-0.6, p1=0.003)
    base.update(kw)
    return OmniRadtanCamera(xi=xi, p2=0.0004, width=640, height=480, **base)


@pytest.mark.parametrize("xi", [0.5, 1.0, 1.5, 2.0, 2.5, 3.0])
def test_valid_pixels_always_lift_and_others_are_refused(xi):
    """valid ⇔ lift finite and project(lift) back: over every pixel of the image."""
    cam = fisheye(xi)
    v, u = np.mgrid[0:480:2, 0:640:2]
    pix = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    ok = cam.valid(pix)
    bearings = cam.lift(pix)
    finite = np.all(np.isfinite(bearings), axis=1)
    assert np.array_equal(ok, finite)  # no valid pixel without a bearing, no bearing refused
    assert ok.mean() > 0.15
    back = cam.project(bearings[ok])
    assert np.abs(back - pix[ok]).max() < 1e-6
    polar = np.arccos(np.clip(bearings[ok, 2], -1, 1))
    assert polar.max() <= cam.fold_angle + 1e-9


@pytest.mark.parametrize("xi", [1.5, 2.0, 3.0])
def test_rays_beyond_the_fold_are_not_imaged(xi):
    cam = fisheye(xi, k1=0.0, k2=0.0, p1=0.0)
    fold = np.arccos(-1.0 / xi)  # ρ(θ) turns back here: two directions, one pixel
    for theta, imaged in [(fold - 0.05, True), (fold + 0.01, False), (fold + 0.3, False)]:
        ray = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
        pix, ok = cam.visible(ray)
        assert bool(np.all(np.isfinite(pix))) == imaged and ok[0] == (imaged and cam.valid(pix)[0])
    # beyond the fold the model would give a pixel another direction owns
    a, b = fold - 0.3, fold + 0.3
    rho = lambda t: np.sin(t) / (np.cos(t) + xi)  # noqa: E731
    assert rho(a) == pytest.approx(rho(b), rel=0.05)  # (what the fold check prevents)


def test_distortion_fold_is_refused_both_ways():
    """A strong barrel term turns r(1 + k1 r²) back: no pixel beyond it, no ray past it."""
    cam = OmniRadtanCamera(0.8, 300, 300, 320, 240, -0.6, 0.0, 0, 0, 640, 480)
    r_star = np.sqrt(1.0 / (3 * 0.6))  # d/dr of r(1 - 0.6 r²) is 0 here
    m = np.array([[r_star * 1.2, 0.0]])  # beyond: distorted back inside, folded branch
    assert not cam.one_to_one(m)[0]
    md = cam.distort(m)
    assert np.all(np.isnan(cam.undistort(md)) | (np.abs(cam.undistort(md)) < r_star))
    far = np.array([[0.9, 0.0, 0.1]])  # its m is beyond r*: refused
    assert np.all(np.isnan(cam.project(far)))


def test_camera_info_is_never_nan_and_json_is_strict(tmp_path, capsys):
    import json

    from mowerhw.cli import main

    path = tmp_path / "fisheye.yaml"
    save_camchain({"cam0": fisheye(2.9), "cam1": fisheye(1.2)}, path)
    assert main(["camera", "info", "--calibration", str(path), "--camera", "all"]) == 0
    text = capsys.readouterr().out
    import re

    assert not re.search(r"\bnan\b", text.lower()) and text.count("calibration  ") == 2
    assert main(["camera", "info", "--calibration", str(path), "--camera", "cam0", "--json"]) == 0

    def refuse(token):
        raise AssertionError(f"non-strict JSON constant {token}")

    report = json.loads(capsys.readouterr().out, parse_constant=refuse)
    fov = report["field_of_view"]
    assert fov["polar_angle_max_deg"] <= fov["model_limit_deg"] < 180.0
    assert main(["camera", "info", "--calibration", str(path), "--camera", "cam7"]) == 78
    assert "no 'cam7' entry (found: cam0, cam1" in capsys.readouterr().err


# ------------------------------------------------------------------- Kalibr camchain keys


def test_skew_is_read_written_and_kept_only_when_it_matters(tmp_path):
    cam = fisheye(1.1, fu=300.0, fv=301.0)
    skewed = OmniRadtanCamera(**{**cam.__dict__, "skew": -0.002})
    for c, kept in ((skewed, True), (OmniRadtanCamera(**{**cam.__dict__, "skew": 1e-9}), False)):
        path = tmp_path / "c.yaml"
        save_camchain(c, path)
        assert ("skew" in yaml.safe_load(path.read_text())["cam0"]) == kept
        back = load_camchain(path)
        assert back.skew == (c.skew if kept else 0.0)
    # skew as OpenCV has it: K[0, 1] = skew · fu
    assert skewed.K[0, 1] == pytest.approx(-0.002 * 300.0)
    pts = np.array([[0.2, -0.3, 1.0], [-0.5, 0.4, 0.6]])
    import cv2

    cv_pix, _ = cv2.omnidir.projectPoints(
        pts.reshape(1, -1, 3), np.zeros(3), np.zeros(3), skewed.K, skewed.xi, skewed.D
    )
    assert np.abs(cv_pix.reshape(-1, 2) - skewed.project(pts)).max() < 1e-9


def test_kalibr_extra_keys_time_shift_and_camera_choice(tmp_path):
    doc = {
        "cam0": {**fisheye(2.0).to_kalibr(), "rostopic": "/fisheye1", "cam_overlaps": [1]},
        "cam1": {
            **fisheye(2.07, cu=300.0).to_kalibr(),
            "T_cn_cnm1": np.eye(4).tolist(),
            "timeshift_cam_imu": 0.0045,
            "rostopic": "/fisheye2",
        },
    }
    path = tmp_path / "chain.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert load_camchain(path, "cam1").cu == 300.0
    assert load_camchain(path, "cam1").timeshift_cam_imu == 0.0045
    doc["cam1"]["T_cn_cnm1"] = [[1, 0], [0, 1]]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(CameraCalibrationError, match=r"cam1\.T_cn_cnm1"):
        load_camchain(path, "cam1")


def test_time_shift_moves_frame_times_onto_the_imu_clock():
    from mowerhw.vision import TeachVision

    class _Teacher:  # the vision layer only needs somewhere to put bearings
        pass

    cam = OmniRadtanCamera(**{**fisheye(1.5).__dict__, "timeshift_cam_imu": 0.004})
    vision = TeachVision(_Teacher(), cam)
    tracks = vision.track(10.0, np.zeros((480, 640), np.uint8), None)
    assert tracks.t == pytest.approx(10.004)


def test_config_takes_the_camera_rotation_from_t_cam_imu(tmp_path):
    from mowerhw.config import ConfigError, config_from_dict

    t = np.eye(4)
    t[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # camera yawed 90° from the IMU
    cam = OmniRadtanCamera(**{**fisheye(1.6).__dict__, "T_cam_imu": t})
    path = tmp_path / "chain.yaml"
    save_camchain({"cam0": fisheye(1.0), "cam1": cam}, path)
    base = {
        "camera": {"calibration": str(path), "camchain_key": "cam1", "width": 640, "height": 480},
        "imu": {"q_bi": [1, 0, 0, 0]},
    }
    cfg = config_from_dict(base)
    from mowerhw.common.geometry import quat_to_rotmat

    assert np.allclose(quat_to_rotmat(cfg.camera.q_bc), t[:3, :3].T, atol=1e-12)  # R_bc = R_ci^T
    agrees = {**base, "camera": {**base["camera"], "q_bc": list(cfg.camera.q_bc)}}
    assert config_from_dict(agrees).camera.q_bc == pytest.approx(cfg.camera.q_bc)
    conflict = {**base, "camera": {**base["camera"], "q_bc": [0, 1, 0, 0]}}
    with pytest.raises(ConfigError, match=r"camera.q_bc: .* differs by 180.0° .*camera.extrinsics"):
        config_from_dict(conflict)
    override = {**base, "camera": {**conflict["camera"], "extrinsics": "config"}}
    assert config_from_dict(override).camera.q_bc == (0, 1, 0, 0)
    no_t = {"camera": {**base["camera"], "camchain_key": "cam0"}}
    assert config_from_dict(no_t).camera.q_bc == (0.0, 1.0, 0.0, 0.0)  # the mirror-up default
    missing = {"camera": {**base["camera"], "camchain_key": "cam2"}}
    with pytest.raises(ConfigError, match="no 'cam2' entry"):
        config_from_dict(missing)


# ------------------------------------------------------------------ real third-party data


real_cameras = load_tool("check_real_cameras")


@pytest.mark.skipif(
    not real_cameras.T265.exists(), reason=f"no T265 camchain at {real_cameras.T265}"
)
def test_real_t265_camchain_both_cameras_and_the_factory_model():
    """A real Kalibr camchain (ξ 2.00 / 2.07, two cameras, T_cam_imu, extra keys) loads; its
    Mei calibration and the factory Kannala–Brandt one of the same lens agree to a few px."""
    res = real_cameras.mei_vs_factory(max_deg=55.0)
    print(res)
    assert [r["camera"] for r in res] == ["cam0", "cam1"]
    for r in res:
        assert r["xi"] > 2.0 and r["max_px_diff_to_55deg"] < 5.0
        assert r["polar_deg_range"][1] < 120.0  # stops before the fold (acos(-1/ξ) ≈ 120°)


@pytest.mark.slow
@pytest.mark.skipif(
    not real_cameras.MIRROR.exists(), reason=f"no mirror photos at {real_cameras.MIRROR}"
)
@pytest.mark.slow
def test_calibrate_the_real_mirror_camera(tmp_path):
    """`mowerhw camera calibrate` on 18 real catadioptric photos (9x6 corners)."""
    report = real_cameras.calibrate_mirror(tmp_path)
    print({k: v for k, v in report.items() if k != "views"})
    assert report["rms_px"] <= 0.45 and report["views_used"] == 17
    assert [v["image"] for v in report["views"] if not v["used"]] == ["18.jpg"]
    ann = report["region"]["annulus"]
    assert 515 < ann["outer_radius_px"] < 535 and 60 < ann["inner_radius_px"] < 80
    assert abs(ann["center_px"][0] - 630) < 6 and abs(ann["center_px"][1] - 434) < 6
    check = report["model_check"]
    assert check["project_vs_opencv_px_max"] < 1e-6
    assert check["opencv_converged_fraction"] == 1.0
    assert check["lift_vs_opencv_px_max_where_opencv_converged"] < 1e-6
    cam = report["camera"]
    assert cam["xi"] == pytest.approx(0.958, abs=0.01) and cam["skew_px"] == pytest.approx(
        -0.76, abs=0.1
    )


def test_calibrating_from_files_that_are_not_images_names_them(tmp_path):
    from mowerhw.camera.calibrate import CalibrationError, calibrate

    photos = [tmp_path / f"{k}.jpg" for k in range(5)]
    for p in photos:
        p.write_bytes(b"not a JPEG")
    with pytest.raises(
        CalibrationError, match=r"none of the 5 images could be read \(0\.jpg, 1\.jpg, 2\.jpg, …\)"
    ):
        calibrate(photos, (9, 6), 0.03)
