"""Benchmark: cost per view on a GPU machine, and the CPU path on 1, 8 and all cores of the same machine
(issue 20).

For each real room, on the machine it runs on:
1. `omnidata generate ROOM` with its default worker settings (a worker per core, one in 8 of them rendering on
   the GPU: OMNIDATA_RENDER_DEVICE, default auto = OptiX, else CUDA), its views/s and wall per view end to
   end, the job's own task rows, and the GPU's busy fraction: nvidia-smi's utilization.gpu (the share of each
   sample period in which a kernel ran) sampled every 100 ms, over the whole run and over the job's task
   window;
2. the bare 1-sample render (Image + Depth + Normal) of the same views on the GPU, and on one CPU core;
3. the same `generate` on the CPU (OMNIDATA_RENDER_DEVICE=cpu) pinned to 1 core, 8 cores and every core:
   views/s against one core's;
4. every cue file of the GPU run against the CPU run of the same plan (same seed and spec) on the most cores:
   the share of pixels equal, within one code value, and the adjusted Rand index of the segmentations.
Each setting runs a 3-view job and its main job (--points on one core, --points-many on the GPU and on many
cores); the views/s of the views the main job adds (the slope, start-ups left out) is what a long job
approaches, and so is each run's rate over its task window (first task start to last task finish: its workers'
first renders in). A 1-point run first (one worker) fills the caches a first run on a new machine pays once
(numba's compiled kernels, the driver's OptiX module cache), so the figures are those of a machine in use.
With --render-workers R,..., also the GPU main job with every worker of which only R render (`generate
--render-workers`: R device contexts, the other workers derive from the pass sets the renderers store); R =
the core count is every worker rendering (the default before one in 8).
It ends with the busy fractions: the GPU's (nvidia-smi) beside the render process's (its time in render
tasks, from the task rows), for the GPU runs and the CPU runs; `--busy FILE` prints them from a results file.
Run: python bench/render/gpu_cost.py [--rooms icl_livingroom] [--points 22] [--cores 1,8,16]
     [--gpu-workers 2,4,8] [--render-workers 1,2] [--out FILE] [--busy FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import room_cost  # noqa: E402  (bench/ is no package)
from room_cost import ROOMS, SCENES, floor, packed_views, unix  # noqa: E402

from bench.lib.results import results_dir  # noqa: E402
from tests.fixtures.segment_agreement import adjusted_rand_index  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "gpu.json"


def room_space(room: str, scenes: Path) -> tuple[Path, list[str]]:
    """bench/render/room_cost.py's room (SPACE argument, generate flags), with its scenes folder at `scenes`
    (a room kept in the repository, bench/scans/, stays where it is: it travels with the tree)."""
    space, extra = ROOMS[room]
    return (scenes / space.relative_to(SCENES) if space.is_relative_to(SCENES) else space), extra


class GpuSampler:
    """nvidia-smi's utilization.gpu (%) and memory used (MiB) every 100 ms, each with the wall clock it was
    read at, and the most processes seen holding a context on the GPU at once (polled twice a second)."""

    def __init__(self) -> None:
        self.samples: list[tuple[float, float, float]] = []
        self.processes = 0
        self.done = threading.Event()
        smi = shutil.which("nvidia-smi") or "true"  # no GPU: no samples
        threading.Thread(target=self._count_processes, args=(smi,), daemon=True).start()
        self.proc = subprocess.Popen(
            [smi, "--query-gpu=utilization.gpu,memory.used", "--format=csv,noheader,nounits", "-lms", "100"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                util, mem = (float(x) for x in line.split(","))
            except ValueError:
                continue
            self.samples.append((time.time(), util, mem))

    def _count_processes(self, smi: str) -> None:
        while not self.done.wait(0.5):
            apps = subprocess.run([smi, "--query-compute-apps=pid", "--format=csv,noheader"],
                                  capture_output=True, text=True).stdout.split()
            self.processes = max(self.processes, len(apps))

    def stop(self) -> list[tuple[float, float, float]]:
        self.done.set()
        self.proc.terminate()
        self.proc.wait()
        self.thread.join(timeout=2)
        return self.samples


def busy(samples: list[tuple[float, float, float]], start: float, end: float) -> dict:
    """Mean utilization (as a fraction) and peak memory of the samples read between `start` and `end`."""
    inside = [(u, m) for t, u, m in samples if start <= t <= end]
    if not inside:
        return {"samples": 0}
    return {"samples": len(inside), "busy_fraction": round(sum(u for u, _ in inside) / len(inside) / 100, 3),
            "peak_memory_mib": max(m for _, m in inside)}


def task_window(out: Path) -> tuple[float, float]:
    """Unix times of the job's first task start and last task finish: its task rows (UTC), and the views a
    long run compacted (services.scheduler.compaction drops their start times: a packed task started its
    duration before it finished). Without the packed views, a long run's window would start late and its
    views/s read
    high."""
    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
        first, last = db.execute(
            "SELECT MIN(started_at), MAX(finished_at) FROM task WHERE state = 'done'"
        ).fetchone()
        packed = [t for tasks in packed_views(db) for t in tasks if t.finished_at is not None]
    starts = [unix(first)] if first else []
    ends = [unix(last)] if last else []
    starts += [t.finished_at.timestamp() - (t.duration_s or 0.0) for t in packed]
    ends += [t.finished_at.timestamp() for t in packed]
    return min(starts), max(ends)


def generate(space: Path, extra: list[str], cores: str, out: Path, spec: Path, device: str,
             workers: int | None = None, gpu: bool = False) -> dict:
    """bench/render/room_cost.py's `generate` run, with the GPU sampled while it runs when `gpu`."""
    sampler, start = (GpuSampler() if gpu else None), time.time()
    try:
        result = room_cost.generate(space, extra, cores, out, spec, workers, device)
    finally:
        samples = sampler.stop() if sampler else []
    first, last = task_window(out)  # a long job's rate: its views over first task start to last task finish
    result["task_window_s"] = round(last - first, 2)
    result["task_window_views_per_s"] = round(result["views"] / (last - first), 3)
    if sampler:
        result["gpu_whole_run"] = busy(samples, start, time.time())
        result["gpu_task_window"] = {**busy(samples, first, last), "seconds": round(last - first, 2)}
        result["gpu_processes_peak"] = sampler.processes  # the workers that rendered on the GPU
    return result


