"""services.worker.blender.exr reads uncompressed float32 scanline EXRs as the OpenEXR module does, and
declines the rest (the pass render's own files: tests/worker/blender/test_pass_identity.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from services.worker.blender.exr import read_channels


def write(path: Path, channels: dict[str, np.ndarray], compression: object) -> None:
    header = {"compression": compression, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))


def test_reads_an_uncompressed_float_exr_like_openexr(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    channels = {
        "L.Depth.Z": rng.random((7, 5), dtype=np.float32),
        "L.a.X": rng.normal(size=(7, 5)).astype(np.float32),
        "L.Combined": rng.random((7, 5, 4), dtype=np.float32),
    }
    channels["L.a.X"][0, 0] = np.nan
    write(tmp_path / "a.exr", channels, OpenEXR.NO_COMPRESSION)
    got = read_channels(str(tmp_path / "a.exr"))
    assert got is not None
    want = {n: c.pixels for n, c in OpenEXR.File(str(tmp_path / "a.exr")).parts[0].channels.items()}
    assert sorted(got) == sorted(["L.Depth.Z", "L.a.X", *(f"L.Combined.{c}" for c in "RGBA")])
    for name, px in want.items():
        if px.ndim == 3:
            for i, c in enumerate("RGBA"):
                assert got[f"{name}.{c}"].tobytes() == np.ascontiguousarray(px[..., i]).tobytes()
        else:
            assert got[name].tobytes() == px.tobytes()


@pytest.mark.parametrize("case", ["zip", "half"])
def test_declines_what_it_does_not_read(tmp_path: Path, case: str) -> None:
    data = np.ones((4, 4), np.float16 if case == "half" else np.float32)
    write(
        tmp_path / "b.exr", {"Z": data}, OpenEXR.ZIP_COMPRESSION if case == "zip" else OpenEXR.NO_COMPRESSION
    )
    assert read_channels(str(tmp_path / "b.exr")) is None
