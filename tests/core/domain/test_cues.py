"""Cue catalog: DAG order, closures, missing dependencies, unknown cues listing the known ones."""

from __future__ import annotations

import pytest

from services.core.domain.cues import (
    CATALOG,
    OUTPUT_CUES,
    Cue,
    UnknownCueError,
    closure,
    default_cues,
    get_cue,
    topological_order,
    unsupported_cues,
    validate_cue_names,
)


def _assert_topological(order: list[str]) -> None:
    pos = {n: i for i, n in enumerate(order)}
    for n in order:
        for dep in CATALOG[n].inputs:
            assert pos[dep] < pos[n], f"{n} comes before its input {dep}"


def test_catalog_inputs_exist_and_whole_catalog_orders() -> None:
    for cue in CATALOG.values():
        for dep in cue.inputs:
            assert dep in CATALOG, f"{cue.name} depends on unknown {dep}"
    order = topological_order(CATALOG)
    assert sorted(order) == sorted(CATALOG)
    _assert_topological(order)
    assert order[0] == "passes"


def test_closure_adds_inputs_in_topological_order() -> None:
    order = closure(["segment_unsup25d"])
    assert set(order) == {"passes", "depth_zbuffer", "normal", "edge_occlusion", "segment_unsup25d"}
    _assert_topological(order)
    assert order[-1] == "segment_unsup25d"
    assert closure(["keypoints3d"]) == ["passes", "depth_zbuffer", "keypoints3d"]  # by dependency level
    assert closure(["point_info"]) == ["point_info"]  # plan cues need no render


def test_order_is_deterministic() -> None:
    names = ["reshading", "edge_texture", "mask_valid", "rgb"]
    a = closure(names)
    b = closure(list(reversed(names)))
    assert a == b
    _assert_topological(a)


def test_missing_dependency_is_named() -> None:
    with pytest.raises(ValueError) as e:
        topological_order(["reshading", "normal", "passes"])
    msg = str(e.value)
    assert "'reshading'" in msg and "depth_zbuffer" in msg


def test_cycle_is_detected() -> None:
    cyc = {
        "a": Cue("a", "png", "", "uint8", 1, "derive", ("b",)),
        "b": Cue("b", "png", "", "uint8", 1, "derive", ("a",)),
        "c": Cue("c", "png", "", "uint8", 1, "render"),
    }
    assert topological_order(["c"], cyc) == ["c"]
    with pytest.raises(ValueError, match="cycle among: a, b"):
        topological_order(["a", "b", "c"], cyc)


def test_unknown_cue_lists_the_known_ones() -> None:
    with pytest.raises(UnknownCueError) as e:
        get_cue("depth_zbufer")
    msg = str(e.value)
    assert "depth_zbufer" in msg
    for known in ("rgb", "depth_zbuffer", "segment_panoptic", "position"):
        assert known in msg
    assert "passes" not in msg.split("known cues:")[1]  # internal cue is not offered
    with pytest.raises(UnknownCueError) as e2:
        validate_cue_names(["rgb", "bogus", "zzz"])
    assert e2.value.names == ["bogus", "zzz"]
    with pytest.raises(UnknownCueError):
        validate_cue_names(["passes"])  # internal cues cannot be requested
    with pytest.raises(UnknownCueError):
        closure(["nope"])


def test_validate_dedups_in_catalog_order() -> None:
    assert validate_cue_names(["normal", "rgb", "normal"]) == ["rgb", "normal"]


def test_defaults_follow_semantics() -> None:
    plain = default_cues(has_semantics=False)
    labelled = default_cues(has_semantics=True)
    assert not any(CATALOG[n].needs_semantics for n in plain)
    assert set(labelled) - set(plain) == {"segment_semantic", "segment_instance", "segment_panoptic"}
    # asked for by name
    optional = {"augment_params", "rgb_refocus", "rgb_fog", "rgb_motion_blur", "rgb_flash"}
    optional.add("mask_photo")  # mask_photo: only jobs with rgb from photos
    assert set(labelled) == set(OUTPUT_CUES) - optional and not any(CATALOG[n].default for n in optional)
    assert "passes" not in labelled
    why = unsupported_cues(["rgb", "segment_semantic"], has_semantics=False)
    assert list(why) == ["segment_semantic"] and "semantic labels" in why["segment_semantic"]
    assert unsupported_cues(["segment_semantic"], has_semantics=True) == {}
