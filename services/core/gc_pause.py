"""Start-up imports with Python's cyclic collector paused.

Importing the scientific stack (numpy, scipy, trimesh, SQLAlchemy, pydantic; Blender in a worker) creates
~10^6 long-lived objects, and the collector's passes over them while they are made find nothing to free:
~15-25% of the import CPU (`generate`'s parent: ~0.98 -> ~0.81 CPU-s; a worker's warm-up: ~0.97 -> ~0.72,
one core, alternated). Garbage is still freed by reference counting; the collector runs again after.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def collections_paused() -> Iterator[None]:
    """No cyclic collection inside; the collector is left as it was found."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()
