"""Global relocalization from one frame (issue 18): candidates by descriptor, pose by RANSAC."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mowerhw.map import Landmark, LawnMap
from mowerhw.mow.relocalize import GlobalRelocalizer

pytest.importorskip("poselib", reason="poselib (absolute pose solvers) is not installed")


def _map(rng: np.random.Generator, n: int = 40) -> tuple[LawnMap, np.ndarray, np.ndarray]:
    ang = rng.uniform(0, 2 * np.pi, n)
    r = rng.uniform(6.0, 14.0, n)
    pts = np.c_[r * np.cos(ang), r * np.sin(ang), rng.uniform(-0.5, 1.7, n)]
    desc = rng.integers(0, 256, size=(n, 2, 32), dtype=np.uint8)  # two views per landmark
    lms = [Landmark(i, pts[i], np.eye(3) * 1e-4, descriptor=desc[i].tobytes()) for i in range(n)]
    ring = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    boundary = np.c_[5 * np.cos(ring), 4 * np.sin(ring)]
    return LawnMap(boundary=boundary, landmarks=lms, camera=None, teach={}), pts, desc


def _view(pts: np.ndarray, p: np.ndarray, yaw: float, rng: np.random.Generator, sigma: float):
    c, s = math.cos(yaw), math.sin(yaw)
    r_wb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    b = (pts - p) @ r_wb  # body frame
    b = b / np.linalg.norm(b, axis=1, keepdims=True) + rng.normal(0, sigma, b.shape)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _noisy(desc: np.ndarray, rng: np.random.Generator, flips: int) -> np.ndarray:
    out = desc.copy()
    for _ in range(flips):
        byte, bit = rng.integers(0, 32), rng.integers(0, 8)
        out[byte] ^= np.uint8(1 << bit)
    return out


def test_the_pose_comes_back_from_one_frame_with_wrong_matches_among_the_right() -> None:
    rng = np.random.default_rng(3)
    lawn_map, pts, desc = _map(rng)
    p, yaw = np.array([1.5, -2.0, 0.0]), 2.3
    seen = rng.permutation(40)[:25]
    bearings = _view(pts[seen], p, yaw, rng, 0.002)
    tracks = [_noisy(desc[i, 0], rng, 12)[None] for i in seen]
    clutter = 15  # features on nothing in the map, with descriptors of their own
    bearings = np.vstack([bearings, _view(rng.normal(0, 8, (clutter, 3)), p, yaw, rng, 0.0)])
    tracks += [rng.integers(0, 256, (1, 32), dtype=np.uint8) for _ in range(clutter)]
    res = GlobalRelocalizer(lawn_map).locate(bearings, tuple(tracks))
    assert res.ok, res.why
    assert np.linalg.norm(res.p_wb - p) < 0.05
    assert abs((res.yaw - yaw + math.pi) % (2 * math.pi) - math.pi) < math.radians(1.0)
    assert {lm for _, lm in res.inliers} <= set(seen.tolist())
    assert len(res.inliers) >= 20


def test_too_few_recognised_landmarks_give_no_pose() -> None:
    rng = np.random.default_rng(4)
    lawn_map, pts, desc = _map(rng)
    seen = np.arange(5)
    bearings = _view(pts[seen], np.zeros(3), 0.0, rng, 0.001)
    res = GlobalRelocalizer(lawn_map).locate(bearings, tuple(desc[i, :1] for i in seen))
    assert not res.ok and "candidate" in res.why
    unknown = tuple(rng.integers(0, 256, (1, 32), dtype=np.uint8) for _ in range(20))
    res = GlobalRelocalizer(lawn_map).locate(_view(pts[:20], np.zeros(3), 0.0, rng, 0.0), unknown)
    assert not res.ok
