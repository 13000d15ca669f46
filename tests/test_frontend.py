"""The vision front end: tracking through turns, outlier rejection, descriptors, association."""

import cv2
import numpy as np
import pytest

from mowerhw.common.geometry import rotmat_exp, tangent_basis
from mowerhw.frontend import FrontEnd, RotationHistory
from mowerhw.frontend.association import (
    Candidates,
    associate,
    isotropic_candidates,
    mahalanobis,
)
from mowerhw.frontend.descriptors import OrbDescriber, hamming, min_hamming, stack_sets
from mowerhw.frontend.epipolar import epipolar_inliers
from mowerhw.sim import make_world
from mowerhw.sim.render import OmniRenderer


@pytest.fixture(scope="module")
def scene():
    world = make_world("paper", 1)
    r = OmniRenderer(world, seed=1)
    c = world.lawn.outline(360).mean(axis=0)
    return world, r, c


def test_rotation_history_integrates_the_gyro():
    h = RotationHistory()
    for k in range(101):
        h.add(k * 0.01, [0.0, 0.0, 0.5])  # 0.5 rad/s about z for 1 s
    r = h.rotation_between(0.2, 0.7)
    assert np.allclose(r, rotmat_exp(np.array([0.0, 0.0, 0.25])), atol=1e-9)
    assert h.rotation_between(0.2, 5.0) is None  # not covered


@pytest.mark.parametrize("turn_deg", [3.0, 25.0, -45.0])
def test_tracks_survive_a_turn(scene, turn_deg):
    """A turn rotates the whole omni image; with the gyro's rotation the tracker undoes it
    first, and the features are still there afterwards, at their true places."""
    world, r, c = scene
    fe = FrontEnd(world.camera, world.q_bc)
    yaw = np.radians(turn_deg)
    a = fe.process(0.0, r.render(c[0], c[1], 0.3))
    b = fe.process(0.25, r.render(c[0], c[1], 0.3 + yaw), rotmat_exp(np.array([0, 0, yaw])))
    kept = np.isin(a.ids, b.ids)
    assert a.ids.size >= 15 and kept.mean() >= 0.8
    # a feature that did not move in the world keeps its bearing in the world: rotated by yaw
    rz = rotmat_exp(np.array([0, 0, -yaw]))
    before = a.bearings[kept]
    after = b.bearings[np.searchsorted(b.ids, a.ids[kept])]
    err = np.degrees(np.arccos(np.clip(np.sum(after * (before @ rz.T), axis=1), -1, 1)))
    assert np.median(err) < 0.15


def test_tracking_on_a_half_size_image_finds_the_same_corners(scene):
    """Lucas–Kanade on pyramid level 1 (``klt_base_level``, a quarter of the pixels) and
    the sub-pixel refinement at full size end on the corners full-size tracking finds: the
    same tracks, at the same pixels to a hundredth of a pixel."""
    import dataclasses

    from mowerhw.config import FrontendConfig

    world, r, c = scene
    frames = [r.render(c[0] + 0.04 * k, c[1], 0.3 + 0.02 * k) for k in range(4)]
    out = {}
    for level in (0, 1):
        cfg = dataclasses.replace(FrontendConfig(), klt_base_level=level)
        fe = FrontEnd(world.camera, world.q_bc, cfg)
        first = fe.process(0.0, frames[0])
        for k in range(1, 4):
            last = fe.process(0.25 * k, frames[k], rotmat_exp(np.array([0, 0, 0.02])))
        out[level] = (first, last)
    (a0, b0), (a1, b1) = out[0], out[1]
    assert np.array_equal(a0.ids, a1.ids) and a0.ids.size >= 15
    both = np.intersect1d(b0.ids, b1.ids)
    assert both.size >= 0.9 * max(b0.ids.size, b1.ids.size)
    p0 = b0.pixels[np.searchsorted(b0.ids, both)]
    p1 = b1.pixels[np.searchsorted(b1.ids, both)]
    gap = np.linalg.norm(p0 - p1, axis=1)
    assert np.median(gap) < 0.01 and np.percentile(gap, 90) < 0.05


