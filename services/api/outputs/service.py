"""Output links: pre-signed URLs that expire (S3's own; for a local store, HMAC-signed links served by the
API).

A job's outputs are the done tasks' objects under its output root. S3 stores sign their own GET URLs; a local
folder store has no URL a browser can fetch, so the API signs `/blobs/<key>?job=&expires=&signature=` with
HMAC-SHA256(secret_key) over the route, the job, the key and the expiry, and serves the file only while the
signature is valid and unexpired and the key lies under that job's own output root: a link names one job's
files, whatever else the store holds. Links start with `public_base_url` (the address clients reach the API
at, configured), never with the request's Host header, which any client can set; without one they are
root-relative.
"""

from __future__ import annotations

import hashlib
import hmac
import time
from collections.abc import Iterable
from datetime import UTC, datetime
from urllib.parse import quote

from sqlalchemy import select
from sqlalchemy.orm import Session

from services.api.outputs.schemas import OutputLink
from services.core.db.compacted import compacted_tasks
from services.core.db.jobs import job_root, root_key
from services.core.db.models import Job, Task, TaskState, ViewOutput
from services.core.domain.cues import CATALOG
from services.core.domain.errors import Forbidden, NotFound
from services.core.domain.keys import output_key
from services.core.settings import Settings
from services.core.storage import ObjectStore
from services.datasets.previews import preview_key

CONTENT_TYPES = {
    "png": "image/png",
    "json": "application/json",
    "jsonl": "application/x-ndjson",
    "npy": "application/octet-stream",
    "npz": "application/octet-stream",
    "exr": "image/x-exr",
}
PUBLIC_CUES = tuple(n for n, c in CATALOG.items() if not c.internal)


def content_type(key: str) -> str:
    """MIME type from the key's extension."""
    return CONTENT_TYPES.get(key.rsplit(".", 1)[-1].lower(), "application/octet-stream")


def link_base(settings: Settings) -> str:
    """What signed links start with: the configured public base URL, else '' (root-relative links)."""
    return (settings.public_base_url or "").rstrip("/")


def blob_signature(
    settings: Settings, key: str, expires: int, *, route: str = "blobs", job_id: int = 0
) -> str:
    """HMAC-SHA256 (hex) of the route, job, `key` and expiry (unix seconds) under the service's secret key."""
    msg = f"{route}\n{job_id}\n{key}\n{expires}".encode()
    return hmac.new(settings.secret_key.get_secret_value().encode(), msg, hashlib.sha256).hexdigest()


LINK_PARAMS = ("job", "expires", "signature")


def check_single_link_params(items: list[tuple[str, str]]) -> None:
    """403 when a link gives one of its signed parameters more than once: the route would read the last one,
    which need not be the one a checker of the first would have seen."""
    names = [name for name, _ in items]
    repeated = sorted({name for name in names if name in LINK_PARAMS and names.count(name) > 1})
    if repeated:
        raise Forbidden(f"link parameter {', '.join(repeated)} given more than once")


def verify_blob(
    settings: Settings,
    *,
    route: str, job_id: int, key: str, expires: int, signature: str, now: float | None = None,
) -> None:
    """403 unless `signature` signs (route, job, key) until `expires` and that time has not passed."""
    want = blob_signature(settings, key, expires, route=route, job_id=job_id)
    if not hmac.compare_digest(want.encode(), signature.encode("utf-8", "replace")):
        raise Forbidden("invalid link signature")
    if (time.time() if now is None else now) > expires:
        raise Forbidden("link expired; ask the API for a fresh one")


def check_job_key(session: Session, *, job_id: int, key: str) -> Job:
    """The job a signed link names, when `key` lies under its own output root; 404 otherwise."""
    job = session.get(Job, job_id)
    root = job_root(job) if job is not None else ""
    if job is None or not root or not key.startswith(root + "/"):
        raise NotFound("no such object")
    return job


