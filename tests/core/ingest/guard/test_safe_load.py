"""Reading a mesh under limits: a child process with an address-space cap, a CPU cap and a wall-clock
timeout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.core.ingest.errors import SpaceError
from services.core.ingest.guard.safe_load import load_space_limited
from services.core.ingest.loading import load_space


@pytest.fixture(scope="module")
def bunny(scenes_dir: Path) -> Path:
    return scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"


def test_the_child_gives_what_load_space_gives(bunny: Path) -> None:
    got = load_space_limited(bunny, max_faces=10**6, memory_mb=4096, timeout_s=120)
    want = load_space(bunny)
    assert got.face_count == want.face_count and len(got.mesh.vertices) == len(want.mesh.vertices)
    np.testing.assert_array_equal(got.source_to_world, want.source_to_world)
    np.testing.assert_array_equal(got.bounds, want.bounds)
    assert (got.up_method, got.checksum, got.has_semantics) == (
        want.up_method, want.checksum, want.has_semantics,
    )


def test_each_limit_gives_a_clear_refusal(bunny: Path) -> None:
    with pytest.raises(SpaceError, match="more than the limit of 100"):
        load_space_limited(bunny, max_faces=100, memory_mb=4096, timeout_s=120)
    with pytest.raises(SpaceError, match="memory limit of 1 MiB"):  # 1 MiB on top of what the child maps
        load_space_limited(bunny, max_faces=10**6, memory_mb=1, timeout_s=120)
    with pytest.raises(SpaceError, match="longer than the limit of 0.001 s"):
        load_space_limited(bunny, max_faces=10**6, memory_mb=4096, timeout_s=0.001)
    with pytest.raises(SpaceError, match="no such file"):
        load_space_limited(bunny.with_name("nope.ply"), max_faces=10**6, memory_mb=4096, timeout_s=120)
