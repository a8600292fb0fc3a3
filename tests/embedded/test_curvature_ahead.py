"""generate computes its spaces' curvature while its workers start (services/embedded/curvature_ahead.py): a
worker must find that file through its own path (the run's loaded-space cache, SpaceContext.curvature), not
compute
it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.core.domain.cues import CATALOG
from services.core.domain.jobspec import JobSpec
from services.core.ingest.loading import load_space
from services.embedded.curvature_ahead import CURVATURE_CUES, curvature_ahead, needs_curvature
from services.worker.cues import get_impl
from services.worker.inputs import curvature as estimator
from services.worker.inputs.loaded_cache import keep_loaded, read_loaded
from services.worker.inputs.space_cache import SpaceContext

FOLDER = "curvature"


def test_the_curvature_cues_are_those_whose_render_reads_the_curvature_pass() -> None:
    assert CURVATURE_CUES == {c for c in CATALOG if c != "passes" and "curvature" in get_impl(c).passes}
    assert needs_curvature(JobSpec())
    assert needs_curvature(JobSpec.model_validate({"cues": ["principal_curvature"]}))
    assert not needs_curvature(
        JobSpec.model_validate({"cues": ["depth_zbuffer", "normal", "segment_unsup25d"]})
    )


def test_a_worker_reads_the_curvature_generate_computed_ahead(scenes_dir: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    spec = JobSpec()
    spaces = {"icl": load_space(scenes_dir / "icl_livingroom"),
              "bunny": load_space(Path(__file__).resolve().parents[2] / "examples/scans/stanford_bunny")}
    cache = tmp_path / "cache"
    for name, loaded in spaces.items():
        # what drive() writes for its workers (keyed by the source checksum)
        keep_loaded(cache, name * 8, loaded)
    # nothing to overlap
    assert curvature_ahead([s.mesh for s in spaces.values()], spec, cache / FOLDER, workers=1) is None
    assert not (cache / FOLDER).exists()
    thread = curvature_ahead([s.mesh for s in spaces.values()], spec, cache / FOLDER, workers=2)
    assert thread is not None
    thread.join(timeout=120)
    assert not thread.is_alive()
    assert len(list((cache / FOLDER).glob("*.npy"))) == 2

    computed = {}
    for name, loaded in spaces.items():
        computed[name] = estimator.principal_curvatures(loaded.mesh, spec.params.curvature_radius_m)
    monkeypatch.setattr(
        estimator, "principal_curvatures", lambda *a: pytest.fail("the worker computed it again")
    )
    for name, loaded in spaces.items():
        cached = read_loaded(cache, name * 8, {"source_to_world": loaded.source_to_world})
        assert cached is not None
        ctx = SpaceContext.from_loaded(cached, key=name)  # the worker's space, as TaskRunner builds it
        ctx.curvature_dir = cache / FOLDER
        got = ctx.curvature(spec.params.curvature_radius_m)
        assert got.dtype == np.float32 and np.array_equal(got, computed[name])
        assert np.abs(got).max() > 0  # a real field, not zeros
