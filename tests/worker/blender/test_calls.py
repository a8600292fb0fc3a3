"""A worker told to stop (SIGTERM) while it renders or loads Blender ends at once and quietly
(services.worker.blender.calls): the embedded pool's released worker, and a Celery prefork child under
billiard's handler. Raised inside Blender's
render, a handler's SystemExit reached PyErr_Print, which exited through Blender's C++ destructors: their leak
report on the user's terminal, then a deadlock that only a kill ended."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

pytestmark = pytest.mark.bpy

# Renders the banana in a loop, as a worker's main thread does, with the SIGTERM handling of argv[3]; a timer
# thread sends SIGTERM argv[2] seconds after that handling is in place: before Blender's import for
# "celery-import" (a Celery child loads Blender in its first task), else before the renders. A SystemExit that
# unwinds to here leaves as the worker process would (multiprocessing and billiard end it with os._exit).
PROBE = r"""
import os, signal, sys, threading

def stop_soon():
    if sys.argv[3] == "embedded":  # what worker_main installs
        from services.worker.blender.calls import exit_at_once_inside_blender
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
        exit_at_once_inside_blender(signal.SIGTERM)
    else:  # a Celery prefork child: billiard's handler, then what the render task adds
        from billiard.common import reset_signals
        from services.worker.tasks import guard_renders_from_sigterm
        reset_signals()
        guard_renders_from_sigterm()
    threading.Timer(float(sys.argv[2]), lambda: os.kill(os.getpid(), signal.SIGTERM)).start()

try:
    if sys.argv[3] == "celery-import":
        stop_soon()
    from services.worker.blender.threads import import_bpy
    import_bpy(1)
    from services.core.ingest.loading import load_space
    from services.worker.inputs.space_cache import SpaceContext
    from tests.fixtures.raycast import object_view
    space = SpaceContext.from_loaded(load_space(sys.argv[1]), key="probe")
    scene = space.scene()
    g = object_view(space.mesh, [0.3, -0.5, 1.0], 384)
    scene.render(g)
    if sys.argv[3] != "celery-import":
        stop_soon()
    for _ in range(1000):
        scene.render(g)
# the stop raised while a numba kernel was called comes back wrapped: the runner unwraps it
except Exception as e:
    from services.worker.run.stop_signal import stop_within
    if not isinstance(stop_within(e), SystemExit):
        raise
    sys.stderr.flush()
    os._exit(int(stop_within(e).code) & 0xFF)
except SystemExit as e:
    sys.stderr.flush()
    os._exit(int(e.code) & 0xFF)
print("not stopped")
"""

# exit codes: 143 (128 + SIGTERM) ended inside Blender; billiard's own exit, -(256 - 15), is 15 elsewhere
CASES = [("embedded", (0.3, 0.5, 0.8), {143}), ("celery", (0.3, 0.5, 0.8), {143, 15}),
         ("celery-import", (0.05, 0.1, 0.2), {143, 15})]


@pytest.mark.parametrize(("kind", "delays", "codes"), CASES, ids=[c[0] for c in CASES])
def test_sigterm_inside_blender_ends_the_worker_at_once_and_quietly(
    banana_path: Path, kind: str, delays: tuple[float, ...], codes: set[int]
) -> None:
    for delay in delays:
        run = subprocess.run(
            [sys.executable, "-c", PROBE, str(banana_path), str(delay), kind], capture_output=True, text=True,
            cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=60,
        )
        assert run.returncode in codes, (delay, run.returncode, run.stdout[-500:], run.stderr[-2000:])
        assert "leak detector" not in run.stderr and "Not freed memory" not in run.stderr, (
            delay, run.stderr[-2000:],
        )
