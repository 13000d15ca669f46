"""Teach: re-identification of new tracks with landmarks the Teacher already located."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from mowerhw.camera import CameraModel
from mowerhw.common.geometry import quat_to_rotmat
from mowerhw.config import FrontendConfig
from mowerhw.frontend import FrameTracks
from mowerhw.frontend.association import Candidates, associate, isotropic_candidates
from mowerhw.frontend.descriptors import stack_sets
from mowerhw.teach.teacher import Teacher, TeachResult
from mowerhw.vision.base import VisionBase, merge_descriptors

FloatArray = NDArray[np.float64]


class TeachVision(VisionBase):
    """Images → a :class:`~mowerhw.teach.Teacher` (see the module doc)."""

    def __init__(
        self,
        teacher: Teacher,
        camera: CameraModel,
        q_bc: ArrayLike = (0.0, 1.0, 0.0, 0.0),
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

    def annotate(self, result: TeachResult) -> TeachResult:
        """Put the descriptors and first keyframes of the mapped landmarks in a TeachResult."""
        result.descriptors = {
            i: self.descriptors[i].tobytes() for i in result.landmarks if i in self.descriptors
        }
        result.landmark_keyframes = {
            i: self.first_keyframe[i] for i in result.landmarks if i in self.first_keyframe
        }
        return result
