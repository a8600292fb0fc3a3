"""Space routes: upload (multipart, streamed, size-limited), register a staged object, list, get, delete; the
side views of an ambiguous space's up candidates and the person's pick."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import anyio
from fastapi import APIRouter, Request, Response, status
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from services.api.deps import ReadSessionDep, SessionDep, SettingsDep, StoreDep, TenantDep
from services.api.errors import validation_errors
from services.api.pagination import Page, PageDep
from services.api.spaces import service, up_choice
from services.api.spaces.schemas import SpaceOptions, SpaceRead, SpaceRegister, UpChoice
from services.api.spaces.upload import receive_upload
from services.api.throttle import ScanSlot
from services.core.domain.json_types import JSONObject
from services.core.temp_dirs import owned_temp_dir

router = APIRouter(prefix="/spaces", tags=["spaces"])

T = TypeVar("T")
_BUSY: dict[int | str, JSONObject] = {429: {"description": "too many of your scan reads at once"}}

SpaceId = Annotated[int, PathParam(ge=1, le=2**63 - 1, description="space id")]

_UPLOAD_BODY: JSONObject = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {
                            "type": "string",
                            "format": "binary",
                            "description": "a mesh (.ply, .obj, .glb, .gltf), a point cloud "
                            "(.ply, .xyz, .pts) or a .zip with mesh + textures",
                        },
                        "capture": {
                            "type": "string",
                            "format": "binary",
                            "description": "optional: a .zip of the scan's posed capture (COLMAP, "
                            "transforms.json, ScanNet export, 7-Scenes frames, camera_poses.json), stored "
                            "with the scan",
                        },
                        "name": {"type": "string", "description": "default: the file name without extension"},
                        "up_axis": {"type": "string", "enum": ["auto", "+x", "-x", "+y", "-y", "+z", "-z"]},
                        "unit_scale": {
                            "anyOf": [
                                {"type": "number", "exclusiveMinimum": 0, "maximum": 1000}, {"const": "auto"},
                            ],
                            "description": "metres per source unit, or auto (default: from the storey "
                            "height)",
                        },
                    },
                }
            }
        },
    }
}


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=SpaceRead,
    openapi_extra=_UPLOAD_BODY,
    summary="Upload a scan",
    responses={413: {"description": "larger than the upload limit"}, 422: {"description": "unusable scan"},
               **_BUSY},
    dependencies=[ScanSlot],
)
async def upload_space(
    request: Request, response: Response, session: SessionDep, store: StoreDep, settings: SettingsDep,
    tenant: TenantDep,
) -> SpaceRead:
    """Upload a mesh or archive; it is validated (format, counts, units, bounds) before it is stored."""
    # named after this process (swept at start-up if it is killed); made and removed off the event loop
    temp = await run_in_threadpool(owned_temp_dir, "upload")
    tmp = temp.name
    try:
        upload = await receive_upload(request, dest_dir=Path(tmp), max_bytes=settings.upload_max_bytes)
        assert upload.path is not None and upload.filename is not None
        try:
            opts = SpaceOptions.model_validate(upload.fields)
        except ValidationError as e:
            errors = validation_errors(e.errors())
            raise RequestValidationError([{**err, "loc": ["body", *err["loc"]]} for err in errors]) from None
        source = upload.path
        if upload.capture_path is not None:  # scan + capture as two parts: one folder, stored together
            from services.core.ingest.capture.bundle import bundle_scan_and_capture

            source = await run_in_threadpool(bundle_scan_and_capture, upload.path, upload.capture_path,
                                             Path(tmp) / "bundle" / Path(upload.filename).stem)
        create = functools.partial(
            service.create_space,
            session,
            store,
            settings,
            owner=tenant,
            name=opts.name or service.default_name(upload.filename),
            source_path=source,
            up_axis=opts.up_axis,
            unit_scale=opts.unit_scale,
        )
        space = await _read_scan(request, create)
    finally:
        await run_in_threadpool(temp.cleanup)
    response.headers["Location"] = f"/spaces/{space.id}"
    return SpaceRead.from_row(space)


@router.post(
    "/register",
    status_code=status.HTTP_201_CREATED,
    response_model=SpaceRead,
    summary="Register a scan already in object storage",
    responses=_BUSY,
    dependencies=[ScanSlot],
)
async def register_space(
    body: SpaceRegister, request: Request, response: Response, session: SessionDep, store: StoreDep,
    settings: SettingsDep, tenant: TenantDep,
) -> SpaceRead:
    """Register an object staged under `uploads/<tenant>/` in the service's store (validated like an
    upload)."""
    key = service.staged_key(settings, owner=tenant, key=body.key, uri=body.uri)
    register = functools.partial(service.register_staged, session, store, settings, owner=tenant, key=key,
                                  name=body.name, up_axis=body.up_axis, unit_scale=body.unit_scale)
    space = await _read_scan(request, register)
    response.headers["Location"] = f"/spaces/{space.id}"
    return SpaceRead.from_row(space)


@router.get("", response_model=Page[SpaceRead], summary="List spaces")
def list_spaces(session: ReadSessionDep, tenant: TenantDep, page: PageDep) -> Page[SpaceRead]:
    """The caller's spaces, newest first."""
    rows, total = service.list_spaces(session, owner=tenant, page=page)
    return Page[SpaceRead](
        items=[SpaceRead.from_row(s) for s in rows], total=total, limit=page.limit, offset=page.offset
    )