def test_without_the_gyro_a_fast_turn_loses_tracks(scene):
    """The check above can fail: the same 45° turn without the gyro loses most tracks."""
    world, r, c = scene
    fe = FrontEnd(world.camera, world.q_bc)
    a = fe.process(0.0, r.render(c[0], c[1], 0.3))
    b = fe.process(0.25, r.render(c[0], c[1], 0.3 + np.radians(45)), None)
    assert np.isin(a.ids, b.ids).mean() < 0.5


def test_a_carried_camera_starts_its_tracks_afresh(scene):
    """After a carry (``restart``) no track goes on: every track of the frame is new, found
    where the corners are now — a track carried along slides onto the corner beside its own
    (issue 18, measured on kidnaps) and would keep its old descriptor."""
    world, r, c = scene
    fe = FrontEnd(world.camera, world.q_bc)
    a = fe.process(0.0, r.render(c[0], c[1], 0.3))
    b = fe.process(0.25, r.render(c[0], c[1], 0.3))
    assert a.ids.size >= 15 and np.isin(a.ids, b.ids).mean() > 0.9  # standing: tracks go on
    moved = r.render(c[0] + 0.3, c[1], 0.35)  # carried 0.3 m: half the tracks would go on
    d = fe.process(0.5, moved, restart=True)
    assert d.ids.size >= 15 and not np.isin(d.ids, b.ids).any()
    assert (d.ages == 0).all() and d.ids.min() > b.ids.max()
    e = FrontEnd(world.camera, world.q_bc).process(0.0, moved)  # a front end seeing it first
    assert np.allclose(np.sort(d.pixels[:, 0]), np.sort(e.pixels[:, 0]))


def test_epipolar_ransac_finds_the_outliers():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-8, 8, (80, 3)) + np.array([0, 0, 1.0])
    r21 = rotmat_exp(np.array([0.0, 0.0, 0.2]))
    t21 = np.array([-0.12, 0.01, 0.0])  # moved 12 cm forward
    y1 = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    p2 = pts @ r21.T + t21
    y2 = p2 / np.linalg.norm(p2, axis=1, keepdims=True)
    bad = np.arange(0, 80, 8)
    # a wrong track: 1.7° off, across its epipolar plane (along it no two views can tell)
    normal = np.cross(t21, y1[bad] @ r21.T)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    y2[bad] = y2[bad] + 0.03 * normal
    y2[bad] /= np.linalg.norm(y2[bad], axis=1, keepdims=True)
    inl, t = epipolar_inliers(y1, y2, r21, np.radians(0.35), 64, rng)
    assert not inl[bad].any() and inl[np.setdiff1d(np.arange(80), bad)].mean() > 0.95
    assert abs(abs(t @ t21 / np.linalg.norm(t21)) - 1) < 1e-3
    # standing still and turning: every track must follow the rotation alone
    inl0, t0 = epipolar_inliers(y1, y1 @ r21.T, r21, np.radians(0.35))
    assert inl0.all() and t0 is None


def test_descriptors_do_not_change_with_heading(scene):
    """ORB in the radial frame: the same corner after a 69° turn is a few bits away; other
    landmarks are far."""
    world, r, c = scene
    d = OrbDescriber((world.camera.cu, world.camera.cv))
    p0, ok0 = r.landmark_pixels(c[0], c[1], 0.3)
    p1, ok1 = r.landmark_pixels(c[0], c[1], 1.5)
    ok = ok0 & ok1
    d0, g0 = d.describe(r.render(c[0], c[1], 0.3), p0[ok])
    d1, g1 = d.describe(r.render(c[0], c[1], 1.5), p1[ok])
    assert g0.all() and g1.all()
    h = hamming(d0, d1)
    assert np.all(np.diag(h) <= 30)
    assert np.median(h[~np.eye(len(h), dtype=bool)]) > 60


