"""`omnidata sheet DIR`: a contact sheet PNG showing every image cue of a few views side by side.

Reads a dataset folder in the DESIGN.md layout through its manifest.jsonl. Display mapping only (the
files themselves are untouched): 16-bit images are stretched to their 1st-99th percentile, label images
get pseudo-random colours, fragments are hashed to colours, positions are normalised per channel.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from services.cli import CliError
from services.core.cues import CATALOG

LABEL_CUES = {"segment_unsup2d", "segment_unsup25d", "segment_semantic", "segment_instance"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="output folder of `omnidata generate` (holds manifest.jsonl)")
    p.add_argument("--out", type=Path, default=None, help="PNG to write (default DIR/contact_sheet.png)")
    p.add_argument("--views", type=int, default=4, help="how many views (rows)")
    p.add_argument("--thumb", type=int, default=128, help="thumbnail size in pixels")


def _colourise_ids(ids: np.ndarray, none: int | None = None) -> np.ndarray:
    """Stable pseudo-random colour per integer id; `none` is black."""
    h = (ids.astype(np.uint64) * np.uint64(2654435761)) & np.uint64(0xFFFFFF)
    rgb = np.stack([(h >> np.uint64(s)) & np.uint64(255) for s in (16, 8, 0)], axis=-1).astype(np.uint8)
    if none is not None:
        rgb[ids == none] = 0
    return rgb


def _stretch(a: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    vals = a[valid] if valid is not None else a.ravel()
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return np.zeros(a.shape, np.uint8)
    lo, hi = np.percentile(vals, [1, 99])
    if hi - lo < 1e-9:  # a constant image shows mid-grey, not black
        lo, hi = lo - 1.0, lo + 1.0
    out = np.clip((a - lo) / (hi - lo), 0, 1)
    out = np.nan_to_num(out, nan=0.0)
    return (out * 255).astype(np.uint8)


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "RGB" in channels:
            return np.asarray(channels["RGB"].pixels, dtype=np.float32)
        return np.stack([np.asarray(channels[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)


def display_image(cue: str, path: Path) -> np.ndarray | None:
    """An 8-bit RGB rendering of one cue file for humans; None for non-image cues."""
    ext = CATALOG[cue].ext
    if ext == "json":
        return None
    if ext == "npy":
        frag = np.load(path)
        return _colourise_ids(frag, none=0xFFFFFFFF)
    if ext == "exr":
        pos = _read_exr(path)
        valid = np.isfinite(pos).all(axis=-1)
        return np.stack([_stretch(pos[..., i], valid) for i in range(3)], axis=-1)
    img = np.asarray(Image.open(path))
    if cue in LABEL_CUES:
        return _colourise_ids(img.astype(np.int64))
    if img.dtype == np.uint16 or img.dtype == np.int32:
        valid = img < 65535 if cue.startswith("depth") else None
        shown = _stretch(img.astype(np.float64), valid)
        img = shown if valid is None else np.where(valid, shown, 0).astype(np.uint8)
    if img.ndim == 2:
        img = np.stack([img] * 3, axis=-1)
    return img[..., :3].astype(np.uint8)


def _pick_views(lines: list[dict], n: int) -> list[dict]:
    """Up to n manifest lines, taken round-robin across spaces so every space shows."""
    by_space: dict[str, list[dict]] = {}
    for line in lines:
        by_space.setdefault(line["space"], []).append(line)
    picked: list[dict] = []
    queues = list(by_space.values())
    while len(picked) < n and any(queues):
        for q in queues:
            if q and len(picked) < n:
                picked.append(q.pop(0))
    return picked


def build_sheet(root: Path, *, views: int = 4, thumb: int = 128) -> Image.Image:
    """Compose the sheet from the first `views` lines of root/manifest.jsonl."""
    manifest = root / "manifest.jsonl"
    if not manifest.is_file():
        raise CliError(f"{root} holds no manifest.jsonl: is it the output folder of `omnidata generate`?")
    lines = _pick_views([json.loads(x) for x in manifest.read_text().splitlines() if x.strip()], views)
    if not lines:
        raise CliError(f"{manifest} lists no views")
    cues = [c for c in CATALOG if any(c in ln["outputs"] for ln in lines) and CATALOG[c].ext != "json"]
    label_h, pad = 14, 4
    sheet = Image.new("RGB", (len(cues) * (thumb + pad) + pad, len(lines) * (thumb + label_h + pad) + label_h),
                      (32, 32, 32))
    draw = ImageDraw.Draw(sheet)
    for j, cue in enumerate(cues):
        draw.text((pad + j * (thumb + pad), 2), cue[:20], fill=(230, 230, 230))
    for i, line in enumerate(lines):
        y = label_h + i * (thumb + label_h + pad)
        draw.text((pad, y), f"{line['space']} point {line['point']} view {line['view']}", fill=(200, 200, 120))
        for j, cue in enumerate(cues):
            out = line["outputs"].get(cue)
            if out is None:
                continue
            img = display_image(cue, root / out["key"])
            if img is not None:
                tile = Image.fromarray(img).resize((thumb, thumb), Image.Resampling.NEAREST)
                sheet.paste(tile, (pad + j * (thumb + pad), y + label_h))
    return sheet


def run(args: argparse.Namespace) -> int:
    out = args.out or args.dir / "contact_sheet.png"
    build_sheet(args.dir, views=args.views, thumb=args.thumb).save(out)
    print(f"contact sheet: {out}")
    return 0
