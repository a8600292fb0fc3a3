"""Benchmark: the fixed start-up CPU of `omnidata generate` on the real rooms, part by part (issue 20).

Each part in a fresh process (so imports and caches start cold as in a run), process CPU seconds:
- parent: validate, register and plan one room as generate does, with the scheduler planning from the space
  the run validated (`loaded_spaces`, now) against loading the stored copy again (before);
- worker imports: `services.worker.run.runner` and the modules a worker process imports before its first task;
- curvature: the room's per-vertex curvature computed (the first worker of a machine) against read back from
  the shared file (every other worker process);
- parts: one process taking the steps of a run's start-up in order, each step's CPU: generate's imports
  (which a forked worker inherits), the run's database created, the worker's own modules, Blender's import
  and the kernels' target (a worker that renders), the space parsed, its Blender scene built, and the first
  bare render against the second (Cycles' kernels and BVH). A derive process pays none of the Blender steps.
  The numba kernels' loads show in bench/render/room_cost.py as the first view's derivations against the
  median view's.
Figures go to bench/results/startup_cpu.json with the load average.
With --user-caches instead: the user's caches that outlive a run (services.core.user_cache), each step in a
fresh process with its modules imported first (generate imports them before it loads), --repeats times: the
space parsed by load_space (no cache), by generate's load_space_kept with an empty cache (a miss: parsed, then
written) and with the entry a run before wrote (a hit); the curvature computed into an empty folder (a miss)
and read back (a hit). Medians and every repeat go to startup_cpu.json under "user_caches" (other keys kept).
Run: .venv/bin/python bench/render/startup_cpu.py [--rooms icl_livingroom,...] [--user-caches [--repeats 5]]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.rooms import ROOMS  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "startup_cpu.json"

PARENT = r"""
import json, sys, time
from pathlib import Path
from services.cli.generate import validate_sources
from services.cli.spec_args import check_sources
from services.core.db.engine import make_engine, make_sessionmaker, migrate
from services.core.domain.jobspec import JobSpec
from services.core.storage import LocalStore
from services.embedded.job import STATE_DIR, embedded_settings, prepare_job
from services.scheduler.loop import Scheduler
from services.scheduler.transport import NullTransport
space, frame, out, hand_over = sys.argv[1], json.loads(sys.argv[2]), Path(sys.argv[3]), sys.argv[4] == "1"
spec = JobSpec.model_validate({"points": {"count": 1, "max_views": 3}, "views": {"resolution": 512}, **frame})
settings = embedded_settings(out, 1)
migrate(settings.database_url)
sessions = make_sessionmaker(make_engine(settings.database_url))
store = LocalStore(out)
c0 = time.process_time()
sources = check_sources([space])
validate_sources(sources, spec)
prepared = prepare_job(sessions, store, spec, sources)
sched = Scheduler(sessions, store, NullTransport(), settings, cache_dir=out / STATE_DIR / "cache",
                  loaded_spaces=prepared.loaded if hand_over else None)
assert sched.plan_pending() == [prepared.job_id]
print(json.dumps({"cpu_s": time.process_time() - c0}))
"""

IMPORTS = r"""
import json, time
c0 = time.process_time()
from services.core.db.engine import make_engine, make_sessionmaker
from services.core.settings import get_settings
from services.core.storage import LocalStore
from services.worker.run.claim import TransientError
from services.worker.run.heartbeat import Heartbeat
from services.worker.run.runner import TaskRunner
import sys
print(json.dumps({"cpu_s": time.process_time() - c0, "scipy_stats": "scipy.stats" in sys.modules}))
"""

CURVATURE = r"""
import json, sys, time
from pathlib import Path
from services.core.domain.jobspec import CueParams
from services.core.ingest.loading import load_space
from services.worker.inputs.shared_curvature import shared_curvature
space, frame, folder = sys.argv[1], json.loads(sys.argv[2]), Path(sys.argv[3])
mesh = load_space(space, **frame).mesh
import trimesh
shared_curvature(trimesh.creation.icosphere(), 0.3, None)  # the estimator's compiled kernels loaded
c0 = time.process_time()
shared_curvature(mesh, CueParams().curvature_radius_m, folder)
print(json.dumps({"cpu_s": time.process_time() - c0, "vertices": len(mesh.vertices)}))
"""


PARTS = r"""
import json, sys, time
import numpy as np
parts = {}
clock = [time.process_time()]
def lap(name):
    now = time.process_time()
    parts[name] = round(now - clock[0], 3)
    clock[0] = now
from services.core.gc_pause import collections_paused  # as `omnidata` and a worker import
with collections_paused():
    import services.cli.generate
lap("generate_imports")
from services.core.db.engine import migrate
migrate(f"sqlite:///{sys.argv[3]}/state.db")
lap("database_created")
with collections_paused():
    import services.worker.run.runner, services.worker.run.heartbeat
lap("worker_modules")
import importlib
from services.worker.blender.threads import import_bpy
with collections_paused():
    import_bpy(1)
    importlib.import_module("services.worker.blender.scene")