def signed_link(settings: Settings, route: str, *, job_id: int, key: str, base_url: str, expires: int) -> str:
    """`<base_url>/<route>/<key>?job=&expires=&signature=`: an API route serving `key` while the HMAC
    holds."""
    sig = blob_signature(settings, key, expires, route=route, job_id=job_id)
    return f"{base_url.rstrip('/')}/{route}/{quote(key)}?job={job_id}&expires={expires}&signature={sig}"


def presign(
    store: ObjectStore, settings: Settings, *, job_id: int, key: str, base_url: str
) -> tuple[str, datetime]:
    """A URL fetching `key` without a token until the returned time (settings.presign_expiry_s from now)."""
    expiry_s = settings.presign_expiry_s
    expires = int(time.time()) + expiry_s
    url = store.presigned_url(key, expiry_s)
    if not url.startswith(("http://", "https://")):
        url = signed_link(settings, "blobs", job_id=job_id, key=key, base_url=base_url, expires=expires)
    return url, datetime.fromtimestamp(expires, UTC)


def task_store_key(job: Job, task: Task, space_name: str) -> str:
    """The store key of a done task's output (workers may record it with or without the job's root)."""
    root = job_root(job)
    key = task.output_key
    if not key:
        return root_key(job, output_key(task.cue, job.name, space_name, task.point_idx, task.view_idx))
    if not root or key.startswith(root + "/"):
        return key
    return root_key(job, key)


def relative_key(job: Job, key: str) -> str:
    """A store key relative to the job's output root."""
    root = job_root(job)
    return key[len(root) + 1 :] if root and key.startswith(root + "/") else key


def signed_preview_url(settings: Settings, *, job_id: int, key: str, base_url: str) -> str:
    """`/previews/<preview key>?job=&expires=&signature=`: the preview is made on first use, then served
    cached."""
    expires = int(time.time()) + settings.presign_expiry_s
    return signed_link(settings, "previews", job_id=job_id, key=key, base_url=base_url, expires=expires)


def links(
    store: ObjectStore, settings: Settings,
    *,
    job: Job, space_name: str, tasks: Iterable[Task], base_url: str,
    view: int | None = None,
) -> dict[str, OutputLink]:
    """Pre-signed links to the outputs of done, public (non-internal) tasks, by cue in catalog order.

    Each link has a preview link too; `view` names the view shown (per-point cues are drawn per view).
    """
    found: dict[str, OutputLink] = {}
    for t in tasks:
        if t.state != TaskState.DONE or t.cue not in PUBLIC_CUES:
            continue
        key = task_store_key(job, t, space_name)
        url, expires_at = presign(store, settings, job_id=job.id, key=key, base_url=base_url)
        rel = relative_key(job, key)
        shown = t.view_idx if view is None else view
        pkey = root_key(job, preview_key(rel, t.cue, t.point_idx, shown))
        found[t.cue] = OutputLink(
            cue=t.cue,
            key=rel,
            preview_url=signed_preview_url(settings, job_id=job.id, key=pkey, base_url=base_url),
            url=url,
            expires_at=expires_at,
            size=t.size,
            sha256=t.sha256,
            content_type=content_type(key),
        )
    return {c: found[c] for c in PUBLIC_CUES if c in found}


def view_tasks(session: Session, *, job: Job, space_id: int, point: int, view: int) -> list[Task]:
    """The tasks of one view, plus the per-point cues of its point (stored on view 0); compacted views'
    too."""
    per_point = [n for n, c in CATALOG.items() if c.per_point]
    rows = session.scalars(
        select(Task).where(
            Task.job_id == job.id,
            Task.space_id == space_id,
            Task.point_idx == point,
            (Task.view_idx == view) | ((Task.view_idx == 0) & Task.cue.in_(per_point)),
        )
    ).all()
    at = (ViewOutput.job_id == job.id) & (ViewOutput.space_id == space_id) & (ViewOutput.point_idx == point)
    packed = compacted_tasks(session, job, at & (ViewOutput.view_idx == view))
    if view != 0:
        packed += [
            t for t in compacted_tasks(session, job, at & (ViewOutput.view_idx == 0)) if t.cue in per_point
        ]
    return [*rows, *packed]
