"""Unsupervised segmentations (16-bit label PNGs): Felzenszwalb superpixels merged by normalized cuts.

segment_unsup2d works on the colour image, segment_unsup25d on a feature image of weighted log-depth and normals
with occlusion edges weakening the graph's links (segment25d_weights; see segment_unsup25d). Steps:
1. skimage.segmentation.felzenszwalb(features in ~[0, 1], segment2d_scale, segment2d_sigma, segment2d_min_size);
   when it yields more than segment_max_superpixels regions it is rerun with a proportionally larger min_size,
   which bounds the cost of step 3 (a dense eigenproblem per split);
2. region adjacency graph (4-connectivity) with similarity weights exp(-|mean_a - mean_b|^2 / segment_ncut_sigma)
   of the regions' mean features on a 0..255 scale (2.5d: times exp(-5 * occlusion strength along the shared
   boundary)), plus self-loops of weight 1 (as skimage.graph.cut_normalized);
3. recursive two-way normalized cuts (Shi & Malik 2000) exactly as skimage.graph.cut_normalized: the second
   smallest eigenvector of D^-1/2 (D - W) D^-1/2, segment_num_cuts thresholds, split while the best ncut value
   is below segment_ncut_thresh. Written here on dense matrices (scipy.linalg.eigh, two eigenpairs) because
   skimage's sparse/networkx version takes seconds per image;
4. labels 1..K numbered in raster order of first appearance; 0 = no surface (2d: nothing seen; 2.5d: no valid
   depth). Pixels off the surface take the nearest surface pixel's features before step 1, so the background
   neither forms segments nor leaves halo regions along silhouettes.
"""

from __future__ import annotations

import functools
import hashlib

import numpy as np
from numba import njit
from scipy.linalg.lapack import _compute_lwork, get_lapack_funcs

from services.worker.context import ViewContext
from services.worker.cues.common import depth_m, hit, normal_cam, valid
from services.worker.cues.edges import occlusion_response
from services.worker.cues.feature_transform import nearest_site
from services.worker.cues.felzenszwalb import Felzenszwalb
from services.worker.cues.registry import register


def superpixels(features: np.ndarray, scale: float, sigma: float, min_size: int, max_count: int) -> np.ndarray:
    """int64 H x W Felzenszwalb labels 0..n-1 with n <= max_count (min_size grown when needed)."""
    fz = Felzenszwalb(features, scale, sigma)  # the merge pass does not depend on min_size: done once
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

    `boundary` (H x W in [0, 1], optional) weakens the link of two regions by exp(-BOUNDARY_GAIN * b), b = the mean
    over their shared pixel pairs of the larger boundary value of the two pixels.
    """
    n = int(labels.max()) + 1
    cnt, sums = _region_sums(np.ascontiguousarray(labels), np.ascontiguousarray(features255), n)
    means = sums / np.maximum(cnt, 1)[:, None]
    has_boundary = boundary is not None
    boundary_or_none = np.zeros((1, 1), np.float32) if boundary is None else boundary
    links, boundary_sum = _adjacent_pairs(labels, boundary_or_none, n, has_boundary)
    ea, eb = np.nonzero(links)  # row-major: pairs (a < b) in increasing a * n + b
    w = np.exp(-((means[ea] - means[eb]) ** 2).sum(axis=1) / sigma)
    if has_boundary:
        strength = boundary_sum[ea, eb] / links[ea, eb]
        w = w * np.exp(-BOUNDARY_GAIN * strength)
    W = np.zeros((n, n), dtype=np.float64)
    W[ea, eb] = w
    W[eb, ea] = w
    np.fill_diagonal(W, 1.0)
    return W


# Links weaker than this count as absent when looking for disconnected parts (self-loops weigh 1; an RBF weight
# this small is exp(-23)): a cut through them costs < 1e-9, far below any useful segment_ncut_thresh.
LINK_EPS = 1e-10


@njit(cache=True, nogil=True)
def _components(w: np.ndarray, eps: float) -> tuple[int, np.ndarray]:
    """Connected components of the graph whose links are the entries of w above eps: (count, id per node)."""
    n = len(w)
    part = np.full(n, -1, np.int64)
    stack = np.empty(n, np.int64)
    count = 0
    for seed in range(n):
        if part[seed] >= 0:
            continue
        part[seed] = count
        stack[0] = seed
        top = 1
        while top:
            top -= 1
            i = stack[top]
            for j in range(n):
                if part[j] < 0 and w[i, j] > eps:
                    part[j] = count
                    stack[top] = j
                    top += 1
        count += 1
    return count, part


@njit(cache=True, nogil=True)
def _first_appearance_ranks(labels: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """uint16 labels 1..K (capped at 65535) in raster order of first appearance inside mask, 0 outside."""
    rank = np.zeros(labels.max() + 1, np.int64)
    out = np.zeros(labels.shape, np.uint16)
    count = 0
    for i in range(labels.size):
        if mask[i]:
            lab = labels[i]
            if rank[lab] == 0:
                count += 1
                rank[lab] = count
            out[i] = min(rank[lab], 65535)
    return out


@njit(cache=True, nogil=True)
def _region_sums(labels: np.ndarray, features: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel count (float64) and per-channel feature sums (float64) of every region, in one pass: each sum adds
    in raster order, as numpy's bincount with weights did channel by channel."""
    h, w, c = features.shape
    cnt = np.zeros(n, np.float64)
    sums = np.zeros((n, c), np.float64)
    for y in range(h):
        for x in range(w):
            lab = labels[y, x]
            cnt[lab] += 1.0
            for k in range(c):
                sums[lab, k] += np.float64(features[y, x, k])
    return cnt, sums


