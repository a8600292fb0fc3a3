"""A spec whose plan could exceed the planning budget is refused when the job is created, naming the
budget."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import func, select

from services.core.db.models import Job
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan_budget import (
    PlanOverBudget,
    check_plan_budget,
    plan_memory_estimate_mb,
    plans_in_chunks,
)
from tests.fixtures.api import Api

SPEC_20M = {"cameras": {"mode": "object", "object_count": 100},
            # exactly 20M views: within the spec limits
            "points": {"count": 200000, "min_views": 2, "max_views": 100}}


@pytest.fixture()
def space_id(api: Api, bunny: Path) -> int:
    r = api.client.post("/spaces", files={"file": ("bunny.ply", bunny.read_bytes())}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    return int(r.json()["id"])


def test_the_20m_view_spec_is_refused_up_front_naming_the_budget(api: Api, space_id: int) -> None:
    with api.sessions() as s:
        before = s.scalar(select(func.count()).select_from(Job))
    r = api.client.post("/jobs", json={"space_ids": [space_id], "spec": SPEC_20M}, headers=api.a.headers)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "20,000,000 views" in detail and "OMNIDATA_PLAN_" in detail and "budget" in detail
    with api.sessions() as s:
        assert s.scalar(select(func.count()).select_from(Job)) == before  # nothing stored


def test_a_spec_within_the_budget_is_accepted(api: Api, space_id: int) -> None:
    spec = {"cameras": {"mode": "object", "object_count": 20}, "points": {"count": 2000, "max_views": 20}}
    r = api.client.post("/jobs", json={"space_ids": [space_id], "spec": spec}, headers=api.a.headers)
    assert r.status_code == 201, r.text


def test_budget_names_memory_or_time_whichever_is_short() -> None:
    whole = JobSpec.model_validate({"cameras": {"mode": "object", "object_count": 100},
                                    "points": {"count": 10000, "max_views": 100},
                                    "views": {"nonfixated_pruning": True}})  # 1M views, planned whole
    assert whole.views_upper_bound() == 1_000_000 and not plans_in_chunks(whole)
    with pytest.raises(PlanOverBudget, match="planning budget of 4,096 MB"):
        check_plan_budget(whole, memory_mb=4096)
    check_plan_budget(whole, memory_mb=plan_memory_estimate_mb(whole))  # exactly enough memory: accepted
    # planned in chunks, the same 1M views need memory for the points and one chunk only
    spec = JobSpec.model_validate({"cameras": {"mode": "object", "object_count": 100},
                                   "points": {"count": 10000, "max_views": 100}})
    assert plans_in_chunks(spec) and plan_memory_estimate_mb(spec) < 1024
    check_plan_budget(spec, memory_mb=1024)
    assert plan_memory_estimate_mb(spec, chunk_views=10**6) > plan_memory_estimate_mb(spec)
    with pytest.raises(PlanOverBudget, match="time budget of 60 s"):
        check_plan_budget(spec, memory_mb=10**6, timeout_s=60)


def test_the_default_room_spec_is_judged_while_planning_not_refused() -> None:
    # cameras in free space, no max_views: bounded only by cameras.max_count
    spec = JobSpec.model_validate({})
    assert spec.views_upper_bound() >= 5_000_000
    check_plan_budget(spec, memory_mb=512, timeout_s=10)  # the planner process's limits cap it instead
    with pytest.raises(PlanOverBudget):
        check_plan_budget(JobSpec.model_validate({"points": {"max_views": 1000}}), memory_mb=512)
