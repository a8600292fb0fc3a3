"""Benchmark: cost per view on real rooms as a user sees it, against the bare render of the same views (issue
20).

For each room it runs, on one core (pinned as `taskset -c CORE` would, so the whole process tree shares it),
interleaved:
1. `omnidata generate ROOM --workers 1` at 512x512 with every default cue: wall time per view end to end
   (start-up, planning, space loading, render, derivations, orchestration), and the job's own task rows
   (sum of `duration_s` per cue / views) from its SQLite state, and per view its passes task and its derived
   tasks together (first view, which carries the worker's one-off set-up, and the median view). A long run's
   finished views are compacted into one row each (services.scheduler.compaction): their durations are read
   from those rows; its timeline (queue and start times, which compaction drops) is then left out;
2. in a fresh process on the same core, the bare 1-sample Cycles render (Image + Depth + Normal, no AOVs,
   nothing read back) of the very views that job rendered (its stored plan): wall seconds per view.
Each repeat runs 1 then 2, so a neighbour's load moves both; the ratio is taken per repeat and reported as the
median and the worst case over repeats, with the load average beside each figure.
With --cores 0,1 it also runs generate with its default worker settings on those cores (all-cores figure) and
compares views/s with the one-core run of the same repeat, and runs the bare render on each of those cores at
once (what the machine's cores give a render at best, the ceiling of that ratio); with the 3-view runs on
both settings, also the views/s of the views a longer job adds (the slope, start-ups left out: what a long job
on many cores approaches).

A 3-view run of the same room on the same core (unless --no-startup) splits generate's CPU into what a run
pays whatever its size (start-up: imports, space loads, curvature, planning) and the CPU of one more view (the
slope), set against the floor's. `claims` counts task claims (a view batch claims a view's derived tasks at
once). Figures go to bench/results/room_cost.json under "room_cost", or --key (the previous run's figures kept
as "<key>_before"; the file's other keys are left as they are). A long job, where start-up
is spread over a thousand views and more: --points 22 --max-views 60 --no-startup --key room_cost_long.
--phases N instead: where the worker's CPU goes per view, N runs timed inside the worker (each cue's task
seconds as its row records them, beside its derivation's CPU; the store, the claims, the serve loop), with
--against REV that revision's alternately; under "worker_overhead".
Run: .venv/bin/python bench/render/room_cost.py [--points 14] [--max-views 3] [--repeats 2] [--core 1] [--key
K] [--phases N [--against REV]]
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import platform
import resource
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from bench.lib.results import results_dir  # noqa: E402
from services.core.db.view_outputs import DoneTask, unpack  # noqa: E402

RESULTS = results_dir() / "room_cost.json"
SCENES = ROOT.parent / "shared" / "scenes"
SCANS = ROOT / "bench" / "scans"
# name -> (SPACE argument, extra generate flags). The kitchen's fused mesh is not gravity aligned; its capture
# ships the gravity direction (gravity-direction.txt: up is its negative), given so no low-confidence guess is
# used. The copy room (textured, in its first camera's frame) is refused as ambiguous without one: its
# measured up.
ROOMS: dict[str, tuple[Path, list[str]]] = {
    "icl_livingroom": (SCENES / "icl_livingroom", []),
    "7scenes_redkitchen": (SCENES / "7scenes_redkitchen" / "mesh_tsdf_2cm_from_1000frames.ply",
                           ["--up", "0.009,-0.904,-0.427"]),
    "copyroom": (SCANS / "copyroom", ["--up=-0.0023,-0.8052,-0.5930"]),  # "=": a value starting with "-"
}

FLOOR_PROBE = r"""
import json, sys, time
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from services.core.domain.plan import plan_from_json
from services.core.ingest.loading import load_space
from services.worker.passes import ViewGeometry
from services.worker.process.heap import keep_freed_memory
from services.worker.inputs.space_cache import SpaceContext
# a worker's heap (services.worker.process.heap): without it the bare render refaults its buffers
keep_freed_memory()
space_path, plan_path, frame = sys.argv[2], sys.argv[3], json.loads(sys.argv[4])
device = sys.argv[5] if len(sys.argv) > 5 else "cpu"
plan = plan_from_json(Path(plan_path).read_bytes())
scene = SpaceContext.from_loaded(load_space(space_path, **frame), key="floor", device=device).scene()
views = [ViewGeometry.of(v) for v in plan.views]
# Cycles kernels and the BVH: a worker pays them once per space, not per view
first = scene.render_floor(views[0])
if len(sys.argv) > 6:  # one of several probes on their own cores: all start the timed renders together
    print("ready", flush=True)
    sys.stdin.readline()
