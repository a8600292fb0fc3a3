"""The quantile knobs of the JobSpec: unset by default, refused with the field named and the reason."""

from __future__ import annotations

from typing import Any

import pytest
from pydantic import ValidationError

from services.core.domain.jobspec import JobSpec


def test_unset_by_default_and_lists_become_tuples() -> None:
    spec = JobSpec()
    assert spec.views.fov_quantiles_deg is None and spec.views.pitch_quantiles_deg is None
    assert spec.cameras.height_quantiles_m is None
    assert spec.cameras.floors == "all" and spec.cameras.enclosed is True
    given = JobSpec.model_validate({"views": {"pitch_quantiles_deg": [-30, -20, -20, -5]}})
    assert given.views.pitch_quantiles_deg == (-30.0, -20.0, -20.0, -5.0)


@pytest.mark.parametrize(("data", "message"), [
    ({"views": {"fov_quantiles_deg": [60.0]}}, "needs 2 to 101 quantiles"),
    ({"views": {"fov_quantiles_deg": [0.5, 60.0]}}, r"must lie in \[1.0, 179.0\]"),
    ({"views": {"pitch_quantiles_deg": [10.0, -10.0]}}, "non-decreasing"),
    ({"views": {"pitch_quantiles_deg": [-10.0, float("nan")]}}, "finite"),
    ({"views": {"mode": "trajectory", "pitch_quantiles_deg": [-10.0, 10.0]}}, "trajectory"),
    ({"cameras": {"height_quantiles_m": [-1.0, 1.0]}}, r"must lie in \[0.0, 100.0\]"),
    ({"cameras": {"height_quantiles_m": list(range(102))}}, "needs 2 to 101"),
    ({"cameras": {"floors": "upper"}}, "all"),
    ({"views": {"roll_quantiles_deg": [-200.0, 0.0]}}, r"must lie in \[-180.0, 180.0\]"),
])
def test_bad_quantiles_are_refused_naming_the_field(data: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message) as e:
        JobSpec.model_validate(data)
    section = next(iter(data))
    assert e.value.errors()[0]["loc"][0] == section
