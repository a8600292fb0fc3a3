"""`omnidata export SOURCE --format webdataset|omnidata --out OUT`: a job's output for other loaders.

The formats are written by services.datasets.export.Exporter; this module reads the arguments, picks the
split, and builds the output in a temporary sibling folder renamed into place at the end, so a failed export
leaves nothing. For the omnidata format, `--component` must name one of the public loader's classes, and that
loader reads split CSVs only from its own package folder: `--loader-dir CHECKOUT` installs them there (also
later, as `omnidata export OUT --loader-dir CHECKOUT`, which drops a stale `.data_cache` too); without it the
one command that remains is printed.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import uuid
from pathlib import Path

from services.cli.errors import CliError
from services.core.domain.cues import UnknownCueError, validate_cue_names
from services.core.domain.keys import check_name
from services.core.storage import ObjectNotFoundError
from services.datasets.export import FORMATS, Exporter
from services.datasets.public_loader import (
    COMPONENTS,
    CUE_NOTES,
    LoaderComponent,
    LoaderDirError,
    component,
    find_dataloader,
    install_splits,
    split_rel_paths,
)
from services.datasets.source import DatasetIntegrityError, missing_file_message, open_root
from services.datasets.splits import DEFAULT_RATIOS, SPLITS, assign_splits, read_split_csv


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "source", help="output folder of a job, s3://bucket/prefix of a job root, or a service job id"
    )
    p.add_argument("--format", choices=FORMATS, help="webdataset tar shards or the Omnidata tree")
    p.add_argument("--out", type=Path, help="folder to create (must not exist or be empty)")
    p.add_argument("--shard-size", type=int, default=1000, help="webdataset: samples (views) per shard")
    p.add_argument(
        "--flat-keys", action="store_true", help="webdataset: keys without '/' (<space>__point_..)"
    )
    p.add_argument("--cues", default=None, help="comma-separated cues to export (default: all the job has)")
    p.add_argument(
        "--component", default=None,
        help=f"omnidata: the loader class's component, one of {', '.join(COMPONENTS)} "
        "(default: the job's name)",
    )
    p.add_argument(
        "--loader-dir", type=Path, default=None,
        help="omnidata: a checkout of the public dataloader to install the split CSVs "
        "into; with no --format, SOURCE is an omnidata export whose splits to install",
    )
    p.add_argument("--split-seed", type=int, default=0, help="omnidata: seed of the split by space")
    p.add_argument("--split-ratios", default=",".join(map(str, DEFAULT_RATIOS)),
                   help="omnidata: train,val,test fractions of spaces")
    p.add_argument(
        "--split-csv", type=Path, default=None, help="omnidata: use this split CSV (id,train,val,test)"
    )
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


def _splits(args: argparse.Namespace, comp: LoaderComponent, spaces: list[str]) -> dict[str, str]:
    """Split per split-CSV id of the loader class (a Hypersim id groups the spaces that share its prefix)."""
    ids = sorted({comp.split_id(s) for s in spaces})
    if args.split_csv is not None:
        try:
            members = read_split_csv(args.split_csv)
        except (OSError, ValueError) as e:
            raise CliError(f"--split-csv: {e}") from None
        return {i: next((name for name, ids in members.items() if i in ids), "none") for i in ids}
    try:
        ratios = [float(x) for x in args.split_ratios.split(",")]
        return assign_splits(ids, seed=args.split_seed, ratios=ratios)
    except ValueError as e:
        raise CliError(f"--split-ratios: {e}") from None


def _split_warnings(splits: dict[str, str]) -> list[str]:
    """One line per split that holds no space: the loader then gives 0 items for it, silently."""
    empty = [s for s in SPLITS if s not in splits.values()]
    if not empty:
        return []
    return [f"warning: the {' and '.join(empty)} split(s) hold no space ({len(splits)} space(s) in all): the "
            "loader gives 0 items for them; choose with --split-csv or --split-ratios"]


def _component(args: argparse.Namespace, exporter: Exporter) -> LoaderComponent:
    job_name = exporter.job["job"].get("name") if exporter.job is not None else None
    name = (
        args.component or (job_name if isinstance(job_name, str) else None) or exporter.records[0].component
    )
    try:
        check_name("--component", name)
        return component(name)
    except ValueError as e:
        hint = "" if args.component else " (the job's name; choose one with --component)"
        raise CliError(f"--component: {e}{hint}") from None


def _install(export_root: Path, loader_dir: Path) -> list[str]:
    try:
        return install_splits(export_root, loader_dir)
    except (LoaderDirError, ValueError, OSError) as e:
        raise CliError(f"--loader-dir: {e}") from None


def _remaining_command(out: Path) -> str:
    return ("the public loader reads split CSVs only from its own folder; one command remains: "
            f"omnidata export {out} --loader-dir PATH_TO_YOUR_OMNIDATA_CHECKOUT")


def run(args: argparse.Namespace) -> int:
    if args.format is None and args.loader_dir is not None:  # install the splits of an existing export
        for line in _install(Path(args.source), args.loader_dir):
            print(f"omnidata export: {line}")
        return 0
    if args.format is None or args.out is None:
        raise CliError(
            "--format and --out are required (or only --loader-dir, to install an export's splits)"
        )
    if args.shard_size < 1:
        raise CliError(f"--shard-size must be >= 1, got {args.shard_size}")
    try:
        cues = (None if args.cues is None
                else validate_cue_names(c.strip() for c in args.cues.split(",") if c.strip()))
        store = open_root(args.source)
        exporter = Exporter(store, cues, verify=args.verify, progress=not args.no_progress)
    except (UnknownCueError, FileNotFoundError, ValueError) as e:
        raise CliError(str(e)) from None
    notes: list[str] = []
    if args.format == "omnidata":
        comp = _component(args, exporter)
        if args.loader_dir is not None:
            try:
                find_dataloader(args.loader_dir)  # before writing anything
            except LoaderDirError as e:
                raise CliError(f"--loader-dir: {e}") from None
        splits = _splits(args, comp, sorted({r.space for r in exporter.records}))
        notes = _split_warnings(splits) + [f"note: {CUE_NOTES[c]}" for c in exporter.cues if c in CUE_NOTES]
    tmp = _prepare_out(args.out)
    try:
        if args.format == "webdataset":
            shards = exporter.webdataset(tmp, shard_size=args.shard_size, flat_keys=args.flat_keys)
            summary = f"{len(exporter.records)} samples in {len(shards)} shard(s)"
        else:
            n = exporter.omnidata(tmp, comp=comp, splits=splits)
            summary = (f"{n} files of {len(exporter.records)} views for {comp.class_name}, "
                       f"split CSV {split_rel_paths(comp)[0]}")
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
    for line in notes:
        print(f"omnidata export: {line}", file=sys.stderr)
    if args.format == "omnidata":
        lines = (_install(args.out, args.loader_dir) if args.loader_dir is not None
                 else [_remaining_command(args.out)])
        for line in lines:
            print(f"omnidata export: {line}")
    return 0
