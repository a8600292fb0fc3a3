"""Felzenszwalb-Huttenlocher graph segmentation (IJCV 2004) as a compiled kernel, the superpixels of the segment cues.

The same definition as skimage.segmentation.felzenszwalb (what the segment cues used before): a Gaussian pre-blur
of each channel (sigma px), an 8-connected pixel grid whose edge weights are the Euclidean distances between
feature vectors, edges visited in increasing weight, two components merged when the edge weight is below both
internal differences Int(C) + k / |C| with k = scale / 255, then a second pass over the same order merging any
component smaller than min_size with its neighbour. Differences from skimage, none of which changes the
definition: features stay float32; edges are ordered by a stable counting sort of the weight quantised to 2^16
levels of the image's largest weight (equal-looking weights keep raster order, where skimage's quicksort order is
arbitrary); union by size; and the merge pass is kept so a larger min_size can be applied without redoing it (the min-size pass walks only
the edges that still join two components after the merge pass, a few percent of them).
About 10x faster than skimage at 512 x 512 with 3-4 channels (no 2 x E int64 edge table, no float64 argsort).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from services.worker.cues.common import gaussian_blur

SORT_LEVELS = 1 << 16


@njit(cache=True, nogil=True)
def _find(parent: np.ndarray, i: int) -> int:
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


_DIRECTIONS = ((0, 1), (1, 0), (1, 1), (-1, 1))  # right, down, down-right, up-right: skimage's edge set


@njit(cache=True, nogil=True)
def _edge_count(h: int, w: int) -> int:
    return h * (w - 1) + (h - 1) * w + 2 * (h - 1) * (w - 1)


@njit(cache=True, nogil=True)
def _distance(img: np.ndarray, y: int, x: int, y2: int, x2: int) -> float:
    s = 0.0
    for k in range(img.shape[2]):
        d = img[y, x, k] - img[y2, x2, k]
        s += d * d
    return np.sqrt(s)


@njit(cache=True, nogil=True)
def _sorted_edges(img: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 8-connected grid's edges (pixel ends a, b and feature distance) in increasing distance quantised to
    `levels` steps of the largest, ties in generation order (a stable counting sort), so the merge passes read
    them in sequence. Generation order: direction by direction, rows, columns (skimage's edge set)."""
    h, w, _ = img.shape
    cost = np.empty(_edge_count(h, w), np.float32)
    e = 0
    for dy, dx in _DIRECTIONS:
        for y in range(max(0, -dy), h - max(0, dy)):
            for x in range(w - dx):
                cost[e] = _distance(img, y, x, y + dy, x + dx)
                e += 1
    top = 0.0
    for v in cost:
        top = max(top, v)
    scale = (levels - 1) / top if top > 0 else 0.0
    start = np.zeros(levels + 1, np.int64)
    for v in cost:
        start[int(v * scale) + 1] += 1
    for i in range(levels):
        start[i + 1] += start[i]
    a = np.empty(len(cost), np.int32)
    b = np.empty(len(cost), np.int32)
    sorted_cost = np.empty(len(cost), np.float32)
    e = 0
    for dy, dx in _DIRECTIONS:
        for y in range(max(0, -dy), h - max(0, dy)):
            for x in range(w - dx):
                q = int(cost[e] * scale)
                j = start[q]
                start[q] += 1
                a[j] = y * w + x
                b[j] = (y + dy) * w + x + dx
                sorted_cost[j] = cost[e]
                e += 1
    return a, b, sorted_cost


@njit(cache=True, nogil=True)
def _merge(a: np.ndarray, b: np.ndarray, cost: np.ndarray, n: int, k: float) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """The greedy merge pass over the sorted edges: parent forest, component sizes, and the edges it did not
    merge across (in order): the only ones that can still join two components afterwards."""
    parent = np.arange(n).astype(np.int32)
    size = np.ones(n, np.int32)
    internal = np.zeros(n, np.float32)
    kept = np.empty(len(a), np.int32)
    n_kept = 0
    for e in range(len(a)):
        r0 = _find(parent, a[e])
        r1 = _find(parent, b[e])
        if r0 == r1:
            continue
        if cost[e] < min(internal[r0] + k / size[r0], internal[r1] + k / size[r1]):
            if size[r0] < size[r1]:
                r0, r1 = r1, r0
            parent[r1] = r0
            size[r0] += size[r1]
            internal[r0] = cost[e]
        else:
            kept[n_kept] = e
            n_kept += 1
    return parent, size, kept[:n_kept]


@njit(cache=True, nogil=True)
def _crossing(a: np.ndarray, b: np.ndarray, kept: np.ndarray, parent: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                            np.ndarray]:
    """The merge pass's forest flattened (every pixel's root) and, in edge order, the ends of the edges that join
    two of its components: the only edges the min-size pass can act on, since components only grow."""
    n = len(parent)
    root = np.empty(n, np.int32)
    for i in range(n):
        root[i] = _find(parent, i)
    ca = np.empty(len(kept), np.int32)
    cb = np.empty(len(kept), np.int32)
    j = 0
    for e in kept:
        if root[a[e]] != root[b[e]]:
            ca[j] = a[e]
            cb[j] = b[e]
            j += 1
    return root, ca[:j], cb[:j]


@njit(cache=True, nogil=True)
def _enforce_min_size(ca: np.ndarray, cb: np.ndarray, parent: np.ndarray, size: np.ndarray,
                      min_size: int) -> np.ndarray:
    """Merge components below min_size along the crossing edges (ends ca, cb, in the merge order); labels 0..n-1
    in raster order."""
    parent = parent.copy()
    size = size.copy()
    for e in range(len(ca)):
        r0 = _find(parent, ca[e])
        r1 = _find(parent, cb[e])
        if r0 != r1 and (size[r0] < min_size or size[r1] < min_size):
            if size[r0] < size[r1]:
                r0, r1 = r1, r0
            parent[r1] = r0
            size[r0] += size[r1]
    n = len(parent)
    label_of_root = np.full(n, -1, np.int64)
    out = np.empty(n, np.int64)
    count = 0
    for i in range(n):
        r = _find(parent, i)
        if label_of_root[r] < 0:
            label_of_root[r] = count
            count += 1
        out[i] = label_of_root[r]
    return out


class Felzenszwalb:
    """The merge pass of one image, done once; `labels(min_size)` then gives its superpixels for any min_size."""

    def __init__(self, features: np.ndarray, scale: float, sigma: float):
        img = np.ascontiguousarray(features, dtype=np.float32)
        if img.ndim == 2:
            img = img[..., None]
        if sigma > 0:
            img = np.stack([gaussian_blur(img[..., c], sigma, mode="reflect") for c in range(img.shape[-1])], axis=-1)
        self.shape = img.shape[:2]
        a, b, cost = _sorted_edges(img, SORT_LEVELS)
        parent, self._size, kept = _merge(a, b, cost, self.shape[0] * self.shape[1], float(scale) / 255.0)
        self._parent, self._ca, self._cb = _crossing(a, b, kept, parent)

    def labels(self, min_size: int) -> np.ndarray:
        """int64 H x W labels 0..n-1 (raster order of first appearance)."""
        flat = _enforce_min_size(self._ca, self._cb, self._parent, self._size, int(min_size))
        return flat.reshape(self.shape)
