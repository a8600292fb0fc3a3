"""Steering knobs that shape distributions by quantiles: unset, plans stay byte for byte what they were; set,
the plan's distributions follow them."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import SpacePlan, plan_to_json
from services.core.domain.plan_budget import plans_in_chunks
from services.core.domain.steering import ks_statistic, view_distributions
from services.scheduler.planning import make_plan, plan_chunks, space_rng
from services.scheduler.planning.views import pitch_acceptance, quantile_sample
from tests.fixtures import scenes
from tests.fixtures.vector_isa import vector_isa

# sha256 of plan_to_json before the quantile knobs existed (this environment's numpy and Embree), on a machine
# of each vector instruction set (an AMD Zen 4 with AVX-512, a Zen 3 without)
PINNED = {
    "wide": ({"cameras": {"max_count": 30, "min_spacing_m": 0.8}, "points": {"count": 25, "max_views": 4},
              "views": {"resolution": 320}},
             {"avx512": "a3ab506a5ea0ca218b295c08451909d9a7b04579403e618449334a7331ddc888",
              "avx2": "cb626714df9cb3fd027f4b84e510960dc0ae90897de3e35dbc9b26de6bf0b094"}),
    "trajectory": ({"cameras": {"max_count": 12, "min_spacing_m": 1.0}, "points": {"count": 4},
                    "views": {"mode": "trajectory", "trajectory_max_frames": 6}},
                   {"avx512": "76b7bb59db012adc0074e914403b2fd6902791803dfce568ea946247192cecfc",
                    "avx2": "1ec388aa68f0d7ac0e15fcb678fef6504b7cf8b05b113178c7ca4f893a79c249"}),
}


def _plan(spec: dict[str, object]) -> SpacePlan:
    job = JobSpec.model_validate(spec)
    return make_plan(scenes.as_space(scenes.l_room()), job, space_rng(job.seed, "lroom"), "lroom")


@pytest.mark.parametrize("name", sorted(PINNED))
def test_unset_knobs_keep_todays_plans_byte_for_byte(name: str) -> None:
    spec, digests = PINNED[name]
    assert hashlib.sha256(plan_to_json(_plan(spec)).encode()).hexdigest() == digests[vector_isa()]


def test_quantile_sample_follows_the_quantiles() -> None:
    x = quantile_sample(np.random.default_rng(0), [10.0, 20.0, 20.0, 50.0], 30_000)
    # levels 0, 1/3, 2/3, 1: a third in [10, 20], a third at 20 exactly, a third in [20, 50]
    assert x.min() >= 10 and x.max() <= 50
    assert np.mean(x < 20) == pytest.approx(1 / 3, abs=0.01)
    assert np.mean(x == 20) == pytest.approx(1 / 3, abs=0.01)
    assert np.median(x[x > 20]) == pytest.approx(35.0, abs=0.5)


def test_pitch_acceptance_reshapes_candidates_to_the_target() -> None:
    rng = np.random.default_rng(1)
    candidates = rng.uniform(-60.0, 30.0, 40_000)
    target = np.quantile(rng.normal(-20.0, 8.0, 5000), np.linspace(0, 1, 21))
    kept = candidates[rng.random(len(candidates)) < pitch_acceptance(candidates, target)]
    assert ks_statistic(kept, rng.normal(-20.0, 8.0, 5000)) < 0.05
    assert pitch_acceptance(candidates, target).max() == pytest.approx(1.0)


def test_fitted_knobs_move_the_plan_to_the_target() -> None:
    """A small room: heights, fovs and pitches drawn from quantiles follow them (KS far below unsteered)."""
    base = {"cameras": {"max_count": 40, "min_spacing_m": 0.4}, "points": {"count": 60, "min_views": 2},
            "views": {"resolution": 64}}
    rng = np.random.default_rng(2)
    target = {"height_m": rng.normal(1.4, 0.08, 300), "fov_deg": rng.normal(50.0, 3.0, 300),
              "pitch_deg": rng.normal(-25.0, 6.0, 300)}
    levels = np.linspace(0, 1, 21)
    q = {k: np.quantile(v, levels).tolist() for k, v in target.items()}
    steered = {"cameras": {**base["cameras"], "height_quantiles_m": q["height_m"]},
               "points": base["points"],
               "views": {**base["views"], "fov_quantiles_deg": q["fov_deg"],
                         "pitch_quantiles_deg": q["pitch_deg"]}}
    before = view_distributions(_plan(base), floor_z=0.0)
    after = view_distributions(_plan(steered), floor_z=0.0)
    assert len(after["pitch_deg"]) > 50
    for name in ("height_m", "fov_deg", "pitch_deg"):
        ks_before = ks_statistic(before[name], target[name])
        ks_after = ks_statistic(after[name], target[name])
        assert ks_before > 0.4 and ks_after < 0.25, (name, ks_before, ks_after)
    assert after["views_per_point"].min() >= 2  # thinned points keep min_views or go


@pytest.mark.parametrize("knobs", [
    {"cameras": {"height_quantiles_m": [1.0, 1.2, 1.6]}},  # planned chunk by chunk
    {"views": {"pitch_quantiles_deg": [-40.0, -10.0, 5.0]}},  # planned whole, then cut
])
def test_the_scheduler_plans_steered_specs_as_make_plan_does(knobs: dict[str, dict[str, object]]) -> None:
    base = PINNED["wide"][0]
    data = {key: {**base.get(key, {}), **knobs.get(key, {})} for key in ("cameras", "points", "views")}
    spec = JobSpec.model_validate(data)
    space = scenes.as_space(scenes.l_room())
    whole = make_plan(space, spec, space_rng(spec.seed, "lroom"), "lroom")
    chunks = list(plan_chunks(space, spec, space_rng(spec.seed, "lroom"), "lroom", 16))
    assert plans_in_chunks(spec) == ("cameras" in knobs)
    assert [plan_to_json(v) for v in _views(chunks)] == [plan_to_json(v) for v in _views([whole])]


def _views(plans: list[SpacePlan]) -> list[SpacePlan]:
    """Each view as a one-view plan (comparable across chunkings)."""
    return [SpacePlan("x", (), (), (v,)) for plan in plans for v in plan.views]
