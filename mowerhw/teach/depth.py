"""Depth pseudo-measurements of landmarks from two views (paper eq. 3, docs/design.md §4).

Anchor frame ``a`` (where a landmark's bearing ``y_a`` was taken) and the current body frame
``b`` form a triangle with the landmark. With ``b`` the current body origin in ``a``
(``b = −R_baᵀ x_a``, ``x_a`` the anchor origin in the current frame) and the current bearing
rotated into ``a`` (``u = R_baᵀ y_k``), the law of sines gives the current distance:

    sin α = sqrt(1 − (b̂ · y_a)²)      angle at the anchor between baseline and y_a
    sin β = sqrt(1 − (u · y_a)²)       angle at the landmark between the two bearings
    d_k   = ‖b‖ sin α / sin β

It is ill-conditioned with little parallax (small β) or a short baseline: those landmarks get
no pseudo-measurement this frame (``ok`` False, with the reason counted by the caller). The
three angles of a real triangle add up to π; rays that do not meet in front of both views
(outliers, a wrong anchor) fail that check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DepthPseudoMeasurement:
    depth: FloatArray  # (N,) d_k, NaN where not ok
    variance: FloatArray  # (N,) approximate variance of d_k (m²)
    ok: NDArray[np.bool_]  # (N,)
    parallax: FloatArray  # (N,) β (rad)
    baseline: FloatArray  # (N,) ‖b‖ (m)
    low_parallax: NDArray[np.bool_]  # (N,) skipped: β or the baseline below the guard
    inconsistent: NDArray[np.bool_]  # (N,) skipped: the rays do not form a triangle


def _angle(a: FloatArray, b: FloatArray) -> FloatArray:
    """Angle between unit vectors (N, 3), accurate near 0 and π."""
    angle: FloatArray = np.arctan2(
        np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("ni,ni->n", a, b)
    )
    return angle


def depth_pseudo_measurement(
    anchor_origin_b: FloatArray,
    r_b_anchor: FloatArray,
    y_anchor: FloatArray,
    y_now: FloatArray,
    bearing_sigma: float,
    min_parallax_rad: float,
    min_baseline_m: float,
    triangle_tolerance_rad: float = 0.05,
    baseline_variance: FloatArray | float = 0.0,
) -> DepthPseudoMeasurement:
    """Eq. (3) for N landmarks at once.

    ``anchor_origin_b`` (N, 3): the anchor frame's origin in the current body frame;
    ``r_b_anchor`` (N, 3, 3): ``R_{b←a}``; ``y_anchor`` (N, 3) the bearing in the anchor frame;
    ``y_now`` (N, 3) the current bearing (body frame).
    """
    b = -np.einsum("nji,nj->ni", r_b_anchor, anchor_origin_b)  # R_baᵀ x_a, negated
    baseline = np.linalg.norm(b, axis=-1)
    b_hat = b / np.where(baseline > 0, baseline, 1.0)[:, None]
    u = np.einsum("nji,nj->ni", r_b_anchor, y_now)  # current bearing in the anchor frame
    alpha = _angle(b_hat, y_anchor)
    beta = _angle(u, y_anchor)
    gamma = _angle(-b_hat, u)  # angle at the current position
    low = (baseline < min_baseline_m) | (beta < min_parallax_rad)
    inconsistent = ~low & (np.abs(alpha + beta + gamma - np.pi) > triangle_tolerance_rad)
    ok = ~low & ~inconsistent
    sin_b = np.sin(beta)
    depth = np.where(ok, baseline * np.sin(alpha) / np.where(ok, sin_b, 1.0), np.nan)
    # First-order error: both rays' noise moves β (√2 σ), the anchor ray moves α; plus the
    # baseline's own uncertainty scales the whole triangle.
    with np.errstate(divide="ignore", invalid="ignore"):
        rel2 = bearing_sigma**2 * (2.0 / np.tan(beta) ** 2 + 1.0 / np.tan(alpha) ** 2)
        rel2 = rel2 + np.asarray(baseline_variance) / np.maximum(baseline, 1e-9) ** 2
    variance = np.where(ok, depth**2 * rel2, np.nan)
    return DepthPseudoMeasurement(depth, variance, ok, beta, baseline, low, inconsistent)