walls, cpus = [], []
for g in views:
    c0 = time.process_time()
    walls.append(scene.render_floor(g))
    cpus.append(time.process_time() - c0)
print(json.dumps({"wall": walls, "cpu": cpus, "first_s": first, "device": scene.device}))
"""


def load() -> list[float]:
    """The 1, 5 and 15 minute load averages (other developers share this machine)."""
    return [round(x, 2) for x in os.getloadavg()]


def cpuinfo() -> dict[str, str]:
    """The first processor's fields of /proc/cpuinfo (empty where there is none)."""
    fields: dict[str, str] = {}
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []:
        if not line.strip():
            break
        key, _, value = line.partition(":")
        fields[key.strip()] = value.strip()
    return fields


def cpu_model() -> str:
    """The processor's name (ratios to the floor move little between hosts; seconds do, ~2x)."""
    return cpuinfo().get("model name") or platform.processor() or "unknown processor"


def median(values: list[float]) -> float:
    s = sorted(values)
    n = len(s)
    return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


def children_cpu_s() -> float:
    """CPU seconds of every finished child process tree (generate reaps its workers, so theirs count too)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def pinned(cores: str) -> Callable[[], None]:
    """Pins a child (and the processes it starts) to `cores`, a CPU list as `taskset -c` takes it ("0", "0,1",
    "0-7"), without taskset (which some machines lack)."""
    wanted: set[int] = set()
    for part in cores.split(","):
        first, _, last = part.partition("-")
        wanted.update(range(int(first), int(last or first) + 1))
    return lambda: os.sched_setaffinity(0, wanted)


def generate(space: Path, extra: list[str], cores: str, out: Path, spec: Path, workers: int | None,
             device: str = "auto", root: Path = ROOT, entry: tuple[str, ...] = ("-m", "services.cli"),
             env: dict[str, str] | None = None) -> dict:
    """Run `omnidata generate` of the checkout at `root` pinned to `cores` rendering on `device`
    (OMNIDATA_RENDER_DEVICE); wall seconds, views, and per-cue task seconds from its task rows. `entry`: what
    python runs (--phases: bench/lib/worker_phases.py), `env` added to its environment."""
    cmd = [sys.executable, *entry, "generate", str(space), "--out", str(out),
           "--spec", str(spec), "--seed", "0", "--no-progress", *extra]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    before = load()
    t0, cpu0, started = time.perf_counter(), children_cpu_s(), time.time()
    run = subprocess.run(cmd, cwd=root, capture_output=True, text=True, preexec_fn=pinned(cores),
                         env={**os.environ, "PYTHONPATH": str(root), "OMNIDATA_RENDER_DEVICE": device,
                              **(env or {})})
    wall, cpu = time.perf_counter() - t0, children_cpu_s() - cpu0
    if run.returncode != 0:
        raise RuntimeError(
            f"generate {space.name} on {device} failed ({run.returncode}): {run.stderr[-2000:]}"
        )
    views = len((out / "manifest.jsonl").read_text().splitlines())
    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
        # a view batch's tasks share their claim's started_at: claims = distinct (worker, started_at)
        tasks, claims = db.execute(
            "SELECT COUNT(*), COUNT(DISTINCT worker_id || started_at) FROM task"
        ).fetchone()
        done = view_durations(db)
        # A long run compacts its finished views (services.scheduler.compaction): their rows, queue and start
        # times are gone, so the timeline reads only from a run that compacted nothing.
        steps = timeline(db, started, started + wall) if not done.compacted else None
        busy = busy_fractions(db, wall) if not done.compacted else None
    # Per view, in the order they ran: the passes task, and the view's derived tasks together. The first
    # view's carry what a worker pays once (the space's scene, curvature, first kernel loads); the median is a
    # view in the steady state.
    renders = [d.get("passes", 0.0) for d in done.per_view]
    derivations = [sum(s for cue, s in d.items() if cue != "passes") for d in done.per_view]
    per_cue: dict[str, float] = {}
    for d in done.per_view:
        for cue, s in d.items():
            per_cue[cue] = per_cue.get(cue, 0.0) + s
    per_cue = {cue: round(total / views, 4) for cue, total in per_cue.items()}
    return {
        "cores": cores, "device": device, "views": views, "wall_s": round(wall, 2),
        "wall_s_per_view": round(wall / views, 4), "views_per_s": round(views / wall, 3),
        "cpu_s": round(cpu, 2), "cpu_s_per_view": round(cpu / views, 4), "load_before": before,
        "load_after": load(), "tasks": tasks, "claims": claims, "compacted_views": done.compacted,
        "task_s_per_view": dict(sorted(per_cue.items(), key=lambda kv: -kv[1])),
        "task_s_per_view_total": round(sum(per_cue.values()), 4),
        "passes_task_s": {"first": round(renders[0], 4), "median": round(median(renders), 4)},
        "derivations_s_per_view": {
            "first": round(derivations[0], 4), "median": round(median(derivations), 4),
        },
        "timeline_s": steps, "busy": busy,
    }


@dataclass
class ViewDurations:
    """Each view's task seconds by cue, in the order the views ran, and how many of them were compacted."""

    per_view: list[dict[str, float]]
    compacted: int


