"""Plan cues (services/worker/cues/plan_cues.py): the JSON of services.core.domain.plan's functions."""

from __future__ import annotations

import pytest

from services.core.domain.plan_cues import nonfixated as plan_nonfixated
from services.core.domain.plan_cues import point_info
from services.core.domain.plan_cues import vanishing_points as plan_vanishing_points
from services.worker.context import ViewContext
from services.worker.cues.encoding import encode_json
from services.worker.executor import produce
from tests.fixtures.plans import small_plan

RES = 64


def test_plan_cues_are_the_plan_functions_json() -> None:
    plan = small_plan()
    view = plan.view(1, 0)
    ctx = ViewContext(view, plan=plan)
    info = point_info(plan, view)
    assert produce("point_info", ctx) == encode_json(info)
    assert produce("nonfixated", ctx) == encode_json(plan_nonfixated(plan, 1))
    assert produce("vanishing_points", ctx) == encode_json(plan_vanishing_points(info))
    assert produce("point_info", ViewContext(view, plan=plan)) == produce("point_info", ctx)  # deterministic
    with pytest.raises(RuntimeError, match="plan"):
        produce("nonfixated", ViewContext(view))
    # A ready point_info (from the database) needs no plan.
    assert produce("point_info", ViewContext(view, point_info=info)) == encode_json(info)
