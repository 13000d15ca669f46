"""Pixel-level vision wired to the estimators: front end + re-identification → teach / mow.

These two classes turn camera images into the ``(t, ids, bearings)`` the estimators take,
with landmark ids that mean the same thing across track losses (teach) and sessions (mow):

* :class:`TeachVision` — every new track is first offered to the landmarks the
  :class:`~mowerhw.teach.Teacher` has already located but does not see now (predicted
  bearing from the teacher's pose and map, gate, ORB distance); a match continues that
  landmark (it comes back into view, the loop closes on it); otherwise the track starts a
  new landmark. Descriptors and the keyframe of first sight are kept for the map.
* :class:`MowVision` — a track becomes a map landmark only through re-identification
  against the :class:`~mowerhw.mow.Localizer`'s prediction for the frame's time (bearing and
  its covariance, χ² gate) plus ORB distance to the map's descriptors; an association the
  localizer's own χ² gate keeps refusing is dropped and that pair is not tried again.

Pure computation (no device I/O): the runtime feeds it frames from the camera driver, the
bench from the renderer.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from mowerhw.config import FrontendConfig
from mowerhw.frontend import FrameTracks, FrontEnd, RotationHistory
from mowerhw.frontend.association import Candidates, associate, isotropic_candidates
from mowerhw.frontend.descriptors import DESCRIPTOR_BYTES, hamming, stack_sets
from mowerhw.geometry import quat_to_rotmat, tangent_basis

FloatArray = NDArray[np.float64]
#: radians per pixel of the omni camera near the horizon (Table I: ~470 px/rad there)
_RAD_PER_PX = 1.0 / 470.0


#: a refused (track, landmark) pair is not tried again for this long (s): long enough to stop
#: a wrong pair coming back every frame, short enough that a standing mower whose tracks
#: all lost their landmarks (a sensor gap) re-identifies them again
BAN_S = 3.0
#: per-frame figures kept (bounded: the daemon runs for days); 20000 frames = 83 min at 4 Hz
STATS_FRAMES = 20000


@dataclass
class VisionStats:
    frames: int = 0
    tracks_per_frame: deque[int] = field(default_factory=lambda: deque(maxlen=STATS_FRAMES))
    observations: int = 0  # bearings handed to the estimator
    reidentified: int = 0  # tracks matched to a known landmark
    dropped_associations: int = 0
    frontend_ms: deque[float] = field(default_factory=lambda: deque(maxlen=STATS_FRAMES))


def merge_descriptors(
    have: NDArray[np.uint8] | None, new: NDArray[np.uint8], limit: int, min_bits: int = 12
) -> NDArray[np.uint8]:
    """Add the descriptors of ``new`` that differ from all of ``have`` (up to ``limit``)."""
    out = np.zeros((0, DESCRIPTOR_BYTES), np.uint8) if have is None else have
    for d in new.reshape(-1, DESCRIPTOR_BYTES):
        if out.shape[0] >= limit:
            break
        if out.shape[0] == 0 or hamming(d[None], out).min() > min_bits:
            out = np.vstack([out, d[None]])
    return out


class _VisionBase:
    def __init__(self, camera: Any, q_bc: Any, config: FrontendConfig | None, seed: int) -> None:
        self.cfg = config or FrontendConfig()
        self.frontend = FrontEnd(camera, q_bc, self.cfg, seed)
        self.camera = camera
        self.r_bc = quat_to_rotmat(np.asarray(q_bc, dtype=np.float64))
        self.rotations = RotationHistory()
        self.stats = VisionStats()
        self._t_prev: float | None = None
        # Kalibr's camera-to-IMU time shift: t_imu = t_cam + shift (calibrations without one: 0)
        self.time_shift_s = float(getattr(camera, "timeshift_cam_imu", 0.0))

    def imu(self, t: float, gyro_xyz: Any) -> None:
        """A gyro sample (body frame, as measured): its rate with the estimator's bias (and
        scale) taken out goes into the rotation history the front end derotates with — a MEMS
        gyro's ±20 °/s turn-on bias would turn every predicted feature 5° per frame."""
        self.rotations.add(t, self.estimator_rate(np.asarray(gyro_xyz, dtype=np.float64)))

    def estimator_rate(self, gyro: FloatArray) -> FloatArray:  # pragma: no cover - overridden
        return gyro

    def frame(self, t: float, image: NDArray[np.uint8]) -> FrameTracks:
        """One image, start to end: :meth:`prepare`, :meth:`track`, :meth:`use`."""
        return self.use(self.track(t, image, self.prepare(t)))

    def prepare(self, t: float) -> FloatArray | None:
        """The gyro's body rotation from the previous frame to the one taken at ``t`` (call on
        the estimator's thread: it reads the IMU history)."""
        t = t + self.time_shift_s
        r = None
        if self._t_prev is not None:
            r = self.rotations.rotation_between(self._t_prev, t)
        self._t_prev = t
        return r

    def track(self, t: float, image: NDArray[np.uint8], r_prev_cur: FloatArray | None):
        """Detection and tracking, the costly part: touches only the front end, so a runtime
        may run it on a worker thread (one frame at a time). ``t`` is the camera's capture
        time; the tracks carry it on the IMU's clock (``timeshift_cam_imu`` applied)."""
        tracks = self.frontend.process(t + self.time_shift_s, image, r_prev_cur)
        self.stats.frames += 1
        self.stats.tracks_per_frame.append(int(tracks.ids.size))
        self.stats.frontend_ms.append(tracks.ms)
        return tracks

    def use(self, tracks: FrameTracks) -> FrameTracks:  # pragma: no cover - overridden
        raise NotImplementedError

    def _track_descriptors(self, tracks: FrameTracks) -> tuple[NDArray[np.uint8], NDArray]:
        """The newest descriptor of every track, and which tracks have one."""
        desc = np.zeros((tracks.ids.size, DESCRIPTOR_BYTES), np.uint8)
        has = np.zeros(tracks.ids.size, bool)
        for k, dd in enumerate(tracks.descriptors):
            if dd.shape[0]:
                desc[k], has[k] = dd[-1], True
        return desc, has

    def _in_view(self, bearings: FloatArray) -> NDArray[np.bool_]:
        """Predicted bearings that land inside the camera's mask."""
        if bearings.shape[0] == 0:
            return np.zeros(0, bool)
        _, ok = self.camera.visible(bearings @ self.r_bc)
        return ok


