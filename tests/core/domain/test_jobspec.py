"""JobSpec: defaults follow the Omnidata annotator; every refusal names the field and says why."""

from __future__ import annotations

from typing import Any

import pytest
from pydantic import ValidationError

from services.core.domain.jobspec import JobSpec, cues_for_space


def _refusal(data: dict[str, Any]) -> tuple[tuple[Any, ...], str]:
    """The (loc, message) of the single error JobSpec raises for `data`."""
    with pytest.raises(ValidationError) as e:
        JobSpec.model_validate(data)
    errors = e.value.errors()
    assert len(errors) == 1, errors
    return tuple(errors[0]["loc"]), str(errors[0]["msg"])


def test_defaults_follow_the_annotator() -> None:
    s = JobSpec()
    assert s.cues is None and s.seed == 0 and s.name == "omnidata"
    assert s.cameras.mode == "generate" and s.cameras.min_spacing_m == 0.5
    assert (s.cameras.height_min_m, s.cameras.height_max_m, s.cameras.clearance_m) == (0.2, 2.0, 0.1)
    assert s.points.per_camera == 5 and s.points.min_views == 3 and s.points.max_views is None
    assert s.points.los_tolerance_m == 0.001
    assert (s.views.fov_min_deg, s.views.fov_mean_deg, s.views.fov_max_deg) == (30.0, 77.5, 125.0)
    assert s.views.roll_max_deg == 10.0 and s.views.resolution == 512
    assert s.params.depth_units_per_m == 512.0 and s.params.max_depth_m == 128.0


def test_json_round_trip_is_exact() -> None:
    s = JobSpec(cues=["normal", "rgb"], seed=7, views={"resolution": 256})  # type: ignore[arg-type]
    dumped = s.model_dump(mode="json")
    assert dumped["cues"] == ["rgb", "normal"]  # catalog order
    assert JobSpec.model_validate(dumped) == s


