"""`omnidata preview SOURCE [--video]`: preview PNGs of every output (cached under `_previews/`), or one MP4
per cue and trajectory (one frame per view, in view order) with --video.

SOURCE is a job's output folder or s3://bucket/prefix of a job root. Videos go to --out (default
SOURCE/_previews/video for folders) as `<space>/point_<p>_<cue>.mp4`.
"""

from __future__ import annotations

import argparse
import io
import sys
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image

from services.cli import CliError
from services.core.domain.cues import UnknownCueError, validate_cue_names
from services.core.storage import LocalStore, ObjectNotFoundError, ObjectStore
from services.datasets.previews import PREVIEW_PREFIX, Previewer, write_video
from services.datasets.source import (
    ViewRecord,
    index_root,
    job_document,
    missing_file_message,
    open_root,
    select_cues,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "source", help="output folder of a job, s3://bucket/prefix of a job root, or a service job id"
    )
    p.add_argument(
        "--video", action="store_true", help="one MP4 per cue and trajectory (point), a frame per view"
    )
    p.add_argument(
        "--out", type=Path, default=None, help="folder for the videos (default SOURCE/_previews/video)"
    )
    p.add_argument("--cues", default=None, help="comma-separated cues (default: every cue the job has)")
    p.add_argument("--fps", type=float, default=10.0, help="video frames per second")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _progress(items: list, what: str, enabled: bool) -> Iterable:
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=what, unit="view", file=sys.stderr, dynamic_ncols=True)


def videos(store: ObjectStore, records: list[ViewRecord], cues: list[str], out: Path, *, fps: float,
           progress: bool = False) -> dict[Path, int]:
    """Write `<out>/<space>/point_<p>_<cue>.mp4` per trajectory (point) and cue; returns frames per video."""
    pv = Previewer(store)
    by_point: dict[tuple[str, int], list[ViewRecord]] = {}
    for r in records:
        by_point.setdefault((r.space, r.point), []).append(r)
    written: dict[Path, int] = {}
    for (space, point), views in _progress(list(by_point.items()), "videos", progress):
        views.sort(key=lambda r: r.view)
        frames: dict[str, list[np.ndarray]] = {}
        for r in views:
            for cue, png in pv.previews(r, cues).items():
                frames.setdefault(cue, []).append(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")))
        for cue, seq in frames.items():
            path = out / space / f"point_{point}_{cue}.mp4"
            written[path] = write_video(seq, path, fps=fps)
    return written


def run(args: argparse.Namespace) -> int:
    try:
        wanted = (
            None
            if args.cues is None
            else validate_cue_names(c.strip() for c in args.cues.split(",") if c.strip())
        )
        store = open_root(args.source)
        records = index_root(store)
        if not records:
            raise CliError(f"{args.source} lists no views")
        cues = select_cues(records, wanted)
    except (UnknownCueError, FileNotFoundError, ValueError) as e:
        raise CliError(str(e)) from None
    try:
        return _write(args, store, records, cues)
    except ObjectNotFoundError as e:
        raise CliError(missing_file_message(e)) from None


def _write(args: argparse.Namespace, store: ObjectStore, records: list[ViewRecord], cues: list[str]) -> int:
    """The preview PNGs, or with --video the MP4s, of the selected views and cues."""
    if not args.video:
        pv = Previewer(store)
        n = sum(len(pv.previews(r, cues)) for r in _progress(records, "previews", not args.no_progress))
        print(f"omnidata preview: {n} previews under {args.source}/{PREVIEW_PREFIX}")
        return 0
    if args.fps <= 0:
        raise CliError(f"--fps must be > 0, got {args.fps}")
    out = args.out
    if out is None:
        if not isinstance(store, LocalStore):
            raise CliError("give --out for a dataset on object storage")
        out = store.root / PREVIEW_PREFIX / "video"
    document = job_document(store)
    spec = document.get("spec") if document is not None else None
    views = spec.get("views") if spec else None
    mode = views.get("mode") if isinstance(views, dict) else None
    if mode not in (None, "trajectory"):
        print(f"omnidata preview: note: views are {mode}, not a trajectory; frames jump between cameras")
    written = videos(store, records, cues, out, fps=args.fps, progress=not args.no_progress)
    frames = sorted(set(written.values()))
    print(f"omnidata preview: {len(written)} video(s) in {out} ({', '.join(map(str, frames))} frames each)")
    return 0
