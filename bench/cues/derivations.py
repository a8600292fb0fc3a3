"""Benchmark: CPU cost of a view's derivations (every default cue but the render, with its file encoding) on
real rooms at 512x512 on one core, against the bare 1-sample render of the same view (issue 20, target <= 1x).

For each room it loads the space, takes the real planner's views (a handful, spread over the room's points),
renders each view's full pass set once (cached under --cache as .npz, so reruns skip Blender), then for each
repeat and view builds a fresh ViewContext on the pass set and produces every default cue in catalog order in
that one context (what a worker batching a view's cues does: shared intermediates are paid by the first cue
that needs them). Per cue it records the CPU seconds (time.process_time) of its derivation (value, including
intermediates it is the first to need) and of its encoding, medians over views x repeats; the total per view
against the floor. The two segmentations, most of the total, are also timed step by step ("segment_steps_s":
features, background fill, Felzenszwalb's blur, edge sort, merge pass and min-size pass, the region graph,
normalized cuts' eigenvectors and the rest).

Floor: the bare render's CPU seconds per view measured by bench/render/room_cost.py on the same rooms (a
separate process per room, one core; bench/results/room_cost.json "room_cost"), or FLOOR_CPU_S when that file
has none. Writes bench/results/derivations.json ("before" kept from a run with --label before).

--against REV: an A/B on a loaded machine. The image cues of each view (not the plan cues) are made by two
processes on the same core, this checkout's and REV's (git archive), in lockstep, view by view in alternating
order, so both see the same load; REV's run is written as "before", this one's as "after" (no segment steps).
--key NAME: the run(s) go under that key of the results file, with --against also "per_cue_ms" ({room: {cue:
[before, after]}}, median CPU ms a view, derivation and encoding), which is printed too.
Run: .venv/bin/python bench/cues/derivations.py [--views 6] [--repeats 3] [--label after] [--against REV]
[--key NAME]
"""

from __future__ import annotations

import os
import sys

if hasattr(os, "sched_setaffinity"):  # one core, one thread, before numpy starts its pools
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.ab import lockstep_sides  # noqa: E402
from bench.lib.results import RECORDED, results_dir  # noqa: E402
from bench.lib.rooms import ROOMS  # noqa: E402
from services.core.domain.cues import default_cues  # noqa: E402
from services.core.domain.jobspec import CueParams, JobSpec  # noqa: E402
from services.core.domain.plan import SpacePlan  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402
from services.scheduler.planning import make_plan, space_rng  # noqa: E402
from services.worker.context import ViewContext  # noqa: E402
from services.worker.cues.registry import cue_value  # noqa: E402
from services.worker.executor import produce  # noqa: E402
from services.worker.passes import RENDER_PASSES, ViewPasses  # noqa: E402
from services.worker.process.heap import keep_freed_memory  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "derivations.json"
# Bare 1-sample render, CPU s per view, one core (bench/render/room_cost.py, issue 20's closing notes; the
# copy room: round 14).
FLOOR_CPU_S = {"icl_livingroom": 0.077, "7scenes_redkitchen": 0.086, "copyroom": 0.18}


def floor_cpu_s(room: str) -> tuple[float, str]:
    """The room's bare-render CPU seconds per view and where the figure comes from."""
    try:
        rooms = json.loads((RECORDED / "room_cost.json").read_text())["room_cost"]["rooms"]
        med = float(np.median([r["floor"]["cpu_s_per_view_median"] for r in rooms[room]["repeats"]]))
        return med, "bench/results/room_cost.json room_cost (bench/render/room_cost.py), median over repeats"
    except (KeyError, OSError, ValueError):
        return FLOOR_CPU_S[room], "issue 20 closing note"