@pytest.mark.parametrize(
    ("data", "loc", "words"),
    [
        ({"views": {"resolution": 8}}, ("views", "resolution"), "greater than or equal to 16"),
        ({"views": {"resolution": 10_000}}, ("views", "resolution"), "less than or equal to 4096"),
        ({"seed": -1}, ("seed",), "greater than or equal to 0"),
        ({"cameras": {"min_spacing_m": 0}}, ("cameras", "min_spacing_m"), "greater than 0"),
        ({"points": {"min_views": 0}}, ("points", "min_views"), "greater than or equal to 1"),
        ({"unit_scale": -2}, ("unit_scale",), "greater than 0"),
        ({"up_axis": "up"}, ("up_axis",), "'+z'"),
        ({"colour": "red"}, ("colour",), "Extra inputs are not permitted"),
        ({"views": {"fov": 60}}, ("views", "fov"), "Extra inputs are not permitted"),
        ({"name": "../etc"}, ("name",), "not a valid name"),
        ({"cues": []}, ("cues",), "at least one cue"),
        ({"cues": ["rgb", "bogus"]}, ("cues",), "known cues: rgb"),
        ({"cameras": {"height_min_m": 2.0, "height_max_m": 1.0}}, ("cameras",), "height_min_m"),
        ({"cameras": {"mode": "provided"}}, ("cameras",), "'poses'"),
        ({"points": {"min_views": 5, "max_views": 2}}, ("points",), "max_views (2) is below min_views (5)"),
        ({"views": {"fov_mean_deg": 20}}, ("views",), "fov_mean_deg"),
        ({"views": {"fov_max_deg": 200}}, ("views",), "fov_max_deg (200.0)"),
        (
            {"cameras": {"mode": "object", "object_count": 2}}, (),
            "points.min_views (3) exceeds cameras.object_count",
        ),
        ({"unit_scale": "feet"}, ("unit_scale",), "'auto' or a number of metres per source unit"),
        ({"up": [0, 0, 0]}, ("up",), "non-zero direction"),
        ({"up": [1, 2]}, ("up", 2), "Field required"),
        (
            {"source_to_world": [[1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
            ("source_to_world",), "degenerate",
        ),
        (
            {"source_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 3, 0], [0, 0, 0, 1]]},
            ("source_to_world",), "rotation times a uniform scale",
        ),
        ({"up": [0, 0, 1], "up_axis": "+z"}, (), "either up (a vector) or up_axis"),
        (
            {"source_to_world": [[2, 0, 0, 1], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]], "unit_scale": 1},
            (), "leave unit_scale unset",
        ),
        ({"views": {"min_valid_fraction": 1.5}}, ("views", "min_valid_fraction"), "less than or equal to 1"),
    ],
)
def test_refusals_name_the_field(data: dict[str, Any], loc: tuple[Any, ...], words: str) -> None:
    got_loc, msg = _refusal(data)
    assert got_loc == loc
    assert words in msg
    # model-level refusals carry the field name in the message itself
    if got_loc in ((), ("cameras",), ("points",), ("views",)):
        assert any(
            field in msg
            for field in ("height_min_m", "poses", "max_views", "fov_", "min_views", "up_axis", "unit_scale")
        )


def test_provided_cameras_fewer_than_min_views_refused() -> None:
    poses = [{"location": [0, 0, 1]}, {"location": [1, 0, 1]}]
    loc, msg = _refusal({"cameras": {"mode": "provided", "poses": poses}})
    assert "points.min_views (3) exceeds the 2 provided cameras" in msg
    ok = JobSpec.model_validate({"cameras": {"mode": "provided", "poses": poses}, "points": {"min_views": 2}})
    assert ok.cameras.poses is not None and len(ok.cameras.poses) == 2


def test_spec_is_frozen() -> None:
    s = JobSpec()
    with pytest.raises(ValidationError):
        s.seed = 3  # type: ignore[misc]


def test_cues_for_space_refuses_semantic_cues_on_unlabelled_scans() -> None:
    spec = JobSpec(cues=["rgb", "segment_semantic"])
    with pytest.raises(ValueError, match="'segment_semantic' needs semantic labels"):
        cues_for_space(spec, has_semantics=False)
    assert cues_for_space(spec, has_semantics=True) == ["rgb", "segment_semantic"]
    everything = cues_for_space(JobSpec(), has_semantics=False)
    assert "rgb" in everything and "segment_semantic" not in everything


def test_space_frame_fields() -> None:
    with pytest.raises(ValidationError, match="not the string '0.0254'"):  # strict: a number, as every field
        JobSpec.model_validate({"unit_scale": "0.0254"})
    spec = JobSpec.model_validate({"unit_scale": 0.0254, "up": [0, 2, 0]})
    assert spec.unit_scale == 0.0254 and JobSpec().unit_scale == "auto"
    assert spec.space_frame() == {
        "up_axis": "auto", "unit_scale": 0.0254, "up": (0.0, 2.0, 0.0), "source_to_world": None,
        "accept_up_guess": False,
    }
    assert JobSpec.model_validate({"accept_up_guess": True}).space_frame()["accept_up_guess"] is True
    T = [[0, -2, 0, 1], [2, 0, 0, 2], [0, 0, 2, 3], [0, 0, 0, 1]]  # a turn, 2 m per unit, a shift: accepted
    assert JobSpec.model_validate({"source_to_world": T}).space_frame()["source_to_world"][0] == (0, -2, 0, 1)
    assert JobSpec.model_validate_json(spec.model_dump_json()) == spec


def test_capture_fields() -> None:
    spec = JobSpec.model_validate({"cameras": {"mode": "capture"}})
    assert spec.uses_photos() and spec.cameras.capture_views == "exact"
    assert "mask_photo" in cues_for_space(spec, has_semantics=False)
    assert not JobSpec().uses_photos() and "mask_photo" not in cues_for_space(JobSpec(), has_semantics=False)
    assert JobSpec.model_validate({"views": {"rgb_source": "photos"}}).uses_photos()
    assert not JobSpec.model_validate(
        {"cameras": {"mode": "capture"}, "views": {"rgb_source": "mesh"}}
    ).uses_photos()
    with pytest.raises(ValidationError, match="mask_photo"):
        JobSpec.model_validate({"cues": ["rgb", "mask_photo"]})
    for bad in ({"cameras": {"mode": "capture", "capture_fov_deg": 0.5}}, {"views": {"min_alignment": -1}},
                {"views": {"min_photo_coverage": 1.5}}, {"views": {"rgb_source": "texture"}},
                {"cameras": {"capture_views": "orbit"}}, {"views": {"photo_count": 0}}):
        with pytest.raises(ValidationError):
            JobSpec.model_validate(bad)
