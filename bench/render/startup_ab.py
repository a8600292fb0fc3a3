"""Benchmark: what a change saves of a run, as an A/B of two revisions on the same host and moment.

`omnidata generate` of --points x 3 views of each real room, --workers 1, pinned to one core. With the default
single point (3 views) its CPU is mostly start-up (imports, validation, levelling, planning, Blender, the
kernels, the curvature, the first render); with --points 22, the 66-view job of bench/render/room_cost.py, end
to end. The run of this checkout and the run of git revision --against (a worktree of it, its kernels compiled
ahead as `make venv` does) alternate, first one then the other, so a neighbour's load moves both; per room,
each side's CPU and wall seconds per repeat, their medians and the paired differences (against minus this
checkout). Writes bench/results/startup_ab.json under --key ("ab"; its other keys kept). With --user-caches,
this checkout against itself: each "against" run with an empty user cache ($OMNIDATA_DATA_DIR: the parsed
space and the curvature computed), each "this" run with the cache an earlier run on the room filled.
Run: .venv/bin/python bench/render/startup_ab.py --against REV [--points 1] [--repeats 5] [--core 1]
     [--worktree DIR] [--key ab]; --against-code DIR runs an existing checkout as the other side instead;
     --user-caches [--key user_caches] runs this checkout cold against warm.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from bench.lib.results import results_dir  # noqa: E402
from bench.render.room_cost import ROOMS, cpu_model, generate, load, median  # noqa: E402

RESULTS = results_dir() / "startup_ab.json"


def job_spec(points: int) -> dict:
    return {"points": {"count": points, "max_views": 3}, "views": {"resolution": 512}}


def worktree(rev: str, folder: Path) -> Path:
    """A checkout of `rev` in `folder` (reused when it holds one), with its kernels compiled, beside
    ../shared."""
    if not (folder / "services").is_dir():
        subprocess.run(["git", "worktree", "add", "--detach", str(folder), rev], cwd=ROOT, check=True,
                       capture_output=True)
    shared = folder.parent / "shared"
    if not shared.exists():
        shared.symlink_to(ROOT.parent / "shared")
    subprocess.run([sys.executable, "-m", "services.cli", "compile-kernels"], cwd=folder, check=True,
                   capture_output=True, env={**os.environ, "PYTHONPATH": str(folder)})
    return folder


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default="HEAD", help="the git revision before the change")
    ap.add_argument("--against-code", type=Path, default=None,
                    help="an existing checkout (kernels compiled) to run instead of a worktree of --against")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--core", default=str(sorted(os.sched_getaffinity(0))[-1]))
    ap.add_argument("--rooms", default=",".join(ROOMS))
    ap.add_argument("--worktree", type=Path, default=None, help="a folder for the revision's checkout (kept)")
    ap.add_argument("--points", type=int, default=1, help="points of the job (3 views each)")
    ap.add_argument("--key", default="ab", help="the entry of bench/results/startup_ab.json to write")
    ap.add_argument("--user-caches", action="store_true",
                    help="this checkout with empty user caches (against) and with warm ones (this)")
    args = ap.parse_args()
    code = ROOT if args.user_caches else args.against_code.resolve() if args.against_code else None
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD" if code else args.against], cwd=code or ROOT,
                         check=True, capture_output=True, text=True).stdout.strip()
    here = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=True, capture_output=True,
                          text=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="omnidata-startup-ab-") as tmp:
        old = code or worktree(rev, args.worktree or Path(tmp) / "before" / "main")
        spec = Path(tmp) / "spec.json"
        spec.write_text(json.dumps(job_spec(args.points)))
        sides = {"against": old, "this": ROOT}
        cpu: dict[str, dict[str, list[float]]] = {
            room: {k: [] for k in sides} for room in args.rooms.split(",")
        }
        wall: dict[str, dict[str, list[float]]] = {room: {k: [] for k in sides} for room in cpu}
        warm = Path(tmp) / "warm-user"
        if args.user_caches:  # one run per room fills the warm side's caches
            os.environ["OMNIDATA_DATA_DIR"] = str(warm)
            for room in cpu:
                generate(ROOMS[room][0], ROOMS[room][1], args.core, Path(tmp) / f"fill-{room}", spec, 1)
        before = load()
        for rep in range(args.repeats):
            for room, runs in cpu.items():
                space, extra = ROOMS[room]
                for side in list(sides)[:: 1 if rep % 2 == 0 else -1]:
                    root = sides[side]
                    if args.user_caches:
                        cold = Path(tmp) / f"cold-{rep}-{room}"
                        os.environ["OMNIDATA_DATA_DIR"] = str(warm if side == "this" else cold)
                    # its own copy
                    source = root / space.relative_to(ROOT) if space.is_relative_to(ROOT) else space
                    with tempfile.TemporaryDirectory(prefix="omnidata-startup-ab-") as out:
                        run = generate(source, extra, args.core, Path(out) / "o", spec, 1, root=root)
                    runs[side].append(run["cpu_s"])
                    wall[room][side].append(run["wall_s"])
            print(rep, json.dumps({"cpu_s": cpu, "wall_s": wall}), flush=True)
        if args.worktree is None and code is None:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, capture_output=True)
    rooms = {room: {"cpu_s": runs, "wall_s": wall[room],
                    "median_s": {k: median(v) for k, v in runs.items()},
                    "median_wall_s": {k: median(v) for k, v in wall[room].items()},
                    "paired_saving_s": paired(runs), "paired_wall_saving_s": paired(wall[room])}
             for room, runs in cpu.items()}
    for room, row in rooms.items():
        print(room, json.dumps({k: v for k, v in row.items() if k not in ("cpu_s", "wall_s")}))
    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    sides_are = {"sides": "against: empty user caches, this: warm ones"} if args.user_caches else {}
    data[args.key] = {"against": rev, "this": here, **sides_are, "views": 3 * args.points, "core": args.core,
                      "clock": "CPU and wall seconds of the run",
                      "machine": f"{os.cpu_count()} cores ({cpu_model()}), shared", "load_before": before,
                      "load_after": load(), "rooms": rooms}
    RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    return 0


def paired(runs: dict[str, list[float]]) -> list[float]:
    """Each repeat's against minus this checkout, sorted."""
    return sorted(round(a - b, 2) for a, b in zip(runs["against"], runs["this"], strict=True))


if __name__ == "__main__":
    raise SystemExit(main())
