"""A stand-in for the designer's warm process: answers each request after `payload["sleep"]` seconds."""

from __future__ import annotations

import os
import time
from multiprocessing.connection import Connection


def serve(conn: Connection) -> None:
    """Answer ("ok", {"pid": ...}) to each request until the pool closes the socket."""
    while True:
        try:
            _kind, payload = conn.recv()
        except (EOFError, OSError):
            return
        if payload.get("crash"):
            os._exit(3)
        time.sleep(float(payload.get("sleep", 0)))
        conn.send(("ok", {"pid": os.getpid()}))


def crash(conn: Connection) -> None:
    """A process that dies on its first request (a crash of the warm process: not the spec's fault)."""
    conn.recv()
    os._exit(3)
