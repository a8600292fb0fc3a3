"""How `generate` starts its local workers (services.embedded.pool.start_method): forked from its own process
when that is safe, so they inherit its imports, else spawned; both give the same bytes."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from services.embedded import pool
from services.worker.process import numeric_threads
from tests.fixtures.cli import REPO, WIDE


def test_fork_only_when_it_is_safe(monkeypatch):
    monkeypatch.setattr(numeric_threads, "_pinned_before_numpy", True)
    monkeypatch.delitem(sys.modules, "bpy", raising=False)
    monkeypatch.setattr(threading, "active_count", lambda: 1)
    assert pool.start_method("auto") == "fork"
    assert pool.start_method("spawn") == "spawn"  # the user's choice
    # another thread could hold a lock the child needs
    monkeypatch.setattr(threading, "active_count", lambda: 2)
    assert pool.start_method("auto") == "spawn"
    monkeypatch.setattr(threading, "active_count", lambda: 1)
    monkeypatch.setitem(sys.modules, "bpy", object())  # Blender's thread pools do not survive a fork
    assert pool.start_method("auto") == "spawn"
    monkeypatch.delitem(sys.modules, "bpy")
    monkeypatch.setattr(numeric_threads, "_pinned_before_numpy", False)  # BLAS loaded with the user's threads
    assert pool.start_method("auto") == "spawn"


def test_generate_pins_blas_before_numpy_loads_so_its_workers_may_be_forked():
    # A user asking for 8 BLAS threads: the generate command's process loads numpy's and scipy's OpenBLAS on
    # one (what a forked worker keeps: the segmentations' labels must not depend on the thread count), and can
    # fork.
    probe = (
        "import ctypes, services.cli.generate, scipy.linalg\n"
        "from services.embedded.pool import start_method\n"
        "libs = sorted({line.split()[-1] for line in open('/proc/self/maps') if 'openblas' in line})\n"
        "names = ('openblas_get_num_threads64_', 'scipy_openblas_get_num_threads', "
        "'openblas_get_num_threads')\n"
        "counts = [next(getattr(ctypes.CDLL(lib), n) for n in names if hasattr(ctypes.CDLL(lib), n))()\n"
        "          for lib in libs]\nprint(start_method(), len(libs), *counts)\n"
    )
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "8", "OMP_NUM_THREADS": "8", "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["fork", "2", "1", "1"]


def _worker_cmdlines(parent: int) -> list[str]:
    try:
        kids = Path(f"/proc/{parent}/task/{parent}/children").read_text().split()
    except OSError:
        return []
    lines = []
    for kid in kids:
        try:
            lines.append(Path(f"/proc/{kid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
        except OSError:
            continue
    return [c for c in lines if "resource_tracker" not in c]


def _run(scenes_dir: Path, out: Path, spec: Path, start: str) -> tuple[list[str], dict[str, str]]:
    """A 2-worker generate of the banana with OMNIDATA_WORKER_START=`start`: its workers' command lines (seen
    while it runs) and the sha256 of every output file but job.json (which holds timings)."""
    cmd = [
        sys.executable, "-m", "services.cli", "generate", str(scenes_dir / "ycb_banana"), "--out", str(out),
        "--spec", str(spec), "--seed", "7", "--workers", "2", "--name", "tiny", "--no-progress",
    ]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "OMNIDATA_WORKER_START": start, "PYTHONPATH": str(REPO)})
    seen: list[str] = []
    # Held workers start at once, before the job exists. A spawned child shows its parent's command line until
    # its exec: wait for the spawned ones' own.
    while proc.poll() is None and (
        len(seen) < 2 or start == "spawn" and not all("spawn_main" in c for c in seen)
    ):
        seen = _worker_cmdlines(proc.pid)
        time.sleep(0.02)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-3000:]
    files = {
        str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(out.rglob("*"))
        if p.is_file() and ".omnidata" not in p.parts and p.name != "job.json"
    }
    return seen, files


@pytest.mark.slow
@pytest.mark.skipif(
    not Path("/proc/self/task").exists(), reason="reads worker command lines from /proc (Linux)"
)
def test_forked_workers_write_the_same_bytes_as_spawned_ones(scenes_dir, tmp_path):
    spec = tmp_path / "tiny.yaml"
    spec.write_text(WIDE)
    forked, forked_files = _run(scenes_dir, tmp_path / "forked", spec, "auto")
    spawned, spawned_files = _run(scenes_dir, tmp_path / "spawned", spec, "spawn")
    # a forked worker keeps its parent's command line; a spawned one runs multiprocessing's spawn_main
    assert len(forked) == 2 and not any("spawn_main" in c for c in forked)
    assert len(spawned) == 2 and all("spawn_main" in c for c in spawned)
    assert len(forked_files) > 50 and forked_files == spawned_files


def test_a_worker_moves_its_long_lived_objects_out_of_the_collectors_reach():
    # A full collection traversed every object a worker had imported or loaded (~130 ms each, 3 a 66-view
    # run); after _freeze_long_lived they sit in the permanent generation, which no collection walks.
    probe = ("import gc, services.embedded.pool as pool, services.worker.run.runner\n"
             "before = len(gc.get_objects())\npool._freeze_long_lived()\n"
             "print(before, len(gc.get_objects()), gc.get_freeze_count())\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    before, after, frozen = map(int, out.stdout.split())
    assert before > 50_000 and after < before / 100 and frozen >= before * 0.9
