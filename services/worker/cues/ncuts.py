"""Recursive two-way normalized cuts (Shi & Malik 2000) on a dense similarity matrix, as
skimage.graph.cut_normalized: the second smallest eigenvector of D^-1/2 (D - W) D^-1/2 (LAPACK ?syevr, two
eigenpairs, in the precision the caller names), num_cuts thresholds between its extremes, split while the best
ncut value is below thresh; the segment cues' step 3 (segmentation.py).

Per split, compiled steps around the two library calls whose rounding the labels depend on (LAPACK's
eigenvector, BLAS's products of the threshold masks with the matrix), with the arithmetic of the numpy
expressions they replaced in the same order: sums are numpy's pairwise sums
(tests/worker/cues/test_kernels.py, test_segment_kernels.py, against tests/fixtures/reference_ncuts.py).
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit
from scipy.linalg.lapack import _compute_lwork, get_lapack_funcs

# Links weaker than this count as absent when looking for disconnected parts (self-loops weigh 1; an RBF
# weight this small is exp(-23)): a cut through them costs < 1e-9, far below any useful segment_ncut_thresh.
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


def normalized_cuts(W: np.ndarray, thresh: float, num_cuts: int, precision: str = "float64",
                    link_eps: float = LINK_EPS) -> np.ndarray:
    """Recursive two-way normalized cuts on a dense similarity matrix; returns a segment id per node.
    `precision`: of the eigenvectors (second_eigenvector); links weaker than `link_eps` count as absent.

    A subgraph falling apart into (numerically) disconnected parts is split into them directly: its
    eigenproblem then has a multiple zero eigenvalue, so the dense solver (O(n^3), most of a segmentation's
    cost at 512 px) would only return some mix of the parts' indicator vectors, and every threshold between
    them cuts at ~0 cost: the cuts end at the same parts, peeled off one eigenproblem at a time.

    Each split is three compiled steps around the two library calls whose rounding the labels depend on
    (LAPACK's eigenvector, BLAS's products of the threshold masks with the matrix): the same arithmetic, in
    the same order, as the numpy expressions they replace (sums pairwise as numpy's;
    tests/worker/cues/test_kernels.py)."""
    W = np.ascontiguousarray(W, dtype=np.float64)
    out = np.zeros(len(W), dtype=np.int64)
    next_id = 0
    stack = [np.arange(len(W))]
    while stack:
        idx = stack.pop()
        best_mask = None
        if len(idx) > 2:
            w, n_parts, part = _subgraph(W, idx, link_eps)
            if n_parts > 1:
                stack.extend(idx[part == k] for k in range(n_parts))
                continue
            best_mask = _best_split(w, thresh, num_cuts, precision)
        if best_mask is None:
            out[idx] = next_id
            next_id += 1
        else:
            stack.append(idx[~best_mask])
            stack.append(idx[best_mask])
    return out


@njit(cache=True, nogil=True)
def _subgraph(W: np.ndarray, idx: np.ndarray, eps: float) -> tuple[np.ndarray, int, np.ndarray]:
    """W[np.ix_(idx, idx)] and its connected components (_components)."""
    n = len(idx)
    w = np.empty((n, n), np.float64)
    for i in range(n):
        for j in range(n):
            w[i, j] = W[idx[i], idx[j]]
    n_parts, part = _components(w, eps)
    return w, n_parts, part


PAIRWISE_BLOCK = 128  # numpy's PW_BLOCKSIZE


@njit(cache=True, nogil=True)
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's pairwise_sum of a[lo:lo + n] for n <= PAIRWISE_BLOCK: a plain loop below 8, else 8 running sums
    added as a tree, then the remainder."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def _pairwise_run(a: np.ndarray, start: int, n: int) -> float:
    """numpy's pairwise_sum of a[start:start + n]: blocks of up to 128 summed by _block_sum, longer runs
    halved at a multiple of 8 and added left + right; on an explicit stack (numba's cache does not take
    recursion)."""
    if n <= PAIRWISE_BLOCK:
        return _block_sum(a, start, n)
    depth = 2 * 64
    f_lo = np.empty(depth, np.int64)  # frames: run start, length, stage (0 new, 1 left pushed, 2 both pushed)
    f_n = np.empty(depth, np.int64)
    f_stage = np.empty(depth, np.int64)
    vals = np.empty(depth, np.float64)  # sums of finished runs, left before right
    f_lo[0], f_n[0], f_stage[0] = start, n, 0
    top, nv = 1, 0
    while top:
        f = top - 1
        lo, m = f_lo[f], f_n[f]
        if m <= PAIRWISE_BLOCK:
            vals[nv] = _block_sum(a, lo, m)
            nv += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if f_stage[f] == 0:
            f_stage[f] = 1
            f_lo[top], f_n[top], f_stage[top] = lo, half, 0
            top += 1
        elif f_stage[f] == 1:
            f_stage[f] = 2
            f_lo[top], f_n[top], f_stage[top] = lo + half, m - half, 0
            top += 1
        else:
            nv -= 1
            vals[nv - 1] = vals[nv - 1] + vals[nv]
            top -= 1
    return vals[0]


REDUCE_BUFFER = 8192  # numpy's default ufunc buffer: add.reduce sums a longer axis in runs of this many


@njit(cache=True, nogil=True)
def _pairwise_sum(a: np.ndarray) -> float:
    """a.sum() of a contiguous float64 vector bit for bit: 0.0 (add's identity, the reduction's start) plus
    the pairwise sums (numpy's pairwise_sum, which its add.reduce uses) of its runs of REDUCE_BUFFER, in
    order."""
    n = len(a)
    res = 0.0
    for start in range(0, n, REDUCE_BUFFER):
        res += _pairwise_run(a, start, min(REDUCE_BUFFER, n - start))
    return res


@njit(cache=True, nogil=True)
def _laplacian(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Degrees d = w.sum(axis=1), dis = 1 / sqrt(d) and A = (diag(d) - w) * dis[:, None] * dis[None, :]."""
    n = len(w)
    d = np.empty(n, np.float64)
    for i in range(n):
        d[i] = _pairwise_sum(w[i])
    dis = 1.0 / np.sqrt(d)
    A = np.empty((n, n), np.float64)
    for i in range(n):
        for j in range(n):
            a = (d[i] if i == j else 0.0) - w[i, j]
            A[i, j] = (a * dis[i]) * dis[j]
    return d, dis, A


@njit(cache=True, nogil=True)
def _threshold_masks(vec: np.ndarray, dis: np.ndarray, num_cuts: int) -> tuple[np.ndarray, np.ndarray]:
    """ev = vec * dis cut at np.linspace(ev.min(), ev.max(), num_cuts, endpoint=False): the masks (ev > t, one
    row per threshold) as bool and as float64."""
    n = len(vec)
    ev = vec * dis
    lo, hi = ev.min(), ev.max()
    delta = hi - lo
    step = delta / num_cuts
    masks = np.empty((num_cuts, n), np.bool_)
    m = np.empty((num_cuts, n), np.float64)
    for t in range(num_cuts):
        # linspace's arithmetic: i * step + start, or (i / div) * delta + start when the step is 0
        th = (t * step if step != 0 else (t / num_cuts) * delta) + lo
        for j in range(n):
            masks[t, j] = ev[j] > th
            m[t, j] = 1.0 if masks[t, j] else 0.0
    return masks, m


@njit(cache=True, nogil=True)
def _cheapest_cut(masks: np.ndarray, m: np.ndarray, mw: np.ndarray, assoc: np.ndarray, d: np.ndarray,
                  thresh: float) -> int:
    """Row of the cheapest proper split below thresh (-1 when none): cost_t = cut / assoc + cut / (d.sum() -
    assoc), cut_t = ((m @ w) * (1 - m)).sum(axis=1)[t], the first of equal minima (np.argmin's, a NaN first of
    all)."""
    rows, n = m.shape
    total = _pairwise_sum(d)
    row = np.empty(n, np.float64)
    best, best_cost = -1, np.inf
    for t in range(rows):
        for j in range(n):
            row[j] = mw[t, j] * (1.0 - m[t, j])
        cut = _pairwise_sum(row)
        some, every = False, True
        for j in range(n):
            some |= masks[t, j]
            every &= masks[t, j]
        cost = cut / assoc[t] + cut / (total - assoc[t]) if some and not every else np.inf
        if best < 0 or cost < best_cost or (np.isnan(cost) and not np.isnan(best_cost)):
            best, best_cost = t, cost
    return best if best_cost < thresh else -1


# eigenvector precision -> LAPACK's ?syevr and its workspace query
_SYEVR = {
    name: get_lapack_funcs(("syevr", "syevr_lwork"), dtype=np.dtype(name)) for name in ("float64", "float32")
}


@functools.lru_cache(maxsize=4096)
def _syevr_work(n: int, precision: str) -> tuple[int, int]:
    """LAPACK's workspace sizes for ?syevr of an n x n matrix, as scipy.linalg.eigh asks for them."""
    lwork, liwork = _compute_lwork(_SYEVR[precision][1], n=n, lower=True)
    return int(lwork), int(liwork)


def second_eigenvector(A: np.ndarray, precision: str = "float64") -> np.ndarray:
    """The eigenvector (float64) of the second smallest eigenvalue of a symmetric matrix: the ?syevr call of
    scipy.linalg.eigh(A.astype(precision), subset_by_index=[0, 1], driver="evr"), same arguments and
    workspace, bit for bit, without its checks and workspace query per call (a normalized cut makes ~100 such
    calls per view). float32 (ssyevr) halves the tridiagonal reduction's cost; its labels are the float64
    ones within the segment cues' equivalence bound (bench/cues/segment_stability.py)."""
    syevr = _SYEVR[precision][0]
    lwork, liwork = _syevr_work(len(A), precision)
    _, vecs, _, _, info = syevr(
        A.astype(precision, copy=False), compute_v=1, range="I", il=1, iu=2, lower=True, lwork=lwork,
        liwork=liwork,
    )
    if info != 0:
        raise np.linalg.LinAlgError(f"?syevr failed (info {info})")
    return vecs[:, 1].astype(np.float64, copy=False)


def _best_split(w: np.ndarray, thresh: float, num_cuts: int, precision: str = "float64") -> np.ndarray | None:
    """The two-way normalized cut of a connected similarity matrix (a node mask), None when none is below
    thresh.

    Every threshold at once: row t of the masks is one candidate split, cut_t = m_t^T w (1 - m_t); the
    products with w stay numpy's (BLAS) calls, whose summation order the costs, hence the choice, depend
    on."""
    d, dis, A = _laplacian(w)
    masks, m = _threshold_masks(second_eigenvector(A, precision), dis, num_cuts)
    best = _cheapest_cut(masks, m, m @ w, m @ d, d, thresh)
    return masks[best] if best >= 0 else None