def packed_views(db: sqlite3.Connection) -> list[list[DoneTask]]:
    """The done tasks of each view a long run compacted into one `view_output` row
    (services.core.db.view_outputs)."""
    return [unpack(blob, lambda cue: "") for (blob,) in db.execute("SELECT outputs FROM view_output")]


def view_durations(db: sqlite3.Connection) -> ViewDurations:
    """Task seconds of every view of a run's state: its done task rows, and the views compaction packed into
    one `view_output` row each (services.core.db.view_outputs; those ran first, so they come first, by finish
    time)."""
    packed = [
        (min(t.finished_at for t in tasks if t.finished_at), {t.cue: t.duration_s or 0.0 for t in tasks})
        for tasks in packed_views(db)
    ]
    rows: dict[tuple, dict[str, float]] = {}
    for space, point, view, cue, seconds in db.execute(
            "SELECT space_id, point_idx, view_idx, cue, duration_s FROM task WHERE state = 'done' "
            "ORDER BY started_at"):
        rows.setdefault((space, point, view), {})[cue] = seconds or 0.0
    return ViewDurations(
        [d for _, d in sorted(packed, key=lambda p: p[0])] + list(rows.values()), len(packed)
    )


def unix(stamp: str) -> float:
    """Unix time of a task row's timestamp (UTC, stored without its zone)."""
    moment = datetime.fromisoformat(stamp)
    return (moment if moment.tzinfo else moment.replace(tzinfo=UTC)).timestamp()