@njit(cache=True, nogil=True)
def _adjacent_pairs(labels: np.ndarray, boundary: np.ndarray, n: int,
                    has_boundary: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per region pair (a < b): how many 4-adjacent pixel pairs join them, and the sum over those of the larger
    boundary value of the two pixels; horizontal pairs first, then vertical, each in raster order (the float sums
    add in the order numpy's bincount over the concatenated pairs did)."""
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


def normalized_cuts(W: np.ndarray, thresh: float, num_cuts: int) -> np.ndarray:
    """Recursive two-way normalized cuts on a dense similarity matrix; returns a segment id per node.

    A subgraph falling apart into (numerically) disconnected parts is split into them directly: its eigenproblem
    then has a multiple zero eigenvalue, so the dense solver (O(n^3), most of a segmentation's cost at 512 px)
    would only return some mix of the parts' indicator vectors, and every threshold between them cuts at ~0 cost:
    the cuts end at the same parts, peeled off one eigenproblem at a time."""
    out = np.zeros(len(W), dtype=np.int64)
    next_id = 0
    stack = [np.arange(len(W))]
    while stack:
        idx = stack.pop()
        best_mask = None
        if len(idx) > 2:
            w = W[np.ix_(idx, idx)]
            n_parts, part = _components(w, LINK_EPS)
            if n_parts > 1:
                stack.extend(idx[part == k] for k in range(n_parts))
                continue
            best_mask = _best_split(w, thresh, num_cuts)
        if best_mask is None:
            out[idx] = next_id
            next_id += 1
        else:
            stack.append(idx[~best_mask])
            stack.append(idx[best_mask])
    return out


_SYEVR, _SYEVR_LWORK = get_lapack_funcs(("syevr", "syevr_lwork"), dtype=np.float64)


@functools.lru_cache(maxsize=4096)
def _syevr_work(n: int) -> tuple[int, int]:
    """LAPACK's workspace sizes for dsyevr of an n x n matrix, as scipy.linalg.eigh asks for them."""
    lwork, liwork = _compute_lwork(_SYEVR_LWORK, n=n, lower=True)
    return int(lwork), int(liwork)


def second_eigenvector(A: np.ndarray) -> np.ndarray:
    """The eigenvector of the second smallest eigenvalue of a symmetric matrix: the dsyevr call of
    scipy.linalg.eigh(A, subset_by_index=[0, 1], driver="evr"), same arguments and workspace, bit for bit, without
    its checks and workspace query per call (a normalized cut makes ~100 such calls per view)."""
    lwork, liwork = _syevr_work(len(A))
    _, vecs, _, _, info = _SYEVR(A, compute_v=1, range="I", il=1, iu=2, lower=True, lwork=lwork, liwork=liwork)
    if info != 0:
        raise np.linalg.LinAlgError(f"dsyevr failed (info {info})")
    return vecs[:, 1]


def _best_split(w: np.ndarray, thresh: float, num_cuts: int) -> np.ndarray | None:
    """The two-way normalized cut of a connected similarity matrix (a node mask), None when none is below thresh."""
    d = w.sum(axis=1)
    dis = 1.0 / np.sqrt(d)
    A = (np.diag(d) - w) * dis[:, None] * dis[None, :]
    ev = second_eigenvector(A) * dis
    # All thresholds at once: row t of `masks` is one candidate split, cut_t = m_t^T w (1 - m_t).
    masks = ev[None, :] > np.linspace(ev.min(), ev.max(), num_cuts, endpoint=False)[:, None]
    m = masks.astype(np.float64)
    cut = ((m @ w) * (1.0 - m)).sum(axis=1)
    assoc = m @ d
    proper = masks.any(axis=1) & ~masks.all(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cost = np.where(proper, cut / assoc + cut / (d.sum() - assoc), np.inf)
    best = int(np.argmin(cost))  # the first of equal minima, as the loop over thresholds took
    return masks[best] if cost[best] < thresh else None


def _relabel(labels: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """uint16 labels 1..K in raster order of first appearance inside mask, 0 outside (labels >= 0)."""
    if labels.size == 0:
        return np.zeros(labels.shape, dtype=np.uint16)
    flat = _first_appearance_ranks(np.ascontiguousarray(labels).ravel(), np.ascontiguousarray(mask).ravel())
    return flat.reshape(labels.shape)


@njit(cache=True, nogil=True)
def _uniform_in_mask(features: np.ndarray, mask: np.ndarray) -> bool:
    """Every pixel inside mask has the same feature vector (True when mask is empty); stops at the first other."""
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
def _gather(features: np.ndarray, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
    """features[iy, ix] (H x W x C) as one compiled pass."""
    h, w, c = features.shape
    out = np.empty_like(features)
    for y in range(h):
        for x in range(w):
            for k in range(c):
                out[y, x, k] = features[iy[y, x], ix[y, x], k]
    return out


def nearest_in_mask(ctx: ViewContext, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of the nearest mask pixel for every pixel; memoised per mask (both segmentations of a view
    usually share theirs: surface seen = valid depth)."""
    known: dict[bytes, tuple[np.ndarray, np.ndarray]] = ctx.memo("nearest_in_mask", dict)
    key = hashlib.blake2b(np.packbits(mask).tobytes(), digest_size=16).digest()
    if key not in known:
        iy, ix = nearest_site(np.ascontiguousarray(mask, dtype=bool))
        known[key] = (iy, ix)
    return known[key]


def segment(ctx: ViewContext, features: np.ndarray, mask: np.ndarray, *, sigma: float,
            boundary: np.ndarray | None = None) -> np.ndarray:
    """Felzenszwalb + normalized cuts on an H x W x C feature image in ~[0, 1]; uint16 labels, 0 off mask."""
    p = ctx.params
    if _uniform_in_mask(features, mask):
        # One colour on the whole surface (an untextured scan's rgb): Felzenszwalb merges every zero-weight edge,
        # so one superpixel and one segment (after the background fill below), without building the graph.
        return _relabel(np.zeros(mask.shape, dtype=np.int64), mask)
    if not mask.all():
        # Background pixels take the nearest surface pixel's features, so silhouettes do not spawn thin
        # mixed-colour regions (Felzenszwalb blurs first) and the background merges into its neighbours.
        iy, ix = nearest_in_mask(ctx, mask)
        features = _gather(features, iy, ix)
    superpixel_ids = superpixels(features, p.segment2d_scale, sigma, p.segment2d_min_size, p.segment_max_superpixels)
    W = region_graph(superpixel_ids, features * 255.0, p.segment_ncut_sigma, boundary)
    merged = normalized_cuts(W, p.segment_ncut_thresh, p.segment_num_cuts)[superpixel_ids]
    return _relabel(merged, mask)


@register("segment_unsup2d")
def segment_unsup2d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W colour segmentation labels 1..K, 0 where nothing is seen."""
    rgb = ctx.passes.rgb.astype(np.float32) / 255.0
    return segment(ctx, rgb, hit(ctx), sigma=ctx.params.segment2d_sigma)


LOG_DEPTH_SCALE = 0.5
BOUNDARY_GAIN = 5.0  # an occlusion boundary at full strength (and weight 1) divides a link by e^5


def features25d(ctx: ViewContext) -> np.ndarray:
    """float32 H x W x 4: weighted [log-depth, normal (3, mapped to [0, 1])].

    Log-depth is 0.5 * ln(metres) relative to the nearest pixel: doubling the depth (0.35) weighs about like
    turning the normal by 40 degrees, so a slanted plane stays one segment while objects at clearly different
    depths separate.
    """
    wd, wn, _ = ctx.params.segment25d_weights
    v = valid(ctx)
    logd = LOG_DEPTH_SCALE * np.log(np.where(v, depth_m(ctx), 1.0))
    if v.any():
        logd = logd - float(logd[v].min())
    logd = np.where(v, logd, 0.0)
    n = (normal_cam(ctx) + 1.0) * 0.5
    return np.concatenate([wd * logd[..., None], wn * n], axis=-1).astype(np.float32)


@register("segment_unsup25d", passes={"normal"})
def segment_unsup25d(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W segmentation of log-depth, normals and occlusion edges: labels 1..K, 0 off valid depth.

    Superpixels come from log-depth and normals without pre-blur (rendered geometry is noise-free; blurring would
    leave strips of averaged normals along creases); occlusion edges (edge_occlusion's response over its maximum
    in the view, times the third weight) weaken the links across them in the normalized-cut graph.
    """
    _, _, we = ctx.params.segment25d_weights
    occ = occlusion_response(ctx)
    boundary = np.clip(we * occ / max(float(occ.max()), 1e-6), 0.0, None)
    return segment(ctx, features25d(ctx), valid(ctx), sigma=0.0, boundary=boundary)
