"""A scan that names server files where trimesh does not look (issue 19) renders with its own texture only:
`omnidata generate` with real Blender renders, the secret's pixels in no RGB output, the secret never
opened."""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.fixtures.file_watch import OpenWatch
from tests.fixtures.hostile_corpus import SECRET_RGB, secret_files

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
OWN_RGB = (0, 90, 255)
TETRA = (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvt 1 0\nvt 0 1\n"
         b"f 1/1 2/2 3/3\nf 1/1 2/2 4/3\nf 1/1 3/2 4/3\nf 2/1 3/2 4/3\n")
# The scan is a box: its up is genuinely ambiguous, and this test is about files, so the spec names it.
SPEC = "cameras: {mode: object, object_count: 6}\npoints: {count: 1, min_views: 2, max_views: 2}\n" \
       "views: {resolution: 32}\ncues: [rgb]\nup_axis: \"+z\"\n"


def _scan(folder: Path) -> Path:
    secret = secret_files()
    own = io.BytesIO()
    Image.new("RGB", (8, 8), OWN_RGB).save(own, format="PNG")
    mtl = (
        f"newmtl m\nKd 1 1 1\nmap_Kd own.png\nmap_Ks {secret['png']}\nbump "
        f"{'../' * 16}{str(secret['png'])[1:]}\nmap_d {secret['png']}\n"
    )
    path = folder / "scan.zip"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("scan.obj", b"# mtllib evil.mtl\no xmtllib_is_not_a_statement\nusemtl m\n" + TETRA)
        zf.writestr("evil.mtl", mtl)
        zf.writestr("own.png", own.getvalue())
    return path


def test_generate_renders_no_pixel_of_a_file_outside_the_scan(tmp_path: Path) -> None:
    scan = _scan(tmp_path)
    spec = tmp_path / "job.yaml"
    spec.write_text(SPEC)
    out = tmp_path / "out"
    with OpenWatch(secret_files().values()) as watch:
        res = subprocess.run([sys.executable, "-m", "services.cli", "generate", str(scan), "--out", str(out),
                              "--spec", str(spec), "--workers", "1", "--no-progress"],
                             cwd=REPO, capture_output=True, text=True, timeout=600)
        opened = watch.opened()
    assert res.returncode == 0, res.stderr[-2000:]
    assert opened == [], f"generate opened {opened}"
    rgbs = [
        np.asarray(Image.open(p).convert("RGB")).reshape(-1, 3).astype(int)
        for p in sorted(out.rglob("*_rgb.png"))
    ]
    assert len(rgbs) == 2
    pixels = np.concatenate(rgbs)
    near = lambda colour: (np.abs(pixels - np.array(colour)).max(axis=1) <= 12).sum()  # noqa: E731
    assert near(OWN_RGB) > 20, "the scan's own texture should be rendered"  # the texture path really works
    assert near(SECRET_RGB) == 0, "the secret's pixels reached a render"
