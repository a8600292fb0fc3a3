"""`omnidata submit SPACE ... [--spec job.yaml] [--points N ...] [--api URL --token T] [--no-follow]`:
submit a job to the service. The spec is built as `generate` and `plan` build it (services/cli/spec_args.py):
the file's fields, or the defaults, with the flags overriding them.

With an API URL (--api or $OMNIDATA_API_URL) the spaces are uploaded (POST /spaces, multipart) and the job is
created over HTTP (POST /jobs {space_ids, spec}); its progress is read from GET /jobs/{id}. With --direct, the
spaces are registered and the job created directly in the service's database and object store
(OMNIDATA_DATABASE_URL, which must be set, / OMNIDATA_STORAGE_URL), for operators on the cluster. With
neither, submit refuses (exit 2): a job written to a database no service reads would wait forever. Either way
the job id is printed on stdout, then progress follows on stderr until the job is final (exit 0 when done, 1
when failed or cancelled). A space already registered under the same name with the same content is reused.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

from services.cli import CliError
from services.cli.spec_args import add_spec_arguments, build_spec, check_sources, refused_summary, usable
from services.core.db.models import JOB_TERMINAL_STATES, TASK_TERMINAL_STATES, JobState, TaskState

if TYPE_CHECKING:  # imported where used: `omnidata --help` stays fast
    from services.core.domain.jobspec import JobSpec
    from services.core.ingest.registry import Source
    from services.core.settings import Settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata submit`."""
    parser.add_argument(
        "spaces", nargs="+", metavar="SPACE",
        help="mesh file (.obj with .mtl/textures, .ply, .glb/.gltf) or a folder or .zip holding one",
    )
    add_spec_arguments(parser)
    parser.add_argument("--api", default=os.environ.get("OMNIDATA_API_URL"), metavar="URL",
                        help="API base URL (default $OMNIDATA_API_URL)")
    parser.add_argument(
        "--direct", action="store_true",
        help="no API: write to the service's database ($OMNIDATA_DATABASE_URL) directly (operators)",
    )
    parser.add_argument("--token", default=os.environ.get("OMNIDATA_API_TOKEN"), metavar="T",
                        help="API token (default $OMNIDATA_API_TOKEN)")
    parser.add_argument(
        "--owner", default=os.environ.get("OMNIDATA_OWNER", "local"),
        help="tenant owning spaces and job without an API (default $OMNIDATA_OWNER or 'local')",
    )
    follow = parser.add_mutually_exclusive_group()
    follow.add_argument("--follow", dest="follow", action="store_true", default=True,
                        help="follow progress until the job is final (default)")
    follow.add_argument("--no-follow", dest="follow", action="store_false", help="print the job id and exit")
    parser.add_argument(
        "--interval", type=float, default=2.0, metavar="S", help="seconds between progress polls"
    )


@dataclass
class Status:
    """A job's state and progress as the follower shows it."""

    state: str
    total: int
    finished: int
    failed: int
    labels_per_s: float | None = None
    eta_s: float | None = None
    error: str | None = None

    def line(self, job_id: int) -> str:
        """One human-readable progress line."""
        pct = 100.0 * self.finished / self.total if self.total else 0.0
        parts = [f"job {job_id} {self.state}: {self.finished}/{self.total} tasks ({pct:.0f}%)"]
        if self.failed:
            parts.append(f"{self.failed} failed")
        if self.labels_per_s:
            parts.append(f"{self.labels_per_s:.1f} labels/s")
        if self.eta_s is not None and self.state not in JOB_TERMINAL_STATES:
            parts.append(f"ETA {self.eta_s:.0f} s")
        return ", ".join(parts)


# ---------------------------------------------------------------------------------------------- HTTP


class SpaceReply(TypedDict):
    """The keys `submit` reads of a space in the API's replies."""

    id: int
    name: str
    checksum: str


class JobReply(TypedDict):
    id: int


