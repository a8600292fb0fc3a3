"""keypoints2d's determinant-of-Hessian response as implemented before issue 10's second pass (Gaussian kernels
to scipy's default 4 sigmas, separate temporaries), kept only as the reference of the equivalence tests
(test_cue_equivalence.py). Not used by the service.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter


def doh_response(g: np.ndarray, sigmas: tuple[float, ...]) -> np.ndarray:
    """float32 H x W max over scales of the scale-normalised determinant of Hessian (>= 0)."""
    out = np.zeros(g.shape, dtype=np.float32)
    L, prev = g.astype(np.float32), 0.0
    for s in sorted(sigmas):
        inc = float(np.sqrt(max(s * s - prev * prev, 0.0)))
        if inc > 0:
            L = gaussian_filter(L, inc, mode="nearest")
        prev = s
        P = np.pad(L, 1, mode="edge")
        lxx = P[1:-1, 2:] - 2 * L + P[1:-1, :-2]
        lyy = P[2:, 1:-1] - 2 * L + P[:-2, 1:-1]
        lxy = (P[2:, 2:] - P[2:, :-2] - P[:-2, 2:] + P[:-2, :-2]) * 0.25
        np.maximum(out, (s**4) * (lxx * lyy - lxy * lxy), out=out)
    return out
