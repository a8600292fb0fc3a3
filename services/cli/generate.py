"""`omnidata generate SPACE [SPACE ...] --out DIR`: plan and render a dataset on this machine, no services.

The embedded default (a laptop, no services), composed from the SAME parts as the service: SQLite at
DIR/.omnidata/state.db, a LocalStore rooted at DIR (space sources under `.omnidata/spaces`, outputs with an
empty output root), the scheduler's planning/dispatch/reaper/completion loop in this process, and W local
worker processes (forked from this one, or spawned: services.embedded.pool) each running the worker's
TaskRunner. A multiprocessing queue replaces Redis.

At the end DIR holds `<cue>/<component>/<space>/point_<p>_view_<v>_domain_<cue>.<ext>`, `manifest.jsonl` and
`job.json`. Exit status: 0 when every requested output exists; 1 with a summary of what failed; 2 for bad
input (nothing is created); 130 on Ctrl-C (writes are atomic; run the same command again to resume: the same
job is reused, interrupted tasks go back to pending, missing files are made again, nothing else renders).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from services.worker.process.heap import keep_freed_memory
from services.worker.process.numeric_threads import pin_numeric_threads

# Before numpy loads (the imports below): the local workers forked from this process keep its BLAS, which must
# run one thread (services.worker.process.numeric_threads); this process's own linear algebra is small
# (planning).
pin_numeric_threads()
# This process too reuses the pages it frees (services.worker.process.heap): loading, checking and planning a
# space allocate and free the same large arrays over and over, each time faulting in fresh pages.
keep_freed_memory()

from services.cli import CliError  # noqa: E402
from services.cli.spec_args import add_spec_arguments, build_spec, check_sources, refused_summary, usable  # noqa: E402
from services.core.db.engine import make_engine, make_sessionmaker, migrate  # noqa: E402
from services.core.domain.jobspec import JobSpec, cues_for_space  # noqa: E402
from services.core.ingest.capture.detect import captures_kept  # noqa: E402
from services.core.ingest.errors import SpaceError  # noqa: E402
from services.core.ingest.parsed_cache import load_space_kept  # noqa: E402
from services.core.ingest.registry import Source  # noqa: E402
from services.core.settings import Settings  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.core.user_cache import CURVATURE, prune_user_caches, user_cache_dir  # noqa: E402
from services.embedded.ctrl_c import latched_sigint  # noqa: E402
from services.embedded.curvature_ahead import curvature_ahead  # noqa: E402
from services.embedded.job import (  # noqa: E402
    STATE_DIR,
    drive,
    embedded_settings,
    find_spaces,
    prepare_job,
    worker_pool,
)
from services.embedded.pool import LocalPool, cpu_count  # noqa: E402


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata generate`."""
    parser.add_argument(
        "spaces", nargs="+", metavar="SPACE",
        help="mesh file (.obj with .mtl/textures, .ply, .glb/.gltf) or a folder or .zip holding one",
    )
    parser.add_argument(
        "--out", "-o", required=True, metavar="DIR", help="output folder (created; reused to resume)"
    )
    add_spec_arguments(parser)
    parser.add_argument(
        "--workers", type=int, metavar="W", help="local worker processes (default: CPU cores)"
    )
    parser.add_argument(
        "--render-workers", type=int, metavar="R",
        help="of the W workers, R render and the others only derive (default: all "
        "render; on a machine with an NVIDIA GPU, one in 8: each renderer holds a device context)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")


def validate_sources(sources: list[Source], spec: JobSpec, *, progress: bool = False) -> None:
    """Load every (not yet registered) space and check it can give the requested cues; CliError otherwise,
    except for a scene of a dataset root, which is marked refused (the others go on)."""
    todo = [s for s in sources if s.has_semantics is None and s.refused is None]
    if progress and len(todo) > 1:
        from tqdm import tqdm

        todo = tqdm(todo, desc="spaces", unit="space", file=sys.stderr, dynamic_ncols=True)
    for src in todo:
        try:
            loaded = load_space_kept(src.path, src.checksum, spec.space_frame())  # a rerun reads it back
        except SpaceError as e:
            if src.from_root:
                src.refused = str(e)
                continue
            raise CliError(str(e)) from None
        src.loaded = loaded
        src.has_semantics = bool(loaded.has_semantics)
        try:
            cues_for_space(spec, has_semantics=src.has_semantics)
        except ValueError as e:
            if src.from_root:
                src.refused = str(e)
                continue
            raise CliError(f"space {src.name!r}: {e}") from None


