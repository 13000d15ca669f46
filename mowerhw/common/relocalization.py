"""What a relocalization is asked and answers (issue 18): plain records, so the front end that
carries an answer with a frame's tracks (:class:`mowerhw.frontend.FrameTracks`) never imports
the relocalizer (:mod:`mowerhw.mow.relocalize`) that computes it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Relocalization:
    """One frame's answer: ``r_wb``, ``p_wb`` (body in the map's world frame), the inlier
    pairs (observation row, map landmark id) and the runner-up's inliers, or why none;
    ``covariance``: of (x, y, heading), from the fit's residuals (None: not computed);
    ``landmark_cross``: (3, 3·len(inliers)) the cross-covariance of that (x, y, heading)
    with the inlier landmarks' map positions, in the inliers' order — the answer's error
    is largely theirs, and a filter that starts from it must know (None: not computed);
    ``trusted``: which inliers the fit trusts, in their order (None: not judged, all);
    ``rival``: no answer because another place or pose explains the frame nearly as well
    (ambiguous, not pinned down, a prior beaten) — a doubt about the place, where other
    refusals (too few bearings, all on one side) say only that this frame cannot tell."""

    ok: bool
    r_wb: FloatArray = field(default_factory=lambda: np.eye(3))
    p_wb: FloatArray = field(default_factory=lambda: np.zeros(3))
    inliers: list[tuple[int, int]] = field(default_factory=list)
    runner_up: int = 0
    hypotheses: int = 0
    ms: float = 0.0
    why: str = ""
    covariance: FloatArray | None = None
    landmark_cross: FloatArray | None = None
    trusted: NDArray[np.bool_] | None = None
    rival: bool = False

    @property
    def yaw(self) -> float:
        return math.atan2(self.r_wb[1, 0], self.r_wb[0, 0])

    def seeds(self) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
        """The inliers a filter restarting from this answer takes as its first associations
        (those the fit trusts: residual inside its χ² gate), and those the fit doubts: a pair
        within the inlier angle but far outside the fit's robust scale is mostly a feature
        beside the landmark's, 0.4–1° off (measured on the paper lawn's kidnaps: a fifth to
        a quarter of the pairs; seeded, they held the pose 0.2° off at σ 0.05° for 10 s)."""
        if self.trusted is None:
            return list(self.inliers), []
        flags = self.trusted.tolist()
        trusted = [p for p, ok in zip(self.inliers, flags, strict=True) if ok]
        doubted = [p for p, ok in zip(self.inliers, flags, strict=True) if not ok]
        return trusted, doubted


@dataclass(frozen=True)
class SearchRequest:
    """A frame to relocalize from: around ``near`` (x, y, heading), or everywhere (None);
    ``heading``: what the compass says while searching everywhere (ψ, σ; rad);
    ``carried``: the mower was lifted since the previous frame, so the front end forgets
    its tracks before this one (a track carried along slides onto the corner next to its
    own and keeps its descriptor: a relocalization would take it for its landmark)."""

    near: tuple[float, float, float] | None = None
    heading: tuple[float, float] | None = None
    carried: bool = False
