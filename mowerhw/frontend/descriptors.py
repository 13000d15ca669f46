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
_WORDS = DESCRIPTOR_BYTES // 8  # a descriptor as four 64-bit words, for the bit counts


class OrbDescriber:
    """ORB descriptors at given pixels (no detection).

    OpenCV's ORB blurs its whole input image before it describes (a 7×7 Gaussian over
    1540×1540 pixels for a handful of keypoints), so the keypoints' neighbourhoods are cut
    out and described side by side in one small mosaic instead: a descriptor depends only
    on the blurred pixels within ``SUPPORT_PX`` of the keypoint's rounded pixel and on its
    angle, which the tile of each holds whole — the same bits as on the whole image
    (tests/test_frontend.py), at a tenth of the cost for a frame's dozen new tracks. A pixel
    whose rounded position is within ``patch_size`` of the image border gets none (OpenCV's
    own rule for the whole image)."""

    #: the BRIEF pattern of a 31-px patch reaches 13·√2 px from the keypoint's pixel,
    #: turned; the 7×7 blur 3 px more
    SUPPORT_PX = 22
    #: half a tile: the keypoint sits at (TILE_HALF, TILE_HALF + j·tile) of the mosaic, at
    #: least ``patch_size`` from the mosaic's border (OpenCV drops keypoints nearer)
    TILE_HALF = 34

    def __init__(self, center_px: tuple[float, float], patch_size: int = 31) -> None:
        self.center = center_px
        self.orb = cv2.ORB_create(edgeThreshold=patch_size, patchSize=patch_size)
        self.patch_size = patch_size
        self._tile = 2 * self.TILE_HALF + 1

    def describe(
        self, image: NDArray[np.uint8], pixels: NDArray
    ) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
        """(N, 32) descriptors and which pixels got one (too close to the border: none)."""
        n = len(pixels)
        out = np.zeros((n, DESCRIPTOR_BYTES), np.uint8)
        ok = np.zeros(n, bool)
        if n == 0:
            return out, ok
        pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        h, w = image.shape[:2]
        edge = self.patch_size
        # ORB rounds a keypoint (float32) to its pixel, half to even as np.rint
        rounded = np.rint(np.nan_to_num(pix.astype(np.float32), nan=-1.0)).astype(np.int64)
        inside = (
            (rounded[:, 0] >= edge)
            & (rounded[:, 0] < w - edge)
            & (rounded[:, 1] >= edge)
            & (rounded[:, 1] < h - edge)
        )
        rows = np.flatnonzero(inside)
        if rows.size == 0:
            return out, ok
        half, size = self.TILE_HALF, self._tile
        x0 = rounded[rows, 0] - half
        y0 = rounded[rows, 1] - half
        # radial direction (outwards = up in the world for this mirror) in degrees
        cx, cy = self.center
        angles = [math.degrees(math.atan2(v - cy, u - cx)) % 360.0 for u, v in pix[rows].tolist()]
        span = np.arange(size)
        # a tile past the image's edge repeats the edge: only pixels beyond SUPPORT_PX of
        # the keypoint come from there, and no descriptor reads them
        cols = np.clip(x0[:, None] + span, 0, w - 1)  # (n, size)
        lines = np.clip(y0[:, None] + span, 0, h - 1)
        tiles = image[lines[:, :, None], cols[:, None, :]]  # (n, size, size)
        kps = [
            cv2.KeyPoint(float(half), float(half + j * size), float(edge), a, 1.0, 0, j)
            for j, a in enumerate(angles)
        ]
        kept, desc = self.orb.compute(tiles.reshape(-1, size), kps)
        if desc is None:
            return out, ok
        idx = rows[np.array([kp.class_id for kp in kept], dtype=np.int64)]
        out[idx] = desc
        ok[idx] = True
        return out, ok


def hamming(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.int64]:
    """(N, M) bit distances between descriptor rows of ``a`` (N, 32) and ``b`` (M, 32)."""
    out = np.zeros((a.shape[0], b.shape[0]), np.int64)
    if a.size == 0 or b.size == 0:
        return out
    wa = np.ascontiguousarray(a).view(np.uint64)  # (N, 4)
    wb = np.ascontiguousarray(b).view(np.uint64)  # (M, 4)
    for k in range(_WORDS):  # word by word: (N, M) at a time, never (N, M, 32)
        out += np.bitwise_count(np.bitwise_xor(wa[:, k, None], wb[None, :, k]))
    return out


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