class TeachVision(_VisionBase):
    """Images → a :class:`~mowerhw.teach.Teacher` (see the module doc)."""

    def __init__(
        self,
        teacher: Any,
        camera: Any,
        q_bc: Any = (0.0, 1.0, 0.0, 0.0),
        config: FrontendConfig | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(camera, q_bc, config, seed)
        self.teacher = teacher
        self.landmark_of: dict[int, int] = {}  # track id → landmark id
        self.descriptors: dict[int, NDArray[np.uint8]] = {}  # landmark id → (K, 32)
        self.first_keyframe: dict[int, int] = {}
        # (t, track id, landmark id, bearing) of every re-identification
        self.reidentifications: list[tuple[float, int, int, FloatArray]] = []
        self.gate = float(chi2.ppf(self.cfg.association_gate, df=2))

    def estimator_rate(self, gyro: FloatArray) -> FloatArray:
        return self.teacher.corrected_rate(gyro)

    def use(self, tracks: FrameTracks) -> FrameTracks:
        """Landmark ids for the tracks (re-identification) → the Teacher."""
        t = tracks.t
        new = np.flatnonzero(tracks.ages == 0)
        if new.size:
            self._reidentify(tracks, new)
        lm = np.array([self.landmark_of[int(i)] for i in tracks.ids], dtype=np.int64)
        self._keep_descriptors(tracks, lm)
        self.teacher.bearings(t, lm, tracks.bearings)
        self.stats.observations += int(lm.size)
        kf = self.teacher.keyframes[-1].index if self.teacher.keyframes else 0
        for i in lm.tolist():
            self.first_keyframe.setdefault(i, kf)
        return tracks

    def _reidentify(self, tracks: FrameTracks, new: NDArray[np.int64]) -> None:
        for k in new.tolist():  # by default a new track is a new landmark
            self.landmark_of[int(tracks.ids[k])] = int(tracks.ids[k])
        if self.teacher.phase != "driving":
            return
        ids, xyz, cov = self.teacher.known_landmarks()
        if ids.size == 0:
            return
        seen = {self.landmark_of[int(i)] for i in tracks.ids[tracks.ages > 0]}
        pos, q_wb = self.teacher.world_pose()
        d = (xyz - pos) @ quat_to_rotmat(q_wb)  # R_wbᵀ (L − x)
        dist = np.linalg.norm(d, axis=1)
        sigma_l = np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, -1], 0.0))
        pred = d / np.maximum(dist, 1e-9)[:, None]
        ok = (
            ~np.isin(ids, list(seen))
            & (sigma_l < 0.1)
            & (dist > 0.5)
            & np.array([i in self.descriptors for i in ids.tolist()], dtype=bool)
        )
        ok[ok] = self._in_view(pred[ok])
        if not ok.any():
            return
        sig_b = self.teacher.sigma
        sigma = np.sqrt(sig_b**2 + (sigma_l[ok] / dist[ok]) ** 2)
        stacked, owner = stack_sets([self.descriptors[i] for i in ids[ok].tolist()])
        cand = isotropic_candidates(ids[ok], pred[ok], sigma, stacked, owner)
        self._match(tracks, new, cand, np.radians(self.cfg.reid_angle_deg))

    def _match(
        self, tracks: FrameTracks, new: NDArray[np.int64], cand: Candidates, max_angle: float
    ) -> None:
        desc, has = self._track_descriptors(tracks)
        assignable = np.zeros(tracks.ids.size, bool)
        assignable[new] = True
        pairs = associate(
            tracks.bearings, desc, has, cand, self.gate, self.cfg.max_hamming, assignable
        )
        for k, c in pairs:
            angle = float(np.arccos(np.clip(tracks.bearings[k] @ cand.bearings[c], -1.0, 1.0)))
            if angle > max_angle:
                continue
            tid = int(tracks.ids[k])
            self.landmark_of[tid] = int(cand.ids[c])
            self.reidentifications.append(
                (tracks.t, tid, int(cand.ids[c]), tracks.bearings[k].copy())
            )
            self.stats.reidentified += 1

    def _keep_descriptors(self, tracks: FrameTracks, lm: NDArray[np.int64]) -> None:
        due = (tracks.ages % self.cfg.descriptor_refresh_frames) == 0
        for k in np.flatnonzero(due).tolist():
            dd = tracks.descriptors[k]
            if dd.shape[0]:
                i = int(lm[k])
                self.descriptors[i] = merge_descriptors(
                    self.descriptors.get(i), dd, self.cfg.max_descriptors
                )

    def annotate(self, result: Any) -> Any:
        """Put the descriptors and first keyframes of the mapped landmarks in a TeachResult."""
        result.descriptors = {
            i: self.descriptors[i].tobytes() for i in result.landmarks if i in self.descriptors
        }
        result.landmark_keyframes = {
            i: self.first_keyframe[i] for i in result.landmarks if i in self.first_keyframe
        }
        return result


