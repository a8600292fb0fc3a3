"""Benchmark: where `generate`'s CPU goes per view, by library, sampled by Linux perf (the native side that
room_cost.py --phases, timed from Python, cannot split: the Cycles render, the compiled kernels, CPython
itself, the OS kernel's page faults and file writes, the PNG deflate, the checksums).

For each room, on one core (pinned as room_cost.py pins), `perf record` samples a whole `omnidata generate
ROOM --workers 1` of --points points (x --max-views views, 512 px, every default cue) and a 3-view run of the
same room; each library's CPU of the longer run minus the shorter one's, over the views it adds, is what one
more view costs in that library (start-up left out), set against the bare 1-sample render of the same views
(room_cost.py's floor, in a fresh process on the same core). Libraries are grouped by what they do
(`GROUPS`); the compiled kernels are numba's cached code, which perf sees as anonymous executable memory
("[JIT]"). Needs `perf` (Debian: linux-perf) and permission to sample (root, or kernel.perf_event_paranoid
<= 1). Writes bench/results/cpu_profile.json.
Run: .venv/bin/python bench/render/cpu_profile.py [--rooms icl_livingroom,...] [--points 14] [--core 1]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from bench.lib.results import results_dir  # noqa: E402
from bench.render.room_cost import ROOMS, add_room_job_arguments, floor, load, pinned  # noqa: E402

RESULTS = results_dir() / "cpu_profile.json"
# (group, substrings of a library's name perf reports), first match wins; the rest is "other"
GROUPS = (
    ("planning's ray casts (embreex)", ("libembree4-", "mesh_construction")),
    ("render: Blender, Cycles, Embree", ("__init__.so", "libembree", "libtbb", "libOpenImageIO",
                                         "libOpenColorIO", "libusd")),
    ("compiled kernels (numba)", ("[JIT]",)),
    ("CPython interpreter", ("libpython",)),
    ("OS kernel: page faults, file writes", ("[kernel",)),
    ("PNG deflate (ISA-L)", ("isal",)),
    ("checksums (sha256, blake2)", ("libcrypto", "_blake2", "_hashlib")),
    ("numpy", ("_multiarray", "_umath")),
    ("libc: copies, malloc", ("libc.so", "libm.so", "ld-linux")),
    ("BLAS, LAPACK (normalized cuts)", ("openblas",)),
    ("SQLite (the run's state)", ("sqlite",)),
)
SMALL_POINTS = 1  # the shorter run: one point, 3 views


def group_of(library: str) -> str:
    """The group of a library perf names (GROUPS), or "other"."""
    return next((name for name, keys in GROUPS if any(k in library for k in keys)), "other")


def cpu_by_group(report: str) -> dict[str, float]:
    """CPU seconds per group from `perf report --sort dso -F period,dso` output (cpu-clock periods are ns)."""
    out: dict[str, float] = {}
    for line in report.splitlines():
        parts = line.split(maxsplit=1)
        if len(parts) == 2 and parts[0].isdigit():
            group = group_of(parts[1].strip())
            out[group] = out.get(group, 0.0) + int(parts[0]) / 1e9
    return out


def sampled_generate(space: Path, extra: list[str], core: str, out: Path, spec: Path) -> tuple[int, dict]:
    """(views, CPU seconds per group) of one `generate` on `core` under perf record."""
    data = out.with_suffix(".perf")
    cmd = ["perf", "record", "-q", "-e", "cpu-clock", "-F", "999", "-o", str(data), "--",
           sys.executable, "-m", "services.cli", "generate", str(space), "--out", str(out),
           "--spec", str(spec), "--seed", "0", "--no-progress", "--workers", "1", *extra]
    run = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, preexec_fn=pinned(core),
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    if run.returncode != 0:
        raise RuntimeError(f"perf record of generate {space.name} failed ({run.returncode}): "
                           f"{run.stderr[-2000:]}")
    report = subprocess.run(["perf", "report", "-i", str(data), "--no-children", "--sort", "dso", "--stdio",
                             "-F", "period,dso"], capture_output=True, text=True, check=True).stdout
    views = len((out / "manifest.jsonl").read_text().splitlines())
    return views, cpu_by_group(report)


def profile_room(room: str, points: int, max_views: int, resolution: int, core: str, tmp: Path) -> dict:
    """One room: per added view, ms of CPU per group and against the floor; the runs' totals beside them."""
    space, extra = ROOMS[room]
    runs = {}
    for name, count in (("long", points), ("short", SMALL_POINTS)):
        spec = tmp / f"{room}-{name}.json"
        spec.write_text(json.dumps({"points": {"count": count, "max_views": max_views},
                                    "views": {"resolution": resolution}}))
        runs[name] = sampled_generate(space, extra, core, tmp / f"{room}-{name}", spec)
    (views, long), (short_views, short) = runs["long"], runs["short"]
    floor_s = floor(space, core, tmp / f"{room}-long")["cpu_s_per_view_median"]
    added = max(views - short_views, 1)
    per_view = {g: round(1000 * (long.get(g, 0.0) - short.get(g, 0.0)) / added, 2)
                for g in sorted(long, key=lambda g: -(long[g] - short.get(g, 0.0)))}
    total, floor_ms = sum(per_view.values()), 1000 * floor_s
    return {
        "views": [views, short_views], "floor_cpu_ms_per_view": round(floor_ms, 2),
        "added_view_cpu_ms": per_view,
        "added_view_x_floor": {g: round(ms / floor_ms, 3) for g, ms in per_view.items()},
        "added_view_total_ms": round(total, 1), "added_view_total_x_floor": round(total / floor_ms, 2),
        "run_cpu_s": {"long": round(sum(long.values()), 2), "short": round(sum(short.values()), 2)},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_room_job_arguments(ap)
    ap.add_argument("--core", default="1")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    if args.points <= SMALL_POINTS:
        ap.error(f"--points must be more than {SMALL_POINTS}: a view's cost is what a longer run adds over a "
                 f"{SMALL_POINTS}-point one")
    if shutil.which("perf") is None:
        print("cpu_profile: needs Linux perf on PATH (Debian: apt install linux-perf)", file=sys.stderr)
        return 2
    result: dict = {"core": args.core, "resolution": args.resolution,
                    "clock": "CPU ms sampled by perf (cpu-clock, 999 Hz), per view a longer run adds over a "
                    "3-view run", "load_before": load(), "rooms": {}}
    with tempfile.TemporaryDirectory(prefix="omnidata-cpuprofile-") as tmp:
        for room in args.rooms.split(","):
            result["rooms"][room] = profile_room(room, args.points, args.max_views, args.resolution,
                                                 args.core, Path(tmp))
            print(room, json.dumps(result["rooms"][room]), flush=True)
    result["load_after"] = load()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for room, r in result["rooms"].items():
        print(f"{room}: {r['added_view_total_ms']} ms a view = {r['added_view_total_x_floor']}x the floor "
              f"({r['floor_cpu_ms_per_view']} ms)")
        for group, ms in r["added_view_cpu_ms"].items():
            print(f"  {group:40s} {ms:7.2f} ms  {r['added_view_x_floor'][group]:.3f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
