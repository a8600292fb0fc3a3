"""The order in which waiting jobs are claimed for planning (pure: no database)."""

from __future__ import annotations

from services.core.db.plan_claims import Waiting, fair_plan_order


def test_tenants_take_turns_and_priority_counts_only_within_a_tenant() -> None:
    waiting = [
        Waiting(1, "a", 0), Waiting(2, "a", 0), Waiting(3, "a", 9), Waiting(4, "b", 0), Waiting(5, "c", 0),
    ]
    # a's priority 9 job goes first within a, but b and c still get their turns before a's second job
    assert fair_plan_order(waiting, {}, 5) == [3, 4, 5, 1, 2]
    assert fair_plan_order(waiting, {}, 2) == [3, 4]


def test_a_tenant_with_plans_under_way_waits_behind_the_others() -> None:
    waiting = [Waiting(1, "a", 0), Waiting(7, "b", 0)]
    assert fair_plan_order(waiting, {"a": 2}, 2) == [7, 1]
    assert fair_plan_order(waiting, {"a": 1, "b": 1}, 1) == [1]  # even: the oldest waiting job first
    assert fair_plan_order([], {"a": 1}, 3) == []
