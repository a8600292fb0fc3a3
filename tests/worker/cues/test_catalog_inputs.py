"""The catalog's declared `inputs` of each cue match what its implementation reads (no Blender: a ray-cast
pass set). Dispatch orders tasks by these declarations, so a missing one could run a cue before its input
exists and an extra one makes a cue wait for nothing."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import trimesh

from services.core.domain.cues import CATALOG
from services.worker.context import ViewContext
from services.worker.cues import REGISTRY
from services.worker.executor import produce
from services.worker.passes import ViewGeometry, ViewPasses
from tests.fixtures.plans import small_plan
from tests.fixtures.raycast import raycast_passes

CHECKED = [name for name, cue in CATALOG.items() if not cue.internal]


class RecordingContext(ViewContext):
    """A ViewContext that records the cue values and the pass set its cues ask for."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.cues_read: list[str] = []
        self.intermediates: set[str] = set()  # other memo entries (shared steps such as occlusion_response)
        self.read_passes = False

    @property
    def passes(self) -> ViewPasses:
        self.read_passes = True
        return super().passes

    def memo(self, key: str, fn: Any) -> Any:
        if key.startswith("cue:"):
            self.cues_read.append(key[4:])
        else:
            self.intermediates.add(key)
        return super().memo(key, fn)


def context() -> RecordingContext:
    plan = small_plan()
    view = plan.view(1, 0)
    cube = trimesh.creation.box(extents=[1, 1, 1])
    labels = np.arange(len(cube.faces)) // 2
    passes = raycast_passes(cube, ViewGeometry.of(view), face_class=labels, face_instance=labels)
    passes.curvature = np.zeros((*passes.depth_z.shape, 2), dtype=np.float32)
    passes.photo_coverage = np.ones(passes.depth_z.shape, dtype=bool)  # as on a capture view (mask_photo)
    return RecordingContext(view, plan=plan, passes=passes)


def test_every_catalog_cue_has_one_implementation() -> None:
    assert set(REGISTRY) == set(CATALOG)


@pytest.mark.parametrize("name", CHECKED)
def test_declared_inputs_are_what_the_implementation_reads(name: str) -> None:
    ctx = produced(name)
    read = set(ctx.cues_read) - {name}
    declared = set(CATALOG[name].inputs)
    assert read <= declared, f"{name} reads {sorted(read - declared)} without declaring them"
    for inp in declared - read:
        if CATALOG[inp].source in ("render", "internal"):
            # a render cue's data is read from the pass set, not through its cue value
            assert ctx.read_passes, f"{name} declares {inp} and never reads the pass set"
        else:
            # a derived input read through the step it shares with that cue (e.g. occlusion_response)
            assert ctx.intermediates & produced(inp).intermediates, (
                f"{name} declares {inp} and never reads it"
            )


def produced(name: str) -> RecordingContext:
    ctx = context()
    produce(name, ctx)
    return ctx
