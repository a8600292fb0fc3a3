"""Fitting a spec to a target's distributions on a small room, and reading a target from a path."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.core.domain.jobspec import JobSpec
from services.core.domain.steering import ks_statistic, view_distributions
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.planning.fit import fit_spec, load_target
from tests.fixtures import scenes
from tests.fixtures.captures import toy_frames, write_colmap

BASE = {"cameras": {"max_count": 80, "min_spacing_m": 0.3}, "points": {"count": 60, "min_views": 2,
                                                                        "max_views": 8},
        "views": {"resolution": 64}}


def test_fitting_moves_the_ks_statistics_below_the_threshold() -> None:
    space = scenes.as_space(scenes.l_room())
    rng = np.random.default_rng(5)
    target = {"fov_deg": rng.normal(55.0, 4.0, 300), "pitch_deg": rng.normal(-15.0, 6.0, 300),
              "height_m": rng.normal(1.3, 0.1, 300), "roll_deg": rng.normal(0.0, 2.0, 300)}
    base = JobSpec.model_validate(BASE)
    plan = make_plan(space, base, space_rng(base.seed, "room"), "room")
    before = view_distributions(plan, floor_z=0.0)
    fit = fit_spec(space, base, target, floor_z=0.0, space_name="room", rounds=3)
    for name in ("fov_deg", "pitch_deg", "height_m"):
        assert ks_statistic(before[name], target[name]) > 0.4
        assert fit.ks[name] < 0.15, (name, fit.ks)
    spec = fit.spec
    assert spec.cameras.floors == "lowest" and spec.cameras.height_quantiles_m is not None
    assert len(spec.views.pitch_quantiles_deg or ()) == 21
    assert fit.ks["roll_deg"] < 0.15 and len(spec.views.roll_quantiles_deg or ()) == 21
    assert spec.points == base.points  # the size knobs stay the user's
    # the fitted spec, planned again as it is, gives the plan the statistics were measured on
    again = view_distributions(make_plan(space, spec, space_rng(spec.seed, "room"), "room"), floor_z=0.0)
    assert ks_statistic(again["pitch_deg"], target["pitch_deg"]) == fit.ks["pitch_deg"]


def test_load_target_of_a_capture_alone_has_no_heights(tmp_path: Path) -> None:
    write_colmap(tmp_path, toy_frames(4))
    target = load_target(tmp_path)
    assert target.source == "capture:colmap"
    assert sorted(target.values) == ["fov_deg", "pitch_deg", "roll_deg"]
    # levelled by the cameras' own up (here +Z already): every toy camera looks down at the origin
    assert (target.values["pitch_deg"] < 0).all()