lap("blender_import")
from services.worker.process import kernel_target
with collections_paused():
    kernel_target.load()
lap("kernel_target")
from services.core.ingest.loading import load_space
loaded = load_space(sys.argv[1], **json.loads(sys.argv[2]))
lap("space_parsed")
from services.worker.inputs.space_cache import SpaceContext
scene = SpaceContext.from_loaded(loaded, key="probe", device="cpu", threads=1).scene()
lap("scene_built")
from services.core.domain.camera import look_at
from services.worker.passes import ViewGeometry
lo, hi = loaded.mesh.bounds
centre = (lo + hi) / 2
pose = look_at(centre, centre + np.array([1.0, 0.3, 0.0]))
view = ViewGeometry(world_to_camera=pose, fov=1.0, resolution=512)
scene.render_floor(view)
lap("first_render")
scene.render_floor(view)
lap("second_render")
print(json.dumps(parts))
"""

PARSED = r"""
import json, sys, time
from pathlib import Path
from services.core.ingest.loading import load_space
from services.core.ingest.parsed_cache import load_space_kept
from services.core.ingest.registry import source_checksum
space, frame, folder = Path(sys.argv[1]), json.loads(sys.argv[2]), sys.argv[3]
checksum = source_checksum(space)  # generate's check_sources has it before loading
c0 = time.process_time()
if folder == "-":
    load_space(space, **frame)
else:
    load_space_kept(space, checksum, frame, Path(folder))
print(json.dumps({"cpu_s": time.process_time() - c0}))
"""


def user_caches(rooms: list[str], repeats: int) -> dict:
    """Cold (no entry) against warm (the entry a run before wrote) for the parsed space and the curvature."""
    out: dict = {}
    for room in rooms:
        space, frame = ROOMS[room]
        runs: dict[str, list[float]] = {k: [] for k in ("load_space", "parsed_miss", "parsed_hit",
                                                        "curvature_miss", "curvature_hit")}
        for _ in range(repeats):
            with tempfile.TemporaryDirectory(prefix="omnidata-user-cache-") as tmp:
                args = (str(space), json.dumps(frame))
                runs["load_space"].append(probe(PARSED, *args, "-")["cpu_s"])
                runs["parsed_miss"].append(probe(PARSED, *args, f"{tmp}/parsed")["cpu_s"])
                runs["parsed_hit"].append(probe(PARSED, *args, f"{tmp}/parsed")["cpu_s"])
                runs["curvature_miss"].append(probe(CURVATURE, *args, f"{tmp}/curvature")["cpu_s"])
                runs["curvature_hit"].append(probe(CURVATURE, *args, f"{tmp}/curvature")["cpu_s"])
        out[room] = {"median_s": {k: round(statistics.median(v), 4) for k, v in runs.items()},
                     "cpu_s": {k: [round(x, 4) for x in v] for k, v in runs.items()}}
        print(room, json.dumps(out[room]["median_s"]), flush=True)
    return out


def probe(code: str, *args: str) -> dict:
    run = subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False)
    if run.returncode != 0:
        raise RuntimeError(run.stderr[-2000:])
    return json.loads(run.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", default=",".join(ROOMS), help="comma-separated: " + ",".join(ROOMS))
    ap.add_argument("--user-caches", action="store_true", help="measure the caches kept across runs only")
    ap.add_argument("--repeats", type=int, default=5, help="--user-caches: fresh processes per figure")
    args = ap.parse_args()
    if args.user_caches:
        before = [round(x, 2) for x in os.getloadavg()]
        rooms = user_caches(args.rooms.split(","), args.repeats)
        data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
        data["user_caches"] = {"unit": "process CPU seconds", "repeats": args.repeats,
                               "machine": f"{os.cpu_count()} cores, shared", "load_before": before,
                               "load_after": [round(x, 2) for x in os.getloadavg()], "rooms": rooms}
        RESULTS.write_text(json.dumps(data, indent=2) + "\n")
        return
    report: dict = {"load_before": [round(x, 2) for x in os.getloadavg()], "unit": "process CPU seconds",
                    "rooms": {}}
    report["worker_imports"] = probe(IMPORTS)
    for room in args.rooms.split(","):
        space, frame = ROOMS[room]
        rec: dict = {}
        with tempfile.TemporaryDirectory(prefix="omnidata-startup-") as tmp:
            for label, hand_over in (("parent_before", "0"), ("parent_now", "1")):
                rec[label] = probe(PARENT, str(space), json.dumps(frame), f"{tmp}/{label}", hand_over)[
                    "cpu_s"
                ]
            for label in ("curvature_computed", "curvature_shared"):  # the second reads the first's file
                rec[label] = probe(CURVATURE, str(space), json.dumps(frame), f"{tmp}/curvature")["cpu_s"]
            rec["parts"] = probe(PARTS, str(space), json.dumps(frame), tmp)
        report["rooms"][room] = {k: v if isinstance(v, dict) else round(v, 3) for k, v in rec.items()}
        print(room, report["rooms"][room], flush=True)
    report["load_after"] = [round(x, 2) for x in os.getloadavg()]
    RESULTS.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