class Api:
    """The few API calls `submit` makes (httpx, bearer token); HTTP errors become CliError with the detail."""

    def __init__(self, base_url: str, token: str | None, *, timeout: float = 300.0) -> None:
        import httpx

        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.base_url = base_url.rstrip("/")
        self.client = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout)

    def _call(self, method: str, path: str, **kw: Any) -> Any:  # httpx's request keywords; its JSON is Any
        import httpx

        try:
            r = self.client.request(method, path, **kw)
        except httpx.HTTPError as e:
            raise CliError(f"cannot reach the API at {self.base_url}: {e}") from None
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except (ValueError, AttributeError):
                detail = r.text
            raise CliError(f"{method} {path} failed with {r.status_code}: {detail}")
        return r.json() if r.content else None

    def find_space(self, name: str) -> SpaceReply | None:
        """The caller's space with this name, if any."""
        offset = 0
        while True:
            page = self._call("GET", "/spaces", params={"limit": 200, "offset": offset})
            for space in page["items"]:
                if space["name"] == name:
                    return space
            offset += len(page["items"])
            if not page["items"] or offset >= page["total"]:
                return None

    def upload_space(self, path: Path, *, name: str, up_axis: str, unit_scale: float | str) -> SpaceReply:
        """POST /spaces (multipart: file, name, up_axis, unit_scale)."""
        with open(path, "rb") as fh:
            return self._call("POST", "/spaces", files={"file": (path.name, fh)},
                              data={"name": name, "up_axis": up_axis, "unit_scale": str(unit_scale)})

    def create_job(self, space_ids: list[int], spec: Mapping[str, object]) -> JobReply:
        """POST /jobs."""
        return self._call("POST", "/jobs", json={"space_ids": space_ids, "spec": spec})

    def status(self, job_id: int) -> Status:
        """GET /jobs/{id} reduced to a Status."""
        job = self._call("GET", f"/jobs/{job_id}")
        p = job.get("progress") or {}
        by = p.get("by_state") or {}
        return Status(
            job["state"], int(p.get("total", 0)), int(p.get("finished", 0)), int(by.get(TaskState.FAILED, 0)),
            p.get("labels_per_s"), p.get("eta_s"), job.get("error"),
        )


def submit_http(api: Api, spec: JobSpec, sources: list[Source]) -> int:
    """Upload (or reuse) the spaces and create the job over HTTP; returns the job id."""
    from services.core.domain.frame_values import similarity_scale
    from services.core.ingest.guard.archive import resolve_source
    from services.core.ingest.registry import pack_source

    ids = []
    for src in sources:
        existing = api.find_space(src.name)
        if existing is not None:
            if existing.get("checksum") != src.checksum:
                raise CliError(
                    f"a different space named {src.name!r} already exists on the service; rename yours"
                )
            ids.append(int(existing["id"]))
            continue
        with tempfile.TemporaryDirectory(prefix="omnidata-submit-") as tmp:
            work = Path(tmp)
            mesh = (
                resolve_source(src.path, work / "x")
                if src.path.suffix.lower() == ".zip"
                else resolve_source(src.path)
            )
            upload = pack_source(src.path, mesh, work)  # the file itself, or a zip with its .mtl and textures
            # the space's own record; the job's spec (up, source_to_world) still decides its frame when
            # planned
            scale = (
                spec.unit_scale if spec.source_to_world is None else similarity_scale(spec.source_to_world)
            )
            created = api.upload_space(upload, name=src.name, up_axis=spec.up_axis, unit_scale=scale)
        print(f"omnidata submit: uploaded space {src.name!r} (id {created['id']})", file=sys.stderr)
        ids.append(int(created["id"]))
    job = api.create_job(ids, spec.model_dump(mode="json"))
    return int(job["id"])


# ---------------------------------------------------------------------------------------------- database


