"""Capture photos within a pixel budget: refused from their header (naming the file and the limit) by the
reader that checks frames and by the loader that decodes them, and decoded no larger than the views sampling
them need. The readers' own errors (Pillow's bomb limit, a JSON nested past the recursion limit, a zip member
'.') come back from the real upload path as one line naming the file."""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.core.domain.camera import intrinsics
from services.core.ingest.capture import find_capture
from services.core.ingest.capture.model import CaptureFrame
from services.core.ingest.capture.photos import MAX_PHOTO_PIXELS, PhotoRefused, load_photo
from services.core.ingest.capture.resample import photo_for_view
from services.core.ingest.errors import SpaceError
from services.core.ingest.guard.safe_load import load_space_limited
from services.worker.inputs.photos import PhotoPainter
from tests.fixtures.captures import toy_frames, write_colmap, write_transforms
from tests.fixtures.hostile_corpus import png_declaring

LIMIT = f"{MAX_PHOTO_PIXELS:,}"


def _photo(path: Path, size: tuple[int, int]) -> CaptureFrame:
    """A smooth photo of `size` at `path` (format by suffix) and its frame: focal length 3/4 the width."""
    w, h = size
    y, x = np.mgrid[0:h, 0:w]
    rgb = np.stack([(x * 255 // w), (y * 255 // h), ((x + y) // 7) % 256], axis=-1).astype(np.uint8)
    Image.fromarray(rgb).save(path, quality=95)
    K = np.array([[0.75 * w, 0, w / 2], [0, 0.75 * w, h / 2], [0, 0, 1]])
    return CaptureFrame("f", path.name, w, h, K, "none", (), np.eye(4))


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_a_photo_is_decoded_no_larger_than_the_view_needs(tmp_path: Path, suffix: str) -> None:
    frame = _photo(tmp_path / f"p{suffix}", (2400, 1800))
    fov = frame.inscribed_fov()
    K = intrinsics(fov, 128)
    small = load_photo(tmp_path / f"p{suffix}", frame, float(K[0, 0]))
    factor = int(1800.0 / K[0, 0])  # 14: the view takes one pixel per 14 of the photo's
    assert small.scale == pytest.approx(1 / factor if suffix == ".png" else 1 / 8)  # a JPEG: its 1/8 scale
    assert small.pixels.shape[1] == -(-2400 * small.scale // 1) and small.pixels.size < 2400 * 1800 * 3 / 60
    full = load_photo(tmp_path / f"p{suffix}", frame)
    assert full.scale == 1.0 and full.pixels.shape == (1800, 2400, 3)
    got, covered = photo_for_view(small, frame, K, frame.world_to_camera, 128, 128)
    want, _ = photo_for_view(full, frame, K, frame.world_to_camera, 128, 128)
    assert covered.all()
    # the same view from a photo 1/14 (1/8) the size
    assert np.abs(got.astype(int) - want.astype(int)).mean() < 2.0


def test_the_painter_keeps_a_reduced_photo_until_a_view_needs_more(tmp_path: Path) -> None:
    write_colmap(tmp_path, toy_frames(2, size=(640, 480)))
    capture = find_capture(tmp_path)
    assert capture is not None and len(capture.frames) == 2
    painter = PhotoPainter(capture)
    coarse = painter.photo(0, 10.0)  # a 50 px focal length, a 10 px one's view: 1 pixel in 5, the JPEG's 1/4
    assert coarse.scale == pytest.approx(1 / 4) and coarse.pixels.shape == (120, 160, 3)
    assert painter.photo(0, 12.0) is coarse  # dense enough: kept
    fine = painter.photo(0, 60.0)
    assert fine.scale == 1.0 and fine.pixels.shape == (480, 640, 3)


def test_the_loader_refuses_a_photo_over_the_budget_from_its_header(tmp_path: Path) -> None:
    for side in (9000, 20000):  # over ours; over Pillow's own bomb limit as well
        path = tmp_path / f"big{side}.png"
        path.write_bytes(png_declaring(side, side))
        K = np.diag([5000.0, 5000.0, 1.0])
        frame = CaptureFrame("f", path.name, side, side, K, "none", (), np.eye(4))
        refusal = rf"photo big{side}\.png declares .* more than the limit of {LIMIT}"
        with pytest.raises(PhotoRefused, match=refusal):
            load_photo(path, frame, 100.0)


def _bunny_capture(scenes_dir: Path, folder: Path) -> Path:
    folder.mkdir(parents=True)
    shutil.copy(scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply", folder / "bunny.ply")
    return folder


@pytest.mark.parametrize("side", [9000, 20000])
def test_upload_skips_a_frame_whose_photo_is_over_the_budget_naming_it(scenes_dir: Path, tmp_path: Path,
                                                                       side: int) -> None:
    folder = _bunny_capture(scenes_dir, tmp_path / "scan")
    frames = toy_frames(3)
    write_colmap(folder, frames)
    (folder / "images" / f"{frames[1].name}.jpg").write_bytes(png_declaring(side, side))
    loaded = load_space_limited(folder, max_faces=10**6, memory_mb=4096, timeout_s=120)
    assert loaded.capture is not None and len(loaded.capture.frames) == 2
    (problem,) = loaded.capture.problems
    assert f"{frames[1].name}.jpg" in problem and f"limit of {LIMIT}" in problem
    assert problem.endswith("skipped")


def test_upload_of_a_transforms_json_nested_past_the_recursion_limit(scenes_dir: Path,
                                                                    tmp_path: Path) -> None:
    folder = _bunny_capture(scenes_dir, tmp_path / "scan")
    write_transforms(folder, toy_frames(2))
    (folder / "transforms.json").write_text("[" * 100_000 + "]" * 100_000)
    loaded = load_space_limited(folder, max_faces=10**6, memory_mb=4096, timeout_s=120)
    assert loaded.capture is not None and not loaded.capture.frames
    assert loaded.capture.problems == ("transforms.json: not readable JSON (nested too deep)",)


def test_upload_of_a_zip_with_a_member_named_dot(scenes_dir: Path, tmp_path: Path) -> None:
    archive = tmp_path / "scan.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        zf.write(scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply", "bunny.ply")
        zf.writestr(".", b"x")
    with pytest.raises(SpaceError, match=r"^scan\.zip: member '\.' names no file"):
        load_space_limited(archive, max_faces=10**6, memory_mb=4096, timeout_s=120)


def test_a_photo_that_does_not_fit_the_memory_left_is_named(tmp_path: Path) -> None:
    """The loader under a real address-space limit (as the planner runs): the MemoryError names the photo."""
    import subprocess
    import sys
    import textwrap

    path = tmp_path / "wide.png"
    Image.new("RGB", (8000, 6000), (10, 20, 30)).save(path)  # 48 Mpx: 144 MB decoded
    script = textwrap.dedent(f"""
        import resource, sys
        from pathlib import Path
        import numpy as np
        from services.core.ingest.capture.model import CaptureFrame
        from services.core.ingest.capture.photos import PhotoRefused, load_photo
        K = np.diag([6000.0, 6000.0, 1.0])
        frame = CaptureFrame("f", "wide.png", 8000, 6000, K, "none", (), np.eye(4))
        status = Path("/proc/self/status").read_text().splitlines()
        mapped = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
        resource.setrlimit(resource.RLIMIT_AS, (mapped + (64 << 20),) * 2)
        try:
            load_photo({str(path)!r}, frame, 100.0)
        except PhotoRefused as e:
            print(e)
            sys.exit(0)
        sys.exit(1)
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[4])
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == ("photo wide.png (8,000 x 6,000 pixels) does not fit in this process's "
                                  "memory budget: downscale the capture's photos")
