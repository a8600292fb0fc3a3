"""OmnidataDataset(where=...): views kept by their steering values, from the plan JSON or from point_info."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from services.cli import main
from services.datasets import OmnidataDataset
from tests.fixtures import scenes

SPEC = {"cameras": {"max_count": 30, "min_spacing_m": 0.5},
        "points": {"count": 30, "min_views": 2, "max_views": 6}, "views": {"resolution": 64}}


@pytest.fixture(scope="module")
def planned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("steer")
    room = root / "room.ply"
    scenes.l_room().export(room)
    (root / "spec.yaml").write_text(yaml.safe_dump(SPEC))
    assert main(["plan", str(room), "--out", str(root / "out"), "--spec", str(root / "spec.yaml")]) == 0
    return root / "out"


def _pitch(info: dict) -> float:
    forward = np.asarray(info["world_to_camera"])[2, :3]  # the optical axis in world coordinates
    return float(np.degrees(np.arcsin(forward[2])))


@pytest.mark.parametrize("from_point_info", [False, True])
def test_where_keeps_the_views_in_range(planned: Path, tmp_path: Path, from_point_info: bool) -> None:
    root = planned
    if from_point_info:  # no plan JSON: the values come from each view's point_info
        root = tmp_path / "copy"
        shutil.copytree(planned, root)
        shutil.rmtree(root / "plans")
    everything = OmnidataDataset(root, "point_info")
    pitches = {v.key: _pitch(json.loads(everything.read(v, "point_info"))) for v in everything.views}
    lo, hi = np.quantile(list(pitches.values()), [0.25, 0.75])
    kept = OmnidataDataset(root, "point_info", where={"pitch_deg": (lo, hi)})
    assert {v.key for v in kept.views} == {k for k, p in pitches.items() if lo <= p <= hi}
    assert 0 < len(kept) < len(everything)
    wide = OmnidataDataset(root, "point_info", where={"height_m": (0.0, 100.0), "views_per_point": (2, 6)})
    assert len(wide) == len(everything)  # every camera is above the floor, every point has 2..6 views


def test_where_refuses_unknown_names_and_bad_ranges(planned: Path) -> None:
    with pytest.raises(ValueError, match="unknown distribution 'tilt'"):
        OmnidataDataset(planned, "point_info", where={"tilt": (0, 1)})
    with pytest.raises(ValueError, match="lo <= hi"):
        OmnidataDataset(planned, "point_info", where={"pitch_deg": (10, -10)})
