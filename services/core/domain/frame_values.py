"""The values that place a scan in the world frame, checked: its unit scale and a given source_to_world."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

MAX_UNIT_SCALE = 1000.0
UP_AXES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")


def parse_unit_scale(v: object, *, numbers_as_text: bool = False) -> float | str:
    """'auto' or metres per source unit in (0, MAX_UNIT_SCALE]; ValueError naming unit_scale otherwise.

    `numbers_as_text`: form fields carry numbers as text; JSON and specs must send a number.
    """
    if v == "auto":
        return "auto"
    if isinstance(v, str) and not numbers_as_text:
        raise ValueError(
            f"unit_scale must be 'auto' or a number of metres per source unit, not the string {v[:40]!r}"
        )
    try:
        x = float(v) if isinstance(v, int | float | str) and not isinstance(v, bool) else math.nan
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and 0 < x <= MAX_UNIT_SCALE):
        raise ValueError(f"unit_scale must be 'auto' or a number of metres per source unit greater than 0 "
                         f"and at most {MAX_UNIT_SCALE:g}, got {v!r}")
    return x


def similarity_scale(matrix: ArrayLike) -> float:
    """The uniform scale of a 4x4 rotation + uniform scale + translation; ValueError saying what is wrong."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"source_to_world must be a finite 4x4 matrix, got shape {list(m.shape)}")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(
            f"source_to_world: the last row must be [0, 0, 0, 1], got {m[3].tolist()} (no projection)"
        )
    sv = np.linalg.svd(m[:3, :3], compute_uv=False)
    if sv[-1] <= 1e-12 * max(sv[0], 1e-300):
        raise ValueError("source_to_world is degenerate: its 3x3 part is singular (it flattens the scan)")
    if sv[0] - sv[-1] > 1e-4 * sv[0]:
        raise ValueError(
            f"source_to_world must be a rotation times a uniform scale (rigid); its 3x3 part scales axes by "
            f"{', '.join(f'{x:.6g}' for x in sv)} (shear or non-uniform scale)"
        )
    if np.linalg.det(m[:3, :3]) < 0:
        raise ValueError("source_to_world mirrors the scan (negative determinant): use a proper rotation")
    scale = float(np.cbrt(np.linalg.det(m[:3, :3])))
    if not 1e-6 <= scale <= 1000:
        raise ValueError(f"source_to_world scales by {scale:.4g} metres per unit, outside [1e-6, 1000]")
    return scale