def timeline(db: sqlite3.Connection, start: float, end: float) -> dict:
    """Where a run's wall time went, in seconds from its start (task rows): its first task queued (the
    parent's validation and planning), started, each worker's first task (its start-up: first, median, last
    worker), the last task finished, and the process's end."""
    queued, first, last = db.execute(
        "SELECT MIN(queued_at), MIN(started_at), MAX(finished_at) FROM task WHERE state = 'done'").fetchone()
    per_worker = sorted(unix(t) - start for (t,) in db.execute(
        "SELECT MIN(started_at) FROM task WHERE state = 'done' GROUP BY worker_id"))
    return {
        "first_task_queued": round(unix(queued) - start, 2),
        "first_task_started": round(unix(first) - start, 2), "workers": len(per_worker),
        "worker_first_task": [
            round(per_worker[i], 2) for i in (0, len(per_worker) // 2, len(per_worker) - 1)
        ],
        "last_task_finished": round(unix(last) - start, 2), "process_end": round(end - start, 2),
    }


def busy_fractions(db: sqlite3.Connection, wall: float) -> dict:
    """How busy each worker process was (its task rows' seconds), and the render process's share of the job's
    wall time in render tasks: of the whole run, and of the task window (first task started to last
    finished). The render process is the one that rendered most views (with renderers of their own, the only
    one on two cores)."""
    rows = db.execute(
        "SELECT worker_id, SUM(CASE WHEN cue = 'passes' THEN duration_s ELSE 0 END), SUM(duration_s), "
        "SUM(cue = 'passes'), MIN(started_at), MAX(finished_at) FROM task WHERE state = 'done' "
        "GROUP BY worker_id").fetchall()
    if not rows:
        return {}
    window = max(1e-9, max(unix(r[5]) for r in rows) - min(unix(r[4]) for r in rows))
    render = max(rows, key=lambda r: r[3])
    return {
        "render_busy_of_wall": round(render[1] / wall, 3),
        "render_busy_of_task_window": round(render[1] / window, 3),
        "render_process_busy_of_task_window": round(render[2] / window, 3), "task_window_s": round(window, 2),
        "processes": [{"views_rendered": int(r[3]), "render_s": round(r[1], 2), "busy_s": round(r[2], 2)}
                      for r in sorted(rows, key=lambda r: -r[3])],
    }


def plan_frame(out: Path) -> dict:
    """The space frame a `generate` into `out` used (job.json's spec), to load the space the same way."""
    spec = json.loads((out / "job.json").read_text()).get("spec", {})
    return {k: spec[k] for k in ("up_axis", "up", "unit_scale", "source_to_world") if k in spec}


def floor(space: Path, cores: str, out: Path, device: str = "cpu") -> dict:
    """Bare 1-sample renders of the views `generate` planned into `out`, in a fresh process on `cores`."""
    plans = sorted((out / "_plan").glob("*.json"))
    before = load()
    run = subprocess.run(
        [
            sys.executable, "-c", FLOOR_PROBE, str(ROOT), str(space), str(plans[0]),
            json.dumps(plan_frame(out)), device,
        ],
        cwd=ROOT, capture_output=True, text=True, preexec_fn=pinned(cores),
        env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"},
    )
    if run.returncode != 0:
        raise RuntimeError(
            f"floor of {space.name} on {device} failed ({run.returncode}): {run.stderr[-2000:]}"
        )
    times = json.loads(run.stdout.strip().splitlines()[-1])
    wall = times["wall"]
    return {
        "device": times["device"], "cores": cores, "views": len(wall),
        "first_render_s": round(times["first_s"], 3), "s_per_view_median": round(median(wall), 4),
        "s_per_view_mean": round(sum(wall) / len(wall), 4), "s_per_view_worst": round(max(wall), 4),
        "cpu_s_per_view_median": round(median(times["cpu"]), 4),
        "cpu_s_per_view_mean": round(sum(times["cpu"]) / len(wall), 4), "load_before": before,
        "load_after": load(),
    }


def floor_all_cores(space: Path, cores: str, out: Path) -> dict:
    """The bare renders of `out`'s views on every core of `cores` at once, one process pinned to each core,
    their timed renders started together: the views/s the machine itself gains from its cores (shared caches,
    memory bandwidth, the host's scheduling), the ceiling of any job's speed-up from them."""
    plans = sorted((out / "_plan").glob("*.json"))
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", FLOOR_PROBE, str(ROOT), str(space), str(plans[0]),
             json.dumps(plan_frame(out)), "cpu", "together"],
            cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            preexec_fn=pinned(core), env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"},
        )
        for core in cores.split(",")
    ]
    for proc in procs:  # each has loaded the space and rendered its first view
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready", "floor probe failed"
    for proc in procs:
        assert proc.stdin is not None
        proc.stdin.write("go\n")
        proc.stdin.flush()
    walls = []
    for proc in procs:
        stdout, _ = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"floor of {space.name} on cores {cores} failed ({proc.returncode})")
        walls.append(json.loads(stdout.strip().splitlines()[-1])["wall"])
    views = sum(len(w) for w in walls)
    return {"cores": cores, "views": views, "views_per_s": round(views / max(sum(w) for w in walls), 3)}


