"""Re-identification: which tracked feature is which known landmark.

Features are matched to landmarks by where an estimator predicts each landmark to be seen
(its bearing and the covariance of that prediction) and by appearance (ORB distance to the
landmark's stored descriptors) — never by track ids, which mean nothing after a track is
lost or in another session. A pair is feasible only inside the χ² gate of the predicted
bearing *and* within ``max_hamming`` bits, and a pair
is made only where it is unambiguous: the landmark has exactly one feature in its gate and
that feature lies in no other landmark's gate. A wrong pair that slipped through is met
again by the localizer's own χ² gate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import tangent_basis
from mowerhw.frontend.descriptors import min_hamming

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Candidates:
    """Landmarks that may be in view, as an estimator predicts them."""

    ids: NDArray[np.int64]  # landmark ids
    bearings: FloatArray  # (L, 3) predicted unit bearings, body frame
    covariance: FloatArray  # (L, 2, 2) prediction + measurement covariance, tangent basis
    descriptors: NDArray[np.uint8]  # (K, 32) every stored descriptor of these landmarks
    owner: NDArray[np.int64]  # (K,) index into ``ids`` of each descriptor


def mahalanobis(meas: FloatArray, cand: Candidates, within: float | None = None) -> FloatArray:
    """(M, L) squared Mahalanobis distance of each measured bearing from each (unit)
    prediction, in the tangent plane of the prediction. ``within``: only the pairs that can
    be that close are computed, the others are ``inf`` — a bearing ``m`` at ``θ`` from the
    prediction ``b`` is ``|m| sin θ`` from it in the tangent plane (squared: ``|m|² −
    (m·b)²``), so at least that squared distance over ``λ_max(S)`` away in d² (pruned only
    beyond twice the bound: rounding never decides it)."""
    m, n_l = meas.shape[0], cand.ids.size
    if m == 0 or n_l == 0:
        return np.zeros((m, n_l))
    dot = meas @ cand.bearings.T  # (M, L) m·b; a bearing behind its prediction is never near
    pairs = dot > 0.0
    if within is not None:
        s = cand.covariance
        half_trace = 0.5 * (s[:, 0, 0] + s[:, 1, 1])
        spread = np.hypot(0.5 * (s[:, 0, 0] - s[:, 1, 1]), s[:, 0, 1])
        norm2 = np.einsum("mk,mk->m", meas, meas)
        pairs &= norm2[:, None] - dot * dot <= 2.0 * within * (half_trace + spread)[None, :]
    mi, li = np.nonzero(pairs)
    d2 = np.full((m, n_l), np.inf)
    if mi.size:
        basis = tangent_basis(cand.bearings)  # (L, 3, 2)
        r = np.einsum("pk,pkj->pj", meas[mi] - cand.bearings[li], basis[li])  # (P, 2)
        s_inv = np.linalg.inv(cand.covariance)  # (L, 2, 2)
        d2[mi, li] = np.einsum("pi,pij,pj->p", r, s_inv[li], r)
    return d2


def associate(
    meas_bearings: FloatArray,
    meas_descriptors: NDArray[np.uint8],
    meas_described: NDArray[np.bool_],
    cand: Candidates,
    gate: float,
    max_hamming: int,
    assignable: NDArray[np.bool_] | None = None,
) -> list[tuple[int, int]]:
    """One-to-one pairs ``(measurement index, candidate index)`` (see the module doc).

    Only unambiguous pairs are made: a candidate with two features inside its gate (two
    corners of one window, a neighbour that looks alike), or a feature inside the gates of
    two candidates, is left alone — an association skipped costs one bearing, a wrong one
    can pull the pose. ``assignable`` marks the measurements that may be paired (the others,
    e.g. tracks already associated, still count for ambiguity)."""
    m, n_l = meas_bearings.shape[0], cand.ids.size
    if m == 0 or n_l == 0:
        return []
    if assignable is None:
        assignable = np.ones(m, bool)
    d2 = mahalanobis(meas_bearings, cand, within=gate)
    ham = min_hamming(meas_descriptors, cand.descriptors, cand.owner, n_l)
    feasible = (d2 <= gate) & (ham <= max_hamming) & meas_described[:, None]
    unique = feasible & (feasible.sum(axis=0) == 1)[None, :] & (feasible.sum(axis=1) == 1)[:, None]
    unique &= assignable[:, None]
    rows, cols = np.nonzero(unique)
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=True)]


def isotropic_candidates(
    ids: NDArray[np.int64],
    bearings: FloatArray,
    sigma_rad: FloatArray | float,
    descriptors: NDArray[np.uint8],
    owner: NDArray[np.int64],
) -> Candidates:
    """Candidates with a circular prediction uncertainty ``sigma_rad`` (per landmark or one)."""
    sig = np.broadcast_to(np.asarray(sigma_rad, dtype=np.float64), ids.shape)
    cov = np.einsum("l,ij->lij", sig**2, np.eye(2))
    return Candidates(ids, bearings, cov, descriptors, owner)
