"""Unsupervised segmentations (16-bit label PNGs): Felzenszwalb superpixels merged by normalized cuts.

segment_unsup2d works on the colour image, segment_unsup25d on a feature image of weighted log-depth and
normals with occlusion edges weakening the graph's links (segment25d_weights; see segment_unsup25d). Steps:
1. skimage.segmentation.felzenszwalb(features in ~[0, 1], segment2d_scale, segment2d_sigma,
   segment2d_min_size); when it yields more than segment_max_superpixels regions it is rerun with a
   proportionally larger min_size, which bounds the cost of step 3 (a dense eigenproblem per split);
2. region adjacency graph (4-connectivity) with similarity weights exp(-|mean_a - mean_b|^2 /
   segment_ncut_sigma) of the regions' mean features on a 0..255 scale (2.5d: times exp(-5 * occlusion
   strength along the shared boundary)), plus self-loops of weight 1 (as skimage.graph.cut_normalized);
3. recursive two-way normalized cuts (Shi & Malik 2000) as skimage.graph.cut_normalized: the second
   smallest eigenvector of D^-1/2 (D - W) D^-1/2, segment_num_cuts thresholds, split while the best ncut value
   is below segment_ncut_thresh; links below UNLINKED count as absent (a subgraph falling apart there is split
   into its parts). On dense matrices (LAPACK, two eigenpairs, in float32: ncuts.py) because skimage's
   sparse/networkx version takes seconds per image;
4. labels 1..K numbered in raster order of first appearance; 0 = no surface (2d: nothing seen; 2.5d: no valid
   depth). Pixels off the surface take the nearest surface pixel's features before step 1, so the background
   neither forms segments nor leaves halo regions along silhouettes.
"""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
from numba import njit

from services.worker.context import ViewContext
from services.worker.cues.common import depth_m, hit, normal_cam, valid
from services.worker.cues.edges import occlusion_response
from services.worker.cues.feature_transform import nearest_site
from services.worker.cues.felzenszwalb import SORT_LEVELS, Felzenszwalb
from services.worker.cues.ncuts import normalized_cuts
from services.worker.cues.registry import register

# Links weaker than this count as no link in the normalized cuts (a subgraph falling apart there is split into
# its parts without an eigenproblem): a weight of 1e-3 is a mean-feature distance of ~42 on the 0..255 scale
# (~22 across a full-strength occlusion edge). Most of the cuts' eigenproblem time goes, and the labels move
# less than under one level of input noise (bench/cues/segment_stability.py).
UNLINKED = 1e-3


@dataclasses.dataclass(frozen=True)
class Definition:
    """The choices of a segment cue's steps that its JobSpec parameters do not set: Felzenszwalb's grid
    connectivity (8 or 4) and edge-sort quantisation (levels of the largest edge weight), the normalized cuts'
    eigenvector precision ("float64": dsyevr, "float32": ssyevr) and the link weight below which two regions
    count as unlinked. A change to them is accepted when the new labels agree with the old ones at least as
    well as the old agree with themselves under imperceptible input noise (docs/conventions.md,
    bench/cues/segment_stability.py)."""

    connectivity: int = 8
    sort_levels: int = SORT_LEVELS
    eigenvectors: str = "float32"
    link_eps: float = UNLINKED


DEFINITIONS = {"segment_unsup2d": Definition(), "segment_unsup25d": Definition()}


def superpixels(
    features: np.ndarray, scale: float, sigma: float, min_size: int, max_count: int,
    definition: Definition = Definition(),
) -> np.ndarray:
    """int64 H x W Felzenszwalb labels 0..n-1 with n <= max_count (min_size grown when needed)."""
    # the merge pass does not depend on min_size: done once
    fz = Felzenszwalb(features, scale, sigma, connectivity=definition.connectivity,
                      levels=definition.sort_levels)
    n = fz.count(min_size)  # counted without labelling the pixels: only the last min_size is labelled
    for _ in range(4):
        if n <= max_count:
            break
        min_size = int(np.ceil(min_size * n / max_count * 1.2))
        n = fz.count(min_size)
    return fz.labels(min_size)


