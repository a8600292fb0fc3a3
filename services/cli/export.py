"""`omnidata export SOURCE --format webdataset|omnidata --out OUT`: a job's output for other loaders.

The formats are written by services.datasets.export.Exporter; this module reads the arguments, picks the
split, and builds the output in a temporary sibling folder renamed into place at the end, so a failed export
leaves nothing.
"""

from __future__ import annotations

import argparse
import shutil
import uuid
from pathlib import Path

from services.cli.errors import CliError
from services.core.domain.cues import UnknownCueError, validate_cue_names
from services.core.domain.keys import check_name
from services.core.storage import ObjectNotFoundError
from services.datasets.export import FORMATS, Exporter, split_csv_path
from services.datasets.source import DatasetIntegrityError, missing_file_message, open_root
from services.datasets.splits import DEFAULT_RATIOS, assign_splits, read_split_csv


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="output folder of a job, s3://bucket/prefix of a job root, or a service job id")
    p.add_argument("--format", required=True, choices=FORMATS, help="webdataset tar shards or the Omnidata tree")
    p.add_argument("--out", required=True, type=Path, help="folder to create (must not exist or be empty)")
    p.add_argument("--shard-size", type=int, default=1000, help="webdataset: samples (views) per shard")
    p.add_argument("--flat-keys", action="store_true", help="webdataset: keys without '/' (<space>__point_..)")
    p.add_argument("--cues", default=None, help="comma-separated cues to export (default: all the job has)")
    p.add_argument("--component", default=None, help="omnidata: component folder name (default: the job's)")
    p.add_argument("--split-seed", type=int, default=0, help="omnidata: seed of the split by space")
    p.add_argument("--split-ratios", default=",".join(map(str, DEFAULT_RATIOS)),
                   help="omnidata: train,val,test fractions of spaces")
    p.add_argument("--split-csv", type=Path, default=None, help="omnidata: use this split CSV (id,train,val,test)")
    p.add_argument("--verify", action="store_true", help="check every file's sha256 against the manifest")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _prepare_out(out: Path) -> Path:
    """A fresh temporary folder beside `out` (which must not exist or be empty)."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise CliError(f"--out {out} exists and is not an empty folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    return tmp


def _splits(args: argparse.Namespace, spaces: list[str]) -> dict[str, str]:
    if args.split_csv is not None:
        try:
            members = read_split_csv(args.split_csv)
        except (OSError, ValueError) as e:
            raise CliError(f"--split-csv: {e}") from None
        return {s: next((name for name, ids in members.items() if s in ids), "none") for s in spaces}
    try:
        ratios = [float(x) for x in args.split_ratios.split(",")]
        return assign_splits(spaces, seed=args.split_seed, ratios=ratios)
    except ValueError as e:
        raise CliError(f"--split-ratios: {e}") from None


def run(args: argparse.Namespace) -> int:
    if args.shard_size < 1:
        raise CliError(f"--shard-size must be >= 1, got {args.shard_size}")
    try:
        cues = None if args.cues is None else validate_cue_names(c.strip() for c in args.cues.split(",") if c.strip())
        store = open_root(args.source)
        exporter = Exporter(store, cues, verify=args.verify, progress=not args.no_progress)
    except (UnknownCueError, FileNotFoundError, ValueError) as e:
        raise CliError(str(e)) from None
    component = args.component or (exporter.job or {}).get("job", {}).get("name") or exporter.records[0].component
    try:
        check_name("--component", component)
    except ValueError as e:
        raise CliError(str(e)) from None
    splits = _splits(args, sorted({r.space for r in exporter.records})) if args.format == "omnidata" else {}
    tmp = _prepare_out(args.out)
    try:
        if args.format == "webdataset":
            shards = exporter.webdataset(tmp, shard_size=args.shard_size, flat_keys=args.flat_keys)
            summary = f"{len(exporter.records)} samples in {len(shards)} shard(s)"
        else:
            n = exporter.omnidata(tmp, component=component, splits=splits)
            summary = f"{n} files of {len(exporter.records)} views, split CSV {split_csv_path(component)}"
        if args.out.exists():
            args.out.rmdir()
        tmp.rename(args.out)
    except DatasetIntegrityError as e:
        raise CliError(str(e)) from None
    except ObjectNotFoundError as e:
        raise CliError(missing_file_message(e)) from None
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    print(f"omnidata export: {summary} in {args.out}")
    return 0
