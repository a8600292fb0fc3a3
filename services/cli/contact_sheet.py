"""`omnidata sheet DIR`: a contact sheet PNG showing every cue of a few views side by side.

Reads a dataset (a folder in the output layout, or s3://bucket/prefix of a job root) through its
manifest.jsonl and draws each file's preview (services/datasets/previews.py: colour maps, palettes, hashed
fragments, drawn JSON cues), cached under the root's `_previews/` like the dashboard's; the files are
untouched.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

from PIL import Image, ImageDraw

from services.cli import CliError
from services.core.domain.keys import MANIFEST_KEY
from services.core.storage import LocalStore, ObjectNotFoundError
from services.datasets.previews import Previewer
from services.datasets.source import ViewRecord, index_manifest, missing_file_message, open_root, select_cues


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "dir",
        help="output folder of `omnidata generate` (holds manifest.jsonl), s3://bucket/prefix or a "
        "service job id",
    )
    p.add_argument("--out", type=Path, default=None, help="PNG to write (default DIR/contact_sheet.png)")
    p.add_argument("--views", type=int, default=4, help="how many views (rows)")
    p.add_argument("--thumb", type=int, default=128, help="thumbnail size in pixels")


def _pick_views(records: list[ViewRecord], n: int) -> list[ViewRecord]:
    """Up to n views, taken round-robin across spaces so every space shows."""
    by_space: dict[str, list[ViewRecord]] = {}
    for r in records:
        by_space.setdefault(r.space, []).append(r)
    picked: list[ViewRecord] = []
    queues = list(by_space.values())
    while len(picked) < n and any(queues):
        for q in queues:
            if q and len(picked) < n:
                picked.append(q.pop(0))
    return picked


def build_sheet(root: Path | str, *, views: int = 4, thumb: int = 128) -> Image.Image:
    """Compose the sheet from `views` views of the root's manifest.jsonl (round-robin over spaces)."""
    try:
        store = open_root(root)
    except FileNotFoundError as e:
        raise CliError(str(e)) from None
    if not store.exists(MANIFEST_KEY):
        raise CliError(f"{root} holds no manifest.jsonl: is it the output folder of `omnidata generate`?")
    picked = _pick_views(index_manifest(store), views)
    if not picked:
        raise CliError(f"{root}/manifest.jsonl lists no views")
    cues = select_cues(picked, None)
    label_h, pad = 14, 4
    sheet = Image.new(
        "RGB", (len(cues) * (thumb + pad) + pad, len(picked) * (thumb + label_h + pad) + label_h),
        (32, 32, 32),
    )
    draw = ImageDraw.Draw(sheet)
    for j, cue in enumerate(cues):
        draw.text((pad + j * (thumb + pad), 2), cue[:20], fill=(230, 230, 230))
    previewer = Previewer(store)
    for i, record in enumerate(picked):
        y = label_h + i * (thumb + label_h + pad)
        draw.text((pad, y), f"{record.space} point {record.point} view {record.view}", fill=(200, 200, 120))
        tiles = previewer.previews(record, cues)
        for j, cue in enumerate(cues):
            if cue in tiles:
                tile = (
                    Image.open(io.BytesIO(tiles[cue]))
                    .convert("RGB")
                    .resize((thumb, thumb), Image.Resampling.NEAREST)
                )
                sheet.paste(tile, (pad + j * (thumb + pad), y + label_h))
    return sheet


def run(args: argparse.Namespace) -> int:
    if args.views < 1 or args.thumb < 1:
        raise CliError(f"--views and --thumb must be at least 1, got {args.views} and {args.thumb}")
    out = args.out
    if out is None:  # the default is inside the dataset's folder: a folder it must be (not s3:// or a job id)
        try:
            store = open_root(args.dir)
        except FileNotFoundError as e:
            raise CliError(str(e)) from None
        if not isinstance(store, LocalStore):
            raise CliError(f"give --out: {args.dir} is not a local folder to write the sheet into")
        out = store.root / "contact_sheet.png"
    try:
        sheet = build_sheet(args.dir, views=args.views, thumb=args.thumb)
    except ObjectNotFoundError as e:
        raise CliError(missing_file_message(e)) from None
    sheet.save(out)
    print(f"contact sheet: {out}")
    return 0
