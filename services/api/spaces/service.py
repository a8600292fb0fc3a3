"""Space logic: list/get with tenant isolation, register an uploaded or staged scan, delete."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from services.api.pagination import PageParams
from services.core.db.models import Job, JobSpace, Space
from services.core.domain.errors import Conflict, Invalid, NotFound, TooLarge
from services.core.ingest.errors import SpaceError
from services.core.ingest.guard.safe_load import load_space_limited
from services.core.ingest.registry import register_space
from services.core.settings import Settings
from services.core.storage import ObjectNotFoundError, ObjectStore, check_key
from services.core.temp_dirs import owned_temp_dir

STAGING_PREFIX = "uploads"  # tenants stage big scans under uploads/<tenant>/ and register them


def not_found(kind: str, ident: object) -> NotFound:
    """NotFound (404) for a missing object, and for another tenant's (never 403: existence is not
    revealed)."""
    return NotFound(f"{kind} {ident} not found")


def list_spaces(session: Session, *, owner: str, page: PageParams) -> tuple[list[Space], int]:
    """The tenant's spaces, newest first, and how many there are."""
    total = session.scalar(select(func.count()).select_from(Space).where(Space.owner == owner)) or 0
    rows = session.scalars(
        select(Space)
        .where(Space.owner == owner)
        .order_by(Space.id.desc())
        .limit(page.limit)
        .offset(page.offset)
    ).all()
    return list(rows), int(total)


def get_space(session: Session, *, owner: str, space_id: int) -> Space:
    """The tenant's space `space_id`, or 404."""
    space = session.get(Space, space_id)
    if space is None or space.owner != owner:
        raise not_found("space", space_id)
    return space


def get_space_released(session: Session, *, owner: str, space_id: int) -> Space:
    """get_space, then the session's connection back to the pool (the row stays readable, and writable
    through the same session later): for routes that read the space's scan for seconds before they write."""
    space = get_space(session, owner=owner, space_id=space_id)
    session.commit()
    return space


def _check_name_free(session: Session, *, owner: str, name: str) -> None:
    existing = session.scalar(select(Space.id).where(Space.owner == owner, Space.name == name))
    if existing is not None:
        raise Conflict(
            f"a space named {name!r} already exists (id {existing}); choose another name or delete it first"
        )


def default_name(filename: str) -> str:
    """Space name from a file name: the part before the first dot ('room.tar.zip' -> 'room')."""
    return filename.split(".", 1)[0] or "space"


def create_space(
    session: Session,
    store: ObjectStore,
    settings: Settings,
    *,
    owner: str,
    name: str,
    source_path: Path,
    up_axis: str,
    unit_scale: float | str,
) -> Space:
    """Validate the scan at `source_path` and register it (stored under spaces/<id>/); 422 when it is
    unusable."""
    _check_name_free(session, owner=owner, name=name)
    try:
        # parsed in a child process with memory and time limits: a hostile file cannot take the API down
        loaded = load_space_limited(
            source_path,
            up_axis=up_axis,
            unit_scale=unit_scale,
            max_faces=settings.upload_max_faces,
            memory_mb=settings.upload_parse_memory_mb,
            timeout_s=settings.upload_parse_timeout_s,
        )
        space = register_space(
            session, store, owner=owner, name=name, source_path=source_path, up_axis=up_axis,
            unit_scale=unit_scale,
            loaded=loaded,
        )
        session.commit()
    except SpaceError as e:
        session.rollback()
        raise Invalid(f"space rejected: {e}") from None
    return space


def staged_key(settings: Settings, *, owner: str, key: str | None, uri: str | None) -> str:
    """The object key a register request names; it must lie in the tenant's staging area uploads/<tenant>/."""
    if (key is None) == (uri is None):
        raise Invalid("give exactly one of 'key' or 'uri'")
    if uri is not None:
        root = settings.storage_url.rstrip("/") + "/"
        if not uri.startswith(root):
            raise Invalid(f"uri {uri!r} is not in this service's object store ({root}...)")
        key = uri[len(root) :]
    assert key is not None
    try:
        check_key(key)
    except ValueError as e:
        raise Invalid(str(e)) from None
    area = f"{STAGING_PREFIX}/{owner}/"
    if not key.startswith(area):
        raise Invalid(
            f"key {key!r} is outside your staging area: stage scans under '{area}' and register them "
            "from there"
        )
    return key


def register_staged(
    session: Session,
    store: ObjectStore,
    settings: Settings,
    *,
    owner: str,
    key: str,
    name: str | None,
    up_axis: str,
    unit_scale: float | str,
) -> Space:
    """Register the staged object `key` as a space (copied to spaces/<id>/; the staged object is kept)."""
    info = store.stat(key)
    if info is None:
        raise not_found("object", repr(key))
    if info.size > settings.upload_max_bytes:
        raise TooLarge(
            f"object {key!r} has {info.size} bytes, above the limit of {settings.upload_max_bytes}"
        )
    filename = key.rsplit("/", 1)[-1]
    name = name or default_name(filename)
    _check_name_free(session, owner=owner, name=name)
    with owned_temp_dir("register") as tmp:
        path = Path(tmp) / filename
        try:
            store.get_file(key, path)
        except ObjectNotFoundError:
            raise not_found("object", repr(key)) from None
        return create_space(
            session, store, settings, owner=owner, name=name, source_path=path, up_axis=up_axis,
            unit_scale=unit_scale,
        )


def delete_space(session: Session, store: ObjectStore, *, owner: str, space_id: int) -> None:
    """Delete the space and its stored source; 409 while jobs still use it."""
    space = get_space(session, owner=owner, space_id=space_id)
    job_ids = session.scalars(
        select(JobSpace.job_id)
        .join(Job, Job.id == JobSpace.job_id)
        .where(JobSpace.space_id == space.id)
        .limit(20)
    ).all()
    if job_ids:
        raise Conflict(
            f"space {space_id} is used by job(s) {', '.join(map(str, job_ids))}; delete those jobs first"
        )
    # a DELETE that matches no row lost a race with another delete of the space: that one answered 204
    res = session.execute(delete(Space).where(Space.id == space.id, Space.owner == owner))
    if int(res.rowcount or 0) != 1:  # type: ignore[attr-defined]
        session.rollback()
        raise not_found("space", str(space_id))
    session.commit()
    store.delete_prefix(f"spaces/{space_id}/")
