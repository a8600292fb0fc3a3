"""Benchmark: what the `passes` task (one Cycles render per view with every pass, stored as .npz) costs on
real rooms, part by part, against the bare render of the same views (issue 20, part 3).

On one core (this process pins itself to --core before bpy starts), for each room: the real planner's views (a
few points, two views each), the space loaded once (load, curvature and the Blender scene are space set-up,
excluded). Per view, interleaved so that a neighbour's load moves every figure alike:
- bare: a 1-sample render with Image + Depth + Normal only (BlenderScene.render_floor), nothing written;
- aov:<set>: the same render with only these AOVs in the view layer (a scene of its own each), nothing
  written;
- <...>+exr_write: the pass scene's settings (Combined + Depth, no Normal pass: the normals come from the face
  index) with these AOVs, its EXR written; aov:old+exr_write is the render before issue 20 part 3 and
  aov:pass+normal+exr_write the one of rounds 9-12 (both with the Normal pass);
- the passes task as the worker runs it (ViewContext render of every pass, produce("passes"), put_bytes into a
  LocalStore): task_in_batch is what it costs when a worker's view batch takes the whole view
  (runner._run_view: render, EXR read, decode; the pass set is never stored), task_stored adds the npz encode
  and the store put (a view not batched whole); wall_render_call_s (Cycles + EXR write), wall_exr_read_s and
  wall_decode_s split it.
Figures are CPU seconds of this process (time.process_time; all its threads) per view, medians over views x
repeats, with wall medians and the load average beside them. Written to bench/results/passes_cost.json (the
previous run kept under "before").

--against REV: an A/B on a loaded machine instead. Two processes on --core, this checkout's and REV's (git
archive), each with the room loaded, render the same views in lockstep, view by view in alternating order: the
passes task (task_in_batch: ViewContext's render of every pass, read back and decoded) and the floor, in
blocks (each block's first render, a persistent-data re-sync, not counted). Written under "ab" (the previous
one kept as "ab_previous", other keys kept): per side and room, CPU and wall medians, the task as x floor, and
the paired differences (the robust figure: task and floor run in different blocks, so x floor moves with the
load between blocks).
Run: .venv/bin/python bench/render/passes_cost.py [--views 8] [--repeats 2] [--core 0] [--against REV]
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__" and hasattr(os, "sched_setaffinity"):  # one core before numpy/bpy size their pools
    _core = sys.argv[sys.argv.index("--core") + 1] if "--core" in sys.argv else "0"
    os.sched_setaffinity(0, {int(_core)})
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.ab import lockstep_sides  # noqa: E402
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.rooms import ROOMS  # noqa: E402
from services.core.domain.jobspec import CueParams, JobSpec  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402
from services.core.storage.local import LocalStore  # noqa: E402
from services.scheduler.planning import make_plan, space_rng  # noqa: E402
from services.worker.context import ViewContext  # noqa: E402
from services.worker.executor import produce  # noqa: E402
from services.worker.inputs.space_cache import SpaceContext  # noqa: E402
from services.worker.passes import RENDER_PASSES, ViewGeometry  # noqa: E402
from services.worker.process.heap import keep_freed_memory  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
OUT = results_dir() / "passes_cost.json"


def median(values: list[float]) -> float:
    s = sorted(values)
    n = len(s)
    return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


def aov_sets(faces: int) -> dict[str, tuple[str, ...]]:
    """The AOV subsets timed on their own (render only, nothing written); "old" is every AOV the pass render
    had before issue 20 part 3, "pass" the pass render's own (render.pass_aovs, absent before)."""
    from services.worker.blender import render as r

    face1 = getattr(r, "AOV_FACE", None)
    sets = {"face_hi_lo": (r.AOV_FACE_HI, r.AOV_FACE_LO), "face": (face1,), "class": (r.AOV_CLASS,),
            "instance": (r.AOV_INSTANCE,), "k1": (r.AOV_K1,), "k2": (r.AOV_K2,),
            "curvature": (r.AOV_K1, r.AOV_K2),
            "old": (r.AOV_FACE_HI, r.AOV_FACE_LO, r.AOV_CLASS, r.AOV_INSTANCE, r.AOV_K1, r.AOV_K2)}
    if hasattr(r, "pass_aovs"):
        sets["pass"] = r.pass_aovs(faces)
    return {k: v for k, v in sets.items() if all(a in r.AOVS for a in v)}


