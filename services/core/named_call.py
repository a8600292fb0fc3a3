"""Run a function named by "package.module:function" in a child process.

The API starts the designer's preview process this way: it names the work, as it names a Celery task, and
never imports the scheduler, the worker or bpy itself; only the child imports them."""

from __future__ import annotations

import importlib
import sys
from multiprocessing.connection import Connection
from typing import Any


def call_named(target: str, *args: Any) -> Any:
    """Import `target` ("module:function") and call it with `args`."""
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)(*args)


if __name__ == "__main__":  # python -m services.core.named_call TARGET FD: serve TARGET on the socket FD
    call_named(sys.argv[1], Connection(int(sys.argv[2])))
