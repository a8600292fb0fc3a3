"""Benchmark: CPU cost of encoding a view's cue files (issue 20, cost per view): each PNG cue with the
deflaters compared (zlib level 1 + Z_RLE, the encoder before; ISA-L levels 0-2), the PNG encoder's steps (Up
filter, deflate, chunks and CRCs), and the position cue's derivation and EXR file, before (numpy temporaries;
OpenEXR writing a temp file read back) and now (one compiled loop; the file's bytes written directly). Every
file is checked to decode to its array bit for bit.

Views: the pass sets bench/cues/derivations.py caches (run it first; the same planner views of ICL and the
kitchen). Clock: process CPU seconds (time.process_time), one core, median over views x repeats.
Writes bench/results/encode_cost.json (keys of other runs kept; this run under --label).
Run: .venv/bin/python bench/output/encode_cost.py [--repeats 5] [--label now]
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
from collections import defaultdict  # noqa: E402
from collections.abc import Callable  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402
from isal import isal_zlib  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.core.domain.cues import default_cues, get_cue  # noqa: E402
from services.core.domain.exr import decode_exr_rgb  # noqa: E402
from services.worker.context import ViewContext  # noqa: E402
from services.worker.cues.common import hit, position_world, ray_dirs_cam64  # noqa: E402
from services.worker.cues.encoding import deflate_png, encode_exr_rgb, encode_png, zlib_deflater  # noqa: E402
from services.worker.cues.registry import cue_value  # noqa: E402
from services.worker.passes import ViewPasses  # noqa: E402
from services.worker.process.heap import keep_freed_memory  # noqa: E402
from tests.fixtures.raycast import decode_png  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "encode_cost.json"
BEFORE, NOW = "zlib level 1, Z_RLE (before)", "isal level 1 (now)"
DEFLATERS: dict[str, Callable[[memoryview], bytes]] = {
    BEFORE: zlib_deflater(1, zlib.Z_RLE),
    NOW: deflate_png,
    "isal level 0": lambda data: isal_zlib.compress(data, 0),
    "isal level 2": lambda data: isal_zlib.compress(data, 2),
}


def cpu_ms(fn: Callable[[], object], repeats: int) -> float:
    """Median CPU milliseconds of fn() over repeats."""
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return 1e3 * float(np.median(times))


def position_before(ctx: ViewContext) -> np.ndarray:
    """position_world before: whole-array float64 numpy on the memoised rays."""
    g = ctx.geometry
    d_cam = ray_dirs_cam64(ctx)
    t = ctx.passes.depth_z.astype(np.float64) / d_cam[..., 2]
    p = g.center + (d_cam @ g.rotation) * t[..., None]
    p[~hit(ctx)] = np.nan
    return p.astype(np.float32)


def exr_before(arr: np.ndarray) -> bytes:
    """encode_exr_rgb before: OpenEXR writes an uncompressed file in /dev/shm, read back."""
    fd, path = tempfile.mkstemp(suffix=".exr", dir="/dev/shm" if os.access("/dev/shm", os.W_OK) else None)
    os.close(fd)
    try:
        with OpenEXR.File(
            {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}, {"RGB": arr}
        ) as f:
            f.write(path)
        with open(path, "rb") as fh:
            return fh.read()
    finally:
        os.remove(path)


def png_steps(arr: np.ndarray, repeats: int) -> dict[str, float]:
    """CPU ms of encode_png's steps on one array: filter (+ chunks, with a no-op deflate), and each deflater
    alone."""
    captured: list[bytes] = []
    encode_png(arr, lambda data: captured.append(bytes(data)) or b"")
    filtered = captured[0]
    out = {"filter_and_chunks": cpu_ms(lambda: encode_png(arr, lambda data: b""), repeats)}
    for name, deflate in DEFLATERS.items():
        out[f"deflate: {name}"] = cpu_ms(partial(deflate, memoryview(filtered)), repeats)
    idat = DEFLATERS[NOW](memoryview(filtered))
    out["IDAT crc32: zlib (before)"] = cpu_ms(lambda: zlib.crc32(b"IDAT" + idat), repeats)
    out["IDAT crc32: isal (now)"] = cpu_ms(lambda: isal_zlib.crc32(idat, isal_zlib.crc32(b"IDAT")), repeats)
    return out


def room_figures(files: list[Path], repeats: int) -> dict:
    png_cues = [c for c in default_cues(has_semantics=False) if get_cue(c).ext == "png"]
    per_cue_ms: dict[str, defaultdict[str, list[float]]] = {n: defaultdict(list) for n in DEFLATERS}
    per_cue_bytes: dict[str, defaultdict[str, list[int]]] = {n: defaultdict(list) for n in DEFLATERS}
    steps: defaultdict[str, list[float]] = defaultdict(list)
    identical = {n: True for n in DEFLATERS}
    pos: defaultdict[str, list[float]] = defaultdict(list)
    pos_same, exr_bytes = True, []
    for f in files:
        passes = ViewPasses.from_bytes(f.read_bytes())
        ctx = ViewContext(None, passes=passes)
        values = {c: cue_value(ctx, c) for c in png_cues}
        for name, deflate in DEFLATERS.items():
            for c, a in values.items():
                per_cue_ms[name][c].append(cpu_ms(partial(encode_png, a, deflate), repeats))
                data = encode_png(a, deflate)
                per_cue_bytes[name][c].append(len(data))
                identical[name] &= bool(np.array_equal(decode_png(data).astype(a.dtype), a))
        view_steps: defaultdict[str, float] = defaultdict(float)
        for a in values.values():
            for k, v in png_steps(a, repeats).items():
                view_steps[k] += v
        for k, v in view_steps.items():
            steps[k].append(v)
        ray_dirs_cam64(ctx)  # memoised rays, shared with other cues: not the position's own cost
        new, old = position_world(ctx), position_before(ctx)
        pos["derive_ms_before"].append(cpu_ms(partial(position_before, ctx), repeats))
        pos["derive_ms_now"].append(cpu_ms(partial(position_world, ctx), repeats))
        pos["encode_ms_before"].append(cpu_ms(partial(exr_before, new), repeats))
        pos["encode_ms_now"].append(cpu_ms(partial(encode_exr_rgb, new), repeats))
        data = encode_exr_rgb(new)
        exr_bytes.append(len(data))
        pos_same &= bool(np.array_equal(new.view(np.uint32), old.view(np.uint32))
                         and data == exr_before(new)
                         and np.array_equal(decode_exr_rgb(data).view(np.uint32), new.view(np.uint32)))

    def med(xs: list[float]) -> float:
        return round(float(np.median(xs)), 3)

    png = {}
    for name in DEFLATERS:
        cues = {
            c: {"ms": med(per_cue_ms[name][c]), "kb": round(float(np.mean(per_cue_bytes[name][c])) / 1e3, 1)}
            for c in png_cues
        }
        png[name] = {"ms_per_view": round(sum(v["ms"] for v in cues.values()), 2),
                     "mb_per_view": round(sum(v["kb"] for v in cues.values()) / 1e3, 3),
                     "identical": identical[name], "per_cue": cues}
    position = {
        **{k: med(v) for k, v in pos.items()},
        "mb_per_view": round(float(np.mean(exr_bytes)) / 1e6, 3), "identical_to_before": pos_same,
    }
    return {"views": len(files), "png": png, "png_steps_ms_per_view": {k: med(v) for k, v in steps.items()},
            "position": position}


def main() -> int:
    keep_freed_memory()  # the worker's heap settings (services.worker.process.heap): timings as a worker's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--label", default="now")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    args = ap.parse_args()
    files = sorted(args.cache.glob("*-512-*.npz"))
    if not files:
        print("no cached pass sets: run bench/cues/derivations.py first")
        return 1
    rooms = sorted({f.name.split("-512-")[0] for f in files})
    load = [round(x, 2) for x in os.getloadavg()]
    run = {
        "clock": "process CPU ms, one core, median over views x repeats (per cue), summed over a view's cues",
        "repeats": args.repeats, "load_before": load,
        "rooms": {
            r: room_figures([f for f in files if f.name.startswith(r + "-512-")], args.repeats) for r in rooms
        },
    }
    run["load_after"] = [round(x, 2) for x in os.getloadavg()]
    data = (json.loads(RESULTS.read_text()) if RESULTS.exists()
            else {"benchmark": "bench/output/encode_cost.py"})
    data[args.label] = run
    RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    for r, res in run["rooms"].items():
        print(r)
        for name, v in res["png"].items():
            print(f"  PNG {name:30s} {v['ms_per_view']:6.2f} ms/view {v['mb_per_view']:.3f} MB "
                  f"identical={v['identical']}")
        print("  PNG steps (ms/view):", res["png_steps_ms_per_view"])
        print("  position:", res["position"])
    print("load", run["load_before"], "->", run["load_after"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
