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
    is largely theirs, and a filter that starts from it must know (None: not computed)."""

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

    @property
    def yaw(self) -> float:
        return math.atan2(self.r_wb[1, 0], self.r_wb[0, 0])


@dataclass(frozen=True)
class SearchRequest:
    """A frame to relocalize from: around ``near`` (x, y, heading), or everywhere (None);
    ``heading``: what the compass says while searching everywhere (ψ, σ; rad)."""

    near: tuple[float, float, float] | None = None
    heading: tuple[float, float] | None = None