def run(args: argparse.Namespace) -> int:
    """Plan and render the dataset into --out; see the module docstring for exit statuses."""
    logging.basicConfig(
        level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s"
    )
    for noisy in ("alembic", "trimesh"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    workers = args.workers if args.workers is not None else cpu_count()
    if workers < 1:
        raise CliError(f"--workers must be at least 1, got {workers}")
    spec = build_spec(args)
    with captures_kept():  # a capture beside a scan is looked for by every step below: read once
        return _checked_run(args, spec, workers)


def _checked_run(args: argparse.Namespace, spec: JobSpec, workers: int) -> int:
    sources = check_sources(args.spaces)
    out = Path(args.out).expanduser().resolve()
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {args.out}: exists and is not a folder")
    state_db = out / STATE_DIR / "state.db"

    if args.render_workers is not None and args.render_workers < 1:
        raise CliError(f"--render-workers must be at least 1, got {args.render_workers}")
    settings = embedded_settings(out, workers, args.render_workers)
    if settings.render_workers is not None and settings.render_workers > workers:
        given = "--render-workers" if args.render_workers is not None else "OMNIDATA_RENDER_WORKERS"
        raise CliError(f"{given} {settings.render_workers} is more than the {workers} worker(s) of this run "
                       "(--workers)")
    if (
        args.render_workers is None
        and settings.render_workers is not None
        and settings.render_workers < workers
    ):
        print(
            f"omnidata generate: {settings.render_workers} of the {workers} workers render, the "
            "others derive (OMNIDATA_RENDER_WORKERS, else one in 8 on a GPU; --render-workers chooses)",
            file=sys.stderr,
        )
    # The workers import (Python, numba kernels, Blender: ~2 CPU-s each) while this process validates and
    # plans; held, they touch nothing until the job exists, and a refused input stops them at once.
    pool = worker_pool(out, settings, workers)
    pool.start(held=True)
    try:
        # a Ctrl-C dropped by a finalizer, while preparing or driving, stops drive's loop
        with latched_sigint():
            return _run(args, spec, sources, out, state_db, settings, workers, pool)
    finally:
        pool.stop()


def _run(args: argparse.Namespace, spec: JobSpec, sources: list[Source], out: Path, state_db: Path,
         settings: Settings, workers: int, pool: LocalPool) -> int:
    if state_db.exists():  # a folder of an earlier run: spaces it already holds need no second validation
        engine = make_engine(settings.database_url)
        migrate(settings.database_url)
        sessions = make_sessionmaker(engine)
        with sessions() as s:
            find_spaces(s, sources)
        engine.dispose()
    # bad input refused before anything is created
    validate_sources(sources, spec, progress=not args.no_progress)
    refused = refused_summary(sources)
    sources = usable(sources)
    if refused:
        print(f"omnidata generate: refused scene(s), left out of the job:\n{refused}", file=sys.stderr)

    # The workers' curvature, computed while they import (several would otherwise wait on the first one's)
    ahead = curvature_ahead([s.loaded.mesh for s in sources if s.loaded is not None], spec,
                            user_cache_dir(CURVATURE), workers)
    migrate(settings.database_url)
    engine = make_engine(settings.database_url)
    sessions = make_sessionmaker(engine)
    store = LocalStore(out)
    try:
        prepared = prepare_job(sessions, store, spec, sources)
        if prepared.resumed:
            store.remove_temp_files()  # writes the interrupted run never committed; no worker runs yet
            print(
                f"omnidata generate: resuming job {prepared.job_id} in {out} ({prepared.requeued} "
                f"interrupted, {prepared.redo} missing, {prepared.retried} failed tasks to redo)",
                file=sys.stderr,
            )
        status = drive(
            sessions, store, settings, out, prepared.job_id, workers, progress=not args.no_progress,
            loaded_spaces=prepared.loaded, pool=pool,
        )
        if refused:
            print(
                f"omnidata generate: {len(sources)} space(s) done; refused scene(s):\n{refused}",
                file=sys.stderr,
            )
        return status
    finally:
        engine.dispose()
        if ahead is not None:
            ahead.join()
        prune_user_caches(settings.user_cache_mb * 2**20)
