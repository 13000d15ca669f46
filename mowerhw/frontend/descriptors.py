"""ORB descriptors of tracked features, in the omni image's radial frame.

In an omnidirectional image the world's vertical runs along the image radius, and a turn of
the mower rotates the whole image. Each keypoint's orientation is therefore set to the
radial direction at its pixel (not estimated from the patch): descriptors are the same
whatever the mower's heading and, for upright things, from any side of the lawn.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

DESCRIPTOR_BYTES = 32  # ORB: 256 bits
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


class OrbDescriber:
    """ORB descriptors at given pixels (no detection)."""

    def __init__(self, center_px: tuple[float, float], patch_size: int = 31) -> None:
        self.center = center_px
        self.orb = cv2.ORB_create(edgeThreshold=patch_size, patchSize=patch_size)
        self.patch_size = patch_size

    def describe(
        self, image: NDArray[np.uint8], pixels: NDArray
    ) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
        """(N, 32) descriptors and which pixels got one (too close to the border: none)."""
        n = len(pixels)
        out = np.zeros((n, DESCRIPTOR_BYTES), np.uint8)
        ok = np.zeros(n, bool)
        if n == 0:
            return out, ok
        cx, cy = self.center
        kps = []
        for k, (u, v) in enumerate(np.asarray(pixels, dtype=np.float64)):
            # radial direction (outwards = up in the world for this mirror) in degrees
            angle = math.degrees(math.atan2(v - cy, u - cx)) % 360.0
            kps.append(cv2.KeyPoint(float(u), float(v), float(self.patch_size), angle, 1.0, 0, k))
        kept, desc = self.orb.compute(image, kps)
        if desc is None:
            return out, ok
        idx = np.array([kp.class_id for kp in kept], dtype=np.int64)
        out[idx] = desc
        ok[idx] = True
        return out, ok


def hamming(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.int64]:
    """(N, M) bit distances between descriptor rows of ``a`` (N, 32) and ``b`` (M, 32)."""
    if a.size == 0 or b.size == 0:
        return np.zeros((a.shape[0], b.shape[0]), np.int64)
    x = np.bitwise_xor(a[:, None, :], b[None, :, :])
    return _POPCOUNT[x].sum(axis=-1, dtype=np.int64)


def min_hamming(
    a: NDArray[np.uint8], stacked: NDArray[np.uint8], owner: NDArray[np.int64], n_sets: int
) -> NDArray[np.int64]:
    """(N, n_sets): distance of each row of ``a`` to the closest descriptor of each set, the
    sets given as all their descriptors ``stacked`` (K, 32) with the set of each (``owner``)."""
    out = np.full((a.shape[0], n_sets), 256, np.int64)
    if a.shape[0] == 0 or stacked.shape[0] == 0:
        return out
    d = hamming(a, stacked)  # (N, K)
    order = np.argsort(owner, kind="stable")
    owner_sorted = owner[order]
    starts = np.flatnonzero(np.r_[True, owner_sorted[1:] != owner_sorted[:-1]])
    out[:, owner_sorted[starts]] = np.minimum.reduceat(d[:, order], starts, axis=1)
    return out


def stack_sets(sets: list[NDArray[np.uint8]]) -> tuple[NDArray[np.uint8], NDArray[np.int64]]:
    """All descriptors of ``sets`` in one (K, 32) array, and the set each came from."""
    parts = [s.reshape(-1, DESCRIPTOR_BYTES) for s in sets]
    if not parts or sum(p.shape[0] for p in parts) == 0:
        return np.zeros((0, DESCRIPTOR_BYTES), np.uint8), np.zeros(0, np.int64)
    owner = np.concatenate([np.full(p.shape[0], j, np.int64) for j, p in enumerate(parts)])
    return np.concatenate(parts), owner
