"""Benchmark: the file codecs of a view's cues on real rooms (issue 20): time and bytes of every lossless EXR
compression OpenEXR offers for the position cue, and of deflaters (zlib settings, ISA-L) for the PNG cues,
decoded arrays checked identical to the values.

Views: the pass sets bench/cues/derivations.py caches (run it first; the same planner views of ICL and the
kitchen). Clock: process CPU seconds (time.process_time), one core, median over views x repeats.
Writes the "encodings" entry of bench/results/encodings.json.
Run: .venv/bin/python bench/output/encodings.py [--repeats 3]
"""

from __future__ import annotations

import os
import sys

if hasattr(os, "sched_setaffinity"):  # one core, as bench/cues/derivations.py
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import zlib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.core.domain.cues import default_cues, get_cue  # noqa: E402
from services.core.domain.exr import decode_exr_rgb  # noqa: E402
from services.worker.context import ViewContext  # noqa: E402
from services.worker.cues.encoding import deflate_png, encode_png, zlib_deflater  # noqa: E402
from services.worker.cues.registry import cue_value  # noqa: E402
from services.worker.passes import ViewPasses  # noqa: E402
from tests.fixtures.raycast import decode_png  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "encodings.json"
# lossless ones; PXR24 is lossy
EXR_CODECS = ("NO", "RLE", "ZIPS", "ZIP", "PIZ", "ZSTD", "HTJ2K32", "HTJ2K256")
PNG_SETTINGS = {"level 1, Z_RLE": zlib_deflater(1, zlib.Z_RLE),
                "level 1, Z_FILTERED": zlib_deflater(1, zlib.Z_FILTERED),
                "level 1, default": zlib_deflater(1, zlib.Z_DEFAULT_STRATEGY),
                "level 1, Z_HUFFMAN_ONLY": zlib_deflater(1, zlib.Z_HUFFMAN_ONLY),
                "level 6, default": zlib_deflater(6, zlib.Z_DEFAULT_STRATEGY),
                # the zlib ones: bench/output/encode_cost.py compares
                "isal level 1 (the encoder's)": deflate_png}


def _exr_bytes(arr: np.ndarray, codec: str, path: str) -> bytes:
    header = {"compression": getattr(OpenEXR, codec + "_COMPRESSION"), "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": arr}) as f:
        f.write(path)
    with open(path, "rb") as fh:
        return fh.read()


def exr_figures(positions: list[np.ndarray], repeats: int) -> dict:
    """Per lossless codec: write and read CPU ms, MB per view, and whether every file decodes bit for bit."""
    out = {}
    fd, path = tempfile.mkstemp(suffix=".exr", dir="/dev/shm" if os.access("/dev/shm", os.W_OK) else None)
    os.close(fd)
    try:
        for codec in EXR_CODECS:
            write, read, size, same = [], [], [], True
            for arr in positions:
                for _ in range(repeats):
                    t0 = time.process_time()
                    data = _exr_bytes(arr, codec, path)
                    write.append(time.process_time() - t0)
                t0 = time.process_time()
                back = decode_exr_rgb(data)
                read.append(time.process_time() - t0)
                size.append(len(data))
                same &= back.dtype == np.float32 and np.array_equal(back.view(np.uint32), arr.view(np.uint32))
            out[codec] = {"write_ms": round(1e3 * float(np.median(write)), 2),
                          "read_ms": round(1e3 * float(np.median(read)), 2),
                          "mb_per_view": round(float(np.mean(size)) / 1e6, 3), "identical": bool(same)}
    finally:
        os.remove(path)
    return out


def png_figures(values: list[dict[str, np.ndarray]], repeats: int) -> dict:
    """Per deflater: CPU ms and MB of a view's PNG cues together, and whether every file decodes to its
    array."""
    out = {}
    for name, deflate in PNG_SETTINGS.items():
        per_view_s, per_view_b, same = [], [], True
        for v in values:
            t0 = time.process_time()
            for _ in range(repeats):
                files = {c: encode_png(a, deflate) for c, a in v.items()}
            per_view_s.append((time.process_time() - t0) / repeats)
            per_view_b.append(sum(len(f) for f in files.values()))
            same &= all(np.array_equal(decode_png(files[c]), a) for c, a in v.items())
        out[name] = {"ms_per_view": round(1e3 * float(np.median(per_view_s)), 2),
                     "mb_per_view": round(float(np.mean(per_view_b)) / 1e6, 3), "identical": bool(same)}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    args = ap.parse_args()
    files = sorted(args.cache.glob("*-512-*.npz"))
    if not files:
        print("no cached pass sets: run bench/cues/derivations.py first")
        return 1
    png_cues = [c for c in default_cues(has_semantics=False) if get_cue(c).ext == "png"]
    positions, values = [], []
    for f in files:
        ctx = ViewContext(None, passes=ViewPasses.from_bytes(f.read_bytes()))
        positions.append(cue_value(ctx, "position"))
        values.append({c: cue_value(ctx, c) for c in png_cues})
    run = {
        "views": [f.stem for f in files], "clock": "process CPU, one core, median over views x repeats",
        "load": [round(x, 2) for x in os.getloadavg()], "position_exr": exr_figures(positions, args.repeats),
        "png_cues": png_figures(values, args.repeats),
    }
    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    data["encodings"] = run
    RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    print(json.dumps({k: run[k] for k in ("position_exr", "png_cues", "load")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
