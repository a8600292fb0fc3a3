"""The kernels are built for the best x86-64 level a machine runs, so one kernel cache serves every machine of
that level (services/worker/process/kernel_target.py)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

from services.worker.process.kernel_target import LEVELS, host_features, levels_for, select

ROOT = Path(__file__).resolve().parents[3]
V4, V3 = (features for _, features in LEVELS)


def test_a_machine_runs_the_levels_whose_features_it_has_best_first():
    assert levels_for("x86_64", V4 | {"gfni"}) == ["x86-64-v4", "x86-64-v3"]
    assert levels_for("AMD64", V3) == ["x86-64-v3"]  # no AVX-512 (a Zen 3, most desktop Intel CPUs)
    assert levels_for("x86_64", V3 - {"avx2"}) == []  # a pre-2013 CPU: its own target
    assert levels_for("aarch64", V4) == []  # not x86: numba's default


def test_select_sets_the_best_level_and_no_host_features():
    env: dict[str, str] = {}
    assert select(env, features=lambda: V4, machine="x86_64") == "x86-64-v4"
    assert env == {"NUMBA_CPU_NAME": "x86-64-v4", "NUMBA_CPU_FEATURES": ""}
    env = {}
    assert select(env, features=lambda: V3, machine="x86_64") == "x86-64-v3"
    assert env == {"NUMBA_CPU_NAME": "x86-64-v3", "NUMBA_CPU_FEATURES": ""}


def test_select_keeps_an_operators_choice_and_a_machine_of_no_level_alone():
    env = {"NUMBA_CPU_NAME": "skylake-avx512"}
    assert select(env, features=lambda: V4, machine="x86_64") == "skylake-avx512"
    assert env == {"NUMBA_CPU_NAME": "skylake-avx512"}
    for machine, features in (("x86_64", {"sse2", "avx"}), ("aarch64", V4)):
        env = {}
        assert select(env, features=lambda f=features: f, machine=machine) is None
        assert env == {}


def probe(code: str) -> list:
    """Run `code` in a fresh interpreter (no NUMBA_CPU_* settings) and return the JSON it prints last."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CPU")}
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


MAGIC = ("from numba.core.registry import cpu_target; "
         "print(json.dumps(cpu_target.target_context.codegen().magic_tuple()))")


def test_a_worker_process_compiles_for_its_level_whether_or_not_numba_was_imported_first():
    levels = levels_for(platform.machine(), host_features())
    first = probe(f"import json, services.worker.cues.felzenszwalb; {MAGIC}")
    # select() reloads its config
    numba_before = probe(f"import json, numba; import services.worker; {MAGIC}")
    for magic in (first, numba_before):
        if levels:
            assert magic[1:] == [levels[0], ""]  # the cache key: the same on every machine of the level
        else:
            assert not magic[1].startswith("x86-64-v")


def test_a_process_that_compiled_for_its_host_already_keeps_that_target():
    # Its cache entries would otherwise be filed under the level with the host's code in them.
    magic = probe("import json, numba; numba.njit(lambda x: x + 1)(1); import os, services.worker; "
                  f"assert 'NUMBA_CPU_NAME' not in os.environ; {MAGIC}")
    assert not magic[1].startswith("x86-64-v")


def test_compile_kernels_every_level_runs_once_per_level_of_the_machine(monkeypatch):
    from services.cli import compile_kernels
    from services.worker.process import kernel_target

    envs = []

    def fake_run(cmd, env):
        envs.append({k: v for k, v in env.items() if k.startswith("NUMBA_CPU")})
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(compile_kernels.subprocess, "run", fake_run)
    monkeypatch.setattr(kernel_target, "host_features", lambda: V4)
    monkeypatch.setattr(compile_kernels.platform, "machine", lambda: "x86_64")
    assert compile_kernels.run(compile_kernels.argparse.Namespace(every_level=True)) == 0
    assert envs == [{"NUMBA_CPU_NAME": "x86-64-v4", "NUMBA_CPU_FEATURES": ""},
                    {"NUMBA_CPU_NAME": "x86-64-v3", "NUMBA_CPU_FEATURES": ""}]


def test_load_makes_the_target_for_the_level_before_any_kernel_and_starts_no_thread():
    """What a held worker (and Celery's parent, before it forks) runs: numba's target made for the selected
    level, with every registry a first kernel would load, the process still single-threaded (safe to fork)."""
    levels = levels_for(platform.machine(), host_features())
    made = probe(
        "import json, threading, numba; from services.worker.process import kernel_target as k; "
        "before = k._codegen_started(); k.load(); from numba.core.registry import cpu_target as t; "
        "loaded = len(t.typing_context._registries); threads = threading.active_count(); "
        "numba.njit(lambda x: x + 1)(1); print(json.dumps([before, k._codegen_started(), threads, loaded, "
        "len(t.typing_context._registries), list(t.target_context.codegen().magic_tuple())]))"
    )
    before, after, threads, loaded, after_a_kernel, magic = made
    assert (before, after, threads) == (False, True, 1)
    assert loaded > 0 and loaded == after_a_kernel  # a first kernel found nothing left to load
    if levels:
        assert magic[1:] == [levels[0], ""]


def test_load_cached_kernels_loads_every_cached_version_without_compiling_one():
    """The warm server's preload (services.cli.warm_server): each kernel of the loaded worker modules comes
    from numba's cache (hits, no misses: nothing compiled), so a run forked from it calls them as they are."""
    hits, misses, loaded, added = probe(
        "import json, sys, numpy as np, services.worker.cues.segmentation\n"
        "from numba.core.dispatcher import Dispatcher\n"
        "from services.worker.cues import ncuts\n"
        "from services.worker.process import kernel_target\n"
        "kernel_target.load()\n"
        "loaded = kernel_target.load_cached_kernels()\n"
        "kernels = {id(d): d for name, m in list(sys.modules.items()) if name.startswith('services.')\n"
        "           for d in vars(m).values() if isinstance(d, Dispatcher)}.values()\n"
        "hits = sum(sum(d.stats.cache_hits.values()) for d in kernels)\n"
        "misses = sum(sum(d.stats.cache_misses.values()) for d in kernels)\n"
        "before = len(ncuts._subgraph.overloads)\n"
        "ncuts._subgraph(np.eye(3), np.arange(3), 1e-10)\n"
        "print(json.dumps([hits, misses, loaded, len(ncuts._subgraph.overloads) - before]))\n"
    )
    assert loaded >= 20 and hits == loaded  # the segmentations' kernels alone are ~20
    assert misses == 0
    assert added == 0  # a kernel called as a job calls it finds its version loaded
