"""Trusting a pose again (issue 18): accepting a global relocalization, and the consistency
check every re-localization passes before the deck may run.

* :class:`RelocalizationSearch` — while the localizer has no trustworthy pose (started with
  no prior, kidnapped, a re-localization that did not check out), each answer of
  :class:`mowerhw.mow.relocalize.GlobalRelocalizer` is compared with the previous one moved
  by the odometry in between (the filter keeps propagating while it searches: its pose is
  meaningless, its *motion* is not). Two answers that agree within :data:`AGREE_M` and
  :data:`AGREE_RAD` are accepted: a pose that explains enough inliers in more than one frame
  and agrees with the IMU/odometry motion between them, with no frame between them that saw
  a rival place or pose (``Relocalization.rival``); once a frame of the search has, the
  place needs :data:`CLEAR_ANSWERS` such answers in a row.
* :class:`Probation` — after any re-localization (resume after a restart, refit after a
  lock-out, global), the filter is not trusted until ``frames_needed`` consecutive frames are
  *consistent*: a fix whose bearings' median normalised innovation (NIS, 2 degrees of freedom
  each) stays below :data:`MEDIAN_NIS_MAX`, three times the χ²₂ median, and of which at least
  :data:`ACCEPTED_FRACTION` passed the χ² gate. A re-localization that cannot show that within
  :data:`PROBATION_S` is dropped (the localizer searches again).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import wrap_angle
from mowerhw.common.relocalization import Relocalization

FloatArray = NDArray[np.float64]

#: two answers agree when the second is this close to the first moved by the odometry
AGREE_M = 0.05
AGREE_RAD = math.radians(2.0)
#: plus this share of the distance driven between them (odometry scale error)
AGREE_PER_M = 0.05
#: an answer older than this is not paired with a new one (s)
PAIR_S = 3.0
#: after a frame that saw a rival place or pose, the answers in a row (none doubted, each
#: agreeing with the one before) a place needs before it is accepted
CLEAR_ANSWERS = 4
#: a search near a prior becomes global after this long without an accepted answer (s)
LOCAL_S = 3.0
#: σ of an accepted pose: the answer's own (its fit's covariance, the map's landmark errors
#: in it), at most what answers are off (measured: 1–3 cm, < 0.3°; a wider prior let the
#: first association after it pair wrong corners, 2–3 cm of bias at σ 1 cm). The floors
#: only keep a degenerate covariance invertible: since the answer's bearings count as at
#: least ``GlobalRelocalizer.BEARING_FLOOR_RAD`` off (stop 70), its own σ matches its error
#: (the pixel pools' first 2.5 s in the map's frame: z² 0.9–1.0 per component, where floors
#: of 2 mm and 0.02° held the heading's at 0.4–0.5; README, issue 18, stop 71)
ACCEPT_SIGMA_M = 0.03
ACCEPT_SIGMA_RAD = math.radians(0.5)
ACCEPT_MIN_SIGMA_M = 0.0002
ACCEPT_MIN_SIGMA_RAD = math.radians(0.002)


def accepted_covariance(covariance: FloatArray | None) -> FloatArray:
    """The (x, y, heading) covariance a filter restarts with at an accepted answer: the
    answer's own, each σ within the bounds above and the correlations kept (a frame whose
    landmarks lie mostly to one side pins the pose down less along them; an isotropic σ at
    the largest axis made the restart surer of nothing and less sure of the rest)."""
    if covariance is None or not np.all(np.isfinite(covariance)):
        return np.diag([ACCEPT_SIGMA_M**2, ACCEPT_SIGMA_M**2, ACCEPT_SIGMA_RAD**2])
    c = 0.5 * (covariance + covariance.T)
    sigma = np.sqrt(np.maximum(np.diag(c), 0.0))
    low = np.array([ACCEPT_MIN_SIGMA_M, ACCEPT_MIN_SIGMA_M, ACCEPT_MIN_SIGMA_RAD])
    high = np.array([ACCEPT_SIGMA_M, ACCEPT_SIGMA_M, ACCEPT_SIGMA_RAD])
    bounded = np.clip(sigma, low, high)
    corr = np.eye(3)
    ok = sigma > 0.0
    both = np.outer(ok, ok)
    corr[both] = (c / np.outer(np.where(ok, sigma, 1.0), np.where(ok, sigma, 1.0)))[both]
    corr = np.clip(corr, -0.999, 0.999)
    np.fill_diagonal(corr, 1.0)
    out: FloatArray = corr * np.outer(bounded, bounded)
    return out


#: χ²₂ median ≈ 1.386; a consistent frame's median NIS stays below three times that
MEDIAN_NIS_MAX = 3.0 * 1.386
ACCEPTED_FRACTION = 0.6
PROBATION_S = 10.0


@dataclass(frozen=True)
class Pose2D:
    """A planar pose (m, m, rad): the search works in x, y and heading only."""

    x: float
    y: float
    yaw: float

    def compose(self, other: Pose2D) -> Pose2D:
        """``self ∘ other``: ``other`` expressed in this pose's frame, taken to the world."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2D(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            wrap_angle(self.yaw + other.yaw),
        )

    def inverse(self) -> Pose2D:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2D(-c * self.x - s * self.y, s * self.x - c * self.y, -self.yaw)

    def between(self, other: Pose2D) -> Pose2D:
        """The motion from this pose to ``other`` (in this pose's frame)."""
        return self.inverse().compose(other)

    def distance(self, other: Pose2D) -> float:
        return math.hypot(self.x - other.x, self.y - other.y)

    def turn(self, other: Pose2D) -> float:
        return abs(wrap_angle(self.yaw - other.yaw))