def variant_scene(space: SpaceContext, aovs: tuple[str, ...], write: bool = False,
                  normal: bool = False) -> Callable[[ViewGeometry], float]:
    """A scene of its own with the bare render's settings plus `aovs` (and, with `write`, the pass scene's EXR
    output written: no Normal pass, unless `normal`, as before round 13); returns a function rendering a view
    that gives its wall seconds."""
    import bpy

    from services.worker.blender import render as r

    bs = space.scene()
    sc = bpy.data.scenes.new("v_" + "_".join(aovs) + ("_w" if write else ""))
    sc.collection.objects.link(bs.object)
    sc.collection.objects.link(bs.camera)
    sc.camera = bs.camera
    if write:
        r.configure_scene(sc, r.RenderOptions(threads=1), os.path.join(bs._tmp, "variant.exr"))
        layer = sc.view_layers[0]
        for a in [a for a in layer.aovs if a.name not in aovs]:
            layer.aovs.remove(a)
        layer.use_pass_normal = normal
    else:
        r.configure_floor_scene(sc, r.RenderOptions(threads=1))
        for name in aovs:
            aov = sc.view_layers[0].aovs.add()
            aov.name = name
            aov.type = "VALUE"

    def render(g: ViewGeometry) -> float:
        r.set_camera(sc, bs.camera, g)
        t0 = time.perf_counter()
        with r._quiet_stdout():
            bpy.ops.render.render(write_still=write, scene=sc.name)
        return time.perf_counter() - t0

    return render


