"""The designer's logic: the spec from JSON or YAML, the caller's spaces as sources, the calls to the warm
pool."""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError
from sqlalchemy.orm import Session

from services.api.designer.pool import DesignPool
from services.api.designer.schemas import DesignFit, DesignPlan, DesignPreviews, DesignRequest
from services.api.errors import summarize, validation_errors
from services.api.spaces.service import get_space
from services.core.db.frame_choice import check_frame_decided, space_frame_for
from services.core.domain.errors import Invalid
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan_budget import PlanOverBudget, check_plan_budget
from services.core.ingest.registry import fetch_space
from services.core.settings import Settings
from services.core.storage import ObjectStore


def parse_yaml(text: str) -> Any:
    """The YAML document `text` (Invalid when it is not YAML, or uses aliases: a few lines of them can expand
    to gigabytes once validated)."""
    try:
        if any(isinstance(event, yaml.AliasEvent) for event in yaml.parse(text, Loader=yaml.SafeLoader)):
            raise Invalid("spec_yaml: aliases (*name) are not accepted; write the values out")
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise Invalid(f"spec_yaml is not YAML: {e}") from None
    return {} if data is None else data


def spec_of(body: DesignRequest) -> JobSpec:
    """The request's spec: its JSON, or its YAML validated like a job's (Invalid naming each bad field)."""
    if body.spec_yaml is None:
        return body.spec if body.spec is not None else JobSpec.model_validate({})
    data = parse_yaml(body.spec_yaml)
    if not isinstance(data, dict):
        raise Invalid("spec_yaml: the spec is a mapping of knobs (cameras:, points:, views:, ...)")
    try:
        return JobSpec.model_validate(data)
    except ValidationError as e:
        raise Invalid(f"spec_yaml: {summarize(validation_errors(e.errors()), e.error_count())}") from None


def spec_yaml(spec: JobSpec) -> str:
    """The knobs of `spec` that differ from the defaults, as YAML (what `omnidata submit --spec` reads)."""
    knobs = spec.model_dump(mode="json", exclude_defaults=True)
    return yaml.safe_dump(knobs, sort_keys=False) if knobs else "{}\n"


def sources(
    session: Session,
    store: ObjectStore,
    settings: Settings,
    *,
    owner: str,
    space_ids: list[int],
    spec: JobSpec,
) -> list[dict[str, Any]]:
    """What the warm process needs of each of the caller's spaces (NotFound for another's): the local path
    of its source, its checksum and the frame a job with `spec` plans it in. Refuses a spec over the
    planning budget."""
    try:
        check_plan_budget(spec, memory_mb=settings.plan_memory_mb, timeout_s=settings.designer_timeout_s)
    except PlanOverBudget as e:
        raise Invalid(str(e).replace("OMNIDATA_PLAN_TIMEOUT_S", "OMNIDATA_DESIGNER_TIMEOUT_S")) from None
    spaces = [get_space(session, owner=owner, space_id=i) for i in space_ids]
    session.commit()  # the connection goes back to the pool while the sources are fetched
    out = []
    for space in spaces:
        try:
            check_frame_decided(spec, space)
        except ValueError as e:
            raise Invalid(str(e)) from None
        path = fetch_space(store, space, Path(settings.data_dir) / "api-space-cache")
        out.append(
            {
                "id": space.id,
                "name": space.name,
                "path": str(path),
                "checksum": space.checksum,
                "frame": dict(space_frame_for(spec, space)),
            }
        )
    return out


def plan(pool: DesignPool, spec: JobSpec, spaces: list[dict[str, Any]], tenant: str) -> DesignPlan:
    """The plan report of `spec` over `spaces` (from `sources`), from a warm process."""
    report = pool.call("plan", {"spec": spec.model_dump(mode="json"), "spaces": spaces}, tenant=tenant)
    return DesignPlan(
        spec=spec.model_dump(mode="json", exclude_defaults=True), yaml=spec_yaml(spec), **report
    )


def previews(pool: DesignPool, spec: JobSpec, spaces: list[dict[str, Any]], count: int,
             tenant: str) -> DesignPreviews:
    """Small previews of `count` views of the plan, as PNG data URLs."""
    payload = {"spec": spec.model_dump(mode="json"), "spaces": spaces, "count": count}
    out = pool.call("previews", payload, tenant=tenant)
    for view in out["previews"]:
        view["images"] = {
            cue: "data:image/png;base64," + base64.b64encode(png).decode("ascii")
            for cue, png in view["images"].items()
        }
    return DesignPreviews(**out)


def fit(pool: DesignPool, spec: JobSpec, spaces: list[dict[str, Any]], tenant: str) -> DesignFit:
    """`spec` fitted to the capture of the first of `spaces`, from a warm process."""
    out = pool.call("fit", {"spec": spec.model_dump(mode="json"), "spaces": spaces[:1]}, tenant=tenant)
    fitted = JobSpec.model_validate(out.pop("spec"))
    return DesignFit(
        spec=fitted.model_dump(mode="json", exclude_defaults=True), yaml=spec_yaml(fitted), **out
    )
