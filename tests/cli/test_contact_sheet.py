"""The contact sheet reads a dataset folder through its manifest and shows every image cue."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from services.cli import CliError, main
from services.cli.contact_sheet import build_sheet


def _dataset(root, spaces=("a", "b")):
    lines = []
    for space in spaces:
        outputs = {}
        rgb = np.zeros((32, 32, 3), np.uint8)
        rgb[8:24, 8:24] = (200, 50, 10)
        depth = np.full((32, 32), 65535, np.uint16)
        depth[8:24, 8:24] = 1024
        for cue, arr in (("rgb", rgb), ("depth_zbuffer", depth)):
            key = f"{cue}/c/{space}/point_0_view_0_domain_{cue}.png"
            (root / key).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(arr).save(root / key)
            outputs[cue] = {"key": key, "size": 1, "sha256": "x"}
        frag = np.full((32, 32), 0xFFFFFFFF, np.uint32)
        frag[8:24, 8:24] = np.arange(256).reshape(16, 16)
        key = f"fragments/c/{space}/point_0_view_0_domain_fragments.npy"
        (root / key).parent.mkdir(parents=True, exist_ok=True)
        np.save(root / key, frag)
        outputs["fragments"] = {"key": key, "size": 1, "sha256": "x"}
        lines.append({"space": space, "point": 0, "view": 0, "outputs": outputs})
    (root / "manifest.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))


def test_sheet_has_a_tile_per_cue_and_view(tmp_path):
    _dataset(tmp_path)
    sheet = np.asarray(build_sheet(tmp_path, views=4, thumb=32))
    pad, label = 4, 14
    assert sheet.shape[1] == 3 * (32 + pad) + pad  # rgb, depth, fragments
    assert sheet.shape[0] == 2 * (32 + label + pad) + label  # both spaces shown
    rgb_tile = sheet[label + label: label + label + 32, pad: pad + 32]
    assert tuple(rgb_tile[16, 16]) == (200, 50, 10)  # colour reproduced
    depth_tile = sheet[2 * label: 2 * label + 32, 2 * pad + 32: 2 * pad + 64]
    assert depth_tile[0, 0].max() == 0 and depth_tile[16, 16].max() > 0  # no surface shows black


def test_missing_manifest_is_a_cli_error(tmp_path, capsys):
    with pytest.raises(CliError, match="no manifest.jsonl"):
        build_sheet(tmp_path)
    assert main(["sheet", str(tmp_path)]) == 2
    assert "no manifest.jsonl" in capsys.readouterr().err


def test_sheet_of_a_service_job_needs_out_and_bad_sizes_are_refused(tmp_path, capsys, monkeypatch):
    # `omnidata sheet 42` reads job 42 of OMNIDATA_STORAGE_URL: no folder to put the default sheet in
    _dataset(tmp_path / "objects" / "jobs" / "42")
    monkeypatch.setenv("OMNIDATA_STORAGE_URL", (tmp_path / "objects").as_uri())
    monkeypatch.chdir(tmp_path)
    assert main(["sheet", "42"]) == 2
    assert "give --out" in capsys.readouterr().err
    assert main(["sheet", "42", "--out", str(tmp_path / "job42.png"), "--thumb", "16"]) == 0
    assert Image.open(tmp_path / "job42.png").size[0] > 16
    for flag in ("--views", "--thumb"):
        assert main(["sheet", str(tmp_path / "objects" / "jobs" / "42"), flag, "0"]) == 2
        assert "must be at least 1" in capsys.readouterr().err
