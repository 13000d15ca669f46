"""The pixel-level renderer: the image agrees with the camera model and with its own truth."""

import math

import cv2
import numpy as np
import pytest

from mowerhw.sim import make_world
from mowerhw.sim.render import OmniRenderer, RenderSettings


@pytest.fixture(scope="module")
def scene():
    world = make_world("paper", 1)
    return world, OmniRenderer(world, seed=1)


def centre(world):
    """A place inside the lawn with no panel close by: the teach drive's start."""
    return world.lawn.point(np.array([0.0]))[0]


def test_black_outside_the_annulus_and_deterministic(scene):
    world, r = scene
    c = centre(world)
    a = r.render(c[0], c[1], 0.3)
    assert a.shape == (1540, 1540) and a.dtype == np.uint8
    assert not a[~r.table.valid].any()
    assert a[r.table.valid].mean() > 60
    other = OmniRenderer(world, seed=1)
    assert np.array_equal(other.render(c[0], c[1], 0.3), a)  # same seed, same frame: same
    assert not np.array_equal(other.render(c[0], c[1], 0.3), a)  # the next frame's noise


def test_landmark_x_corners_sit_at_their_exact_projection(scene):
    """A corner refiner started 0.8 px off lands on the projected landmark point: the panels
    are ray-cast with the same camera model the estimators use (docs/design.md §6)."""
    world, _ = scene
    quiet = OmniRenderer(world, 1, RenderSettings(noise_sigma=0.0))
    c = centre(world)
    errors = []
    for dx, yaw in ((0.0, 0.3), (0.0, 2.0), (-1.5, 1.0), (1.5, -2.0)):
        pix, ok = quiet.landmark_pixels(c[0] + dx, c[1], yaw)
        img = quiet.render(c[0] + dx, c[1], yaw, noise=False)
        start = (pix[ok] + 0.8 / math.sqrt(2)).astype(np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.001)
        cv2.cornerSubPix(img, start, (3, 3), (-1, -1), crit)
        errors.append(np.linalg.norm(start.reshape(-1, 2) - pix[ok], axis=1))
    e = np.concatenate(errors)
    assert e.size >= 20
    assert np.median(e) < 0.25 and np.percentile(e, 90) < 0.6


def test_true_points_see_the_landmark_and_the_ground(scene):
    world, r = scene
    c = centre(world)
    pix, ok = r.landmark_pixels(c[0], c[1], 0.3)
    pts = r.true_points(c[0], c[1], 0.3, pix[ok])
    centres = world.landmarks_map[ok]
    assert np.max(np.linalg.norm(pts - centres, axis=1)) < 0.02
    # pixels looking down near the annulus' inner edge see the ground (z = 0), or a panel
    ang = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    ring = np.column_stack(
        [world.camera.cu + 200 * np.cos(ang), world.camera.cv + 200 * np.sin(ang)]
    )
    ground = r.true_points(c[0], c[1], 0.3, ring)
    assert np.sum(np.abs(ground[:, 2]) < 1e-9) >= 30
    assert np.all(ground[:, 2] < world.scenario.camera_height_m)
    sky = r.true_points(c[0], c[1], 0.3, np.array([[world.camera.cu + 740.0, world.camera.cv]]))
    assert np.all(np.isnan(sky)) or sky[0, 2] > 0.0  # the sky, or a panel
