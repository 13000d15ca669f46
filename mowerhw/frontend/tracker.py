"""The vision front end: features found, tracked and described in omni images.

Per frame (:meth:`FrontEnd.process`):

1. **Track** (the paper's method): pyramidal Lucas–Kanade from the previous frame, each
   feature's start guess rotated by the gyro (``R21``) so a turn does not lose it, and the
   previous image first turned by the same amount about the mirror centre (Lucas–Kanade
   follows shifts, not rotated patches); then tracked back, and kept only if it returns
   within ``fb_max_px`` (forward–backward check). It runs on the half-size image
   (``klt_base_level``: a quarter of the pixels, the same patch and coarsest level); step 2
   puts each corner back on the full-size image.
2. **Refine**: corners are snapped to sub-pixel (``cv2.cornerSubPix``); KLT alone drifts a
   little every frame, and over a 60 s teach loop the drift adds up. A feature the refinement
   moves more than ``max_refine_px`` is not a corner and is dropped.
3. **Reject outliers on the sphere**: bearings of the surviving tracks must satisfy the
   two-view epipolar constraint with the gyro's rotation (:mod:`.epipolar`).
4. **Detect** when fewer than ``max_features`` remain: Shi–Tomasi corners on a pyramid level,
   inside the mirror annulus and the configured elevation band, away from existing tracks,
   spread over a grid; refined at full size.
5. **Describe**: ORB descriptors in the radial frame (:mod:`.descriptors`), at birth and
   every ``descriptor_refresh_frames``, up to ``max_descriptors`` per track.
6. **Lift** every tracked pixel to a unit bearing in the body frame (camera model, docs/design.md
   §6, eq. 24, and the mount ``q_bc``).

The output (:class:`FrameTracks`) is ``(t, ids, bearings)`` as the estimators take it, plus
pixels and ages. Track ids are never reused.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from mowerhw.camera import OmniRadtanCamera
from mowerhw.common.geometry import quat_to_rotmat
from mowerhw.common.relocalization import Relocalization
from mowerhw.config import FrontendConfig
from mowerhw.frontend.descriptors import DESCRIPTOR_BYTES, OrbDescriber, hamming
from mowerhw.frontend.epipolar import epipolar_inliers

FloatArray = NDArray[np.float64]


@dataclass
class FrameTracks:
    """What the front end saw in one frame."""

    t: float
    ids: NDArray[np.int64]
    bearings: FloatArray  # (N, 3) unit, body frame
    pixels: FloatArray  # (N, 2)
    ages: NDArray[np.int64]  # frames each track has been followed (0: born now)
    ms: float = 0.0  # processing time of this frame
    #: every track's ORB descriptors, oldest first: (K, 32) each, K may be 0. Carried with
    #: the frame so that association never reads the tracker's state (which the worker
    #: thread changes on the next frame)
    descriptors: tuple[NDArray[np.uint8], ...] = ()
    #: a global relocalization from this frame's bearings, when the mow chain asked for one
    #: (it runs where the tracking runs: :meth:`mowerhw.vision.MowVision.track`)
    relocalization: Relocalization | None = None


@dataclass
class FrontendStats:
    frames: int = 0
    detected: int = 0
    lost_klt: int = 0
    lost_forward_backward: int = 0
    lost_refine: int = 0
    lost_epipolar: int = 0
    lost_outside: int = 0
    rejected_at_birth: int = 0
    ms_total: float = 0.0
    # frames, of each ended track (the newest 20000: bounded for a long-running daemon)
    track_lengths: deque[int] = field(default_factory=lambda: deque(maxlen=20000))


def shi_tomasi(image: NDArray[np.uint8], pts: FloatArray, half: int = 3) -> FloatArray:
    """Shi–Tomasi corner strength (smaller eigenvalue of the structure tensor over a
    (2·half+1)² window) at each pixel of ``pts``, computed on small patches only."""
    n = pts.shape[0]
    if n == 0:
        return np.zeros(0)
    h, w = image.shape
    r = half + 1
    u = np.clip(np.round(pts[:, 0]).astype(int), r, w - r - 1)
    v = np.clip(np.round(pts[:, 1]).astype(int), r, h - r - 1)
    off = np.arange(-r, r + 1)
    patch = image[(v[:, None] + off)[:, :, None], (u[:, None] + off)[:, None, :]].astype(np.float32)
    gx = 0.5 * (patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2])
    gy = 0.5 * (patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1])
    sxx, syy, sxy = (gx * gx).sum((1, 2)), (gy * gy).sum((1, 2)), (gx * gy).sum((1, 2))
    return 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)


def spread(pts: FloatArray, min_distance: float, limit: int) -> FloatArray:
    """Greedy non-maximum suppression: ``pts`` (strongest first) at least ``min_distance``
    apart, at most ``limit`` of them."""
    if limit <= 0:
        return np.zeros((0, 2))
    if not min_distance > 0.0:
        return np.asarray(pts, dtype=np.float64).reshape(-1, 2)[:limit].copy()
    # Chosen points kept in a grid of min_distance cells: a point closer than that to a
    # chosen one is in its cell or one of the eight around it (plain floats: the loop runs
    # over a frame's thousands of candidates).
    d2 = min_distance * min_distance
    grid: dict[tuple[int, int], list[tuple[float, float]]] = {}
    chosen: list[tuple[float, float]] = []
    for x, y in np.asarray(pts, dtype=np.float64).reshape(-1, 2).tolist():
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        i, j = int(x // min_distance), int(y // min_distance)
        if any(
            (cx - x) ** 2 + (cy - y) ** 2 < d2
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
            for cx, cy in grid.get((i + di, j + dj), ())
        ):
            continue
        chosen.append((x, y))
        grid.setdefault((i, j), []).append((x, y))
        if len(chosen) >= limit:
            break
    return np.array(chosen, dtype=np.float64).reshape(-1, 2)


class FrontEnd:
    """Detection, KLT tracking, outlier rejection, description (see the module doc)."""

    #: undo an image rotation larger than this before tracking (deg)
    DEROTATE_ABOVE_DEG = 2.0
    #: a detector's corner (FAST: a pixel next to it) may move this much more when first
    #: refined; from then on a tracked corner may move only ``max_refine_px``
    BIRTH_SLACK_PX = 2.0

    def __init__(
        self,
        camera: OmniRadtanCamera,
        q_bc: tuple[float, ...] | NDArray = (0.0, 1.0, 0.0, 0.0),
        config: FrontendConfig | None = None,
        seed: int = 0,
    ) -> None:
        self.camera = camera
        self.cfg = config or FrontendConfig()
        self.r_bc = quat_to_rotmat(np.asarray(q_bc, dtype=np.float64))
        self.stats = FrontendStats()
        self._rng = np.random.default_rng([seed, 50])
        self._next_id = 0
        self._ids = np.zeros(0, np.int64)
        self._pts = np.zeros((0, 2), np.float32)
        self._bear = np.zeros((0, 3))
        self._age = np.zeros(0, np.int64)
        self._desc: dict[int, NDArray[np.uint8]] = {}
        self._prev_pyr: NDArray[np.uint8] | None = None
        self._t_prev: float | None = None
        center = camera.mask.center_px if camera.mask else (camera.cu, camera.cv)
        self.describer = OrbDescriber((float(center[0]), float(center[1])))
        self.detect_mask = self._detection_mask()
        c = self.cfg
        win = max(5, (c.klt_window_px >> c.klt_base_level) | 1)  # the same patch, smaller
        self._win = (win, win)
        self._criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        self._subpix = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
        self._refine_win = (3, 3)  # a 7×7 window: small enough to see one corner only
        self._fast = cv2.FastFeatureDetector_create(threshold=c.fast_threshold)
        self._strongest = 0.0  # Shi–Tomasi strength of the strongest candidate just seen
        self._center = np.array(center, dtype=np.float32)

    # ------------------------------------------------------------------------------ masks

    def _detection_mask(self) -> NDArray[np.uint8]:
        """Where features may be born: the annulus, within the elevation band (full size).
        The elevation of a pixel is taken from a 4-px grid (it varies slowly)."""
        cam, c = self.camera, self.cfg
        step = 4
        v, u = np.mgrid[0 : cam.height : step, 0 : cam.width : step]
        pix = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        ok = cam.valid(pix)
        elev = np.full(pix.shape[0], np.nan)
        rays = cam.lift(pix[ok]) @ self.r_bc.T
        elev[ok] = np.degrees(np.arcsin(np.clip(rays[:, 2], -1, 1)))
        band = ok & (elev >= c.min_elevation_deg) & (elev <= c.max_elevation_deg)
        coarse = (band.reshape(v.shape) * 255).astype(np.uint8)
        full = cv2.resize(coarse, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
        # never within half a KLT window of the annulus rim: the window would see black
        valid = cam.mask_image()
        rim = cv2.erode(valid, np.ones((c.klt_window_px, c.klt_window_px), np.uint8))
        return cv2.bitwise_and(full, rim)

    # ------------------------------------------------------------------------------ public

    @property
    def track_count(self) -> int:
        return int(self._ids.size)

    def descriptors(self, track_id: int) -> NDArray[np.uint8]:
        """(K, 32) ORB descriptors of a live track (K may be 0)."""
        return self._desc.get(int(track_id), np.zeros((0, DESCRIPTOR_BYTES), np.uint8))

    def lift(self, pixels: NDArray) -> FloatArray:
        """Unit bearings in the body frame of pixels (N, 2)."""
        if len(pixels) == 0:
            return np.zeros((0, 3))
        return self.camera.lift(np.asarray(pixels, dtype=np.float64)) @ self.r_bc.T

    def drop(self, track_ids: NDArray[np.int64]) -> None:
        """Forget tracks (e.g. ones the estimator refused)."""
        keep = ~np.isin(self._ids, track_ids)
        self._end(~keep)
        self._keep(keep)

    def process(
        self,
        t: float,
        image: NDArray[np.uint8],
        r_prev_cur: FloatArray | None = None,
        restart: bool = False,
    ):
        """One frame; ``r_prev_cur`` maps current body-frame vectors into the previous frame's
        (from the gyro; identity if unknown); ``restart``: the camera moved in a way tracking
        cannot follow (the mower was carried): every track ends, and this frame's are all new.
        Returns :class:`FrameTracks`."""
        t0 = time.perf_counter()
        c = self.cfg
        if restart:
            self.drop(self._ids.copy())
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        # Lucas–Kanade runs on pyramid level ``klt_base_level`` (OpenCV 5's Python binding
        # takes images, not prebuilt pyramids, so each call builds both images' pyramids: on
        # a half-size image a quarter of the work); the refinement then finds each corner at
        # full size
        pyr = image
        for _ in range(c.klt_base_level):
            pyr = cv2.pyrDown(pyr)
        r21 = np.eye(3) if r_prev_cur is None else np.asarray(r_prev_cur).T
        if self._prev_pyr is not None and self._ids.size:
            self._track(pyr, r21)
            if c.subpixel and self._ids.size:
                self._refine(image)
            if self._ids.size:
                self._epipolar(r21)
        self._age += 1
        if self._ids.size < c.max_features:
            self._detect(image, pyr)
        self._describe(image)  # the bearings are current: the epipolar check's and the new ones
        self._prev_pyr = pyr
        self._t_prev = t
        ms = (time.perf_counter() - t0) * 1e3
        self.stats.frames += 1
        self.stats.ms_total += ms
        return FrameTracks(
            float(t),
            self._ids.copy(),
            self._bear.copy(),
            self._pts.astype(np.float64),
            self._age.copy(),
            ms,
            tuple(self.descriptors(int(i)).copy() for i in self._ids.tolist()),
        )

    # --------------------------------------------------------------------------- internals

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        for k in np.flatnonzero(~keep):
            self._desc.pop(int(self._ids[k]), None)
        self._ids, self._pts = self._ids[keep], self._pts[keep]
        self._bear, self._age = self._bear[keep], self._age[keep]

    def _end(self, gone: NDArray[np.bool_]) -> None:
        self.stats.track_lengths.extend(int(a) for a in self._age[gone])

    def _predict(self, r21: FloatArray) -> NDArray[np.float32]:
        """Where each feature should be if the mower only turned (gyro)."""
        pred = self.camera.project((self._bear @ r21.T) @ self.r_bc)
        bad = ~np.all(np.isfinite(pred), axis=1)
        pred[bad] = self._pts[bad]
        return pred.astype(np.float32)

    def _image_rotation(self, p0: NDArray[np.float32], pred: NDArray[np.float32]) -> float:
        """The rotation (deg) about the mirror centre that best maps ``p0`` onto ``pred``:
        a turn of the mower turns the whole omni image."""
        a = p0 - self._center
        b = pred - self._center
        cross = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
        dot = float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
        return float(np.degrees(np.arctan2(cross, dot)))

    def _track(self, pyr: NDArray[np.uint8], r21: FloatArray) -> None:
        """Lucas–Kanade from the previous image (``pyr``: the current one at the tracking
        level ``klt_base_level``; pixels there are full-size ones over ``2**level``)."""
        c = self.cfg
        prev = self._prev_pyr
        assert prev is not None
        scale = 0.5**c.klt_base_level
        p0 = self._pts.reshape(-1, 2).copy()
        guess = self._predict(r21) if c.gyro_prediction else p0.copy()
        # Lucas–Kanade follows translations; a turn rotates every patch too (12° per frame
        # at 0.8 rad/s and 4 Hz). Undo the turn on the previous image first, so what is
        # left to track is the parallax of the mower's own travel.
        angle = self._image_rotation(p0, guess)
        p0, guess = p0 * scale, guess * scale
        if abs(angle) > self.DEROTATE_ABOVE_DEG:
            m = cv2.getRotationMatrix2D(tuple((self._center * scale).tolist()), -angle, 1.0)
            prev = cv2.warpAffine(prev, m, (prev.shape[1], prev.shape[0]), flags=cv2.INTER_LINEAR)
            p0 = (p0 @ m[:, :2].T + m[:, 2]).astype(np.float32)
        p0 = p0.reshape(-1, 1, 2)
        guess = guess.reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(
            prev,
            pyr,
            p0,
            guess.copy(),
            winSize=self._win,
            maxLevel=c.klt_levels - c.klt_base_level,
            criteria=self._criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        p0b, st_b, _ = cv2.calcOpticalFlowPyrLK(
            pyr,
            prev,
            p1,
            p0.copy(),
            winSize=self._win,
            maxLevel=c.klt_levels - c.klt_base_level,
            criteria=self._criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        st, st_b = st.ravel().astype(bool), st_b.ravel().astype(bool)
        fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1) / scale  # full-size px
        p1 = p1.reshape(-1, 2) / scale
        inside = np.zeros(len(p1), bool)
        fin = np.all(np.isfinite(p1), axis=1)
        ui = np.round(p1[fin]).astype(int)
        h, w = self.detect_mask.shape
        in_img = (ui[:, 0] >= 0) & (ui[:, 0] < w) & (ui[:, 1] >= 0) & (ui[:, 1] < h)
        idx = np.flatnonzero(fin)[in_img]
        inside[idx] = self.camera.valid(p1[idx].astype(np.float64))
        ok_klt = st & fin
        ok_fb = ok_klt & st_b & (fb < c.fb_max_px)
        keep = ok_fb & inside
        s = self.stats
        s.lost_klt += int((~ok_klt).sum())
        s.lost_forward_backward += int((ok_klt & ~ok_fb).sum())
        s.lost_outside += int((ok_fb & ~inside).sum())
        self._pts = np.where(keep[:, None], p1, self._pts).astype(np.float32)
        self._end(~keep)
        self._keep(keep)

    def _refine(self, image: NDArray[np.uint8]) -> None:
        pts = self._pts.reshape(-1, 1, 2).copy()
        cv2.cornerSubPix(image, pts, self._refine_win, (-1, -1), self._subpix)
        pts = pts.reshape(-1, 2)
        shift = np.linalg.norm(pts - self._pts, axis=1)
        keep = np.all(np.isfinite(pts), axis=1) & (shift <= self.cfg.max_refine_px)
        self.stats.lost_refine += int((~keep).sum())
        self._pts = np.where(keep[:, None], pts, self._pts).astype(np.float32)
        self._end(~keep)
        self._keep(keep)

    def _epipolar(self, r21: FloatArray) -> None:
        y1 = self._bear
        y2 = self.lift(self._pts)
        inl, _ = epipolar_inliers(
            y1,
            y2,
            r21,
            np.radians(self.cfg.epipolar_threshold_deg),
            self.cfg.ransac_iterations,
            self._rng,
        )
        self.stats.lost_epipolar += int((~inl).sum())
        self._end(~inl)
        self._bear = y2  # the tracks' bearings now, kept with them (not lifted twice a frame)
        self._keep(inl)

    def _candidates(self, image: NDArray[np.uint8]) -> FloatArray:
        """Corner candidates (full-size pixels), strongest first, at least
        ``min_distance_px`` apart, inside the detection mask."""
        c = self.cfg
        if c.detector == "fast":
            kps = self._fast.detect(image, self.detect_mask)
            if not kps:
                return np.zeros((0, 2))
            pts = np.array([kp.pt for kp in kps], dtype=np.float64)
            score = shi_tomasi(image, pts)
            self._strongest = float(score.max())
            keep = score >= c.quality_level * self._strongest
            pts, score = pts[keep], score[keep]
            return spread(pts[np.argsort(-score)], c.min_distance_px, 4 * c.max_features)
        lv = c.detect_level
        scale = 2**lv
        small = image
        for _ in range(lv):
            small = cv2.pyrDown(small)
        mask = (
            self.detect_mask
            if lv == 0
            else cv2.resize(
                self.detect_mask, (small.shape[1], small.shape[0]), interpolation=cv2.INTER_NEAREST
            )
        )
        corners = cv2.goodFeaturesToTrack(
            small,
            maxCorners=4 * c.max_features,
            qualityLevel=c.quality_level,
            minDistance=c.min_distance_px / scale,
            mask=mask,
            blockSize=c.block_size,
        )
        if corners is None:
            return np.zeros((0, 2))
        cand = corners.reshape(-1, 2) * scale + (scale - 1) / 2.0  # level → full-size pixels
        self._strongest = float(shi_tomasi(image, cand).max())
        return cand

    def _detect(self, image: NDArray[np.uint8], pyr: NDArray[np.uint8]) -> None:
        c = self.cfg
        scale = 2**c.detect_level if c.detector == "shi-tomasi" else 1
        need = c.max_features - self._ids.size
        cand = self._candidates(image)
        if cand.size == 0:
            return
        if self._pts.size:
            d2 = ((cand[:, None, :] - self._pts[None, :, :]) ** 2).sum(-1)
            cand = cand[d2.min(axis=1) >= c.min_distance_px**2]
        if cand.size == 0:
            return
        # spread over a grid: a cell takes at most its share, strongest first
        h, w = image.shape
        cell = np.floor(cand[:, 1] * c.grid / h) * c.grid + np.floor(cand[:, 0] * c.grid / w)
        cap = max(2, -(-2 * c.max_features // (c.grid * c.grid)))
        if self._pts.size:
            old = np.floor(self._pts[:, 1] * c.grid / h) * c.grid + np.floor(
                self._pts[:, 0] * c.grid / w
            )
            counts = dict(zip(*np.unique(old, return_counts=True), strict=True))
        else:
            counts = {}
        chosen = []
        for k, cl in enumerate(cell.tolist()):  # candidates are sorted by strength
            if counts.get(cl, 0) < cap:
                counts[cl] = counts.get(cl, 0) + 1
                chosen.append(k)
                if len(chosen) >= need:
                    break
        if not chosen:
            return
        raw = cand[chosen].astype(np.float32).reshape(-1, 2)
        pts = raw.reshape(-1, 1, 2).copy()
        cv2.cornerSubPix(image, pts, self._refine_win, (-1, -1), self._subpix)
        pts = pts.reshape(-1, 2)
        # a corner the refinement does not hold still is not one (it would be dropped by
        # the same test after its first tracked frame)
        ok = (
            np.all(np.isfinite(pts), axis=1)
            & (np.linalg.norm(pts - raw, axis=1) <= c.max_refine_px + self.BIRTH_SLACK_PX * scale)
            & self.camera.valid(pts.astype(np.float64))
        )
        # ... nor is a point the refinement pulled into a blob's flat middle
        strength = shi_tomasi(image, np.nan_to_num(pts.astype(np.float64)))
        ok &= strength >= c.quality_level * self._strongest
        self.stats.rejected_at_birth += int((~ok).sum())
        pts = pts[ok]
        n = len(pts)
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        self._ids = np.concatenate([self._ids, ids])
        self._pts = np.concatenate([self._pts, pts]).astype(np.float32)
        self._bear = np.concatenate([self._bear, self.lift(pts)])
        self._age = np.concatenate([self._age, np.zeros(n, np.int64)])
        self.stats.detected += n

    def _describe(self, image: NDArray[np.uint8]) -> None:
        c = self.cfg
        due = (self._age % c.descriptor_refresh_frames) == 0
        if not due.any():
            return
        idx = np.flatnonzero(due)
        desc, ok = self.describer.describe(image, self._pts[idx])
        for k, d, good in zip(idx.tolist(), desc, ok, strict=True):
            if not good:
                continue
            tid = int(self._ids[k])
            have = self._desc.get(tid)
            if have is None:
                self._desc[tid] = d[None].copy()
            elif have.shape[0] < c.max_descriptors and hamming(d[None], have).min() > 12:
                self._desc[tid] = np.vstack([have, d[None]])
