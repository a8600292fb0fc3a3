"""`omnidata compile-kernels` leaves nothing for a job to compile: after it, real jobs on a real room with
holes and on a textured object add nothing to numba's cache (services/worker/process/kernel_warm_up.py)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from services.worker.process.kernel_target import host_features, levels_for
from services.worker.process.kernel_warm_up import warm_up_cues, worker_kernels
from tests.fixtures.cli import REPO

ROOM = '{"points": {"count": 1, "max_views": 3}, "views": {"resolution": 48}}'
OBJECT = (
    '{"cameras": {"mode": "object", "object_count": 4}, "points": {"count": 1}, "views": {"resolution": 48}}'
)


def test_the_warm_up_makes_every_cue_with_a_kernel_and_none_it_cannot():
    cues = warm_up_cues()
    assert {"passes", "segment_unsup2d", "segment_unsup25d", "keypoints3d", "principal_curvature",
            "position", "rgb_motion_blur"} <= set(cues)
    assert not {"point_info", "nonfixated", "vanishing_points", "segment_semantic", "mask_photo"} & set(cues)


def test_every_compiled_function_of_the_worker_is_listed_but_inlined_ones():
    kernels = worker_kernels()
    assert {"services.worker.cues.felzenszwalb._merge", "services.worker.blender.decode.faces_hit",
            "services.worker.inputs.curvature._fit_one", "services.worker.cues.ncuts._laplacian",
            } <= set(kernels)
    assert "services.worker.cues.keypoints._doh_row" not in kernels  # inline="always": compiled into _max_doh
    assert len(kernels) >= 60


def cache_files(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file of a numba cache folder with its size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")
            if p.is_file()}


def run(args: list[str], env: dict[str, str], timeout: float = 600) -> subprocess.CompletedProcess[str]:
    res = subprocess.run(
        [sys.executable, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert res.returncode == 0, res.stderr[-3000:]
    return res


PARTIAL = """
import json
from services.worker.process import kernel_warm_up
FEW = ("passes", "rgb", "depth_zbuffer")
kernel_warm_up.warm_up_cues = lambda: [c for c in kernel_warm_up.CATALOG if c in FEW]
print(json.dumps(kernel_warm_up.compile_kernels().missed))
"""


@pytest.mark.slow
def test_after_compile_kernels_real_jobs_compile_nothing(tmp_path: Path, scenes_dir: Path):
    cache = tmp_path / "kernels"
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")},
        "NUMBA_CACHE_DIR": str(cache),
    }
    # A warm-up that skips most cues reports the kernels it left: the check can fail.
    missed = json.loads(run(["-c", PARTIAL], env).stdout.strip().splitlines()[-1])
    assert (
        "services.worker.cues.felzenszwalb._merge" in missed
        and "services.worker.cues.narf_kernels.interest" in missed
    )
    assert "services.worker.blender.decode.faces_hit" not in missed  # the render's decode ran

    out = run(["-m", "services.cli", "compile-kernels"], env).stdout
    levels = levels_for(platform.machine(), host_features())
    assert f"{len(worker_kernels())} kernels" in out
    assert (levels[0] if levels else "this machine's CPU") in out
    warmed = cache_files(cache)
    assert len([f for f in warmed if f.endswith(".nbi")]) == len(worker_kernels())

    # A real room with holes (the segmentations' background fill) and a textured object (the colour
    # segmentation)
    for i, (space, spec_text) in enumerate(
        [(scenes_dir / "icl_livingroom", ROOM), (scenes_dir / "ycb_banana", OBJECT)]
    ):
        spec = tmp_path / f"spec{i}.json"
        spec.write_text(spec_text)
        run(
            [
                "-m", "services.cli", "generate", str(space), "--out", str(tmp_path / f"out{i}"), "--spec",
                str(spec), "--seed", "0", "--workers", "1", "--no-progress",
            ],
            env,
        )
        assert (tmp_path / f"out{i}" / "manifest.jsonl").read_text().strip()
    assert cache_files(cache) == warmed  # no kernel compiled (a compile writes its cache entry)
