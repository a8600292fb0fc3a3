"""The 3D augmentation cues of a real job (`omnidata generate`, 32 px renders of the banana): written per view
beside their inputs, read back by OmnidataDataset like rgb, with the per-view draws in augment_params, and
previewed as the gallery shows them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.datasets import OmnidataDataset
from services.datasets.previews import preview_array
from tests.fixtures.cli import generate_output

AUGMENTED = """
cameras: {mode: object, object_count: 6}
points: {count: 2, min_views: 2, max_views: 2}
views: {resolution: 32}
cues: [rgb, rgb_refocus, rgb_fog, rgb_motion_blur, rgb_flash]
params:
  augment: {fog_beta_per_m: 2.0, fog_airlight: 0.9, refocus_f_number: {dist: uniform, low: 1.4, high: 2.0}}
"""
CUES = ["rgb", "rgb_refocus", "rgb_fog", "rgb_motion_blur", "rgb_flash", "augment_params"]


@pytest.mark.slow
@pytest.mark.bpy
def test_augmentations_of_a_real_job(tmp_path: Path, scenes_dir: Path) -> None:
    out = generate_output(scenes_dir / "ycb_banana", tmp_path / "banana", AUGMENTED, "aug", 5)
    ds = OmnidataDataset(out, CUES)
    assert len(ds) == 4
    draws = []
    for item in ds:
        for cue in CUES[:-1]:
            assert item[cue].shape == (3, 32, 32) and item[cue].dtype == np.float32, cue
        doc = json.loads(item["augment_params"])
        assert doc["rgb_fog"] == {"beta_per_m": 2.0, "airlight": 0.9}  # constants as given
        assert 1.4 <= doc["rgb_refocus"]["f_number"] <= 2.0
        draws.append(doc["rgb_refocus"]["f_number"])
        # fog adds light where the banana is seen (airlight 0.9 over a darker object) and is the fog elsewhere
        rgb, fog = item["rgb"], item["rgb_fog"]
        seen = rgb.sum(axis=0) > 0
        assert (fog[:, seen].mean() > rgb[:, seen].mean()) and np.allclose(
            fog[:, ~seen], fog[0, ~seen].mean(), atol=0.01
        )
    assert len(set(draws)) == len(draws)  # one draw per view
    key = next((out / "rgb_fog" / "aug" / "ycb_banana").glob("*.png"))
    assert preview_array("rgb_fog", key.read_bytes()).shape == (32, 32, 3)
    info = next((out / "augment_params" / "aug" / "ycb_banana").glob("*.json"))
    assert preview_array("augment_params", info.read_bytes()).std() > 0