def compare_outputs(gpu_out: Path, cpu_out: Path) -> dict:
    """Per cue over every view: pixels equal and within one code value (worst view, mean), ARI for
    segmentations."""
    from services.datasets.decode import read_raw

    per_cue: dict[str, dict[str, list[float]]] = {}
    for path in sorted(gpu_out.rglob("point_*_domain_*")):
        rel = path.relative_to(gpu_out)
        cue = rel.parts[0]
        other = cpu_out / rel
        stats = per_cue.setdefault(cue, {"equal": [], "within_1": [], "ari": [], "missing": []})
        if not other.exists():
            stats["missing"].append(1.0)
            continue
        a, b = read_raw(cue, path.read_bytes()), read_raw(cue, other.read_bytes())
        if not isinstance(a, np.ndarray) or not isinstance(b, np.ndarray):
            stats["equal"].append(float(a == b))
            continue
        if a.dtype.kind == "f":
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            # position in metres: within a millimetre
            near = same | (np.abs(a.astype(np.float64) - b) <= 1e-3)
        else:
            same = a == b
            near = np.abs(a.astype(np.int64) - b.astype(np.int64)) <= 1
        stats["equal"].append(float(same.mean()))
        stats["within_1"].append(float(near.mean()))
        if cue.startswith("segment_unsup"):
            stats["ari"].append(adjusted_rand_index(a, b))
    summary = {}
    for cue, stats in per_cue.items():
        summary[cue] = {name: {"worst": round(min(v), 4), "mean": round(sum(v) / len(v), 4)}
                        for name, v in stats.items() if v and name != "missing"}
        summary[cue]["files"] = len(stats["equal"]) + len(stats["missing"])
        if stats["missing"]:
            summary[cue]["missing_on_cpu"] = len(stats["missing"])
    return summary


def gpu_info() -> dict:
    """The GPU and driver nvidia-smi reports, and this machine's cores."""
    try:
        info = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError) as e:
        info = f"no nvidia-smi: {e}"
    return {"gpu": info, "cores": os.cpu_count(), "cpu": room_cost.cpu_model(), **cpu_topology()}


