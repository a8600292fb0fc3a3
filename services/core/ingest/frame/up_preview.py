"""A small side view of a scan under a candidate up (PNG), so a person can tell the floor at a glance.

Frames: the scan in its source frame is rotated so the candidate up is +Z; the picture looks along the
horizontal direction of least extent, so the long side of the room spans the width, up is the top of
the picture and the floor should be the bottom edge. Pixels: surface samples (by area) splatted as a
section: the middle slab across the view in black, the rest in grey; pure numpy and Pillow, no renderer.
"""

from __future__ import annotations

import io

import numpy as np
import trimesh
from PIL import Image

from services.core.ingest.frame.resolve import rotation_to_z

WIDTH, HEIGHT = 240, 150
SAMPLES = 60_000


def side_view_png(mesh: trimesh.Trimesh, up: np.ndarray, seed: int = 0) -> bytes:
    """PNG bytes of the scan seen from the side with `up` (source frame) at the top of the picture."""
    pts, _ = trimesh.sample.sample_surface(mesh, SAMPLES, seed=seed)
    pts = np.asarray(pts) @ rotation_to_z(np.asarray(up, dtype=np.float64)).T
    horiz = pts[:, :2] - pts[:, :2].mean(axis=0)
    _, vecs = np.linalg.eigh(horiz.T @ horiz)
    across, along = horiz @ vecs[:, 1], horiz @ vecs[:, 0]  # width: the longest horizontal direction
    z = pts[:, 2]
    span = max(np.ptp(across) / (WIDTH - 8), np.ptp(z) / (HEIGHT - 8), 1e-12)
    col = ((across - across.min()) / span + 4).astype(int)
    row = (HEIGHT - 5 - (z - z.min()) / span).astype(int)
    # a section: the middle slab of the room in black over the rest in light grey, so the floor reads
    # as a line along the bottom and the walls as lines up the sides
    slab = np.abs(along - np.median(along)) < 0.12 * max(np.ptp(along), 1e-12)
    img = np.full((HEIGHT, WIDTH), 255, dtype=np.uint8)
    img[row[~slab], col[~slab]] = 205
    img[row[slab], col[slab]] = 20
    out = io.BytesIO()
    Image.fromarray(img, mode="L").save(out, format="PNG")
    return out.getvalue()