@router.get("/{space_id}", response_model=SpaceRead, summary="Get a space")
def get_space(space_id: SpaceId, session: ReadSessionDep, tenant: TenantDep) -> SpaceRead:
    """One of the caller's spaces."""
    return SpaceRead.from_row(service.get_space(session, owner=tenant, space_id=space_id))


@router.delete("/{space_id}", status_code=status.HTTP_204_NO_CONTENT, summary="Delete a space")
def delete_space(space_id: SpaceId, session: SessionDep, store: StoreDep, tenant: TenantDep) -> Response:
    """Delete a space and its stored source (409 while a job uses it)."""
    service.delete_space(session, store, owner=tenant, space_id=space_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


async def _read_scan(request: Request, func: Callable[..., T], *args: Any) -> T:
    """`func(*args)` (work that reads a scan, in a child process) in a thread of the API's few scan-reading
    slots: 40 up choices at once wait for a slot instead of starting 40 readers that starve the event loop."""
    limiter: anyio.CapacityLimiter = request.app.state.scan_reads.get()
    return await anyio.to_thread.run_sync(functools.partial(func, *args), limiter=limiter)


CandidateIndex = Annotated[
    int, PathParam(ge=0, le=2, description="0: detection's best, 1: the runner-up, 2: the next")
]


@router.get("/{space_id}/up-candidates/{index}.png", summary="Side view of a space under an up candidate",
            response_class=Response, responses={200: {"content": {"image/png": {}}}, **_BUSY},
            dependencies=[ScanSlot])
async def up_candidate_preview(space_id: SpaceId, index: CandidateIndex, request: Request,
                               session: ReadSessionDep, store: StoreDep, settings: SettingsDep,
                               tenant: TenantDep) -> Response:
    """A small PNG: the scan seen from the side with up candidate `index` pointing to the top of the
    picture."""
    space = await run_in_threadpool(service.get_space_released, session, owner=tenant, space_id=space_id)
    png = await _read_scan(request, up_choice.candidate_preview, store, settings, space, index)
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


@router.put("/{space_id}/up", response_model=SpaceRead, summary="Pick the up direction of a space",
            responses=_BUSY, dependencies=[ScanSlot])
async def choose_up(space_id: SpaceId, body: UpChoice, request: Request, session: SessionDep, store: StoreDep,
                    settings: SettingsDep, tenant: TenantDep) -> SpaceRead:
    """Store the up (source coordinates) and/or units a person picked; later jobs plan the space in that
    frame."""
    space = await run_in_threadpool(service.get_space_released, session, owner=tenant, space_id=space_id)
    loaded = await _read_scan(request, up_choice.load_choice, store, settings, space, body.up,
                              body.unit_scale)
    space = await run_in_threadpool(up_choice.record_up, session, space, loaded, tenant)
    return SpaceRead.from_row(space)
