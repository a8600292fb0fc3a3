"""Benchmark: `omnidata generate` with the user's warm-start server against without it
(services.cli.warm_start), on real rooms, as a user sees it: wall seconds of the command.

For each room and repeat, alternating which goes first: a 3-view job and a --points x --max-views job (512 px,
every default cue), each cold (OMNIDATA_WARM_START=0: the command imports everything itself) and warm (a
server of this checkout, started once per room and waited for, forks the run). One core (`--core`, the whole
process tree pinned as room_cost.py pins it), and with --cores 0,1 the longer job on both cores too. The run's
CPU: cold, the command's process tree; warm, the server's record of its run (its own and its workers'). The
longer job's wall per view is set against the bare 1-sample render of its views on the same core
(room_cost.floor), the ratio issue 49 states its target in. Writes bench/results/warm_start.json.
Run: .venv/bin/python bench/render/warm_start.py [--rooms icl_livingroom,...] [--points 14] [--repeats 3]
[--cores 0,1] [--out FILE]; the long job: --points 60 --out bench/results/warm_start_long.json
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from bench.lib.results import results_dir  # noqa: E402
from bench.render.room_cost import (  # noqa: E402
    ROOMS,
    add_room_job_arguments,
    floor,
    generate,
    load,
    median,
    pinned,
)
from services.cli import warm_start  # noqa: E402

RESULTS = results_dir() / "warm_start.json"
ENDED = re.compile(r"^run (\d+) ended: .*, cpu_s ([0-9.]+)$")


def start_server(folder: Path, core: str) -> subprocess.Popen[bytes]:
    """This checkout's warm server for `folder`, ready (its socket in place); it preloads on `core`."""
    log = open(folder / "server.log", "ab")  # noqa: SIM115 (the server writes it while it lives)
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli.warm_server", str(folder), warm_start.server_name()],
        cwd=ROOT, stdout=log, stderr=log, start_new_session=True, preexec_fn=pinned(core),
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    deadline = time.monotonic() + 120
    while not (folder / f"{warm_start.server_name()}.sock").exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            log_tail = (folder / "server.log").read_text()[-2000:]
            raise RuntimeError(f"the warm server did not start: {log_tail}")
        time.sleep(0.05)
    return proc


def last_run_cpu(folder: Path) -> float:
    """CPU seconds of the server's last finished run (its log's last "run PID ended" line)."""
    lines = [m for m in map(ENDED.match, (folder / "server.log").read_text().splitlines()) if m]
    return float(lines[-1].group(2))


def run(room: str, cores: str, out: Path, spec: Path, workers: int | None, warm: Path | None) -> dict:
    env = {"OMNIDATA_WARM_START": "1", "OMNIDATA_WARM_DIR": str(warm)} if warm else {
        "OMNIDATA_WARM_START": "0"}
    res = generate(*ROOMS[room], cores, out, spec, workers, env=env)
    cpu = last_run_cpu(warm) if warm else res["cpu_s"]
    # the render process's time in render tasks, of the run's wall time (None where compaction took the rows)
    render_busy = res["busy"]["render_busy_of_wall"] if res["busy"] else None
    return {"views": res["views"], "wall_s": res["wall_s"], "cpu_s": round(cpu, 3),
            "render_busy_of_wall": render_busy, "load_before": res["load_before"]}


def room_figures(room: str, args: argparse.Namespace, tmp: Path) -> dict:
    warm_dir = Path(tempfile.mkdtemp(prefix="ow-"))  # short: a socket's path is at most 107 bytes
    server = start_server(warm_dir, args.core)
    small, big = tmp / "small.json", tmp / "big.json"
    views = {"resolution": args.resolution}
    small.write_text(json.dumps({"points": {"count": 1, "max_views": 3}, "views": views}))
    big.write_text(json.dumps({"points": {"count": args.points, "max_views": args.max_views},
                               "views": views}))
    jobs = [("small", small, args.core, 1), ("big", big, args.core, 1)]
    if args.cores:
        jobs.append(("big_all_cores", big, args.cores, None))
    runs: dict[str, dict[str, list[dict]]] = {name: {"cold": [], "warm": []} for name, *_ in jobs}
    try:
        for i in range(args.repeats):
            for mode in (("cold", "warm") if i % 2 == 0 else ("warm", "cold")):
                for name, spec, cores, workers in jobs:
                    out = tmp / f"{room}-{name}-{mode}-{i}"
                    runs[name][mode].append(
                        run(room, cores, out, spec, workers, warm_dir if mode == "warm" else None))
        bare = floor(ROOMS[room][0], args.core, tmp / f"{room}-big-cold-0")
    finally:
        server.kill()
        server.wait()
    figures: dict = {"floor_s_per_view": bare["s_per_view_mean"], "runs": runs}
    for name, by_mode in runs.items():
        med = {mode: {k: median([r[k] for r in rs]) for k in ("wall_s", "cpu_s")}
               for mode, rs in by_mode.items()}
        views = by_mode["cold"][0]["views"]
        figures[name] = {
            "views": views, **{f"{mode}_{k}": round(v, 3) for mode, m in med.items() for k, v in m.items()},
            "wall_s_saved": round(med["cold"]["wall_s"] - med["warm"]["wall_s"], 3),
            "cpu_s_saved": round(med["cold"]["cpu_s"] - med["warm"]["cpu_s"], 3),
        }
        if name == "big":
            for mode in ("cold", "warm"):
                per_view = med[mode]["wall_s"] / views
                figures[name][f"{mode}_x_floor"] = round(per_view / bare["s_per_view_mean"], 2)
    if "big_all_cores" in figures:
        for mode in ("cold", "warm"):
            figures["big_all_cores"][f"{mode}_views_per_s_to_one_core"] = round(
                figures["big"][f"{mode}_wall_s"] / figures["big_all_cores"][f"{mode}_wall_s"], 2)
            busy = [r["render_busy_of_wall"] for r in runs["big_all_cores"][mode] if r["render_busy_of_wall"]]
            figures["big_all_cores"][f"{mode}_render_busy_of_wall"] = round(median(busy), 3) if busy else None
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_room_job_arguments(ap)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--core", default=str(sorted(os.sched_getaffinity(0))[-1]))
    ap.add_argument("--cores", default="", help="also the longer job on these cores, e.g. 0,1")
    ap.add_argument("--out", type=Path, default=RESULTS, help="results file (a longer job: its own)")
    args = ap.parse_args()
    compileall.compile_dir(ROOT / "services", quiet=1)  # as room_cost.py: bytecode written before timing
    result: dict = {"clock": "wall seconds (CPU beside)", "core": args.core, "cores": args.cores,
                    "load_before": load(), "rooms": {}}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="omnidata-warm-bench-") as tmp:
        for room in args.rooms.split(","):
            result["rooms"][room] = room_figures(room, args, Path(tmp))
            shown = {k: v for k, v in result["rooms"][room].items() if k != "runs"}
            print(room, json.dumps(shown), flush=True)
    result.update(load_after=load(), wall_s=round(time.perf_counter() - t0, 1))
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
