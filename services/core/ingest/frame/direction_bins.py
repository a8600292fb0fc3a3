"""Directions binned on the hemisphere, antipodes folded: the histogram the levelling
(services.core.ingest.frame.gravity) votes plane orientations into, smoothed over neighbouring bins."""

from __future__ import annotations

import functools

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

N_BINS = 2000  # Fibonacci bins on the hemisphere (about 2.6 degrees apart)
NEIGHBOUR_COS = float(np.cos(np.radians(6.0)))  # bins this close smooth each other's votes


def _fibonacci_hemisphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = i / n  # upper hemisphere, z in (0, 1]
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


BINS = _fibonacci_hemisphere(N_BINS)


@functools.cache
def bin_tree() -> cKDTree:
    """Nearest bin of a normal: a tree over the bins and their antipodes (index modulo the bin count)."""
    return cKDTree(np.vstack([BINS, -BINS]))


@functools.cache
def bin_neighbours() -> sparse.csr_matrix:
    """Bins within 6 degrees of each other (antipodes folded): smooths the histogram into peaks. The pairs
    come from the bin tree (unit vectors: a.b > c exactly when |a - b| < sqrt(2 - 2c)) and are then tested as
    defined; the dense 2000 x 2000 product this replaces was 0.16 CPU-s of every generate's start-up."""
    near = bin_tree().query_ball_point(BINS, np.sqrt(2.0 - 2.0 * NEIGHBOUR_COS) * (1.0 + 1e-6))
    rows = np.repeat(np.arange(N_BINS), [len(n) for n in near])
    cols = np.concatenate([np.asarray(n, dtype=np.int64) for n in near]) % N_BINS
    keep = np.abs((BINS[rows] * BINS[cols]).sum(axis=1)) > NEIGHBOUR_COS
    rows, cols = rows[keep], cols[keep]
    # each row's columns ascending, as a dense matrix's conversion gives them
    order = np.lexsort((cols, rows))
    return sparse.csr_matrix((np.ones(len(order)), (rows[order], cols[order])), shape=(N_BINS, N_BINS))
