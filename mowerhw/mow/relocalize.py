"""Global relocalization: the mower's pose from one frame, with no prior (issue 18).

For a mower switched on in the middle of the lawn, or carried there: the map's landmarks are
recognised by their ORB descriptors and the pose is solved from the bearings to them.

1. **Candidates** — every track's descriptors against every map landmark's descriptor set
   (Hamming distance, the least over both sets). A track keeps up to :data:`TOP_K` landmarks
   within ``max_hamming`` and within :data:`RATIO` of its best: with look-alike landmarks the
   single best is often wrong, and RANSAC sorts the right one out.
2. **Absolute pose** — RANSAC over those correspondences with PoseLib's generalized absolute
   pose solver (P3P minimal samples, local optimisation, then bundle refinement): the
   omnidirectional camera is given to it as a rig of :data:`VIRTUAL_CAMERAS` pinhole cameras
   sharing its centre, turned 360°/n apart about the vertical, each taking the bearings nearest
   its axis (a pinhole camera cannot hold a bearing 90° off its axis; the rig can hold all).
3. **Plausibility** — the mower upright (tilt under :data:`MAX_TILT_RAD`) at about the taught
   camera height, with at least ``min_inliers`` inliers spread in azimuth (not all from one
   side: a degenerate geometry).

Whether to *trust* a pose (the same answer over more than one frame, agreeing with the motion
in between) is the caller's decision (:class:`RelocalizationVote`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mowerhw.frontend.descriptors import DESCRIPTOR_BYTES, stack_sets
from mowerhw.map import LawnMap

FloatArray = NDArray[np.float64]

TOP_K = 3
RATIO = 1.3  # a candidate's distance at most this times the track's best
VIRTUAL_CAMERAS = 6
MAX_TILT_RAD = math.radians(15.0)
MAX_HEIGHT_ERROR_M = 0.3
MIN_AZIMUTH_SPREAD_RAD = math.radians(90.0)

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


@dataclass(frozen=True)
class Relocalization:
    """One frame's answer: ``r_wb``, ``p_wb`` (body in the map's world frame) and the inlier
    correspondences (track row, map landmark id), or why none."""

    ok: bool
    r_wb: FloatArray = field(default_factory=lambda: np.eye(3))
    p_wb: FloatArray = field(default_factory=lambda: np.zeros(3))
    inliers: list[tuple[int, int]] = field(default_factory=list)
    candidates: int = 0
    ms: float = 0.0
    why: str = ""

    @property
    def yaw(self) -> float:
        return math.atan2(self.r_wb[1, 0], self.r_wb[0, 0])


def _rig() -> tuple[list[FloatArray], FloatArray]:
    """Rotations body → virtual camera (z along the camera's axis, y down) and the axes."""
    rots, axes = [], []
    for k in range(VIRTUAL_CAMERAS):
        a = 2 * math.pi * k / VIRTUAL_CAMERAS
        z = np.array([math.cos(a), math.sin(a), 0.0])
        y = np.array([0.0, 0.0, -1.0])
        x = np.cross(y, z)
        rots.append(np.vstack([x, y, z]))
        axes.append(z)
    return rots, np.array(axes)


class GlobalRelocalizer:
    """Recognises the map's landmarks in one frame and solves the pose (module doc)."""

    def __init__(
        self,
        lawn_map: LawnMap,
        max_hamming: int = 60,
        inlier_angle_rad: float = math.radians(1.0),
        min_inliers: int = 8,
        seed: int = 0,
    ) -> None:
        lms = [lm for lm in lawn_map.landmarks if lm.descriptor]
        self.ids = np.array([lm.id for lm in lms], dtype=np.int64)
        self.points = np.array([lm.xyz for lm in lms], dtype=np.float64).reshape(-1, 3)
        sets = [
            np.frombuffer(lm.descriptor or b"", np.uint8).reshape(-1, DESCRIPTOR_BYTES)
            for lm in lms
        ]
        self.stacked, self.owner = (
            stack_sets(sets) if sets else (np.zeros((0, 32), np.uint8), np.zeros(0, np.int64))
        )
        self.max_hamming = max_hamming
        self.inlier_angle = inlier_angle_rad
        self.min_inliers = min_inliers
        # the camera's height in the map: the dock pose's (where teaching started)
        self.height = float(lawn_map.dock_position[2])
        self.dock_xy = np.asarray(lawn_map.dock_position[:2], dtype=np.float64)
        self.seed = seed
        self._rots, self._axes = _rig()

    # ------------------------------------------------------------------------ candidates

    def candidates(
        self, descriptors: tuple[NDArray[np.uint8], ...]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(track row, landmark row) pairs worth trying, at most :data:`TOP_K` per track."""
        if not descriptors or self.stacked.shape[0] == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        query, track = stack_sets(
            [np.asarray(d, np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in descriptors]
        )
        if query.shape[0] == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        # Hamming distance of every query descriptor to every map descriptor, then the least
        # per (track, landmark)
        dist = _POPCOUNT[np.bitwise_xor(query[:, None, :], self.stacked[None, :, :])].sum(axis=2)
        n_tracks, n_lm = len(descriptors), self.ids.size
        best = np.full((n_tracks, n_lm), np.iinfo(np.int32).max, dtype=np.int64)
        np.minimum.at(best, (track[:, None], self.owner[None, :]), dist)
        rows, cols = [], []
        k = min(TOP_K, n_lm)
        order = np.argsort(best, axis=1)[:, :k]
        top = np.take_along_axis(best, order, axis=1)
        ok = (top <= self.max_hamming) & (top <= RATIO * top[:, :1])
        for r in range(n_tracks):
            for j in np.flatnonzero(ok[r]).tolist():
                rows.append(r)
                cols.append(int(order[r, j]))
        return np.asarray(rows, np.int64), np.asarray(cols, np.int64)

    # ------------------------------------------------------------------------------ pose

    def locate(
        self, bearings: FloatArray, descriptors: tuple[NDArray[np.uint8], ...]
    ) -> Relocalization:
        """The pose from one frame's body-frame bearings and their tracks' descriptors."""
        import poselib

        t0 = time.perf_counter()
        rows, cols = self.candidates(descriptors)
        n = int(rows.size)

        def done(why: str) -> Relocalization:
            return Relocalization(False, candidates=n, ms=1e3 * (time.perf_counter() - t0), why=why)

        if n < max(4, self.min_inliers):
            return done(f"{n} candidate matches (need {max(4, self.min_inliers)})")
        b = np.asarray(bearings, dtype=np.float64)[rows]
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        cam = np.argmax(b @ self._axes.T, axis=1)
        points2d, points3d, which = [], [], []
        for i, rot in enumerate(self._rots):
            sel = np.flatnonzero(cam == i)
            in_cam = b[sel] @ rot.T
            points2d.append(in_cam[:, :2] / in_cam[:, 2:3])
            points3d.append(self.points[cols[sel]])
            which.append(sel)
        exts = [poselib.CameraPose() for _ in self._rots]
        for ext, rot in zip(exts, self._rots, strict=True):
            ext.R = rot
            ext.t = np.zeros(3)
        cameras = [
            {"model": "SIMPLE_PINHOLE", "width": 2, "height": 2, "params": [1.0, 0.0, 0.0]}
            for _ in self._rots
        ]
        thr = math.tan(self.inlier_angle)
        pose, info = poselib.estimate_generalized_absolute_pose(
            points2d,
            points3d,
            exts,
            cameras,
            {
                "max_reproj_error": thr,
                "max_iterations": 2000,
                "success_prob": 0.9999,
                "seed": self.seed,
            },
            {},
        )
        r_bw = np.asarray(pose.R, dtype=np.float64)
        r_wb = r_bw.T
        p_wb = -r_wb @ np.asarray(pose.t, dtype=np.float64)
        mask = (
            np.concatenate([np.asarray(m, bool) for m in info.get("inliers", [])])
            if info.get("inliers")
            else np.zeros(0, bool)
        )
        order = np.concatenate(which) if which else np.zeros(0, np.int64)
        inl = order[mask] if mask.size == order.size else np.zeros(0, np.int64)
        # one landmark per track and one track per landmark among the inliers
        pairs: dict[int, int] = {}
        used: set[int] = set()
        for k in inl.tolist():
            track_row, lm_row = int(rows[k]), int(cols[k])
            if track_row not in pairs and lm_row not in used:
                pairs[track_row] = lm_row
                used.add(lm_row)
        if len(pairs) < self.min_inliers:
            return done(f"{len(pairs)} inliers (need {self.min_inliers})")
        tilt = math.acos(float(np.clip(r_wb[2, 2], -1.0, 1.0)))
        if tilt > MAX_TILT_RAD:
            return done(f"not upright: tilted {math.degrees(tilt):.0f}°")
        # about the dock's height, give or take a 15 % grade between here and there
        allowed = MAX_HEIGHT_ERROR_M + 0.15 * float(np.hypot(*(p_wb[:2] - self.dock_xy)))
        if abs(float(p_wb[2]) - self.height) > allowed:
            return done(f"camera {p_wb[2] - self.height:+.2f} m above the dock's height")
        to_lm = self.points[list(pairs.values())] - p_wb
        az = np.sort(np.arctan2(to_lm[:, 1], to_lm[:, 0]))
        gaps = np.diff(np.concatenate([az, az[:1] + 2 * math.pi]))
        if 2 * math.pi - gaps.max() < MIN_AZIMUTH_SPREAD_RAD:
            return done("inliers all on one side")
        return Relocalization(
            True,
            r_wb,
            p_wb,
            [(r, int(self.ids[c])) for r, c in pairs.items()],
            n,
            1e3 * (time.perf_counter() - t0),
        )