DERIVED_EXCLUDE = ("passes",)  # the render task; every other task is a derivation (and its encoding)


def summarise(repeats: list[dict]) -> dict:
    """Per-repeat ratios to the floor (mean floor per view, as the end-to-end figure is a mean), median and
    worst."""
    e2e = [r["generate"]["wall_s_per_view"] / r["floor"]["s_per_view_mean"] for r in repeats]
    e2e_cpu = [r["generate"]["cpu_s_per_view"] / r["floor"]["cpu_s_per_view_mean"] for r in repeats]
    passes = [
        r["generate"]["task_s_per_view"].get("passes", 0.0) / r["floor"]["s_per_view_mean"] for r in repeats
    ]
    derived = [sum(v for k, v in r["generate"]["task_s_per_view"].items() if k not in DERIVED_EXCLUDE)
               / r["floor"]["s_per_view_mean"] for r in repeats]
    out = {
        "end_to_end_to_floor": {"median": round(median(e2e), 2), "worst": round(max(e2e), 2)},
        "end_to_end_cpu_to_floor_cpu": {"median": round(median(e2e_cpu), 2), "worst": round(max(e2e_cpu), 2)},
        "passes_task_to_floor": {"median": round(median(passes), 2), "worst": round(max(passes), 2)},
        "derivations_to_floor": {"median": round(median(derived), 2), "worst": round(max(derived), 2)},
    }
    # The steady state: a median view's passes task and derivations against the floor's median view (the means
    # above also carry the first view's one-off set-up)
    for name, key in (("passes_task_median_view_to_floor", "passes_task_s"),
                      ("derivations_median_view_to_floor", "derivations_s_per_view")):
        ratios = [r["generate"][key]["median"] / r["floor"]["s_per_view_median"] for r in repeats
                  if key in r["generate"]]
        if ratios:
            out[name] = {"median": round(median(ratios), 2), "worst": round(max(ratios), 2)}
    multi = [
        r["all_cores"]["views_per_s"] / r["generate"]["views_per_s"] for r in repeats if "all_cores" in r
    ]
    if multi:
        out["all_cores_to_one_core_views_per_s"] = {
            "median": round(median(multi), 2), "worst": round(min(multi), 2),
        }
    machine = [r["floor_all_cores"]["views_per_s"] * r["floor"]["s_per_view_mean"] for r in repeats
               if "floor_all_cores" in r]
    if machine:  # the bare render alone on all cores against one: what the cores give at best
        out["floor_all_cores_to_one_core_views_per_s"] = {"median": round(median(machine), 2),
                                                          "worst": round(min(machine), 2)}
    for name, run in (("one_core", "generate"), ("all_cores", "all_cores")):
        busy = [r[run]["busy"] for r in repeats if r.get(run, {}).get("busy")]
        if busy:  # the render process's time in render tasks: of the run's wall, of its task window
            out[f"render_busy_{name}"] = {
                k: round(median([b[k] for b in busy]), 3)
                for k in ("render_busy_of_wall", "render_busy_of_task_window",
                          "render_process_busy_of_task_window")
            }
    multi_floor = [r["all_cores"]["wall_s_per_view"] / r["floor"]["s_per_view_mean"] for r in repeats
                   if "all_cores" in r]
    if multi_floor:
        out["all_cores_end_to_end_to_floor"] = {"median": round(median(multi_floor), 2),
                                                "worst": round(max(multi_floor), 2)}
    steady = [
        marginal_views_per_s(r["all_cores"], r["all_cores_startup"])
        / marginal_views_per_s(r["generate"], r["startup"])
        for r in repeats
        if "all_cores_startup" in r
    ]
    if steady:  # a long job's ratio: one more view's wall time, on all cores against one (start-ups left out)
        out["all_cores_to_one_core_marginal_views_per_s"] = {"median": round(median(steady), 2),
                                                             "worst": round(min(steady), 2)}
    starts = [r for r in repeats if "startup" in r]
    if starts:
        # what a run pays whatever its size (imports, space loads, curvature, planning) and the cost of one
        # more view
        fixed = [r["startup"]["cpu_s"] - r["startup"]["views"] * marginal_cpu(r) for r in starts]
        marginal = [marginal_cpu(r) / r["floor"]["cpu_s_per_view_mean"] for r in starts]
        out["startup_cpu_s"] = {"median": round(median(fixed), 2), "worst": round(max(fixed), 2)}
        out["marginal_cpu_per_view_to_floor_cpu"] = {"median": round(median(marginal), 2),
                                                     "worst": round(max(marginal), 2)}
    return out


