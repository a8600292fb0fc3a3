"""Blender imported for a worker (services.worker.blender.threads): OpenEXR's global pool has no threads, so
the scanline writes of a pass render read back through an EXR (render.configure_scene without `memory`) wake
none (~800 context switches a view on one core), and every channel of the EXR stays the same."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

pytestmark = pytest.mark.bpy

# Renders the banana 4 times at 256x256 in a fresh process (`pool`: OpenEXR given 2 threads back after the
# import).
PROBE = r"""
import hashlib, resource, sys
from services.worker.blender.threads import import_bpy, set_exr_threads
import_bpy(1)
print("threads", set_exr_threads(2) if sys.argv[1] == "pool" else set_exr_threads(0))
from services.core.ingest.loading import load_space
from services.worker.inputs.space_cache import SpaceContext
from tests.fixtures.raycast import object_view
space = SpaceContext.from_loaded(load_space(sys.argv[2]), key="probe")
scene = space.scene()
from services.worker.blender.render import configure_scene, pass_aovs
# the readback that writes the EXR (a worker's scene reads its passes from memory: readback.py)
configure_scene(scene.scene, scene.options, scene._tmp + "/passes.exr", pass_aovs(len(space.mesh.faces)))
g = object_view(space.mesh, [0.3, -0.5, 1.0], 256)
scene.render(g)
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw
for _ in range(3):
    scene.render(g)
print("switches", resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw - r0)
from services.worker.blender.exr import read_channels
channels = read_channels(scene.scene.render.filepath)  # (the header holds the render time: not the bytes)
exr = b"".join(k.encode() + channels[k].tobytes() for k in sorted(channels))
print("exr", hashlib.sha256(exr).hexdigest())
"""


def probe(mode: str, mesh: Path) -> dict[str, str]:
    # the pool's threads then take turns with the render's thread
    one_core = str(min(os.sched_getaffinity(0)))
    out = subprocess.run(
        ["taskset", "-c", one_core, sys.executable, "-c", PROBE, mode, str(mesh)], capture_output=True,
        text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return dict(line.split(" ", 1) for line in out.stdout.splitlines() if " " in line)


def test_exr_writes_wake_no_thread_and_write_the_same_bytes(banana_path: Path) -> None:
    worker, pool = probe("worker", banana_path), probe("pool", banana_path)
    assert (worker["threads"], pool["threads"]) == ("0", "2")
    assert worker["exr"] == pool["exr"]  # every channel the same, written in the calling thread
    # 3 renders of 256 scanlines: with a pool every scanline block wakes a thread; without, next to none
    assert int(pool["switches"]) > 300
    assert int(worker["switches"]) < 100
