"""API test fixtures: an app per test on the session's Postgres database, a local store, fresh tenants."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.core.storage import LocalStore
from tests.fixtures.api import Api, make_api


@pytest.fixture()
def api(pg_url: str, local_store: LocalStore) -> Iterator[Api]:
    """The API on Postgres with a local object store and two tenants (a, b)."""
    with make_api(pg_url, local_store) as a:
        yield a


@pytest.fixture(scope="session")
def bunny(scenes_dir: Path) -> Path:
    """A small untextured PLY scan."""
    return scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply"


@pytest.fixture(scope="session")
def banana_dir(scenes_dir: Path) -> Path:
    """A textured OBJ with its .mtl and texture."""
    return scenes_dir / "ycb_banana"