def _orb_on_the_whole_image(image, pixels, center):
    """OpenCV's ORB on the whole image at ``pixels`` with the radial angle (the reference
    :class:`OrbDescriber` must equal bit for bit)."""
    orb = cv2.ORB_create(edgeThreshold=31, patchSize=31)
    kps = [
        cv2.KeyPoint(
            float(u),
            float(v),
            31.0,
            np.degrees(np.arctan2(v - center[1], u - center[0])) % 360.0,
            1.0,
            0,
            k,
        )
        for k, (u, v) in enumerate(pixels.tolist())
    ]
    kept, desc = orb.compute(image, kps)
    out = np.zeros((len(pixels), 32), np.uint8)
    ok = np.zeros(len(pixels), bool)
    idx = np.array([kp.class_id for kp in kept], dtype=np.int64)
    out[idx], ok[idx] = desc, True
    return out, ok


def test_descriptors_from_tiles_are_the_whole_images(scene):
    """The describer cuts each keypoint's neighbourhood out and describes the tiles side by
    side: the same bits as ORB over the whole image, the same keypoints refused at the
    border — on a rendered frame and on noise, at random pixels, next to the border and at
    half pixels (where rounding decides)."""
    world, r, c = scene
    rng = np.random.default_rng(4)
    rendered = r.render(c[0], c[1], 0.3)
    h, w = rendered.shape[:2]
    near = np.r_[rng.uniform(25, 37, 150), rng.uniform(w - 37, w - 25, 150)]
    pix = np.r_[
        np.c_[rng.uniform(-3, w + 3, 400), rng.uniform(-3, h + 3, 400)],
        np.c_[near, rng.uniform(40, h - 40, 300)],
        np.c_[rng.uniform(40, w - 40, 300), near],
    ]
    pix = np.r_[pix, np.floor(pix[:200]) + 0.5].astype(np.float32)
    center = (world.camera.cu + 3.3, world.camera.cv - 1.7)
    for image in (rendered, rng.integers(0, 256, (h, w), dtype=np.uint8)):
        want, want_ok = _orb_on_the_whole_image(image, pix, center)
        got, got_ok = OrbDescriber(center).describe(image, pix)
        assert np.array_equal(got_ok, want_ok) and 0 < want_ok.sum() < len(pix)
        assert np.array_equal(got, want)


def test_hamming_helpers_match_brute_force():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (7, 32), dtype=np.uint8)
    brute = np.array([[np.unpackbits(x ^ y).sum() for y in b] for x in a])
    assert np.array_equal(hamming(a, b), brute)
    stacked, owner = stack_sets([b[:3], b[3:4], np.zeros((0, 32), np.uint8), b[4:]])
    m = min_hamming(a, stacked, owner, 4)
    assert np.array_equal(m[:, 0], brute[:, :3].min(1)) and np.all(m[:, 2] == 256)


def _candidates(bearings, sigma=0.002, desc=None):
    n = len(bearings)
    desc = np.zeros((n, 32), np.uint8) if desc is None else desc
    return isotropic_candidates(
        np.arange(100, 100 + n), np.asarray(bearings), sigma, desc, np.arange(n)
    )


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_association_by_gate_and_descriptor():
    cand = _candidates(unit([[1, 0, 0], [0, 1, 0.1]]))
    meas = unit([[1, 0.003, 0], [0, 1, 0.1 + 0.002], [0, 0, 1]])
    desc = np.zeros((3, 32), np.uint8)
    pairs = associate(meas, desc, np.ones(3, bool), cand, 13.8, 50)
    assert sorted(pairs) == [(0, 0), (1, 1)]
    # a descriptor 64 bits away is not that landmark, however well it fits
    far = desc.copy()
    far[0, :8] = 0xFF
    assert (0, 0) not in associate(meas, far, np.ones(3, bool), cand, 13.8, 50)
    # outside the gate: 0.02 rad with σ 0.002 is 10σ
    off = unit([[1, 0.02, 0]])
    assert associate(off, desc[:1], np.ones(1, bool), cand, 13.8, 50) == []
    # undescribed features are never associated
    assert associate(meas, desc, np.zeros(3, bool), cand, 13.8, 50) == []