def marginal_views_per_s(big: dict, small: dict) -> float:
    """Views a second of the views a bigger run adds: the slope of wall time between two runs of one
    setting."""
    return (big["views"] - small["views"]) / max(1e-9, big["wall_s"] - small["wall_s"])


def marginal_cpu(rep: dict) -> float:
    """CPU seconds of one more view: the slope between the 3-view run and the full run of a repeat."""
    big, small = rep["generate"], rep["startup"]
    return (big["cpu_s"] - small["cpu_s"]) / max(1, big["views"] - small["views"])


def add_room_job_arguments(ap: argparse.ArgumentParser) -> None:
    """The job every `generate` benchmark of real rooms runs: --rooms, --points x --max-views views, at
    --resolution."""
    ap.add_argument("--rooms", default=",".join(ROOMS), help="comma-separated: " + ",".join(ROOMS))
    ap.add_argument("--points", type=int, default=14, help="points per room (x max-views = views)")
    ap.add_argument("--max-views", type=int, default=3)
    ap.add_argument("--resolution", type=int, default=512)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_room_job_arguments(ap)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--core", default=str(sorted(os.sched_getaffinity(0))[-1]), help="the one core")
    ap.add_argument("--cores", default="", help="also run generate's defaults on these cores, e.g. 0,1")
    ap.add_argument("--no-startup", dest="startup", action="store_false",
                    help="skip the 3-view run that splits the CPU into start-up and per-view cost")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--key", default="room_cost",
                    help='the entry of --out to write (e.g. room_cost_long for a run of thousands of views)')
    ap.add_argument("--phases", type=int, default=0,
                    help="instead: N repeats of where the worker's CPU goes per view (key worker_overhead)")
    ap.add_argument("--against", default="", help="with --phases: also this git revision, interleaved")
    args = ap.parse_args()
    if args.phases:
        return phases(args)
    # The project's bytecode, written now: with PYTHONDONTWRITEBYTECODE set (as on CI machines) every generate
    # would otherwise compile its modules again (~0.3 CPU-s of start-up) where an installed package has them
    # compiled.
    compileall.compile_dir(ROOT / "services", quiet=1)
    t0 = time.perf_counter()
    result: dict = {
        "resolution": args.resolution, "core": args.core, "clock": "wall seconds",
        "machine": f"{os.cpu_count()} cores ({cpu_model()}, Linux {platform.release()}), shared "
        "with other developers' work (load averages beside each figure)", "rooms": {},
    }
    with tempfile.TemporaryDirectory(prefix="omnidata-roomcost-") as tmp:
        spec = Path(tmp) / "spec.json"
        spec.write_text(json.dumps({"points": {"count": args.points, "max_views": args.max_views},
                                    "views": {"resolution": args.resolution}}))
        for room in args.rooms.split(","):
            repeats = []
            for i in range(args.repeats):
                out = Path(tmp) / f"{room}-{i}"
                rep: dict = {"generate": generate(*ROOMS[room], args.core, out, spec, 1)}
                rep["floor"] = floor(ROOMS[room][0], args.core, out)
                if args.startup:
                    small = Path(tmp) / "spec-small.json"
                    small.write_text(json.dumps({"points": {"count": 1, "max_views": 3},
                                                 "views": {"resolution": args.resolution}}))
                    rep["startup"] = generate(
                        *ROOMS[room], args.core, Path(tmp) / f"{room}-{i}-small", small, 1
                    )
                if args.cores:
                    rep["floor_all_cores"] = floor_all_cores(ROOMS[room][0], args.cores, out)
                    rep["all_cores"] = generate(
                        *ROOMS[room], args.cores, Path(tmp) / f"{room}-{i}-all", spec, None
                    )
                    if args.startup:
                        rep["all_cores_startup"] = generate(*ROOMS[room], args.cores,
                                                            Path(tmp) / f"{room}-{i}-all-small", small, None)
                repeats.append(rep)
                print(room, i, json.dumps({k: {kk: v for kk, v in r.items() if kk != "task_s_per_view"}
                                           for k, r in rep.items()}), flush=True)
            result["rooms"][room] = {"summary": summarise(repeats), "repeats": repeats}
            print(room, json.dumps(result["rooms"][room]["summary"]), flush=True)
            result["wall_s"] = round(time.perf_counter() - t0, 1)
            # a later failure keeps it
            write_result(args.out, args.key, result, first=len(result["rooms"]) == 1)
    result["segment_stability"] = segment_stability()
    write_result(args.out, args.key, result, first=False)
    print("\n".join(figures_table(result)), flush=True)
    return 0


