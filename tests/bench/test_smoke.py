"""Every benchmark with a main runs, tiny (seconds), so that none rots unnoticed: its command as
bench/README.md documents it (`python bench/<concern>/<name>.py`), with small arguments, its results sent to a
temp folder (OMNIDATA_BENCH_RESULTS) so that the checkout stays as it was. The figures of such a run mean
nothing; that it ends with exit status 0 and writes its results file is what is checked."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bench.lib.results import RESULTS_ENV
from tests.conftest import REPO_ROOT

BENCH = REPO_ROOT / "bench"
# script -> (tiny arguments, the results file it writes). {passes}: the room views' pass sets, rendered by
# the first benchmark that needs them and read by the others.
SMOKE: dict[str, tuple[str, str]] = {
    "api/api_progress.py": ("--clients 2 --seconds 1 --workers 1 --tasks 2000", "api_progress.json"),
    "api/health_load.py": ("--smoke", "health_load.json"),
    "api/hostile_requests.py": ("", "hostile_requests.json"),
    "cues/background_fill.py": ("--views 1 --repeats 1 --rooms icl_livingroom --cache {passes}",
                                "background_fill.json"),
    "cues/curvature.py": ("--repeats 1 --rooms icl_livingroom", "curvature.json"),
    "cues/derivations.py": ("--views 1 --repeats 1 --rooms icl_livingroom --cache {passes}",
                            "derivations.json"),
    "cues/felzenszwalb.py": ("--views 1 --repeats 1 --rooms icl_livingroom --cache {passes}",
                             "felzenszwalb.json"),
    "cues/segment_stability.py": ("--views 1 --repeats 1 --rooms icl_livingroom --cache {passes}",
                                  "segment_stability.json"),
    "ingest/capture.py": ("--views 1 --resolution 64 --alignment-frames 5 --import-copies 1 --no-big-photos",
                          "capture.json"),
    "ingest/degenerate_refusal.py": ("10000", "degenerate_refusal.json"),
    "ingest/ingest.py": ("--rotations 1 --synthetic 1 --closed 1 --cloud-points 0 --no-real-corpus",
                         "ingest.json"),
    "ingest/ingest_real.py": ("--rooms copyroom", "ingest_real.json"),
    "ingest/mirror_sign.py": ("--rooms copyroom", "mirror_sign.json"),
    "output/datasets.py": ("--resolution 64 --views 1", "datasets.json"),
    "output/encode_cost.py": ("--repeats 1 --cache {passes}", "encode_cost.json"),
    "output/encodings.py": ("--repeats 1 --cache {passes}", "encodings.json"),
    "output/store_put.py": ("--views 2 --cache {passes}", "store_put.json"),
    "plan/designer_fit.py": ("--other-seeds=", "designer_fit.json"),
    "plan/planner.py": ("--smoke", "planner.json"),
    "plan/sampling.py": ("--cell 0.5 --cameras 100 --points 500", "sampling.json"),
    "plan/trajectory.py": ("--points 2 --rooms 1", "trajectory.json"),
    "render/augment.py": ("--views 1 --resolution 64", "augment.json"),
    "render/cpu_profile.py": ("--rooms icl_livingroom --points 2 --resolution 64", "cpu_profile.json"),
    # no CPU-path runs: a core count above the machine's is left out
    "render/gpu_cost.py": ("--rooms icl_livingroom --points 1 --points-many 1 --device cpu --cores 4096",
                           "gpu.json"),
    "render/kernel_cache.py": ("--parts derive --repeats 1 --rooms icl_livingroom --views 1 --targets worker"
                               " --passes-cache {passes}", "kernel_cache.json"),
    "render/passes_cost.py": ("--rooms icl_livingroom --views 1 --repeats 1 --resolution 64",
                              "passes_cost.json"),
    "render/render.py": ("--views 1 --scenes= --room-views 1 --room-repeats 1 --e2e-points 1"
                         " --e2e-max-views 3 --idle-s 0.5 --resolution 64", "render.json"),
    "render/render_workers.py": ("--rooms icl_livingroom --points 1 --repeats 1", "render_workers.json"),
    "render/room_cost.py": ("--rooms icl_livingroom --points 1 --max-views 3 --resolution 64 --repeats 1"
                            " --no-startup", "room_cost.json"),
    "render/warm_start.py": ("--rooms icl_livingroom --points 1 --max-views 3 --resolution 64 --repeats 1",
                             "warm_start.json"),
    "render/startup_ab.py": ("--against-code . --repeats 1 --rooms icl_livingroom", "startup_ab.json"),
    "render/startup_cpu.py": ("--rooms icl_livingroom", "startup_cpu.json"),
    "scale/big_job.py": ("--views 2000 --chunk-views 1000 --passes 2", "big_job.json"),
    "scale/bulk_insert.py": ("--rows 1000", "bulk_insert.json"),
    "scale/compaction.py": ("--views 1000 --chunk-views 1000", "compaction.json"),
    "scale/fairness.py": ("--smoke", "fairness.json"),
    "scale/fanout.py": ("--views 100 --big-tasks 10000 --progress-samples 20 --max-seconds 60",
                        "fanout.json"),
    "scale/orchestration_cpu.py": ("--views 200 --window 100 --rounds 1", "orchestration_cpu.json"),
    "scale/scale_sim.py": ("--workers 10 --seconds 2 --task-s 0.05 --kill-fraction 0 --warmup 0.5"
                           " --processes 1",
                           "scale_sim.json"),
    "scale/scaling.py": ("--workers 1 --resolution 64 --repeat 1 --points 1 --views 1", "scaling.json"),
    "scale/worker_moves.py": ("--views 10", "worker_moves.json"),
}


def has_main(path: Path) -> bool:
    """True when the module runs something as a script (an `if __name__ == "__main__":` block)."""
    return any(isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)
               for node in ast.parse(path.read_text()).body)


def test_every_benchmark_with_a_main_has_a_smoke_run() -> None:
    scripts = {str(p.relative_to(BENCH)) for p in BENCH.rglob("*.py") if has_main(p)}
    missing, gone = sorted(scripts - set(SMOKE)), sorted(set(SMOKE) - scripts)
    assert not missing and not gone, f"no smoke run: {missing}; not a benchmark (any more): {gone}"


def test_the_shared_code_has_no_main() -> None:
    assert not [p.name for p in (BENCH / "lib").glob("*.py") if has_main(p)]


@pytest.fixture(scope="session")
def passes_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("bench-passes")


def smoke_params() -> list[pytest.ParameterSet]:
    """Each script; those sharing the pass sets in one xdist group (one at a time: one renders, the rest
    read); the warm-start one with tests/cli/test_warm_start.py, one of which retires every warm server of
    this checkout."""
    def group(script: str, args: str) -> list[pytest.MarkDecorator]:
        if "{passes}" in args:
            return [pytest.mark.xdist_group("bench-passes")]
        if script == "render/cpu_profile.py":  # a sampling profiler's: the machine's, not the project's
            return [pytest.mark.skipif(shutil.which("perf") is None, reason="Linux perf is not installed")]
        return [pytest.mark.xdist_group("warm-server")] if script == "render/warm_start.py" else []

    return [pytest.param(script, marks=group(script, args)) for script, (args, _) in sorted(SMOKE.items())]


@pytest.mark.slow
@pytest.mark.parametrize("script", smoke_params())
def test_benchmark_runs_tiny(script: str, tmp_path: Path, passes_cache: Path) -> None:
    args, results = SMOKE[script]
    out = tmp_path / "results"
    env = {**os.environ, RESULTS_ENV: str(out), "PYTHONPATH": str(REPO_ROOT)}
    cmd = [sys.executable, str(BENCH / script), *args.replace("{passes}", str(passes_cache)).split()]
    run = subprocess.run(cmd, cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, f"{' '.join(cmd)}\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}"
    assert (out / results).is_file(), f"{script} wrote no {results}: {sorted(p.name for p in out.glob('*'))}"
