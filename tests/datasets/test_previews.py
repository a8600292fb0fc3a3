"""Previews: every cue of a real job gives a readable, non-constant tile; cached next to the outputs;
`omnidata preview --video` writes one MP4 per cue and trajectory with one frame per view."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image

from services.cli import main
from services.core.domain.cues import CATALOG
from services.core.storage import LocalStore
from services.datasets import previews
from services.datasets.previews import cached_preview, preview_array, preview_key
from tests.datasets.test_decode import png8, png16


def _lines(job: Path) -> list[dict]:
    return [json.loads(x) for x in (job / "manifest.jsonl").read_text().splitlines()]


def test_every_cue_of_a_real_job_previews_non_constant(small_job: Path) -> None:
    seen = set()
    for e in _lines(small_job):
        for cue, o in e["outputs"].items():
            img = preview_array(cue, (small_job / o["key"]).read_bytes(), view=e["view"], resolution=32)
            assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3, cue
            assert img.reshape(-1, 3).std(axis=0).max() > 5, f"{cue} preview is (nearly) constant"
            seen.add(cue)
    assert seen == {c for e in _lines(small_job) for c in e["outputs"]} and "nonfixated" in seen


def test_mappings_show_what_the_values_mean(small_job: Path) -> None:
    depth = np.full((8, 8), 65535, np.uint16)
    depth[2:6, 2:6] = np.arange(16).reshape(4, 4) * 100 + 512
    img = preview_array("depth_zbuffer", png16(depth))
    # none black, depth coloured
    assert (img[0, 0] == 0).all() and img[2:6, 2:6].reshape(-1, 3).std(axis=0).max() > 20
    assert not np.array_equal(img[2, 2], img[5, 5])  # near and far differ
    labels = np.array([[1, 1, 2, 40000]], np.uint16)
    tile = preview_array("segment_unsup2d", png16(labels))
    assert np.array_equal(tile[0, 0], tile[0, 1]) and not np.array_equal(tile[0, 1], tile[0, 2])
    assert not np.array_equal(tile[0, 2], tile[0, 3])  # labels above 32767 get their own colour
    sem = preview_array("segment_semantic", png8(np.array([[0, 3, 3, 7]], np.uint8)))
    assert np.array_equal(sem[0, 1], sem[0, 2]) and len({tuple(p) for p in sem[0]}) == 3
    pan = np.zeros((1, 3, 3), np.uint8)
    pan[0, 1], pan[0, 2] = (3, 0, 1), (3, 0, 2)  # same class, two instances
    assert len({tuple(p) for p in preview_array("segment_panoptic", png8(pan))[0]}) == 3
    inst = preview_array("segment_instance", png16(np.array([[0, 5, 5]], np.uint16)))
    assert not np.array_equal(inst[0, 0], inst[0, 1])
    curv = np.zeros((1, 3, 3), np.uint8)
    curv[0, 1], curv[0, 2] = (127, 127, 0), (254, 254, 0)
    c = preview_array("principal_curvature", png8(curv)).astype(int)
    # grey flat, red convex
    assert (c[0, 0] == 0).all() and abs(c[0, 1] - c[0, 1].mean()).max() < 10 and c[0, 2, 0] > c[0, 2, 2]
    normal = (small_job / "normal/tiny/ycb_banana/point_0_view_0_domain_normal.png").read_bytes()
    assert np.array_equal(preview_array("normal", normal), np.asarray(Image.open(io.BytesIO(normal))))
    big = preview_array("rgb", png8(np.zeros((600, 300, 3), np.uint8)))
    assert big.shape == (200, 100, 3) and max(big.shape) <= previews.MAX_PREVIEW_PX  # every 3rd pixel


def test_previews_are_cached_next_to_the_outputs(
    small_job: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = tmp_path / "job"
    shutil.copytree(small_job, root)
    store = LocalStore(root)
    key = "nonfixated/tiny/ycb_banana/point_1_domain_nonfixated.json"
    pkey, data = cached_preview(store, key, "nonfixated", point=1, view=1, resolution=32)
    assert (
        pkey
        == preview_key(key, "nonfixated", 1, 1)
        == "_previews/v1/nonfixated/tiny/ycb_banana/point_1_view_1_domain_nonfixated.png"
    )
    assert store.get_bytes(pkey) == data and data[:8] == b"\x89PNG\r\n\x1a\n"
    monkeypatch.setattr(previews, "preview_array", lambda *a, **k: pytest.fail("the cache was not used"))
    assert cached_preview(store, key, "nonfixated", point=1, view=1)[1] == data
    # the CLI fills the cache for every output, one preview per view
    monkeypatch.undo()
    assert main(["preview", str(root), "--no-progress"]) == 0
    lines = _lines(small_job)
    want = {preview_key(o["key"], c, e["point"], v)
            for e in lines for c, o in e["outputs"].items()
            for v in ([0, 1] if CATALOG[c].per_point else [e["view"]])}
    assert set(store.list("_previews/")) == want


def test_trajectory_video_has_one_frame_per_view(trajectory_job: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    lines = _lines(trajectory_job)
    frames = len(lines)
    assert frames >= 2 and {e["point"] for e in lines} == {0}
    out = tmp_path / "videos"
    assert main(["preview", str(trajectory_job), "--video", "--out", str(out), "--no-progress"]) == 0
    assert f"({frames} frames each)" in capsys.readouterr().out
    videos = sorted(out.glob("ycb_banana/point_0_*.mp4"))
    cues = {c for e in lines for c in e["outputs"]}
    assert {v.name for v in videos} == {f"point_0_{c}.mp4" for c in cues}
    for video in videos:
        reader = imageio_ffmpeg.read_frames(str(video))
        meta = next(reader)
        decoded = [np.frombuffer(f, np.uint8) for f in reader]
        assert len(decoded) == frames, video.name
        assert meta["size"][0] >= 32 and meta["size"][0] % 2 == 0
    depth = [
        np.frombuffer(f, np.uint8)
        for f in list(imageio_ffmpeg.read_frames(str(out / "ycb_banana/point_0_depth_zbuffer.mp4")))[1:]
    ]
    assert all(f.std() > 5 for f in depth) and not np.array_equal(depth[0], depth[-1])  # the camera moves


def test_preview_cli_errors(trajectory_job: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["preview", str(tmp_path / "none"), "--no-progress"]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert main(["preview", str(trajectory_job), "--cues", "rgb,nope", "--no-progress"]) == 2
    assert "unknown cue" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "manifest.jsonl").write_text("")
    assert main(["preview", str(empty), "--cues", "rgb", "--no-progress"]) == 2
    assert "lists no views" in capsys.readouterr().err
    assert main(["preview", str(trajectory_job), "--video", "--fps", "0", "--out", str(tmp_path / "v")]) == 2
    assert "--fps" in capsys.readouterr().err and not (tmp_path / "v").exists()