def submit_db(settings: Settings, spec: JobSpec, sources: list[Source], owner: str) -> int:
    """Register (or reuse) the spaces and create the job in the configured database and store."""
    from sqlalchemy import select

    from services.core.db.engine import make_engine, make_sessionmaker, migrate, require_schema
    from services.core.db.jobs import create_job
    from services.core.db.models import Space
    from services.core.ingest.errors import SpaceError
    from services.core.ingest.registry import register_space
    from services.core.storage import open_store

    if settings.is_sqlite:
        migrate(settings.database_url)
    require_schema(settings.database_url)
    engine = make_engine(settings.database_url)
    store = open_store(settings.storage_url, settings)
    try:
        with make_sessionmaker(engine)() as s:
            spaces = []
            for src in sources:
                space = s.scalars(select(Space).where(Space.owner == owner, Space.name == src.name)).first()
                if space is not None and space.checksum != src.checksum:
                    raise CliError(
                        f"a different space named {src.name!r} already exists for {owner!r}; rename yours"
                    )
                if space is None:
                    try:
                        space = register_space(s, store, owner=owner, name=src.name, source_path=src.path,
                                            **spec.space_frame())
                    except SpaceError as e:
                        raise CliError(str(e)) from None
                    print(f"omnidata submit: registered space {src.name!r} (id {space.id})", file=sys.stderr)
                spaces.append(space)
            try:
                job = create_job(s, owner=owner, spec=spec, spaces=spaces)
            except ValueError as e:
                raise CliError(str(e)) from None
            s.commit()
            return int(job.id)
    finally:
        engine.dispose()


def db_status_fn(settings: Settings) -> tuple[Callable[[int], Status], Callable[[], None]]:
    """A Status reader on the database (counters only) and its close function."""
    from services.core.db.counters import job_progress
    from services.core.db.engine import make_engine, make_sessionmaker
    from services.core.db.models import Job
    from services.core.domain.cues import CATALOG

    engine = make_engine(settings.database_url)
    sessions = make_sessionmaker(engine)
    t0, first_labels = time.monotonic(), None

    def status(job_id: int) -> Status:
        nonlocal first_labels
        with sessions() as s:
            job = s.get(Job, job_id)
            if job is None:
                raise CliError(f"job {job_id} does not exist")
            prog = job_progress(s, job_id)
        total = sum(sum(st.values()) for st in prog.values())
        finished = sum(st.get(k, 0) for st in prog.values() for k in TASK_TERMINAL_STATES)
        labels = sum(st.get(TaskState.DONE, 0) for cue, st in prog.items() if not CATALOG[cue].internal)
        first_labels = labels if first_labels is None else first_labels
        dt = time.monotonic() - t0
        rate = (labels - first_labels) / dt if dt > 1 else None
        return Status(
            job.state, total, finished, sum(st.get(TaskState.FAILED, 0) for st in prog.values()), rate, None,
            job.error,
        )

    return status, engine.dispose


# ---------------------------------------------------------------------------------------------- follow


def follow(job_id: int, status: Callable[[int], Status], interval: float) -> Status:
    """Poll until the job is final, printing a line to stderr whenever the progress changes."""
    last = ""
    while True:
        st = status(job_id)
        line = st.line(job_id)
        if line != last:
            print(line, file=sys.stderr, flush=True)
            last = line
        if st.state in JOB_TERMINAL_STATES:
            return st
        time.sleep(interval)


def run(args: argparse.Namespace) -> int:
    """Submit the job; with --follow, return 0 when it finished done and 1 otherwise."""
    if args.interval <= 0:
        raise CliError(f"--interval must be positive, got {args.interval}")
    if not args.api and not args.direct:
        raise CliError(
            "no service configured: pass --api URL or set OMNIDATA_API_URL (--direct writes to "
            "OMNIDATA_DATABASE_URL instead; `omnidata generate` renders locally without a service)"
        )
    if args.direct and not os.environ.get("OMNIDATA_DATABASE_URL"):
        raise CliError("--direct needs OMNIDATA_DATABASE_URL: the database the service's scheduler reads")
    spec = build_spec(args)
    sources = check_sources(args.spaces)
    if refused := refused_summary(sources):
        print(f"omnidata submit: refused scene(s), left out of the job:\n{refused}", file=sys.stderr)
    sources = usable(sources)
    if args.api:
        api = Api(args.api, args.token)
        job_id = submit_http(api, spec, sources)
        status: Callable[[int], Status] = api.status
        close: Callable[[], None] = api.client.close
    else:
        from services.core.settings import load_settings

        settings = load_settings()
        job_id = submit_db(settings, spec, sources, args.owner)
        status, close = db_status_fn(settings)
    print(job_id, flush=True)
    try:
        if not args.follow:
            return 0
        final = follow(job_id, status, args.interval)
    finally:
        close()
    if final.state == JobState.DONE:
        return 0
    print(f"omnidata submit: job {job_id} {final.state}" + (f": {final.error}" if final.error else ""),
          file=sys.stderr)
    return 1