def phases(args: argparse.Namespace) -> int:
    """--phases: per room, N runs of generate (one worker, one core) timed inside the worker
    (bench/lib/worker_phases.py), this checkout's and --against's alternately; per view after the first, each
    cue's task seconds as recorded in its row (its make's and a share of the view's store write, by bytes)
    beside its make's CPU, and the worker's phases. Medians over repeats, under "worker_overhead"."""
    from bench.lib import worker_phases
    from bench.lib.worker_phases import ENV, summary

    entry = ("-c", worker_phases.ENTRY, str(Path(worker_phases.__file__).resolve()))
    result: dict = {"core": args.core, "clock": "ms per view, worker process CPU (wall beside it)",
                    "points": args.points, "max_views": args.max_views, "rooms": {}}
    with tempfile.TemporaryDirectory(prefix="omnidata-phases-") as tmp:
        sides = {"this": ROOT}
        if args.against:
            archive = subprocess.run(["git", "archive", args.against], cwd=ROOT, capture_output=True,
                                     check=True).stdout
            (Path(tmp) / "against").mkdir()
            subprocess.run(["tar", "-x", "-C", str(Path(tmp) / "against")], input=archive, check=True)
            sides = {"against": Path(tmp) / "against", **sides}
        spec = Path(tmp) / "spec.json"
        spec.write_text(json.dumps({"points": {"count": args.points, "max_views": args.max_views},
                                    "views": {"resolution": args.resolution}}))
        for room in args.rooms.split(","):
            runs: dict[str, list[dict]] = {side: [] for side in sides}
            for i in range(-1, args.phases):  # run -1 fills each checkout's kernel cache: not kept
                for side in sides if i % 2 == 0 else list(sides)[::-1]:
                    out, rec = Path(tmp) / f"{room}-{side}-{i}", Path(tmp) / f"rec-{room}-{side}-{i}"
                    gen = generate(*ROOMS[room], args.core, out, spec, 1, root=sides[side], entry=entry,
                                   env={ENV: str(rec)})
                    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
                        rows = view_durations(db).per_view[1:]
                    recorded = {c: round(1000 * sum(v.get(c, 0.0) for v in rows) / len(rows), 2)
                                for c in rows[0]}
                    if i < 0:
                        continue
                    runs[side].append({**summary(rec), "recorded_task_ms": recorded,
                                       "load": [gen["load_before"], gen["load_after"]]})
                    print(room, side, i, json.dumps(runs[side][-1]), flush=True)
            result["rooms"][room] = {side: phase_medians(r) for side, r in runs.items()}
    result["against_rev"] = args.against or None
    write_result(args.out, "worker_overhead", result, first=True)
    print(json.dumps(result["rooms"], indent=1))
    return 0