@dataclass
class _Answer:
    t: float
    pose: Pose2D  # the relocalizer's, in the map
    odometry: Pose2D  # the filter's at the same time (its own, drifting frame)


class RelocalizationSearch:
    """Pairs relocalizer answers through the odometry (module doc)."""

    def __init__(
        self, why: str, t: float | None, near: bool = False, checks_prior: bool = False
    ) -> None:
        self.why = why
        self.since = t
        #: check the filter's own pose first (a prior: the dock, a resumed pose, a lock-out)
        self.near = near
        #: the pose checked is a start pose (no sign that anything went wrong)
        self.checks_prior = checks_prior
        self.answers = 0
        self.frames = 0
        self.last_why = "no frame searched yet"
        self._last: _Answer | None = None
        #: a frame of this search saw a rival place or pose (``Relocalization.rival``)
        self._doubted = False
        #: answers in a row since the last doubt
        self._clear = 0

    def offer(self, t: float, answer: Relocalization, odometry: Pose2D) -> Pose2D | None:
        """One frame's answer, with the filter's pose at its time; the accepted pose at
        ``t`` (in the map) when it agrees with the previous answer, else None."""
        self.frames += 1
        if self.since is None:
            self.since = t
        if not answer.ok:
            self.last_why = answer.why
            if answer.rival:
                # a frame that saw a rival place or pose: a doubt about the place. Answers
                # that pass such a frame's test only just (noise flickers a borderline
                # verdict) must not pair across it, and after it the place needs a run of
                # :data:`CLEAR_ANSWERS` answers with no doubt between them (stop 75: a
                # look-alike start standing still, 6 answers in 48 frames, the rest "not
                # pinned down" or "ambiguous": two answers 0.5 s apart across a doubt were
                # accepted 0.25 m off at σ 2 cm, and — with that pairing refused — two in
                # a row 4 s later)
                self._last = None
                self._doubted = True
                self._clear = 0
            return None
        self.answers += 1
        self._clear += 1
        pose = Pose2D(float(answer.p_wb[0]), float(answer.p_wb[1]), answer.yaw)
        prev, self._last = self._last, _Answer(t, pose, odometry)
        if prev is None or not 0.0 < t - prev.t <= PAIR_S:
            self.last_why = "one answer: waiting for a second that agrees"
            self._clear = 1  # paired with nothing: the run starts here
            return None
        motion = prev.odometry.between(odometry)
        predicted = prev.pose.compose(motion)
        d, turn = predicted.distance(pose), predicted.turn(pose)
        if d > AGREE_M + AGREE_PER_M * math.hypot(motion.x, motion.y) or turn > AGREE_RAD:
            self.last_why = (
                f"two answers disagree by {d:.2f} m, {math.degrees(turn):.1f}° "
                f"after the odometry between them"
            )
            self._clear = 1  # this answer starts the run again
            return None
        if self._doubted and self._clear < CLEAR_ANSWERS:
            self.last_why = (
                f"answers agree, but a frame doubted the place: {self._clear} of "
                f"{CLEAR_ANSWERS} answers in a row since"
            )
            return None
        return pose

    def hold(self) -> None:
        """The mower is in the air: no answer from before pairs with one after."""
        self._last = None
        self._clear = 0

    def widen(self, t: float) -> None:
        """A local search that has not confirmed the prior within :data:`LOCAL_S` becomes
        a global one."""
        if not self.near or self.since is None or t - self.since < LOCAL_S:
            return
        self.near = self.checks_prior = False
        self._last = None
        self._clear = 0
        self.why += f"; the pose near the prior was not confirmed in {LOCAL_S:.0f} s"

    def describe(self) -> str:
        where = "near the prior" if self.near else "everywhere (global relocalization)"
        return (
            f"searching for the pose {where} {self.why}: "
            f"{self.answers} answers in {self.frames} frames; last: {self.last_why}"
        )


class Probation:
    """The consistency check after a re-localization (module doc)."""

    def __init__(self, kind: str, t: float | None, frames_needed: int) -> None:
        self.kind = kind
        self.since = t
        self.frames_needed = frames_needed
        self.consistent = 0
        self.last = "no frame yet"

    def frame(
        self, t: float, nis: FloatArray, accepted: NDArray[np.bool_], fix: bool
    ) -> str | None:
        """One frame's bearings after the update: "passed", "failed" (too long without
        passing) or None (still on probation)."""
        if self.since is None:
            self.since = t
        med = float(np.median(nis)) if nis.size else math.inf
        share = float(np.mean(accepted)) if accepted.size else 0.0
        if fix and med <= MEDIAN_NIS_MAX and share >= ACCEPTED_FRACTION:
            self.consistent += 1
        else:
            self.consistent = 0
            self.last = (
                f"a frame with {accepted.size} bearings, {share:.0%} accepted, "
                f"median NIS {med:.1f} (consistent: ≥ {ACCEPTED_FRACTION:.0%} accepted, "
                f"median NIS ≤ {MEDIAN_NIS_MAX:.1f})"
            )
        if self.consistent >= self.frames_needed:
            return "passed"
        if t - self.since > PROBATION_S:
            return "failed"
        return None

    def describe(self) -> str:
        return (
            f"checking the {self.kind} re-localization: {self.consistent}/{self.frames_needed} "
            f"consistent frames in a row (last inconsistent: {self.last})"
        )
