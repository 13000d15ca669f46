"""Mow: tracks associated with map landmarks (prediction, χ² gate, ORB distance)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from mowerhw.camera import CameraModel
from mowerhw.common.geometry import tangent_basis
from mowerhw.common.relocalization import SearchRequest
from mowerhw.config import FrontendConfig
from mowerhw.frontend import FrameTracks
from mowerhw.frontend.association import Candidates, associate
from mowerhw.frontend.descriptors import DESCRIPTOR_BYTES, stack_sets
from mowerhw.map import LawnMap
from mowerhw.mow.localizer import Localizer
from mowerhw.mow.relocalize import GlobalRelocalizer
from mowerhw.vision.base import BAN_S, RAD_PER_PX, VisionBase

FloatArray = NDArray[np.float64]


class FrameSearch:
    """A frame's relocalization from its tracks' bearings, with the map's relocalizer built
    on first use (megabytes of tables): what :class:`MowVision` runs where it tracks — on
    its own thread, or in the front end's worker process, which builds one from
    :attr:`MowVision.search_args`."""

    def __init__(self, lawn_map: LawnMap) -> None:
        self.map = lawn_map
        self._relocalizer: GlobalRelocalizer | None = None

    def __call__(self, tracks: FrameTracks, search: SearchRequest) -> FrameTracks:
        if self._relocalizer is None:
            self._relocalizer = GlobalRelocalizer(self.map)
        found = self._relocalizer.locate(tracks.bearings, search.near, search.heading)
        return replace(tracks, relocalization=found)


class MowVision(VisionBase):
    """Images → a :class:`~mowerhw.mow.Localizer` by re-identification against the map."""

    def __init__(
        self,
        localizer: Localizer,
        camera: CameraModel,
        q_bc: ArrayLike = (0.0, 1.0, 0.0, 0.0),
        config: FrontendConfig | None = None,
        seed: int = 0,
        pixel_sigma: float = 1.0,
    ) -> None:
        super().__init__(camera, q_bc, config, seed)
        self.loc = localizer
        self.gate = float(chi2.ppf(self.cfg.association_gate, df=2))
        self.sigma_px_rad = pixel_sigma * RAD_PER_PX
        lms = localizer.map.landmarks
        self._map_ids = np.array([lm.id for lm in lms], dtype=np.int64)
        sets = [
            np.frombuffer(lm.descriptor, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
            if lm.descriptor
            else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
            for lm in lms
        ]
        self._has_desc = np.array([s.shape[0] > 0 for s in sets], dtype=bool)
        # every landmark's descriptors stacked once, with the landmark (row) of each: a
        # frame's candidates take theirs by a mask, not by stacking them again
        self._desc_all, self._desc_row = stack_sets(sets)
        self.landmark_of: dict[int, int] = {}  # live track id → map landmark id
        self._refusals: dict[int, int] = {}  # track id → consecutive χ² refusals
        self._banned: dict[tuple[int, int], float] = {}  # pair → when it was refused
        self._t_last = -math.inf
        self._lifted_calls = 0  # the localizer's, at the previous frame's search request
        # the last frame's associations: track ids, map ids, pixels
        self.last_associated = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
        self.last_bearings = np.zeros((0, 3))
        self.search_args = (localizer.map,)
        self._search = FrameSearch(*self.search_args)
        localizer.use_relocalizer()  # every start pose is checked, kidnaps are searched

    def estimator_rate(self, gyro: FloatArray) -> FloatArray:
        return self.loc.corrected_rate(gyro)

    def wants_search(self) -> SearchRequest | None:
        """While the localizer has given its pose up, every frame is searched; a frame after
        the mower was lifted, with tracks that start afresh (a carried track slides onto the
        corner next to its own: after a kidnap, a quarter of the answer's pairs were such)."""
        lifts = self.loc.lifted_calls
        carried, self._lifted_calls = lifts > self._lifted_calls, lifts
        if not self.loc.searching:
            return None
        return SearchRequest(self.loc.search_near(), self.loc.search_heading(), carried)

    def searched(self, tracks: FrameTracks, search: SearchRequest) -> FrameTracks:
        return self._search(tracks, search)

    def use(self, tracks: FrameTracks) -> FrameTracks:
        """Associations of the tracks with map landmarks → the Localizer; while it searches
        for its pose, the frame's global relocalization instead, and when that is accepted
        the inliers its fit trusts become the first associations."""
        t = tracks.t
        if self.loc.searching:
            self.landmark_of.clear()
            answer = tracks.relocalization
            if answer is None or not self.loc.relocalization(t, answer):
                self.loc.bearings(t, np.zeros(0, np.int64), np.zeros((0, 3)))
                none = np.zeros(0, np.int64)
                self.last_associated = (none, none, np.zeros((0, 2)))
                self.last_bearings = np.zeros((0, 3))
                self._t_last = t
                return tracks
            trusted, doubted = answer.seeds()
            self.landmark_of = {int(tracks.ids[r]): lid for r, lid in trusted}
            for r, lid in doubted:  # not re-associated at once either: the pose is the fit's
                self._banned[(int(tracks.ids[r]), lid)] = t
        live = set(tracks.ids.tolist())
        for tid in [k for k in self.landmark_of if k not in live]:
            del self.landmark_of[tid]
            self._refusals.pop(tid, None)
        prediction = self._predict(t)
        refused = self._confirm(tracks, prediction)
        free = np.array([int(i) not in self.landmark_of for i in tracks.ids], dtype=bool)
        if free.any():
            self._associate(tracks, np.flatnonzero(free), prediction)
        rows = np.array([int(i) in self.landmark_of for i in tracks.ids], dtype=bool)
        tids = tracks.ids[rows]
        lm = np.array([self.landmark_of[int(i)] for i in tids], dtype=np.int64)
        self.loc.bearings(t, lm, tracks.bearings[rows], refused=refused)
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

    def _confirm(self, tracks: FrameTracks, prediction: tuple) -> int:
        """Every frame, each associated track must still be where its landmark is predicted
        (χ² gate at the front end's precision); one that is not (it slid off the corner, was
        occluded and jumped — or the mower was carried) loses the landmark, and the pair is
        not tried again. How many lost theirs (the localizer counts them as disagreeing)."""
        if not self.landmark_of:
            return 0
        ids, pred, cov = prediction
        row_of = {int(i): k for k, i in enumerate(ids.tolist())}
        ks = [k for k, tid in enumerate(tracks.ids.tolist()) if tid in self.landmark_of]
        if not ks:
            return 0
        rows = np.array([row_of[self.landmark_of[int(tracks.ids[k])]] for k in ks])
        b = tracks.bearings[ks]
        basis = tangent_basis(pred[rows])
        r = np.einsum("nk,nkj->nj", b - pred[rows], basis)
        d2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(cov[rows]), r)
        refused = 0
        for k, dist2 in zip(ks, d2.tolist(), strict=True):
            if not dist2 <= self.gate:
                tid = int(tracks.ids[k])
                self._banned[(tid, self.landmark_of.pop(tid))] = tracks.t
                self._refusals.pop(tid, None)
                self.stats.dropped_associations += 1
                refused += 1
        return refused

    def _associate(self, tracks: FrameTracks, free: NDArray[np.int64], prediction: tuple) -> None:
        ids, pred, cov = prediction
        taken = set(self.landmark_of.values())
        ok = self._has_desc & ~np.isin(ids, list(taken))
        ok[ok] = self._in_view(pred[ok])
        if not ok.any():
            return
        sel = np.flatnonzero(ok)
        mine = ok[self._desc_row]
        position = np.cumsum(ok) - 1  # a landmark row's index among ``sel``
        stacked, owner = self._desc_all[mine], position[self._desc_row[mine]]
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
