"""A PNG sheet of steering distributions: one panel per histogram (several series overlaid on the same bins)
and a top-down view of cameras and points. Drawn with Pillow (matplotlib is not a dependency)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from services.core.domain.steering import Histogram

PANEL = (360, 230)
MARGIN = 30
COLUMNS = 3
COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189)]
TopDown = Mapping[str, tuple[np.ndarray, np.ndarray]]  # label -> (camera xy (n, 2), point xy (m, 2)), metres


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def _histogram_panel(draw: ImageDraw.ImageDraw, box: tuple[int, int], name: str,
                     series: Mapping[str, Histogram]) -> None:
    """Each series as a step line of its share per bin (so series of different sizes compare)."""
    x0, y0 = box
    w, h = PANEL[0] - 2 * MARGIN, PANEL[1] - 2 * MARGIN
    left, top = x0 + MARGIN, y0 + MARGIN
    draw.rectangle([left, top, left + w, top + h], outline=(120, 120, 120))
    draw.text((left, y0 + 8), name, fill=(0, 0, 0))
    shares = {k: np.asarray(s["counts"], float) / max(1.0, float(np.sum(s["counts"])))
              for k, s in series.items()}
    peak = max((float(v.max()) for v in shares.values() if len(v)), default=0.0) or 1.0
    for i, (label, share) in enumerate(shares.items()):
        colour = COLOURS[i % len(COLOURS)]
        n = len(share)
        pts: list[tuple[float, float]] = []
        for b, v in enumerate(share):
            y = top + h - h * v / peak
            pts += [(left + w * b / n, y), (left + w * (b + 1) / n, y)]
        if pts:
            draw.line(pts, fill=colour, width=2)
        draw.text((left + w - 110, top + 4 + 12 * i), f"{label} (n={int(sum(series[label]['counts']))})",
                  fill=colour)
    edges = next(iter(series.values()))["edges"]
    for t, x in ((0.0, edges[0]), (0.5, (edges[0] + edges[-1]) / 2), (1.0, edges[-1])):
        draw.text((left + w * t - 8, top + h + 4), _fmt(x), fill=(60, 60, 60))


def _top_down_panel(draw: ImageDraw.ImageDraw, box: tuple[int, int], views: TopDown) -> None:
    """Cameras (filled) and points (small) seen from above, on one metric scale for every series."""
    x0, y0 = box
    w, h = PANEL[0] - 2 * MARGIN, PANEL[1] - 2 * MARGIN
    left, top = x0 + MARGIN, y0 + MARGIN
    draw.text((left, y0 + 8), "top-down (x right, y up): cameras o, points .", fill=(0, 0, 0))
    xy = [a for cams, pts in views.values() for a in (cams, pts) if len(a)]
    if not xy:
        return
    allxy = np.concatenate(xy)
    lo, hi = allxy.min(axis=0), allxy.max(axis=0)
    scale = min(w / max(hi[0] - lo[0], 1e-6), h / max(hi[1] - lo[1], 1e-6))
    draw.rectangle([left, top, left + w, top + h], outline=(120, 120, 120))

    def px(p: np.ndarray) -> tuple[float, float]:
        return left + (p[0] - lo[0]) * scale, top + h - (p[1] - lo[1]) * scale

    for i, (cams, pts) in enumerate(views.values()):
        colour = COLOURS[i % len(COLOURS)]
        for p in pts:
            x, y = px(p)
            draw.point((x, y), fill=colour)
        for c in cams:
            x, y = px(c)
            draw.ellipse([x - 2, y - 2, x + 2, y + 2], outline=colour)
    draw.text((left, top + h + 4), f"{_fmt(hi[0] - lo[0])} x {_fmt(hi[1] - lo[1])} m", fill=(60, 60, 60))


def draw_sheet(path: Path, title: str, series: Mapping[str, Mapping[str, Histogram]],
               top_down: TopDown | None = None) -> None:
    """Write a PNG: one panel per distribution of `series` (label -> name -> histogram, overlaid in that
    order), then the top-down view when given."""
    names = list(dict.fromkeys(name for hists in series.values() for name in hists))
    panels = len(names) + (1 if top_down else 0)
    rows = -(-panels // COLUMNS)
    image = Image.new("RGB", (COLUMNS * PANEL[0], rows * PANEL[1] + 24), "white")
    draw = ImageDraw.Draw(image)
    draw.text((8, 6), title, fill=(0, 0, 0))
    for i, name in enumerate(names):
        box = ((i % COLUMNS) * PANEL[0], 24 + (i // COLUMNS) * PANEL[1])
        overlaid = {label: hists[name] for label, hists in series.items() if name in hists}
        _histogram_panel(draw, box, name, overlaid)
    if top_down:
        i = len(names)
        _top_down_panel(draw, ((i % COLUMNS) * PANEL[0], 24 + (i // COLUMNS) * PANEL[1]), top_down)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)