def phase_medians(runs: list[dict]) -> dict:
    """Medians over repeats of phases()'s figures, the loads kept."""
    def med(values: list[float]) -> float:
        return round(median(values), 2)

    makes = {c: med([r["make"][c]["cpu_ms"] for r in runs]) for c in runs[0]["make"]}
    return {
        "repeats": len(runs), "views": runs[0]["views"],
        "per_cue_ms": {c: {"recorded_task": med([r["recorded_task_ms"].get(c, 0.0) for r in runs]),
                           "make_cpu": makes[c]} for c in makes},
        "phases_cpu_ms": {p: med([r["phases"][p]["cpu_ms"] for r in runs]) for p in runs[0]["phases"]},
        "phases_wall_ms": {p: med([r["phases"][p]["wall_ms"] for r in runs]) for p in runs[0]["phases"]},
        "run_cpu_ms": med([r["run_cpu_ms"] for r in runs]),
        "between_views_cpu_ms": med([r["between_views_cpu_ms"] for r in runs]),
        "makes_cpu_ms": round(sum(makes.values()), 2), "loads": [r["load"] for r in runs],
    }


STABILITY = results_dir() / "segment_stability.json"


def segment_stability(path: Path = STABILITY) -> list[dict]:
    """The segment cues' equivalence decisions (bench/cues/segment_stability.py's latest run): per room, cue
    and cheaper definition, the noise floor's ARI median/p10 (the current definition against its perturbed
    self), the candidate's against the current one, PASS/FAIL and the ms a view it saves. Empty when the file
    is absent or of another form."""
    try:
        return _stability_rows(json.loads(path.read_text())["after"]["rooms"])
    except (OSError, ValueError, AttributeError, KeyError, TypeError):
        return []


def _stability_rows(rooms: dict) -> list[dict]:
    rows: list[dict] = []
    for room, r in rooms.items():
        floor = r.get("noise_floor") or {}
        for name, c in (r.get("candidates") or {}).items():
            for cue, got in c.items():
                noise = floor.get(cue) or {}
                if "decision" not in got or not noise.get("views"):
                    continue
                rows.append({"room": room, "cue": cue, "candidate": name,
                             "noise_ari": (noise.get("ari_median"), noise.get("ari_p10")),
                             "candidate_ari": (got.get("ari_median"), got.get("ari_p10")),
                             "decision": got["decision"], "ms_saved": got.get("ms_saved_per_view_median")})
    return rows


def figures_table(result: dict) -> list[str]:
    """One line a room: one core and all cores x floor, all cores against one in views/s, and the render
    process's busy fraction (of the wall, of the task window), then the segment-stability table."""
    lines = ["room | 1 core x floor | all cores x floor | all/1 views/s | bare render all/1 views/s | "
             "render busy 1 core | render busy all cores (wall, task window)"]
    for room, r in result["rooms"].items():
        s = r["summary"]
        one, multi = s.get("render_busy_one_core", {}), s.get("render_busy_all_cores", {})
        lines.append(" | ".join(str(x) for x in (
            room, s["end_to_end_to_floor"]["median"],
            s.get("all_cores_end_to_end_to_floor", {}).get("median"),
            s.get("all_cores_to_one_core_views_per_s", {}).get("median"),
            s.get("floor_all_cores_to_one_core_views_per_s", {}).get("median"),
            one.get("render_busy_of_wall"),
            (multi.get("render_busy_of_wall"), multi.get("render_busy_of_task_window")),
        )))
    rows = result.get("segment_stability") or []
    lines.append("segment cues' equivalence (bench/results/segment_stability.json): room | cue | "
                 "definition | noise floor ARI (median, p10) | against the current (median, p10) | "
                 "decision | "
                 "ms saved a view" if rows else "segment stability: no results")
    lines += [f"{x['room']} | {x['cue']} | {x['candidate']} | {x['noise_ari']} | {x['candidate_ari']} | "
              f"{x['decision']} | {x['ms_saved']}" for x in rows]
    return lines


def write_result(out: Path, key: str, result: dict, *, first: bool) -> None:
    """This run's figures as `key`; on its first write the previous run's move to "<key>_before"."""
    doc = json.loads(out.read_text()) if out.exists() else {}
    if first and key in doc:
        if f"{key}_before" in doc:  # earlier rounds' figures are kept, oldest first
            doc.setdefault(f"{key}_history", []).append(doc[f"{key}_before"])
        doc[f"{key}_before"] = doc[key]
    doc[key] = result
    out.write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
