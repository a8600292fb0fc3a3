"""Benchmark: what compiling the worker's kernels ahead costs and saves, and what the portable CPU target
costs.

1. `omnidata compile-kernels` into an empty numba cache (NUMBA_CACHE_DIR), on one core: wall and CPU seconds.
2. The first `omnidata generate` a user or a new worker pod meets, ICL living room, 3 views at 512 px: with an
   empty cache (every kernel compiled by the job's workers), and with the cache compile-kernels filled; on one
   core with one worker, and on --cores with the default workers (one a core: each compiles the same kernels
   at once).
3. Derivation CPU seconds per view (every default cue but the render, encodings included;
   bench/cues/derivations.py's views and clock; per cue too) with the kernels built for this machine's own
   CPU, for each x86-64 level it runs (services/worker/process/kernel_target.py) and for numba's baseline
   "generic" x86-64, each in a fresh process with its own cache; the order of the targets rotates between
   repeats.

Writes bench/results/kernel_cache.json (a part not run keeps its last figures; --key puts the derive part's
under another entry, e.g. another host's beside this one's).
Run: .venv/bin/python bench/render/kernel_cache.py [--core 1] [--cores 0,1] [--parts first,derive] [--repeats
6] [--key K]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from bench.render.room_cost import children_cpu_s, cpu_model, load, median, pinned  # noqa: E402
from services.worker.process.kernel_target import host_features, level_environment, levels_for  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "kernel_cache.json"
ICL = ROOT.parent / "shared" / "scenes" / "icl_livingroom"
SPEC = '{"points": {"count": 1, "max_views": 3}, "views": {"resolution": 512}}'

DERIVE = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
from bench.cues.derivations import room_views, time_view
from services.core.domain.cues import default_cues
cues = default_cues(has_semantics=False)
out, per_cue = {}, {}
for room in sys.argv[2].split(","):
    passes, plan, views = room_views(room, int(sys.argv[4]), 512, __import__("pathlib").Path(sys.argv[3]))
    time_view(passes[0], views[0], plan, cues)  # compiles this target's kernels (its own cache)
    runs = [time_view(p, v, plan, cues) for _ in range(3) for p, v in zip(passes, views)]
    out[room] = float(np.median([sum(d + e for d, e in t.values()) for t in runs]))
    per_cue[room] = {c: round(float(np.median([sum(t[c]) for t in runs])), 5) for c in cues}
from numba.core.registry import cpu_target
print(json.dumps({"per_view_s": out, "per_cue_s": per_cue,
                  "codegen": cpu_target.target_context.codegen().magic_tuple()[1]}))
"""


