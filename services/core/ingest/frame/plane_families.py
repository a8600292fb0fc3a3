"""The dominant plane orientations of a scan, whatever its orientation (step 1 of
services.core.ingest.frame.gravity): face normals are folded onto a hemisphere (a normal and its opposite
belong to the same family: floors and ceilings, opposite walls) and binned on a Fibonacci grid
(`direction_bins`), weighted by face area. The strongest bin is refined by mean shift over all faces within a
shrinking cone (10 then 5 degrees), its neighbourhood (25 degrees) is suppressed and the next one is taken.

Frames: the source frame; directions are unit 3-vectors.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.core.ingest.frame.direction_bins import BINS, N_BINS, bin_neighbours, bin_tree

_SAMPLE_FACES = 50_000  # faces (drawn by area) that vote for bins; refinement uses every face
_SUPPRESS_COS = float(np.cos(np.radians(25.0)))
_MAX_FAMILIES = 6
_MIN_FAMILY_SHARE = 0.03


def _mean_shift(axis: np.ndarray, normals: np.ndarray, areas: np.ndarray) -> np.ndarray:
    for cone in (10.0, 10.0, 5.0, 5.0):
        d = normals @ axis
        sel = np.abs(d) > np.cos(np.radians(cone))
        if not sel.any():
            break
        mean = (normals[sel] * (areas[sel] * np.sign(d[sel]))[:, None]).sum(axis=0)
        norm = np.linalg.norm(mean)
        if norm == 0:
            break
        axis = mean / norm
    return axis


def plane_families(normals: np.ndarray, areas: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Dominant plane orientations (unit axis, area within 10 degrees), strongest first."""
    total = float(areas.sum())
    if total <= 0:
        return []
    if len(areas) > _SAMPLE_FACES:  # a fixed draw: the same mesh gives the same families
        rng = np.random.default_rng(0)
        pick = rng.choice(len(areas), size=_SAMPLE_FACES, p=areas / total)
        votes_n, votes_w = normals[pick], np.full(_SAMPLE_FACES, total / _SAMPLE_FACES)
    else:
        votes_n, votes_w = normals, areas
    _, nearest = bin_tree().query(votes_n)
    hist = np.bincount(nearest % N_BINS, weights=votes_w, minlength=N_BINS)
    score = bin_neighbours() @ hist
    families: list[tuple[np.ndarray, float]] = []
    for _ in range(_MAX_FAMILIES):
        b = int(np.argmax(score))
        if score[b] < _MIN_FAMILY_SHARE * total:
            break
        axis = _mean_shift(BINS[b], normals, areas)
        area = float(areas[np.abs(normals @ axis) > np.cos(np.radians(10.0))].sum())
        if all(abs(float(axis @ f)) < _SUPPRESS_COS for f, _ in families):
            families.append((axis, area))
        score[np.abs(BINS @ axis) > _SUPPRESS_COS] = 0.0
        score[b] = 0.0
    families.sort(key=lambda fa: -fa[1])
    return families


def with_axes(families: list[tuple[np.ndarray, float]], axes: Sequence[np.ndarray]
              ) -> list[tuple[np.ndarray, float]]:
    """`families` and, after them, each of `axes` no family already holds (within the suppression cone)."""
    out = list(families)
    for axis in axes:
        if all(abs(float(axis @ f)) < _SUPPRESS_COS for f, _ in out):
            out.append((axis, 0.0))
    return out
