"""Output routes: a view's cue files as pre-signed links, the job's manifest.jsonl and job.json, signed
blobs."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Iterator
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from sqlalchemy import select

from services.api.deps import ReadSessionDep, SettingsDep, StoreDep, TenantDep
from services.api.jobs.service import get_job
from services.api.outputs import service
from services.api.outputs.schemas import ViewOutputs
from services.api.spaces.service import not_found
from services.api.throttle import BulkSlot
from services.core.db.manifest import iter_manifest_chunks, job_document, manifest_line
from services.core.db.models import Space, View
from services.core.domain import keys
from services.core.domain.errors import NotFound
from services.core.storage import LocalStore, ObjectNotFoundError, ObjectStore, check_key, prefixed
from services.datasets.previews import PIXEL_JSON_CUES, cached_preview, parse_preview_key

router = APIRouter(tags=["outputs"])

JobId = Annotated[int, Path(ge=1, le=2**63 - 1)]
SpaceId = Annotated[int, Path(ge=1, le=2**63 - 1)]
Index = Annotated[int, Path(ge=0, le=2**31 - 1)]


def _signed_key(route: str) -> Callable[..., str]:
    def signed_key(
        key: str,
        request: Request,
        settings: SettingsDep,
        session: ReadSessionDep,
        job: Annotated[int, Query(ge=1, le=2**63 - 1, description="the job the link belongs to")],
        expires: Annotated[int, Query(ge=0, le=2**62)],
        signature: Annotated[str, Query(pattern="^[0-9a-f]{64}$", description="hex HMAC from the link")],
    ) -> str:
        """The `{key:path}` of a signed link, once its signature checked out (403) and it is the job's
        (404)."""
        service.check_single_link_params(request.query_params.multi_items())
        service.verify_blob(settings, route=route, job_id=job, key=key, expires=expires, signature=signature)
        service.check_job_key(session, job_id=job, key=key)
        return key

    return signed_key


SignedBlobKey = Annotated[str, Depends(_signed_key("blobs"))]
SignedPreviewKey = Annotated[str, Depends(_signed_key("previews"))]


@router.get(
    "/jobs/{job_id}/views/{space_id}/{point}/{view}/outputs",
    response_model=ViewOutputs,
    summary="Output files of a view (pre-signed links)",
)
def view_outputs(
    job_id: JobId,
    space_id: SpaceId,
    point: Index,
    view: Index,
    session: ReadSessionDep,
    store: StoreDep,
    settings: SettingsDep,
    tenant: TenantDep,
) -> ViewOutputs:
    """Links to every finished cue file of view `view` of point `point`; they expire after
    presign_expiry_s."""
    job = get_job(session, owner=tenant, job_id=job_id)
    row = session.execute(
        select(View.v, Space.name)
        .join(Space, Space.id == View.space_id)
        .where(View.job_id == job.id, View.space_id == space_id, View.point_idx == point, View.v == view)
    ).first()
    if row is None:
        raise not_found("view", f"{space_id}/{point}/{view} of job {job_id}")
    tasks = service.view_tasks(session, job=job, space_id=space_id, point=point, view=view)
    outputs = service.links(
        store, settings, job=job, space_name=row[1], tasks=tasks, base_url=service.link_base(settings),
        view=view,
    )
    return ViewOutputs(
        job_id=job.id, space_id=space_id, space=row[1], point=point, view=view, outputs=outputs
    )


MANIFEST_CHUNK_POINTS = 100  # points read per short session while streaming: ~300 lines, a few hundred KB


@router.get(
    "/jobs/{job_id}/manifest.jsonl",
    summary="The job's manifest (one JSON line per view)",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/x-ndjson": {}}}, 429: {"description": "too many bulk reads"}},
    dependencies=[BulkSlot],
)
def manifest(
    job_id: JobId, request: Request, session: ReadSessionDep, tenant: TenantDep
) -> StreamingResponse:
    """manifest.jsonl rebuilt from the database: {space, point, view, outputs: {cue: {key, size, sha256}}} per
    line."""
    job = get_job(session, owner=tenant, job_id=job_id)  # 404 before the stream starts
    maker = request.app.state.read_sessionmaker

    def lines() -> Iterator[bytes]:
        # Each chunk is read in a session closed before it is sent: a reader that stops reading holds no
        # database connection, only its place in the tenant's bulk reads (BulkSlot) until the stream ends.
        for chunk in iter_manifest_chunks(maker, job, points=MANIFEST_CHUNK_POINTS):
            yield "".join(manifest_line(entry) for entry in chunk).encode("utf-8")

    return StreamingResponse(
        lines(),
        media_type="application/x-ndjson",
        headers={"Content-Disposition": f'attachment; filename="job-{job_id}-manifest.jsonl"'},
    )


@router.get("/jobs/{job_id}/job.json", dependencies=[BulkSlot],
            summary="The job's job.json (spec, conventions, cue encodings, spaces)")
def job_json(job_id: JobId, session: ReadSessionDep, tenant: TenantDep) -> JSONResponse:
    """job.json rebuilt from the database."""
    job = get_job(session, owner=tenant, job_id=job_id)
    return JSONResponse(job_document(session, job))


@router.get(
    "/blobs/{key:path}",
    summary="Fetch an output through a signed link (local stores)",
    responses={
        200: {"content": {"application/octet-stream": {}}}, 403: {"description": "bad or expired link"},
    },
)
def blob(key: SignedBlobKey, store: StoreDep) -> Response:
    """Serve an object named by a link from the outputs routes; the signature is the credential."""
    try:
        check_key(key)
    except ValueError:
        raise NotFound("no such object") from None
    headers = {"Cache-Control": "private, max-age=300"}
    media = service.content_type(key)
    if isinstance(store, LocalStore):
        try:
            path = store.path(key)
        except ObjectNotFoundError:  # a link in the store: not an object
            raise NotFound("no such object") from None
        if not path.is_file():
            raise NotFound("no such object")
        return FileResponse(path, media_type=media, headers=headers)
    try:
        data = store.get_bytes(key)
    except ObjectNotFoundError:
        raise NotFound("no such object") from None
    return Response(data, media_type=media, headers=headers)


@router.get(
    "/previews/{key:path}",
    summary="A cue file's preview PNG through a signed link (made on first request, then cached)",
    responses={200: {"content": {"image/png": {}}}, 403: {"description": "bad or expired link"}},
)
async def preview(key: SignedPreviewKey, request: Request, store: StoreDep) -> Response:
    """Serve the preview named by a `preview_url` of the outputs routes, making and storing it when
    missing."""
    # decoding a cue file and drawing it is CPU work: a few at a time, or a gallery of 100 starves the rest
    limiter = request.app.state.preview_draws.get()
    data = await anyio.to_thread.run_sync(functools.partial(_preview_png, store, key), limiter=limiter)
    return Response(data, media_type="image/png", headers={"Cache-Control": "private, max-age=300"})


def _preview_png(store: ObjectStore, key: str) -> bytes:
    """The PNG of the preview `key`, made and stored when missing (NotFound: a bad key, a missing output)."""
    try:
        root, output_key, cue, point, view = parse_preview_key(check_key(key))
    except ValueError:
        raise NotFound("no such preview") from None
    job_store = prefixed(store, root)
    resolution = None
    if cue in PIXEL_JSON_CUES:  # drawn at pixel positions: the view's resolution is in its point_info
        _cue, component, space = output_key.split("/")[:3]
        try:
            info = job_store.get_bytes(keys.output_key("point_info", component, space, point, view))
            resolution = json.loads(info).get("resolution")
        except (ObjectNotFoundError, ValueError):
            pass  # drawn on a default-size tile
    try:
        _key, data = cached_preview(job_store, output_key, cue, point=point, view=view, resolution=resolution)
    except ObjectNotFoundError:
        raise NotFound("no such output") from None
    return data