def environment(cache: Path, **extra: str) -> dict[str, str]:
    """This environment without numba settings, with `cache` as numba's cache folder."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    return {**env, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(cache), **extra}


def timed(cmd: list[str], env: dict[str, str], cores: str) -> dict:
    """Run `cmd` pinned to `cores`: wall and CPU seconds of its whole process tree."""
    before = load()
    t0, cpu0 = time.perf_counter(), children_cpu_s()
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, preexec_fn=pinned(cores))
    if res.returncode != 0:
        raise RuntimeError(f"{cmd[2:4]} failed: {res.stderr[-2000:]}")
    return {
        "wall_s": round(time.perf_counter() - t0, 2), "cpu_s": round(children_cpu_s() - cpu0, 2),
        "load_before": before, "load_after": load(), "stdout": (res.stdout.strip().splitlines() or [""])[-1],
    }


def first_generate(tmp: Path, cores: str, workers: int | None, warm: bool) -> dict:
    """`generate` of 3 ICL views with a fresh cache, filled by compile-kernels first when `warm`."""
    cache = tmp / f"cache-{cores}-{workers}-{warm}"
    env = environment(cache)
    out: dict = {
        "cores": cores, "workers": workers or "default",
        "cache": "compile-kernels first" if warm else "empty",
    }
    if warm:
        out["compile_kernels"] = timed([sys.executable, "-m", "services.cli", "compile-kernels"], env, cores)
    spec = tmp / "spec.json"
    spec.write_text(SPEC)
    cmd = [
        sys.executable, "-m", "services.cli", "generate", str(ICL), "--out", str(cache.with_suffix(".out")),
        "--spec", str(spec), "--seed", "0", "--no-progress",
        *(["--workers", str(workers)] if workers else []),
    ]
    out["generate"] = timed(cmd, env, cores)
    return out


def derivations(tmp: Path, core: str, repeats: int, rooms: str, passes_cache: Path, views: int = 6,
                only: str = "") -> dict:
    """Derivation CPU-s per view with the kernels built for the host CPU, each x86-64 level it runs and
    generic x86-64."""
    levels = levels_for(platform.machine(), host_features())
    host = subprocess.run(
        [sys.executable, "-c", "import llvmlite.binding as ll; print(ll.get_host_cpu_name())"],
        capture_output=True, text=True,
    ).stdout.strip()
    targets = {"host": {"NUMBA_CPU_NAME": host}, **{level: level_environment(level) for level in levels},
               "generic": {"NUMBA_CPU_NAME": "generic"}}
    # "worker": the worker's own choice and the checkout's cache (compile-kernels'), nothing compiled
    if only:
        targets = {name: targets.get(name, {}) for name in only.split(",")}
    runs: dict[str, list[dict]] = {t: [] for t in targets}
    names = list(targets)
    for r in range(repeats):
        for name in names[r % len(names):] + names[:r % len(names)]:
            env = (environment(tmp / f"derive-{name}", **targets[name]) if name != "worker"
                   else {**os.environ, "PYTHONPATH": str(ROOT)})
            cmd = [sys.executable, "-c", DERIVE, str(ROOT), rooms, str(passes_cache), str(views)]
            res = timed(cmd, env, core)
            runs[name].append({**json.loads(res.pop("stdout")), **res})
    summary = {
        name: {room: round(median([x["per_view_s"][room] for x in rs]), 4) for room in rooms.split(",")}
        for name, rs in runs.items()
    }
    cues = {
        name: {
            room: {
                c: round(median([x["per_cue_s"][room][c] for x in rs]), 4) for c in rs[0]["per_cue_s"][room]
            }
            for room in rooms.split(",")
        }
        for name, rs in runs.items()
    }
    return {"host_cpu": host, "per_view_s_median": summary,
            "to_host": {name: {room: round(v / summary["host"][room], 3) for room, v in s.items()}
                        for name, s in summary.items()} if "host" in summary else None,
            "per_cue_s_median": cues,
            "runs": runs}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--core", default=str(sorted(os.sched_getaffinity(0))[-1]))
    ap.add_argument("--cores", default=",".join(map(str, sorted(os.sched_getaffinity(0)))))
    ap.add_argument("--repeats", type=int, default=6, help="derivation runs per target")
    ap.add_argument(
        "--parts", default="first,derive", help="first (the first generate), derive (the targets)"
    )
    ap.add_argument("--rooms", default="icl_livingroom,7scenes_redkitchen")
    ap.add_argument("--passes-cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    ap.add_argument("--views", type=int, default=6, help="views per room of the derive part")
    ap.add_argument("--targets", default="", help="only these targets of the derive part (e.g. host,generic; "
                    "worker: the worker's own, from the checkout's kernel cache, nothing compiled)")
    ap.add_argument("--key", default="derivations_by_target",
                    help="entry of the derive part (another host's figures beside this one's)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    parts = set(args.parts.split(","))
    data = (json.loads(RESULTS.read_text()) if RESULTS.exists()
            else {"benchmark": "bench/render/kernel_cache.py"})
    with tempfile.TemporaryDirectory(prefix="omnidata-kernelcache-") as tmp_name:
        tmp = Path(tmp_name)
        if "first" in parts:
            data["first_generate"] = [
                first_generate(tmp, cores, workers, warm)
                for cores, workers in ((args.core, 1), (args.cores, None))
                for warm in (False, True)
            ]
            for run in data["first_generate"]:
                print(json.dumps(run), flush=True)
        if "derive" in parts:
            before = load()
            figures = derivations(tmp, args.core, args.repeats, args.rooms, args.passes_cache, args.views,
                                  args.targets)
            data[args.key] = {"machine": f"{os.cpu_count()} cores ({cpu_model()})", "load_before": before,
                              **figures,
                              "load_after": load()}
            print(json.dumps({k: v for k, v in data[args.key].items() if k != "runs"}), flush=True)
    data.update(commit=subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                      text=True).stdout.strip(),
                machine=f"{os.cpu_count()} cores, shared", wall_s=round(time.perf_counter() - t0, 1))
    RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