def room_views(
    room: str, n_views: int, resolution: int, cache: Path
) -> tuple[list[ViewPasses], SpacePlan, list]:
    """Pass sets (every render pass) of n_views planner views of the room, rendered once and cached."""
    path, frame = ROOMS[room]
    loaded = load_space(path, **frame)
    spec = JobSpec.model_validate({"views": {"resolution": resolution}})
    plan = make_plan(loaded, spec, space_rng(0, room), room)  # type: ignore[arg-type]
    # Two consecutive views of points spread over the room, as a worker meets them (the per-point nonfixated
    # JSON is shared by a point's views and encoded once for them, as in a job).
    points = sorted({v.point_idx for v in plan.views})
    points = points[:: max(1, len(points) // max(1, n_views // 2))][: max(1, n_views // 2)]
    views = [v for p in points for v in plan.views_of(p)[:2]]
    cache.mkdir(parents=True, exist_ok=True)
    files = [cache / f"{room}-{resolution}-p{v.point_idx}v{v.v}.npz" for v in views]
    if not all(f.exists() for f in files):
        from services.worker.inputs.space_cache import SpaceContext

        space = SpaceContext.from_loaded(loaded, key=f"{room}-derivations")
        try:
            for v, f in zip(views, files, strict=True):
                ctx = ViewContext(v, CueParams(), space=space, plan=plan, render_passes=RENDER_PASSES)
                f.write_bytes(ctx.passes.to_bytes())
        finally:
            space.close()
    return [ViewPasses.from_bytes(f.read_bytes()) for f in files], plan, views


def time_view(
    passes: ViewPasses, view: object, plan: SpacePlan, cues: list[str]
) -> dict[str, tuple[float, float]]:
    """{cue: (derive CPU s, encode CPU s)} of every cue made in one fresh context, in order."""
    ctx = ViewContext(view, CueParams(), passes=passes, plan=plan)
    out = {}
    for c in cues:
        c0 = time.process_time()
        cue_value(ctx, c)
        c1 = time.process_time()
        # the value is memoised: this is the encoding (a JSON shared by views is encoded once)
        produce(c, ctx)
        out[c] = (c1 - c0, time.process_time() - c1)
    return out


def segment_input(ctx: ViewContext, kind: str) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None]:
    """What `segment` gets for the 2d or 2.5d segmentation: features, mask, blur sigma and occlusion
    boundary."""
    from services.worker.cues import segmentation as seg
    from services.worker.cues.common import hit, valid
    from services.worker.cues.edges import occlusion_response

    p = ctx.params
    if kind == "2d":
        return ctx.passes.rgb.astype(np.float32) / 255.0, hit(ctx), p.segment2d_sigma, None
    occ = occlusion_response(ctx)
    boundary = seg._boundary(
        occ, np.float32(p.segment25d_weights[2]), np.float32(max(float(occ.max()), 1e-6))
    )
    return seg.features25d(ctx), valid(ctx), 0.0, boundary


def segment_stages(passes: list[ViewPasses], repeats: int) -> dict[str, dict[str, float]]:
    """Per segmentation (2d, 2.5d), the median CPU seconds of each step of `segment` on these views: the
    feature image (2.5d: log-depth, normals and occlusion boundary; the occlusion response counted as
    edge_occlusion's), the background fill, Felzenszwalb's blur, edge sort, merge pass and min-size pass with
    labels, the region graph, and the normalized cuts split into LAPACK's eigenvectors and the rest."""
    from services.worker.cues import felzenszwalb as fz
    from services.worker.cues import ncuts
    from services.worker.cues import segmentation as seg
    from services.worker.cues.common import gaussian_blur
    from services.worker.cues.edges import occlusion_response

    params = CueParams()
    eig_s = [0.0]
    solve = ncuts.second_eigenvector

    def timed_solve(a: np.ndarray, precision: str = "float64") -> np.ndarray:
        c0 = time.process_time()
        try:
            return solve(a, precision)
        finally:
            eig_s[0] += time.process_time() - c0

    steps: dict[str, defaultdict[str, list[float]]] = {"2d": defaultdict(list), "25d": defaultdict(list)}
    ncuts.second_eigenvector = timed_solve
    try:
        for _ in range(repeats):
            for p in passes:
                ctx = ViewContext(None, params, passes=p)
                occlusion_response(ctx)
                for kind in ("2d", "25d"):
                    t, definition = steps[kind], seg.DEFINITIONS["segment_unsup2d" if kind == "2d" else
                                                                  "segment_unsup25d"]
                    c0 = time.process_time()
                    features, mask, sigma, boundary = segment_input(ctx, kind)
                    # one colour (an untextured room's rgb): no graph
                    if seg._uniform_in_mask(features, mask):
                        continue
                    c1 = time.process_time()
                    if not mask.all():
                        iy, ix = seg.nearest_in_mask(ctx, mask)
                        features = seg._gather(features, mask, iy, ix)
                    c2 = time.process_time()
                    img = np.ascontiguousarray(features, dtype=np.float32)
                    h, w = img.shape[:2]
                    planes = np.zeros((fz.CHANNELS, h, w), np.float32)  # as felzenszwalb's superpixels
                    for c in range(img.shape[-1]):
                        plane = img[..., c]
                        planes[c] = gaussian_blur(plane, sigma, mode="reflect") if sigma > 0 else plane
                    c3 = time.process_time()
                    edges = fz._sorted_edges(planes, definition.sort_levels,
                                             fz.DIRECTIONS[definition.connectivity])
                    c4 = time.process_time()
                    fz._merge(edges, w, h * w, float(params.segment2d_scale) / 255.0)
                    c5 = time.process_time()
                    labels = seg.superpixels(
                        features, params.segment2d_scale, sigma, params.segment2d_min_size,
                        params.segment_max_superpixels, definition,
                    )
                    c6 = time.process_time()
                    graph = seg.region_graph(labels, features * 255.0, params.segment_ncut_sigma, boundary)
                    c7 = time.process_time()
                    eig_s[0] = 0.0
                    ncuts.normalized_cuts(graph, params.segment_ncut_thresh, params.segment_num_cuts,
                                          definition.eigenvectors, definition.link_eps)
                    c8 = time.process_time()
                    # the superpixel step run again: the rest of it once its blur, sort and merge
                    whole = c6 - c5
                    for name, v in (
                        ("features", c1 - c0), ("background_fill", c2 - c1), ("blur", c3 - c2),
                        ("edge_sort", c4 - c3), ("merge_pass", c5 - c4),
                        ("min_size_and_labels", whole - (c5 - c2)), ("superpixels_total", whole),
                        ("region_graph", c7 - c6), ("ncuts_eigenvectors", eig_s[0]),
                        ("ncuts_rest", c8 - c7 - eig_s[0]), ("superpixels", float(labels.max() + 1)),
                    ):
                        t[name].append(v)
    finally:
        ncuts.second_eigenvector = solve
    # a segmentation every view short-cut (uniform features) has no steps
    return {
        kind: {name: round(float(np.median(v)), 4) for name, v in t.items()} for kind, t in steps.items() if t
    }


def run_room(room: str, n_views: int, repeats: int, resolution: int, cache: Path) -> dict:
    passes, plan, views = room_views(room, n_views, resolution, cache)
    cues = default_cues(has_semantics=False)
    time_view(passes[0], views[0], plan, cues)  # numba compile / caches
    derive: defaultdict[str, list[float]] = defaultdict(list)
    enc: defaultdict[str, list[float]] = defaultdict(list)
    totals = []
    for _ in range(repeats):
        for p, v in zip(passes, views, strict=True):
            t = time_view(p, v, plan, cues)
            for c, (d, e) in t.items():
                derive[c].append(d)
                enc[c].append(e)
            totals.append(sum(d + e for d, e in t.values()))
    floor, floor_src = floor_cpu_s(room)
    per_cue = {
        c: {"derive_s": round(float(np.median(derive[c])), 4), "encode_s": round(float(np.median(enc[c])), 4)}
        for c in cues
    }
    total = float(np.median(totals))
    return {
        "views": len(views), "repeats": repeats, "floor_cpu_s": floor, "floor_source": floor_src,
        "total_s_median": round(total, 4), "total_s_worst": round(float(max(totals)), 4),
        "ratio_to_floor": round(total / floor, 2),
        "encode_s_total": round(sum(v["encode_s"] for v in per_cue.values()), 4),
        "per_cue": dict(sorted(per_cue.items(), key=lambda kv: -(kv[1]["derive_s"] + kv[1]["encode_s"]))),
        "segment_steps_s": segment_stages(passes, repeats),
    }


# One side of --against: the image cues of the views it is sent ("room index"), one JSON line each: {cue:
# [derive CPU s, encode CPU s]}. argv: the checkout, then the pass-set files of each room ("room=f1,f2,...").
SERVE = r"""
import json, sys, time
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from services.core.domain.cues import default_cues
from services.core.domain.jobspec import CueParams
from services.core.domain.cues import CATALOG
from services.worker.context import ViewContext
from services.worker.cues.registry import cue_value
from services.worker.executor import produce
from services.worker.passes import ViewPasses
from services.worker.process.heap import keep_freed_memory
keep_freed_memory()
cues = [c for c in default_cues(has_semantics=False) if CATALOG[c].ext != "json"]  # plan cues need the plan
rooms = {a.split("=")[0]: [ViewPasses.from_bytes(Path(f).read_bytes()) for f in a.split("=")[1].split(",")]
         for a in sys.argv[2:]}
def view(passes):
    ctx, out = ViewContext(None, CueParams(), passes=passes), {}
    for c in cues:
        c0 = time.process_time()
        cue_value(ctx, c)
        c1 = time.process_time()
        produce(c, ctx)
        out[c] = [c1 - c0, time.process_time() - c1]
    return out
for views in rooms.values():
    view(views[0])  # kernels loaded, caches warm
print("ready", flush=True)
for line in sys.stdin:
    room, i = line.split()
    print(json.dumps(view(rooms[room][int(i)])), flush=True)
"""


def lockstep(rev: str, rooms: list[str], n_views: int, repeats: int, resolution: int,
             cache: Path) -> dict[str, dict]:
    """{"before": REV's rooms, "after": this checkout's}: each view's image cues made by both sides in
    turn."""

    files = {}
    for room in rooms:
        views = room_views(room, n_views, resolution, cache)[2]
        files[room] = [cache / f"{room}-{resolution}-p{v.point_idx}v{v.v}.npz" for v in views]
    args = [f"{room}={','.join(map(str, fs))}" for room, fs in files.items()]
    times: dict[str, dict[str, list[dict]]] = {"before": defaultdict(list), "after": defaultdict(list)}
    with lockstep_sides(rev, SERVE, args) as sides:
        for rep in range(repeats):
            for room, fs in files.items():
                for i in range(len(fs)):
                    for side in ("before", "after") if (rep + i) % 2 == 0 else ("after", "before"):
                        proc = sides[side]
                        assert proc.stdin is not None and proc.stdout is not None
                        proc.stdin.write(f"{room} {i}\n")
                        proc.stdin.flush()
                        times[side][room].append(json.loads(proc.stdout.readline()))
    return {side: {room: ab_summary(room, views, repeats) for room, views in t.items()}
            for side, t in times.items()}


def ab_summary(room: str, views: list[dict], repeats: int) -> dict:
    """One side's figures of a room in run_room's form, from its views' {cue: [derive, encode]}."""
    floor, floor_src = floor_cpu_s(room)
    per_cue = {c: {"derive_s": round(float(np.median([v[c][0] for v in views])), 4),
                   "encode_s": round(float(np.median([v[c][1] for v in views])), 4)} for c in views[0]}
    totals = [sum(d + e for d, e in v.values()) for v in views]
    segments = ("segment_unsup2d", "segment_unsup25d")
    others = float(np.median([sum(d + e for c, (d, e) in v.items() if c not in segments) for v in views]))
    total = float(np.median(totals))
    return {
        "views": len(views) // repeats, "repeats": repeats, "floor_cpu_s": floor, "floor_source": floor_src,
        "total_s_median": round(total, 4), "total_s_worst": round(float(max(totals)), 4),
        "ratio_to_floor": round(total / floor, 2), "but_segments_s_median": round(others, 4),
        "but_segments_to_floor": round(others / floor, 3),
        "encode_s_total": round(sum(v["encode_s"] for v in per_cue.values()), 4),
        "per_cue": dict(sorted(per_cue.items(), key=lambda kv: -(kv[1]["derive_s"] + kv[1]["encode_s"]))),
    }


def main() -> int:
    keep_freed_memory()  # the worker's heap settings (services.worker.process.heap): timings as a worker's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--rooms", default=",".join(ROOMS))
    ap.add_argument("--label", default="after", help="key of this run in the results file (before / after)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    ap.add_argument("--against", default="", help="a git revision: lockstep A/B, written as before / after")
    ap.add_argument("--key", default="", help="write the run(s) under this key of the results file (its "
                    "before / after, and with --against the per-cue ms of both), not at its top level")
    args = ap.parse_args()
    t0, cpu0 = time.perf_counter(), time.process_time()
    load_before = os.getloadavg()
    names = args.rooms.split(",")
    if args.against:
        sides = lockstep(args.against, names, args.views, args.repeats, args.resolution, args.cache)
    else:
        sides = {args.label: {r: run_room(r, args.views, args.repeats, args.resolution, args.cache)
                              for r in names}}

    def rev(name: str) -> str:
        return subprocess.run(["git", "rev-parse", "--short", name], cwd=ROOT, capture_output=True,
                              text=True).stdout.strip()

    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {
        "benchmark": "bench/cues/derivations.py",
        "target": "derivations (all default cues but the render, encodings included) <= 1x the bare 1-sample "
                  "render per view, 512 px, one core"}
    block = data.setdefault(args.key, {}) if args.key else data
    for label, rooms in sides.items():
        block[label] = {
            "commit": rev(args.against) if args.against and label == "before" else rev("HEAD"),
            "resolution": args.resolution, "clock": "process CPU seconds (time.process_time), one core",
            **({"lockstep_against": args.against} if args.against else {}),
            "load_before": [round(x, 2) for x in load_before],
            "load_after": [round(x, 2) for x in os.getloadavg()],
            "wall_s": round(time.perf_counter() - t0, 1), "cpu_s": round(time.process_time() - cpu0, 1),
            "rooms": rooms,
        }
    if args.key and {"before", "after"} <= block.keys():
        block["per_cue_ms"] = per_cue_ms(block["before"]["rooms"], block["after"]["rooms"])
    RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    for label, rooms in sides.items():
        print(label, block[label]["commit"])
        report(rooms)
    if "per_cue_ms" in block:
        print_per_cue(block["per_cue_ms"])
    last = block[label]
    print("load", last["load_before"], "->", last["load_after"], "wall", last["wall_s"], "cpu", last["cpu_s"])
    return 0


def per_cue_ms(before: dict, after: dict) -> dict:
    """{room: {cue: [before, after]}}: each cue's median CPU ms a view (derivation and encoding), and the
    total, of the rooms both runs have."""
    def ms(cue: dict) -> float:
        return round(1e3 * (cue["derive_s"] + cue["encode_s"]), 2)

    out = {}
    for room in before.keys() & after.keys():
        b, a = before[room]["per_cue"], after[room]["per_cue"]
        out[room] = {c: [ms(b[c]), ms(a[c])] for c in b if c in a}
        out[room]["total"] = [round(1e3 * before[room]["total_s_median"], 2),
                              round(1e3 * after[room]["total_s_median"], 2)]
    return out


def print_per_cue(table: dict) -> None:
    for room, cues in table.items():
        print(f"{room}: CPU ms a view, before -> after")
        for c, (b, a) in cues.items():
            print(f"  {c:20s} {b:7.2f} -> {a:7.2f}  ({a - b:+.2f})")


def report(rooms: dict) -> None:
    for r, res in rooms.items():
        ratio = res.get("but_segments_to_floor")
        others = "" if ratio is None else f"; but the segments {ratio}x"
        print(f"{r}: {res['total_s_median']:.3f} CPU-s/view = {res['ratio_to_floor']}x floor "
              f"({res['floor_cpu_s']:.3f}); encode {res['encode_s_total']:.3f}{others}")
        for c, v in res["per_cue"].items():
            print(f"  {c:20s} derive {v['derive_s']:.4f}  encode {v['encode_s']:.4f}")
        for kind, steps in res.get("segment_steps_s", {}).items():
            print(f"  segment {kind}: " + ", ".join(f"{k} {v}" for k, v in steps.items()))


if __name__ == "__main__":
    sys.exit(main())
