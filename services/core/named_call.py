"""Run a function named by "package.module:function" in a child process.

The API starts the designer's preview process this way: it names the work, as it names a Celery task, and
never imports the scheduler, the worker or bpy itself; only the child imports them."""

from __future__ import annotations

import importlib
from typing import Any


def call_named(target: str, *args: Any) -> Any:
    """Import `target` ("module:function") and call it with `args`."""
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)(*args)