def test_the_gate_prunes_only_pairs_that_cannot_be_inside_it():
    """``mahalanobis(within=gate)`` leaves out (inf) only the pairs too far apart to be
    within the gate; the pairs it computes are the full computation's to the bit, so the
    feasible pairs are the same. Its bound, a whole factor 2 under what it prunes at, checked
    on pairs placed just inside and outside the gate along each covariance's long axis."""
    rng = np.random.default_rng(11)
    n_l = 40
    b = unit(rng.normal(size=(n_l, 3)))
    a = rng.normal(size=(n_l, 2, 2)) * 0.004
    cov = a @ a.transpose(0, 2, 1) + 1e-6 * np.eye(2)
    cand = Candidates(np.arange(n_l), b, cov, np.zeros((n_l, 32), np.uint8), np.arange(n_l))
    gate = 9.21
    basis = tangent_basis(b)
    w, v = np.linalg.eigh(cov)
    near = []
    for k in range(n_l):  # at 0.99 and 1.01 of the gate along the long axis
        for f in (0.99, 1.01):
            step = np.sqrt(f * gate * w[k, 1]) * (basis[k] @ v[k, :, 1])
            near.append(b[k] + step)
    meas = unit(np.vstack([np.array(near), rng.normal(size=(30, 3))]))
    for scale in (1.0, 0.999, 1.001):  # bearings a little off the unit sphere as well
        m = meas * scale
        full, pruned = mahalanobis(m, cand), mahalanobis(m, cand, within=gate)
        assert np.array_equal(full <= gate, pruned <= gate)
        kept = np.isfinite(pruned)
        assert np.array_equal(pruned[kept], full[kept])
        assert kept.sum() < 0.2 * kept.size  # most pairs are never computed
        assert (full <= gate).sum() >= n_l // 2  # the pairs just inside are found


def test_ambiguous_associations_are_not_made():
    """Two features inside one landmark's gate: neither is taken for it. A feature inside
    two landmarks' gates: it is taken for neither."""
    cand = _candidates(unit([[1, 0, 0]]), sigma=0.003)
    two = unit([[1, 0.002, 0], [1, -0.003, 0]])
    assert associate(two, np.zeros((2, 32), np.uint8), np.ones(2, bool), cand, 13.8, 50) == []
    # ... even when the competitor is a track already associated elsewhere (not assignable)
    assignable = np.array([True, False])
    assert (
        associate(two, np.zeros((2, 32), np.uint8), np.ones(2, bool), cand, 13.8, 50, assignable)
        == []
    )
    near_both = _candidates(unit([[1, 0.003, 0], [1, -0.003, 0]]), sigma=0.003)
    one = unit([[1, 0.0, 0]])
    assert associate(one, np.zeros((1, 32), np.uint8), np.ones(1, bool), near_both, 13.8, 50) == []
    assert isinstance(near_both, Candidates)


def test_derotation_uses_the_estimators_bias_corrected_rate():
    """A MEMS gyro standing still reads its turn-on bias (here ≈ 25 °/s): the rotation the
    front end predicts between frames must be the estimator's bias-corrected one, not 6° per
    frame of a turn that is not happening."""
    from mowerhw.camera import paper_table1_camera
    from mowerhw.common.geometry import rotmat_log
    from mowerhw.teach import Teacher
    from mowerhw.vision import TeachVision

    teacher = Teacher()
    vision = TeachVision(teacher, paper_table1_camera())
    bias = np.array([0.3, -0.2, 0.35])
    for k in range(300):
        t = 0.01 * k
        teacher.imu(t, bias)
        teacher.speed(t, 0.0)
        vision.imu(t, bias)
    r = vision.rotations.rotation_between(2.0, 2.25)
    assert np.linalg.norm(rotmat_log(r)) < 1e-3
