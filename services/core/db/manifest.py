"""A job's `manifest.jsonl` and `job.json`, built from the database (execution contract: Completion).

Both can be rebuilt at any time from the rows alone (the API serves them; `generate` and the scheduler
write them when a job finishes). Output keys in the manifest are relative to the job's output root, so a
copied output folder is self-describing.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, nullcontext
from datetime import datetime
from itertools import chain
from pathlib import Path
from typing import NotRequired, TypedDict

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.core.db.compacted import iter_compacted, space_names
from services.core.db.counters import job_progress
from services.core.db.jobs import job_cues, job_root, job_spaces, root_key
from services.core.db.models import Job, Space, Task, TaskState, View, ViewOutput
from services.core.domain.cues import CATALOG
from services.core.domain.job_document import JobDocument, SpaceRecord, job_json_bytes, space_record
from services.core.domain.job_document import job_document as build_job_document
from services.core.domain.keys import JOB_JSON_KEY, MANIFEST_KEY, output_key
from services.core.storage import ObjectStore

POINT_CHUNK = 2_000  # points read per query while streaming the manifest (bounds memory on 1M-task jobs)


def _relative(job: Job, key: str | None, fallback: str) -> str:
    """A stored output key relative to the job root (workers may record it with or without the root)."""
    if not key:
        return fallback
    root = job_root(job)
    if root and key.startswith(root + "/"):
        return key[len(root) + 1 :]
    return key


class ManifestOutput(TypedDict):
    key: str
    size: int | None
    sha256: str | None


class ManifestEntry(TypedDict):
    """One line of manifest.jsonl: a view and its done outputs."""

    space: str
    point: int
    view: int
    outputs: dict[str, ManifestOutput]
    alignment: NotRequired[float]  # capture views: the photo/geometry alignment score


def _done_outputs(
    session: Session, job: Job, space: Space, points: tuple[int, int], public: list[str],
    names: dict[int, str],
) -> dict[tuple[int, int], dict[str, ManifestOutput]]:
    """(point, view) -> cue -> output, of the done public tasks of points [p0, p1) of a space: task rows and
    compacted views."""
    p0, p1 = points
    rows = session.execute(
        select(Task.point_idx, Task.view_idx, Task.cue, Task.output_key, Task.size, Task.sha256)
        .where(
            Task.job_id == job.id, Task.space_id == space.id, Task.state == TaskState.DONE,
            Task.point_idx >= p0, Task.point_idx < p1, Task.cue.in_(public),
        )
        .order_by(Task.point_idx, Task.view_idx, Task.cue)
    )
    compacted = (
        (p, v, t.cue, t.output_key, t.size, t.sha256)
        for (_s, p, v), tasks in iter_compacted(
            session, job, ViewOutput.space_id == space.id, ViewOutput.point_idx >= p0,
            ViewOutput.point_idx < p1, names=names,
        )
        for t in tasks
        if t.cue in public
    )
    outputs: dict[tuple[int, int], dict[str, ManifestOutput]] = {}
    for p, v, cue, key, size, sha in chain(rows, compacted):
        fallback = output_key(cue, job.name, space.name, int(p), int(v))
        outputs.setdefault((int(p), int(v)), {})[cue] = {
            "key": _relative(job, key, fallback),
            "size": None if size is None else int(size),
            "sha256": sha,
        }
    return outputs


def iter_manifest(session: Session, job: Job) -> Iterator[ManifestEntry]:
    """One dict per view: {"space", "point", "view", "outputs": {cue: {"key", "size", "sha256"}}}, plus
    "alignment" (the photo/geometry score) for views at capture cameras.

    Sorted by space name, point, view; internal cues (the pass cache) are left out; per-point cues
    appear on view 0 of their point; only done tasks are listed (task rows and compacted views alike).
    """
    for chunk in iter_manifest_chunks(lambda: nullcontext(session), job):
        yield from chunk


def iter_manifest_chunks(
    sessions: Callable[[], AbstractContextManager[Session]], job: Job, *, points: int = POINT_CHUNK
) -> Iterator[list[ManifestEntry]]:
    """The entries of iter_manifest, `points` points of a space at a time, each chunk read in a session of its
    own from `sessions` and closed before the chunk is handed out: a consumer that stops between chunks (a
    client reading a streamed manifest slowly) holds no database connection."""
    public = [n for n, c in CATALOG.items() if not c.internal]
    with sessions() as session:
        names = space_names(session, job.id)
        spaces = sorted((space for _job_space, space in job_spaces(session, job.id)),
                        key=lambda space: space.name)
        max_points = {space.id: session.scalar(  # one index lookup per space
            select(func.max(View.point_idx)).where(View.job_id == job.id, View.space_id == space.id)
        ) for space in spaces}
    planned = (job.plan_summary or {}).get("spaces", {})
    for space in spaces:
        # capture views: the photo/geometry alignment score of each view, "point/view" -> score
        alignment = (planned.get(space.name, {}).get("capture_plan") or {}).get("view_alignment") or {}
        max_point = max_points.get(space.id)
        if max_point is None:
            continue
        for p0 in range(0, int(max_point) + 1, points):
            with sessions() as session:
                views = session.execute(
                    select(View.point_idx, View.v)
                    .where(View.job_id == job.id, View.space_id == space.id, View.point_idx >= p0,
                           View.point_idx < p0 + points)
                    .order_by(View.point_idx, View.v)
                ).all()
                outputs = _done_outputs(session, job, space, (p0, p0 + points), public, names)
            chunk: list[ManifestEntry] = []
            for p, v in views:
                outs = outputs.get((int(p), int(v)), {})
                entry: ManifestEntry = {
                    "space": space.name,
                    "point": int(p),
                    "view": int(v),
                    "outputs": {c: outs[c] for c in public if c in outs},  # catalog order
                }
                if f"{p}/{v}" in alignment:
                    entry["alignment"] = alignment[f"{p}/{v}"]
                chunk.append(entry)
            yield chunk


def manifest_line(entry: ManifestEntry) -> str:
    """One line of manifest.jsonl (ending in a newline)."""
    return json.dumps(entry, separators=(",", ":"), sort_keys=False) + "\n"


def iter_manifest_lines(session: Session, job: Job) -> Iterator[str]:
    """The manifest as JSON lines (each ending in a newline)."""
    for entry in iter_manifest(session, job):
        yield manifest_line(entry)


def manifest_bytes(session: Session, job: Job) -> bytes:
    """The whole manifest.jsonl in memory (small jobs; use iter_manifest_lines to stream big ones)."""
    return "".join(iter_manifest_lines(session, job)).encode("utf-8")


def _iso(dt: datetime | None) -> str | None:
    return None if dt is None else dt.isoformat()


def _space_records(session: Session, job: Job) -> dict[str, SpaceRecord]:
    plan_spaces = (job.plan_summary or {}).get("spaces", {})
    spaces: dict[str, SpaceRecord] = {}
    for job_space, space in job_spaces(session, job.id):
        planned = plan_spaces.get(space.name, {})
        spaces[space.name] = space_record(
            space_id=space.id, position=job_space.position, cues=job_space.cues, checksum=space.checksum,
            source_format=space.source_format,
            # the job's own load (its up_axis/unit_scale) wins over the space's defaults
            source_to_world=planned.get("source_to_world", space.source_to_world),
            unit_scale=planned.get("unit_scale", space.unit_scale),
            up_axis=planned.get("up_axis", space.up_axis), bounds=planned.get("bounds", space.bounds),
            face_count=space.face_count, has_texture=space.has_texture, has_semantics=space.has_semantics,
            counts=planned, shortfall=planned.get("shortfall"), valid_fraction=planned.get("valid_fraction"),
            clips=planned.get("clips"), plan=_relative(job, planned.get("plan_key"), "") or None,
            warnings=planned.get("warnings", []), frame=planned, distributions=planned.get("distributions"),
        )
    return spaces


def job_document(session: Session, job: Job) -> JobDocument:
    """The content of job.json (services.core.domain.job_document), from the job's rows."""
    spec = job.spec or {}
    return build_job_document(
        stage="render",
        job={
            "id": job.id,
            "name": job.name,
            "owner": job.owner,
            "state": job.state,
            "error": job.error,
            "output_root": job.output_root,
            "created_at": _iso(job.created_at),
            "started_at": _iso(job.started_at),
            "finished_at": _iso(job.finished_at),
            "total_tasks": int(job.total_tasks or 0),
        },
        component=job.name or str(spec.get("name", "")),
        spec=spec,
        cues=job_cues(session, job.id),
        spaces=_space_records(session, job),
        plan_summary={k: v for k, v in (job.plan_summary or {}).items() if k != "spaces"},
        counts=job_progress(session, job.id),
    )


def write_job_files(session: Session, store: ObjectStore, job: Job) -> tuple[str, str]:
    """Write manifest.jsonl (streamed through a temporary file) and job.json under the job's root.

    Returns their store keys. job.json is written last, so its presence means the manifest is complete.
    """
    mkey, jkey = root_key(job, MANIFEST_KEY), root_key(job, JOB_JSON_KEY)
    fd, tmp = tempfile.mkstemp(prefix="manifest-", suffix=".jsonl")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            for line in iter_manifest_lines(session, job):
                f.write(line)
        store.put_file(mkey, Path(tmp), content_type="application/x-ndjson")
    finally:
        Path(tmp).unlink(missing_ok=True)
    store.put_bytes(jkey, job_json_bytes(job_document(session, job)), content_type="application/json")
    return mkey, jkey