class MowVision(_VisionBase):
    """Images → a :class:`~mowerhw.mow.Localizer` by re-identification against the map."""

    def __init__(
        self,
        localizer: Any,
        camera: Any,
        q_bc: Any = (0.0, 1.0, 0.0, 0.0),
        config: FrontendConfig | None = None,
        seed: int = 0,
        pixel_sigma: float = 1.0,
    ) -> None:
        super().__init__(camera, q_bc, config, seed)
        self.loc = localizer
        self.gate = float(chi2.ppf(self.cfg.association_gate, df=2))
        self.sigma_px_rad = pixel_sigma * _RAD_PER_PX
        lms = localizer.map.landmarks
        self._map_ids = np.array([lm.id for lm in lms], dtype=np.int64)
        sets = [
            np.frombuffer(lm.descriptor, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
            if lm.descriptor
            else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
            for lm in lms
        ]
        self._has_desc = np.array([s.shape[0] > 0 for s in sets], dtype=bool)
        self._desc_sets = sets
        self.landmark_of: dict[int, int] = {}  # live track id → map landmark id
        self._refusals: dict[int, int] = {}  # track id → consecutive χ² refusals
        self._banned: dict[tuple[int, int], float] = {}  # pair → when it was refused
        self._t_last = -math.inf
        # the last frame's associations: track ids, map ids, pixels
        self.last_associated = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
        self.last_bearings = np.zeros((0, 3))

    def estimator_rate(self, gyro: FloatArray) -> FloatArray:
        return self.loc.corrected_rate(gyro)

    def use(self, tracks: FrameTracks) -> FrameTracks:
        """Associations of the tracks with map landmarks → the Localizer."""
        t = tracks.t
        live = set(tracks.ids.tolist())
        for tid in [k for k in self.landmark_of if k not in live]:
            del self.landmark_of[tid]
            self._refusals.pop(tid, None)
        prediction = self._predict(t)
        self._confirm(tracks, prediction)
        free = np.array([int(i) not in self.landmark_of for i in tracks.ids], dtype=bool)
        if free.any():
            self._associate(tracks, np.flatnonzero(free), prediction)
        rows = np.array([int(i) in self.landmark_of for i in tracks.ids], dtype=bool)
        tids = tracks.ids[rows]
        lm = np.array([self.landmark_of[int(i)] for i in tids], dtype=np.int64)
        self.loc.bearings(t, lm, tracks.bearings[rows])
        self.stats.observations += int(lm.size)
        self.last_associated = (tids, lm, tracks.pixels[rows])
        self.last_bearings = tracks.bearings[rows]
        self._t_last = t
        self._review(tids, lm)
        if len(self._banned) > 256:  # forget expired bans (bounded memory)
            self._banned = {k: v for k, v in self._banned.items() if t - v < BAN_S}
        return tracks

    def _predict(self, t: float) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """Every map landmark as the localizer expects it in the frame taken at ``t``, with a
        covariance at the front end's precision. The localizer weighs bearings with a
        conservative σ; an association is judged at the front end's own (``pixel_sigma``),
        or two features a few pixels apart — a board's corner and the pane next to it —
        would both pass, and a track sliding off its corner would keep its landmark."""
        ids, pred, cov = self.loc.predict_bearings(t)
        cov = cov + (self.sigma_px_rad**2 - self.loc.cfg.bearing_sigma_rad**2) * np.eye(2)
        return ids, pred, cov

    def _confirm(self, tracks: FrameTracks, prediction: tuple) -> None:
        """Every frame, each associated track must still be where its landmark is predicted
        (χ² gate at the front end's precision); one that is not (it slid off the corner, was
        occluded and jumped) loses the landmark, and the pair is not tried again."""
        if not self.landmark_of:
            return
        ids, pred, cov = prediction
        row_of = {int(i): k for k, i in enumerate(ids.tolist())}
        ks = [k for k, tid in enumerate(tracks.ids.tolist()) if tid in self.landmark_of]
        if not ks:
            return
        rows = np.array([row_of[self.landmark_of[int(tracks.ids[k])]] for k in ks])
        b = tracks.bearings[ks]
        basis = tangent_basis(pred[rows])
        r = np.einsum("nk,nkj->nj", b - pred[rows], basis)
        d2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(cov[rows]), r)
        for k, dist2 in zip(ks, d2.tolist(), strict=True):
            if not dist2 <= self.gate:
                tid = int(tracks.ids[k])
                self._banned[(tid, self.landmark_of.pop(tid))] = tracks.t
                self._refusals.pop(tid, None)
                self.stats.dropped_associations += 1

    def _associate(self, tracks: FrameTracks, free: NDArray[np.int64], prediction: tuple) -> None:
        ids, pred, cov = prediction
        taken = set(self.landmark_of.values())
        ok = self._has_desc & ~np.isin(ids, list(taken))
        ok[ok] = self._in_view(pred[ok])
        if not ok.any():
            return
        sel = np.flatnonzero(ok)
        stacked, owner = stack_sets([self._desc_sets[k] for k in sel.tolist()])
        cand = Candidates(ids[sel], pred[sel], cov[sel], stacked, owner)
        # every track takes part (for ambiguity); only free ones may be paired
        desc, has = self._track_descriptors(tracks)
        assignable = np.zeros(tracks.ids.size, bool)
        assignable[free] = True
        pairs = associate(
            tracks.bearings, desc, has, cand, self.gate, self.cfg.max_hamming, assignable
        )
        for k, c in pairs:
            tid, lid = int(tracks.ids[k]), int(cand.ids[c])
            if tracks.t - self._banned.get((tid, lid), -math.inf) < BAN_S:
                continue
            self.landmark_of[tid] = lid
            self.stats.reidentified += 1

    def _review(self, tids: NDArray[np.int64], lm: NDArray[np.int64]) -> None:
        """Drop associations the localizer's χ² gate refuses ``drop_after_rejections`` times
        running; a refused pair is not tried again."""
        refused = set(np.asarray(self.loc.last_rejected).tolist())
        for tid, i in zip(tids.tolist(), lm.tolist(), strict=True):
            if i in refused:
                self._refusals[tid] = self._refusals.get(tid, 0) + 1
                if self._refusals[tid] >= self.cfg.drop_after_rejections:
                    del self.landmark_of[tid]
                    self._refusals.pop(tid, None)
                    self._banned[(tid, i)] = self._t_last
                    self.stats.dropped_associations += 1
            else:
                self._refusals.pop(tid, None)