def cpu_topology() -> dict:
    """Hardware threads per physical core (/proc/cpuinfo's siblings over cpu cores): with 2, a 16-core
    machine's 16 workers share 8 cores' caches and units, and each task slows down (what limits its
    scaling)."""
    fields = room_cost.cpuinfo()
    try:
        return {"threads_per_core": int(fields["siblings"]) // int(fields["cpu cores"])}
    except (KeyError, ValueError, ZeroDivisionError):
        return {}


def spec_file(tmp: Path, name: str, points: int) -> Path:
    path = tmp / name
    path.write_text(json.dumps({"points": {"count": points, "max_views": 3}, "views": {"resolution": 512}}))
    return path


def run_setting(space: Path, extra: list[str], cores: str, out: Path, specs: dict[str, Path], device: str,
                gpu: bool) -> dict:
    """One setting's 3-view run and its main run; views/s of the views the main run adds (start-ups left
    out)."""
    small = generate(space, extra, cores, out.with_name(out.name + "-small"), specs["small"], device, gpu=gpu)
    main = generate(space, extra, cores, out, specs["one" if cores == "0" else "many"], device, gpu=gpu)
    main["small_run"] = {k: small[k] for k in ("views", "wall_s", "cpu_s")}
    added = main["wall_s"] - small["wall_s"]  # no slope when the main job took no longer (noise on tiny jobs)
    main["marginal_views_per_s"] = round((main["views"] - small["views"]) / added, 3) if added > 0 else None
    return main


def ratio(a: float | None, b: float | None) -> float | None:
    """a / b to two places; None where either is missing (a run with no slope)."""
    return round(a / b, 2) if a and b else None


def run_room(room: str, args: argparse.Namespace, tmp: Path, specs: dict[str, Path], result: dict,
             save: Callable[[], None]) -> None:
    """Every figure of one room (module docstring, steps 1-4) into `result`, saved after each step (a device
    machine's lease can end mid-run: what was measured stays)."""
    space, extra = room_space(room, args.scenes)
    all_cores = f"0-{os.cpu_count() - 1}"
    gpu_out = tmp / f"{room}-gpu"
    result["gpu_generate"] = run_setting(space, extra, all_cores, gpu_out, specs, args.device, gpu=True)
    print(room, "gpu generate", json.dumps(result["gpu_generate"]), flush=True)
    save()
    # fewer workers: fewer CUDA contexts, kernel loads and scene uploads on the one GPU
    for n in args.gpu_workers:
        run = generate(
            space, extra, all_cores, tmp / f"{room}-gpu-w{n}", specs["many"], args.device, workers=n, gpu=True
        )
        result.setdefault("gpu_generate_by_workers", {})[str(n)] = run
        print(room, f"gpu generate, {n} workers", json.dumps(run), flush=True)
        save()
    for n in args.render_workers:  # one context per renderer, every other core deriving
        run = generate(space, [*extra, "--render-workers", str(n)], all_cores, tmp / f"{room}-gpu-r{n}",
                       specs["many"], args.device, gpu=True)
        result.setdefault("gpu_generate_by_render_workers", {})[str(n)] = run
        print(room, f"gpu generate, {n} render workers", json.dumps(run), flush=True)
        save()
    result["gpu_floor"] = floor(space, all_cores, gpu_out, args.device)
    result["cpu_floor_one_core"] = floor(space, "0", gpu_out, "cpu")
    print(room, "floors", json.dumps([result["gpu_floor"], result["cpu_floor_one_core"]]), flush=True)
    cpu_runs = result["cpu_generate"] = {}
    for n in args.cores:
        cores = "0" if n == 1 else f"0-{n - 1}"
        cpu_runs[str(n)] = run_setting(space, extra, cores, tmp / f"{room}-cpu{n}", specs, "cpu", gpu=False)
        print(room, f"cpu generate on {n} cores", json.dumps(cpu_runs[str(n)]), flush=True)
        save()
    room_ratios(result)
    save()
    many = [n for n in args.cores if n > 1]
    if many:  # the same plan (spec and seed) on the CPU: every cue file of the GPU run against it
        result["cues_gpu_vs_cpu"] = compare_outputs(gpu_out, tmp / f"{room}-cpu{max(many)}")


def room_ratios(result: dict) -> None:
    """The room's ratios from its runs: GPU floor to one core's, N cores and the GPU to one core (end to end,
    the slope, the task window), the GPU to the most cores."""
    result["gpu_floor_to_cpu_floor"] = ratio(result["gpu_floor"]["s_per_view_mean"],
                                             result["cpu_floor_one_core"]["s_per_view_mean"])
    cpu_runs, gpu = result["cpu_generate"], result["gpu_generate"]
    one = cpu_runs.get("1")
    if one:
        for key in [
            k for k in ("views_per_s", "marginal_views_per_s", "task_window_views_per_s") if k in one
        ]:
            result[f"cores_to_one_core_{key}"] = {
                n: ratio(r.get(key), one.get(key)) for n, r in cpu_runs.items()
            }
            result[f"gpu_to_one_core_{key}"] = ratio(gpu.get(key), one.get(key))
    many = [n for n in cpu_runs if n != "1"]
    if many:
        top = cpu_runs[max(many, key=int)]
        result["gpu_to_all_cores_cpu_views_per_s"] = ratio(gpu["views_per_s"], top["views_per_s"])


def busy_lines(result: dict) -> list[str]:
    """Per room and GPU or CPU run: the GPU's busy fraction (nvidia-smi, over the task window) beside the
    render process's (its time in render tasks, from the task rows: bench/render/room_cost.py's
    busy_fractions), of the task window and of the whole run."""
    lines = ["room | run | GPU busy, task window | render process in render tasks: task window, whole run"]
    for room, r in result.get("rooms", {}).items():
        runs = [("gpu", r.get("gpu_generate"))]
        runs += [(f"gpu, {n} rendering", v) for n, v in r.get("gpu_generate_by_render_workers", {}).items()]
        runs += [(f"cpu, {n} cores", v) for n, v in r.get("cpu_generate", {}).items()]
        for name, run in runs:
            if not run:
                continue
            busy = run.get("busy") or {}
            lines.append(f"{room} | {name} | {(run.get('gpu_task_window') or {}).get('busy_fraction')} | "
                         f"{busy.get('render_busy_of_task_window')}, {busy.get('render_busy_of_wall')}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", default=",".join(ROOMS), help="comma-separated: " + ",".join(ROOMS))
    ap.add_argument("--scenes", type=Path, default=ROOT.parent / "shared" / "scenes")
    ap.add_argument("--points", type=int, default=22, help="points per room (x 3 views) of the one-core runs")
    ap.add_argument(
        "--points-many", type=int, default=44, help="points per room of the GPU and many-core runs"
    )
    ap.add_argument(
        "--device", default="auto", choices=("auto", "optix", "cuda", "cpu"), help="the GPU run's device"
    )
    ap.add_argument(
        "--cores", default="1,8,16", help="CPU runs on these core counts (those above nproc are left out)"
    )
    ap.add_argument(
        "--gpu-workers", default="", help="also the GPU main job with these worker counts (e.g. 2,4,8)"
    )
    ap.add_argument("--render-workers", default="",
                    help="also the GPU main job with every worker, these many of them rendering (e.g. 1,2)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--busy", type=Path, metavar="FILE",
                    help="only print the busy fractions of an earlier run's results FILE")
    args = ap.parse_args()
    if args.busy:
        print("\n".join(busy_lines(json.loads(args.busy.read_text()))))
        return 0
    args.gpu_workers = [int(n) for n in args.gpu_workers.split(",") if n]
    args.render_workers = [int(n) for n in args.render_workers.split(",") if n]
    args.cores = [n for n in (int(c) for c in args.cores.split(",")) if n <= (os.cpu_count() or 1)]
    t0 = time.perf_counter()
    result: dict = {"machine": gpu_info(), "resolution": 512, "points_one_core": args.points,
                    "points_gpu_and_many_cores": args.points_many, "rooms": {}}
    with tempfile.TemporaryDirectory(prefix="omnidata-gpucost-") as tmp_name:
        tmp = Path(tmp_name)
        rooms = args.rooms.split(",")
        warm = generate(*room_space(rooms[0], args.scenes), "0-0", tmp / "warm-up",
                        spec_file(tmp, "warm.json", 1), args.device, workers=1, gpu=True)
        result["warm_up"] = {k: warm[k] for k in ("wall_s", "gpu_processes_peak", "gpu_whole_run")}
        print("warm-up", json.dumps(result["warm_up"]), flush=True)
        specs = {"small": spec_file(tmp, "small.json", 1), "one": spec_file(tmp, "one.json", args.points),
                 "many": spec_file(tmp, "many.json", args.points_many)}
        def save() -> None:
            args.out.write_text(json.dumps(result, indent=1) + "\n")

        for room in rooms:
            room_result = result["rooms"][room] = {}
            try:
                run_room(room, args, tmp, specs, room_result, save)
            except Exception as e:  # keep what the other rooms measured
                room_result["error"] = str(e)[-2000:]
                print(room, "failed:", e, flush=True)
            save()
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({room: {k: v for k, v in r.items() if k not in ("cpu_generate", "gpu_generate")}
                      for room, r in result["rooms"].items()}, indent=1))
    print("\n".join(busy_lines(result)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
