"""A released embedded worker told to stop (SIGTERM, after the stop's grace period) while it renders ends at once
and quietly (services.worker.blender.calls, embedded.pool._on_sigterm_released). Raised inside Blender's render,
the handler's SystemExit reached PyErr_Print, which exited through Blender's C++ destructors: their leak report on
the user's terminal, then a deadlock that only the parent's kill ended."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

pytestmark = pytest.mark.bpy

# Renders the banana in a loop, as a worker's main thread does, with the released worker's SIGTERM handler; a
# timer thread sends SIGTERM after argv[2] seconds. A SystemExit that unwinds to here leaves as a worker process
# does (multiprocessing ends it with os._exit).
PROBE = r"""
import os, signal, sys, threading
from services.embedded.pool import _on_sigterm_released
from services.worker.blender.threads import import_bpy
import_bpy(1)
from services.core.ingest.loading import load_space
from services.worker.space_cache import SpaceContext
from tests.fixtures.raycast import object_view
space = SpaceContext.from_loaded(load_space(sys.argv[1]), key="probe")
scene = space.scene()
g = object_view(space.mesh, [0.3, -0.5, 1.0], 384)
scene.render(g)
signal.signal(signal.SIGTERM, _on_sigterm_released)
threading.Timer(float(sys.argv[2]), lambda: os.kill(os.getpid(), signal.SIGTERM)).start()
try:
    for _ in range(1000):
        scene.render(g)
except SystemExit as e:
    sys.stderr.flush()
    os._exit(int(e.code))
print("not stopped")
"""


def test_sigterm_during_renders_ends_the_worker_at_once_and_quietly(banana_path: Path) -> None:
    for delay in (0.3, 0.5, 0.8):
        run = subprocess.run([sys.executable, "-c", PROBE, str(banana_path), str(delay)], capture_output=True,
                             text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=60)
        assert run.returncode == 143, (delay, run.returncode, run.stdout[-500:], run.stderr[-2000:])
        assert "leak detector" not in run.stderr and "Not freed memory" not in run.stderr, (delay, run.stderr[-2000:])