def room_views(path: Path, frame: dict, resolution: int, n: int) -> tuple[SpaceContext, list[ViewGeometry]]:
    loaded = load_space(path, **frame)
    spec = JobSpec.model_validate({"views": {"resolution": resolution}})
    plan = make_plan(loaded, spec, space_rng(0, path.name), path.name)
    points = sorted({v.point_idx for v in plan.views})
    points = points[:: max(1, len(points) // max(1, n // 2))][: max(1, n // 2)]
    views = [ViewGeometry.of(v) for p in points for v in plan.views_of(p)[:2]]
    return SpaceContext.from_loaded(loaded, key=path.name, threads=1), views


def task(
    space: SpaceContext, g: ViewGeometry, params: CueParams, store: LocalStore, i: int
) -> dict[str, float]:
    """The passes task as runner.execute runs it; CPU seconds of its parts."""
    c0 = time.process_time()
    ctx = ViewContext(g, params, space=space, render_passes=RENDER_PASSES)
    p = ctx.passes
    c1 = time.process_time()
    data = produce("passes", ctx)
    c2 = time.process_time()
    store.put_bytes(f"passes/{i}.npz", data)
    c3 = time.process_time()
    parts = {k: p.meta.get(k, 0.0) for k in ("render_call_s", "exr_read_s", "decode_s")}  # wall, one thread
    return {"task_stored": c3 - c0, "task_in_batch": c1 - c0, "npz_encode": c2 - c1, "store_put": c3 - c2,
            "npz_mb": len(data) / 1e6, **{"wall_" + k: v for k, v in parts.items()}}


def run_room(name: str, n_views: int, repeats: int, resolution: int) -> dict:
    path, frame = ROOMS[name]
    space, views = room_views(path, frame, resolution, n_views)
    params = CueParams()
    scene = space.scene()
    space.curvature(params.curvature_radius_m)
    variants: dict[str, Callable[[ViewGeometry], float]] = {"bare": scene.render_floor}
    sets = aov_sets(len(space.mesh.faces))
    variants.update({f"aov:{k}": variant_scene(space, v) for k, v in sets.items()})
    variants["bare+exr_write"] = variant_scene(space, (), write=True)
    for k in ("old", "pass"):
        if k in sets:
            variants[f"aov:{k}+exr_write"] = variant_scene(space, sets[k], write=True, normal=k == "old")
    if "pass" in sets:  # the pass render of rounds 9-12: the same AOVs and the Normal pass
        variants["aov:pass+normal+exr_write"] = variant_scene(space, sets["pass"], write=True, normal=True)
    cpu: defaultdict[str, list[float]] = defaultdict(list)
    wall: defaultdict[str, list[float]] = defaultdict(list)
    with tempfile.TemporaryDirectory(prefix="omnidata-passes-cost-") as tmp:
        store = LocalStore(tmp)
        for rep in range(repeats):
            # Blocks of views per variant: rendering another scene re-syncs Cycles' persistent data (a BVH
            # rebuild, 0.2 s on ICL), so each block starts with a render that is not counted.
            keys = list(variants) + ["task_stored"]
            for key in keys[rep % len(keys):] + keys[:rep % len(keys)]:
                for i, g in enumerate([views[-1], *views]):
                    if key == "task_stored":
                        t0 = time.perf_counter()
                        parts = task(space, g, params, store, rep * len(views) + i)
                        if i:
                            wall[key].append(time.perf_counter() - t0)
                            for k, v in parts.items():
                                cpu[k].append(v)
                        continue
                    c0 = time.process_time()
                    w = variants[key](g)
                    if i:
                        wall[key].append(w)
                        cpu[key].append(time.process_time() - c0)
    bare = median(cpu["bare"])
    out = {
        "views": len(views), "faces": len(space.mesh.faces),
        "load_avg": [round(x, 2) for x in os.getloadavg()],
        "cpu_s_per_view_median": {k: round(median(v), 4) for k, v in cpu.items()},
        "wall_s_per_view_median": {k: round(median(v), 4) for k, v in wall.items()},
        "to_bare_cpu": {
            k: round(median(v) / bare, 2) for k, v in cpu.items() if not k.startswith(("npz_mb", "wall_"))
        },
    }
    space.close()
    return out


# One side of --against: commands on stdin ("room [path, frame]", then "task i" or "floor i"), one JSON line
# each: the room's view count, or [CPU s, wall s] of the render. argv: checkout, resolution, views, core.
SERVE = r"""
import json, os, sys, time
os.sched_setaffinity(0, {int(sys.argv[4])})
sys.path.insert(0, sys.argv[1])
from pathlib import Path
from bench.render.passes_cost import room_views
from services.core.domain.jobspec import CueParams
from services.worker.context import ViewContext
from services.worker.passes import RENDER_PASSES
from services.worker.process.heap import keep_freed_memory
keep_freed_memory()
params, space = CueParams(), None
def render(kind, g):
    if kind == "task":
        ViewContext(g, params, space=space, render_passes=RENDER_PASSES).passes
    else:
        space.scene().render_floor(g)
print("ready", flush=True)
for line in sys.stdin:
    kind, arg = line.split(" ", 1)
    if kind == "room":
        if space is not None:
            space.close()
        path, frame = json.loads(arg)
        space, views = room_views(Path(path), frame, int(sys.argv[2]), int(sys.argv[3]))
        space.curvature(params.curvature_radius_m)
        render("task", views[0]), render("floor", views[0])  # kernels, curvature, both scenes built
        print(json.dumps(len(views)), flush=True)
        continue
    c0, w0 = time.process_time(), time.perf_counter()
    render(kind, views[int(arg)])
    print(json.dumps([time.process_time() - c0, time.perf_counter() - w0]), flush=True)
"""


def ask(proc: subprocess.Popen, line: str) -> object:
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdin.write(line + "\n")
    proc.stdin.flush()
    return json.loads(proc.stdout.readline())


def lockstep(rev: str, rooms: list[str], n_views: int, repeats: int, resolution: int, core: str) -> dict:
    """{room: {side: {"task": [[cpu, wall], ...], "floor": [...]}}} of REV ("before") and this checkout
    ("after")."""
    out: dict = {}
    with lockstep_sides(rev, SERVE, [str(resolution), str(n_views), core]) as sides:
        for room in rooms:
            path, frame = ROOMS[room]
            n = [ask(p, "room " + json.dumps([str(path), frame])) for p in sides.values()][0]
            times: dict = {side: {"task": [], "floor": []} for side in sides}
            for rep in range(repeats):
                for kind in ("task", "floor") if rep % 2 == 0 else ("floor", "task"):
                    for p in sides.values():
                        ask(p, f"{kind} {n - 1}")  # the block's re-sync, not counted
                    for i in range(int(n)):  # type: ignore[call-overload]
                        order = ("before", "after") if (rep + i) % 2 == 0 else ("after", "before")
                        for side in order:
                            times[side][kind].append(ask(sides[side], f"{kind} {i}"))
            out[room] = times
            print(room, json.dumps(ab_summary(times)), flush=True)
    return out


def ab_summary(times: dict) -> dict:
    """Per side: CPU and wall medians (ms) of the task and the floor, the task as x floor; the paired
    differences (after - before) of the task's CPU, median."""
    out: dict = {}
    for side, t in times.items():
        cpu = {k: median([c for c, _ in v]) for k, v in t.items()}
        wall = {k: median([w for _, w in v]) for k, v in t.items()}
        out[side] = {"task_cpu_ms": round(1e3 * cpu["task"], 2), "floor_cpu_ms": round(1e3 * cpu["floor"], 2),
                     "task_wall_ms": round(1e3 * wall["task"], 2),
                     "floor_wall_ms": round(1e3 * wall["floor"], 2),
                     "task_to_floor_cpu": round(cpu["task"] / cpu["floor"], 3),
                     "task_to_floor_wall": round(wall["task"] / wall["floor"], 3)}
    pairs = zip(times["before"]["task"], times["after"]["task"], strict=True)
    out["task_cpu_ms_after_minus_before"] = round(1e3 * median([a[0] - b[0] for b, a in pairs]), 2)
    return out


def main() -> int:
    keep_freed_memory()  # the worker's heap settings (services.worker.process.heap): timings as a worker's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", default=",".join(ROOMS), help="comma-separated: " + ",".join(ROOMS))
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--core", default="0", help="the one core this process runs on")
    ap.add_argument("--label", default="", help="a note stored with the figures (e.g. the commit measured)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--against", default="", help="a git revision: lockstep A/B, written under \"ab\"")
    args = ap.parse_args()
    if args.against:
        rooms = args.rooms.split(",")
        times = lockstep(args.against, rooms, args.views, args.repeats, args.resolution, args.core)
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True).stdout.strip()
        doc = json.loads(args.out.read_text()) if args.out.exists() else {}
        if "ab" in doc:
            doc["ab_previous"] = doc["ab"]
        doc["ab"] = {"before": args.against, "after": f"{head} (working tree)", "label": args.label,
                     "resolution": args.resolution, "core": args.core, "repeats": args.repeats,
                     "load_avg": [round(x, 2) for x in os.getloadavg()],
                     "rooms": {room: {"views": len(t["after"]["task"]) // args.repeats, **ab_summary(t),
                                      "raw": t} for room, t in times.items()}}
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
        return 0
    result: dict = {"resolution": args.resolution, "core": args.core, "label": args.label,
                    "clock": "CPU seconds of this process per view (medians); wall beside", "rooms": {}}
    for room in args.rooms.split(","):
        result["rooms"][room] = run_room(room, args.views, args.repeats, args.resolution)
        print(room, json.dumps(result["rooms"][room], indent=1), flush=True)
    doc = json.loads(args.out.read_text()) if args.out.exists() else {}
    if "after" in doc:
        doc["before"] = doc["after"]
    doc["after"] = result
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
