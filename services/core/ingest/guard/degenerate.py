"""A cheap refusal of meshes made mostly of degenerate faces, before the full parse (OBJ text).

Ten million faces that each name a vertex twice, or three points on a line, are accepted by every other
check but cost the full parse (tens of seconds, gigabytes) to find that the mesh renders nothing. The OBJ
scan of `mesh_checks` already reads every face line: it keeps an even sample of at most SAMPLE_FACES faces
(the stride doubles as the file grows), and when the file has at least CHECKED_FROM_FACES faces, a second
pass reads only the sample's vertices; a mesh whose sampled faces are more than MAX_DEGENERATE_FRACTION
degenerate (a repeated vertex, or an area below 1e-12 of the squared extent of the sample) is refused. The
same check runs wherever a mesh is loaded (upload, register, plan and generate: `loading.load_space`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.core.ingest.errors import SpaceError

SAMPLE_FACES = 4096
CHECKED_FROM_FACES = 100_000  # smaller meshes parse in a moment: the parse's own zero-area check is enough
MAX_DEGENERATE_FRACTION = 0.9
_RELATIVE_AREA = 1e-12


class FaceSample:
    """An even sample of a file's faces (1-based vertex indices, as resolved), kept while it is read."""

    def __init__(self) -> None:
        self.stride = 1
        self.faces: list[tuple[int, ...]] = []
        self.seen = 0

    def add(self, indices: tuple[int, ...]) -> None:
        if self.seen % self.stride == 0:
            self.faces.append(indices)
            if len(self.faces) >= 2 * SAMPLE_FACES:
                self.faces = self.faces[::2]
                self.stride *= 2
        self.seen += 1


def degenerate_refusal(source: Path, sample: FaceSample) -> None:
    """SpaceError when most sampled faces of a big OBJ are degenerate (module docstring)."""
    if sample.seen < CHECKED_FROM_FACES or not sample.faces:
        return
    tris = [f[:3] for f in sample.faces if len(f) >= 3]
    repeated = sum(1 for f in tris if len(set(f)) < 3)
    needed = {i for f in tris for i in f}
    positions = _vertices(source, needed)
    distinct = [f for f in tris if len(set(f)) == 3 and all(i in positions for i in f)]
    flat = 0
    if distinct:
        p = np.array([[positions[i] for i in f] for f in distinct], dtype=np.float64)
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        extent = float(np.ptp(p.reshape(-1, 3), axis=0).max()) if len(p) else 0.0
        flat = int((area <= _RELATIVE_AREA * max(extent, 1e-300) ** 2).sum())
    fraction = (repeated + flat) / max(len(tris), 1)
    if fraction > MAX_DEGENERATE_FRACTION:
        raise SpaceError(
            f"{source.name}: {fraction:.0%} of {len(tris):,} sampled faces (of {sample.seen:,}) "
            "are degenerate "
            "(a repeated vertex or no area): the mesh would render nothing; refusing it before parsing"
        )


def _vertices(source: Path, needed: set[int]) -> dict[int, tuple[float, float, float]]:
    """The positions of the 1-based vertex indices `needed` (one pass up to the last, parsing only those
    lines)."""
    found: dict[int, tuple[float, float, float]] = {}
    n, last = 0, max(needed, default=0)
    with open(source, "rb") as f:
        for line in f:
            if n >= last:
                break
            if line[:2] in (b"v ", b"v\t"):
                n += 1
                if n in needed:
                    try:
                        x, y, z = (float(t) for t in line.split()[1:4])
                    except ValueError:
                        continue
                    found[n] = (x, y, z)
    return found
