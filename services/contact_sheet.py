"""`omnidata sheet DIR`: a contact sheet PNG showing every cue of a few views side by side.

Reads a dataset (a folder in the DESIGN.md layout, or s3://bucket/prefix of a job root) through its
manifest.jsonl and draws each file's preview (services/datasets/previews.py: colour maps, palettes, hashed
fragments, drawn JSON cues); the files themselves are untouched.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from services.cli import CliError
from services.core.cues import CATALOG
from services.core.keys import MANIFEST_KEY
from services.datasets.decode import cue_params
from services.datasets.previews import preview_array
from services.datasets.source import job_document, open_root


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", help="output folder of `omnidata generate` (holds manifest.jsonl), or s3://bucket/prefix")
    p.add_argument("--out", type=Path, default=None, help="PNG to write (default DIR/contact_sheet.png)")
    p.add_argument("--views", type=int, default=4, help="how many views (rows)")
    p.add_argument("--thumb", type=int, default=128, help="thumbnail size in pixels")


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


def build_sheet(root: Path | str, *, views: int = 4, thumb: int = 128) -> Image.Image:
    """Compose the sheet from `views` lines of the root's manifest.jsonl (round-robin over spaces)."""
    try:
        store = open_root(root)
    except FileNotFoundError as e:
        raise CliError(str(e)) from None
    if not store.exists(MANIFEST_KEY):
        raise CliError(f"{root} holds no manifest.jsonl: is it the output folder of `omnidata generate`?")
    all_lines = [json.loads(x) for x in store.get_bytes(MANIFEST_KEY).decode().splitlines() if x.strip()]
    lines = _pick_views(all_lines, views)
    if not lines:
        raise CliError(f"{root}/manifest.jsonl lists no views")
    params = cue_params(job_document(store))
    per_point = {(ln["space"], ln["point"]): ln["outputs"] for ln in all_lines if ln["view"] == 0}
    cues = [c for c in CATALOG if any(c in ln["outputs"] for ln in lines) or
            (CATALOG[c].per_point and any(c in per_point.get((ln["space"], ln["point"]), {}) for ln in lines))]
    label_h, pad = 14, 4
    sheet = Image.new("RGB", (len(cues) * (thumb + pad) + pad, len(lines) * (thumb + label_h + pad) + label_h),
                      (32, 32, 32))
    draw = ImageDraw.Draw(sheet)
    for j, cue in enumerate(cues):
        draw.text((pad + j * (thumb + pad), 2), cue[:20], fill=(230, 230, 230))
    for i, line in enumerate(lines):
        y = label_h + i * (thumb + label_h + pad)
        draw.text((pad, y), f"{line['space']} point {line['point']} view {line['view']}", fill=(200, 200, 120))
        outputs = {**per_point.get((line["space"], line["point"]), {}), **line["outputs"]}
        resolution = None
        if "point_info" in outputs:
            resolution = json.loads(store.get_bytes(outputs["point_info"]["key"])).get("resolution")
        for j, cue in enumerate(cues):
            out = outputs.get(cue)
            if out is None:
                continue
            img = preview_array(cue, store.get_bytes(out["key"]), params, view=line["view"], resolution=resolution)
            tile = Image.fromarray(np.ascontiguousarray(img)).resize((thumb, thumb), Image.Resampling.NEAREST)
            sheet.paste(tile, (pad + j * (thumb + pad), y + label_h))
    return sheet


def run(args: argparse.Namespace) -> int:
    if args.out is None and "://" in args.dir:
        raise CliError("give --out for a dataset on object storage")
    out = args.out or Path(args.dir) / "contact_sheet.png"
    build_sheet(args.dir, views=args.views, thumb=args.thumb).save(out)
    print(f"contact sheet: {out}")
    return 0