def region_graph(labels: np.ndarray, features255: np.ndarray, sigma: float,
                 boundary: np.ndarray | None = None) -> np.ndarray:
    """Dense n x n similarity matrix of 4-adjacent regions (mean-feature RBF), self-loops of weight 1.

    `boundary` (H x W in [0, 1], optional) weakens the link of two regions by exp(-BOUNDARY_GAIN * b), b = the
    mean over their shared pixel pairs of the larger boundary value of the two pixels.
    """
    n = int(labels.max()) + 1
    cnt, sums = _region_sums(np.ascontiguousarray(labels), np.ascontiguousarray(features255), n)
    has_boundary = boundary is not None
    boundary_or_none = np.zeros((1, 1), np.float32) if boundary is None else boundary
    links, boundary_sum = _adjacent_pairs(labels, boundary_or_none, n, has_boundary)
    ea, eb, dist2, strength = _link_terms(links, boundary_sum, cnt, sums)
    w = np.exp(-dist2 / sigma)  # numpy's exp (its own vector code): kept, as every value it rounds
    if has_boundary:
        w = w * np.exp(-BOUNDARY_GAIN * strength)
    return _dense_graph(n, ea, eb, w)


@njit(cache=True, nogil=True)
def _link_terms(links: np.ndarray, boundary_sum: np.ndarray, cnt: np.ndarray,
                sums: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The linked pairs (a < b, increasing a * n + b: np.nonzero's order), the squared distance of their mean
    features (channels added in order from 0, as numpy sums fewer than 8) and their mean boundary value."""
    n, c = sums.shape
    means = np.empty((n, c), np.float64)
    for a in range(n):
        for k in range(c):
            means[a, k] = sums[a, k] / max(cnt[a], 1.0)
    count = 0
    for a in range(n):
        for b in range(n):
            count += links[a, b] != 0
    ea = np.empty(count, np.int64)
    eb = np.empty(count, np.int64)
    dist2 = np.empty(count, np.float64)
    strength = np.empty(count, np.float64)
    e = 0
    for a in range(n):
        for b in range(n):
            if links[a, b] == 0:
                continue
            ea[e], eb[e] = a, b
            s = 0.0
            for k in range(c):
                t = means[a, k] - means[b, k]
                s += t * t
            dist2[e] = s
            strength[e] = boundary_sum[a, b] / links[a, b]
            e += 1
    return ea, eb, dist2, strength


@njit(cache=True, nogil=True)
def _dense_graph(n: int, ea: np.ndarray, eb: np.ndarray, w: np.ndarray) -> np.ndarray:
    """n x n float64: w on the pairs both ways, 1 on the diagonal (self-loops), 0 elsewhere."""
    W = np.zeros((n, n), np.float64)
    for e in range(len(w)):
        W[ea[e], eb[e]] = w[e]
        W[eb[e], ea[e]] = w[e]
    for i in range(n):
        W[i, i] = 1.0
    return W


@njit(cache=True, nogil=True)
def _first_appearance_ranks(labels: np.ndarray, mask: np.ndarray, lookup: np.ndarray) -> np.ndarray:
    """uint16 labels 1..K (capped at 65535) of lookup[labels] in raster order of first appearance inside
    mask, 0 outside (lookup: the segment of each superpixel, read per pixel instead of an image of them)."""
    rank = np.zeros(lookup.max() + 1, np.int64)
    out = np.zeros(labels.shape, np.uint16)
    count = 0
    for i in range(labels.size):
        if mask[i]:
            lab = lookup[labels[i]]
            if rank[lab] == 0:
                count += 1
                rank[lab] = count
            out[i] = min(rank[lab], 65535)
    return out


@njit(cache=True, nogil=True)
def _region_sums(labels: np.ndarray, features: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel count (float64) and per-channel feature sums (float64; at most 4 channels) of every region, in
    one pass: each sum adds in raster order, as numpy's bincount with weights did channel by channel. A run
    of one label along a row adds in registers, stored once at its end (the same additions, without a store
    and reload per pixel); counts add whole runs (integers, exact)."""
    h, w, c = features.shape
    if c > 4:
        raise ValueError("at most 4 feature channels")
    cnt = np.zeros(n, np.float64)
    sums = np.zeros((n, 4), np.float64)
    for y in range(h):
        x = 0
        while x < w:
            lab = labels[y, x]
            s0, s1, s2, s3 = sums[lab, 0], sums[lab, 1], sums[lab, 2], sums[lab, 3]
            start = x
            while x < w and labels[y, x] == lab:
                s0 += np.float64(features[y, x, 0])
                if c > 1:
                    s1 += np.float64(features[y, x, 1])
                if c > 2:
                    s2 += np.float64(features[y, x, 2])
                if c > 3:
                    s3 += np.float64(features[y, x, 3])
                x += 1
            cnt[lab] += x - start
            sums[lab, 0], sums[lab, 1], sums[lab, 2], sums[lab, 3] = s0, s1, s2, s3
    return cnt, sums[:, :c].copy()


@njit(cache=True, nogil=True)
def _adjacent_pairs(labels: np.ndarray, boundary: np.ndarray, n: int,
                    has_boundary: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per region pair (a < b): how many 4-adjacent pixel pairs join them, and the sum over those of the
    larger boundary value of the two pixels; horizontal pairs first, then vertical, each in raster order (the
    float sums add in the order numpy's bincount over the concatenated pairs did)."""
    h, w = labels.shape
    links = np.zeros((n, n), np.int64)
    total = np.zeros((n, n), np.float64)
    for vertical in (False, True):
        for y in range(h - 1 if vertical else h):
            for x in range(w if vertical else w - 1):
                y2, x2 = (y + 1, x) if vertical else (y, x + 1)
                la, lb = labels[y, x], labels[y2, x2]
                if la == lb:
                    continue
                lo, hi = min(la, lb), max(la, lb)
                links[lo, hi] += 1
                if has_boundary:
                    total[lo, hi] += np.float64(max(boundary[y, x], boundary[y2, x2]))
    return links, total


def _relabel(labels: np.ndarray, mask: np.ndarray, lookup: np.ndarray | None = None) -> np.ndarray:
    """uint16 labels 1..K in raster order of first appearance inside mask, 0 outside (labels >= 0); of
    lookup[labels] when lookup is given."""
    if labels.size == 0:
        return np.zeros(labels.shape, dtype=np.uint16)
    flat = np.ascontiguousarray(labels).ravel()
    if lookup is None:
        lookup = np.arange(int(flat.max()) + 1)
    return _first_appearance_ranks(flat, np.ascontiguousarray(mask).ravel(),
                                   np.ascontiguousarray(lookup, dtype=np.int64)).reshape(labels.shape)


@njit(cache=True, nogil=True)
def _uniform_in_mask(features: np.ndarray, mask: np.ndarray) -> bool:
    """Every pixel inside mask has the same feature vector (True when mask is empty); stops at the first
    other."""
    h, w, c = features.shape
    first_y, first_x = -1, -1
    for y in range(h):
        for x in range(w):
            if not mask[y, x]:
                continue
            if first_y < 0:
                first_y, first_x = y, x
                continue
            for k in range(c):
                if features[y, x, k] != features[first_y, first_x, k]:
                    return False
    return True


@njit(cache=True, nogil=True)
def _gather(features: np.ndarray, mask: np.ndarray, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
    """features[iy, ix] (H x W x C) as one compiled pass, where (iy, ix) is each pixel's nearest mask pixel: a
    mask pixel is its own nearest, so only the pixels off the mask are gathered (the rest is one copy)."""
    h, w, c = features.shape
    out = features.copy()
    for y in range(h):
        for x in range(w):
            if not mask[y, x]:
                sy, sx = iy[y, x], ix[y, x]
                for k in range(c):
                    out[y, x, k] = features[sy, sx, k]
    return out


def nearest_in_mask(ctx: ViewContext, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of the nearest mask pixel for every pixel; memoised per mask (both segmentations of a
    view usually share theirs: surface seen = valid depth)."""
    known: dict[bytes, tuple[np.ndarray, np.ndarray]] = ctx.memo("nearest_in_mask", dict)
    key = hashlib.blake2b(np.packbits(mask).tobytes(), digest_size=16).digest()
    if key not in known:
        iy, ix = nearest_site(np.ascontiguousarray(mask, dtype=bool))
        known[key] = (iy, ix)
    return known[key]


def segment(ctx: ViewContext, features: np.ndarray, mask: np.ndarray, *, sigma: float, definition: Definition,
            boundary: np.ndarray | None = None) -> np.ndarray:
    """Felzenszwalb + normalized cuts on an H x W x C feature image in ~[0, 1]; uint16 labels, 0 off mask."""
    p = ctx.params
    if _uniform_in_mask(features, mask):
        # One colour on the whole surface (an untextured scan's rgb): Felzenszwalb merges every zero-weight
        # edge, so one superpixel and one segment (after the background fill below), without building the
        # graph.
        return _relabel(np.zeros(mask.shape, dtype=np.int64), mask)
    if not mask.all():
        # Background pixels take the nearest surface pixel's features, so silhouettes do not spawn thin
        # mixed-colour regions (Felzenszwalb blurs first) and the background merges into its neighbours.
        iy, ix = nearest_in_mask(ctx, mask)
        features = _gather(features, mask, iy, ix)
    superpixel_ids = superpixels(
        features, p.segment2d_scale, sigma, p.segment2d_min_size, p.segment_max_superpixels, definition
    )
    W = region_graph(superpixel_ids, features * 255.0, p.segment_ncut_sigma, boundary)
    merged = normalized_cuts(W, p.segment_ncut_thresh, p.segment_num_cuts, definition.eigenvectors,
                             definition.link_eps)
    return _relabel(superpixel_ids, mask, merged)


@register("segment_unsup2d")
def segment_unsup2d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W colour segmentation labels 1..K, 0 where nothing is seen."""
    rgb = ctx.passes.rgb.astype(np.float32) / 255.0
    return segment(ctx, rgb, hit(ctx), sigma=ctx.params.segment2d_sigma,
                   definition=DEFINITIONS["segment_unsup2d"])


LOG_DEPTH_SCALE = 0.5
BOUNDARY_GAIN = 5.0  # an occlusion boundary at full strength (and weight 1) divides a link by e^5


def features25d(ctx: ViewContext) -> np.ndarray:
    """float32 H x W x 4: weighted [log-depth, normal (3, mapped to [0, 1])].

    Log-depth is 0.5 * ln(metres) relative to the nearest pixel: doubling the depth (0.35) weighs about like
    turning the normal by 40 degrees, so a slanted plane stays one segment while objects at clearly different
    depths separate. The logarithm is numpy's (its float32 log); the rest one compiled pass in float32, the
    arithmetic of the numpy expressions it replaces (tests/worker/cues/test_kernels.py).
    """
    wd, wn, _ = ctx.params.segment25d_weights
    v = valid(ctx)
    log_depth = np.log(np.where(v, depth_m(ctx), np.float32(1.0)))
    return _features25d(log_depth, v, normal_cam(ctx), np.float32(wd), np.float32(wn))


@njit(cache=True, nogil=True)
def _features25d(log_depth: np.ndarray, v: np.ndarray, normals: np.ndarray, wd: np.float32,
                 wn: np.float32) -> np.ndarray:
    """[wd * (LOG_DEPTH_SCALE * log_depth - its minimum over v) (0 off v), wn * (normals + 1) * 0.5],
    float32."""
    h, w = log_depth.shape
    scale, one, half = np.float32(LOG_DEPTH_SCALE), np.float32(1.0), np.float32(0.5)
    lo = np.float32(np.inf)
    for y in range(h):
        for x in range(w):
            if v[y, x]:
                d = scale * log_depth[y, x]
                if d < lo or np.isnan(d):  # np.min's: a NaN wins
                    lo = d
    out = np.empty((h, w, 4), np.float32)
    for y in range(h):
        for x in range(w):
            out[y, x, 0] = wd * (scale * log_depth[y, x] - lo if v[y, x] else np.float32(0.0))
            for k in range(3):
                out[y, x, k + 1] = wn * ((normals[y, x, k] + one) * half)
    return out


@register("segment_unsup25d", passes={"normal"})
def segment_unsup25d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W segmentation of log-depth, normals and occlusion edges: labels 1..K, 0 off valid depth.

    Superpixels come from log-depth and normals without pre-blur (rendered geometry is noise-free; blurring
    would leave strips of averaged normals along creases); occlusion edges (edge_occlusion's response over its
    maximum in the view, times the third weight) weaken the links across them in the normalized-cut graph.
    """
    _, _, we = ctx.params.segment25d_weights
    occ = occlusion_response(ctx)
    boundary = _boundary(occ, np.float32(we), np.float32(max(float(occ.max()), 1e-6)))
    return segment(ctx, features25d(ctx), valid(ctx), sigma=0.0, definition=DEFINITIONS["segment_unsup25d"],
                   boundary=boundary)


@njit(cache=True, nogil=True)
def _boundary(occ: np.ndarray, we: np.float32, top: np.float32) -> np.ndarray:
    """np.clip(we * occ / top, 0, None) in float32 (occ >= 0: no signed zeros or NaNs to order)."""
    out = np.empty_like(occ)
    for y in range(occ.shape[0]):
        for x in range(occ.shape[1]):
            v = we * occ[y, x] / top
            out[y, x] = v if v >= 0 else np.float32(0.0)
    return out
